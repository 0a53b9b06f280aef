"""Truth targets that are exact under the SITL's zero-order hold: one row per step interval, not per sample.

For logs without the SITL's logged true accelerations (TRUE_ACC, since session 43: the .tlog reader takes
those instead, exact at each step's state); the derivation below is what such logs get.

Within one exchange step [t_k, t_k+1] the command is held, so the motion is smooth there and every kink (the
motor lag restarting toward a new command) sits on a sample. A difference over one step is then not an
approximation of anything: (v_k+1 - v_k) / dt is exactly the mean acceleration over the interval (NED m/s^2),
(w_k+1 - w_k) / dt the mean angular acceleration (FRD rad/s^2). Point derivatives at the samples cannot be
had to that accuracy once every sample is a kink (a controller that changes every command every step): the
stencils fall back to low order there (identification.targets.kink_aware_derivative).

So each interval becomes one row, at its midpoint t_k + dt/2, whose regressors give that mean:
- position: cubic Hermite midpoint (p_k + p_k+1)/2 + dt/8 (v_k - v_k+1) (m, NED); attitude: the normalised
  mean of the two quaternions (same hemisphere); velocity and body rates: the step means (the mean of the
  ends less the first moment of the acceleration over the step, and the velocity such that R_mid^T v is the
  step mean of the body velocity R^T v: _mean_body_velocity, _rate_moment);
- rotor speeds: the RMS over the interval of the first-order lag u(s) = c + (u_k - c) r^(s/dt) that the
  logged speeds follow under a held command c (c = (u_k+1 - r u_k) / (1 - r) per interval and rotor), so
  every thrust and moment term (u^2) has its exact interval mean; the lag ratio r = exp(-dt / Tm) is
  estimated from the log (motor_lag_ratio), not taken from a vehicle file.
The rotors' speeds change within a step (the lag), so the thrust and torques come early or late in it: their
first moments about the midpoint (lagged_square_moments) enter the force target (the body turns under a
thrust that changes: w x f_b' dt^2/12, which a height loop ties to the climb rate: 3.2e-5 * wb * (-wy, wx)
m/s^2 in fx, fy on a closed-loop flight of the paper vehicle, found as a spurious fy: wb*wx) and the step
means of velocity and rates. Measured against a dense replay of the SITL's own derivative over each step
(64 RK4 substeps from each logged state): fx, fy residual RMS 9.3e-5 -> 7.7e-6 m/s^2 (the float32 velocity's
level; 60 s, 14,988 rows of that flight), rate regressors 6.5e-4 -> 4.8e-5 rad/s RMS (4.3e-4 of w before,
fang-chen-aero's flight), body velocity 2e-6 m/s RMS after; on an in-process flight (tests) the body
velocity's largest error 1.9e-4 -> 4.5e-7 m/s (dw x v_b dt^2/12 the largest part) and the rates' 2.7e-3 ->
6.4e-5 rad/s.
The .tlog reader uses these rows for flights whose commands change at most steps; for held commands
(paper-train) point stencils are 4th order between the few kinks and stay (identification.readers.tlog).
Measured on 9 s closed-loop flights from the ground (quadsr excite --profile closed-loop, ideal sensors),
true model's lowest R^2 over the six targets: fang-chen-aero 0.99999410 (per-sample kink-aware stencils) ->
0.99999995, fang-chen-buaa 0.99998764 -> 0.99999997 (bench/step_targets.py).
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

from bridge.rotations import euler_from_quaternions, rotation_matrix

LAG_KNOTS = 64  # hat functions per rotor for the unknown throttle -> commanded-speed curve


def motor_lag_ratio(
    speeds: np.ndarray, throttles: np.ndarray, usable: np.ndarray
) -> float | None:
    """The motors' per-step lag ratio r = exp(-dt/Tm) from logged speeds (N,4) rad/s and held throttles (N,4).

    Under a held command c_k, u_k+1 = r u_k + (1 - r) c(throttle_k) for each rotor, with c an unknown
    monotone curve: r is the common coefficient of a least-squares fit with each rotor's curve written as
    LAG_KNOTS piecewise-linear hat functions of its throttle (saturated throttles 0 and 1 left out; three
    passes dropping residuals beyond 6 MADs). usable (N,): samples that may be used (both ends of a step).
    None when there are too few steps or r falls outside (0, 1) (no first-order lag to see).
    """
    u = np.asarray(speeds, dtype=float)
    thr = np.asarray(throttles, dtype=float)
    ok = np.asarray(usable, dtype=bool)
    finite = ok & np.isfinite(u).all(axis=1)
    pair = finite[:-1] & finite[1:] & np.isfinite(thr[:-1]).all(axis=1)
    cols, ys, rows_i, cols_j, vals = 1 + 4 * LAG_KNOTS, [], [], [], []
    row0 = 0
    for i in range(4):
        s = thr[:-1, i]
        k = np.flatnonzero(pair & (s > 1e-6) & (s < 1.0 - 1e-6))
        if len(k) < 4 * LAG_KNOTS:
            continue
        lo, hi = float(s[k].min()), float(s[k].max())
        x = (s[k] - lo) / max(hi - lo, 1e-12) * (LAG_KNOTS - 1)
        j = np.minimum(np.floor(x).astype(int), LAG_KNOTS - 2)
        w = x - j
        rows = row0 + np.arange(len(k))
        rows_i += [rows, rows, rows]
        cols_j += [np.zeros(len(k), int), 1 + i * LAG_KNOTS + j, 2 + i * LAG_KNOTS + j]
        vals += [u[k, i], 1.0 - w, w]
        ys.append(u[k + 1, i])
        row0 += len(k)
    if not ys:
        return None
    a = sparse.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows_i), np.concatenate(cols_j))), shape=(row0, cols)
    )
    y = np.concatenate(ys)
    scale = 1.0 / max(float(np.abs(y).mean()), 1e-12)  # the speed column to the hat functions' size
    a = a @ sparse.diags(np.r_[scale, np.ones(cols - 1)])
    keep = np.ones(len(y), dtype=bool)
    r = float("nan")
    for _ in range(3):  # normal equations (cols x cols, sparse rows): fast at any flight length
        ak = a[keep]
        try:
            sol, *_ = np.linalg.lstsq((ak.T @ ak).toarray(), ak.T @ y[keep], rcond=None)
        except np.linalg.LinAlgError:
            return None
        r = float(sol[0]) * scale
        res = y - a @ sol
        mad = 1.4826 * float(np.median(np.abs(res[keep])))
        keep = np.abs(res) <= 6.0 * mad + 1e-9
    return r if 0.0 < r < 1.0 else None


def lagged_rms_speed(u_start: np.ndarray, u_end: np.ndarray, ratio: float) -> np.ndarray:
    """RMS rotor speed (rad/s) over a step whose speed goes u_start -> u_end along a first-order lag.

    u(s) = c + d r^(s/dt), d = u_start - c, c = (u_end - r u_start) / (1 - r); the mean of u^2 over the step
    is c^2 + 2 c d m1 + d^2 m2 with m1 = (1 - r) / x, m2 = (1 - r^2) / (2 x), x = -ln r.
    """
    mean_sq, _ = lagged_square_moments(u_start, u_end, ratio)
    return np.sqrt(np.maximum(mean_sq, 0.0))


def _lag_path(u_start: np.ndarray, u_end: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray, float]:
    """(c, d, x): a step's lagged speed u(tau) = c + d exp(-x tau) (rad/s, tau in [0, 1]) from its ends
    u_start, u_end (rad/s) and the lag ratio r = exp(-x) per step: c the held command's speed."""
    r = float(ratio)
    c = (u_end - r * u_start) / (1.0 - r)
    return c, u_start - c, -np.log(r)


def lagged_square_moments(
    u_start: np.ndarray, u_end: np.ndarray, ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """(mean of u^2, mean of (tau - 1/2) u^2) over a step along the lag of lagged_rms_speed ((rad/s)^2).

    tau = s/dt in [0, 1] is the time within the step, so the second is the first moment of u^2 about the
    midpoint (in units of dt): how much of the squared speed, hence of the thrust, comes late in the step.
    With e(tau) = r^tau = exp(-x tau): u^2 = c^2 + 2 c d e + d^2 e^2, the mean of (tau - 1/2) e^(a tau) is
    _centred_moment(a) (zero for a constant), so the first moment is 2 c d J(x) + d^2 J(2x).
    """
    r = float(ratio)
    c, d, x = _lag_path(u_start, u_end, r)
    mean_sq = c * c + 2.0 * c * d * (1.0 - r) / x + d * d * (1.0 - r * r) / (2.0 * x)
    first = 2.0 * c * d * _centred_moment(x) + d * d * _centred_moment(2.0 * x)
    return mean_sq, first


def _centred_moment(a: float) -> float:
    """J(a) = integral over tau in [0, 1] of (tau - 1/2) exp(-a tau), a > 0 (-a/12 + a^2/24 for small a)."""
    if a < 1e-3:
        return -a / 12.0 + a * a / 24.0 - a**3 / 80.0
    e = -np.expm1(-a)  # 1 - exp(-a)
    return float((e - a * np.exp(-a)) / (a * a) - e / (2.0 * a))


def step_interval_rows(
    t: np.ndarray,
    position: np.ndarray,
    velocity: np.ndarray,
    quaternion: np.ndarray,
    rates: np.ndarray,
    speeds: np.ndarray,
    ratio: float,
    gravity: float | None = None,
    notes: list[str] | None = None,
    row_targets: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rows of the N-1 intervals between samples: (t_mid s, xi (N-1,12), u (N-1,4), targets (N-1,6)).

    Inputs per sample: t (s), position NED (m), velocity NED (m/s), quaternion (w, x, y, z) body FRD -> NED,
    body rates FRD (rad/s), rotor speeds (rad/s); ratio the motors' lag ratio per interval (motor_lag_ratio).
    Targets: ax ay az (NED m/s^2) and dwx dwy dwz (FRD rad/s^2), the exact means over each interval; with
    gravity (m/s^2) ax ay az are taken to the midpoint attitude (_midpoint_acceleration) and the targets
    from the step means to the rows' state where that is known (_at_row_state; what moved is appended to
    notes). row_targets False (rows for the caller's own targets, raw sensor ones): the targets are not
    taken to the rows' state; gravity still makes the rows' velocity the step mean of R^T v. The caller
    keeps only intervals of one step whose two ends are usable.
    """
    t = np.asarray(t, dtype=float)
    dt = np.diff(t)[:, None]
    p, v, w, u = (np.asarray(a, dtype=float) for a in (position, velocity, rates, speeds))
    q = np.asarray(quaternion, dtype=float)
    qa, qb = q[:-1], q[1:]
    qb = qb * np.where((qa * qb).sum(axis=1) < 0.0, -1.0, 1.0)[:, None]
    qm = qa + qb
    qm /= np.linalg.norm(qm, axis=1)[:, None]
    xi = np.concatenate(
        (
            0.5 * (p[:-1] + p[1:]) + dt / 8.0 * (v[:-1] - v[1:]),
            0.5 * (v[:-1] + v[1:]),
            euler_from_quaternions(qm),
            0.5 * (w[:-1] + w[1:]),
        ),
        axis=1,
    )
    a_mean = (v[1:] - v[:-1]) / dt
    a_mid = a_mean
    dw_mean = (w[1:] - w[:-1]) / dt
    mean_sq, first = lagged_square_moments(u[:-1], u[1:], ratio)
    v_b = sample_body_velocity(v, q)
    xi[:, 9:12] -= _rate_moment(dw_mean, (u, w, v_b), ratio, mean_sq, first, dt[:, 0])
    if gravity is not None:
        r = rotation_matrix(xi[:, 6], xi[:, 7], xi[:, 8])
        rough = np.einsum("nji,nj->ni", r, a_mean - np.array([0.0, 0.0, gravity]))  # f_b, to fit the map
        moment = _force_moment(rough, mean_sq, first, dt[:, 0])
        a_mid = _midpoint_acceleration(a_mean, r, xi[:, 9:12], dt[:, 0], gravity, dw_mean, moment)
        xi[:, 3:6] = _mean_body_velocity(xi[:, 3:6], a_mean, a_mid, r, xi[:, 9:12], dw_mean,
                                         moment, dt[:, 0], gravity)
    u_mid = np.sqrt(np.maximum(mean_sq, 0.0))
    if gravity is not None and row_targets:
        g_e3 = np.array([0.0, 0.0, gravity])
        f_b = np.einsum("nji,nj->ni", r, a_mid - g_e3)
        paths = _node_deviations(u[:-1], u[1:], u_mid, ratio, w[1:] - w[:-1], v_b[1:] - v_b[:-1])
        state = np.column_stack((u_mid, xi[:, 9:12], np.einsum("nji,nj->ni", r, xi[:, 3:6])))
        body, moved = _at_row_state(np.concatenate((f_b, dw_mean), axis=1), state, paths)
        if notes is not None:
            names = ("fx", "fy", "fz", "wx'", "wy'", "wz'")
            notes.append("truth targets taken from the step means to the rows' state (step_targets."
                         f"_at_row_state): {' '.join(names[j] for j in moved) or 'none'} (the other targets: "
                         "the two halves of the flight disagree on the shift)")
        a_mid = np.einsum("nij,nj->ni", r, body[:, :3]) + g_e3
        dw_mean = body[:, 3:]
    targets = np.concatenate((a_mid, dw_mean), axis=1)
    return 0.5 * (t[:-1] + t[1:]), xi, u_mid, targets


GAUSS_NODES = (0.5 - np.sqrt(3.0) / 6.0, 0.5 + np.sqrt(3.0) / 6.0)  # two-point Gauss-Legendre on [0, 1]


def _node_deviations(
    u_start: np.ndarray, u_end: np.ndarray, u_row: np.ndarray, ratio: float, dw: np.ndarray, dv_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The state's deviation from the row's (M,10 each: u1..u4 rad/s, w FRD rad/s, v_b FRD m/s) at the two
    Gauss nodes of each step: the rotors on their lag's closed form (lagged_square_moments), the rates and
    body velocity on the chord of their change over the step (dw, dv_b: end minus start) about the row's
    step means (their curvature about the mean is orthogonal to what a product with a chord picks up)."""
    r = float(ratio)
    c, d, _ = _lag_path(u_start, u_end, r)
    out = []
    for tau in GAUSS_NODES:
        du = c + d * r**tau - u_row
        out.append(np.concatenate((du, (tau - 0.5) * dw, (tau - 0.5) * dv_b), axis=1))
    return out[0], out[1]


def sample_body_velocity(velocity: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    """Body velocity R^T v (N,3 FRD m/s) at each sample from its NED velocity (N,3 m/s) and attitude
    quaternion (N,4: w, x, y, z, body FRD -> NED)."""
    ends = rotation_matrix(*euler_from_quaternions(np.asarray(quaternion, dtype=float)).T)
    return np.einsum("nji,nj->ni", ends, np.asarray(velocity, dtype=float))


def step_node_offsets(
    velocity: np.ndarray,
    quaternion: np.ndarray,
    rates: np.ndarray,
    speeds: np.ndarray,
    ratio: float,
    xi_rows: np.ndarray,
    u_rows: np.ndarray,
) -> np.ndarray:
    """(N-1, 2, 16): the state xi (12) and rotor speeds u (4) at the two Gauss nodes of each step, less the
    step row's (step_interval_rows' xi_rows, u_rows).

    Inputs per sample: velocity NED (m/s), quaternion (w, x, y, z) body FRD -> NED, body rates FRD (rad/s),
    rotor speeds (rad/s); ratio the motors' lag ratio per step. The rotors' two speeds have the lag's step
    mean and mean square (u_rows must be the RMS speeds); the rates and the body velocity lie on the chord
    of their change over the step about the row's (_node_deviations); position and attitude stay the row's
    (the body-frame physics does not read them within a step). A step-mean target is the mean of the
    physics over the step's path: the two-node mean of any term is that mean to the chord's accuracy, where
    the term at the row's state misses it by its curvature times the change within the step
    (identification.weak_form.node_groups).
    """
    v, w, u = (np.asarray(a, dtype=float) for a in (velocity, rates, speeds))
    v_b = sample_body_velocity(v, quaternion)
    r_row = rotation_matrix(xi_rows[:, 6], xi_rows[:, 7], xi_rows[:, 8])
    out = np.zeros((len(xi_rows), 2, 16))
    devs = _node_deviations(u[:-1], u[1:], u_rows, ratio, w[1:] - w[:-1], v_b[1:] - v_b[:-1])
    for k, dev in enumerate(devs):
        out[:, k, 3:6] = np.einsum("nij,nj->ni", r_row, dev[:, 7:10])
        out[:, k, 9:12] = dev[:, 4:7]
    # the rotors' nodes hold the lag's exact step mean of u and of u^2 (the thrust), the earlier node on the
    # start's side: two-point quadrature of the exponential would miss the thrust by up to 1.5e-5 of it
    r = float(ratio)
    c, d, x = _lag_path(u[:-1], u[1:], r)
    mean = c + d * (1.0 - r) / x
    spread = np.sqrt(np.maximum(np.asarray(u_rows, dtype=float) ** 2 - mean**2, 0.0)) * np.sign(d)
    out[:, 0, 12:16] = mean + spread - u_rows
    out[:, 1, 12:16] = mean - spread - u_rows
    return out


def body_state_nodes(offsets: np.ndarray, xi_rows: np.ndarray, u_rows: np.ndarray) -> np.ndarray:
    """(2, M, 10): z = (u1..u4 rad/s, w FRD rad/s, v_b FRD m/s) at each step's two Gauss nodes, from the rows
    (xi (M,12), u (M,4) rad/s) and step_node_offsets' offsets (M,2,16); v_b in the row's attitude."""
    r = rotation_matrix(xi_rows[:, 6], xi_rows[:, 7], xi_rows[:, 8])
    return np.stack([
        np.column_stack((u_rows + offsets[:, k, 12:16], xi_rows[:, 9:12] + offsets[:, k, 9:12],
                         np.einsum("nji,nj->ni", r, xi_rows[:, 3:6] + offsets[:, k, 3:6])))
        for k in range(2)
    ])


def sampled_step_means(
    samples: np.ndarray, state: np.ndarray, nodes: np.ndarray, usable: np.ndarray
) -> np.ndarray:
    """Step means (N-1,K) of a quantity measured at the steps' ends (samples (N,K), e.g. the accelerometer's
    FRD m/s^2) that is a smooth function of z = (u1..u4 rad/s, w FRD rad/s, v_b FRD m/s): the ends' average
    plus what a surrogate of it in z (_drag_basis, the t rule of _surrogate; fitted on the samples `usable`
    (N,) at their own z, state (N,10)) says the mean over each step's path (its two Gauss nodes, nodes
    (2,N-1,10): body_state_nodes) adds to that average.

    The ends' average (the trapezoid) misses the mean by the quantity's curvature over the step times dt^2/12:
    the thrust's through the rotors' lag (the nodes hold the lag's exact mean square), and in a tumble the
    body velocity's, which turns with the body (w x (w x v_b)), through the drag: measured on in-process
    tumbles against an exact replay (fang-chen-aero to 29 rad/s, fang-chen-buaa to 43), the accelerometer's
    step mean (the thrust's slope alone) 1e-3 .. 9e-3 m/s^2 RMS off, which the weak form reads as the drag's
    curvature. Drag is odd in the velocity and quadratic in the speed, which no polynomial in v_b follows
    across v = 0, so the surrogate also holds the two laws of a body in air, |v_i| v_i per axis and |v| v_i
    (_drag_basis): with them the error is the two nodes' own (fang-chen-aero 4e-5, 7e-5, 2e-4 m/s^2 RMS, fx fy
    fz; the quadratic alone 6e-4, 1.3e-3, 1.6e-3). The surrogate only carries the curvature within a step: the
    engines never see its columns."""
    y = np.asarray(samples, dtype=float)
    z = np.asarray(state, dtype=float)
    scale = _rms_scale(z)
    ends = _drag_basis(z / scale)
    along = 0.5 * (_drag_basis(nodes[0] / scale) + _drag_basis(nodes[1] / scale))
    shift = along - 0.5 * (ends[:-1] + ends[1:])
    out = 0.5 * (y[:-1] + y[1:])
    fit = np.where(usable, 1.0, np.nan)[:, None] * ends
    for j in range(y.shape[1]):
        b = _surrogate(fit, y[:, j])
        if b is not None:
            out[:, j] += np.nan_to_num(shift @ b)
    return out


def _rms_scale(z: np.ndarray) -> np.ndarray:
    """Each column's RMS over its finite values (1 where that is not positive): the surrogates' units."""
    scale = np.sqrt(np.nanmean(z**2, axis=0))
    scale[~(scale > 0.0)] = 1.0
    return scale


def _drag_basis(z: np.ndarray) -> np.ndarray:
    """_quadratic_basis of z (M,10: u1..u4, w, v_b) with the drag laws of v_b: |v_i| v_i and |v| v_i."""
    v = z[:, 7:10]
    return np.column_stack((_quadratic_basis(z), np.abs(v) * v, np.linalg.norm(v, axis=1)[:, None] * v))


def _quadratic_basis(z: np.ndarray) -> np.ndarray:
    """1, z_i and z_i z_j (i <= j) of z (M,10: u1..u4, w, v_b), except the products of two different rotors'
    speeds: the columns of a local quadratic surrogate. A rotor's thrust and torques are its own; under a
    controller the rotors move together, so u_i u_j columns would only share the thrust with u_i^2 and
    u_j^2 (whose shifts are nil: the rows hold the RMS speeds) and lend it their own shifts."""
    k = z.shape[1]
    products = [z[:, i] * z[:, j] for i in range(k) for j in range(i, k) if not (j < 4 and i != j)]
    return np.column_stack((np.ones(len(z)), z, *products))


def _at_row_state(
    y: np.ndarray, state: np.ndarray, paths: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, list[int]]:
    """Step-mean targets y (M,6: body specific force m/s^2, angular acceleration rad/s^2) taken to the
    row's state (M,10: u_i as their RMS over the step, w and v_b as their step means).

    A target's step mean is the mean of f over the state's path, not f at the row's state: a product of
    two quantities that change within the step (the rotors' gyroscopic u_i w_j, rotor drag u_i v_b) has the
    mean of the product, not the product of the means (and a u-linear term sees the RMS speed, not the
    mean). Measured on a closed-loop fang-chen-aero flight (every command changes every step), against a
    dense replay of each step: f at the row's state was 7.5e-4 rad/s^2 RMS off the step mean of wx'.
    The difference mean - f(row) is second order in the within-step changes and needs only the curvature
    of f: a quadratic surrogate P in (u, w, v_b) is fitted to the step means as the mean of P over the two
    Gauss nodes of each step (_surrogate), and each target moves by P(row) - mean(P at the nodes).
    A target moves only where that shift is known: surrogates fitted on the flight's first and second
    halves must agree on it (their shifts' RMS difference, about twice the full fit's error, under
    SHIFT_AGREEMENT of the shift's RMS), and the shift they share must be the full fit's (their mean's
    difference from it under the same fraction). Where a quadratic cannot hold the flight (open-loop paper
    flights: the rotors at a few common levels, speeds to 20 m/s) the step means stay: there the halves'
    t rule kept only the constant, and by the first test alone they agreed (on no shift) while the full
    fit's, from columns only the flight's start transient held, moved the first row's y'' of a tumbling
    paper-validate flight by 0.9 m/s^2 and wy' by 0.08 rad/s^2 RMS where the step means were 0.0026 off
    the SITL's accelerations at the rows (a shift applied regardless moved fang-chen-aero's az by 2.9e-3
    m/s^2 RMS, 1 - R^2 1e-9 -> 3.5e-7). Returns (targets, the indices of the targets that moved).
    """
    mean, shift = _surrogate_columns(state, paths)
    out = y.copy()
    moved = []
    first = np.arange(len(y)) < len(y) // 2
    ok = np.isfinite(shift).all(axis=1)
    for j in range(y.shape[1]):
        b = _surrogate(mean, y[:, j])
        halves = [_surrogate(mean, np.where(part, y[:, j], np.nan)) for part in (first, ~first)]
        if b is None or halves[0] is None or halves[1] is None:
            continue
        full = np.sqrt(np.mean((shift[ok] @ b) ** 2))
        apart = np.sqrt(np.mean((shift[ok] @ (halves[0] - halves[1])) ** 2))
        # Two halves that both keep only the constant agree (on no shift) whatever the full fit says: the
        # shift the halves share must also be the full fit's.
        off = np.sqrt(np.mean((shift[ok] @ (0.5 * (halves[0] + halves[1]) - b)) ** 2))
        if full > 0.0 and apart < SHIFT_AGREEMENT * full and off < SHIFT_AGREEMENT * full:
            out[:, j] = y[:, j] - shift @ b
            moved.append(j)
    return out, moved


SHIFT_AGREEMENT = 0.5  # the halves' surrogates must agree on a target's shift to this fraction of its RMS


def _surrogate_columns(
    state: np.ndarray, paths: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """(mean over the two Gauss nodes, that mean minus the value at the row) of _quadratic_basis, in the
    monomials of the physical quantities scaled by their RMS (not centred: u_i^2 is then the thrust's
    column, whose shift is nil as the rows hold the RMS speeds, and the t rule keeps or drops physical
    terms)."""
    scale = _rms_scale(state)
    basis = [_quadratic_basis((state + dev) / scale) for dev in paths]
    mean = 0.5 * (basis[0] + basis[1])
    return mean, mean - _quadratic_basis(state / scale)


SURROGATE_T = 5.0  # t ratio a surrogate's column needs to stay: a collinear column's coefficient is noise
SURROGATE_RIDGE = 1e-8  # ridge on the unit-RMS columns, per row: only for columns that are exactly collinear


def _surrogate(a: np.ndarray, y: np.ndarray) -> np.ndarray | None:
    """Coefficients (P,) of a surrogate of y (M,) on columns a (M,P), column 0 the constant: ridge-conditioned
    least squares (SURROGATE_RIDGE) in three passes dropping rows beyond 6 MADs (the ground's reaction),
    then refitted on the columns whose t ratio is at least SURROGATE_T. A held-command flight's rotors sit
    at a few common levels, so their u_i w_j columns are exactly collinear and plain least squares gave
    them coefficients of 1e6 whose shift moved the targets by 1e3 m/s^2; None with too few finite rows."""
    finite = np.isfinite(a).all(axis=1) & np.isfinite(y)
    cols = np.arange(a.shape[1])
    b = np.zeros(0)
    for attempt in range(2):
        keep = finite.copy()
        if keep.sum() < 4 * len(cols):
            return None
        x = a[:, cols]
        scale = np.sqrt(np.mean(x[keep] ** 2, axis=0))
        scale[scale == 0.0] = 1.0
        x = np.nan_to_num(x / scale)
        for _ in range(3):
            gram = x[keep].T @ x[keep] + SURROGATE_RIDGE * keep.sum() * np.eye(len(cols))
            b = np.linalg.solve(gram, x[keep].T @ y[keep])
            res = np.abs(np.nan_to_num(y - x @ b))
            mad = 1.4826 * np.median(res[keep])
            keep = finite & (res <= 6.0 * mad + 1e-12)
        dof = max(int(keep.sum()) - len(cols), 1)
        cov = np.linalg.pinv(x[keep].T @ x[keep]) * (res[keep] @ res[keep] / dof)
        t = np.abs(b) / np.sqrt(np.maximum(np.diag(cov), 1e-300))
        strong = (t >= SURROGATE_T) | (cols == 0)
        b = b / scale
        if attempt or strong.all():
            break
        cols = cols[strong]
    out = np.zeros(a.shape[1])
    out[cols] = b
    return out


def _midpoint_acceleration(
    a_mean: np.ndarray,
    r: np.ndarray,
    rates: np.ndarray,
    dt: np.ndarray,
    gravity: float,
    dw: np.ndarray | None = None,
    moment: np.ndarray | None = None,
) -> np.ndarray:
    """NED acceleration (M,3) m/s^2 at the step's midpoint attitude (r: body->NED matrices, (M,3,3)) from
    its mean over the step.

    The body turns during a step: with the specific force f_b held and the rates w (FRD rad/s) constant,
    the mean of R(t) f_b is R_mid (I + [w]x^2 dt^2/24) f_b, not R_mid f_b (6.7e-4 of the thrust at 30 rad/s,
    which the engines would fit with spurious |w| terms). With the rates changing at dw (FRD rad/s^2, the
    step's mean angular acceleration) the midpoint attitude (halfway between the ends' quaternions) is
    itself turned by [dw] dt^2/8 and the mean is R_mid (I + ([w]x^2 - 2 [dw]x) dt^2/24) f_b: without that,
    a per-motor PRBS (dw ~ 50 rad/s^2 under 10 m/s^2 of thrust) puts 3e-4 m/s^2 of the pitch torque into
    fx, which the engines fit as spurious signed rotor terms. With the specific force changing over the step
    (the rotors lagging toward a new command) the mean gains R_mid [w]x m1, m1 the first moment of f_b about
    the midpoint (moment, FRD m/s: _force_moment). So f_b = (that matrix)^-1 (R_mid^T (a - g e3) - w x m1).
    """
    g = np.array([0.0, 0.0, gravity])
    body = np.einsum("nji,nj->ni", r, a_mean - g)
    k = _cross_matrices(rates)
    m = k @ k if dw is None else k @ k - 2.0 * _cross_matrices(dw)
    m = np.eye(3)[None] + m * (dt**2 / 24.0)[:, None, None]
    if moment is not None:
        body = body - np.cross(rates, moment)
    body = np.linalg.solve(m, body[:, :, None])[:, :, 0]
    return np.einsum("nij,nj->ni", r, body) + g


def _rate_moment(
    dw: np.ndarray, ends: tuple[np.ndarray, np.ndarray, np.ndarray], ratio: float, mean_sq: np.ndarray,
    first: np.ndarray, dt: np.ndarray
) -> np.ndarray:
    """The first moment (M,3) rad/s of the angular acceleration about each step's midpoint: the mean of the
    ends' rates minus it is the step mean of the rates.

    The rates curve over a step: the torques follow the rotors' squared speeds, which lag toward a new
    command within every step, and the rates' own products (the inertia coupling), the rotors' gyroscopic
    torque and rotor drag move with the rates and the body velocity. dw (M,3, each step's mean angular
    acceleration) is written as a quadratic surrogate in the state z = (u_i, w, v_b) (_quadratic_basis, the
    t rule of _surrogate), fitted as its mean over each step's two Gauss nodes with z on its path (ends: u
    (N,4) rad/s, w (N,3) FRD rad/s, v_b (N,3) FRD m/s per sample; the rotors on their lag, w and v_b on the
    chord of the ends), and the moment is the surrogate's: (P(z2) - P(z1)) dt / (4 sqrt 3) by two-point
    Gauss quadrature of (s - dt/2) P, the rotors' squares' exactly (mean_sq, first:
    lagged_square_moments). Rates linear in w alone (the damping) missed the inertia coupling, which
    dominates in a tumbling open-loop flight: on a paper-train tumble at up to 17 rad/s (tests) the rows'
    rates were 3.1e-4 rad/s RMS off the step means (the ends' mean 6.5e-4), 3e-7 now; on a 60 s paper
    flight of fang-chen-buaa (to 34 rad/s) the gyro's differences (raw sensor targets) missed the true
    model's step means at the rows' Gauss nodes by 17 % of the realistic gyro's noise variance in the weak
    form (wy'), 2e-5 of it now.
    """
    u, w, v_b = ends
    r = float(ratio)
    c, d, _ = _lag_path(u[:-1], u[1:], r)
    nodes = [np.column_stack((c + d * r**tau, w[:-1] + tau * (w[1:] - w[:-1]),
                              v_b[:-1] + tau * (v_b[1:] - v_b[:-1]))) for tau in GAUSS_NODES]
    scale = _rms_scale(nodes[0])
    b1, b2 = (_quadratic_basis(z / scale) for z in nodes)
    mean = 0.5 * (b1 + b2)
    moment = (b2 - b1) / (4.0 * np.sqrt(3.0))
    for i, col in enumerate(_square_columns(nodes[0].shape[1])):  # the rotors' thrust: exact on the lag
        mean[:, col] = mean_sq[:, i] / scale[i] ** 2
        moment[:, col] = first[:, i] / scale[i] ** 2
    out = np.zeros_like(dw)
    for j in range(dw.shape[1]):
        b = _surrogate(mean, dw[:, j])
        if b is not None:
            out[:, j] = np.nan_to_num(moment @ b) * dt
    return out


def _square_columns(k: int) -> list[int]:
    """The columns of u1^2 .. u4^2 in _quadratic_basis of k quantities (u1..u4 first)."""
    pairs = [(i, j) for i in range(k) for j in range(i, k) if not (j < 4 and i != j)]
    return [1 + k + pairs.index((i, i)) for i in range(4)]


def _force_moment(f_b: np.ndarray, mean_sq: np.ndarray, first: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """The first moment (M,3) FRD m/s of the rotors' part of the specific force about each step's midpoint.

    The thrust follows the rotors' squared speeds, which lag toward a new command within every step: f_b
    (M,3, the steps' body specific force, m/s^2) is written as A [mean u_i^2] + c, fitted by least squares
    over the flight's steps (the thrust coefficients over the mass, tilted rotors included), and the
    moment is A [first moments of u_i^2] dt (lagged_square_moments). The rest of f_b (drag) changes over a
    step with the body velocity only, smoothly; taking the moment as f_b's times the rotors' relative one
    instead made open-loop flights (fast, high rates) worse: fang-chen-buaa paper-validate ax 1 - R^2
    5.5e-9 -> 9.3e-8.
    """
    a = _fit_on_rotors(f_b, mean_sq)
    if a is None:
        return np.zeros_like(f_b)
    return first @ a[:4] * dt[:, None]


def _fit_on_rotors(y: np.ndarray, mean_sq: np.ndarray, *extra: np.ndarray) -> np.ndarray | None:
    """Least-squares coefficients (4 + extra columns + 1, K) of y (M,K) on the steps' mean squared rotor
    speeds, the extra columns and a constant; three passes dropping rows beyond 6 MADs (the ground's
    reaction, touchdowns). None when there are too few finite rows."""
    return _robust_lstsq(np.column_stack((mean_sq, *extra, np.ones(len(mean_sq)))), y)


def _robust_lstsq(a: np.ndarray, y: np.ndarray) -> np.ndarray | None:
    """Least-squares coefficients (P, K) of y (M,K) on the columns a (M,P), three passes dropping rows
    beyond 6 MADs (the ground's reaction, touchdowns); None when there are too few finite rows."""
    keep = np.isfinite(a).all(axis=1) & np.isfinite(y).all(axis=1)
    if keep.sum() < 4 * a.shape[1]:
        return None
    scale = np.abs(a[keep]).max(axis=0)
    scale[scale == 0.0] = 1.0
    finite = keep.copy()
    b = np.zeros((a.shape[1], y.shape[1]))
    for _ in range(3):
        b, *_ = np.linalg.lstsq(a[keep] / scale, y[keep], rcond=None)
        res = np.abs(np.nan_to_num(y - (np.nan_to_num(a) / scale) @ b))
        mad = 1.4826 * np.median(res[keep], axis=0)
        keep = finite & (res <= 6.0 * mad + 1e-12).all(axis=1)
        if keep.sum() < 4 * a.shape[1]:
            return None
    return b / scale[:, None]


def _mean_body_velocity(
    v_ends: np.ndarray,
    a_mean: np.ndarray,
    a_mid: np.ndarray,
    r: np.ndarray,
    rates: np.ndarray,
    dw: np.ndarray,
    moment: np.ndarray,
    dt: np.ndarray,
    gravity: float,
) -> np.ndarray:
    """The row's NED velocity (M,3) m/s whose body-frame view R_mid^T v is the step mean of R^T v.

    Body-frame laws (drag, rotor drag) are linear or quadratic in v_b = R^T v, so the row must hold the
    interval mean of v_b. The mean of the ends' velocities v_ends misses it at second order in dt:
    - the velocity's own curvature: mean v = v_ends - the first moment of a about the midpoint, which is
      R_mid (m1 + w x f_b dt^2/12) with f_b the body specific force (m1 = moment, the rotors' part's first
      moment over the step, the one _midpoint_acceleration uses; and the body's turn under f_b);
    - the body's turn: with R(s) = R_mid exp([w s + dw (s^2/2 - dt^2/8)]x) about the quaternion midpoint,
      mean v_b = R_mid^T mean v - w x (R_mid^T a) dt^2/12 + dw x v_b dt^2/12 + w x (w x v_b) dt^2/24.
    The dw term is the largest: a motor PRBS (dw ~ 100 rad/s^2) at 1 m/s puts 1.3e-4 m/s into v_b, and a
    rotor drag of 0.34 m/s^2 per m/s made spurious wb*(u1^2 - u2^2 + u3^2 - u4^2) terms in fx of it.
    """
    f_b = np.einsum("nji,nj->ni", r, a_mid - np.array([0.0, 0.0, gravity]))
    h2 = (dt**2 / 12.0)[:, None]
    v_b = np.einsum("nji,nj->ni", r, v_ends) - moment - h2 * np.cross(rates, f_b)
    a_b = np.einsum("nji,nj->ni", r, a_mean)
    v_b = v_b + h2 * (np.cross(dw, v_b) - np.cross(rates, a_b) + 0.5 * np.cross(rates, np.cross(rates, v_b)))
    return np.einsum("nij,nj->ni", r, v_b)


def _cross_matrices(v: np.ndarray) -> np.ndarray:
    """[v]x (M,3,3) of vectors v (M,3): [v]x a = v x a."""
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    o = np.zeros_like(x)
    return np.stack((np.stack((o, -z, y), 1), np.stack((z, o, -x), 1), np.stack((-y, x, o), 1)), 1)
