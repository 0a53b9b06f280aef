"""The known kinematics: symbolic ZYX rotation, Euler-angle rates from body rates (not learned).

The numeric rotation matrix is bridge.rotations.rotation_matrix.

R = Rz(psi) Ry(theta) Rx(phi) maps body FRD to earth NED. The Euler rates are the paper's transform
(phi', theta', psi') = W(phi, theta) (wx, wy, wz), singular at theta = +-pi/2.
"""

from __future__ import annotations

import numpy as np
import sympy


def rotation_matrix_sym(phi: sympy.Expr, theta: sympy.Expr, psi: sympy.Expr) -> sympy.Matrix:
    """Body FRD -> earth NED rotation Rz(psi) Ry(theta) Rx(phi) as a sympy Matrix."""
    cf, sf = sympy.cos(phi), sympy.sin(phi)
    ct, st = sympy.cos(theta), sympy.sin(theta)
    cp, sp = sympy.cos(psi), sympy.sin(psi)
    return sympy.Matrix(
        [
            [ct * cp, sf * st * cp - cf * sp, cf * st * cp + sf * sp],
            [ct * sp, sf * st * sp + cf * cp, cf * st * sp - sf * cp],
            [-st, sf * ct, cf * ct],
        ]
    )


def euler_rate_matrix_sym(phi: sympy.Expr, theta: sympy.Expr) -> sympy.Matrix:
    """The paper's W with (phi', theta', psi') = W (wx, wy, wz), sympy."""
    t, c = sympy.tan(theta), sympy.cos(theta)
    return sympy.Matrix(
        [
            [1, sympy.sin(phi) * t, sympy.cos(phi) * t],
            [0, sympy.cos(phi), -sympy.sin(phi)],
            [0, sympy.sin(phi) / c, sympy.cos(phi) / c],
        ]
    )


def euler_rates(phi: np.ndarray | float, theta: np.ndarray | float, rates: np.ndarray) -> np.ndarray:
    """Euler angle rates (phi', theta', psi') in rad/s from body rates FRD (...,3) in rad/s."""
    w = np.asarray(rates, float)
    phi = np.asarray(phi, float)
    theta = np.asarray(theta, float)
    wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
    sf, cf, ct, tt = np.sin(phi), np.cos(phi), np.cos(theta), np.tan(theta)
    return np.stack([wx + (sf * wy + cf * wz) * tt, cf * wy - sf * wz, (sf * wy + cf * wz) / ct], axis=-1)


def euler_rate_expressions(symbols: dict[str, sympy.Symbol]) -> dict[str, sympy.Expr]:
    """phi', theta', psi' (rad/s) as sympy expressions of the state symbols (the known transform)."""
    s = symbols
    rates = euler_rate_matrix_sym(s["phi"], s["theta"]) * sympy.Matrix([s["wx"], s["wy"], s["wz"]])
    return {"dphi": rates[0], "dtheta": rates[1], "dpsi": rates[2]}
