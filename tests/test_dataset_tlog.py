"""Datasets from our .tlog: real SITL flights (a `quadsr sitl` process, real UDP) read back and checked
against the SITL's own dynamics along the same flight; damaged and incomplete logs give clear errors."""

from __future__ import annotations

import csv
import hashlib
import struct

import numpy as np
import pytest
from conftest import SitlProcess, altitude_sitl_args
from physics_targets import physics_targets, r2

from bridge.errors import UserError
from bridge.tlog import read_tlog
from identification.dataset import INPUT_NAMES, STATE_NAMES, TARGET_NAMES, Dataset, load_dataset
from identification.excite import fly
from identification.readers.tlog import read_tlog_dataset
from identification.segmentation import segment


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """A paper-train (3 s) and a paper-validate (2 s) flight of a noise-free SITL at 200 m, no ground."""
    d = tmp_path_factory.mktemp("tlog")
    sitl = SitlProcess(altitude_sitl_args(3))
    try:
        train = fly("paper-train", d / "train.tlog", hil=sitl.hil, duration=3.0, seed=5, progress=False)
        val = fly("paper-validate", d / "val.tlog", hil=sitl.hil, duration=2.0, progress=False)
    finally:
        sitl.stop()
    return {"train": train.out, "val": val.out, "dir": d}


@pytest.mark.parametrize("name", ["train", "val"])
def test_truth_targets_are_the_sitls_logged_accelerations(flights, name):
    """The SITL logs its true accelerations at each step's state (TRUE_ACC): the truth targets are those,
    one row per step, and equal the SITL's dynamics at the rows to single precision (measured: largest
    error 2.1e-6 m/s^2, 1.0e-5 rad/s^2; 1 - R^2 <= 6e-14)."""
    ds = load_dataset(flights[name], targets="truth")
    assert any("TRUE_ACC" in w for w in ds.warnings)
    assert np.allclose(np.diff(ds.t), 0.004)  # every step, none dropped for a stencil
    phys = physics_targets(ds)
    scale = np.abs(phys).max(axis=0)
    error = np.abs(ds.targets - phys).max(axis=0)
    assert (error <= 1e-6 * scale + 1e-6).all(), error
    assert (phys.std(0) > 0.3).all()  # the flight really moves every target


@pytest.mark.parametrize("name", ["train", "val"])
def test_truth_targets_derived_from_the_states_match_the_sitl_dynamics(flights, name):
    """A log without the SITL's accelerations (older logs; here the same log told to ignore them) gets its
    truth targets from the states: held commands (train) 7-point stencils on the rows clear of a command
    change (1 - R^2 <= 2.4e-9 measured; the same flight as step means: 1.5e-6 on dwx); sinusoids (val)
    step means."""
    ds = segment(read_tlog_dataset(flights[name], targets="truth", logged_accelerations=False))
    assert not any("TRUE_ACC" in w for w in ds.warnings)
    fit = r2(ds.targets, physics_targets(ds))
    floor = 1 - 1e-7 if name == "train" else 0.9999
    assert (fit > floor).all(), dict(zip(TARGET_NAMES, (1 - fit).round(12), strict=True))


def test_sensor_targets_match_the_sitl_dynamics(flights):
    ds = load_dataset(flights["train"], targets="sensors")
    assert ds.target_source == "sensors"
    fit = r2(ds.targets, physics_targets(ds))
    assert (fit > 0.999).all(), dict(zip(TARGET_NAMES, fit.round(6), strict=True))


def test_raw_sensor_targets_of_the_weak_form_are_step_intervals(flights):
    """The weak form's raw sensor targets (RAW_SENSOR_TARGETS) of our .tlog: one step per 4 ms step at its
    midpoint, the gyro's difference over the step (its exact mean derivative there). Integrated against the
    test functions they hold the SITL's dynamics at the rows several times better than the per-sample
    5-point derivative, whose stencil spans the kinks a held command's change leaves at a sample (measured
    on fang-chen-aero's 60 s paper-train flight, true model, weak RMS of wy': 3.5e-2 -> 6.9e-3 rad/s^2;
    here 3.5e-2 -> 8.5e-3 on wx'), and each step as two rows, its Gauss nodes, far better again (here
    1.6e-4). The specific force, no derivative, is its samples' mean over the step plus the rotors' lag
    within it (here 3.9e-4 m/s^2 at most; the ends' average alone 1.7e-3)."""
    from dataclasses import replace

    from identification.weak_form import RAW_SENSOR_TARGETS, WeakSettings, weak_rows
    from identification.weak_noise import STEP_DIFFERENCE, STEP_MEAN

    g = 9.8  # fang-chen-buaa's
    intervals = load_dataset(flights["train"], targets="sensors", gravity=g,
                             sensor_settings=RAW_SENSOR_TARGETS)
    samples = load_dataset(flights["train"], targets="sensors", gravity=g,
                           sensor_settings=replace(RAW_SENSOR_TARGETS, step_intervals=False))
    assert np.allclose(np.round(intervals.t / 0.004 % 1.0, 6), 0.5)  # step midpoints
    assert np.allclose(np.round(samples.t / 0.004 % 1.0, 6) % 1.0, 0.0)
    assert len(intervals) > 600
    # neighbouring step rows share an IMU sample: the log states that noise (the generalised refit's)
    assert intervals.target_noise == (STEP_MEAN,) * 3 + (STEP_DIFFERENCE,) * 3
    assert samples.target_noise is None
    assert intervals.select(slice(0, 10)).target_noise == intervals.target_noise

    def weak_error(ds: Dataset) -> np.ndarray:
        V = weak_rows(ds.t, ds.flight, WeakSettings())
        return np.sqrt(np.mean((V @ (ds.targets - physics_targets(ds))) ** 2, axis=0))

    ours, before = weak_error(intervals), weak_error(samples)
    print("step intervals", ours, "samples", before)
    assert (ours[3:] < before[3:] / 3.0).all(), (ours, before)
    assert (ours[:3] < 1e-3).all(), ours
    # each step is two rows at one time, its Gauss nodes (Dataset.at_step_nodes), whose mean is the step's:
    # the physics at the steps' own rows (their mean state) misses the step means by the products' curvature
    rows = segment(read_tlog_dataset(flights["train"], targets="sensors", gravity=g,
                                     sensor_settings=RAW_SENSOR_TARGETS))
    assert intervals.nodes == 2 and rows.nodes == 1 and len(intervals) == 2 * len(rows)
    assert np.array_equal(intervals.t, np.repeat(rows.t, 2))
    for fraction in (0.2, 0.25, 0.3):  # a held-out block never takes one node of a step and not the other
        train, hold = intervals.split(fraction)
        assert train.t.max() < hold.t.min() and len(train) % 2 == 0 and len(hold) % 2 == 0, fraction
    # also where the cut falls at the flight's first time (3 steps, 90 % held): that step's rows stay in train
    train, hold = intervals.select(slice(0, 6)).split(0.9)
    assert len(train) == 2 and len(hold) == 4 and train.t.max() < hold.t.min(), (train.t, hold.t)
    # the two rotor speeds hold the step's mean square, so the thrust, as the row's RMS speed does
    assert np.allclose((intervals.u**2).reshape(-1, 2, 4).mean(axis=1), rows.u**2, rtol=1e-9, atol=1e-6)
    at_rows = weak_error(rows)
    print("node rows", ours, "step rows", at_rows)
    # measured: wx' 8.5e-3 -> 1.6e-4, wy' 4.0e-3 -> 1.6e-4 rad/s^2 (wz' 1.9e-5 -> 1.3e-5: the rotors' u^2)
    assert (ours[3:5] < at_rows[3:5] / 10.0).all() and ours[5] <= at_rows[5], (ours, at_rows)


def test_rows_columns_and_provenance(flights):
    path = flights["train"]
    logged = load_dataset(path)
    assert logged.format == "tlog" and logged.target_source == "truth" and logged.source == str(path)
    assert logged.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    # the SITL's logged accelerations: one row per step, the time-0 step included (750 steps + 1)
    assert np.allclose(logged.t, np.round(np.arange(751) * 0.004, 6)) and logged.dropped_rows == 0
    ds = segment(read_tlog_dataset(path, logged_accelerations=False))
    # 750 steps + the time-0 step; held commands: point derivatives on the 7-point stencil, so a row is kept
    # only when no command changes strictly inside its span (the motor lag restarts there) and the stencil
    # fits in the flight (2 rows lost at each end, where the 5-point one is used); the changes counted from
    # the log's own commands
    commands = {round(m.time_usec * 1e-6, 6): tuple(m.controls[:4]) for _, m in read_tlog(path)
                if m.get_type() == "HIL_ACTUATOR_CONTROLS"}
    steps = np.round(np.arange(751) * 0.004, 6)
    held = [commands.get(s) for s in steps]  # the last step has no reply: unknown counts as a change
    changed = np.array([False] + [a is None or a != b for a, b in zip(held[:-1], held[1:], strict=True)])
    clear = np.array([2 <= i <= 748 and not changed[i - 2 : i + 3].any() for i in range(751)])
    assert 100 < clear.sum() < 751 - 4  # the flight has both kinds of rows
    assert np.allclose(ds.t, steps[clear])
    assert ds.dropped_rows == 751 - clear.sum() and sum(ds.drop_reasons.values()) == ds.dropped_rows
    assert any("command change" in k for k in ds.drop_reasons)
    assert any("commands held" in w for w in ds.warnings)
    # paper-validate's sinusoids change every command every step: one row per step interval, at its midpoint
    val = segment(read_tlog_dataset(flights["val"], logged_accelerations=False))
    steps = (val.t - 0.002) / 0.004
    assert len(val) >= 500 - 1 and np.allclose(steps, np.round(steps))  # rows at the steps' midpoints
    assert any("exact mean accelerations over each 4 ms step" in w for w in val.warnings)
    assert ds.xi.shape == (len(ds), len(STATE_NAMES)) and ds.u.shape == (len(ds), len(INPUT_NAMES))
    assert np.isfinite(ds.xi).all() and np.isfinite(ds.u).all() and np.isfinite(ds.targets).all()
    # Euler angles in rad within their ranges; rotor speeds in rad/s within the paper's 0..1000
    assert np.abs(ds.xi[:, 6:9]).max() <= np.pi + 1e-9 and np.abs(ds.xi[:, 7]).max() <= np.pi / 2 + 1e-9
    assert ds.u.min() >= 0.0 and ds.u.max() <= 1006.7
    # every motor got its own random speeds (f1..f4 not collinear)
    assert np.linalg.matrix_rank(np.column_stack([ds.u[:, i] ** 2 for i in range(4)]), tol=1.0) == 4


def test_decimation_to_a_lower_rate(flights):
    ds = load_dataset(flights["val"], rate_hz=50)
    assert np.allclose(np.diff(ds.t), 0.02)
    with pytest.raises(UserError, match="does not divide"):
        load_dataset(flights["val"], rate_hz=60)


def test_concat_split_and_csv(flights, tmp_path):
    a, b = load_dataset(flights["train"]), load_dataset(flights["val"])
    both = Dataset.concat([a, b])
    assert len(both) == len(a) + len(b)
    assert [f.file for f in both.flights] == [str(flights["train"]), str(flights["val"])]
    assert set(np.unique(both.flight)) == {0, 1}
    train, hold = both.split(0.25)
    assert len(train) + len(hold) == len(both)
    for i, d in enumerate((a, b)):
        tr_t, ho_t = train.t[train.flight == i], hold.t[hold.flight == i]
        assert abs(len(ho_t) - 0.25 * len(d)) <= 1
        assert tr_t.max() < ho_t.min()  # time-contiguous: the holdout is each flight's last quarter
    path = both.to_csv(tmp_path / "rows.csv")
    with path.open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["flight", "t", *STATE_NAMES, *INPUT_NAMES, *TARGET_NAMES]
    assert len(rows) == len(both) + 1
    assert np.allclose(
        [float(v) for v in rows[5][1:]],
        np.concatenate(([both.t[4]], both.xi[4], both.u[4], both.targets[4])),
        rtol=1e-8,
    )
    with pytest.raises(UserError, match="between 0 and 1"):
        both.split(1.0)


def _mid_flight_cut(data: bytes) -> int:
    """A byte offset 13 bytes into the record after the HIL_SENSOR of the log's middle step: a cut there
    leaves a partial last record. (A fixed offset such as half the file landed on a record boundary in some
    runs, leaving nothing truncated, and held fewer steps when the SITL had resent its time-0 datagram more
    often while waiting for its client: both vary with the wall clock.)"""
    sensors, i = {}, 0
    while i < len(data):
        end = i + 8 + 12 + data[i + 9] + (13 if data[i + 10] & 0x01 else 0)  # 8-byte time, MAVLink 2 frame
        if int.from_bytes(data[i + 15 : i + 18], "little") == 107:  # HIL_SENSOR: its time_usec, its end
            sensors[int.from_bytes(data[i + 18 : i + 26], "little")] = end
        i = end
    times = sorted(sensors)
    return sensors[times[len(times) // 2]] + 13


def test_truncated_log_yields_what_it_holds_with_a_warning(flights, tmp_path):
    data = flights["val"].read_bytes()
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[: _mid_flight_cut(data)])
    ds = load_dataset(cut)
    full = load_dataset(flights["val"])
    assert 0.4 * len(full) < len(ds) < 0.6 * len(full), (len(ds), len(full), ds.drop_reasons)
    assert any("truncated" in w for w in ds.warnings)


def test_empty_garbage_and_missing_files_are_clear_errors(tmp_path):
    empty = tmp_path / "empty.tlog"
    empty.write_bytes(b"")
    with pytest.raises(UserError, match=r"empty\.tlog is empty"):
        load_dataset(empty)
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(
        np.random.default_rng(0)
        .integers(0, 256, 4000, dtype=np.uint8)
        .tobytes()
        .replace(b"\xfd", b"\x00")
        .replace(b"\xfe", b"\x00")
    )
    with pytest.raises(UserError, match=r"junk\.tlog is not a MAVLink \.tlog"):
        load_dataset(junk)
    with pytest.raises(UserError, match="does not exist"):
        load_dataset(tmp_path / "nope.tlog")


def _filtered_copy(src, dst, drop: set[str]) -> None:
    """Rewrite a tlog without the frames of the given message types (real bytes, same stamps)."""
    out = bytearray()
    for t, msg in read_tlog(src):
        if msg.get_type() not in drop:
            out += struct.pack(">Q", int(round(t * 1e6))) + bytes(msg.get_msgbuf())
    dst.write_bytes(bytes(out))


def test_missing_messages_are_named(flights, tmp_path):
    no_lpn = tmp_path / "no_lpn.tlog"
    _filtered_copy(flights["val"], no_lpn, {"LOCAL_POSITION_NED"})
    with pytest.raises(UserError, match="no_lpn.tlog has no LOCAL_POSITION_NED"):
        load_dataset(no_lpn)
    only_commands = tmp_path / "commands.tlog"
    _filtered_copy(
        flights["val"],
        only_commands,
        {"HIL_SENSOR", "HIL_STATE_QUATERNION", "LOCAL_POSITION_NED", "RAW_RPM", "HIL_GPS"},
    )
    with pytest.raises(UserError, match="has no HIL_SENSOR"):
        load_dataset(only_commands)
    no_rpm = tmp_path / "no_rpm.tlog"
    _filtered_copy(flights["train"], no_rpm, {"RAW_RPM"})
    with pytest.raises(UserError, match="no rotor speeds") as info:
        load_dataset(no_rpm)
    assert "--motor-curve" in str(info.value)


def test_rotor_speeds_from_commands_through_the_motor_curve(flights, tmp_path):
    no_rpm = tmp_path / "no_rpm.tlog"
    _filtered_copy(flights["train"], no_rpm, {"RAW_RPM"})
    ds = load_dataset(no_rpm, motor_curve="fang-chen-buaa")
    ref = load_dataset(flights["train"])
    common, ia, ib = np.intersect1d(ds.t, ref.t, return_indices=True)
    assert len(common) > 0.9 * len(ref)
    # the same first-order motor lag as the SITL: speeds agree to a fraction of a rad/s
    assert np.abs(ds.u[ia] - ref.u[ib]).max() < 0.5
    assert "motor lag settling after the start" in ds.drop_reasons
    assert any("HIL_ACTUATOR_CONTROLS" in w for w in ds.warnings)
