"""Tracking metrics on constructed signals whose figures are known in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.metrics import (
    compute_metrics,
    metrics_from_csv,
    read_metrics_csv,
    settle_time,
    wrap_angle,
    write_metrics,
)

DT = 0.004


def _flight(error_of_t, duration=10.0, yaw=None):
    """Samples whose 3-D position error is error_of_t(t), split over x and z (3-4-5 triangle)."""
    t = np.arange(int(round(duration / DT)) + 1) * DT
    e = np.array([error_of_t(s) for s in t])
    desired = np.column_stack((np.sin(t), np.cos(t), -0.2 * t))
    actual = desired + np.column_stack((0.6 * e, np.zeros_like(e), -0.8 * e))
    yaw_d = np.zeros_like(t)
    return t, actual, desired, (yaw if yaw is not None else yaw_d), yaw_d


def test_rms_after_5s_and_overall_rms_of_a_two_level_error():
    t, p, pd, y, yd = _flight(lambda s: 0.3 if s < 5.0 else 0.02)
    m = compute_metrics(t, p, pd, y, yd, np.zeros(t.size, bool), np.full(t.size, 1e-4))
    assert m.rms_after_5s_m == pytest.approx(0.02, rel=1e-9)
    n_before = np.count_nonzero(t < 5.0)
    expected = math.sqrt((n_before * 0.09 + (t.size - n_before) * 0.0004) / t.size)
    assert m.rms_m == pytest.approx(expected, rel=1e-9)
    assert m.max_m == pytest.approx(0.3)
    assert m.final_m == pytest.approx(0.02)
    assert m.settle_time_s == pytest.approx(5.0)
    assert m.samples == t.size and m.duration_s == pytest.approx(10.0)


def test_settling_requires_staying_within_5_cm():
    # decays below 5 cm at 2 s, one excursion to 6 cm at 3.5 s, then within 5 cm for good
    def err(s):
        if abs(s - 3.5) < 1e-9:
            return 0.06
        return 1.0 if s < 2.0 else 0.01

    t, p, pd, y, yd = _flight(err)
    m = compute_metrics(t, p, pd, y, yd, np.zeros(t.size, bool), np.full(t.size, 1e-4))
    assert m.settle_time_s == pytest.approx(3.5 + DT)
    # exactly at the tolerance counts as within
    assert settle_time(np.array((0.0, 1.0, 2.0)), np.array((0.2, 0.05, 0.0))) == 1.0
    # out at the last sample: never settled
    assert settle_time(np.array((0.0, 1.0, 2.0)), np.array((0.0, 0.0, 0.07))) is None
    assert settle_time(np.array((0.0, 1.0)), np.array((0.01, 0.0))) == 0.0


def test_yaw_error_is_wrapped_and_motor_limits_and_step_times_counted():
    t, p, pd, _, yd = _flight(lambda s: 0.0, duration=1.0)
    yaw = np.full(t.size, math.pi - 0.05)
    yd = np.full(t.size, -math.pi + 0.05)  # 0.1 rad apart across the +-pi seam
    sat = np.zeros(t.size, bool)
    sat[: t.size // 4] = True
    steps = np.linspace(100e-6, 199e-6, t.size)
    m = compute_metrics(t, p, pd, yaw, yd, sat, steps, controller="se3", trajectory="case2")
    assert m.yaw_rms_rad == pytest.approx(0.1, abs=1e-9)
    assert m.yaw_max_rad == pytest.approx(0.1, abs=1e-9)
    assert m.motor_limit_share == pytest.approx((t.size // 4) / t.size)
    assert m.step_median_us == pytest.approx(149.5, abs=0.2)
    assert m.step_p99_us == pytest.approx(np.percentile(steps, 99) * 1e6)
    assert wrap_angle(3 * math.pi) == pytest.approx(-math.pi)


def test_short_flight_has_no_rms_after_5s_and_nan_position_is_not_completed():
    t, p, pd, y, yd = _flight(lambda s: 0.01, duration=2.0)
    m = compute_metrics(t, p, pd, y, yd, np.zeros(t.size, bool), np.full(t.size, 1e-4))
    assert m.rms_after_5s_m is None and m.completed
    p[-1, 0] = np.nan
    m = compute_metrics(t, p, pd, y, yd, np.zeros(t.size, bool), np.full(t.size, 1e-4))
    assert not m.completed and m.max_m == math.inf


def test_markdown_and_csv_writers(tmp_path):
    t, p, pd, y, yd = _flight(lambda s: 0.3 if s < 5.0 else 0.02)
    m = compute_metrics(t, p, pd, y, yd, np.zeros(t.size, bool), np.full(t.size, 1e-4), controller="pid",
                        trajectory="case1", tilt_rad=np.full(t.size, math.radians(10.0)))
    md, csv_path = write_metrics(m, tmp_path)
    text = md.read_text()
    assert "| RMS 3-D position error after 5 s | 0.02 | m |" in text
    assert "| time to settle within 5 cm (and stay) | 5 | s |" in text
    row = read_metrics_csv(csv_path)
    assert row["controller"] == "pid" and row["trajectory"] == "case1"
    assert float(row["rms_after_5s_m"]) == pytest.approx(0.02)
    assert float(row["max_tilt_deg"]) == pytest.approx(10.0)
    never = compute_metrics(t, p + 1.0, pd, y, yd, np.zeros(t.size, bool), np.full(t.size, 1e-4))
    md, csv_path = write_metrics(never, tmp_path)
    assert "never settled" in md.read_text()
    assert read_metrics_csv(csv_path)["settle_time_s"] == ""
    # read back whole (repr: a nan tilt compares equal), the unsettled time as None
    back = metrics_from_csv(csv_path)
    assert repr(back) == repr(never) and back.settle_time_s is None
    assert metrics_from_csv(write_metrics(m, tmp_path / "m")[1]) == m


def test_overshoot_along_the_first_approach_including_a_takeoff_phase():
    from controller.metrics import overshoot

    t = np.linspace(0.0, 10.0, 1001)
    # a take-off reference starting at the vehicle and climbing to 2 m; the vehicle overshoots by 7 cm
    ref = np.zeros((t.size, 3))
    ref[:, 2] = -2.0 * np.clip(t / 4.0, 0.0, 1.0)
    pos = ref.copy()
    pos[:, 2] -= 0.07 * np.exp(-((t - 5.0) ** 2))  # 7 cm above it around t = 5 s
    assert overshoot(pos, ref) == pytest.approx(0.07, rel=1e-3)
    # lagging behind (never past) is no overshoot; passing sideways is not along the approach
    assert overshoot(ref * 0.9, ref) == 0.0
    side = ref.copy()
    side[:, 0] += 0.5
    assert overshoot(side, ref) == pytest.approx(0.0, abs=1e-12)
    # a take-off from where an estimated state puts the vehicle, 7 cm off in x, then a 3 m step in x: the
    # direction is the climb (from the true start it leaned 37 deg toward -x and the step's lag counted)
    est = ref.copy()
    est[:, 0] = -0.06
    est[t >= 6.0, 0] = 3.0
    flown = est.copy()
    flown[t >= 6.0, 0] = 3.0 - 3.0 * np.exp(-(t[t >= 6.0] - 6.0) * 3.0)
    flown[:, 2] -= 0.02 * np.exp(-((t - 5.0) ** 2))
    flown[0] = 0.0
    assert overshoot(flown, est) == pytest.approx(0.02, rel=1e-2)
    # a reference starting 4.5 m away (Case II): past it along that direction
    ref2 = np.tile([2.0, 4.0, 0.0], (t.size, 1))
    share = np.minimum(t / 3.0, 1.0 + 0.02 * np.sin(np.pi * np.clip(t - 3.0, 0.0, 1.0)))  # 2 % past at 3.5 s
    pos2 = np.outer(share, [2.0, 4.0, 0.0])
    m = compute_metrics(t, pos2, ref2, np.zeros_like(t), np.zeros_like(t), np.zeros(t.size, bool),
                        np.full(t.size, 1e-4))
    assert m.overshoot_m == pytest.approx(0.02 * np.hypot(2.0, 4.0), rel=1e-3)
    assert m.max_after_5s_m == pytest.approx(0.0, abs=1e-12)


def test_a_step_without_truth_is_left_out_not_the_flights_truth(tmp_path):
    # One step whose truth frame did not arrive switched the whole flight's metrics to the estimator's own
    # state: a vehicle wandering 0.2 m whose estimate sat on the reference scored 0.
    import types

    from controller.companion import CSV_COLUMNS, Companion, FlightSettings, StepLog, _col

    def flown(lost_step: int):
        c = Companion.__new__(Companion)
        c.settings = FlightSettings(state="sensors", figures=False)
        c.controller, c.trajectory = types.SimpleNamespace(name="se3"), types.SimpleNamespace(name="hover")
        out = tmp_path / f"lost{lost_step}"
        out.mkdir()
        log = StepLog(out / "steps.csv")
        for k in range(2500):
            t = k * DT
            row = [math.nan] * len(CSV_COLUMNS)
            values = {"t": t, "ref_x": 0.0, "ref_y": 0.0, "ref_z": -1.0, "x": 0.0, "y": 0.0, "z": -1.0}
            zeros = ("phi", "theta", "psi", "true_phi", "true_theta", "true_psi", "ref_yaw", "saturated",
                     "control_us")
            values |= dict.fromkeys(zeros, 0.0)
            if k != lost_step:
                values |= {"true_x": 0.2 * math.sin(t), "true_y": 0.0, "true_z": -1.0}
            for name, v in values.items():
                row[_col(name)] = v
            log.add(row)
        log.close()
        return c._finish(log, out, {}, True, False)

    whole, lost = flown(-1), flown(1234)
    assert whole.rms_m == pytest.approx(0.138, abs=0.002)
    assert lost.rms_m == pytest.approx(whole.rms_m, rel=1e-3) and lost.samples == whole.samples - 1
