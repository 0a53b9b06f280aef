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
stays. Rows without a stated noise (truth targets, logs without it) have no test and keep the pick.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import sympy

from identification.candidate import Candidate
from identification.collinearity import term_shapes
from identification.engine_settings import SelectionSettings
from identification.pareto import within_pick_tolerance
from identification.weak_noise import RefitTest

StructureTest = Callable[[Sequence[sympy.Expr]], "RefitTest | None"]


def specification_pick(chosen: Candidate, candidates: Sequence[Candidate], settings: SelectionSettings,
                       scale: float, test: StructureTest) -> tuple[Candidate, dict | None]:
    """(the pick or the simplest equally good candidate whose structure the test does not reject, what was
    done: None when the pick stays untested or passes; module docstring). test: a structure's specification
    test on the fit and pick rows (None when it cannot be made)."""
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
    return chosen, record


def _summary(c: Candidate, result: RefitTest) -> dict:
    """The model file's line for a structure and its test."""
    return {"expression": str(c.expression), "hausman_statistic": round(float(result.statistic), 4),
            "dof": int(result.dof), "p_value": float(f"{result.p_value:.4g}")}


def specification_line(target: str, record: dict) -> str:
    """The terminal's note on what specification_pick did for a target."""
    rejected = record["rejected"]
    head = (f"note: {target}: the rows reject the structure the pick chose (Hausman's test of the "
            f"generalised fit, p = {rejected['p_value']:.2g})")
    if "picked" in record:
        p_new, tried = record["picked"]["p_value"], record["tried"]
        return f"{head}; picked an equally good one they do not reject (p = {p_new:.2g}; {tried} tried)"
    return (f"{head}, and none of the {record['tried']} equally good candidates tried: the model may lack a "
            "term the flight holds (its coefficients are the weak rows' own fit)")
