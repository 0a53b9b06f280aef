"""Honest selection: fit / pick / validate blocks with gaps and their record, the same model from the same
seed, the collinearity warning on a confounded flight, and `quadsr identify --strict`."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from synthetic_data import synthetic_dataset

from bridge.errors import UserError
from identification.cli_models import EXIT_BELOW_THRESHOLD
from identification.collinearity import column_collinearity
from identification.data_roles import DEFAULT_GAP_S, assign_roles
from identification.dataset import Dataset
from identification.engine import EngineSettings, OperonSettings, SparseSettings
from identification.identify import identify
from identification.metrics import table_metrics
from identification.model_file import load_model, save_model
from identification.true_model import random_states, true_model
from quadsr.cli import main

REPO = Path(__file__).resolve().parent.parent
ULOG = REPO.parent / "shared" / "logs" / "px4_sitl_quad_takeoff.ulg"


def _flight(n: int, seed: int, name: str, t0: float = 0.0) -> Dataset:
    d = synthetic_dataset(n, seed)
    return replace(d, t=d.t + t0, source=name, sha256=f"{seed:064x}", flights=[])


def test_blocks_are_separated_by_the_gap_and_every_row_is_accounted_for():
    flights = Dataset.concat([_flight(3000, 1, "a.tlog"), _flight(2000, 2, "b.tlog", t0=5.0)])
    roles = assign_roles(flights, gap_s=0.5)
    record = roles.as_dict()
    assert record["gap_s"] == 0.5
    for f, name in enumerate(("a.tlog", "b.tlog")):
        blocks = {r: [b for b in record[r] if b["file"] == name] for r in ("fit", "pick", "validate")}
        assert all(len(v) == 1 for v in blocks.values()), blocks
        fit, pick, val = (blocks[r][0] for r in ("fit", "pick", "validate"))
        assert pick["t_start_s"] - fit["t_end_s"] >= 0.5 and val["t_start_s"] - pick["t_end_s"] >= 0.5
        assert fit["sha256"] == f"{f + 1:064x}"
        # the fractions (60/20/20 of the time left after the gaps), within a sample
        n = 3000 if f == 0 else 2000
        usable = (n - 1) * 0.004 - 2 * 0.5
        assert pick["t_end_s"] - pick["t_start_s"] == pytest.approx(0.2 * usable, abs=0.009)
        assert fit["t_end_s"] - fit["t_start_s"] == pytest.approx(0.6 * usable, abs=0.009)
    # no row in two roles; the rows no role holds are those in the gaps (2 gaps x 0.5 s x 250 Hz per flight)
    sets = [roles.fit, roles.pick, roles.validate]
    keys = [set(zip(d.flight.tolist(), d.t.round(6).tolist(), strict=True)) for d in sets]
    assert not (keys[0] & keys[1] or keys[0] & keys[2] or keys[1] & keys[2])
    assert sum(len(d) for d in sets) + roles.unused_rows == len(flights)
    assert roles.unused_rows == pytest.approx(2 * 2 * 0.5 / 0.004, abs=4)


def test_a_validation_flight_replaces_the_validate_block_and_must_be_another_flight():
    fit = _flight(2000, 3, "train.tlog")
    other = _flight(1000, 4, "other.tlog")
    roles = assign_roles(fit, validate=other)
    assert [b.file for b in roles.blocks if b.role == "validate"] == ["other.tlog"]
    assert len(roles.validate) == 1000
    assert roles.blocks[0].role == "fit" and roles.blocks[0].t_end < roles.blocks[1].t_start
    with pytest.raises(UserError, match="given both to fit and to validate"):
        assign_roles(fit, validate=_flight(2000, 3, "copy-of-train.tlog"))
    with pytest.raises(UserError, match="only 0 rows to fit on .* 0.4 s gaps"):
        assign_roles(_flight(60, 5, "short.tlog"))  # 0.24 s: less than the two gaps
    with pytest.raises(UserError, match="only 18 rows to pick on"):
        assign_roles(_flight(400, 5, "short.tlog"), pick_fraction=0.05, gap_s=0.1)  # 0.07 s


def test_validation_metrics_come_only_from_rows_used_neither_to_fit_nor_to_pick(tmp_path):
    data = synthetic_dataset(2500, seed=6, noise=0.02)
    model = identify(data, engine="sparse", targets=["dwy"], progress=False)
    path = save_model(model, tmp_path / "m.yaml")
    again = load_model(path)
    record = again.extra["data"]
    assert record["gap_s"] == DEFAULT_GAP_S
    val = record["validate"][0]
    rows = (data.t >= val["t_start_s"] - 1e-9) & (data.t <= val["t_end_s"] + 1e-9)
    assert rows.sum() == val["rows"]
    expected = table_metrics(data.targets[rows, 4], again.evaluate(data.xi[rows], data.u[rows])[:, 0])
    assert again.targets["dwy"].metrics["validation"]["r2"] == pytest.approx(expected["r2"], rel=1e-9)
    assert again.targets["dwy"].metrics["validation"]["rmse"] == pytest.approx(expected["rmse"], rel=1e-6)
    assert set(again.targets["dwy"].metrics) == {"train", "pick", "validation"}
    assert again.engine["rows"]["validate"] == val["rows"]


def test_the_same_seed_gives_the_same_model_with_genetic_programming(tmp_path):
    xi, u = random_states(1200, seed=8)
    y = true_model("fang-chen-buaa").accelerations(xi, u)
    y[:, 3] += 20.0 * np.sin(xi[:, 6]) * np.cos(xi[:, 6])  # not in the grown features either
    data = Dataset(t=np.arange(1200) * 0.004, xi=xi, u=u, targets=y, source="synthetic", format="synthetic",
                   target_source="truth")
    small = EngineSettings(
        sparse=SparseSettings(thresholds=10, forward_terms=8),
        operon=OperonSettings(population_size=100, max_length=15, optimizer_iterations=3, n_threads=2),
    )
    models = [identify(data, engine="default", targets=["dwx"], budget=6, seed=3, settings=small,
                       progress=False) for _ in range(2)]
    fronts = [m.body.targets["dwx"].pareto for m in models]  # the default engine learns in the body frame
    assert any("operon" in (p.engine or "") for p in fronts[0])  # genetic programming ran (never gated)
    assert [p.expression for p in fronts[0]] == [p.expression for p in fronts[1]]
    assert str(models[0].targets["dwx"].expression) == str(models[1].targets["dwx"].expression)
    assert models[0].engine["budget_generations_per_target"] == 6
    # the engine's account of its search is in the file, per target, as the run left it
    stats = load_model(save_model(models[0], tmp_path / "m.yaml")).engine["stats"]["dwx"]
    assert stats == models[1].engine["stats"]["dwx"]
    assert stats["features"] > 0 and stats["rounds"] >= 1 and 1 <= stats["operon_generations"] <= 6, stats


def _confounded_flight(n: int, seed: int, tied: bool) -> Dataset:
    """Random states; the roll torque f2 follows -wx (a rate controller) when tied, else independent."""
    rng = np.random.default_rng(seed)
    xi, _ = random_states(n, seed)
    drive = -3000.0 * xi[:, 9] if tied else 3000.0 * rng.standard_normal(n)
    drive = drive + 20.0 * rng.standard_normal(n)
    signs = np.array([-1.0, 1.0, 1.0, -1.0])  # f2 = -u1^2 + u2^2 + u3^2 - u4^2
    u = np.sqrt(560.0**2 * (1 + 1e-3 * rng.standard_normal((n, 4))) + signs * drive[:, None])
    y = true_model("fang-chen-buaa").accelerations(xi, u)
    return Dataset(t=np.arange(n) * 0.004, xi=xi, u=u, targets=y, source="confounded.tlog",
                   format="synthetic", target_source="truth")


def test_a_confounded_flight_names_the_terms_it_cannot_separate_and_the_excitation(capsys, tmp_path):
    model = identify(_confounded_flight(2500, 7, tied=True), engine="sparse", targets=["dwx"], progress=False)
    err = capsys.readouterr().err
    info = load_model(save_model(model, tmp_path / "m.yaml")).extra["identifiability"]["targets"]["dwx"]
    f2 = "u2**2 + u3**2 - u1**2 - u4**2"
    # the roll torque and the rate are named as tied: both kept in the model (on these noise-free targets
    # the pick may separate them) and flagged not identifiable, or one kept, the other named confused with it
    pairs = {(c["term"], c["candidate"]) for c in info["confused_with_candidates"]}
    flagged = {c["term"]: c for c in info.get("not_identifiable", [])}
    if (f2, "wx") in pairs:
        assert "cannot be told apart" in err and "with wx" in err
    else:
        assert {f2, "wx"} <= set(flagged), info
        assert flagged[f2]["vif"] > 100 and flagged["wx"]["vif"] > 100
        assert "not identifiable from this flight" in err and "tied most to wx" in err
    assert all(c["vif_with_it"] == "inf" or c["vif_with_it"] > 100 for c in info["confused_with_candidates"])
    assert "excite each motor independently" in info["excitation"] and "excite each motor" in err

    free = _confounded_flight(2500, 7, tied=False)
    model = identify(free, engine="sparse", targets=["dwx"], progress=False)
    info = model.extra["identifiability"]["targets"]["dwx"]
    assert info["confused_with_candidates"] == [] and info["not_identifiable"] == []
    assert "wx" in {str(s) for s in model.targets["dwx"].expression.free_symbols}


def test_vif_and_condition_number_of_known_columns():
    rng = np.random.default_rng(9)
    a, b, c = rng.standard_normal((3, 5000))
    cols = np.column_stack([a, b, a + 0.1 * c, np.ones(5000)])
    result = column_collinearity(cols, ["a", "b", "a_c", "one"])
    vif = {t.term: t.vif for t in result.terms}
    assert set(vif) == {"a", "b", "a_c"}  # the constant is no collinearity
    assert vif["b"] == pytest.approx(1.0, abs=0.01)
    assert vif["a"] == pytest.approx(101.0, rel=0.05) and vif["a_c"] == pytest.approx(101.0, rel=0.05)
    assert {t.term for t in result.unidentifiable} == {"a", "a_c"}
    assert dict((t.term, t.partner) for t in result.terms)["a"] == "a_c"
    r = 1 / np.sqrt(1.01)  # correlation of a and a + 0.1 c: eigenvalues 1 +- r of their block, and 1
    assert result.condition_number == pytest.approx(np.sqrt((1 + r) / (1 - r)), rel=0.05)


def test_identify_strict_exits_4_when_a_target_is_below_the_threshold(tmp_path, capsys):
    base = ["identify", str(ULOG), "--engine", "sparse", "--targets", "dwz", "--no-progress"]
    out = tmp_path / "m.yaml"
    assert main([*base, "-o", str(out), "--r2-threshold", "0.999"]) == 0  # flagged, not strict
    flagged = load_model(out).extra["checks"]
    r2 = load_model(out).targets["dwz"].metrics["validation"]["r2"]
    assert r2 < 0.999 and flagged["below_threshold"] == {"dwz": pytest.approx(r2)}
    assert flagged["validation_r2_threshold"] == 0.999
    assert "below the validation R^2 threshold 0.999: dwz" in capsys.readouterr().out
    strict = tmp_path / "strict.yaml"
    code = main([*base, "-o", str(strict), "--r2-threshold", "0.999", "--strict"])
    assert code == EXIT_BELOW_THRESHOLD == 4
    assert strict.exists()  # the model is still written
    assert main([*base, "-o", str(strict), "--r2-threshold", str(r2 - 0.01), "--strict"]) == 0
    assert load_model(strict).extra["checks"]["below_threshold"] == {}


@pytest.mark.parametrize(
    "flags,expect",
    [
        (["--gap", "0.1"], "--gap must be at least 0.4 s"),
        (["--budget", "0"], "--budget must be a whole number of generations"),
        (["--validate-fraction", "1.5"], "--validate-fraction must be a fraction"),
        (["--r2-threshold", "2"], "--r2-threshold must be a number <= 1"),
    ],
)
def test_identify_bad_selection_flags_are_clear_errors(tmp_path, capsys, flags, expect):
    code = main(["identify", str(ULOG), "-o", str(tmp_path / "m.yaml"), *flags])
    assert code == 2 and expect in capsys.readouterr().err


def test_identify_refuses_to_validate_on_the_flight_it_fits(tmp_path, capsys):
    code = main(["identify", str(ULOG), "-o", str(tmp_path / "m.yaml"), "--validate-log", str(ULOG)])
    assert code == 2 and "is given both to fit and to validate" in capsys.readouterr().err
    assert not (tmp_path / "m.yaml").exists()
