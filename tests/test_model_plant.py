"""The controller's in-process plant (controller.simulate.ModelPlant) steps a model as the SITL steps its
physics: with the vehicle's true model, one control period after command jumps lands where the SITL does."""

from __future__ import annotations

import numpy as np

from bridge.vehicle import load_vehicle
from controller.simulate import ModelPlant
from identification.true_model import true_model
from sitl.dynamics import Quadrotor


def test_model_plant_steps_the_true_model_as_the_sitl_does():
    """Twenty 4 ms steps of the paper vehicle from a hover with +-150 rad/s command jumps: the model plant
    (true model, the vehicle's motor lag from its closed form) and the SITL agree to rounding (4e-16 rad/s
    measured); with RK4's own stages for the plant's lag (as before) the rates were 3.2e-6 rad/s apart."""
    vehicle = load_vehicle("fang-chen-buaa").with_overrides(sensors="ideal", ground="none")
    plant = ModelPlant(true_model("fang-chen-buaa"), motor_time_constant=vehicle.motor.time_constant,
                       ground=False)
    quad = Quadrotor(vehicle)
    w = vehicle.hover_speed
    quad.reset(position=(0.0, 0.0, -50.0), rotor_speeds=(w,) * 4)
    plant.set_state([0.0, 0.0, -50.0] + [0.0] * 9, [w] * 4)
    rates_apart, speeds_apart = [], []
    for k in range(20):
        cmd = [w + 150.0 * (1 if (k + i) % 3 else -1) for i in range(4)]
        quad.step([vehicle.motor_curve.throttle_for_speed(c) for c in cmd])
        plant.step(np.asarray(quad.commanded_speeds))
        state = plant.observe()
        rates_apart.append(np.abs(np.asarray(state.xi[9:12]) - np.asarray(quad.rates)).max())
        speeds_apart.append(np.abs(np.asarray(state.rotor_speeds) / np.asarray(quad.rotor_speeds) - 1).max())
    assert max(np.abs(quad.rates)) > 0.05  # the jumps turn the vehicle
    assert max(rates_apart) < 1e-12, max(rates_apart)
    assert max(speeds_apart) < 1e-12, max(speeds_apart)
