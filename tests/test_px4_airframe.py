"""`quadsr px4-airframe`: PX4 parameters matched to a vehicle (geometry, thrust model, hover, limits)."""

from __future__ import annotations

import subprocess
import sys

import yaml
from conftest import REPO

from bridge.px4_thrust import normalised_thrust, px4_thrust, thrust_fraction
from bridge.vehicle import load_vehicle
from quadsr.px4_airframe import airframe_for


def params_of(text: str) -> dict[str, float]:
    """The `param set-default NAME VALUE` lines of an airframe file."""
    out = {}
    for line in text.splitlines():
        if line.startswith("param set-default "):
            _, _, name, value = line.split()
            out[name] = float(value)
    return out


def test_paper_vehicle_airframe_matches_the_simulated_vehicle(tmp_path):
    out = tmp_path / "airframe"
    done = subprocess.run([sys.executable, "-m", "quadsr.cli", "px4-airframe", "-o", str(out)], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    text = out.read_text()
    assert ". ${R}etc/init.d/rc.mc_defaults" in text
    p = params_of(text)
    r = 0.225 / 2**0.5  # Quad-X arm 0.225 m
    expected = [(r, r, 1), (-r, -r, 1), (r, -r, -1), (-r, r, -1)]  # PX4 order, +1 = CCW
    for i, (x, y, spin) in enumerate(expected):
        assert abs(p[f"CA_ROTOR{i}_PX"] - x) < 1e-5 and abs(p[f"CA_ROTOR{i}_PY"] - y) < 1e-5
        assert abs(p[f"CA_ROTOR{i}_KM"] - spin * 1.779e-7 / 1.105e-5) < 1e-5
        assert p[f"PWM_MAIN_FUNC{i + 1}"] == 101 + i
    v = load_vehicle("fang-chen-buaa")
    # thrust goes as (1148 u - 141.4)^2: PX4's model fits it best at its quadratic end
    assert p["THR_MDL_FAC"] == 1.0
    u_hover = v.motor_curve.throttle_for_speed(v.hover_speed)
    assert abs(u_hover - 0.6085) < 1e-3
    assert abs(p["MPC_THR_HOVER"] - px4_thrust(1.0, u_hover)) < 1e-3
    # the companion's thrust for hover f1 = 4 w_h^2 is the same hover thrust
    assert abs(normalised_thrust(v, 1.0, 4 * v.hover_speed**2) - p["MPC_THR_HOVER"]) < 1e-3
    assert abs(thrust_fraction(v, 1.0) - 1.0) < 1e-12
    assert p["MPC_TILTMAX_AIR"] == 45.0 and p["MPC_ACC_UP_MAX"] == 4.0


def test_weak_vehicle_is_a_user_error(tmp_path):
    data = yaml.safe_load((REPO / "sitl" / "vehicles" / "fang-chen-buaa.yaml").read_text())
    data["mass"] = 4.0  # thrust-to-weight 1.14
    weak = tmp_path / "weak.yaml"
    weak.write_text(yaml.safe_dump(data))
    done = subprocess.run([sys.executable, "-m", "quadsr.cli", "px4-airframe", "--vehicle", str(weak), "-o",
                           str(tmp_path / "af")], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "thrust-to-weight 1.14 is below 1.2" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "af").exists()
    assert airframe_for(load_vehicle("fang-chen-buaa")).model_name() == "none_quadsr_fang_chen_buaa"
