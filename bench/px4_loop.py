"""Real PX4 in the loop with quadsr's SITL: speed, hover hold and Case I / II through PX4 OFFBOARD beside
quadsr's own companion, and identification from PX4-flown excitation flights.

1. `quadsr px4` (lockstep; ideal sensors unless --sensors realistic, in every PX4 run): real-time factor
   (PX4's simulated ms per wall second) on the ground and during a take-off and hover (PX4's own take-off),
   the CPU time of each process (the SITL, PX4, this ground station) per simulated second in that hover, the
   machine's load; the hover hold over 10 s of simulated time from quadsr's truth log.
2. One table: a 2.5 m hover hold, Case I and Case II flown by `quadsr fly --autopilot` through PX4 OFFBOARD
   (`quadsr px4 --mode realtime`, a fresh PX4 per flight; the hover from PX4's own take-off to 2.5 m: a climb
   from the ground in OFFBOARD leaves PX4's height estimate 10-30 cm above the truth for many seconds), beside
   quadsr's own companion flying the same trajectory directly on a `quadsr sitl` (ideal sensors, true state,
   from the ground): RMS of the 3-D error after 5 s, truth.
3. Identification from PX4-flown flights: two `quadsr excite --autopilot --profile px4-offboard` flights
   (seeds 1 and 2, a fresh PX4 each); a model identified (sparse engine) from the first flight's PX4 ULog
   (targets from its IMU, `--targets-from sensors`) and one from its truth .tlog, each validated on the
   second flight's log of the same kind, in the excitation's window: R^2 per target.

Prints the figures, then PASS/FAIL lines: real-time factor in hover >= 5; RMS after 5 s <= 5 cm for each
flight through PX4 (issue 9's floor, stated for ideal sensors); R^2 >= 0.99 on every target of the second
flight, for the truth .tlog and for the ULog (issue 14's floor).
Usage: python bench/px4_loop.py [--px4 DIR] [--duration 20] [--out DIR] [--skip-tracking]
                                [--sensors realistic]
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from bridge.messages import mavlink  # noqa: E402
from bridge.offboard import OffboardLink  # noqa: E402
from bridge.tlog import read_tlog  # noqa: E402
from bridge.vehicle import load_vehicle  # noqa: E402
from identification.true_model import write_true_model  # noqa: E402
from quadsr.child_process import OutputProcess  # noqa: E402
from quadsr.px4_launch import Px4Ports  # noqa: E402
from quadsr.sitl_process import SitlProcess  # noqa: E402

STARTED = re.compile(r"started PX4 \(pid (\d+)\) and the SITL \(pid (\d+)\)")
WINDOW = re.compile(r"excitation from ([\d.]+) to ([\d.]+) s of PX4's clock")
R2_ROW = re.compile(r"\| \S+ \((\w+)\) \|.*\| ([-\d.e+]+|nan) \|$")
HOLD = 'name: hold-2.5m\nduration: 60\nexpressions: {x: "0", y: "0", z: "-2.5", yaw: "0"}\n'

QUADSR = [sys.executable, "-m", "quadsr.cli"]


def start_px4(px4: Path, work: Path, mode: str, sensors: str) -> tuple[OutputProcess, int]:
    """`quadsr px4` on a free instance (held by it), ready for takeoff; (process, instance)."""
    instances = "1-9" if mode == "realtime" else "60-120"  # realtime: a companion answers from 14540+N
    run = OutputProcess([*QUADSR, "px4", "--px4", str(px4), "--instance", instances, "--work", str(work),
                         "--sensors", sensors, "--mode", mode], cwd=REPO)
    if run.find("ready for takeoff", 120.0) is None:
        run.stop()
        raise SystemExit(f"PX4 did not get ready:\n{run.tail()}")
    return run, int(run.find(r"using PX4 instance (\d+)", 1.0).group(1))


def sim_rate(link: OffboardLink, wall_s: float) -> float:
    """PX4's simulated seconds per wall second over wall_s of reading its messages."""
    link.poll(0.1)
    start_ms, start = link.state.time_boot_ms, time.monotonic()
    while time.monotonic() - start < wall_s:
        link.poll(0.05)
    return (link.state.time_boot_ms - start_ms) * 1e-3 / (time.monotonic() - start)


def cpu_seconds(pid: int) -> float:
    """User + system CPU time (s) a process has used so far (Linux /proc), nan if it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
    except OSError:
        return math.nan
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def take_off(gcs: OffboardLink) -> None:
    """Arm, PX4's own take-off to MIS_TAKEOFF_ALT (2.5 m), then 8 s of its clock to settle."""
    assert gcs.arm() == mavlink.MAV_RESULT_ACCEPTED
    nan = math.nan
    assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, (nan, 0, 0, nan, nan, nan, nan)) == \
        mavlink.MAV_RESULT_ACCEPTED
    while gcs.state.position is None or gcs.state.position[2] > -2.4:
        gcs.poll(0.1)
    settle = gcs.state.time_boot_ms + 8000
    while gcs.state.time_boot_ms < settle:
        gcs.poll(0.05)


def hover(px4: Path, out: Path, sensors: str) -> dict[str, float]:
    """Lockstep PX4: real-time factors, CPU per simulated second, take-off to 2.5 m and the truth's hover hold
    over 10 s."""
    work = out / "hover"
    run, n = start_px4(px4, work, "lockstep", sensors)
    pids = {"PX4": int(STARTED.search(run.output).group(1)), "SITL": int(STARTED.search(run.output).group(2)),
            "ground station (this)": os.getpid()}
    try:
        gcs = OffboardLink(f"udp:127.0.0.1:{Px4Ports(n).gcs}")
        gcs.connect(30.0)
        ground_rtf = sim_rate(gcs, 3.0)
        take_off(gcs)
        start_ms, wall = gcs.state.time_boot_ms, time.monotonic()
        cpu0 = {k: cpu_seconds(p) for k, p in pids.items()}
        load0 = os.getloadavg()[0]
        while gcs.state.time_boot_ms < start_ms + 10000:
            gcs.poll(0.05)
        sim_s = (gcs.state.time_boot_ms - start_ms) * 1e-3
        flight_rtf = sim_s / (time.monotonic() - wall)
        cpu = {k: (cpu_seconds(p) - cpu0[k]) / sim_s for k, p in pids.items()}
        load = 0.5 * (load0 + os.getloadavg()[0])
        gcs.close()
    finally:
        run.stop()
    pts = [(m.x, m.y, m.z) for _, m in read_tlog(work / "truth.tlog")
           if m.get_type() == "LOCAL_POSITION_NED" and start_ms <= m.time_boot_ms <= start_ms + 10000]
    mean = [sum(p[i] for p in pts) / len(pts) for i in range(3)]
    rms = math.sqrt(sum(math.dist(p, mean) ** 2 for p in pts) / len(pts))
    return {"rtf_ground": ground_rtf, "rtf_hover": flight_rtf, "hover_rms_m": rms,
            "hover_max_m": max(math.dist(p, mean) for p in pts), "hover_z_m": mean[2], "cpu": cpu,
            "load": load}


def rms_after_5s(steps: Path) -> float:
    """RMS of the 3-D truth-vs-reference error for t >= 5 s, from a steps.csv."""
    err = [math.dist((float(r["true_x"]), float(r["true_y"]), float(r["true_z"])),
                     (float(r["ref_x"]), float(r["ref_y"]), float(r["ref_z"])))
           for r in csv.DictReader(steps.open()) if float(r["t"]) >= 5.0]
    return math.sqrt(sum(e * e for e in err) / len(err))


def through_px4(px4: Path, out: Path, model: Path, case: str, duration: float, sensors: str,
                airborne: bool = False) -> float:
    """A trajectory (case1, case2 or a file) flown through PX4 OFFBOARD (real-time pacing), from the ground or
    (airborne) from PX4's own take-off: RMS after 5 s (truth)."""
    work = out / f"px4-{Path(case).stem}"
    run, n = start_px4(px4, work, "realtime", sensors)
    try:
        if airborne:
            gcs = OffboardLink(f"udp:127.0.0.1:{Px4Ports(n).gcs}")
            gcs.connect(30.0)
            take_off(gcs)
            gcs.close()
        done = subprocess.run([*QUADSR, "fly", "--model", str(model), "--trajectory", case, "--duration",
                               str(duration), "--autopilot", f"udp:127.0.0.1:{Px4Ports(n).offboard}",
                               "--truth", str(work / "truth.tlog"), "--out", str(work / "flight"),
                               "--no-progress"], cwd=REPO, capture_output=True, text=True)
    finally:
        run.stop()
    if done.returncode != 0:
        print(done.stdout[-2000:], done.stderr[-2000:])
        return math.inf
    return rms_after_5s(work / "flight" / "steps.csv")


def own_companion(out: Path, model: Path, case: str, duration: float) -> float:
    """The same trajectory flown by quadsr's own companion on the HIL link (ideal sensors, true state): RMS
    after 5 s."""
    with SitlProcess(["--sensors", "ideal"]) as sitl:
        done = subprocess.run([*QUADSR, "fly", "--model", str(model), "--trajectory", case, "--duration",
                               str(duration), "--hil", sitl.hil, "--out", str(out / f"own-{Path(case).stem}"),
                               "--no-progress"], cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0:
        print(done.stdout[-2000:], done.stderr[-2000:])
        return math.inf
    return rms_after_5s(out / f"own-{Path(case).stem}" / "steps.csv")


def excite_through_px4(px4: Path, out: Path, seed: int, sensors: str) -> dict[str, object]:
    """A px4-offboard excitation through PX4 OFFBOARD on a fresh PX4: its ULog, truth .tlog and windows."""
    work = out / f"px4-excite-{seed}"
    run, n = start_px4(px4, work, "realtime", sensors)
    try:
        done = subprocess.run([*QUADSR, "excite", "--autopilot", f"udp:127.0.0.1:{Px4Ports(n).offboard}",
                               "--profile", "px4-offboard", "--seed", str(seed), "--out",
                               str(work / "offboard.tlog")], cwd=REPO, capture_output=True, text=True)
    finally:
        run.stop()
    m = WINDOW.search(done.stdout)
    if done.returncode != 0 or m is None:
        raise SystemExit(f"the excitation through PX4 failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    from pyulog import ULog

    ulog = sorted((work / "rootfs" / "log").rglob("*.ulg"))[-1]
    start, end = float(m.group(1)), float(m.group(2))
    log_start = ULog(str(ulog), ["vehicle_status"]).start_timestamp * 1e-6  # PX4's clock at the ULog's t = 0
    return {"ulog": ulog, "truth": work / "truth.tlog", "truth_window": f"{start:.3f}:{end:.3f}",
            "ulog_window": f"{start - log_start:.3f}:{end - log_start:.3f}", "summary": done.stdout}


def identify_and_validate(out: Path, train: dict, test: dict, kind: str) -> dict[str, float]:
    """Identify (sparse engine) from the first excitation's log of `kind` (ulog or truth), validate on the
    second's in its excitation window: R^2 per target."""
    model = out / f"px4-{kind}-model.yaml"
    extra = ["--motor-curve", "fang-chen-buaa", "--targets-from", "sensors"] if kind == "ulog" else []
    subprocess.run([*QUADSR, "identify", str(train[kind]), "--window", train[f"{kind}_window"], "-o",
                    str(model), "--engine", "sparse", "--no-progress", *extra], cwd=REPO, capture_output=True,
                   text=True, check=True)
    done = subprocess.run([*QUADSR, "validate", str(model), str(test[kind]), "--window",
                           test[f"{kind}_window"], "--out", str(out / f"px4-{kind}-validation"), *extra],
                          cwd=REPO, capture_output=True, text=True, check=True)
    return {m.group(1): float(m.group(2)) for m in map(R2_ROW.match, done.stdout.splitlines()) if m}


def main() -> int:
    """Run the measurements, print them and the PASS/FAIL lines; exit 0 when all pass."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--px4", type=Path, default=REPO.parent / "shared" / "px4")
    p.add_argument("--duration", type=float, default=20.0, help="tracking flight length, s")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--skip-tracking", action="store_true", help="no hover/Case I/II table")
    p.add_argument("--sensors", choices=("ideal", "realistic"), default="ideal",
                   help="the SITL's sensors under PX4 (default ideal, as the floors are stated)")
    args = p.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="px4_loop-"))
    model = out / "true-model.yaml"
    out.mkdir(parents=True, exist_ok=True)
    write_true_model(load_vehicle("fang-chen-buaa"), model)
    h = hover(args.px4, out, args.sensors)
    print(f"PX4 lockstep: real-time factor {h['rtf_ground']:.1f} on the ground, {h['rtf_hover']:.1f} in hover"
          f" (load average {h['load']:.1f} on {os.cpu_count()} cores); CPU s per simulated s in hover: "
          + ", ".join(f"{k} {v:.3f}" for k, v in h["cpu"].items())
          + f"; hover at z = {h['hover_z_m']:.3f} m (truth): RMS {h['hover_rms_m'] * 1000:.1f} mm, max "
          f"{h['hover_max_m'] * 1000:.1f} mm over 10 s simulated", flush=True)
    rows = []
    if not args.skip_tracking:
        hold = out / "hold-2.5m.yaml"
        hold.write_text(HOLD)
        print(f"| flight ({args.duration:g} s, {args.sensors} sensors under PX4, truth) | RMS after 5 s "
              "through PX4 OFFBOARD [mm] | quadsr's own companion [mm] |\n|---|---|---|", flush=True)
        for name, case in (("hover 2.5 m (PX4: from its take-off)", str(hold)), ("Case I", "case1"),
                           ("Case II", "case2")):
            rows.append((name, through_px4(args.px4, out, model, case, args.duration, args.sensors,
                                           case == str(hold)),
                         own_companion(out, model, case, args.duration)))
            print(f"| {name} | {rows[-1][1] * 1000:.1f} | {rows[-1][2] * 1000:.4f} |", flush=True)
    train, test = (excite_through_px4(args.px4, out, seed, args.sensors) for seed in (1, 2))
    for f in (train, test):
        print(f"excitation through PX4: {f['summary'].splitlines()[1]}; ULog window {f['ulog_window']} s",
              flush=True)
    r2 = {kind: identify_and_validate(out, train, test, kind) for kind in ("truth", "ulog")}
    for kind, label in (("truth", "quadsr's truth .tlog"), ("ulog", "PX4's ULog (targets from its IMU)")):
        print(f"identified from the first excitation through PX4 ({label}), validated on the second: R^2 "
              + ", ".join(f"{k} {v:.4f}" for k, v in r2[kind].items()), flush=True)
    checks = [(h["rtf_hover"] >= 5.0, f"real-time factor in hover {h['rtf_hover']:.1f} >= 5")]
    for kind in ("truth", "ulog"):
        checks.append((len(r2[kind]) == 6 and min(r2[kind].values()) >= 0.99,
                       f"R^2 >= 0.99 on every target of the second flight ({kind})"))
    checks += [(px4 <= 0.05, f"{name} through PX4 OFFBOARD: RMS after 5 s {px4 * 1000:.1f} mm <= 50 mm")
               for name, px4, _ in rows]
    for ok, text in checks:
        print(f"{'PASS' if ok else 'FAIL'} {text}")
    print(f"outputs in {out}")
    return 0 if all(ok for ok, _ in checks) else 1


if __name__ == "__main__":
    sys.exit(main())
