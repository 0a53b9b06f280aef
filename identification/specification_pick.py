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
rows, the candidates the pick's rule passes within its tolerance, at most one term larger than the pick,
are tried simplest first, and the first the test does not reject is picked instead; when none, the pick
stays unless the specification search (identification.specification_search: terms added or put in
another's place, from every candidate's terms, and a passing structure the rule declines reduced one term at
a time) finds a structure the test passes and the pick's rule and tolerance take; when it finds none, the
model file and the terminal say where its walk ended (the terms it added, the best fit at each step, and the
test's p there): what the rows ask for most. Rows without a stated noise (truth targets, logs without it)
have no test and keep the pick.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import sympy

from identification.candidate import Candidate
from identification.collinearity import term_shapes
from identification.cv_polish import model_size
from identification.engine_settings import SelectionSettings
from identification.pareto import within_pick_tolerance
from identification.specification_search import SearchSpace, search
from identification.weak_noise import RefitTest

StructureTest = Callable[[Sequence[sympy.Expr]], "RefitTest | None"]


def specification_pick(chosen: Candidate, candidates: Sequence[Candidate], settings: SelectionSettings,
                       scale: float, test: StructureTest, space: SearchSpace | None = None
                       ) -> tuple[Candidate, dict | None]:
    """(the pick or the simplest equally good candidate whose structure the test does not reject, what was
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
    for c in tied:
        terms = term_shapes(c.expression)
        key = frozenset(terms)
        if key in seen or len(terms) > len(shapes) + 1:
            continue
        seen.add(key)
        if not rule(c):
            continue
        record["tried"] += 1
        result = test(terms)
        if result is not None and result.generalised:
            record["picked"] = _summary(c, result)
            return c, record
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
