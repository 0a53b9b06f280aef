"""The pick's ground-effect law refit beside its other terms (the law's own coefficients, not its hubs).

A hub law (identification.hub_law) enters the engine's space as one feature: its coefficients b_ik are fitted
once, by variable projection beside the terms the model held then, and the model gives the law one
coefficient. The polish then moves the model's other terms, and the law's b_ik stay where the old terms left
them. On seed 41's heavy closed loop (bench/vehicles/heavy-650-aero.yaml) the stale law left 1.5-2.5x the
residual of the law refit beside the pick's terms (wx' 1.24e-5 -> 8.0e-6 rad/s^2 with the missing terms, its
law alone 1.38e-5 -> 9.8e-6), and the small rate terms the flight pins down (wx^2, wx wz in wx'; wx^2, wy^2,
wy wz in wy') had t 0.8-6.3 beside it, 4.2-16.3 beside the refit one: below the pick's min_t, so no move
took them. Here each of the law's additive parts (b_ik u_i^2 / H_i^k, c_ik s_i / H_i^k) gets a multiplier,
fitted by least squares with the other terms on the fit rows (the hubs' offsets kept: the linear part of
the law's variable projection), and the law is rebuilt with the parts so scaled, still one feature.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS
from identification.cross_validation import FoldedRows
from identification.weak_noise import column_scale


def is_hub_law(shape: sympy.Expr) -> bool:
    """Whether a term is a hub law: a sum of two or more parts, each reading the height h and the gravity
    direction gx (the hubs' heights; HubLaw.expression)."""
    h, gx = PRIMITIVE_SYMBOLS["h"], PRIMITIVE_SYMBOLS["gx"]
    if not shape.is_Add or len(shape.args) < 2:
        return False
    return all(a.has(h) and a.has(gx) for a in shape.args)


def refit_law(shapes: Sequence[sympy.Expr], rows: FoldedRows) -> list[sympy.Expr] | None:
    """The terms with their hub law's parts rescaled by least squares beside the other terms on the fit rows
    (module docstring), in the same order; None when they hold no hub law (or more than one), the fit is
    not finite, or the law would not change."""
    laws = [i for i, s in enumerate(shapes) if is_hub_law(s)]
    if len(laws) != 1:
        return None
    at = laws[0]
    parts = list(sympy.Add.make_args(shapes[at]))
    others = [s for i, s in enumerate(shapes) if i != at]
    a, y, _ = rows.fit_part([*others, *parts])
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(y))) or len(y) <= a.shape[1]:
        return None
    scale = column_scale(a)
    coef = np.linalg.lstsq(a / scale, y, rcond=None)[0] / scale
    multipliers = coef[len(others):]
    if not np.all(np.isfinite(multipliers)) or np.allclose(multipliers, multipliers.mean(), rtol=1e-9):
        return None  # the same law up to its one coefficient
    law = sympy.Add(*[sympy.Float(float(m)) * p for m, p in zip(multipliers, parts, strict=True) if m != 0.0])
    return [*shapes[:at], law, *shapes[at + 1:]]
