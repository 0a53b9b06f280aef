"""The Python API (identification.quad_model): fit, predict, score, simulate and the model.yaml round trip
on flights whose accelerations come from the SITL's true model."""

from __future__ import annotations

import numpy as np
import pytest
import sympy
from synthetic_data import synthetic_dataset

from bridge.errors import UserError
from bridge.vehicle import load_vehicle
from identification.quad_model import QuadrotorModel, flight_from_arrays
from identification.true_model import write_true_model


@pytest.fixture(scope="module")
def fitted():
    return QuadrotorModel(engine="sparse", budget=10, seed=0).fit(synthetic_dataset(3000, seed=1))


def test_fit_predict_score_on_new_data(fitted):
    test = synthetic_dataset(1000, seed=7)
    scores = fitted.scores(test)
    assert set(scores) == {"ax", "ay", "az", "dwx", "dwy", "dwz"}
    assert min(scores.values()) > 0.999, scores
    assert fitted.score(test) == pytest.approx(np.mean(list(scores.values())))
    pred = fitted.predict(test)
    assert pred.shape == (1000, 6)
    assert np.allclose(fitted.predict(test.xi, test.u), pred)


def test_round_trip_through_model_yaml(fitted, tmp_path):
    path = fitted.save(tmp_path / "model.yaml")
    again = QuadrotorModel.load(path)
    test = synthetic_dataset(200, seed=9)
    assert np.allclose(again.predict(test), fitted.predict(test), rtol=1e-9, atol=1e-9)
    for name, expr in fitted.equations.items():  # the same formula (the file may order its terms anew)
        assert sympy.expand(again.equations[name] - expr) == 0, name


def test_simulate_hover_and_against_the_true_model(fitted, tmp_path):
    truth = QuadrotorModel.load(write_true_model("fang-chen-buaa", tmp_path / "true.yaml"))
    hover = load_vehicle("fang-chen-buaa").hover_speed
    x0 = np.zeros(12)
    x0[2] = -10.0
    steps = np.full((250, 4), hover)  # 1 s at 4 ms
    still = truth.simulate(x0, steps, dt=0.004)
    assert still.shape == (251, 12)
    assert np.abs(still[-1] - x0).max() < 1e-6  # the true model hovers in place at the hover speed
    # a roll command: more thrust on motors 2 and 3 (left side) rolls right (phi > 0) and drifts east
    roll = np.tile(hover + np.array([-5.0, 5.0, 5.0, -5.0]), (250, 1))
    a, b = truth.simulate(x0, roll, dt=0.004), fitted.simulate(x0, roll, dt=0.004)
    assert a[-1, 6] > 0.1 and a[-1, 4] > 0.0
    assert np.abs(a[:, 6:9] - b[:, 6:9]).max() < 0.01 * np.abs(a[:, 6:9]).max()  # learned model flies alike


def test_arrays_in_and_unfitted_errors():
    ds = synthetic_dataset(50, seed=3)
    t = np.arange(50) * 0.01
    flight = flight_from_arrays(t, ds.xi, ds.u)  # targets differentiated: the edges have none
    assert 0 < len(flight) < 50 and np.isfinite(flight.targets).all()
    with pytest.raises(UserError, match="not fitted"):
        QuadrotorModel().predict(flight)
    with pytest.raises(UserError, match="xi must be"):
        flight_from_arrays(t, ds.xi[:, :6], ds.u)


def test_a_log_without_rotor_speeds_fits_through_its_thrust_curve(tmp_path):
    from dataflash_fixture import fly_synthetic, write_flight

    from identification.dataset import load_dataset

    # 8 s: enough for separate fit, pick and validation blocks (with their gaps) of each flight
    path = write_flight(tmp_path / "no_esc.bin", fly_synthetic(duration=8.0, seed=11), with_esc=False)
    data = load_dataset(path, airborne=False)
    model = QuadrotorModel(engine="sparse", budget=10, seed=0, targets=("az",)).fit(data)
    assert model.motor_ is not None and model.motor_.k >= 0.6
    assert model.scores(data)["az"] > 0.9
    again = QuadrotorModel.load(model.save(tmp_path / "m.yaml"))
    assert (again.motor_.k, again.motor_.voltage_ref) == (model.motor_.k, model.motor_.voltage_ref)
    assert np.allclose(again.predict(data), model.predict(data))
