"""Terms the flight supports beyond the pick: one-term additions its tolerance left out, named, not added.

The pick takes the simplest candidate within its tolerance of the best cross-validated loss (identification.
pareto: best x (1 + rel_tol) + abs_tol x the target's spread). The absolute part is there for the truth
targets' float32 rounding and the ground-effect law's systematic error: below it a smaller model is as good
(sessions 43, 66 and 74 of docs/discovery-log.md measured smaller tolerances; the extras they let in were the
law's misfit). So a small term the rows do pin down can stay out: on the bench's closed-loop heavy vehicle
(seed 89) wy' leaves out its small rate term wy wz, whose addition lowers the cross-validated loss 8.7 % at
a paired t of 5.2 over the folds' 30 blocks, inside a tolerance of 18 % of the loss (16 % its absolute
part).

Here each term of the polish's pool (identification.cv_polish.move_pool: every candidate's terms and the
polish's extra ones) is added to the chosen structure in turn, scored by the same cross-validation, and an
addition that lowers the loss by at least `min_t` paired standard errors over the folds' blocks
(identification.paired_loss) is reported: in the model file and on the terminal, for the engineer to weigh
against the physics. It is not added: on the same bench the most significant addition is as often a
look-alike of a missing term (the closed-loop racer's wx': u4 wy^2 at t 5.4, for the true wy^2 that no
candidate held) or a stand-in for the law's misfit as a true term.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import sympy

from identification.candidate import Candidate
from identification.collinearity import term_shapes
from identification.cross_validation import FoldedRows
from identification.cv_polish import move_pool
from identification.metrics import loss as loss_fn
from identification.model_file import expression_to_string
from identification.paired_loss import paired_loss_t

# the additions scored by their paired t, lowest cross-validated loss first (each a fold refit's
# predictions: about 2 ms on a 15,000-row flight)
MAX_TESTED = 64


@dataclass(frozen=True)
class SupportedTerm:
    """A term the rows support beside the chosen ones: its paired t ratio (negative: the addition is
    better) and the cross-validated loss's relative change with it (negative: lower)."""

    term: sympy.Expr
    paired_t: float
    loss_change: float

    def as_dict(self) -> dict[str, object]:
        """For the model file."""
        return {"term": expression_to_string(self.term), "paired_t": round(self.paired_t, 2),
                "loss_change": round(self.loss_change, 4)}


def supported_additions(chosen: Candidate, candidates: Sequence[Candidate], folded: FoldedRows, kind: str,
                        min_t: float, extra: Sequence[sympy.Expr] = (),
                        limit: int = 3) -> list[SupportedTerm]:
    """Up to `limit` pool terms whose addition to chosen's lowers the cross-validated loss by at least min_t
    paired standard errors, the most significant first (module docstring)."""
    shapes = term_shapes(chosen.expression)
    if not shapes or min_t <= 0.0:
        return []
    pool = move_pool(chosen, candidates, folded, extra)
    have = set(shapes)
    others = [s for s in pool if s not in have]
    base = folded.predictions(shapes)
    current = loss_fn(folded.y, base, kind)  # the chosen structure's cross-validated loss (terms_loss)
    if not others or not np.isfinite(current) or current <= 0.0:
        return []
    losses = folded.addition_losses(shapes, others, kind)
    better = [j for j in np.argsort(losses, kind="stable") if losses[j] < current][:MAX_TESTED]
    found = []
    for j in better:
        t = paired_loss_t(folded.y, folded.predictions([*shapes, others[j]]), base, kind, folded.blocks)
        if t <= -min_t:
            found.append(SupportedTerm(others[j], float(t), float(losses[j] / current - 1.0)))
    found.sort(key=lambda f: f.paired_t)
    return found[:limit]


def common_factor(terms: Sequence[sympy.Expr]) -> sympy.Expr | None:
    """The product of the factors every one of two or more terms holds (None: none): the racer's wx' named
    u4 wy^2, wy^2 sqrt(u1^2 + .. + u4^2) and u1 wy^2, each wy^2 times a factor nearly constant in flight."""
    if len(terms) < 2:
        return None
    shared = set(sympy.Mul.make_args(terms[0]))
    for t in terms[1:]:
        shared &= set(sympy.Mul.make_args(t))
    shared.discard(sympy.Integer(1))
    return sympy.Mul(*shared) if shared else None


def supported_line(target: str, found: Sequence[SupportedTerm], blocks: int) -> str:
    """The terminal's note on a target's supported additions."""
    listed = "; ".join(f"{expression_to_string(f.term)} (t {-f.paired_t:.1f}, loss {f.loss_change:+.1%})"
                       for f in found)
    common = common_factor([f.term for f in found])
    if common is not None:
        listed += f", each {expression_to_string(common)} times another factor"
    return (f"note: {target}: the flight also supports {listed} (each alone beside the chosen terms, paired "
            f"t over {blocks} blocks of the cross-validation); within the pick's tolerance, so the simpler "
            "model was kept: weigh such a term against the physics (a small true effect, or a stand-in for "
            "one)")
