"""The airframe wrench in one pass (the SITL's fast path): every effect of sitl.airframe_dynamics fused.

The same body force and moment (FRD, about the CG) as sitl.airframe_dynamics.airframe_wrench, which composes
the readable per-effect functions (sitl.rotor_geometry, sitl.translational_lift, sitl.ground_effect,
sitl.rotor_drag, sitl.frame_drag) and stays the reference: tests/test_fused_wrench.py checks that the two
agree to 1e-12 at many random states, near the ground and in wind. Here the four rotors are unrolled once for
all effects, the constants are bound at construction, no tuple is built between effects, and an effect that
is off costs one branch. The arithmetic keeps each effect's order of operations, so the results are normally
bit-identical to the reference's. Change a law in its own module first, then here.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from bridge.vehicle import VehicleConfig
from sitl.rotor_geometry import RotorGeometry


def wrench_constants(vehicle: VehicleConfig) -> dict[str, float]:
    """The constants the fused wrench binds (arms m FRD, coefficients SI, 0/1 effect switches), by name."""
    geometry = RotorGeometry(vehicle)
    c: dict[str, float] = {}
    for i, (ct, (x, y, z), spin, cm) in enumerate(zip(
            geometry.thrust_coefficients, geometry.arms, geometry.spins, geometry.moment_coefficients,
            strict=True), start=1):
        c[f"ct{i}"], c[f"x{i}"], c[f"y{i}"], c[f"z{i}"] = ct, x, y, z
        c[f"q{i}"] = -spin * cm
        c[f"j{i}"] = spin * geometry.rotor_inertia
    aero = vehicle.aero
    has_drag = aero.rotor_drag is not None
    c["has_drag"] = float(has_drag)
    c["kd"], c["kz"] = (aero.rotor_drag.k_d, aero.rotor_drag.k_z) if has_drag else (0.0, 0.0)
    c["kh"] = aero.translational_lift
    c["has_lift"] = float(c["kh"] != 0.0)
    has_ground = aero.ground_effect is not None and vehicle.ground == "plane"
    c["has_ground"] = float(has_ground)
    c["rr"] = (aero.ground_effect.rotor_radius / 4.0) ** 2 if has_ground else 0.0  # (R/4)^2, m^2
    c["hmin"] = aero.ground_effect.min_height if has_ground else 0.0  # m
    c["cx"], c["cy"], c["cz"] = aero.frame_drag
    c["dx"], c["dy"], c["dz"] = vehicle.drag.body_quadratic
    c["has_frame"] = float(any(aero.frame_drag) or any(vehicle.drag.body_quadratic))
    c["need_air"] = float(has_drag or c["has_lift"] != 0.0)
    return c


def fused_airframe_wrench(vehicle: VehicleConfig, wind: list[float]) -> Callable[..., tuple[float, ...]]:
    """f(z, v NED, w FRD, rotor speeds, R row-major) -> (F_b N, M_b N m, h_z N m s), body FRD about the CG.

    The signature and results of sitl.airframe_dynamics.airframe_wrench. wind: NED m/s, read at every call.
    """
    c = wrench_constants(vehicle)
    ct1, ct2, ct3, ct4 = c["ct1"], c["ct2"], c["ct3"], c["ct4"]
    x1, y1, z1, x2, y2, z2 = c["x1"], c["y1"], c["z1"], c["x2"], c["y2"], c["z2"]  # m, FRD from the CG
    x3, y3, z3, x4, y4, z4 = c["x3"], c["y3"], c["z3"], c["x4"], c["y4"], c["z4"]
    q1, q2, q3, q4 = c["q1"], c["q2"], c["q3"], c["q4"]
    j1, j2, j3, j4 = c["j1"], c["j2"], c["j3"], c["j4"]
    has_drag, kd, kz = c["has_drag"] != 0.0, c["kd"], c["kz"]
    kh, has_lift = c["kh"], c["has_lift"] != 0.0
    has_ground, rr, hmin = c["has_ground"] != 0.0, c["rr"], c["hmin"]
    cx, cy, cz, dx, dy, dz = c["cx"], c["cy"], c["cz"], c["dx"], c["dy"], c["dz"]
    has_frame, need_air = c["has_frame"] != 0.0, c["need_air"] != 0.0
    sqrt = math.sqrt

    def wrench(z: float, vx: float, vy: float, vz: float, wx: float, wy: float, wz: float,
               w1: float, w2: float, w3: float, w4: float, r00: float, r01: float, r02: float, r10: float,
               r11: float, r12: float, r20: float, r21: float, r22: float) -> tuple[float, ...]:
        # body airspeed R^T (v - wind), m/s FRD
        wn, we, wd = wind
        ex, ey, ez = vx - wn, vy - we, vz - wd
        ux = r00 * ex + r10 * ey + r20 * ez
        uy = r01 * ex + r11 * ey + r21 * ez
        uz = r02 * ex + r12 * ey + r22 * ez
        t1, t2, t3, t4 = ct1 * w1 * w1, ct2 * w2 * w2, ct3 * w3 * w3, ct4 * w4 * w4
        if need_air:  # each hub's airspeed v_a + w x r_i (sitl.rotor_geometry)
            a1x, a1y, a1z = ux + wy * z1 - wz * y1, uy + wz * x1 - wx * z1, uz + wx * y1 - wy * x1
            a2x, a2y, a2z = ux + wy * z2 - wz * y2, uy + wz * x2 - wx * z2, uz + wx * y2 - wy * x2
            a3x, a3y, a3z = ux + wy * z3 - wz * y3, uy + wz * x3 - wx * z3, uz + wx * y3 - wy * x3
            a4x, a4y, a4z = ux + wy * z4 - wz * y4, uy + wz * x4 - wx * z4, uz + wx * y4 - wy * x4
            if has_lift:  # sitl.translational_lift
                t1 = t1 + kh * (a1x * a1x + a1y * a1y)
                t2 = t2 + kh * (a2x * a2x + a2y * a2y)
                t3 = t3 + kh * (a3x * a3x + a3y * a3y)
                t4 = t4 + kh * (a4x * a4x + a4y * a4y)
        if has_ground:  # sitl.ground_effect at each hub's height -(z + (R r_i)_z)
            h1 = -(z + r20 * x1 + r21 * y1 + r22 * z1)
            h2 = -(z + r20 * x2 + r21 * y2 + r22 * z2)
            h3 = -(z + r20 * x3 + r21 * y3 + r22 * z3)
            h4 = -(z + r20 * x4 + r21 * y4 + r22 * z4)
            h1 = h1 if h1 > hmin else hmin
            h2 = h2 if h2 > hmin else hmin
            h3 = h3 if h3 > hmin else hmin
            h4 = h4 if h4 > hmin else hmin
            t1 = t1 * (1.0 / (1.0 - rr / (h1 * h1)))
            t2 = t2 * (1.0 / (1.0 - rr / (h2 * h2)))
            t3 = t3 * (1.0 / (1.0 - rr / (h3 * h3)))
            t4 = t4 * (1.0 / (1.0 - rr / (h4 * h4)))
        # the rotors' thrust and torques (sitl.rotor_geometry.wrench)
        fbz = -(t1 + t2 + t3 + t4)
        tx = -(y1 * t1 + y2 * t2 + y3 * t3 + y4 * t4)
        ty = x1 * t1 + x2 * t2 + x3 * t3 + x4 * t4
        tz = q1 * w1 * w1 + q2 * w2 * w2 + q3 * w3 * w3 + q4 * w4 * w4
        hz = j1 * w1 + j2 * w2 + j3 * w3 + j4 * w4
        fbx = fby = 0.0
        if has_drag:  # sitl.rotor_drag: F_i = -w_i diag(kd, kd, kz) v_i at the hub
            d1, d2, d3, d4 = -w1 * kd, -w2 * kd, -w3 * kd, -w4 * kd
            fx1, fy1, fz1 = d1 * a1x, d1 * a1y, -w1 * kz * a1z
            fx2, fy2, fz2 = d2 * a2x, d2 * a2y, -w2 * kz * a2z
            fx3, fy3, fz3 = d3 * a3x, d3 * a3y, -w3 * kz * a3z
            fx4, fy4, fz4 = d4 * a4x, d4 * a4y, -w4 * kz * a4z
            fbx = fx1 + fx2 + fx3 + fx4
            fby = fy1 + fy2 + fy3 + fy4
            fbz += fz1 + fz2 + fz3 + fz4
            tx += ((y1 * fz1 - z1 * fy1) + (y2 * fz2 - z2 * fy2) + (y3 * fz3 - z3 * fy3)
                   + (y4 * fz4 - z4 * fy4))
            ty += ((z1 * fx1 - x1 * fz1) + (z2 * fx2 - x2 * fz2) + (z3 * fx3 - x3 * fz3)
                   + (z4 * fx4 - x4 * fz4))
            tz += ((x1 * fy1 - y1 * fx1) + (x2 * fy2 - y2 * fx2) + (x3 * fy3 - y3 * fx3)
                   + (x4 * fy4 - y4 * fx4))
        if has_frame:  # sitl.frame_drag: -|v_a| C v_a - Cd v_a |v_a| per axis
            speed = sqrt(ux * ux + uy * uy + uz * uz)
            fbx += -(speed * cx + dx * (ux if ux > 0.0 else -ux)) * ux  # |u| without a builtin call
            fby += -(speed * cy + dy * (uy if uy > 0.0 else -uy)) * uy
            fbz += -(speed * cz + dz * (uz if uz > 0.0 else -uz)) * uz
        return fbx, fby, fbz, tx, ty, tz, hz

    return wrench
