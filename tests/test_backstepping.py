"""The backstepping controller: the paper's closed-loop error dynamics at sample states, the real-vehicle
limits, and closed-loop flights in the in-process simulator (the model's equations, the SITL's dynamics)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import sympy

from bridge.errors import UserError
from bridge.rotations import rotation_matrix
from controller.backstepping import BacksteppingController, ModelErrorObserver
from controller.gains import BacksteppingGains, gains_from_dict, load_gains
from controller.plugin import Reference, VehicleState
from controller.simulate import ModelPlant, simulate
from controller.trajectories import load_trajectory
from identification.kinematics import euler_rates
from identification.model_file import SYMBOLS as S
from identification.paper_model import paper_model as paper_learned_model

STATE = ("x", "y", "z", "vx", "vy", "vz", "phi", "theta", "psi", "wx", "wy", "wz")


@pytest.fixture(scope="module")
def ctl(model, vehicle):
    return BacksteppingController(model, vehicle)


def paper_model() -> dict[str, sympy.Expr]:
    """The paper's learned equations (Section II-B), zeta_4..zeta_12 in our symbols."""
    return dict(paper_learned_model().expressions)


def _samples(seed: int, n: int, att: float = 0.15, rates: float = 0.4, yaw: float = 0.1, err: float = 1.0):
    """Airborne states near hover and references within the PI's linear range (no limit active)."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        xi = np.zeros(12)
        xi[0:3] = rng.uniform(-1, 1, 3) + [0, 0, -3.0]
        xi[3:6] = rng.uniform(-0.8, 0.8, 3)
        xi[6:9] = rng.uniform(-att, att, 3)
        xi[9:12] = rng.uniform(-rates, rates, 3)
        small = np.array([1.0, 1.0, 0.1]) * err  # the z design's gains are high: keep its request in range
        ref = Reference(
            position=xi[0:3] + rng.uniform(-0.3, 0.3, 3) * small,
            velocity=xi[3:6] + rng.uniform(-0.3, 0.3, 3) * small,
            acceleration=rng.uniform(-0.5, 0.5, 3), jerk=rng.uniform(-0.5, 0.5, 3),
            snap=rng.uniform(-0.5, 0.5, 3),
            yaw=xi[8] + rng.uniform(-yaw, yaw), yaw_rate=rng.uniform(-2 * yaw, 2 * yaw),
            yaw_acceleration=rng.uniform(-2 * yaw, 2 * yaw))
        speeds = np.full(4, 557.0) + rng.uniform(-20, 20, 4)
        yield xi, speeds, ref


def _converged_command(controller, xi, speeds, ref):
    """Update until the measured rotor speeds equal the command (the odd-in-u terms are then exact)."""
    controller.reset()
    for _ in range(30):
        cmd = controller.update(1.0, VehicleState(xi=xi, rotor_speeds=speeds), ref)
        if np.allclose(cmd.rotor_speeds, speeds, rtol=0, atol=1e-10):
            break
        speeds = cmd.rotor_speeds
    return cmd, speeds


def test_outer_loop_gives_the_papers_error_dynamics(ctl, model):
    g = ctl.gains
    for xi, speeds, ref in _samples(0, 25):
        ctl.reset()
        cmd = ctl.update(1.0, VehicleState(xi=xi, rotor_speeds=speeds), ref)
        info = cmd.info
        assert not info["limited"] and info["outer_ok"]
        xs = xi.copy()
        xs[6], xs[7] = info["phi_d"], info["theta_d"]
        u = math.sqrt(info["f1_d"] / 4.0)
        ax, ay, az = model.accelerations(xs, np.full(4, u))[:3]
        e, de = ref.position - xi[0:3], ref.velocity - xi[3:6]
        # x'' = k_px e_x' + k_ix e_x + x_d'', i.e. e'' + k_p e' + k_i e = 0
        # (to the Newton tolerance: a step under 2e-4 rad is accepted, leaving < 1e-6 m/s^2)
        assert math.isclose(ax, g.k_px * de[0] + g.k_ix * e[0] + ref.acceleration[0], abs_tol=1e-6)
        assert math.isclose(ay, g.k_py * de[1] + g.k_iy * e[1] + ref.acceleration[1], abs_tol=1e-6)
        ex2, ey2 = ref.acceleration[0] - ax, ref.acceleration[1] - ay
        assert abs(ex2 + g.k_px * de[0] + g.k_ix * e[0]) < 1e-6
        assert abs(ey2 + g.k_py * de[1] + g.k_iy * e[1]) < 1e-6
        assert math.isclose(az, info["gamma_d"][0], abs_tol=1e-6)  # with it, z'' as the z design asks


def test_outer_loop_on_the_papers_learned_model(vehicle):
    c = BacksteppingController(paper_model(), vehicle)
    g = c.gains
    fn = sympy.lambdify([S[n] for n in STATE] + [S[f"u{i}"] for i in range(1, 5)],
                        [paper_model()["ax"], paper_model()["ay"]])
    for xi, speeds, ref in _samples(1, 10):
        c.reset()
        info = c.update(1.0, VehicleState(xi=xi, rotor_speeds=speeds), ref).info
        xs = xi.copy()
        xs[6], xs[7] = info["phi_d"], info["theta_d"]
        ax, ay = fn(*xs, *speeds)  # u frozen at its measured value, as the paper does
        e, de = ref.position - xi[0:3], ref.velocity - xi[3:6]
        assert math.isclose(ax, g.k_px * de[0] + g.k_ix * e[0] + ref.acceleration[0], abs_tol=1e-9)
        assert math.isclose(ay, g.k_py * de[1] + g.k_iy * e[1] + ref.acceleration[1], abs_tol=1e-9)


def test_inner_loop_lyapunov_derivative_is_negative_definite(ctl, model):
    c = ctl.gains.c_gains
    rng = np.random.default_rng(5)
    for xi, speeds, ref in _samples(2, 25, att=0.02, rates=0.05, yaw=0.005, err=0.05):
        # attitude near the outer loop's phi_d, theta_d, so the designed torques are within the motors' range
        ctl.reset()
        info0 = ctl.update(1.0, VehicleState(xi=xi, rotor_speeds=speeds), ref).info
        xi[6:8] = [info0["phi_d"], info0["theta_d"]] + rng.uniform(-0.02, 0.02, 2)
        cmd, u = _converged_command(ctl, xi, speeds, ref)
        info = cmd.info
        assert not cmd.saturated
        acc = model.accelerations(xi, u)  # the model's own z'' and w' under the commanded speeds
        w, dw = xi[9:12], acc[3:6]
        eul = euler_rates(xi[6], xi[7], w)
        h = 1e-6  # Euler accelerations by differentiating the known transform numerically, not symbolically
        ep = euler_rates(xi[6] + h * eul[0], xi[7] + h * eul[1], w + h * dw)
        em = euler_rates(xi[6] - h * eul[0], xi[7] - h * eul[1], w - h * dw)
        gamma = [acc[2], *((ep - em) / (2 * h))]
        s = [xi[2], xi[6], xi[7], xi[8], xi[5], *eul]
        sd = [ref.position[2], info["phi_d"], info["theta_d"], ref.yaw]
        sd1 = [ref.velocity[2], info["dphi_d"], info["dtheta_d"], ref.yaw_rate]
        sd2 = [ref.acceleration[2], info["ddphi_d"], info["ddtheta_d"], ref.yaw_acceleration]
        for i in range(4):
            e, de = sd[i] - s[i], sd1[i] - s[i + 4]
            delta = sd1[i] + c[i] * e - s[i + 4]
            ddelta = sd2[i] + c[i] * de - gamma[i]
            w_dot = e * de + delta * ddelta
            designed = -c[i] * e**2 - c[i + 4] * delta**2
            assert designed < 0
            assert abs(w_dot - designed) <= 1e-6 * (abs(designed) + 1e-6), (i, w_dot, designed)


def test_far_reference_keeps_tilt_and_arcsine_in_range(vehicle, ctl):
    xi = np.zeros(12)
    xi[2] = -5.0
    ref = Reference(position=np.array([0.0, 100.0, -5.0]))
    for c in (ctl, BacksteppingController(paper_model(), vehicle)):
        c.reset()
        cmd = c.update(1.0, VehicleState(xi=xi, rotor_speeds=np.full(4, 557.0)), ref)
        phi, theta = cmd.info["phi_d"], cmd.info["theta_d"]
        tilt = math.degrees(math.acos(math.cos(phi) * math.cos(theta)))
        assert math.isfinite(phi) and tilt <= c.gains.max_tilt_deg + 1e-9
        assert phi > 0.3  # still leaning towards +y (east)
        assert np.all(cmd.rotor_speeds >= 0) and np.all(cmd.rotor_speeds <= c.w_max)


def test_a_far_height_asks_the_vertical_limit_not_the_motor_limits(ctl, model):
    """A 50 m climb or sink is flown at the outer loop's vertical limits: no motor saturates (thrust and
    attitude keep their room); only a request beyond the motors (a huge yaw acceleration) saturates."""
    xi = np.zeros(12)
    xi[2] = -10.0
    up, down = ctl.outer_loop.vertical_limits()
    for z_d, limit in ((-60.0, up), (40.0, down)):
        ctl.reset()
        cmd = ctl.update(1.0, VehicleState(xi=xi, rotor_speeds=np.full(4, 557.0)),
                         Reference(position=np.array([0.0, 0.0, z_d])))
        assert not cmd.saturated and np.all(cmd.rotor_speeds > 0.0) and np.all(cmd.rotor_speeds < ctl.w_max)
        az = model.accelerations(xi, cmd.rotor_speeds)[2]
        assert az == pytest.approx(limit, abs=1e-6)
    ctl.reset()
    cmd = ctl.update(1.0, VehicleState(xi=xi, rotor_speeds=np.full(4, 557.0)),
                     Reference(position=xi[:3].copy(), yaw_acceleration=1e5))
    assert cmd.saturated and cmd.info["allocation"] == "yaw"
    assert np.all(cmd.rotor_speeds >= 0.0) and np.all(cmd.rotor_speeds <= ctl.w_max)


def test_case2_from_the_ground(ctl, plant):
    tr = load_trajectory("case2")
    r = simulate(ctl, tr, plant, 10.0, keep_info=True)
    e = r.error
    # the floors: within 5 cm of (2, 4, z_d) by 4 s and RMS after 5 s under 1 cm
    assert np.all(e[r.t >= 4.0] < 0.05)
    assert r.rms_after(5.0) < 0.01
    assert r.rms_after(5.0) < 1e-4  # measured: 5 um
    # on the ground: level take-off, then no limit but the tilt limit
    on = [k for k, info in enumerate(r.infos) if info["on_ground"]]
    assert on and r.t[on[-1]] < 0.5  # lifted off within half a second
    for k in on:
        tilt = math.acos(math.cos(r.infos[k]["phi_d"]) * math.cos(r.infos[k]["theta_d"]))
        assert math.degrees(tilt) <= ctl.gains.ground_tilt_deg + 1e-9
    assert np.all(r.xi[:, 2] <= 1e-5)  # never into the ground (as the SITL's contact: < 2 um for one step)
    assert r.max_tilt_deg < ctl.gains.max_tilt_deg + 3.0
    assert float(np.median(r.step_time)) < 1e-3  # measured ~0.1 ms (the floor 0.2 ms: see report)


def test_case1_with_the_reference_starting_3_7_m_away(ctl, plant):
    tr = load_trajectory("case1")
    r = simulate(ctl, tr, plant, 20.0, keep_info=True)
    e = r.error
    assert e[0] > 3.6
    assert r.rms_after(5.0) < 0.01
    assert r.rms_after(5.0) < 1e-4  # measured: 2.3 um (6 um without the model-error observer)
    # a sane transient: the commanded tilt stays within its limit, no overshoot past the reference
    tilts = [math.degrees(math.acos(math.cos(i["phi_d"]) * math.cos(i["theta_d"]))) for i in r.infos]
    assert max(tilts) <= ctl.gains.max_tilt_deg + 1e-9
    assert r.max_tilt_deg < ctl.gains.max_tilt_deg + 3.0
    settled = np.argmax(e < 0.05)
    assert r.t[settled] < 3.5 and np.all(e[settled:] < 0.05)
    assert np.max(e) < e[0] + 0.5  # the reference runs away at 1.06 m/s while the vehicle speeds up
    assert not r.saturated[r.t > 5].any()


def test_analytic_derivatives_beat_the_command_filter(model, vehicle, plant):
    tr = load_trajectory("case1")
    rms = {}
    for mode in ("analytic", "filter"):
        c = BacksteppingController(model, vehicle, BacksteppingGains(derivative_mode=mode))
        rms[mode] = simulate(c, tr, plant, 10.0).rms_after(5.0)
    assert rms["analytic"] < 0.05 * rms["filter"]  # measured: 4 um against 1.0 mm (0.5 mm, observer off)


def test_integral_anti_windup(model, vehicle, plant):
    g = BacksteppingGains(k_int=8.0, integral_zone=0.3, max_integral_accel=0.2)
    c = BacksteppingController(model, vehicle, g)
    r = simulate(c, load_trajectory("case2"), plant, 6.0, keep_info=True)
    integ = np.array([i["integral"] for i in r.infos])
    horizontal = np.linalg.norm(r.ref_position[:, :2] - r.xi[:, :2], axis=1)
    first_near = int(np.argmax(horizontal < g.integral_zone))
    assert first_near > 0 and np.all(integ[:first_near] == 0.0)  # nothing while far or on the ground
    assert np.any(integ != 0.0)
    assert np.all(np.abs(integ) * g.k_int <= g.max_integral_accel + 1e-12)
    assert np.all(r.error[r.t >= 4.0] < 0.05)


def test_outer_loop_integrator_rules():
    from controller.outer_loop import OuterLoop

    g = BacksteppingGains(k_int=4.0, integral_zone=0.5, max_integral_accel=0.2)
    loop = OuterLoop(g, 9.8)
    zero = [0.0, 0.0, 0.0]
    az = (0.0, 0.0, 0.0)

    def step(ref_pos, ref_acc=zero, on_ground=False):
        return loop.update(0.01, [0.0, 0.0, -1.0], zero, ref_pos, zero, ref_acc, zero, zero, az, on_ground)

    assert step([0.55, 0.0, -1.0]).integral == (0.0, 0.0)  # outside the zone (and not limited)
    assert step([0.2, 0.0, -1.0]).integral == pytest.approx((0.002, 0.0))  # inside: integrates e dt
    assert step([0.2, 0.0, -1.0], ref_acc=[50.0, 0.0, 0.0]).limited  # the tilt limit is hit ...
    assert step([0.2, 0.0, -1.0]).integral == pytest.approx((0.004, 0.0))  # ... so that step did not count
    assert step([0.2, 0.0, -1.0]).integral == pytest.approx((0.006, 0.0))
    for _ in range(200):
        out = step([0.4, -0.1, -1.0])
    assert out.integral[0] * g.k_int == pytest.approx(g.max_integral_accel)  # clamped
    assert step([0.4, 0.0, -1.0], on_ground=True).integral == (0.0, 0.0)  # reset on the ground
    # the error fed to k_i is clipped: 50 m away asks no more than a 2 m error would (then the tilt limit)
    far = step([50.0, 0.0, -1.0])
    assert far.limited and math.hypot(far.accel[0], far.accel[1]) <= math.tan(math.radians(35.0)) * 9.8 + 1e-9


def test_on_the_sitl_dynamics(model, vehicle):
    from sitl.dynamics import Quadrotor  # test only: the controller package never imports sitl

    class SitlPlant:
        def __init__(self):
            self.q = Quadrotor(vehicle)

        def reset(self):
            self.q.reset(position=(0.0, 0.0, 0.0), yaw=0.0)

        def step(self, speeds):
            self.q.step([vehicle.motor_curve.throttle_for_speed(float(w)) for w in speeds])

        def observe(self):
            q = self.q
            return VehicleState(xi=np.array([*q.position, *q.velocity, *q.euler, *q.rates]),
                                rotor_speeds=np.array(q.rotor_speeds))

    c = BacksteppingController(model, vehicle)
    r = simulate(c, load_trajectory("case2"), SitlPlant(), 8.0)
    assert np.all(r.error[r.t >= 4.0] < 0.05)
    assert r.rms_after(5.0) < 1e-3
    final = r.xi[-1, :3]
    assert np.allclose(final[:2], [2.0, 4.0], atol=1e-3) and abs(final[2] - (-0.3 * r.t[-1])) < 1e-3


def test_gains_yaml(tmp_path):
    p = tmp_path / "gains.yaml"
    p.write_text("c1: 10\nk_px: 6\nmax_tilt_deg: 30\nderivative_mode: filter\n")
    g = load_gains(p)
    assert g.c[0] == 10.0 and g.c[1] == 28.0 and g.k_px == 6.0 and g.max_tilt_deg == 30.0
    assert g.derivative_mode == "filter"
    for text, words in (("c9: 1\n", "unknown key 'c9'"), ("k_px: -1\n", "k_px"), ("c2: fast\n", "'c2'"),
                        ("derivative_mode: guess\n", "derivative_mode"), ("k_int: 1000\n", "k_int"),
                        ("observer_rate: -1\n", "observer_rate"),
                        ("observer_angular_rate: 40\n", "observer_angular_rate")):
        p.write_text(text)
        with pytest.raises(UserError) as err:
            load_gains(p)
        assert str(p) in str(err.value) and words in str(err.value)
    assert gains_from_dict({}).c == (11.52, 28.00, 16.63, 6.54, 8.40, 27.50, 15.54, 5.49)


def test_refuses_a_model_it_cannot_invert(model, vehicle):
    exprs = dict(model.expressions)
    exprs["az"] = 9.8 + 0 * S["vz"]
    with pytest.raises(UserError, match="az does not depend on the motors"):
        BacksteppingController(exprs, vehicle)


def _thrust_scaled(model, k: float) -> dict[str, sympy.Expr]:
    """The model's expressions with the thrust coefficient k times the truth's (u_i -> sqrt(k) u_i in
    x'', y'', z''): a learned model's typical error."""
    sub = {S[f"u{i}"]: sympy.sqrt(k) * S[f"u{i}"] for i in range(1, 5)}
    exprs = dict(model.expressions)
    for name in ("ax", "ay", "az"):
        exprs[name] = exprs[name].xreplace(sub)
    return exprs


OBSERVER_OFF = BacksteppingGains(observer_rate=0.0, observer_angular_rate=0.0)


@pytest.mark.parametrize("case, duration", [("case2", 8.0), ("case1", 10.0)])
def test_a_wrong_thrust_coefficient_costs_nothing_with_the_model_error_observer(model, vehicle, plant, case,
                                                                                 duration):
    tr = load_trajectory(case)
    reference = simulate(BacksteppingController(model, vehicle), tr, plant, duration).rms_after(5.0)
    wrong = _thrust_scaled(model, 1.005)  # 0.5 %: the paper-train model is off by 4e-5, noisy data by 0.5 %
    with_observer = simulate(BacksteppingController(wrong, vehicle), tr, plant, duration).rms_after(5.0)
    raw = BacksteppingController(wrong, vehicle, OBSERVER_OFF)
    without = simulate(raw, tr, plant, duration).rms_after(5.0)
    assert with_observer <= 1.2 * reference  # measured 1.01 x (Case II), 1.05 x (Case I)
    assert without > 50.0 * reference  # measured 0.5 mm: 80 x, 150 x


def test_the_observer_finds_an_unmodelled_force_and_leaves_an_exact_model_alone(model, vehicle):
    tr = load_trajectory("case2")
    # an exact model with instantaneous motors: the observer sees nothing but the trapezoid rule's error
    exact = simulate(BacksteppingController(model, vehicle), tr, ModelPlant(model), 6.0, keep_info=True)
    d = np.array([i["model_error"] for i in exact.infos])
    assert np.abs(d).max() < 2e-3 and np.abs(d[exact.t > 3.0]).max() < 1e-4  # measured 7e-4, 2e-6
    # a vehicle pushed by a constant force and torque the model does not know (wind, an offset payload)
    pushed = dict(model.expressions)
    extra = {"ax": 0.05, "ay": -0.03, "az": 0.2, "dwx": 0.1, "dwy": 0.0, "dwz": -0.02}
    for name, value in extra.items():
        pushed[name] = pushed[name] + value
    plant = ModelPlant(pushed, motor_time_constant=vehicle.motor.time_constant)
    r = simulate(BacksteppingController(model, vehicle), tr, plant, 8.0, keep_info=True)
    np.testing.assert_allclose(r.infos[-1]["model_error"], list(extra.values()), atol=1e-4)
    assert r.rms_after(5.0) < 5e-5  # measured 16 um; 15 mm without the observer
    off = simulate(BacksteppingController(model, vehicle, OBSERVER_OFF), tr, plant, 8.0)
    assert off.rms_after(5.0) > 100 * r.rms_after(5.0)


def test_an_earth_fixed_push_is_rejected_while_the_heading_swings(model, vehicle):
    """A steady wind's drag is a force fixed in NED: the observer keeps the part across the thrust axis in
    NED, so the figure-eight with a swinging heading (+-0.5 rad) is flown as without the push (the push
    slows the take-off's approach, so after 8 s: 18 um, 14 um without it). Kept in the body frame, the
    estimate turned away with the heading: 5.9 mm RMS after 5 s of a 20 s flight (28 um without the push)."""
    tr = load_trajectory(str(Path(__file__).resolve().parent.parent / "bench" / "trajectories"
                             / "figure8-yaw.yaml"))
    pushed = dict(model.expressions)
    pushed["ax"] = pushed["ax"] + 1.0  # m/s^2 toward north, e.g. 5 m/s of wind on this vehicle's drag
    pushed["ay"] = pushed["ay"] - 0.5
    plant = ModelPlant(pushed, motor_time_constant=vehicle.motor.time_constant)
    r = simulate(BacksteppingController(model, vehicle), tr, plant, 12.0, keep_info=True)
    late = r.t > 8.0
    d = np.array([i["model_error"] for i in r.infos])[late, :3]
    np.testing.assert_allclose(d.mean(axis=0), [1.0, -0.5, 0.0], atol=2e-3)
    assert r.rms_after(8.0) < 1e-4


def test_model_error_observer_filter_frame_clamp_and_nan():
    g = 9.8
    k = 1e-5
    exprs = {"ax": 0 * S["vx"], "ay": 0 * S["vy"], "az": g - k * (S["u1"] ** 2 + S["u2"] ** 2 + S["u3"] ** 2
                                                                   + S["u4"] ** 2),
             "dwx": 0 * S["wx"], "dwy": 0 * S["wy"], "dwz": 0 * S["wz"]}
    hover = math.sqrt(g / (4 * k))
    obs = ModelErrorObserver(exprs, rate=10.0, angular_rate=10.0, max_accel=1.0, max_angular=5.0)
    dt = 0.004
    xi = [0.0] * 12
    xi[7] = 0.3  # pitched: the body frame is not NED
    true_d = np.array([0.2, -0.1, 0.3])  # NED, what the model misses (constant)
    for _ in range(250):  # 1 s = 10 time constants
        obs.start_step(list(xi), [hover] * 4)
        xi[3:6] = (np.array(xi[3:6]) + true_d * dt).tolist()  # the vehicle's velocity change, hover thrust
        xi[9] += 0.05 * dt  # and an unmodelled roll acceleration
        d_ned, rate = obs.end_step(dt, list(xi))
    np.testing.assert_allclose(d_ned[:3], true_d, atol=1e-4)  # e^-10 of it left
    np.testing.assert_allclose(d_ned[3:], [0.05, 0.0, 0.0], atol=1e-5)
    r = rotation_matrix(xi[6], xi[7], xi[8])
    b3 = r[:, 2]  # the body z axis in NED
    # split as d_T b3 (turns with the body: a thrust error) + (d_Ex, d_Ey, 0) (stays put in NED: wind)
    d_t = true_d[2] / b3[2]
    np.testing.assert_allclose(obs.value[:3], [*(true_d[:2] - d_t * b3[:2]), d_t], atol=1e-4)
    w = np.array(xi[9:12])
    np.testing.assert_allclose(rate, obs.value[2] * (r @ np.cross(w, [0.0, 0.0, 1.0])),
                               atol=1e-12)  # d' = d_T R (w x e3)
    # first-order low-pass at the rate: 1 - e^-1 of a step change after 1/rate
    obs.reset()
    assert obs.end_step(dt, list(xi))[0] == [0.0] * 6  # nothing without a started step
    for _ in range(25):
        obs.start_step(list(xi), [hover] * 4)
        xi[5] += 0.3 * dt
        d_ned, _ = obs.end_step(dt, list(xi))
    assert np.linalg.norm(d_ned[:3] - np.array([0.0, 0.0, 0.3]) * (1 - math.exp(-1.0))) < 1e-3
    # clamped per body axis, NaN ignored
    for _ in range(100):
        obs.start_step(list(xi), [hover] * 4)
        xi[5] += 50.0 * dt
        obs.end_step(dt, list(xi))
    assert max(abs(v) for v in obs.value[:3]) == pytest.approx(1.0)
    before = list(obs.value)
    obs.start_step(list(xi), [hover] * 4)
    bad = list(xi)
    bad[5] = math.nan
    obs.end_step(dt, bad)
    assert obs.value == before
    off = ModelErrorObserver(exprs, rate=0.0, angular_rate=0.0, max_accel=1.0, max_angular=5.0)
    off.start_step(list(xi), [hover] * 4)
    assert off.end_step(dt, list(xi)) == ([0.0] * 6, [0.0] * 3)
