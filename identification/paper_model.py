"""The paper's learned model (Fang & Chen, Sec. II-B) in our variable names: a reference to compare with.

xi_4..6 = vx, vy, vz (NED m/s), xi_7..9 = phi, theta, psi (rad), xi_10..12 = wx, wy, wz (FRD rad/s),
u1..u4 rotor speeds (rad/s). zeta_4..6 are x'', y'', z'' and zeta_10..12 are wx', wy', wz'; zeta_7..9 are the
known Euler-angle rates. Its gyroscopic signs are flipped against Euler's equations (see quadsr.equations).
"""

from __future__ import annotations

import functools

from identification.model_file import Model, parse_expression

PAPER_EQUATIONS: dict[str, str] = {
    "ax": "-0.00768*u1*sin(phi)*sin(psi) - 1.63e-5*u2*u4*sin(phi)*sin(psi)"
          " - 0.00665*theta*u1*cos(phi)*cos(psi) - 1.63e-5*theta*u2*u4*cos(phi)*cos(psi)",
    "ay": "7.87e-6*u1**2*sin(phi + psi) + 7.78e-6*u2**2*sin(phi + psi) + 7.78e-6*u3**2*sin(phi + psi)"
          " + 7.78e-6*u4**2*sin(phi + psi) - 0.0441",
    "az": "9.44 - 6.90e-6*cos(phi)*(u1**2 + u2**2 + u3**2 + u4**2) - 0.000289*vz**2",
    "dwx": "0.697*wy*wz + 8.33e-5*(u2**2 + u3**2 - u1**2 - u4**2)",
    "dwy": "-0.708*wx*wz + 8.03e-5*(u1**2 + u3**2 - u2**2 - u4**2)",
    "dwz": "0.0219*wx*wy + 4.86e-6*(u1**2 + u2**2 - u3**2 - u4**2)",
}
PAPER_ZETA = {"ax": 4, "ay": 5, "az": 6, "dwx": 10, "dwy": 11, "dwz": 12}
PAPER_KINEMATICS: dict[str, str] = {
    "dphi": "sin(phi)*sin(theta)/cos(theta)*wy + cos(phi)*sin(theta)/cos(theta)*wz + wx",
    "dtheta": "cos(phi)*wy - sin(phi)*wz",
    "dpsi": "sin(phi)/cos(theta)*wy + cos(phi)/cos(theta)*wz",
}


@functools.lru_cache(maxsize=1)
def paper_model() -> Model:
    """The paper's zeta_4..6 and zeta_10..12 as a Model in our variable names."""
    return Model({name: parse_expression(text) for name, text in PAPER_EQUATIONS.items()}, kind="learned",
                 engine={"name": "paper (Eureqa)"})
