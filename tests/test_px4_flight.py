"""Real PX4 (../shared/px4) flies quadsr's SITL through `quadsr px4`, driven over PX4's GCS MAVLink link.

One PX4 boot is shared by the module (the kill test ends it, so it runs last). Waits are on PX4's events and
on simulated time (PX4's time_boot_ms in lockstep), with wall bounds only as a safety net. Lockstep at most
twice real time: PX4's three EKF2 instances are not part of its lockstep, and at full speed beside other
load they fell behind simulated time on the ground, learned a wrong accelerometer bias (-0.03 to -0.05
m/s^2 for +0.009) and hovered 15-19 cm from the point by the truth (2 of 18 flights under five CPU hogs;
none of 16 at twice real time; see README, "Pace on a loaded machine").
"""

from __future__ import annotations

import math
import os
import re
import shutil
import signal
import time

import pytest
from px4_run import PX4_DIR, Gcs, QuadsrPx4, gone, mav

from bridge.tlog import read_tlog
from quadsr.px4_launch import Px4Ports

HOVER_ALT = 2.5  # m, PX4's default takeoff altitude (MIS_TAKEOFF_ALT)
HOVER_HELD = 0.10  # m, over 10 s of simulated time, by PX4's estimate and by the truth
AUTO_TAKEOFF = (4 << 16) | (2 << 24)  # PX4's HEARTBEAT.custom_mode: main mode AUTO, sub mode TAKEOFF
AUTO_LOITER = (4 << 16) | (3 << 24)  # ... sub mode LOITER


@pytest.fixture(scope="module")
def px4_flight(tmp_path_factory):
    """`quadsr px4` on a free instance with ideal sensors, ready for takeoff; a GCS connected to it."""
    work = tmp_path_factory.mktemp("px4")
    started = time.monotonic()
    run = QuadsrPx4("--px4", str(PX4_DIR), "--instance", "60-120", "--work", str(work), "--sensors", "ideal",
                    "--max-rtf", "2")
    instance = run.instance
    try:
        run.wait_for("is flying quadsr's SITL", 60.0)
        run.wait_for("ready for takeoff", max(1.0, 60.0 - (time.monotonic() - started)))
        ready_wall = time.monotonic() - started
        gcs = Gcs(Px4Ports(instance).gcs, instance + 1)
        gcs.connect()
        yield run, gcs, work, ready_wall
        gcs.close()
    finally:
        run.stop()


def _tails(work, lines: int = 25) -> str:
    """The last lines of PX4's and the SITL's logs: what a failed assert shows beside its values."""
    out = []
    for name in ("px4.log", "sitl.log"):
        path = work / name
        text = path.read_text(errors="replace").splitlines()[-lines:] if path.exists() else ["(missing)"]
        out.append(f"--- {name} (last {lines} lines)\n" + "\n".join(text))
    return "\n".join(out)


def test_px4_connects_arms_takes_off_hovers_lands_disarms(px4_flight):
    run, gcs, work, ready_wall = px4_flight
    assert ready_wall < 60.0, f"PX4 ready for takeoff after {ready_wall:.1f} s wall\n{_tails(work)}"
    assert "autopilot connected" in (work / "sitl.log").read_text()
    assert "SYS_AUTOSTART=10099" in (work / "px4.log").read_text()  # the matched airframe
    gcs.run_until(lambda g: g.position is not None, sim_s=5.0)
    x0, y0, z0 = gcs.position  # PX4's estimate on the ground: its take-off climbs 2.5 m from there
    assert gcs.arm() == mav.MAV_RESULT_ACCEPTED
    assert gcs.takeoff() == mav.MAV_RESULT_ACCEPTED
    gcs.run_until(lambda g: g.custom_mode == AUTO_TAKEOFF, sim_s=5.0)
    gcs.run_until(lambda g: g.custom_mode == AUTO_LOITER, sim_s=20.0)  # PX4's take-off done: it holds
    settle_until = gcs.sim_ms + 8000  # PX4 settles its height estimate within ~8 s (see README)
    gcs.run_until(lambda g: g.sim_ms >= settle_until, sim_s=10.0)
    estimate = []
    end = gcs.sim_ms + 10000
    while gcs.sim_ms < end:
        msg = gcs.recv(1.0)
        if msg is not None and msg.get_type() == "LOCAL_POSITION_NED":
            estimate.append(gcs.position)
    assert len(estimate) > 100, f"{len(estimate)} position estimates in 10 s simulated (50 Hz expected)\n" \
        + _tails(work)
    worst = max(math.dist(p, (x0, y0, z0 - HOVER_ALT)) for p in estimate)
    assert worst < HOVER_HELD, \
        f"hover strayed {worst:.3f} m from ({x0:.2f}, {y0:.2f}, {z0 - HOVER_ALT:.2f}) " \
        f"(PX4's ULog in {work / 'rootfs' / 'log'})\n{_tails(work)}"
    assert gcs.armed, f"disarmed while hovering\n{_tails(work)}"
    assert gcs.command(mav.MAV_CMD_NAV_LAND, 0, 0, 0, math.nan, math.nan, math.nan, math.nan) == \
        mav.MAV_RESULT_ACCEPTED
    gcs.run_until(lambda g: g.landed_state == mav.MAV_LANDED_STATE_ON_GROUND and not g.armed, sim_s=30.0)
    # The truth (quadsr's log, simulated time = PX4's): the same hover held 2.5 m above where it stood, then
    # on the ground.
    truth = [(m.time_boot_ms, (m.x, m.y, m.z)) for _, m in read_tlog(work / "truth.tlog")
             if m.get_type() == "LOCAL_POSITION_NED"]
    window = [p for t, p in truth if end - 10000 <= t <= end]
    assert len(window) > 2000, f"{len(window)} truth rows in 10 s simulated (250 Hz expected)\n{_tails(work)}"
    gx, gy, gz = truth[0][1]
    worst = max(math.dist(p, (gx, gy, gz - HOVER_ALT)) for p in window)
    assert worst < HOVER_HELD, f"the truth strayed {worst:.3f} m from the hover point\n{_tails(work)}"
    assert truth[-1][1][2] > -0.02, f"last truth height {-truth[-1][1][2]:.3f} m: not landed\n{_tails(work)}"
    # PX4 saw working sensors (none failed as stuck: sitl.sensors' never_repeat) and a live ground station
    said = (work / "px4.log").read_text()
    assert "STALE" not in said and "switch from" not in said, said
    assert "Connection to ground station lost" not in said, said
    # --max-rtf 2 held: each status interval (5 s wall) at most twice real time, 0.1 s of catch-up allowed
    paces = [float(m) for m in re.findall(r" rtf=([0-9.]+) ", (work / "sitl.log").read_text())]
    assert paces and max(paces) <= 2.1, f"real-time factors {paces} with --max-rtf 2"


def test_px4_killed_mid_flight_stops_everything_with_a_clear_message(px4_flight):
    run, gcs, work, _ = px4_flight
    gcs.drain()
    assert gcs.arm() == mav.MAV_RESULT_ACCEPTED  # just after the first test's landing
    assert gcs.takeoff() == mav.MAV_RESULT_ACCEPTED
    gcs.run_until(lambda g: g.position[2] < -1.0, sim_s=20.0)
    # A SITL too slow to see the link drop before the launcher reacts (as on a loaded machine) must still
    # log it: hold the SITL still while PX4 dies, past several of the launcher's polls.
    os.kill(run.sitl_pid, signal.SIGSTOP)
    os.kill(run.px4_pid, signal.SIGKILL)
    time.sleep(1.0)
    os.kill(run.sitl_pid, signal.SIGCONT)
    code = run.proc.wait(60.0)
    run.wait_for("PX4 and the SITL stopped", 5.0)
    assert code == 1
    assert "error: PX4 exited (code -9)" in run.output
    assert "Traceback" not in run.output
    assert gone(run.sitl_pid) and gone(run.px4_pid)
    assert "autopilot disconnected" in (work / "sitl.log").read_text()


def test_px4_that_never_connects_gives_a_clear_message(tmp_path):
    # The real PX4 program, with its simulator start-up script emptied: it boots but never connects.
    build = tmp_path / "px4-nosim"
    (build / "bin").mkdir(parents=True)
    (build / "bin" / "px4").symlink_to(PX4_DIR / "bin" / "px4")
    for entry in (PX4_DIR / "bin").iterdir():
        if entry.name.startswith("px4-"):
            shutil.copy(entry, build / "bin" / entry.name)
    shutil.copytree(PX4_DIR / "etc", build / "etc")
    sim = build / "etc" / "init.d-posix" / "px4-rc.simulator"
    sim.chmod(0o644)
    sim.write_text("#!/bin/sh\necho 'simulator start-up removed for this test'\n")
    run = QuadsrPx4("--px4", str(build), "--instance", "121-180", "--work", str(tmp_path / "work"),
                    "--connect-timeout", "5")
    instance = run.instance
    try:
        code = run.proc.wait(90.0)
    finally:
        run.stop()
    run.wait_for("PX4 and the SITL stopped", 5.0)
    assert code == 1
    assert f"PX4 did not connect to the simulator on tcp:127.0.0.1:{4560 + instance} within 5 s" in run.output
    assert "Traceback" not in run.output
    assert gone(run.sitl_pid) and gone(run.px4_pid)
