"""Flight segmentation: airborne rows against hand-labelled windows, every drop reason counted, --window
by hand, several logs joined; and the alignment of topics at different rates by interpolation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bridge.errors import UserError
from identification.dataset import load_dataset, load_datasets
from identification.flight_evidence import NoFlightError
from identification.readers import Stream
from identification.segmentation import parse_window, segment
from identification.table import Dataset

REPO = Path(__file__).resolve().parent.parent
LOGS = REPO.parent / "shared" / "logs"
PX4 = LOGS / "px4_sitl_quad_takeoff.ulg"


def hop(land_detector_early: bool = False, impact_at: float | None = None) -> Dataset:
    """A synthetic hop at 50 Hz, hand-labelled: motors spin up at 2 s, lift-off at 3 s, 3 m up by 5 s, down
    again by 8 s (touch-down), motors off at 9 s, log ends at 10 s."""
    t = np.arange(0, 10, 0.02)
    z = np.where(t < 3, 0.0, np.where(t < 5, -1.5 * (1 - np.cos(np.pi * (t - 3) / 2)), 0.0))
    z = np.where((t >= 5) & (t < 8), -1.5 * (1 + np.cos(np.pi * (t - 5) / 3)), z)
    vz = np.gradient(z, t)
    xi = np.zeros((len(t), 12))
    xi[:, 2], xi[:, 5] = z, vz
    thr = np.where(t < 2, 0.0, np.where(t < 9, 0.5, 0.0))
    u = np.tile((900 * thr)[:, None], (1, 4))
    landed = np.where((t >= (2.2 if land_detector_early else 3.0)) & (t < 8.4), 0.0, 1.0)
    dev = np.full(len(t), 0.1)
    if impact_at is not None:
        dev[np.abs(t - impact_at) < 0.03] = 25.0
    aux = {"throttle": np.tile(thr[:, None], (1, 4)), "landed": landed, "accel_dev": dev}
    return Dataset(
        t=t,
        xi=xi,
        u=u,
        targets=np.zeros((len(t), 6)),
        source="hop",
        format="ulog",
        target_source="truth",
        aux=aux,
    )


def test_the_airborne_rows_of_a_hand_labelled_hop():
    ds = segment(hop(land_detector_early=True))
    assert ds.t[0] >= 3.0 and ds.t[-1] <= 8.0  # within lift-off..touch-down
    assert ds.t[0] < 3.7 and ds.t[-1] > 7.0  # and most of it (0.15 m up plus 0.3 s margins)
    # every dropped row has a reason, counted once; the early land detector shows in the cross-check
    assert ds.dropped_rows == sum(ds.drop_reasons.values()) == 500 - len(ds)
    assert ds.drop_reasons["below 0.15 m above the take-off point"] > 0
    text = "\n".join(ds.segments)
    assert "cross-check: the detectors disagree" in text and "land detector from 2.20 s" in text
    assert "kept" in text and "1 segment(s)" in text


def test_an_impact_splits_the_flight_and_short_pieces_go():
    ds = segment(hop(impact_at=5.5))
    assert not ((ds.t > 5.5 - 0.3) & (ds.t < 5.5 + 0.3)).any()
    assert ds.drop_reasons["ground contact on the accelerometer (impact)"] > 0
    assert "2 segment(s)" in "\n".join(ds.segments)


def test_windows_by_hand_replace_the_detectors_and_report_doubts():
    ds = segment(hop(), windows=[(1.0, 2.0), (4.0, 6.0)])
    assert ((ds.t >= 1.0) & (ds.t <= 2.0) | (ds.t >= 4.0) & (ds.t <= 6.0)).all()
    assert ds.drop_reasons["outside --window"] == 500 - len(ds)
    assert "cross-check: land detector calls 51 rows inside your windows ground rows (kept)" in "\n".join(
        ds.segments
    )
    assert parse_window("19.5:27") == (19.5, 27.0)
    for bad in ("19.5", "a:b", "5:3"):
        with pytest.raises(UserError, match="expected START:END"):
            parse_window(bad)


def test_interpolation_not_nearest_sample_aligns_slow_topics():
    # a 4 Hz ramp (as esc_status rpm) read on a 50 Hz timeline: linear interpolation is exact, the
    # nearest sample would be off by up to half a step of the ramp
    slow = Stream("esc", np.arange(0, 2.01, 0.25), 100.0 * np.arange(0, 2.01, 0.25))
    timeline = np.arange(0, 2.0, 0.02)
    values, ok = slow.resample(timeline)
    assert ok.all() and np.allclose(values[:, 0], 100.0 * timeline)
    # angles interpolate across the +-pi wrap the short way; quaternions too (q and -q are one attitude)
    ang = Stream("yaw", [0.0, 1.0], [np.pi - 0.1, -np.pi + 0.1], kind="angle")
    mid, _ = ang.resample(np.array([0.5]))
    assert abs(abs(mid[0, 0]) - np.pi) < 1e-9
    q = Stream("q", [0.0, 1.0], [[1, 0, 0, 0], [-np.cos(0.1), -np.sin(0.1), 0, 0]], kind="quaternion")
    qm, _ = q.resample(np.array([0.5]))
    assert np.allclose(np.abs(qm[0]), [np.cos(0.05), np.sin(0.05), 0, 0], atol=1e-3)
    # a gap longer than 4 median steps is not bridged
    gappy = Stream("g", [0, 1, 2, 3, 10, 11], [0, 1, 2, 3, 10, 11])
    _, ok = gappy.resample(np.array([2.5, 6.0]))
    assert ok.tolist() == [True, False]


@pytest.mark.skipif(not PX4.is_file(), reason=f"the shared logs are absent ({LOGS})")
def test_several_logs_and_windows_join_into_one_dataset(tmp_path):
    copy = tmp_path / "second.ulg"
    copy.write_bytes(PX4.read_bytes())
    ds = load_datasets([PX4, copy], windows=[(20.0, 21.0), (23.0, 24.0)])
    assert len(ds.flights) == 2 and ds.flight.tolist().count(0) == ds.flight.tolist().count(1)
    assert (((ds.t >= 20) & (ds.t <= 21)) | ((ds.t >= 23) & (ds.t <= 24))).all()
    assert 180 <= len(ds) <= 210  # 2 logs x 2 windows x 1 s at 50 Hz


@pytest.mark.skipif(not PX4.is_file(), reason=f"the shared logs are absent ({LOGS})")
@pytest.mark.parametrize("name", ["pyulog_sample_auavx21.ulg", "pyulog_appended_fmuv4pro.ulg"])
def test_old_px4_logs_without_a_flight_say_so(name):
    with pytest.raises(UserError, match="never armed in this log") as info:
        load_dataset(LOGS / name)
    assert "vehicle_local_position not valid" in str(info.value)


@pytest.mark.skipif(not PX4.is_file(), reason=f"the shared logs are absent ({LOGS})")
def test_an_old_px4_log_gives_rates_from_vehicle_attitude_and_motors_from_pwm(tmp_path):
    """The real v1.6-era log, its local position marked valid (it had no GPS): every stream is found."""
    from pyulog import ULog

    ulog = ULog(str(LOGS / "pyulog_appended_fmuv4pro.ulg"))
    for d in ulog.data_list:
        if d.name == "vehicle_local_position":
            for flag in ("xy_valid", "z_valid", "v_xy_valid", "v_z_valid"):
                d.data[flag][:] = 1
    path = tmp_path / "valid.ulg"
    ulog.write_ulog(str(path))
    ds = load_dataset(path, airborne=False)
    notes = "\n".join(ds.warnings)
    assert "body rates from vehicle_attitude rollspeed/pitchspeed/yawspeed" in notes
    assert "actuator_outputs (PWM us 1075-1950" in notes  # PWM_MIN/PWM_MAX of that era
    assert ds.u_from_throttle and (ds.aux["throttle"] == 0).all()  # disarmed: 900 us, below PWM_MIN
    assert (ds.aux["armed"] == 0).all() and np.median(np.diff(ds.t)) == pytest.approx(0.02)
    att = {d.name: d for d in ulog.data_list}["vehicle_attitude"].data
    assert np.abs(ds.xi[:, 9]).max() <= np.abs(att["rollspeed"]).max() + 1e-6
    # and the segmentation keeps nothing of a vehicle that never armed: a log with rows but no flight
    assert len(segment(ds)) == 0
    with pytest.raises(NoFlightError, match="never armed in this log"):
        load_dataset(path)
    assert len(load_dataset(path, windows=[(2.0, 6.0)])) > 100  # chosen by hand: the user's call
