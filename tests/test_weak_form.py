"""The weak (integral) form (identification.weak_form): its test-function matrix, and on a flight of the
SITL's physics (in-process, 12 s of held random rotor commands) with a noisy 250 Hz gyro, the weak targets
agree with the true model where point derivatives of the gyro do not; `identify(weak=...)` learns wz'."""

from __future__ import annotations

import numpy as np
import pytest

from bridge.errors import UserError
from bridge.vehicle import load_vehicle
from identification.identify import identify
from identification.metrics import r2
from identification.table import Dataset
from identification.targets import sensor_targets
from identification.true_model import true_model
from identification.weak_form import RAW_SENSOR_TARGETS, WeakSettings, weak_operator, weak_rows
from sitl.dynamics import Quadrotor

DT = 0.004
GYRO_NOISE = 0.01  # rad/s per sample at 250 Hz: the realistic preset's order


def test_operator_rows_are_weighted_means_inside_runs():
    t = np.concatenate((np.arange(300) * DT, 2.0 + np.arange(40) * DT, 5.0 + np.arange(500) * DT))
    v = weak_operator(t, WeakSettings(half_window_s=0.2, stride_s=0.02))
    assert np.allclose(v.sum(axis=1), 1.0)
    dense = v.toarray()
    for row in dense:  # a window lies inside one run: never across the gaps at rows 300 and 340
        cols = np.flatnonzero(row)
        assert np.all(np.diff(t[cols]) < 1.5 * DT) and len(cols) == 101
    assert not dense[:, 300:340].any()  # the 40-sample run is shorter than one window
    # two flights with the same clock: no window mixes them
    both = weak_rows(np.concatenate((t[:300], t[:300])), np.repeat([0, 1], 300), WeakSettings())
    mixed = [(r[:300].any() and r[300:].any()) for r in both.toarray()]
    assert both.shape[0] > 0 and not any(mixed)
    with pytest.raises(UserError, match="half window"):
        weak_operator(t, WeakSettings(half_window_s=-1.0))


def test_rows_sharing_a_time_are_one_samples_nodes():
    """Two rows per step (Dataset.at_step_nodes: the step's Gauss nodes, one time): each window weighs the
    step as it weighs one sample and shares that weight between its nodes, so V y of a target held on both
    nodes is the steps' and V f of a quantity that differs between them is the steps' node means'."""
    rng = np.random.default_rng(8)
    t = np.concatenate((np.arange(400) * DT, 3.0 + np.arange(300) * DT))
    steps = weak_operator(t, WeakSettings())
    nodes = weak_operator(np.repeat(t, 2), WeakSettings())
    assert nodes.shape == (steps.shape[0], 2 * len(t)) and np.allclose(nodes.sum(axis=1), 1.0)
    y = rng.normal(size=len(t))
    assert np.allclose(nodes @ np.repeat(y, 2), steps @ y)
    a, b = rng.normal(size=len(t)), rng.normal(size=len(t))
    assert np.allclose(nodes @ np.column_stack((a, b)).ravel(), steps @ (0.5 * (a + b)))
    # per flight, as weak_rows builds it
    both = weak_rows(np.repeat(np.r_[t[:400], t[:400]], 2), np.repeat([0, 1], 800), WeakSettings())
    half = steps[: both.shape[0] // 2] @ y
    assert np.allclose(both @ np.repeat(np.r_[y[:400], y[:400]], 2), np.tile(half, 2))


@pytest.fixture(scope="module")
def noisy_flight() -> tuple[Dataset, np.ndarray]:
    """(sensor-target Dataset with a noisy gyro, the true model's targets at its rows)."""
    vehicle = load_vehicle("fang-chen-buaa")
    quad = Quadrotor(vehicle)
    hover = vehicle.motor_curve.throttle_for_speed(550.0)
    quad.reset(position=(0.0, 0.0, -200.0), rotor_speeds=[550.0] * 4)
    rng = np.random.default_rng(4)
    n = 3000
    xi, u, thr = np.empty((n, 12)), np.empty((n, 4)), np.full(4, hover)
    for k in range(n):
        xi[k] = (*quad.position, *quad.velocity, *quad.euler, *quad.rates)
        u[k] = quad.rotor_speeds
        if k % 50 == 0:  # a new held command every 0.2 s, as paper-train's random speeds
            thr = np.clip(hover + 0.08 * rng.standard_normal(4), 0.0, 1.0)
        quad.step(thr)
    exact = true_model(vehicle).accelerations(xi, u)
    t = np.arange(n) * DT
    gyro = xi[:, 9:12] + GYRO_NOISE * rng.standard_normal((n, 3))
    from bridge.rotations import rotation_matrix

    r = rotation_matrix(xi[:, 6], xi[:, 7], xi[:, 8])
    accel = np.einsum("nji,nj->ni", r, exact[:, :3] - [0.0, 0.0, vehicle.gravity])  # specific force FRD
    st = sensor_targets(t, accel, gyro, xi[:, 6:9], vehicle.gravity, settings=RAW_SENSOR_TARGETS, dt=DT)
    ok = np.isfinite(st.values).all(axis=1)
    ds = Dataset(t=t[ok], xi=xi[ok], u=u[ok], targets=st.values[ok], source="sim", format="synthetic",
                 target_source="sensors")
    return ds, exact[ok]


def test_weak_targets_do_not_amplify_gyro_noise(noisy_flight):
    ds, exact = noisy_flight
    v = weak_operator(ds.t)
    point = r2(exact[:, 5], ds.targets[:, 5])
    weak = r2(v @ exact[:, 5], v @ ds.targets[:, 5])
    assert point < 0.9 and weak > 0.999, (point, weak)


def test_identify_in_the_weak_form_learns_yaw_acceleration(noisy_flight):
    ds, exact = noisy_flight
    model = identify(ds, targets=("dwz",), budget=1, seed=0, weak=WeakSettings(), progress=False)
    assert model.engine["weak_form"]["half_window_s"] == 0.2
    record = model.extra["identifiability"]["targets"]["dwz"]
    assert "standard_errors" not in record  # no noise stated
    assert record["pick_t_ratios"] == "from the residual's effective sample size"
    assert model.targets["dwz"].metrics["validation"]["r2"] > 0.995
    pred = model.evaluate(ds.xi, ds.u)[:, 0]
    assert r2(exact[:, 5], pred) > 0.995  # the learned point model, against the truth at every row
    with pytest.raises(UserError, match="default"):
        identify(ds, targets=("dwz",), engine="sparse", budget=1, weak=WeakSettings(), progress=False)


def test_cli_refuses_a_bad_window_and_another_engine(tmp_path, capsys):
    from quadsr.cli import main

    log = tmp_path / "any.tlog"
    log.write_bytes(b"")  # never read: the options are refused first
    assert main(["identify", str(log), "-o", str(tmp_path / "m.yaml"), "--weak-window", "-1"]) == 2
    assert "half window" in capsys.readouterr().err
    assert main(["identify", str(log), "-o", str(tmp_path / "m.yaml"), "--weak", "--engine", "sparse"]) == 2
    assert "default (discovery) engine" in capsys.readouterr().err


def test_validate_reports_table_one_in_the_weak_form(noisy_flight, tmp_path):
    from identification.validate import validate

    ds, _ = noisy_flight
    truth = true_model("fang-chen-buaa")
    point = validate(truth, ds, tmp_path / "point").metrics["dwz"]
    weak = validate(truth, ds, tmp_path / "weak", weak=WeakSettings()).metrics["dwz"]
    assert point["r2"] < 0.9 and weak["r2"] > 0.999, (point, weak)
    assert weak["rows"] == weak_operator(ds.t).shape[0] < len(ds)


def test_identify_refits_by_generalised_least_squares_and_reports_standard_errors(noisy_flight, capsys):
    """A dataset that states its targets' raw noise (here the gyro's 5-point quadratic derivative of white
    noise) gets its chosen terms refit on whitened weak rows (identification.weak_noise): the model file
    holds each term's standard error, and a term above the stated fraction of its value is named."""
    from dataclasses import replace

    from identification.engine_settings import EngineSettings

    ds, exact = noisy_flight
    quadratic5 = (-0.2, -0.1, 0.0, 0.1, 0.2)  # d/dt of a quadratic through 5 samples, times dt
    stated = replace(ds, target_noise=(None,) * 3 + (quadratic5,) * 3)
    strict = EngineSettings()
    strict = replace(strict, selection=replace(strict.selection, report_relative_se=1e-9))
    model = identify(stated, targets=("dwz",), budget=1, seed=0, weak=WeakSettings(), progress=False,
                     settings=strict)
    errors = model.extra["identifiability"]["targets"]["dwz"]["standard_errors"]
    assert errors and all(0 < e["standard_error"] < abs(e["coefficient"]) for e in errors.values())
    refit = model.extra["identifiability"]["targets"]["dwz"]["refit"]
    assert refit["method"] == "generalised least squares" and refit["p_value"] >= refit["level"]
    assert model.extra["identifiability"]["targets"]["dwz"]["pick_t_ratios"] == (
        "under the log's stated noise of the weak rows")
    assert "standard error above" in capsys.readouterr().err
    assert model.targets["dwz"].metrics["validation"]["r2"] > 0.995
