"""Rotor speeds' power twins and the mixer's patterns in the cross-validated polish
(identification.cv_polish.rotor_power_twins, rotor_patterns).

Rotor speeds vary a few per cent about hover in flight, so u_i and u_i^2 are near twins in every product, and
a model written in one family is reached from the other only by moving several terms together: on
realistic-sensor fang-chen-aero (seed 5) fy held -2.67e-8 wz (u1^2 - u2^2 + u3^2 - u4^2), written as two
terms, where the SITL's rotor drag is linear in the rotor speeds. The polish now scores the pick with every
square of a rotor speed lowered, and with every speed raised, in all terms at once and in the terms of each
cofactor apart (a roll moment's thrust terms u_i^2 beside its rotor drag wz u_i). It also merges a cofactor's
rotor terms into the mixer's sign pattern nearest their fitted coefficients, alone and beside the rotors' sum
(session 37: closed-loop realistic-sensor fang-chen-aero, seed 5, dwx's wz u2^2 and wz (u1^2 + u2^2 + u3^2 -
u4^2) for the SITL's wz (u1 - u2 + u3 - u4)). Seeded, small synthetic data with the rotor speeds spread over
0..1000 rad/s (the families far apart); the power-twin truths are no pattern, so the polish stops at them."""

from __future__ import annotations

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS, expression_columns
from identification.collinearity import term_shapes
from identification.cross_validation import FoldedRows
from identification.cv_polish import (
    _expanded,
    move_candidate,
    polish_by_cross_validation,
    rotor_patterns,
    rotor_power_twins,
)
from identification.engine import EngineSettings
from identification.true_model import random_states

S = PRIMITIVE_SYMBOLS
U1, U2, U3, U4 = (S[f"u{i}"] for i in range(1, 5))
ONE, VB, WZ = sympy.Integer(1), S["vb"], S["wz"]
SQUARED = [ONE, VB, WZ * U1**2, WZ * (U1**2 + U2**2 - U3**2 + U4**2)]
LINEAR = [ONE, VB, WZ * U1, WZ * (U1 + U2 - U3 + U4)]


def test_the_twins_lower_and_raise_every_rotor_speed_at_once():
    lowered, raised = rotor_power_twins(SQUARED), rotor_power_twins(LINEAR)
    assert lowered == [LINEAR]  # nothing to raise: every rotor term holds a square
    assert raised == [SQUARED]  # nothing to lower
    thrust = [U1**2, U2**2, U1 * VB]  # a term with a square is not raised
    assert rotor_power_twins(thrust) == [[U1, U2, U1 * VB], [U1**2, U2**2, U1**2 * VB]]
    # a twin that would write two terms alike is no move (the model would lose a term, not change family)
    assert rotor_power_twins([U1**2, U1]) == []
    assert rotor_power_twins([ONE, VB]) == []  # no rotor speed: no twin
    # a moment's thrust terms (cofactor 1) apart from its rotor drag (cofactor wz)
    moment = [U1**2 - U2**2 - U3**2 + U4**2, WZ * U1**2, WZ * (U1**2 + U2**2 - U3**2 + U4**2)]
    twins = rotor_power_twins(moment)
    assert [moment[0], WZ * U1, WZ * (U1 + U2 - U3 + U4)] in twins
    assert [U1 - U2 - U3 + U4, *moment[1:]] in twins


def _rows(truth: list[sympy.Expr], coef: list[float], seed: int) -> FoldedRows:
    xi, u = random_states(6000, seed)
    X = np.hstack([xi, u])
    y = expression_columns(truth, X) @ np.array(coef)
    y = y + 0.02 * float(np.std(y)) * np.random.default_rng(seed).standard_normal(len(y))
    return FoldedRows([(X[:4800], y[:4800], None, 3), (X[4800:], y[4800:], None, 3)], folds=5)


def _polish(rows: FoldedRows, start: list[sympy.Expr]) -> set[str]:
    picked = move_candidate(start, rows.terms_loss(start, "absolute"), rows, "absolute", "t")
    final = polish_by_cross_validation(picked, [picked], rows, "absolute", EngineSettings().selection,
                                       lambda new: None)
    assert final.holdout_loss <= picked.holdout_loss
    return {str(s) for s in term_shapes(final.expression)}


def test_a_pick_in_squares_is_lowered_when_the_physics_is_linear_in_the_rotor_speeds():
    rows = _rows(LINEAR, [0.1, -0.4, 3e-4, 2e-4], 3)
    assert _polish(rows, SQUARED) == {str(s) for s in LINEAR}


def test_a_pick_in_squares_stays_when_the_physics_is_quadratic():
    rows = _rows(SQUARED, [0.1, -0.4, 3e-7, 2e-7], 4)
    assert _polish(rows, SQUARED) == {str(s) for s in SQUARED}
    assert _polish(rows, LINEAR) == {str(s) for s in SQUARED}  # and a linear pick is raised


def test_a_moments_rotor_drag_is_lowered_beside_its_squared_thrust():
    thrust = U1**2 - U2**2 - U3**2 + U4**2
    rows = _rows([thrust, WZ * U1, WZ * (U1 + U2 - U3 + U4)], [1e-5, 3e-4, 2e-4], 5)
    start = [thrust, WZ * U1**2, WZ * (U1**2 + U2**2 - U3**2 + U4**2)]
    assert _polish(rows, start) == {str(s) for s in [thrust, WZ * U1, WZ * (U1 + U2 - U3 + U4)]}


def test_the_patterns_merge_a_cofactors_rotor_terms_into_the_nearest_mixer_pattern():
    thrust = U1**2 - U2**2 - U3**2 + U4**2
    start = [thrust, WZ * U2**2, WZ * (U1**2 + U2**2 + U3**2 - U4**2), VB]
    # -9e-8 wz (u1^2 - u2^2 + u3^2 - u4^2) split: 1.8e-7 wz u2^2 - 9e-8 wz (u1^2 + u2^2 + u3^2 - u4^2)
    fitted = 8e-5 * thrust + 1.8e-7 * start[1] - 9e-8 * start[2] - 0.4 * VB
    moves = [[str(t) for t in m if t not in start] for m in rotor_patterns(fitted, start)]
    assert ["wz*(u1**2 - u2**2 + u3**2 - u4**2)"] in moves  # the nearest pattern, alone
    assert ["wz*(u1 - u2 + u3 - u4)"] in moves  # and in the other power
    assert ["wz*(u1 - u2 + u3 - u4)", "wz*(u1 + u2 + u3 + u4)"] in moves  # beside the rotors' sum
    # the merged group's terms left, the others kept
    alone = next(m for m in rotor_patterns(fitted, start) if WZ * (U1 - U2 + U3 - U4) in m and len(m) == 3)
    assert set(alone) == {thrust, VB, WZ * (U1 - U2 + U3 - U4)}
    assert rotor_patterns(0.1 * VB + 2e-7 * WZ * U1**2, [VB, WZ * U1**2]) == []  # one rotor: no pattern


def test_the_polish_merges_a_split_yaw_pattern_with_its_small_common_part():
    thrust = U1**2 - U2**2 - U3**2 + U4**2
    truth = [thrust, WZ * (U1 - U2 + U3 - U4), WZ * (U1 + U2 + U3 + U4)]
    rows = _rows(truth, [1e-5, 2e-4, -4e-5], 6)
    start = [thrust, WZ * U2**2, WZ * (U1**2 + U2**2 + U3**2 - U4**2)]
    assert _polish(rows, start) == {str(s) for s in truth}


def _hub(rx: float, ry: float) -> sympy.Expr:
    """A hub's height h - r . g (m) as identification.hub_law writes it (hub 5 cm above the CG)."""
    return S["h"] - rx * S["gx"] - ry * S["gy"] - (-0.05) * sympy.sqrt(1 - S["gx"] ** 2 - S["gy"] ** 2)


def test_a_hub_laws_rotors_stay_apart_and_its_denominators_are_not_multiplied_out():
    hubs = [_hub(0.16, 0.16), _hub(-0.16, -0.16), _hub(0.16, -0.16), _hub(-0.16, 0.16)]
    law = sum(2e-9 * x**2 / H**4 + 3e-7 * x**2 / H**2 for x, H in zip((U1, U2, U3, U4), hubs, strict=True))
    airspeed = 1e-3 * (S["ub"] - 0.05 * S["wy"]) ** 2 / hubs[0] ** 3  # no rotor speed: no group
    thrust = U1**2 - U2**2 - U3**2 + U4**2
    start = [thrust, WZ * U2**2, WZ * (U1**2 + U2**2 + U3**2 - U4**2), law + airspeed]
    fitted = 8e-5 * thrust + 1.8e-7 * start[1] - 9e-8 * start[2] + 1.0 * start[3]
    moves = [[str(t) for t in m if t not in start] for m in rotor_patterns(fitted, start)]
    # the split yaw terms merge as without the law; each rotor's 1/H_i^k is its own cofactor, so the law
    # makes no pattern, and each merge keeps the law as it was
    assert ["wz*(u1**2 - u2**2 + u3**2 - u4**2)"] in moves
    assert ["wz*(u1 - u2 + u3 - u4)", "wz*(u1 + u2 + u3 + u4)"] in moves
    assert all(start[3] in m for m in rotor_patterns(fitted, start))
    assert len(moves) == len(rotor_patterns(8e-5 * thrust + 1.8e-7 * start[1] - 9e-8 * start[2], start[:3]))
    # a series law's common 1/h^k is one cofactor: its rotors merge into a pattern
    series = [U1**2 / S["h"] ** 2, U2**2 / S["h"] ** 2, VB]
    merged = [[str(t) for t in m if t not in series]
              for m in rotor_patterns(4e-7 * series[0] + 4e-7 * series[1] + 0.1 * VB, series)]
    assert ["(u1**2 + u2**2 + u3**2 + u4**2)/h**2"] in merged
    # the law's monomials keep their hub's power as written (multiplied out, 1/H^4 is 35 terms)
    assert dict(_expanded(3e-7 * U1**2 / hubs[0] ** 4)) == {U1**2 / hubs[0] ** 4: 3e-7}
    assert dict(_expanded(law)) == {x**2 / H**k: c for x, H in zip((U1, U2, U3, U4), hubs, strict=True)
                                    for k, c in ((4, 2e-9), (2, 3e-7))}  # the law as one term, likewise
