"""Identification from a flight real PX4 flies: `quadsr excite --autopilot` through PX4 OFFBOARD (body-rate
and thrust PRBS around a hover path, `quadsr px4 --mode realtime`), then PX4's ULog of it identified.

Short on purpose (12 s of PX4's clock, two targets, the sparse engine): bench/px4_loop.py flies the full
profile twice and validates on the second flight.
"""

from __future__ import annotations

import re
import subprocess
import sys

import yaml
from px4_run import PX4_DIR, REPO, QuadsrPx4
from pyulog import ULog

from bridge.vehicle import load_vehicle
from quadsr.px4_launch import Px4Ports

WINDOW = re.compile(r"excitation from ([\d.]+) to ([\d.]+) s of PX4's clock")
R2_ROW = re.compile(r"\| \S+ \((\w+)\) \|.*\| ([-\d.e+]+|nan) \|$")


def quadsr(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """A quadsr command as a separate process."""
    return subprocess.run([sys.executable, "-m", "quadsr.cli", *args], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout)


def test_excitation_through_px4_offboard_is_identified_from_px4s_ulog(tmp_path):
    work = tmp_path / "px4"
    # the companion answers from 14540+N (N <= 9); a range, so the instance is held from choice to use
    run = QuadsrPx4("--px4", str(PX4_DIR), "--instance", "1-9", "--work", str(work), "--sensors",
                    "ideal", "--mode", "realtime")
    instance = run.instance
    try:
        run.wait_for("ready for takeoff", 90.0)
        done = quadsr("excite", "--autopilot", f"udp:127.0.0.1:{Px4Ports(instance).offboard}", "--profile",
                      "px4-offboard", "--duration", "12", "--seed", "3", "--out", str(tmp_path / "link.tlog"),
                      timeout=180)
    finally:
        run.stop()
    said = done.stdout + done.stderr
    assert done.returncode == 0, said
    assert "Traceback" not in said
    m = WINDOW.search(said)
    assert m, said
    start, end = float(m.group(1)), float(m.group(2))
    assert end - start > 7.0  # 12 s less the climb (2.5 s) and the settling (1.5 s), at 100 setpoints/s
    setpoints = int(re.search(r"(\d+) setpoints", said).group(1))
    assert setpoints >= 50 * 12  # at least 50 Hz of PX4's clock
    ulogs = sorted((work / "rootfs" / "log").rglob("*.ulg"))
    assert ulogs, "PX4 wrote no ULog"
    log_start = ULog(str(ulogs[-1]), ["vehicle_status"]).start_timestamp * 1e-6  # PX4 clock at the log's t=0
    window = f"{start - log_start:.3f}:{end - log_start:.3f}"
    ident = quadsr("identify", str(ulogs[-1]), "--window", window, "-o", str(tmp_path / "model.yaml"),
                   "--motor-curve", "fang-chen-buaa", "--targets-from", "sensors", "--engine", "sparse",
                   "--targets", "ax,dwx", "--no-progress")
    out = ident.stdout + ident.stderr
    assert ident.returncode == 0, out
    # PX4's system identification logging (quadsr's airframe) gives the motor commands at the control rate
    assert "motor commands from actuator_motors" in out, out
    r2 = {m.group(1): float(m.group(2)) for m in map(R2_ROW.match, out.splitlines()) if m}
    assert set(r2) == {"ax", "dwx"}, out
    # sanity floors (bench/px4_loop.py: R^2 of all six on a second flight): x'' on the held-out end of the
    # excitation, and the roll control term of wx' learned from PX4's motor commands within 10% of the
    # vehicle's (the held-out second of a 12 s flight can be one where the excitation faded near a limit)
    assert r2["ax"] >= 0.99, r2
    dwx = yaml.safe_load((tmp_path / "model.yaml").read_text())["targets"]["dwx"]["expression"]
    m = re.search(r"([-\d.e]+)\*\(u2\*\*2 \+ u3\*\*2 - u1\*\*2 - u4\*\*2\)", dwx)
    assert m, dwx
    v = load_vehicle("fang-chen-buaa")
    expected = v.mixer_gain / v.inertia[0][0]  # (rad/s^2) per (rad/s)^2 of f2
    assert abs(float(m.group(1)) / expected - 1.0) < 0.10, (dwx, expected)


def test_an_open_loop_profile_through_px4_is_a_user_error(tmp_path):
    done = quadsr("excite", "--autopilot", "udp:127.0.0.1:14589", "--profile", "paper-train", "--out",
                  str(tmp_path / "x.tlog"), timeout=60)
    assert done.returncode == 2, done.stderr
    assert "only a closed-loop profile" in done.stderr and "px4-offboard" in done.stderr
    assert "Traceback" not in done.stderr
    assert not (tmp_path / "x.tlog").exists()
