"""Dryden turbulence (MIL-F-8785C, low altitude): three shaping filters on seeded white noise, exact samples.

Components in the mean-wind axes (u along the horizontal wind, v to its right, w down), m/s. One-sided power
spectral densities over angular frequency omega (rad/s), V the mean wind speed (m/s), L the scale lengths (m):
  Phi_u(omega) = sigma_u^2 (2 L_u / (pi V)) / (1 + (L_u omega / V)^2)
  Phi_v(omega) = sigma_v^2 (L_v / (pi V)) (1 + 3 (L_v omega / V)^2) / (1 + (L_v omega / V)^2)^2   (w alike)
Each filter is a linear system driven by white noise, advanced by its exact discrete form (transition e^(A dt)
and the noise covariance by Van Loan's method) and started from its stationary covariance, so the samples have
exactly the variance sigma^2 from the first one on.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import expm, solve_continuous_lyapunov

from bridge.airframe import dryden_parameters

Vec3 = tuple[float, float, float]
NOISE_BLOCK = 4096  # steps of white noise drawn at once


def dryden_psd(component: str, omega: np.ndarray, sigma: float, length: float, speed: float) -> np.ndarray:
    """The analytic one-sided PSD of component u, v or w, (m/s)^2/(rad/s), at omega (rad/s)."""
    x2 = (length * np.asarray(omega) / speed) ** 2
    if component == "u":
        return sigma**2 * 2.0 * length / (math.pi * speed) / (1.0 + x2)
    return sigma**2 * length / (math.pi * speed) * (1.0 + 3.0 * x2) / (1.0 + x2) ** 2


def _discrete(a: np.ndarray, b: np.ndarray, c: np.ndarray, sigma: float, dt: float):
    """(Ad, cholesky(Qd), C scaled to output variance sigma^2, a stationary-state sampler's factor)."""
    n = a.shape[0]
    q = b @ b.T
    # Van Loan: expm([[-A, Q], [0, A^T]] dt) = [[., Ad^-1 Qd], [0, Ad^T]]
    block = np.zeros((2 * n, 2 * n))
    block[:n, :n] = -a
    block[:n, n:] = q
    block[n:, n:] = a.T
    e = expm(block * dt)
    ad = e[n:, n:].T
    qd = ad @ e[:n, n:]
    qd = 0.5 * (qd + qd.T)
    p = solve_continuous_lyapunov(a, -q)  # stationary covariance: A P + P A^T + Q = 0
    scale = sigma / math.sqrt(float(c @ p @ c))
    return ad, np.linalg.cholesky(qd), c * scale, np.linalg.cholesky(p)


class DrydenTurbulence:
    """Seeded Dryden turbulence sampled every dt seconds: step() -> (u, v, w) m/s in the mean-wind axes."""

    def __init__(self, preset: str, altitude: float, speed: float, dt: float, seed: int):
        self.sigma, self.length = dryden_parameters(preset, altitude)  # m/s, m
        self.speed = speed  # m/s
        self.dt = dt  # s
        self._rng = np.random.default_rng(seed)
        parts = []
        for i, comp in enumerate("uvw"):
            tau = self.length[i] / speed  # s
            if comp == "u":
                a = np.array([[-1.0 / tau]])
                c = np.array([1.0])
            else:  # (1 + sqrt(3) tau s) / (1 + tau s)^2 in controllable canonical form
                a = np.array([[0.0, 1.0], [-1.0 / tau**2, -2.0 / tau]])
                c = np.array([1.0 / tau**2, math.sqrt(3.0) / tau])
            b = np.zeros((a.shape[0], 1))
            b[-1, 0] = 1.0
            parts.append(_discrete(a, b, c, self.sigma[i], dt))
        # plain floats from here on: one step per 4 ms exchange, numpy's per-call cost would dominate
        (self._au,), (self._lu,) = parts[0][0].tolist(), parts[0][1].tolist()
        (self._cu,) = parts[0][2].tolist()
        # the 2x2 transitions A, lower-triangular noise factors L and outputs C of v and w, entry by entry
        (self._av00, self._av01), (self._av10, self._av11) = parts[1][0].tolist()
        (self._lv00, _), (self._lv10, self._lv11) = parts[1][1].tolist()
        self._cv0, self._cv1 = parts[1][2].tolist()
        (self._aw00, self._aw01), (self._aw10, self._aw11) = parts[2][0].tolist()
        (self._lw00, _), (self._lw10, self._lw11) = parts[2][1].tolist()
        self._cw0, self._cw1 = parts[2][2].tolist()
        x0 = [(p[3] @ self._rng.standard_normal(p[3].shape[0])).tolist() for p in parts]  # stationary start
        self._xu = x0[0][0]
        self._xv0, self._xv1 = x0[1]
        self._xw0, self._xw1 = x0[2]
        self._noise: list[float] = []

    def current(self) -> Vec3:
        """The turbulence now, (u, v, w) m/s in the mean-wind axes."""
        return (self._cu * self._xu, self._cv0 * self._xv0 + self._cv1 * self._xv1,
                self._cw0 * self._xw0 + self._cw1 * self._xw1)

    def step(self) -> Vec3:
        """Advance dt seconds (x' = A x + L n for each filter); the new (u, v, w), m/s."""
        if not self._noise:  # white noise drawn in blocks, 5 numbers a step, in a fixed order
            self._noise = self._rng.standard_normal(5 * NOISE_BLOCK).tolist()[::-1]
        pop = self._noise.pop
        self._xu = self._au[0] * self._xu + self._lu[0] * pop()
        n0, n1 = pop(), pop()
        x0, x1 = self._xv0, self._xv1
        self._xv0 = self._av00 * x0 + self._av01 * x1 + self._lv00 * n0
        self._xv1 = self._av10 * x0 + self._av11 * x1 + self._lv10 * n0 + self._lv11 * n1
        n0, n1 = pop(), pop()
        x0, x1 = self._xw0, self._xw1
        self._xw0 = self._aw00 * x0 + self._aw01 * x1 + self._lw00 * n0
        self._xw1 = self._aw10 * x0 + self._aw11 * x1 + self._lw10 * n0 + self._lw11 * n1
        return self.current()
