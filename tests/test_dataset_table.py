"""Flight tables (CSV and Parquet, README "Tables from anywhere"): the schema, its errors, the round trip
from a Dataset, and the same rows as the .bin log they were made from."""

from __future__ import annotations

import numpy as np
import pytest
from dataflash_fixture import fly_synthetic, write_flight

from bridge.errors import UserError
from identification.dataset import load_dataset
from identification.table import INPUT_NAMES, STATE_NAMES, TARGET_NAMES


@pytest.fixture(scope="module")
def logged(tmp_path_factory):
    flight = fly_synthetic(duration=2.0, seed=5)
    path = write_flight(tmp_path_factory.mktemp("tab") / "f.bin", flight)
    return load_dataset(path, airborne=False)


def _write(path, columns: dict[str, np.ndarray]) -> None:
    names = list(columns)
    rows = np.column_stack([columns[n] for n in names])
    with path.open("w") as fh:
        fh.write(",".join(names) + "\n")
        for r in rows:
            fh.write(",".join(f"{v:.12g}" for v in r) + "\n")


def _columns(ds) -> dict[str, np.ndarray]:
    cols = {"t": ds.t}
    cols.update({n: ds.xi[:, i] for i, n in enumerate(STATE_NAMES)})
    cols.update({n: ds.u[:, i] for i, n in enumerate(INPUT_NAMES)})
    cols.update({n: ds.targets[:, i] for i, n in enumerate(TARGET_NAMES)})
    return cols


def test_csv_round_trip_of_a_dataset(logged, tmp_path):
    path = logged.to_csv(tmp_path / "flight.csv")  # our own CSV (with a 'flight' column) is a valid table
    ds = load_dataset(path, airborne=False)
    assert ds.format == "table" and len(ds) == len(logged)
    assert np.allclose(ds.xi, logged.xi, rtol=1e-8, atol=1e-9)
    assert np.allclose(ds.u, logged.u, rtol=1e-8) and np.allclose(
        ds.targets, logged.targets, rtol=1e-8, atol=1e-9
    )


def test_parquet_with_quaternions_and_throttles(logged, tmp_path):
    import pyarrow as pa  # a test dependency (pyproject [test])
    import pyarrow.parquet as pq

    cols = _columns(logged)
    phi, theta, psi = (cols.pop(n) for n in ("phi", "theta", "psi"))
    cy, sy, cp, sp, cr, sr = (f(a / 2) for a in (psi, theta, phi) for f in (np.cos, np.sin))
    cols.update(qw=cr * cp * cy + sr * sp * sy, qx=sr * cp * cy - cr * sp * sy)
    cols.update(qy=cr * sp * cy + sr * cp * sy, qz=cr * cp * sy - sr * sp * cy)
    thr = np.clip(logged.u / 1200.0, 0, 1)
    for i in range(4):
        cols.pop(f"u{i + 1}")
        cols[f"throttle{i + 1}"] = thr[:, i]
    for n in TARGET_NAMES:
        cols.pop(n)  # targets from the derivatives of the states
    cols["voltage"] = np.full(len(logged), 15.5)
    path = tmp_path / "flight.parquet"
    pq.write_table(pa.table(cols), path)
    ds = load_dataset(path, airborne=False, motor_curve="1200,0")
    _, a, b = np.intersect1d(ds.t, logged.t, return_indices=True)
    assert len(a) == len(ds) > 0.9 * len(logged)  # the differentiation's edges have no target
    assert np.abs(ds.xi[a, 6:9] - logged.xi[b, 6:9]).max() < 1e-9  # quaternion -> Euler
    assert np.allclose(ds.u[a], 1200.0 * thr[b])
    assert np.allclose(ds.aux["voltage"], 15.5)
    # derivatives of the rates: the same as the .bin reader's truth targets
    assert np.corrcoef(ds.targets[a, 3], logged.targets[b, 3])[0, 1] > 0.99
    plain = load_dataset(path, airborne=False)
    assert plain.u_from_throttle and "throttle" in plain.aux


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda c: c.pop("wy"), "has no column 'wy' \\(body rates FRD, rad/s\\)"),
        (lambda c: [c.pop(n) for n in ("phi", "theta", "psi")], "has no column 'phi' \\(the attitude"),
        (lambda c: [c.pop(f"u{i}") for i in range(1, 5)], "has no column 'throttle1'"),
        (lambda c: c.update(t=c["t"][::-1].copy()), "column 't' must be finite and strictly increasing"),
    ],
)
def test_schema_errors_name_the_column(logged, tmp_path, change, message):
    cols = _columns(logged)
    change(cols)
    path = tmp_path / "bad.csv"
    _write(path, cols)
    with pytest.raises(UserError, match=message):
        load_dataset(path, airborne=False)


def test_bad_values_name_line_and_column(tmp_path):
    path = tmp_path / "text.csv"
    path.write_text("t,x\n0.0,1\n0.1,abc\n")
    with pytest.raises(UserError, match="text.csv, line 3, column 'x': 'abc' is not a number"):
        load_dataset(path)
    short = tmp_path / "short.csv"
    short.write_text("t,x,y\n0.0,1\n")
    with pytest.raises(UserError, match="line 2: 2 values for 3 columns"):
        load_dataset(short)
    with pytest.raises(UserError, match="need an IMU"):
        load_dataset(short, targets="sensors")
