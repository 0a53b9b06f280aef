"""Readable equations, plausibility flags on a deliberately wrong model, the model report, and `quadsr
identify` end to end (a separate process) on the real PX4 log."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import sympy
from synthetic_data import synthetic_dataset

from bridge.vehicle import load_vehicle
from identification.equation_form import equation_text
from identification.model_file import SYMBOLS, Model
from identification.model_report import write_model_report
from identification.plausibility import plausibility_checks
from identification.quad_model import QuadrotorModel
from identification.true_model import true_model

REPO = Path(__file__).resolve().parent.parent
PX4 = REPO.parent / "shared" / "logs" / "px4_sitl_quad_takeoff.ulg"
S = SYMBOLS


def _wrong_model() -> QuadrotorModel:
    """The true model with three mistakes: no gravity in z'', the roll torque flipped, +55 wx in wx'."""
    exprs = dict(true_model("fang-chen-buaa").expressions)
    exprs["az"] = exprs["az"] - 9.8
    f2 = -(S["u1"] ** 2) + S["u2"] ** 2 + S["u3"] ** 2 - S["u4"] ** 2
    exprs["dwx"] = sympy.expand(exprs["dwx"]) - 2 * 8.33e-05 * f2 + 55 * S["wx"]
    return QuadrotorModel.from_model(Model(exprs))


def test_the_true_model_passes_and_a_wrong_one_is_flagged():
    data = synthetic_dataset(400, seed=2)
    vehicle = load_vehicle("fang-chen-buaa")
    good = QuadrotorModel.from_model(true_model("fang-chen-buaa"))
    assert all(c.ok for c in plausibility_checks(good, data.xi, data.u, vehicle=vehicle))
    flags = {c.name: c for c in plausibility_checks(_wrong_model(), data.xi, data.u, vehicle=vehicle)}
    assert not flags["gravity"].ok and not flags["hover thrust"].ok
    assert not flags["control dwx"].ok and "rolls right" in flags["control dwx"].text
    assert not flags["self-feedback dwx"].ok and "anti-damping" in flags["self-feedback dwx"].text
    assert "+55" in flags["self-feedback dwx"].text
    ok = [n for n, c in flags.items() if c.ok]
    assert {"control dwy", "control dwz", "self-feedback dwy", "self-feedback ax"} <= set(ok)


def test_the_hover_point_is_where_the_log_flew_not_the_origin():
    """A model with a height term (0.01/z, like a ground-effect fit) is judged at the rows' median z."""
    exprs = dict(true_model("fang-chen-buaa").expressions)
    exprs["az"] = exprs["az"] + 0.01 / S["z"]
    data = synthetic_dataset(400, seed=2)
    xi = data.xi.copy()
    xi[:, 2] = -2.0 - 0.1 * (xi[:, 2] - xi[:, 2].mean())  # flying about 2 m up (NED)
    checks = {c.name: c for c in plausibility_checks(QuadrotorModel.from_model(Model(exprs)), xi, data.u)}
    assert checks["gravity"].ok and "+9.8" in checks["gravity"].text  # 9.8 - 0.005 at z = -2 m; inf at 0


def test_equations_read_as_grouped_terms_with_rounded_coefficients():
    lines = {t: dict(equation_text(t, e, 3)) for t, e in true_model("fang-chen-buaa").expressions.items()}
    assert lines["az"]["thrust"] == "- 7.89e-06 f1*cos(phi)*cos(theta)"
    assert lines["az"]["gravity/bias"] == "+ 9.8"
    assert lines["dwx"]["control"] == "+ 8.33e-05 f2"
    assert lines["dwx"]["coupling"] == "- 0.0061 Omega_r*wy - 0.697 wy*wz"
    assert lines["dwx"]["drag"] == "- 0.00474 wx"
    assert "|vbx|" in lines["ax"]["drag"]
    text = " ".join(v for d in lines.values() for v in d.values())
    assert "*(-1)*" not in text and "e-06" in text
    # a long learned expression (as an engine may find): rounded, no '*(-1)*'
    odd = -sympy.Float(1.23456789) * S["u1"] * sympy.sin(sympy.Float(2.3456789) * S["u1"])
    assert equation_text("ax", odd, 3) == [("thrust", "- 1.23 u1*sin(2.35*u1)")]


def test_model_report_has_the_metrics_equations_checks_and_figure(tmp_path):
    data = synthetic_dataset(600, seed=4)
    train, hold = data.split(0.25)
    model = _wrong_model()
    checks = plausibility_checks(model, data.xi, data.u)
    md, png = write_model_report(model, train, hold, tmp_path / "rep", checks)
    text = md.read_text()
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    assert "| dwx | rad/s^2 |" in text and "(coefficients to 3 significant digits)" in text
    assert "FLAG self-feedback dwx" in text and "- control: `- 8.33e-05 f2`" in text
    assert "validation R^2" in text and "![measured and model, residuals](fit.png)" in text


@pytest.mark.skipif(not PX4.is_file(), reason=f"the shared log {PX4} is absent")
def test_identify_a_real_log_end_to_end(tmp_path):
    out = tmp_path / "m.yaml"
    cmd = [
        sys.executable,
        "-m",
        "quadsr.cli",
        "identify",
        str(PX4),
        "-o",
        str(out),
        "--engine",
        "sparse",
        "--budget",
        "5",
        "--targets",
        "az,dwz",
        "--window",
        "19.5:25.3",
        "--no-progress",
    ]
    run = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "dropped" in run.stderr and "outside --window" in run.stderr
    assert "plausibility:" in run.stdout and "az [m/s^2, NED] =" in run.stdout
    assert (tmp_path / "m_report" / "report.md").is_file() and (tmp_path / "m_report" / "fit.png").is_file()
    old = REPO.parent / "shared" / "logs" / "pyulog_sample_auavx21.ulg"
    bad = subprocess.run(
        [*cmd[:4], str(old), "-o", str(tmp_path / "x.yaml")],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert bad.returncode == 2 and "never armed" in bad.stderr and "Traceback" not in bad.stderr


def test_an_equation_with_abs_of_a_rate_is_displayed_not_raised():
    """A learned |wz| beside wx (dwy's wx*|wz| on a flight whose yaw rate keeps its sign) is a coupling line;
    sympy.degree raised PolynomialError on it and `quadsr identify` ended in a traceback."""
    lines = equation_text("dwy", 0.7 * S["wx"] * sympy.Abs(S["wz"]) - 0.0046 * S["wy"])
    groups = {group for group, _ in lines}
    assert "coupling" in groups and "drag" in groups


def test_without_a_vehicle_the_hover_is_the_models_own_not_the_logs_median_speed():
    # an open-loop excitation from altitude falls: its rotors run at about half the hover speed, so the
    # median rotor speed is no hover speed; the true model hovers where the vehicle does (~ the file's)
    model = QuadrotorModel.from_model(true_model("fang-chen-buaa"))
    vehicle = load_vehicle("fang-chen-buaa")
    data = synthetic_dataset(400, seed=2)
    rng = np.random.default_rng(0)
    falling = vehicle.hover_speed * rng.uniform(0.3, 0.9, (400, 4))
    check = {c.name: c for c in plausibility_checks(model, data.xi, falling)}["hover thrust"]
    assert check.ok, check.text
    hover = float(check.text.split("hovers at ")[1].split(" rad/s")[0])
    assert abs(hover / vehicle.hover_speed - 1.0) < 0.01
    # a model whose thrust never balances gravity (z'' without the rotors' term) is flagged
    exprs = dict(true_model("fang-chen-buaa").expressions)
    exprs["az"] = sympy.Float(9.8)
    flat = {c.name: c for c in plausibility_checks(QuadrotorModel.from_model(Model(exprs)), data.xi, falling)}
    assert not flat["hover thrust"].ok and "never balances gravity" in flat["hover thrust"].text
    # one that hovers only far beyond the speeds the log flew (thrust 4x too weak: twice the speed) is flagged
    az = true_model("fang-chen-buaa").expressions["az"]
    thrust = az - az.subs({S[f"u{i}"]: 0 for i in range(1, 5)})  # the rotor terms (negative: up, NED)
    exprs["az"] = 9.8 + thrust / 4
    weak = {c.name: c for c in plausibility_checks(QuadrotorModel.from_model(Model(exprs)), data.xi, falling)}
    assert not weak["hover thrust"].ok and "outside" in weak["hover thrust"].text


def test_an_equation_with_a_root_or_a_quotient_is_shown_as_printed_with_rounded_numbers():
    """The ground effect's 1/(1 - (R/4h)^2) and the frame drag's |v| are no polynomial: such an equation is
    one line as sympy prints it, its numbers rounded (shown so without expanding it first: closed-loop aero's
    hub laws took 46 s to expand); the polynomial wz' of the same vehicle keeps its grouped normal form."""
    lines = {t: equation_text(t, e, 3) for t, e in true_model("fang-chen-aero").expressions.items()}
    for target in ("ax", "ay", "az", "dwx", "dwy"):
        (group, text), = lines[target]
        assert group == "other" and "Abs(" in text, (target, text[:200])
        numbers = re.findall(r"(?<![\w.])\d+\.\d+(?:e-?\d+)?", text)
        digits = [len(n.split("e")[0].replace(".", "").lstrip("0")) for n in numbers]
        assert numbers and max(digits) <= 3, (target, numbers[:20])
    assert dict(lines["dwz"])["coupling"] == "- 0.0219 wx*wy"
