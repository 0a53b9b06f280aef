"""Validation outputs (Table I md/csv, Fig. 3 png), the reference comparison, and the CLI's errors."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import sympy
from synthetic_data import synthetic_dataset

from identification.model_file import SYMBOLS, Model, load_model
from identification.true_model import true_model
from identification.validate import validate
from quadsr.cli import main

S = SYMBOLS
ULOG = Path(__file__).resolve().parents[2] / "shared" / "logs" / "px4_sitl_quad_takeoff.ulg"


def test_validate_writes_table_csv_and_figure_with_right_numbers(tmp_path):
    truth = true_model("fang-chen-buaa")
    exprs = dict(truth.expressions)
    exprs["dwx"] = exprs["dwx"] + sympy.Float(0.5)  # a known error: RMSE = MAE = 0.5 on wx'
    report = validate(Model(exprs), synthetic_dataset(800, seed=41), tmp_path / "out")
    assert report.metrics["ax"]["r2"] == pytest.approx(1.0) and report.metrics["ax"]["rmse"] < 1e-9
    assert report.metrics["dwx"]["rmse"] == pytest.approx(0.5) and report.metrics["dwx"][
        "mae"
    ] == pytest.approx(0.5)
    md = report.table_md.read_text()
    assert "| Variable | RMSE | MAE | R^2 |" in md and md.count("\n| ") == 8
    rows = list(csv.DictReader(report.table_csv.open()))
    assert [r["target"] for r in rows] == ["ax", "ay", "az", "dwx", "dwy", "dwz"]
    assert float(rows[3]["rmse"]) == pytest.approx(0.5)
    png = report.figure.read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    assert report.comparisons is None and report.compare_md is None


def test_comparison_flags_a_missing_term_an_extra_term_and_coefficient_errors(tmp_path):
    truth = true_model("fang-chen-buaa")
    exprs = dict(truth.expressions)
    wx, wy, wz = S["wx"], S["wy"], S["wz"]
    learned_dwx = sympy.expand(exprs["dwx"])
    gyro = learned_dwx.coeff(wy * wz) * wy * wz
    damping = learned_dwx.coeff(wx) * wx
    # drop the damping term, add a spurious one, and make the gyroscopic coefficient 1% too large
    exprs["dwx"] = learned_dwx - damping + 0.01 * gyro + sympy.Float(0.3) * wz
    report = validate(Model(exprs), synthetic_dataset(800, seed=41), tmp_path, reference=truth)
    by_target = {c.target: c for c in report.comparisons}
    assert all(by_target[t].same_terms for t in ("ax", "ay", "az", "dwy", "dwz"))
    c = by_target["dwx"]
    assert not c.same_terms and c.missing == ["wx"] and c.extra == ["wz"]
    assert c.max_relative_error == pytest.approx(0.01, rel=1e-6)
    md = report.compare_md.read_text()
    assert "| dwx | no |" in md and "`wx`" in md and "`wz`" in md
    rows = [r for r in csv.DictReader(report.compare_csv.open()) if r["target"] == "dwx"]
    status = {r["term"]: r["status"] for r in rows}
    assert status["wx"] == "missing" and status["wz"] == "extra" and status["wy*wz"] == "both"
    assert float(next(r for r in rows if r["term"] == "wy*wz")["relative_error"]) == pytest.approx(
        0.01, rel=1e-6
    )


def test_cli_model_from_vehicle_then_validate_and_identify_on_a_real_px4_log(tmp_path, capsys):
    if not ULOG.exists():
        pytest.skip(f"{ULOG} is absent (the shared test logs live beside the project)")
    true_path = tmp_path / "true.yaml"
    assert main(["model-from-vehicle", "-o", str(true_path)]) == 0
    assert load_model(true_path).kind == "true-model"
    out = tmp_path / "val"
    assert (
        main(["validate", str(true_path), str(ULOG), "--out", str(out), "--reference", str(true_path)]) == 0
    )
    printed = capsys.readouterr().out
    assert "| Variable | RMSE | MAE | R^2 |" in printed and "| dwz | yes |" in printed
    for name in ("table1.md", "table1.csv", "fig3_targets.png", "compare.md", "compare.csv"):
        assert (out / name).stat().st_size > 0
    learned = tmp_path / "learned.yaml"
    code = main(
        [
            "identify",
            str(ULOG),
            "-o",
            str(learned),
            "--engine",
            "sparse",
            "--budget",
            "20",
            "--targets",
            "az,dwz",
            "--no-progress",
        ]
    )
    assert code == 0
    model = load_model(learned)
    assert model.target_names == ("az", "dwz") and model.flights[0]["format"] == "ulog"
    assert len(model.flights[0]["sha256"]) == 64 and model.engine["name"] == "sparse"
    assert set(model.engine["wall_time_s"]) == {"az", "dwz"}


@pytest.mark.parametrize(
    "argv,expect",
    [
        (["validate", "{tmp}/nope.yaml", "{tmp}/x.tlog"], "does not exist"),
        (["identify", "{tmp}/none.tlog", "-o", "{tmp}/m.yaml"], "does not exist"),
        (
            ["identify", "{tmp}/none.tlog", "-o", "{tmp}/m.yaml", "--targets", "ax,dwq"],
            "unknown target 'dwq'",
        ),
        (["identify", "{tmp}/none.tlog", "-o", "{tmp}/m.yaml", "--budget", "-3"], "--budget"),
        (["identify", "{tmp}/none.tlog", "-o", "{tmp}/m.yaml", "--holdout", "1.5"], "--holdout"),
        (["identify", "{tmp}/none.tlog", "-o", "{tmp}/m.yaml", "--seed", "-1"], "--seed"),
        (["identify", "{tmp}/none.tlog", "-o", "{tmp}"], "is a directory"),
        (
            ["identify", "{tmp}/none.tlog", "-o", "{tmp}/m.yaml", "--settings", "{tmp}/bad_settings.yaml"],
            "unknown key 'sparse.treshold'",
        ),
        (["model-from-vehicle", "--vehicle", "no-such-vehicle", "-o", "{tmp}/m.yaml"], "not found"),
        (["validate", "{tmp}/true.yaml", "{tmp}/x.tlog", "--out", "{tmp}/true.yaml"], "not a directory"),
    ],
)
def test_cli_bad_inputs_are_clear_errors_with_exit_code_2(tmp_path, capsys, argv, expect):
    (tmp_path / "bad_settings.yaml").write_text("sparse:\n  treshold: 0.1\n")
    assert main(["model-from-vehicle", "-o", str(tmp_path / "true.yaml")]) == 0
    capsys.readouterr()
    code = main([a.format(tmp=tmp_path) for a in argv])
    err = capsys.readouterr().err
    assert code == 2
    assert expect in err and "Traceback" not in err, err
