"""One Pareto front per target (complexity against error) and the final pick on the pick rows.

The pick rows (identification.data_roles) are held out from fitting and never used for validation; the
"held-out loss" below is the loss on them. The pick: among candidates with a finite held-out loss, let
`best` be the smallest held-out loss; choose the least complex candidate whose held-out loss is
<= best * (1 + rel_tol) + abs_tol * std(held-out target), ties broken by the lower held-out loss. In the
final pick and its polish (select's by_degree) ties in complexity go first to the lower summed degree of the
terms (`degree`: of two equally complex models the tolerance calls equally good, the one that grows more
slowly away from the flight's states; wz^2 and wz^4 cost the same, and on realistic-sensor fang-chen-aero,
seed 19, the quartic won by noise). The engine's own rounds keep loss alone: with the degree there too,
closed-loop fang-chen-aero (seed 19) took 242 s of CPU instead of 207 for the same structure.
rel_tol (2%) lets a simpler model win when extra terms only fit noise; abs_tol (1e-7 of the target's
spread, about the float32 rounding of the accelerations a .tlog logs as its truth targets) treats
differences at rounding level as equal on noise-free data. At 1e-4 it hid real terms worth under 1e-4 of
the spread (a rotor-drag flight's damping term, 13 % better on the pick rows); at 1e-6, once the truth
targets were the SITL's own accelerations (session 43), it hid two of closed-loop fang-chen-aero's wy'
terms that lower the pick loss 4x (2.1e-6 against 9.2e-6 rad/s^2, a spread of 14 rad/s^2). Whether a small
term is real is left to rel_tol and the identification rules below, which do not depend on the target's
scale.
Before that, candidates the flight does not identify are set aside: those with a term whose t ratio
(coefficient over its standard error, inflated by the term's VIF; beside a constant offset when the candidate
has no constant: a term the flight cannot tell from a sensor's bias is not identified) on the rows it is
measured on (the fit rows; the fit and pick rows when the pick cross-validates,
SelectionSettings.identify_on_pick_rows) is below `min_t` (identification.collinearity.term_identification;
measured by the engines that can, else None), or a term whose VIF there is above `max_vif` (the flight barely
separates it from the others) unless its t ratio is at least min_t VIF / max_vif (with the model's
weakest t and largest VIF: `terms_identified`), as long as one candidate that passes exists. On closed-loop
data the regressors are collinear and a model of tied terms with cancelling coefficients can have the lowest
pick loss by fitting the targets' errors; it is not a model of the vehicle, and a controller derived from it
can crash. What a missing or misshapen term leaves along a term's own direction (the part of its column no
other term holds, 1/VIF of its variance) is divided by that part's variance, so the error it puts in the
coefficient grows with the VIF: a term past max_vif needs that much more evidence, not none. With the hard
cap (vif_rule "cap", before session 63) a heavier vehicle's noise-free closed-loop flight, whose per-rotor
terms are pinned down at t in the thousands, had every candidate holding them refused and the rest of the
model took their place (wx' 28 of its 36 monomials, the residual 450x the true structure's); with the VIF's
square root instead of the VIF itself, realistic-sensor fang-chen-aero's fy took a tied expansion of its
frame drag (vb, vb^3, vb|vb|, vb ub^2, vb wb^2 at VIF 437) for vb|v|. Likewise a
candidate whose self-feedback is positive beyond `max_self_feedback_t` standard errors
(identification.self_feedback: anti-damping, which no rigid body with rotors and drag has) is set aside while
one that passes exists.
Where no candidate passes both, those without anti-damping are compared, else all (the plausibility check
then flags what was picked).

Excitation: a target is not excited by the flight when no candidate that passes the rules above has a
pick loss below the constant model's (the fit rows' mean, or median for the absolute loss) by `min_gain`
of it (5%: an R^2 of about 0.1 on the pick rows): what the candidates fit there is noise or an artefact.
identification.identify then gives it the minimal physical model (identification.physics_candidates) and
says so.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from identification.candidate import Candidate
from identification.engine_settings import SelectionSettings
from identification.metrics import loss as loss_fn
from identification.model_file import ParetoPoint, degree, expression_to_string


def attach_holdout(
    candidates: Sequence[Candidate], X: np.ndarray, y: np.ndarray, loss: str, operator: Any = None
) -> None:
    """Set each candidate's held-out loss on (X (N,16), y (N,)); inf when its prediction is not finite.

    operator: a weak-form matrix V (M, N) (identification.weak_form): the loss is then on V y and V f(X).
    """
    weak_y = y if operator is None else operator @ y
    for c in candidates:
        if len(weak_y) == 0:
            c.holdout_loss = float("nan")
            continue
        try:
            pred = c.evaluate(X)
            c.holdout_loss = loss_fn(weak_y, pred if operator is None else operator @ pred, loss)
        except (ValueError, TypeError, ZeroDivisionError, OverflowError):
            c.holdout_loss = float("inf")


def _score(c: Candidate) -> float:
    value = (c.holdout_loss if c.holdout_loss is not None and not math.isnan(c.holdout_loss)
             else c.trained().train_loss)
    return value if math.isfinite(value) else float("inf")


def pareto_front(candidates: Sequence[Candidate]) -> list[Candidate]:
    """The non-dominated candidates (complexity against held-out loss, else train loss), by complexity."""
    front: list[Candidate] = []
    best = float("inf")
    for c in sorted(candidates, key=lambda c: (c.complexity, _score(c))):
        s = _score(c)
        if s < best:
            front.append(c)
            best = s
    return front


def select(candidates: Sequence[Candidate], settings: SelectionSettings, scale: float = 1.0,
           by_degree: bool = False) -> Candidate:
    """The final pick (module docstring); scale is the held-out target's standard deviation; by_degree:
    of equally complex candidates the lower degree first (the final pick and its polish; the engine's own
    rounds keep loss alone, the path they search by)."""
    if not candidates:
        raise ValueError("no candidates to choose from")
    ok, rule = within_pick_tolerance(candidates, settings, scale)
    if not ok:
        return min(candidates, key=lambda c: c.complexity)
    first = next(c for c in ok if rule(c))
    if not by_degree:
        return first
    # of equally complex ones, the lower degree (module docstring); only these are measured by the rule
    low = degree(first.expression)
    ties = sorted(((c, _score(c), d) for c in ok if c.complexity == first.complexity and c is not first
                   and (d := degree(c.expression)) < low), key=lambda csd: (csd[2], csd[1]))
    return next((c for c, _, _ in ties if rule(c)), first)


def within_tolerance(best: float, settings: SelectionSettings, scale: float = 1.0) -> float:
    """The largest held-out loss the pick treats as equal to `best`: best * (1 + rel_tol) + abs_tol * scale
    (scale: the held-out target's standard deviation; module docstring)."""
    return best * (1.0 + settings.rel_tol) + settings.abs_tol * (scale if scale > 0 else 1.0)


def pick_limit(candidates: Sequence[Candidate], settings: SelectionSettings, scale: float = 1.0) -> float:
    """The pick's tolerance limit over `candidates` (select's: within_tolerance of the lowest held-out loss
    among those the pick compares); inf when none has a finite one."""
    best = pick_best(candidates, settings)
    return within_tolerance(best, settings, scale) if math.isfinite(best) else best


def pick_best(candidates: Sequence[Candidate], settings: SelectionSettings) -> float:
    """The lowest held-out loss among the candidates the pick compares (those its rule passes: select);
    inf when none has a finite one."""
    finite = [(c, s) for c in candidates if math.isfinite(s := _score(c))]
    return _passing_rule(finite, settings)[1] if finite else float("inf")


def within_pick_tolerance(
    candidates: Sequence[Candidate], settings: SelectionSettings, scale: float = 1.0
) -> tuple[list[Candidate], Callable[[Candidate], bool]]:
    """The candidates select treats as equally good (held-out loss within its tolerance of the best it
    compares), simplest first then lower loss, and the rule it compares them by; ([], the rule) when
    none has a finite held-out loss."""
    finite = [(c, s) for c in candidates if math.isfinite(s := _score(c))]
    if not finite:
        return [], lambda c: True
    rule, best = _passing_rule(finite, settings)
    limit = within_tolerance(best, settings, scale)
    ok = sorted(((c, s) for c, s in finite if s <= limit), key=lambda cs: (cs[0].complexity, cs[1]))
    return [c for c, _ in ok], rule


def _passing_rule(
    scored: list[tuple[Candidate, float]], settings: SelectionSettings
) -> tuple[Callable[[Candidate], bool], float]:
    """The rule the pick compares candidates by (identified and without anti-damping; else without
    anti-damping; else none: module docstring) and the lowest score among those it passes. The candidates
    are tried lowest score first, so only those the answer depends on are measured (Candidate.measured)."""
    ranked = sorted(scored, key=lambda cs: cs[1])
    rules: list[Callable[[Candidate], bool]] = [
        lambda c: admissible(c, settings), lambda c: not anti_damping(c, settings), lambda c: True]
    for rule in rules:
        best = next((s for c, s in ranked if rule(c)), None)
        if best is not None:
            return rule, best
    raise ValueError("no candidates to choose from")


def anti_damping(c: Candidate, settings: SelectionSettings) -> bool:
    """True when the candidate's self-feedback is positive beyond max_self_feedback_t standard errors."""
    slope, se = c.self_feedback, c.self_feedback_se
    if slope is None or not slope > 0:
        return False
    return se is not None and slope > settings.max_self_feedback_t * se


def admissible(c: Candidate, settings: SelectionSettings) -> bool:
    """True when the candidate passes the pick's rules: terms identified, no anti-damping."""
    return _identified(c, settings) and not anti_damping(c, settings)


def excited(candidates: Sequence[Candidate], constant_loss: float, settings: SelectionSettings) -> bool:
    """False when no candidate passing the pick's rules (identified, no anti-damping) has a pick loss below
    constant_loss (the constant model's on the pick rows) by min_gain of it (module docstring)."""
    ranked = sorted(candidates, key=_score)
    best = next((_score(c) for c in ranked if admissible(c, settings)), float("inf"))
    return bool(best < constant_loss * (1.0 - settings.min_gain))


def _identified(c: Candidate, settings: SelectionSettings) -> bool:
    """False when the rows it is measured on do not identify the candidate's terms (module docstring)."""
    c.measured()
    return terms_identified(c.weakest_t, c.largest_vif, settings)


def terms_identified(weakest_t: float | None, largest_vif: float | None, settings: SelectionSettings) -> bool:
    """The pick's identification rule on a model's weakest t ratio and largest VIF (None: not measured):
    t >= min_t, and a VIF above max_vif asks for t >= min_t VIF / max_vif ("scaled"; "cap": no VIF
    above max_vif)."""
    if weakest_t is not None and weakest_t < settings.min_t:
        return False
    if largest_vif is None or largest_vif <= settings.max_vif:
        return True
    if settings.vif_rule == "cap" or weakest_t is None:
        return False
    return bool(weakest_t >= settings.min_t * largest_vif / settings.max_vif)


def front_points(candidates: Sequence[Candidate], chosen: Candidate | None = None) -> list[ParetoPoint]:
    """The front as model-file points (the chosen candidate always included)."""
    front = pareto_front(candidates)
    if chosen is not None and all(c is not chosen for c in front):
        front = sorted([*front, chosen], key=lambda c: c.complexity)
    return [
        ParetoPoint(
            complexity=int(c.complexity),
            loss=float(c.trained().train_loss),
            holdout_loss=None
            if c.holdout_loss is None or math.isnan(c.holdout_loss)
            else float(c.holdout_loss),
            expression=expression_to_string(c.expression),
            engine=c.engine or None,
        )
        for c in front
    ]
