"""Where the held-out blocks go (identification.data_roles): the tail of a flight when every target varies
there, else where they vary, never fitting on held-out rows; and logs that hold no flight say so
(identification.flight_evidence)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from synthetic_data import synthetic_dataset

from bridge.errors import UserError
from identification.data_roles import DEFAULT_GAP_S, MIN_SPREAD_RATIO, assign_roles, time_block_masks
from identification.dataset import Dataset, load_dataset
from identification.flight_evidence import NoFlightError, no_flight_evidence
from identification.identify import identify
from identification.model_file import load_model, save_model
from quadsr.cli import main

REPO = Path(__file__).resolve().parent.parent
LOGS = REPO.parent / "shared" / "logs"
TAKEOFF = LOGS / "px4_sitl_quad_takeoff.ulg"


def _steady_tail(n: int = 3000, seed: int = 11, steady_from: float = 0.55) -> Dataset:
    """A synthetic flight (250 Hz) whose targets are constant plus 1% noise after steady_from of its time."""
    d = synthetic_dataset(n, seed)
    y = d.targets.copy()
    rng = np.random.default_rng(seed)
    late = d.t >= d.t[0] + steady_from * (d.t[-1] - d.t[0])
    y[late] = y[~late].mean(axis=0) + 0.01 * y[~late].std(axis=0) * rng.standard_normal((late.sum(), 6))
    return replace(d, targets=y, source="steady.tlog", sha256="ab" * 32, flights=[])


def _role_of_rows(data: Dataset, roles) -> dict[str, np.ndarray]:
    """Per role, the times of its rows (one flight)."""
    return {r: getattr(roles, r).t for r in ("fit", "pick", "validate")}


def test_a_flight_that_varies_to_its_end_keeps_the_tail_layout():
    data = synthetic_dataset(2500, seed=4)
    roles = assign_roles(data)
    (layout,) = roles.layouts
    assert layout.kind == "tail" and layout.min_spread_ratio >= MIN_SPREAD_RATIO
    fit, pick, val = time_block_masks(data.t, (0.6, 0.2, 0.2), DEFAULT_GAP_S)
    assert np.array_equal(roles.validate.t, data.t[val]) and np.array_equal(roles.pick.t, data.t[pick])
    assert np.array_equal(roles.fit.t, data.t[fit]) and roles.notes() == []
    assert roles.as_dict()["layout"][0]["placement"] == "tail"


def test_a_steady_tail_moves_the_held_out_blocks_where_the_targets_vary_and_never_fits_on_them():
    data = _steady_tail()
    roles = assign_roles(data)
    (layout,) = roles.layouts
    assert layout.kind == "spread"
    assert layout.tail_min_spread_ratio < 0.1 <= MIN_SPREAD_RATIO <= layout.min_spread_ratio
    steady_from = data.t[0] + 0.55 * (data.t[-1] - data.t[0])
    for role in ("validate", "pick"):  # each held-out block moved (at least partly) into the varying part
        held = getattr(roles, role)
        assert held.t.min() < steady_from
        assert (held.targets.std(axis=0) >= MIN_SPREAD_RATIO * data.targets.std(axis=0)).all()
    # no row in two roles; every fit row more than the gap (s) from every held-out row
    times = _role_of_rows(data, roles)
    held = np.concatenate((times["pick"], times["validate"]))
    assert not set(times["fit"].round(6)) & set(held.round(6))
    assert not set(times["pick"].round(6)) & set(times["validate"].round(6))
    nearest = np.min(np.abs(times["fit"][:, None] - held[None, :]), axis=1)
    assert nearest.min() > DEFAULT_GAP_S
    pv = np.min(np.abs(times["pick"][:, None] - times["validate"][None, :]))
    assert pv >= DEFAULT_GAP_S
    # the record: one block per piece of the fit rows (the steady tail is still fitted on), rows add up
    record = roles.as_dict()
    assert len(record["fit"]) >= 2 and sum(b["rows"] == 0 for b in record["fit"]) == 0
    assert sum(b["rows"] for b in record["fit"]) == len(roles.fit)
    assert record["fit"][-1]["t_end_s"] == pytest.approx(data.t[-1])
    assert record["layout"][0]["placement"] == "spread"
    assert len(roles.fit) + len(roles.pick) + len(roles.validate) + roles.unused_rows == len(data)
    (note,) = roles.notes()
    assert "steady.tlog" in note and "validate" in note and "barely varies" in note


def test_a_flight_that_varies_only_in_a_short_transient_keeps_its_tail_and_says_so():
    data = _steady_tail(3000, seed=13, steady_from=0.08)  # like a take-off transient, then steady
    roles = assign_roles(data)
    (layout,) = roles.layouts
    assert layout.kind == "tail" and layout.tail_min_spread_ratio < MIN_SPREAD_RATIO
    fit, pick, val = time_block_masks(data.t, (0.6, 0.2, 0.2), DEFAULT_GAP_S)
    assert np.array_equal(roles.validate.t, data.t[val])
    (note,) = roles.notes()
    assert "kept the tail" in note and "says little" in note


def test_the_model_file_records_the_moved_blocks_and_validates_only_on_them(tmp_path):
    data = _steady_tail(2500, seed=12)
    model = identify(data, engine="sparse", targets=["dwy"], progress=False)
    again = load_model(save_model(model, tmp_path / "m.yaml"))
    record = again.extra["data"]
    assert record["layout"][0]["placement"] == "spread"
    (val,) = record["validate"]
    rows = (data.t >= val["t_start_s"] - 1e-9) & (data.t <= val["t_end_s"] + 1e-9)
    assert rows.sum() == val["rows"] == again.engine["rows"]["validate"]
    assert again.engine["rows"]["fit"] == sum(b["rows"] for b in record["fit"])


@pytest.mark.skipif(not TAKEOFF.is_file(), reason=f"the shared logs are absent ({LOGS})")
def test_the_short_px4_takeoff_is_validated_where_it_accelerates_not_on_its_steady_descent():
    data = load_dataset(TAKEOFF)
    roles = assign_roles(data)
    assert roles.layouts[0].kind == "spread"
    # the tail (the last 20 %) is a steady descent: z'' spread 0.03 m/s^2; the moved block holds variation
    tail = data.t >= data.t.max() - 0.2 * (data.t.max() - data.t.min())
    assert data.targets[tail, 2].std() < 0.06
    assert roles.validate.targets[:, 2].std() > 0.3 and roles.pick.targets[:, 2].std() > 0.2
    held = np.concatenate((roles.pick.t, roles.validate.t))
    assert np.min(np.abs(roles.fit.t[:, None] - held[None, :])) > DEFAULT_GAP_S


def test_flight_evidence_of_arrays():
    t = np.arange(500) * 0.02
    climb = -np.linspace(0, 3, 500)  # m NED: 3 m up
    never = no_flight_evidence(t, {"armed": np.zeros(500), "throttle": np.full((500, 4), 0.6)}, climb)
    assert "never armed in this log" in " ".join(never)
    flying = {"throttle": np.full((500, 4), 0.5)}
    assert no_flight_evidence(t, flying, climb) is None  # no arming state, motors ran
    bench = no_flight_evidence(t, {"throttle": np.zeros((500, 4))}, np.full(500, 0.1))
    assert bench is not None and "at most 0.000 of full" in " ".join(bench)
    assert no_flight_evidence(t, {"armed": np.ones(500)}, np.full(500, 0.1)) is None  # armed: the detectors


@pytest.mark.skipif(not TAKEOFF.is_file(), reason=f"the shared logs are absent ({LOGS})")
def test_the_real_hardware_log_that_never_armed_says_no_flight_with_its_evidence(tmp_path, capsys):
    with pytest.raises(NoFlightError) as info:
        load_dataset(LOGS / "pyulog_sample_auavx21.ulg")
    text = str(info.value)
    assert "holds no flight" in text and "armed in 0 of" in text
    assert "motor commands: at most 0.000 of full" in text and "height: varies by 0.01" in text
    code = main(["identify", str(LOGS / "pyulog_sample_auavx21.ulg"), "-o", str(tmp_path / "m.yaml")])
    err = capsys.readouterr().err
    assert code == 2 and "holds no flight" in err and "Traceback" not in err
    assert not (tmp_path / "m.yaml").exists()


def test_pick_blocks_spread_the_pick_over_the_flight_each_a_gap_from_every_fit_row(tmp_path, capsys):
    data = synthetic_dataset(5000, seed=4)  # 20 s
    roles = assign_roles(data, pick_blocks=4)
    (layout,) = roles.layouts
    assert layout.kind == "interleaved" and roles.notes() == []
    pieces = [b for b in roles.blocks if b.role == "pick"]
    assert len(pieces) == 4
    span = data.t[-1] - data.t[0]
    assert pieces[0].t_end < data.t[0] + 0.25 * span and pieces[-1].t_start > data.t[0] + 0.5 * span
    fit, pick, val = roles.fit.t, roles.pick.t, roles.validate.t
    assert np.min(np.abs(fit[:, None] - pick[None, :])) >= DEFAULT_GAP_S - 1e-9
    assert val.min() - max(fit.max(), pick.max()) >= DEFAULT_GAP_S - 1e-9  # the tail validates
    usable = span - DEFAULT_GAP_S * (2 * 4 + 1)
    assert abs(len(pick) * 0.004 - 0.2 * usable) < 0.1 and abs(len(val) * 0.004 - 0.2 * usable) < 0.1
    with pytest.raises(UserError, match="pick blocks"):
        assign_roles(data, pick_blocks=0)
    steady = assign_roles(_steady_tail(3000, seed=11), pick_blocks=4)  # its tail (validate) barely varies
    (fallback,) = steady.layouts
    assert fallback.kind == "spread" and "4 pick blocks spread over the flight" in fallback.note
    log = tmp_path / "flight.csv"
    log.write_text("not a log\n")
    code = main(["identify", str(log), "--pick-blocks", "0", "-o", str(tmp_path / "m.yaml")])
    err = capsys.readouterr().err
    assert code == 2 and "--pick-blocks must be a whole number >= 1" in err and "Traceback" not in err
