"""The vehicle file's airframe sections: rotors, CG, aerodynamics, thrust models, wind. Bad files are clear
errors naming the file and the key, exit 2 from the command line (a separate process, no traceback)."""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import REPO

from bridge.errors import UserError
from bridge.vehicle import load_vehicle, vehicles_dir

AERO = "fang-chen-aero"


@pytest.fixture(scope="module")
def aero_data() -> dict:
    return yaml.safe_load((vehicles_dir() / f"{AERO}.yaml").read_text())


def write(tmp_path: Path, data: dict) -> Path:
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_the_aero_vehicle_is_the_paper_airframe_with_every_effect_on():
    aero, paper = load_vehicle(AERO), load_vehicle("fang-chen-buaa")
    assert (aero.mass, aero.inertia, aero.thrust_coefficient) == (paper.mass, paper.inertia,
                                                                  paper.thrust_coefficient)
    assert paper.paper_physics and not aero.paper_physics
    assert aero.aero.rotor_drag is not None and aero.aero.translational_lift > 0
    assert all(c > 0 for c in aero.aero.frame_drag) and aero.aero.ground_effect is not None
    assert any(aero.center_of_gravity) and aero.motor_curve.kind == "px4"
    assert not aero.wind.active  # wind comes from `quadsr sitl --wind ...`
    assert aero.motor_curve.max_speed == pytest.approx(1006.6)


def test_a_wide_frame_and_a_weak_rotor_are_expressible(tmp_path, aero_data):
    data = copy.deepcopy(aero_data)
    data["rotors"] = [  # PX4's Iris (x +-0.1515 m, y +-0.245 front / +-0.1875 rear), rotor 2 8 % weak
        {"position": [0.1515, 0.245, 0.0], "direction": "ccw"},
        {"position": [-0.1515, -0.1875, 0.0], "direction": "ccw", "thrust_coefficient": 0.92 * 1.105e-5},
        {"position": [0.1515, -0.245, 0.0], "direction": "cw"},
        {"position": [-0.1515, 0.1875, 0.0], "direction": "cw"},
    ]
    v = load_vehicle(write(tmp_path, data))
    assert v.rotor_set[1].thrust_coefficient == pytest.approx(0.92 * 1.105e-5)
    assert v.rotor_arms[0] == pytest.approx((0.1565, 0.245, -0.01))  # relative to the CG (-0.005, 0, 0.01)


def _mutate(data: dict, path: str, value) -> dict:
    out = copy.deepcopy(data)
    node = out
    keys = path.split(".")
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    node[keys[-1]] = value
    return out


BAD = [
    ("aerodynamics.rotor_drag.k_d", -1e-4, "aerodynamics.rotor_drag.k_d' must be >= 0"),
    ("aerodynamics.translational_lift.k_h", -0.1, "aerodynamics.translational_lift.k_h' must be >= 0"),
    ("aerodynamics.vortex_ring", {"k": 1.0}, "unknown key 'aerodynamics.vortex_ring'"),
    ("aerodynamics.ground_effect.min_height", 0.01, "aerodynamics.ground_effect.min_height' must be > "),
    ("aerodynamics.frame_drag", [0.01, -0.01, 0.01], "aerodynamics.frame_drag' must be >= 0"),
    ("wind", {"turbulence": "moderate"}, "key 'wind.turbulence' is moderate but the steady wind speed is 0"),
    ("wind", {"steady": [5, 0, 0], "turbulence": "hurricane"}, "key 'wind.turbulence' must be one of"),
    ("wind", {"gusts": [{"start": 1.0, "duration": 0.0, "amplitude": [1, 0, 0]}]},
     "key 'wind.gusts[0].duration' must be > 0"),
    ("motor.thr_mdl_fac", 1.5, "key 'motor.thr_mdl_fac' must be within [0, 1]"),
    ("motor.thrust_model", "cubic", "key 'motor.thrust_model' must be one of linear, px4, polynomial"),
    ("rotors", [{"position": [0.2, 0.2, 0.0], "direction": "ccw"}], "'rotors' must be a list of 4 rotors"),
    ("center_of_gravity", [0.1, "x", 0.0], "key 'center_of_gravity[1]' must be a number"),
]


@pytest.mark.parametrize("key,value,expect", BAD, ids=[b[0] + "-" + str(i) for i, b in enumerate(BAD)])
def test_bad_values_name_the_file_and_the_key(tmp_path, aero_data, key, value, expect):
    path = write(tmp_path, _mutate(aero_data, key, value))
    with pytest.raises(UserError) as err:
        load_vehicle(path)
    assert str(path) in str(err.value) and expect in str(err.value), str(err.value)


DEGENERATE = [
    # all four rotors spin the same way: thrust and yaw torque are the same combination
    ([(0.16, 0.16, "ccw"), (-0.16, -0.16, "ccw"), (0.16, -0.16, "ccw"), (-0.16, 0.16, "ccw")],
     "independently"),
    # all on the x axis: no roll torque at all
    ([(0.2, 0.0, "ccw"), (-0.2, 0.0, "ccw"), (0.1, 0.0, "cw"), (-0.1, 0.0, "cw")], "give no roll torque"),
    # two rotors at the same place
    ([(0.16, 0.16, "ccw"), (0.16, 0.16, "ccw"), (0.16, -0.16, "cw"), (-0.16, 0.16, "cw")], "independently"),
]


@pytest.mark.parametrize("layout,expect", DEGENERATE)
def test_degenerate_geometries_are_refused(tmp_path, aero_data, layout, expect):
    data = copy.deepcopy(aero_data)
    data["rotors"] = [{"position": [x, y, 0.0], "direction": d} for x, y, d in layout]
    path = write(tmp_path, data)
    with pytest.raises(UserError) as err:
        load_vehicle(path)
    text = str(err.value)
    assert str(path) in text and "key 'rotors'" in text and "degenerate rotor geometry" in text
    assert expect in text


def test_a_bad_vehicle_file_exits_2_from_the_command_line_without_a_traceback(tmp_path, aero_data):
    path = write(tmp_path, _mutate(aero_data, "aerodynamics.rotor_drag.k_z", -2.0))
    for argv in (["sitl", "--vehicle", str(path), "--no-gcs", "--hil", "udp:127.0.0.1:0"],
                 ["model-from-vehicle", "--vehicle", str(path), "-o", str(tmp_path / "m.yaml")]):
        run = subprocess.run([sys.executable, "-m", "quadsr.cli", *argv], capture_output=True, text=True,
                             timeout=60, cwd=REPO)
        assert run.returncode == 2, run.stderr
        assert "aerodynamics.rotor_drag.k_z" in run.stderr and str(path) in run.stderr
        assert "Traceback" not in run.stderr


@pytest.mark.parametrize("flags,expect", [
    (["--turbulence", "light"], "Dryden turbulence needs a wind speed"),
    (["--wind", "5,0"], "--wind must be three numbers N,E,D in m/s"),
    (["--gust", "1,2,3"], "--gust must be five numbers T0,DURATION,N,E,D"),
    (["--gust=-1,2,3,0,0", "--wind", "1,0,0"], "key 'wind.gusts[0]' needs start >= 0 s"),
])
def test_bad_wind_flags_exit_2(flags, expect):
    run = subprocess.run([sys.executable, "-m", "quadsr.cli", "sitl", "--no-gcs", "--hil", "udp:127.0.0.1:0",
                          *flags], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert run.returncode == 2 and expect in run.stderr and "Traceback" not in run.stderr, run.stderr


@pytest.mark.parametrize("value", ["-1", "nan", "2e6"])
def test_a_bad_lockstep_spin_exits_2(value):
    argv = ["sitl", "--no-gcs", "--hil", "udp:127.0.0.1:0", f"--lockstep-spin-us={value}"]
    run = subprocess.run([sys.executable, "-m", "quadsr.cli", *argv], capture_output=True, text=True,
                         timeout=60, cwd=REPO)
    assert run.returncode == 2 and "--lockstep-spin-us must be" in run.stderr, run.stderr
    assert "Traceback" not in run.stderr
