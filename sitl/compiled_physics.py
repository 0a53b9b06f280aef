"""The compiled state derivative (C extension sitl._derivative), when the install could build it.

The C code is sitl.dynamics.make_derivative's Python derivative (with sitl.fused_wrench's airframe wrench)
written out in the same order, built without fused multiply-adds, so both give bit-identical results
(tests/test_compiled_derivative.py holds them equal with ==). The Python derivative stays the reference and
the fallback: an install without a C compiler runs the same physics about 4x slower per step.
QUADSR_PHYSICS=python in the environment chooses the Python derivative even where the extension is built.
"""

from __future__ import annotations

import functools
import os
import struct

from bridge.integration import Derivative
from bridge.vehicle import VehicleConfig
from sitl.airframe_dynamics import inverse3
from sitl.fused_wrench import wrench_constants

try:
    from sitl import _derivative
except ImportError:  # no compiler at install time: the Python derivative
    _derivative = None

LAYOUT_VERSION = 1.0
# the C struct's doubles, in order (sitl/_derivative.c, Constants)
LAYOUT = (
    "version", "paper", "itm", "g", "im",
    *(f"j{r}{c}" for r in range(3) for c in range(3)), *(f"i{r}{c}" for r in range(3) for c in range(3)),
    "d0", "d1", "d2",
    "ct", "k", "cm", "jm", "cdx", "cdy", "cdz", "has_body_drag",
    "ct1", "ct2", "ct3", "ct4",
    "x1", "y1", "z1", "x2", "y2", "z2", "x3", "y3", "z3", "x4", "y4", "z4",
    "q1", "q2", "q3", "q4", "j1", "j2", "j3", "j4",
    "has_drag", "kd", "kz", "has_lift", "kh", "has_ground", "rr", "hmin", "has_frame",
    "cx", "cy", "cz", "dx", "dy", "dz", "need_air",
)
_PACK = struct.Struct(f"={len(LAYOUT)}d")


def available() -> bool:
    """True when the compiled derivative is built, matches this layout and is not switched off."""
    return (_derivative is not None and os.environ.get("QUADSR_PHYSICS", "").lower() != "python"
            and _derivative.CONSTANTS_SIZE == _PACK.size and _derivative.LAYOUT_VERSION == LAYOUT_VERSION)


def compiled_derivative(vehicle: VehicleConfig, inv_time_constant: float, mixer_constants: dict[str, float],
                        wind: list[float]) -> Derivative:
    """f(state, cmd) -> 17 floats: the compiled derivative with this vehicle's constants bound.

    mixer_constants: the paper physics' ct, k, cm, jm (sitl.mixer.QuadXMixer); wind: NED m/s, read at every
    call. Raises RuntimeError when the extension is not available().
    """
    if not available():
        raise RuntimeError("the compiled derivative (sitl._derivative) is not built or is switched off")
    paper = vehicle.paper_physics
    c = {name: 0.0 for name in LAYOUT}
    c["version"] = LAYOUT_VERSION
    c["paper"] = float(paper)
    c["itm"], c["g"], c["im"] = inv_time_constant, vehicle.gravity, 1.0 / vehicle.mass
    for r, row in enumerate(vehicle.inertia):
        for col, value in enumerate(row):
            c[f"j{r}{col}"] = value
    for n, value in enumerate(inverse3(vehicle.inertia)):  # 9 floats, row-major
        c[f"i{n // 3}{n % 3}"] = value
    c["d0"], c["d1"], c["d2"] = vehicle.drag.angular_damping
    if paper:
        c.update({k: mixer_constants[k] for k in ("ct", "k", "cm", "jm")})
        c["cdx"], c["cdy"], c["cdz"] = vehicle.drag.body_quadratic
        c["has_body_drag"] = float(any(x != 0.0 for x in vehicle.drag.body_quadratic))
    else:
        c.update(wrench_constants(vehicle))
    constants = _PACK.pack(*(float(c[name]) for name in LAYOUT))
    return functools.partial(_derivative.derivative, constants, wind)
