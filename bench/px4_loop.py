"""Real PX4 in the loop with quadsr's SITL: speed, hover hold, and Case I / II through PX4 OFFBOARD.

1. `quadsr px4` (lockstep, ideal sensors): real-time factor (PX4's simulated ms per wall second) on the ground
   and during a take-off and hover; the hover hold over 10 s of simulated time from quadsr's truth log.
2. Case I and Case II flown by `quadsr fly --autopilot` through PX4 OFFBOARD (`quadsr px4 --mode realtime`,
   a fresh PX4 per case), beside quadsr's own companion flying the same case directly on a `quadsr sitl`
   (ideal sensors, true state): RMS of the 3-D error after 5 s from quadsr's truth.
3. Identification from PX4-flown flights: the model learned from Case I's truth .tlog, validated on Case II's.

Prints the figures, then PASS/FAIL lines: real-time factor in flight >= 5; RMS after 5 s <= 5 cm for each case
through PX4; R^2 >= 0.95 per target on the second flight.
Usage: python bench/px4_loop.py [--px4 DIR] [--duration 20] [--out DIR]
"""

from __future__ import annotations

import argparse
import csv
import math
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
from quadsr.px4_launch import Px4Ports, free_instance  # noqa: E402
from quadsr.sitl_process import SitlProcess  # noqa: E402

QUADSR = [sys.executable, "-m", "quadsr.cli"]


def start_px4(px4: Path, work: Path, mode: str) -> tuple[OutputProcess, int]:
    """`quadsr px4` on a free instance, ready for takeoff; (process, instance)."""
    n = free_instance(1, 9) if mode == "realtime" else free_instance(60, 120)
    run = OutputProcess([*QUADSR, "px4", "--px4", str(px4), "--instance", str(n), "--work", str(work),
                         "--sensors", "ideal", "--mode", mode], cwd=REPO)
    if run.find("ready for takeoff", 120.0) is None:
        run.stop()
        raise SystemExit(f"PX4 did not get ready:\n{run.tail()}")
    return run, n


def sim_rate(link: OffboardLink, wall_s: float) -> float:
    """PX4's simulated seconds per wall second over wall_s of reading its messages."""
    link.poll(0.1)
    start_ms, start = link.state.time_boot_ms, time.monotonic()
    while time.monotonic() - start < wall_s:
        link.poll(0.05)
    return (link.state.time_boot_ms - start_ms) * 1e-3 / (time.monotonic() - start)


def hover(px4: Path, out: Path) -> dict[str, float]:
    """Lockstep PX4: real-time factors, take-off to 2.5 m and the truth's hover hold over 10 s."""
    work = out / "hover"
    run, n = start_px4(px4, work, "lockstep")
    try:
        gcs = OffboardLink(f"udp:127.0.0.1:{Px4Ports(n).gcs}")
        gcs.connect(30.0)
        ground_rtf = sim_rate(gcs, 3.0)
        assert gcs.arm() == mavlink.MAV_RESULT_ACCEPTED
        nan = math.nan
        assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, (nan, 0, 0, nan, nan, nan, nan)) == \
            mavlink.MAV_RESULT_ACCEPTED
        while gcs.state.position is None or gcs.state.position[2] > -2.4:
            gcs.poll(0.1)
        settle = gcs.state.time_boot_ms + 8000
        while gcs.state.time_boot_ms < settle:
            gcs.poll(0.05)
        start_ms, wall = gcs.state.time_boot_ms, time.monotonic()
        while gcs.state.time_boot_ms < start_ms + 10000:
            gcs.poll(0.05)
        flight_rtf = (gcs.state.time_boot_ms - start_ms) * 1e-3 / (time.monotonic() - wall)
        gcs.close()
    finally:
        run.stop()
    pts = [(m.x, m.y, m.z) for _, m in read_tlog(work / "truth.tlog")
           if m.get_type() == "LOCAL_POSITION_NED" and start_ms <= m.time_boot_ms <= start_ms + 10000]
    mean = [sum(p[i] for p in pts) / len(pts) for i in range(3)]
    rms = math.sqrt(sum(math.dist(p, mean) ** 2 for p in pts) / len(pts))
    return {"rtf_ground": ground_rtf, "rtf_hover": flight_rtf, "hover_rms_m": rms,
            "hover_max_m": max(math.dist(p, mean) for p in pts), "hover_z_m": mean[2]}


def rms_after_5s(steps: Path) -> float:
    """RMS of the 3-D truth-vs-reference error for t >= 5 s, from a steps.csv."""
    err = [math.dist((float(r["true_x"]), float(r["true_y"]), float(r["true_z"])),
                     (float(r["ref_x"]), float(r["ref_y"]), float(r["ref_z"])))
           for r in csv.DictReader(steps.open()) if float(r["t"]) >= 5.0]
    return math.sqrt(sum(e * e for e in err) / len(err))


def through_px4(px4: Path, out: Path, model: Path, case: str, duration: float) -> float:
    """Case flown through PX4 OFFBOARD (real-time pacing): RMS after 5 s (truth)."""
    work = out / f"px4-{case}"
    run, n = start_px4(px4, work, "realtime")
    try:
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
    """Case flown by quadsr's own companion on the HIL link (ideal sensors, true state): RMS after 5 s."""
    with SitlProcess(["--sensors", "ideal"]) as sitl:
        done = subprocess.run([*QUADSR, "fly", "--model", str(model), "--trajectory", case, "--duration",
                               str(duration), "--hil", sitl.hil, "--out", str(out / f"own-{case}"),
                               "--no-progress"], cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0:
        print(done.stdout[-2000:], done.stderr[-2000:])
        return math.inf
    return rms_after_5s(out / f"own-{case}" / "steps.csv")


def identify_and_validate(out: Path) -> dict[str, float]:
    """Identify (sparse engine) from the Case I flight PX4 flew (quadsr's truth .tlog), validate on Case II's:
    R^2 per target."""
    train, test = out / "px4-case1" / "truth.tlog", out / "px4-case2" / "truth.tlog"
    model = out / "px4-learned.yaml"
    subprocess.run([*QUADSR, "identify", str(train), "-o", str(model), "--engine", "sparse", "--no-progress"],
                   cwd=REPO, capture_output=True, text=True, check=True)
    done = subprocess.run([*QUADSR, "validate", str(model), str(test), "--out", str(out / "px4-validation")],
                          cwd=REPO, capture_output=True, text=True, check=True)
    r2 = {}
    for line in done.stdout.splitlines():
        m = re.match(r"\| \S+ \((\w+)\) \|.*\| ([-\d.e+]+|nan) \|$", line)
        if m:
            r2[m.group(1)] = float(m.group(2))
    return r2


def main() -> int:
    """Run the measurements, print them and the PASS/FAIL lines; exit 0 when all pass."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--px4", type=Path, default=REPO.parent / "shared" / "px4")
    p.add_argument("--duration", type=float, default=20.0, help="tracking flight length, s")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="px4_loop-"))
    model = out / "true-model.yaml"
    out.mkdir(parents=True, exist_ok=True)
    write_true_model(load_vehicle("fang-chen-buaa"), model)
    h = hover(args.px4, out)
    print(f"PX4 lockstep: real-time factor {h['rtf_ground']:.1f} on the ground, {h['rtf_hover']:.1f} in hover"
          "; "
          f"hover at z = {h['hover_z_m']:.3f} m (truth): RMS {h['hover_rms_m'] * 1000:.1f} mm, max "
          f"{h['hover_max_m'] * 1000:.1f} mm over 10 s simulated", flush=True)
    rows = []
    for case in ("case1", "case2"):
        rows.append((case, through_px4(args.px4, out, model, case, args.duration),
                     own_companion(out, model, case, args.duration)))
        print(f"{case}: RMS after 5 s through PX4 OFFBOARD {rows[-1][1] * 1000:.1f} mm, quadsr's own "
              f"companion {rows[-1][2] * 1000:.4f} mm", flush=True)
    r2 = identify_and_validate(out)
    print("identified from the Case I flight through PX4 (truth .tlog), validated on Case II's: R^2 "
          + ", ".join(f"{k} {v:.4f}" for k, v in r2.items()), flush=True)
    checks = [(h["rtf_hover"] >= 5.0, f"real-time factor in hover {h['rtf_hover']:.1f} >= 5")]
    checks.append((len(r2) == 6 and min(r2.values()) >= 0.95,
                   "R^2 >= 0.95 on every target of the second flight"))
    checks += [(px4 <= 0.05, f"{case} through PX4 OFFBOARD: RMS after 5 s {px4 * 1000:.1f} mm <= 50 mm")
               for case, px4, _ in rows]
    for ok, text in checks:
        print(f"{'PASS' if ok else 'FAIL'} {text}")
    print(f"outputs in {out}")
    return 0 if all(ok for ok, _ in checks) else 1


if __name__ == "__main__":
    sys.exit(main())
