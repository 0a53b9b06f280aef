"""Of equally good structures, one the rows do not show misspecified (SelectionSettings.specification_pick).

The pick takes the simplest candidate its rule passes within tolerance of the best cross-validated loss.
Two terms a flight ties (wz and wz (u1 + .. + u4) on a flight whose rotor sum varies by a few per cent)
make models of equal loss, and the simpler one is picked whether or not it is the physics. On weak-form rows
whose log states its sensors' noise there is a test that can tell them apart: Hausman's test of the
generalised fit (which weighs the low frequencies, where the gyro's differenced noise is small) against the
weak rows' own least squares (weak_noise.specification_test). Under a right model both are unbiased; a
model that writes a term as its tie differs from the physics by a slowly varying factor, which the two fits
weigh differently. Measured on realistic-sensor fang-chen-aero (seed 37, the training flight's weak rows):
wx' as picked, with wz for the rotor drag's common part -2.25e-6 wz (u1 + .. + u4), p = 2.4e-4; the same
model with wz (u1 + .. + u4) in its place p = 0.63 (the true structure: 0.96), where the t ratio of wz
beside the true structure is 0.53: the t rule cannot separate them and the test can.

So when the test rejects the pick's structure (p below weak_noise.SPECIFICATION_LEVEL) on the fit and pick
rows, the candidates within the pick's tolerance, at most one term larger than the pick, are tested, and of
those the test does not reject and the pick's rule passes, the one with the fewest terms, the simplest of
those the best generalised fit does not beat clearly, is picked instead (_best_supported). The rule asks
each term's t ratio of the better of the two fits (generalised_t): under a structure the test passes both
are unbiased, and the generalised one pins down what the weak rows' own fit cannot (a rate damping, at the
low frequencies; session 77: the paper vehicle's -0.0047 wx on a closed-loop realistic flight, t 2.7-5.4
against 17-35, whose absence the test had seen and a constant had stood in for). The specification search
below keeps the weak rows' own t ratios: with the generalised ones it took stand-ins the rule had declined
(seed 71's closed-loop realistic fang-chen-aero, dwy: 94 / 2 / 2 -> 94 / 2 / 7). When none, the pick
stays unless the specification search (identification.specification_search: terms added or put in
another's place, from every candidate's terms, and a passing structure the rule declines reduced one term at
a time) finds a structure the test passes and the pick's rule and tolerance take; when it finds none, the
model file and the terminal say where its walk ended (the terms it added, the best fit at each step, and the
test's p there): what the rows ask for most. Rows without a stated noise (truth targets, logs without it)
have no test and keep the pick.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
import sympy
from scipy import stats

from identification.candidate import Candidate
from identification.collinearity import term_shapes
from identification.cv_polish import model_size
from identification.engine_settings import SelectionSettings
from identification.pareto import within_pick_tolerance
from identification.specification_search import SearchSpace, search
from identification.weak_noise import SPECIFICATION_LEVEL, RefitTest

StructureTest = Callable[[Sequence[sympy.Expr]], "RefitTest | None"]


def specification_pick(chosen: Candidate, candidates: Sequence[Candidate], settings: SelectionSettings,
                       scale: float, test: StructureTest, space: SearchSpace | None = None
                       ) -> tuple[Candidate, dict | None]:
    """(the pick or the equally good candidate the test does not reject that the rows support best, what was
    done: None when the pick stays untested or passes; module docstring). test: a structure's specification
    test on the fit and pick rows (None when it cannot be made); space: where the specification search
    walks when no equally good candidate passes (None: no search)."""
    shapes = term_shapes(chosen.expression)
    first = test(shapes)
    if first is None or first.generalised:
        return chosen, None
    record = {"rejected": _summary(chosen, first), "tried": 0}
    tied, rule = within_pick_tolerance(candidates, settings, scale)
    seen = {frozenset(shapes)}
    passing: list[tuple[Candidate, RefitTest]] = []
    for c in tied:
        terms = term_shapes(c.expression)
        key = frozenset(terms)
        if key in seen or len(terms) > len(shapes) + 1:
            continue
        seen.add(key)
        if not rule(c) and not rule(generalised_t(c, None, terms)):
            continue
        record["tried"] += 1
        result = test(terms)
        if result is not None and result.generalised and rule(c := generalised_t(c, result, terms)):
            passing.append((c, result))
    if passing:
        best = _best_supported(passing)
        record["picked"] = _summary(*best)
        return best[0], record
    if space is None or space.steps <= 0:
        return chosen, record
    screen = space.screen(shapes)
    if screen is None:
        return chosen, record

    def accept(terms: list[sympy.Expr]) -> tuple[Candidate, RefitTest] | None:
        result = test(terms)
        if result is None or not result.generalised:
            return None
        c = space.make(terms)
        if not isinstance(c, Candidate):
            return None
        tied_now, rule_now = within_pick_tolerance([*candidates, c], settings, scale)
        return (c, result) if any(t is c for t in tied_now) and rule_now(c) else None

    found, walk = search(shapes, screen, space.steps, accept, model_size)
    record["searched"] = {"pool": len(screen.terms), "checked": walk.asked}
    if found is None:
        added = [str(t) for t in walk.terms if t not in shapes]
        if added:  # the terms that, one step at a time, fit the rows best: what they ask for most
            record["searched"]["walked_to"] = {
                "added": added, "left_out": [str(t) for t in shapes if t not in walk.terms],
                "p_value": float(f"{walk.p_value:.4g}")}
        return chosen, record
    record["picked"] = _summary(*found)
    return found[0], record


# of structures with as many terms, one whose generalised fit's chi^2 is lower than another's by more than
# this is supported better by the rows (the 1 - SPECIFICATION_LEVEL point of chi^2 with one degree of
# freedom, as for one coefficient's likelihood ratio: two structures of as many terms that differ in one)
CLEARLY_BETTER_CHI2 = float(stats.chi2.ppf(1.0 - SPECIFICATION_LEVEL, 1))


def _best_supported(passing: list[tuple[Candidate, RefitTest]]) -> tuple[Candidate, RefitTest]:
    """Of structures the test does not reject and the rule takes: those with the fewest terms, of them those
    the best generalised fit is not clearly better than (CLEARLY_BETTER_CHI2), and of those the simplest,
    then the better fit. A constant in place of a term the rows hold (the paper vehicle's weak roll damping
    -0.0047 wx on a closed-loop realistic-sensor flight, seed 89: chi^2 524 worse) passes the test too, and
    is a node simpler; a rotor pattern and its twin in the squares (fy's wx (u1 - u2 + u3 + u4) and wx (u1^2
    + .. + u4^2) on closed-loop realistic fang-chen-aero: 5.1 apart) are not told apart by the rows."""
    sizes = [len(term_shapes(c.expression)) for c, _ in passing]
    same = [cr for cr, size in zip(passing, sizes, strict=True) if size == min(sizes)]
    top = min(same, key=lambda cr: cr[1].rss)[1]
    margin = CLEARLY_BETTER_CHI2 * top.s2 if np.isfinite(top.s2) else 0.0
    close = [(c, r) for c, r in same if r.rss <= top.rss + margin]
    return min(close, key=lambda cr: (cr[0].complexity, cr[1].rss))


def generalised_t(c: Candidate, result: RefitTest | None, terms: Sequence[sympy.Expr]) -> Candidate:
    """A copy of the candidate whose weakest t ratio counts, of a structure the test does not reject (result,
    of these terms in this order), each term's better t ratio of the two fits (the weak rows' own and the
    generalised), as its own measure does its terms' (a constant left out): under a structure the test
    passes both fits are unbiased, and a term either pins down is identified. A weak damping is pinned down
    by the low frequencies, which the weak rows' own fit barely weighs (closed-loop realistic-sensor wx' of
    the paper vehicle: its -0.0047 wx has t 2.7-5.4 from that fit, 17-35 from the generalised). Never below
    the candidate's own measure. result None: the t ratio left out, the VIF kept (could the rule pass the
    candidate with some t ratio)."""
    c.measured()
    if result is None:
        return dataclasses.replace(c, weakest_t=None)
    varying = np.asarray([t != 1 for t in terms], bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.maximum(*(np.abs(np.asarray(b, float) / np.asarray(se, float))
                         for b, se in ((result.plain, result.se_plain), (result.gls, result.se_gls))))
    t = np.where(np.isnan(t), 0.0, t)[varying] if len(t) == len(varying) else np.zeros(1)
    weakest = float(np.min(t)) if t.size else float("inf")
    own = c.weakest_t if c.weakest_t is not None and np.isfinite(c.weakest_t) else 0.0
    return dataclasses.replace(c, weakest_t=max(weakest, own))


def _summary(c: Candidate, result: RefitTest) -> dict:
    """The model file's line for a structure and its test."""
    return {"expression": str(c.expression), "hausman_statistic": round(float(result.statistic), 4),
            "dof": int(result.dof), "p_value": float(f"{result.p_value:.4g}")}


def specification_line(target: str, record: dict) -> str:
    """The terminal's note on what specification_pick did for a target."""
    rejected = record["rejected"]
    head = (f"note: {target}: the rows reject the structure the pick chose (Hausman's test of the "
            f"generalised fit, p = {rejected['p_value']:.2g})")
    searched = record.get("searched")
    if "picked" in record:
        p_new, tried = record["picked"]["p_value"], record["tried"]
        if searched is None:
            return f"{head}; picked an equally good one they do not reject (p = {p_new:.2g}; {tried} tried)"
        return (f"{head}, as none of the {tried} equally good candidates; the specification search over "
                f"{searched['pool']} terms found one they do not reject and the pick's rule takes (p = "
                f"{p_new:.2g}): {record['picked']['expression']}")
    also = ""
    if searched is not None:
        walked = searched.get("walked_to")
        went = "" if walked is None else (f"; its walk, the best fit at each step, added "
                                          f"{', '.join(walked['added'])}, p = {walked['p_value']:.2g}")
        also = (f", nor the specification search over {searched['pool']} terms ({searched['checked']} "
                f"structures checked{went})")
    return (f"{head}, and none of the {record['tried']} equally good candidates tried{also}: the model may "
            "lack a term the flight holds (its coefficients are the weak rows' own fit)")
