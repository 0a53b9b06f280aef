"""The weak (integral) form of identification, after weak SINDy (Messenger and Bortz 2021).

Differentiating 250 Hz IMU data amplifies its noise; smoothing the derivative (Savitzky-Golay) trades that
noise for bias, because the smoothed target is compared with the model at one instant. In the weak form the
equation y' = f(xi, u) is multiplied by test functions phi_j that vanish at the ends of their windows and
integrated: int phi_j y' dt = -int phi_j' y dt = int phi_j f(xi, u) dt. The data are never differentiated on
their own (the left side is the test function's derivative against the measured y), and the model is
integrated against the same test function, so a long window removes noise without biasing anything.

Here a test function is phi(s) = (1 - s^2)^p on s = (t - t_j) / T in [-1, 1] (T the half window, s), its
weights over the samples normalised to sum 1, so every weak value is a weighted mean in the target's own
unit (m/s^2, rad/s^2). One sparse matrix V (M, N) holds them (weak_operator): weak targets are V y_raw and
weak predictions V f(rows), for any model, learned or true. y_raw is the least-smoothed point target
(specific force as measured; the gyro's 5-sample derivative): by summation by parts, V times a difference
quotient of the gyro is -sum(phi_j') w dt, the weak form's left side.

Both sides must be the same functional of the flight. On our SITL's .tlog the commands are held over 4 ms
steps and every change leaves a kink at a sample (the motor lag restarts): V f(samples) and V times the
gyro's 5-sample derivative then differ by that kink's quadrature error, which grows with the motion, not
the noise (fang-chen-aero's paper-train flight, ideal sensors, true model: weak RMS of wy' 3.5e-2 rad/s^2,
as large as the realistic gyro's noise). So the raw targets of such a log are one row per step interval
(SensorTargetSettings.step_intervals, identification.readers.tlog): the gyro's difference over the step is
its exact mean derivative there and the rows' regressors are the step's (identification.step_targets):
6.9e-3 rad/s^2 on the same flight. The step's mean of a product is not the product of its means, though:
at a command change the rotors move by up to a fifth of the change within the step, and the true model at
the row's state missed the gyro's step means by up to 0.97 rad/s^2 (0.030 rad/s^2 RMS, wx', fang-chen-aero's
realistic-sensor paper-train flight, seed 23, against its noise-free rates), an error that is systematic
and whose low frequencies were 13 times the differenced gyro noise's there, the band the weak form weighs
up. So each step is two rows, its Gauss nodes on the step's path (Dataset.at_step_nodes), with the step's
t and target, and a test function weighs each step's rows by half its weight (node_groups): V f(rows) is
then the two-node mean of any model over each step: 0.0031 rad/s^2 RMS, 0.04 at most, on that flight, the
low frequencies under the noise's. Real logs (ULog, DataFlash) sample continuous motors: samples as they
are.

Windows never span a gap: centres every `stride_s` inside each contiguous run, whole windows only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse

from bridge.errors import UserError
from identification.targets import SensorTargetSettings, contiguous_runs, nominal_step

# the point targets the weak form integrates: raw specific force, the gyro's 5-sample quadratic derivative
# (on our .tlog: per step interval, the gyro's difference over the step)
RAW_SENSOR_TARGETS = SensorTargetSettings(window_s=0.0, polyorder=2, smooth_accel=False, step_intervals=True)


@dataclass(frozen=True)
class WeakSettings:
    """Test functions: half window T (s), spacing of their centres (s), power p of (1 - s^2)^p."""

    half_window_s: float = 0.2
    stride_s: float = 0.02
    power: int = 4

    def check(self) -> None:
        """UserError for a window or stride that is not a positive number of seconds, or p < 1."""
        for name, v in (("half window", self.half_window_s), ("stride", self.stride_s)):
            if not (np.isfinite(v) and v > 0):
                raise UserError(f"weak form: the {name} must be a positive number of seconds, got {v}")
        if int(self.power) != self.power or self.power < 1:
            raise UserError(f"weak form: the test function's power must be a whole number >= 1, "
                            f"got {self.power}")


def node_groups(t: np.ndarray) -> tuple[np.ndarray, sparse.csr_matrix]:
    """(the distinct times, G (T, N)): rows at one time t (s, non-decreasing) are one sample's nodes
    (Dataset.at_step_nodes), G[g, i] = 1 / (rows at time g) for each row i at it: G y is each sample's
    mean."""
    t = np.asarray(t, dtype=float)
    times, group, counts = np.unique(t, return_inverse=True, return_counts=True)
    g = sparse.csr_matrix((1.0 / counts[group], (group, np.arange(len(t)))), shape=(len(times), len(t)))
    return times, g


def weak_operator(t: np.ndarray, settings: WeakSettings | None = None) -> sparse.csr_matrix:
    """V (M, N): row j the normalised test-function weights of window j over samples at times t (s).

    Windows of 2 K + 1 samples (K = round(T / dt), dt the median spacing) centred every stride inside each
    contiguous run of t; a run shorter than one window gives none. M may be 0. Rows that share a time are
    one sample's nodes: the sample's weight is shared among them (node_groups).
    """
    t = np.asarray(t, dtype=float)
    if len(t) > 1 and not np.all(np.diff(t) > 0):
        times, groups = node_groups(t)
        return (weak_operator(times, settings) @ groups).tocsr()
    s = settings or WeakSettings()
    s.check()
    n = len(t)
    if n < 3:
        return sparse.csr_matrix((0, n))
    dt = nominal_step(t)
    k = max(1, int(round(s.half_window_s / dt)))
    stride = max(1, int(round(s.stride_s / dt)))
    offsets = np.arange(-k, k + 1)
    phi = (1.0 - (offsets / (k + 1.0)) ** 2) ** int(s.power)  # zero just past each end of the window
    phi /= phi.sum()
    centres = [
        np.arange(run.start + k, run.stop - k, stride)
        for run in contiguous_runs(t, dt)
        if run.stop - run.start >= 2 * k + 1
    ]
    c = np.concatenate(centres) if centres else np.zeros(0, int)
    m = len(c)
    rows = np.repeat(np.arange(m), len(offsets))
    cols = (c[:, None] + offsets[None, :]).ravel()
    return sparse.csr_matrix((np.tile(phi, m), (rows, cols)), shape=(m, n))


def weak_rows(t: np.ndarray, flight: np.ndarray | None, settings: WeakSettings | None) -> sparse.csr_matrix:
    """weak_operator over rows of several flights (flight (N,) index per row): no window spans two flights."""
    t = np.asarray(t, dtype=float)
    if flight is None or len(np.unique(flight)) <= 1:
        return weak_operator(t, settings)
    blocks = []
    order = []
    for f in np.unique(flight):
        idx = np.flatnonzero(flight == f)
        blocks.append(weak_operator(t[idx], settings))
        order.append(idx)
    stacked = sparse.block_diag(blocks, format="csr")
    perm = np.concatenate(order)  # stacked columns follow perm: put them back at their rows
    out = sparse.csr_matrix((stacked.shape[0], len(t)))
    out = stacked @ sparse.csr_matrix((np.ones(len(t)), (np.arange(len(t)), perm)), shape=(len(t), len(t)))
    return out.tocsr()


def overlap_lag(operator: sparse.spmatrix) -> int:
    """The largest distance in weak rows between two test-function windows that share a sample (0 when none
    do): weak values of white point noise are correlated up to this lag and not beyond (an MA(q) process),
    the lag collinearity.effective_rows sums autocorrelations to for weak rows."""
    v = sparse.csr_matrix(operator)
    if v.shape[0] < 2 or v.nnz == 0:
        return 0
    shared = (abs(v) @ abs(v).T).tocoo()
    return int(np.max(np.abs(shared.row - shared.col)))
