"""Body force and moment of a quadrotor with its own rotor geometry, aerodynamic effects and wind (PX4 SIH).

Each contribution to the body force and moment (FRD, about the CG) is summed; sitl.dynamics integrates the
rigid body. With v_a = R^T (v - v_wind) the body airspeed (m/s, FRD) and v_i = v_a + w x r_i each hub's
airspeed:

    T_i = ground_effect(h_i) * (Ct_i w_i^2 + translational_lift(v_i))        rotor thrusts, N along -z
    F_b = sum_i (0, 0, -T_i) + rotor_drag(w_i, v_i) + frame_drag(v_a)        body force, N
    M_b = sum_i r_i x (0, 0, -T_i) - s_i Cm_i w_i^2 e3 + rotor drag moment   body moment, N m
    m dv/dt = m g e3 + R F_b ;  J dw/dt = M_b - w x (J w + (0, 0, h_z)) - D w,  h_z = Jm sum_i s_i w_i

The effects are plug-ins of two kinds, each built from the vehicle file and None when off: thrust modifiers
(sitl.translational_lift adds to T_i, sitl.ground_effect multiplies it) and wrench sources (sitl.rotor_drag,
sitl.frame_drag). The wind list is read at every call (sitl.dynamics.Quadrotor sets it once per exchange
step). This composition is the readable reference; the SITL steps with sitl.fused_wrench, the same wrench in
one pass, which tests/test_fused_wrench.py holds equal to it.
"""

from __future__ import annotations

from collections.abc import Callable

from bridge.vehicle import VehicleConfig
from sitl.frame_drag import frame_drag
from sitl.ground_effect import ground_effect
from sitl.rotor_drag import rotor_drag
from sitl.rotor_geometry import RotorGeometry
from sitl.translational_lift import translational_lift


def inverse3(m: tuple) -> tuple:
    """Inverse of a 3x3 matrix (rows of floats), as 9 floats row-major."""
    (a, b, c), (d, e, f), (g, h, i) = m
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    return (
        (e * i - f * h) / det, (c * h - b * i) / det, (b * f - c * e) / det,
        (f * g - d * i) / det, (a * i - c * g) / det, (c * d - a * f) / det,
        (d * h - e * g) / det, (b * g - a * h) / det, (a * e - b * d) / det,
    )


def airframe_wrench(vehicle: VehicleConfig, wind: list[float]) -> Callable[..., tuple[float, ...]]:
    """f(z, v NED, w FRD, rotor speeds, R row-major) -> (F_b N, M_b N m, h_z N m s), body FRD about the CG.

    wind: NED m/s, read at every call. Rotor speeds in rad/s, z in m (NED), R body -> earth.
    """
    geometry = RotorGeometry(vehicle)
    ct1, ct2, ct3, ct4 = geometry.thrust_coefficients
    aero = vehicle.aero
    drag = rotor_drag(aero.rotor_drag, geometry.arms) if aero.rotor_drag is not None else None
    lift = translational_lift(aero.translational_lift) if aero.translational_lift else None
    ground = (ground_effect(aero.ground_effect)
              if aero.ground_effect is not None and vehicle.ground == "plane" else None)
    frame = (frame_drag(aero.frame_drag, vehicle.drag.body_quadratic)
             if any(aero.frame_drag) or any(vehicle.drag.body_quadratic) else None)
    need_air = drag is not None or lift is not None
    airspeeds = geometry.airspeeds()
    heights = geometry.heights()
    rotor_wrench = geometry.wrench()

    def wrench(z: float, vx: float, vy: float, vz: float, wx: float, wy: float, wz: float,
               w1: float, w2: float, w3: float, w4: float, r00: float, r01: float, r02: float, r10: float,
               r11: float, r12: float, r20: float, r21: float, r22: float) -> tuple[float, ...]:
        # body airspeed R^T (v - wind)
        ex, ey, ez = vx - wind[0], vy - wind[1], vz - wind[2]
        ux = r00 * ex + r10 * ey + r20 * ez
        uy = r01 * ex + r11 * ey + r21 * ez
        uz = r02 * ex + r12 * ey + r22 * ez
        t1, t2, t3, t4 = ct1 * w1 * w1, ct2 * w2 * w2, ct3 * w3 * w3, ct4 * w4 * w4
        if need_air:
            air = airspeeds(ux, uy, uz, wx, wy, wz)
            if lift is not None:
                e1, e2, e3, e4 = lift(air)
                t1, t2, t3, t4 = t1 + e1, t2 + e2, t3 + e3, t4 + e4
        if ground is not None:
            g1, g2, g3, g4 = ground(*heights(z, r20, r21, r22))
            t1, t2, t3, t4 = t1 * g1, t2 * g2, t3 * g3, t4 * g4
        thrust, tx, ty, tz, hz = rotor_wrench(t1, t2, t3, t4, w1, w2, w3, w4)
        fbx = fby = 0.0
        fbz = -thrust
        if drag is not None:
            fx, fy, fz, mx, my, mz = drag(w1, w2, w3, w4, air)
            fbx += fx
            fby += fy
            fbz += fz
            tx += mx
            ty += my
            tz += mz
        if frame is not None:
            fx, fy, fz = frame(ux, uy, uz)
            fbx += fx
            fby += fy
            fbz += fz
        return fbx, fby, fbz, tx, ty, tz, hz

    return wrench
