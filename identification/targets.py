"""The six identification targets from a flight: ax ay az (NED, m/s^2) and dwx dwy dwz (FRD, rad/s^2).

Two sources:
- truth: differentiate the true (or estimated) velocity NED and body rates FRD (a quadsr SITL .tlog carries
  its true accelerations, which its reader takes instead: identification.readers.tlog). On uniform samples
  we use the 5-point central difference (4th order). The SITL's commands change only at step boundaries, so
  the accelerations have kinks at samples (the rotor speed's slope jumps when a new command arrives), and a
  stencil across a kink is only first-order accurate there. Where the log says where the kinks are (our
  .tlog holds the companion's commands), stencils are chosen not to cross them: the 5-point central one
  where no kink is within one sample, else a 4-point one-sided one that stays on one smooth side (both
  averaged when both fit), else the 3-point central one, else 3- and 2-point one-sided ones. Measured on a
  paper-train flight of the SITL against its exact dynamics: R^2 of dwx/dwy 0.99988/0.99981 with the plain
  5-point stencil, above 0.99999 kink-aware (3-point central: 0.9994; Savitzky-Golay 7-9 samples:
  0.9985-0.9997, smoothing spreads each kink). The first and last two samples of a contiguous run have
  no value. Our .tlog uses exact step means instead where it can (identification.step_targets): with a
  new command every step every sample is a kink and these stencils fall to low order.
- sensors: specific force (accelerometer, FRD) rotated to NED with the attitude plus gravity (0, 0, g),
  and the gyro differentiated with a Savitzky-Golay filter; the specific force is smoothed likewise. No
  single window suits every axis: the yaw angular acceleration of the default vehicle is ~0.5 rad/s^2 RMS
  in the paper's validation flight while realistic gyro noise (0.01 rad/s at 250 Hz) differentiated over
  9 samples gives ~0.3 rad/s^2, yet roll and pitch need short windows to keep the motor-lag kinks. So by
  default each axis gets the window (1 or 5 samples .. 0.4 s) and order (2 or 4) of least estimated
  error (choose_savgol: the signal's spectrum from Welch minus the white-noise floor, the noise from the
  third differences). Noise-free sensors thus get the 5-point stencil and raw accelerations. Measured
  against the exact dynamics on 250 Hz SITL flights with the realistic sensor preset, R^2 of the worst
  target (always dwz), fixed 0.036 s order-2 window -> per-axis choice: paper-train (32 s) 0.991 ->
  0.9956, paper-validate (10 s) 0.547 -> 0.990, closed-loop (40 s) 0.841 -> 0.965 (the other five targets
  >= 0.997); each choice within 0.001 of the best window found by trying them all against the truth.
  The windows chosen are reported in the dataset's notes. quadsr identify fits sensor targets in the weak
  form by default (identification.weak_form), which needs these raw (RAW_SENSOR_TARGETS) instead.

Also the attitude helpers the readers share: quaternion -> ZYX Euler, body-to-NED rotation matrices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import savgol_coeffs

from bridge.rotations import rotation_matrix
from identification.robust_weights import robust_sigma

STANDARD_GRAVITY = 9.80665  # m/s^2, what PX4 and ArduPilot use


@dataclass(frozen=True)
class SensorTargetSettings:
    """Savitzky-Golay settings for sensor-derived targets.

    window_s None (default): each axis gets the window and polynomial order (2 or 4) with the least
    estimated error, from windows of 5 samples up to max_window_s (see choose_savgol). A number: that
    window (s, made odd in samples, at least polyorder + 2) and `polyorder` for every axis.
    """

    window_s: float | None = None
    polyorder: int = 2
    smooth_accel: bool = True  # smooth the specific force too (value, not derivative)
    max_window_s: float = 0.4
    # a log with the SITL's step structure (our .tlog: commands held over 4 ms steps): one row per step
    # interval instead, the gyro's difference over the step and the accelerometer's two ends averaged
    # (identification.readers.tlog); for the weak form, which integrates these raw targets
    step_intervals: bool = False

    def window_samples(self, dt: float) -> int:
        """Odd fixed window length in samples for sample interval dt (s), at least polyorder + 2."""
        n = int(round((self.window_s or 0.0) / dt))
        n = max(n, self.polyorder + 2)
        return n if n % 2 == 1 else n + 1


@dataclass(frozen=True)
class SavgolChoice:
    """The filter used on one axis: window (samples), polynomial order, the estimated white-noise std of
    the input (its unit) and the estimated RMS error of the output (its unit per s^deriv)."""

    window: int
    polyorder: int
    noise: float
    error: float


@dataclass(frozen=True)
class SensorTargets:
    """Sensor-derived targets (N,6) and the Savitzky-Golay filter chosen for each of the six axes."""

    values: np.ndarray
    filters: tuple[SavgolChoice, ...]

    @property
    def max_half_window(self) -> int:
        """Half the longest window (samples): rows this close to an event are affected by it."""
        return max(f.window for f in self.filters) // 2

    def describe(self, dt: float) -> str:
        """One line naming each axis's window (ms) and order."""
        parts = [
            f"{n} raw" if f.window == 1 else f"{n} {1000 * f.window * dt:.0f} ms/p{f.polyorder}"
            for n, f in zip(("ax", "ay", "az", "dwx", "dwy", "dwz"), self.filters, strict=True)
        ]
        return "Savitzky-Golay windows: " + ", ".join(parts)


# --------------------------------------------------------------------------------------------------------
# Attitude


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi) rad."""
    return (np.asarray(a, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi


# --------------------------------------------------------------------------------------------------------
# Contiguous runs and differentiation


def contiguous_runs(t: np.ndarray, dt: float, rtol: float = 0.05) -> list[slice]:
    """Slices of t (s) whose consecutive spacing is dt (s) within rtol: the runs a stencil may span."""
    t = np.asarray(t, dtype=float)
    if len(t) == 0:
        return []
    steps = np.diff(t)
    breaks = np.flatnonzero(np.abs(steps - dt) > rtol * dt) + 1
    edges = np.concatenate(([0], breaks, [len(t)]))
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]


def finite_runs(t: np.ndarray, dt: float, y: np.ndarray) -> list[slice]:
    """contiguous_runs of t (s) further split at the samples where y (N,) is not finite (a gap's NaN)."""
    finite = np.isfinite(np.asarray(y, dtype=float))
    out = []
    for run in contiguous_runs(t, dt):
        ok = np.concatenate(([False], finite[run], [False])).astype(np.int8)
        starts = np.flatnonzero(np.diff(ok) == 1)
        stops = np.flatnonzero(np.diff(ok) == -1)
        out += [slice(run.start + int(a), run.start + int(b)) for a, b in zip(starts, stops, strict=True)]
    return out


def five_point_derivative(y: np.ndarray, dt: float) -> np.ndarray:
    """d/dt of uniform samples y (N,...) by the 4th-order central stencil; NaN at the 2 end samples."""
    y = np.asarray(y, dtype=float)
    out = np.full(y.shape, np.nan)
    if len(y) >= 5:
        out[2:-2] = (y[:-4] - 8.0 * y[1:-3] + 8.0 * y[3:-1] - y[4:]) / (12.0 * dt)
    return out


def per_run(t: np.ndarray, dt: float, y: np.ndarray, fn) -> np.ndarray:
    """Apply fn(y_run) -> array to each contiguous run of t separately (NaN where fn gives none)."""
    out = np.full(np.shape(y), np.nan)
    for run in contiguous_runs(t, dt):
        out[run] = fn(y[run])
    return out


def nominal_step(t: np.ndarray) -> float:
    """The nominal sample interval (s): the median spacing of t."""
    if len(t) < 2:
        return float("nan")
    return float(np.median(np.diff(t)))


# --------------------------------------------------------------------------------------------------------
# Targets


# Finite-difference stencils (offsets, weights) for d/dt at offset 0, in units of 1/dt, by preference.
_CENTRAL5 = ((-2, -1, 1, 2), (1 / 12, -8 / 12, 8 / 12, -1 / 12))
_CENTRAL7 = ((-3, -2, -1, 1, 2, 3), (-1 / 60, 9 / 60, -45 / 60, 45 / 60, -9 / 60, 1 / 60))  # 6th order
_ONE_SIDED4 = (((0, 1, 2, 3), (-11 / 6, 3.0, -1.5, 1 / 3)), ((-3, -2, -1, 0), (-1 / 3, 1.5, -3.0, 11 / 6)))
_CENTRAL3 = ((-1, 1), (-0.5, 0.5))
_ONE_SIDED3 = (((0, 1, 2), (-1.5, 2.0, -0.5)), ((-2, -1, 0), (0.5, -2.0, 1.5)))
_ONE_SIDED2 = (((0, 1), (-1.0, 1.0)), ((-1, 0), (-1.0, 1.0)))


def kink_aware_derivative(y: np.ndarray, dt: float, kinks: np.ndarray) -> np.ndarray:
    """d/dt of uniform y (N,k) whose slope may jump at samples where kinks (N,) is True.

    A stencil is usable at sample i if it lies inside the run and has no kink strictly inside its span.
    Preference: 7-point central (6th order: the motor lag's transient after a kink has large high
    derivatives); 5-point central; mean of the usable 4-point one-sided ones; 3-point central; mean of the
    usable 3-point one-sided ones; then 2-point. The two samples at each end get NaN, like the 5-point rule.
    """
    y = np.asarray(y, dtype=float)
    n = len(y)
    out = np.full(y.shape, np.nan)
    if n < 5:
        return out
    kinks = np.asarray(kinks, dtype=bool)
    kink_count = np.concatenate(([0], np.cumsum(kinks)))  # kinks in samples [a, b) = kc[b] - kc[a]
    idx = np.arange(n)
    done = np.zeros(n, dtype=bool)
    done[:2] = done[n - 2 :] = True  # same edge loss as the 5-point rule

    def usable(offsets: tuple[int, ...]) -> np.ndarray:
        lo, hi = idx + min(offsets), idx + max(offsets)
        inside = (lo >= 0) & (hi < n)
        lo_c, hi_c = np.clip(lo, 0, n - 1), np.clip(hi, 0, n - 1)
        interior = kink_count[hi_c] - kink_count[np.minimum(lo_c + 1, n)]
        return inside & (interior == 0)

    def apply(stencil: tuple[tuple[int, ...], tuple[float, ...]], rows: np.ndarray) -> np.ndarray:
        offsets, weights = stencil
        return sum(w * y[rows + o] for o, w in zip(offsets, weights, strict=True)) / dt

    for group in ((_CENTRAL7,), (_CENTRAL5,), _ONE_SIDED4, (_CENTRAL3,), _ONE_SIDED3, _ONE_SIDED2):
        masks = [usable(s[0]) & ~done for s in group]
        any_ok = np.logical_or.reduce(masks)
        if not any_ok.any():
            continue
        total = np.zeros((n, *y.shape[1:]))
        count = np.zeros(n)
        for s, m in zip(group, masks, strict=True):
            rows = np.flatnonzero(m)
            total[rows] += apply(s, rows)
            count[rows] += 1
        rows = np.flatnonzero(any_ok)
        out[rows] = total[rows] / count[rows].reshape(-1, *([1] * (y.ndim - 1)))
        done |= any_ok
    return out


def truth_targets(
    t: np.ndarray,
    velocity_ned: np.ndarray,
    rates_frd: np.ndarray,
    dt: float | None = None,
    kinks: np.ndarray | None = None,
) -> np.ndarray:
    """Targets (N,6) from true velocity NED (m/s) and body rates FRD (rad/s) by 5-point differentiation.

    kinks (N,): samples where the command changed (the accelerations' slope jumps); stencils avoid
    crossing them (kink_aware_derivative). Rows without a stencil inside their contiguous run are NaN.
    """
    dt = nominal_step(t) if dt is None else dt
    y = np.concatenate((np.asarray(velocity_ned, float), np.asarray(rates_frd, float)), axis=1)
    if kinks is None:
        return per_run(t, dt, y, lambda run: five_point_derivative(run, dt))
    out = np.full(y.shape, np.nan)
    for run in contiguous_runs(t, dt):
        out[run] = kink_aware_derivative(y[run], dt, np.asarray(kinks)[run])
    return out


def specific_force_to_ned(accel_frd: np.ndarray, euler: np.ndarray, gravity: float) -> np.ndarray:
    """NED acceleration (N,3) m/s^2 = R(euler) f + (0, 0, g) of specific force f FRD (N,3) m/s^2."""
    r = rotation_matrix(euler[:, 0], euler[:, 1], euler[:, 2])
    a = np.einsum("nij,nj->ni", r, np.asarray(accel_frd, dtype=float))
    a[:, 2] += gravity
    return a


def white_noise_std(y: np.ndarray, runs: list[slice] | None = None) -> float:
    """Robust estimate of the white-noise std in a smooth signal y (N,): MAD of its third differences,
    pooled over the runs (slices of y; default all of y) so that each sample weighs the same.

    A third difference of white noise has variance 20 sigma^2; a smooth signal's is tiny at high rates,
    and the median ignores the few samples where the signal has a kink. A median over runs instead would
    let a few short scraps between gaps (too short for an estimate: 0) outvote the long runs.
    """
    y = np.asarray(y, dtype=float)
    parts = [np.diff(y[r], n=3) for r in (runs if runs is not None else [slice(0, len(y))])]
    d3 = np.concatenate(parts) if parts else np.zeros(0)
    d3 = d3[np.isfinite(d3)]
    if len(d3) < 10:
        return 0.0
    return robust_sigma(d3) / float(np.sqrt(20.0))


def run_noise_std(t: np.ndarray, dt: float, y: np.ndarray) -> float:
    """white_noise_std of y (N,) over its runs of finite, evenly spaced samples (finite_runs; t, dt in s)."""
    return white_noise_std(y, finite_runs(t, dt, y))


def _savgol_1d(y: np.ndarray, coeffs: np.ndarray) -> np.ndarray:
    out = np.full(len(y), np.nan)
    n = len(coeffs)
    if len(y) >= n:
        out[n // 2 : len(y) - n // 2] = np.convolve(y, coeffs[::-1], mode="valid")
    return out


def _candidates(dt: float, deriv: int, max_window_s: float) -> list[tuple[int, int, np.ndarray]]:
    """(window, polyorder, coefficients) tried by choose_savgol, smallest first (the reference)."""
    n_max = max(5, int(max_window_s / dt) | 1)
    windows = [
        n for n in (5, 7, 9, 11, 13, 15, 19, 23, 27, 33, 39, 47, 55, 65, 75, 89, 105, 125) if n <= n_max
    ]
    out = [(1, 0, np.ones(1))] if deriv == 0 else []
    for n in windows:
        for p in (2, 4):
            if p < n:
                out.append((n, p, savgol_coeffs(n, p, deriv=deriv, delta=dt, use="dot")))
    if deriv == 1:
        out.sort(key=lambda c: (c[0], -c[1]))  # reference: the 5-sample quartic, i.e. the 5-point stencil
    return out


def _signal_spectrum(
    t: np.ndarray, y: np.ndarray, dt: float, sigma: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """(frequencies Hz, one-sided PSD of the signal without its white noise) from Welch over the runs of
    finite samples (a NaN inside a Welch segment would make every bin NaN); None when no run is long enough.

    Bins where the measured PSD does not stand clear of the noise floor (3 standard errors) count as 0.
    """
    from scipy.signal import welch

    runs = [r for r in finite_runs(t, dt, y) if r.stop - r.start >= 64]
    nperseg = min(256, max((r.stop - r.start for r in runs), default=0))
    if nperseg < 64:
        return None
    total, segments = None, 0
    for r in runs:
        if r.stop - r.start < nperseg:
            continue
        f, p = welch(y[r], fs=1.0 / dt, nperseg=nperseg)
        k = max(1, 2 * (r.stop - r.start) // nperseg - 1)
        total = p * k if total is None else total + p * k
        segments += k
    psd = total / segments
    floor = 2.0 * sigma**2 * dt
    signal = np.where(psd > floor * (1.0 + 3.0 / np.sqrt(segments)), psd - floor, 0.0)
    return f, signal


def choose_savgol(
    t: np.ndarray, y: np.ndarray, dt: float, deriv: int, max_window_s: float = 0.4
) -> SavgolChoice:
    """The Savitzky-Golay window and order with the least estimated RMS error for signal y (N,).

    error^2 = sum over frequency of |H(f) - D(f)|^2 S(f) df + noise^2 sum(c^2): H the filter's response, D
    the ideal one (1, or j 2 pi f for the derivative), S the signal's spectrum (Welch PSD minus the white
    noise floor), noise the white-noise std from white_noise_std. Without a run of finite samples long
    enough for a spectrum: the reference (the 5-point stencil, or no smoothing), with its noise error.
    """
    y = np.asarray(y, dtype=float)
    sigma = run_noise_std(t, dt, y)
    cands = _candidates(dt, deriv, max_window_s)
    estimated = _signal_spectrum(t, y, dt, sigma)
    if estimated is None:  # an unknown spectrum is no licence to smooth (an empty one makes the widest win)
        n, p, c = cands[0]
        return SavgolChoice(n, p, sigma, float(sigma * np.sqrt((c**2).sum())))
    f, spectrum = estimated
    df = f[1] - f[0] if len(f) > 1 else 0.0
    ideal = (2j * np.pi * f) if deriv == 1 else np.ones(len(f))
    best = None
    for n, p, c in cands:
        lags = (np.arange(n) - n // 2) * dt
        response = np.exp(2j * np.pi * np.outer(f, lags)) @ c
        bias2 = float(np.sum(np.abs(response - ideal) ** 2 * spectrum) * df)
        err = float(np.sqrt(sigma**2 * float((c**2).sum()) + bias2))
        if best is None or err < best.error * (1.0 - 1e-9):
            best = SavgolChoice(n, p, sigma, err)
    return best


def sensor_targets(
    t: np.ndarray,
    accel_frd: np.ndarray,
    gyro_frd: np.ndarray,
    euler: np.ndarray,
    gravity: float = STANDARD_GRAVITY,
    settings: SensorTargetSettings | None = None,
    dt: float | None = None,
) -> SensorTargets:
    """Targets from specific force FRD (m/s^2), gyro FRD (rad/s) and attitude (ZYX rad) samples.

    ax..az: the specific force (Savitzky-Golay smoothed unless disabled) rotated to NED plus gravity;
    dwx..dwz: Savitzky-Golay derivative of the gyro; each axis's filter chosen per the settings. NaN where
    a window does not fit inside a contiguous run.
    """
    s = settings or SensorTargetSettings()
    dt = nominal_step(t) if dt is None else dt
    accel = np.asarray(accel_frd, dtype=float)
    gyro = np.asarray(gyro_frd, dtype=float)
    filters = []
    smoothed = np.empty_like(accel)
    dw = np.empty_like(gyro)
    for data, out, deriv in ((accel, smoothed, 0), (gyro, dw, 1)):
        for j in range(3):
            if deriv == 0 and not s.smooth_accel:
                choice = SavgolChoice(1, 0, run_noise_std(t, dt, data[:, j]), float("nan"))
            elif s.window_s is None:
                choice = choose_savgol(t, data[:, j], dt, deriv, s.max_window_s)
            else:
                choice = SavgolChoice(s.window_samples(dt), s.polyorder, run_noise_std(t, dt, data[:, j]),
                                      float("nan"))
            coeffs = (
                np.ones(1)
                if choice.window == 1
                else savgol_coeffs(choice.window, choice.polyorder, deriv=deriv, delta=dt, use="dot")
            )
            out[:, j] = per_run(t, dt, data[:, j], lambda run, c=coeffs: _savgol_1d(run, c))
            filters.append(choice)
    a_ned = specific_force_to_ned(smoothed, euler, gravity)
    return SensorTargets(np.concatenate((a_ned, dw), axis=1), tuple(filters))


def stream_derivative(
    t: np.ndarray, y: np.ndarray, window_s: float | None = None, polyorder: int = 2, max_window_s: float = 0.4
) -> np.ndarray:
    """d/dt (per s) of a stream y (N,k) sampled at possibly uneven times t (s), at those times.

    The stream is put on a uniform grid at its median spacing (runs split at gaps over 3 spacings),
    differentiated with Savitzky-Golay and interpolated back; NaN where no window fits. window_s None:
    each column's window and order chosen by choose_savgol; else that window (s) and polyorder.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    out = np.full(y.shape, np.nan)
    if len(t) < 5:
        return out
    dt = nominal_step(t)
    breaks = np.flatnonzero(np.diff(t) > 3.0 * dt) + 1
    edges = np.concatenate(([0], breaks, [len(t)]))
    pieces = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        if b - a < 5:
            continue
        grid = np.arange(int(np.floor((t[b - 1] - t[a]) / dt + 1e-9)) + 1) * dt + t[a]
        yg = np.stack([np.interp(grid, t[a:b], y[a:b, j]) for j in range(y.shape[1])], axis=1)
        pieces.append((a, b, grid, yg))
    if not pieces:
        return out
    all_t = np.concatenate([p[2] for p in pieces])
    all_y = np.concatenate([p[3] for p in pieces])
    for j in range(y.shape[1]):
        if window_s is None:
            choice = choose_savgol(all_t, all_y[:, j], dt, 1, max_window_s)
            n, order = choice.window, choice.polyorder
        else:
            n = SensorTargetSettings(window_s=window_s, polyorder=polyorder).window_samples(dt)
            order = polyorder
        coeffs = savgol_coeffs(n, order, deriv=1, delta=dt, use="dot")
        for a, b, grid, yg in pieces:
            d = _savgol_1d(yg[:, j], coeffs)
            # back at the stream's times, only between two grid points that both have a derivative: a
            # straight line across a hole (NaN samples, a window's edge) would be a made-up target
            k = np.clip(np.searchsorted(grid, t[a:b]), 1, len(grid) - 1)
            inside = np.isfinite(d[k - 1]) & np.isfinite(d[k]) & (t[a:b] >= grid[0]) & (t[a:b] <= grid[-1])
            out[a:b, j][inside] = np.interp(t[a:b][inside], grid, np.nan_to_num(d))
    return out
