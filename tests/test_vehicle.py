"""The vehicle file: the paper's numbers, the motor curve, validation errors naming file and key."""

from __future__ import annotations

import copy
import hashlib
import math
from pathlib import Path

import pytest
import yaml

from bridge.errors import UserError
from bridge.vehicle import (
    MotorCurve,
    list_vehicles,
    load_vehicle,
    resolve_vehicle_path,
    vehicle_sha256,
    vehicles_dir,
)

DEFAULT = "fang-chen-buaa"


@pytest.fixture(scope="module")
def default_data() -> dict:
    return yaml.safe_load((vehicles_dir() / f"{DEFAULT}.yaml").read_text())


def write(tmp_path: Path, data: dict, name: str = "x.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def test_default_vehicle_has_the_papers_numbers():
    v = load_vehicle(DEFAULT)
    assert v.name == DEFAULT
    assert v.mass == 1.4 and v.gravity == 9.8
    assert v.inertia == ((0.0211, 0.0, 0.0), (0.0, 0.0219, 0.0), (0.0, 0.0, 0.0366))
    assert v.arm_length == 0.225
    assert v.thrust_coefficient == 1.105e-5 and v.moment_coefficient == 1.779e-7
    assert v.motor.time_constant == 0.02
    assert v.motor.curve_slope == 1148.0 and v.motor.curve_offset == -141.4
    assert v.motor.rotor_inertia == 1.287e-4
    assert v.drag.body_quadratic == (0.055, 0.055, 0.055)
    assert v.ground == "plane"
    assert v.initial.position == (0.0, 0.0, 0.0) and v.initial.yaw == 0.0
    assert v.simulation.physics_step == 0.004 and v.simulation.substeps == 1
    assert (v.home.lat, v.home.lon, v.home.alt) == (47.397742, 8.545594, 488.0)
    assert v.sensors.preset == "realistic"
    assert v.source_path == resolve_vehicle_path(DEFAULT)
    assert math.isclose(v.mixer_gain, math.sqrt(2) / 2 * 0.225 * 1.105e-5)


def test_hover_speed_and_motor_curve():
    v = load_vehicle(DEFAULT)
    curve = v.motor_curve
    assert v.hover_speed == pytest.approx(557.14, abs=0.01)
    assert MotorCurve.hover_speed(1.4, 9.8, 1.105e-5) == v.hover_speed
    assert curve.max_speed == pytest.approx(1006.6)
    assert curve.speed_for_throttle(1.0) == pytest.approx(1006.6)
    assert curve.speed_for_throttle(0.0) == 0.0  # wb < 0: clipped to 0
    assert curve.speed_for_throttle(1.5) == pytest.approx(1006.6)
    assert curve.speed_for_throttle(-1.0) == 0.0
    sigma = curve.throttle_for_speed(v.hover_speed)
    assert sigma == pytest.approx((557.142 + 141.4) / 1148, abs=1e-5)
    assert curve.speed_for_throttle(sigma) == pytest.approx(v.hover_speed, rel=1e-12)
    # The inverse: w <= 0 gives the largest throttle that still gives 0 rad/s.
    assert curve.throttle_for_speed(0.0) == pytest.approx(141.4 / 1148)
    assert curve.speed_for_throttle(curve.throttle_for_speed(0.0)) == pytest.approx(0.0, abs=1e-12)
    assert curve.throttle_for_speed(-50.0) == curve.throttle_for_speed(0.0)
    assert curve.throttle_for_speed(2000.0) == 1.0
    for w in (0.0, 100.0, 557.0, 1000.0):
        assert curve.speed_for_throttle(curve.throttle_for_speed(w)) == pytest.approx(w, abs=1e-9)


def test_bare_name_resolves_from_any_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert load_vehicle(DEFAULT).name == DEFAULT
    assert DEFAULT in list_vehicles()
    path = resolve_vehicle_path(DEFAULT)
    assert vehicle_sha256(DEFAULT) == hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_path_loads_too(tmp_path, default_data):
    path = write(tmp_path, default_data, "copy.yaml")
    v = load_vehicle(path)
    assert v.mass == 1.4 and v.source_path == path
    assert load_vehicle(str(path)).mass == 1.4


def test_missing_file_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="not found") as err:
        load_vehicle(tmp_path / "nope.yaml")
    assert "nope.yaml" in str(err.value)
    with pytest.raises(UserError, match="fang-chen-buaa"):  # the hint lists the bundled names
        load_vehicle("no-such-vehicle")


def _mutated(data: dict, dotted: str, value) -> dict:
    out = copy.deepcopy(data)
    *parents, leaf = dotted.split(".")
    node = out
    for p in parents:
        node = node[p]
    if value is _DELETE:
        del node[leaf]
    else:
        node[leaf] = value
    return out


_DELETE = object()


@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [
        ("mass", _DELETE, "key 'mass' is missing"),
        ("mass", -1.0, "key 'mass' must be > 0, got -1"),
        ("mass", 0, "key 'mass' must be > 0, got 0"),
        ("mass", "heavy", "key 'mass' must be a number"),
        ("motor.time_constant", -1, "key 'motor.time_constant' must be > 0, got -1"),
        ("motor.curve_slope", 0.0, "key 'motor.curve_slope' must be > 0"),
        ("motor.rotor_inertia", _DELETE, "key 'motor.rotor_inertia' is missing"),
        ("motor.spin", 3, "unknown key 'motor.spin'"),
        ("colour", "red", "unknown key 'colour'"),
        ("inertia", [0.0211, -0.0219, 0.0366], "key 'inertia' must be positive definite"),
        ("inertia", [[0.02, 0.03, 0], [0.03, 0.02, 0], [0, 0, 0.03]], "must be positive definite"),
        ("inertia", [[0.02, 0.001, 0], [0.0, 0.02, 0], [0, 0, 0.03]], "key 'inertia' must be symmetric"),
        ("inertia", [0.02, 0.02], "key 'inertia' must be 3 diagonal values"),
        ("drag.body_quadratic", -0.1, "key 'drag.body_quadratic' must be >= 0"),
        ("ground", "lava", "key 'ground' must be one of plane, none"),
        ("simulation.physics_step", 0.003, "key 'simulation.physics_step' must divide"),
        ("simulation.physics_step", 0.008, "key 'simulation.physics_step' must divide"),
        ("initial.position", [0, 0, 5], "key 'initial.position' has z = 5"),
        ("initial.position", [0, 0], "key 'initial.position' must be a list of 3 numbers"),
        ("sensors.preset", "noisy", "key 'sensors.preset' must be one of realistic, ideal"),
        ("sensors.gyro.noise", -0.1, "key 'sensors.gyro.noise' must be >= 0"),
        ("sensors.gps.satellites", 2.5, "key 'sensors.gps.satellites' must be an integer"),
        ("home.lat", 91.0, "key 'home.lat'"),
        ("motor", 5, "key 'motor' must be a mapping"),
    ],
)
def test_each_mistake_names_the_file_and_the_key(tmp_path, default_data, key, value, expected):
    path = write(tmp_path, _mutated(default_data, key, value))
    with pytest.raises(UserError) as err:
        load_vehicle(path)
    text = str(err.value)
    assert text.startswith(f"vehicle file {path}: "), text
    assert expected in text


def test_yaml_syntax_error_gives_the_line(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("name: x\nmass: [1.4\ngravity: 9.8\n")
    with pytest.raises(UserError, match=r"YAML syntax error at line \d+") as err:
        load_vehicle(path)
    assert str(path) in str(err.value)


def test_empty_and_non_mapping_files(tmp_path):
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    with pytest.raises(UserError, match="empty"):
        load_vehicle(empty)
    listing = tmp_path / "list.yaml"
    listing.write_text("- 1\n- 2\n")
    with pytest.raises(UserError, match="top level must be a mapping"):
        load_vehicle(listing)


def test_finer_physics_step_and_full_inertia_matrix(tmp_path, default_data):
    data = _mutated(default_data, "simulation.physics_step", 0.001)
    data["inertia"] = [[0.0211, 0.001, 0.0], [0.001, 0.0219, 0.0], [0.0, 0.0, 0.0366]]
    data["drag"]["body_quadratic"] = [0.05, 0.06, 0.07]
    v = load_vehicle(write(tmp_path, data))
    assert v.simulation.substeps == 4
    assert v.inertia[0][1] == 0.001
    assert v.drag.body_quadratic == (0.05, 0.06, 0.07)


def test_overrides():
    v = load_vehicle(DEFAULT)
    w = v.with_overrides(ground="none", initial_position=(1.0, 2.0, -50.0), sensors="ideal", seed=7)
    assert w.ground == "none" and w.initial.position == (1.0, 2.0, -50.0)
    assert w.sensors.preset == "ideal" and w.simulation.seed == 7
    eff = w.sensors.effective()
    assert eff.accel.noise == (0, 0, 0) and eff.accel.bias == (0, 0, 0)
    assert eff.gyro.noise == (0, 0, 0) and eff.gps.horizontal_noise == 0 and eff.baro.noise == 0
    assert eff.mag.earth_field == v.sensors.mag.earth_field  # the field itself is physics, not noise
    assert v.ground == "plane" and v.sensors.preset == "realistic"  # the original is unchanged
    assert v.sensors.effective() is v.sensors
    with pytest.raises(UserError, match="ground must be one of"):
        v.with_overrides(ground="water")
    with pytest.raises(UserError, match="sensors must be one of"):
        v.with_overrides(sensors="perfect")
    with pytest.raises(UserError, match="seed"):
        v.with_overrides(seed=-3)
    with pytest.raises(UserError, match="below the ground"):
        v.with_overrides(initial_position=(0.0, 0.0, 3.0))
    assert v.with_overrides(ground="none", initial_position=(0.0, 0.0, 3.0)).initial.position[2] == 3.0
