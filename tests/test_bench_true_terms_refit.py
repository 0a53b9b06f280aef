"""bench/discovery.py's "true terms refit" row: the true terms with their coefficients refit on the training
flight, scored as an engine's model. On noise-free rows it is the reference itself (every term found, no
extra, coefficients and the height law's scale exact); with noise on the rate targets its coefficient error
is the noise's (what the flight gives the exact structure), and it is no baseline: no floor is judged
against it."""

from __future__ import annotations

import numpy as np
from bench_module import bench_module

discovery = bench_module("discovery.py", "bench_discovery_refit")


def _refit_row(case, train, val, body, law=None, far=None):
    reference = discovery.reference_model(case.effects)
    hidden = discovery.unidentifiable_terms(far or body, train, 9.8, weak=False, height_law=law)
    refit = discovery.true_terms_refit(far or body, train, 9.8, weak=False, height_law=law)
    return discovery.score_true_terms_refit(case.name, refit, val, reference, far or body, 0.0, 0.0, False,
                                            hidden, law)


def test_on_noise_free_rows_the_refit_is_the_reference():
    case = discovery.Case("paper vehicle")
    train, val = discovery.synthetic(case, 2000, seed=4), discovery.synthetic(case, 1000, seed=1004)
    body = discovery.body_expressions(discovery.VEHICLE, case.effects)
    row = _refit_row(case, train, val, body)
    assert (row.missing, row.extra) == (0, 0) and row.found == row.reference_terms > 10
    assert row.max_error < 1e-6 and min(row.r2.values()) > 1 - 1e-9


def test_a_height_law_is_refit_by_its_scale_and_the_rest_against_the_no_ground_terms():
    case = discovery.Case("ground effect", discovery.Effects(ground_effect=0.08), height=(0.3, 3.0))
    train, val = discovery.synthetic(case, 2000, seed=4), discovery.synthetic(case, 1000, seed=1004)
    full = discovery.body_expressions(discovery.VEHICLE, case.effects)
    far = discovery.body_expressions(discovery.VEHICLE, discovery.Effects())
    law = {n: full[n] - far[n] for n in full}
    row = _refit_row(case, train, val, full, law=law, far=far)
    assert set(row.height_law) == {n for n, e in law.items() if e != 0} and row.height_law
    assert all(e < 1e-6 for e in row.height_law.values())
    assert (row.missing, row.extra) == (0, 0) and row.max_error < 1e-6


def test_noise_on_the_targets_is_the_refits_coefficient_error_and_no_floor_is_judged_against_it():
    case = discovery.Case("paper vehicle")
    train, val = discovery.synthetic(case, 2000, seed=4), discovery.synthetic(case, 1000, seed=1004)
    body = discovery.body_expressions(discovery.VEHICLE, case.effects)
    rng = np.random.default_rng(8)
    train.targets[:, 3:] += 0.05 * rng.standard_normal((len(train), 3))  # rad/s^2 on dwx dwy dwz
    row = _refit_row(case, train, val, body)
    assert row.max_error > 1e-3 and row.worst.split(":")[0] in ("dwx", "dwy", "dwz")
    assert row.engine == discovery.TRUE_TERMS_REFIT and row.engine not in discovery.BASELINES
    assert discovery.case_floors(case, [row], 60.0) == []  # ours did not run: no floor from this row alone


def test_the_coefficient_floor_quotes_the_refit_when_it_misses_the_floor_too():
    """The floor's verdict is ours alone; its line quotes the refit's error where that is beyond the floor
    as well (the flight, not only the engine's terms, misses it there)."""
    case = discovery.Case("paper vehicle")
    train, val = discovery.synthetic(case, 2000, seed=4), discovery.synthetic(case, 1000, seed=1004)
    body = discovery.body_expressions(discovery.VEHICLE, case.effects)
    refit = _refit_row(case, train, val, body)
    labels = {}
    for ours_error, refit_error in ((0.5, 0.2), (0.5, 1e-3), (1e-3, 0.2)):
        rows = [discovery.replace(refit, engine="discovery", max_error=ours_error),
                discovery.replace(refit, max_error=refit_error)]
        floors = dict(discovery.case_floors(case, rows, 60.0))
        label = next(label for label in floors if "coefficients within" in label)
        assert floors[label] is (ours_error <= 0.05)
        assert f": largest {ours_error:.2%} ({refit.worst})" in label  # which term misses it
        labels[ours_error, refit_error] = label
    assert "the true terms refit on the training flight: 20.0%" in labels[0.5, 0.2]
    assert "the true terms refit" not in labels[0.5, 1e-3]


def test_the_csv_names_where_each_rows_largest_coefficient_error_is(tmp_path):
    """The CSV's max_coef_term column: the target and term of each row's largest coefficient error."""
    import csv

    case = discovery.Case("paper vehicle")
    train, val = discovery.synthetic(case, 2000, seed=4), discovery.synthetic(case, 1000, seed=1004)
    body = discovery.body_expressions(discovery.VEHICLE, case.effects)
    rng = np.random.default_rng(8)
    train.targets[:, 3:] += 0.05 * rng.standard_normal((len(train), 3))
    row = _refit_row(case, train, val, body)
    discovery.write_outputs([row], [], tmp_path, stem="t")
    with (tmp_path / "t.csv").open(encoding="utf-8") as fh:
        (read,) = list(csv.DictReader(fh))
    assert read["max_coef_term"] == row.worst and read["max_coef_term"].split(":")[0] in ("dwx", "dwy", "dwz")
    assert float(read["max_coef_error"]) == float(f"{row.max_error:.6g}")
