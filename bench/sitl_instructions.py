"""Instructions per lockstep step of the SITL process and of the companion, counted by valgrind's callgrind.

What bench/sitl_speed.py measures in seconds depends on the machine's load (other processes evict the caches
and take the cores); the number of user-space instructions a step executes does not. Both processes run as
in bench/sitl_speed.py (`quadsr sitl` in lockstep, a LockstepClient with constant throttles, the same
vehicles and wind), one of them at a time under callgrind with instrumentation switched on (callgrind_control)
only around --steps steps after a warm-up. Kernel work (the UDP system calls, waking the other process) is
not counted: it is the part of a step this code cannot make cheaper by doing less.

Usage: python bench/sitl_instructions.py [--steps 300]   (needs valgrind; takes a few minutes)
"""

from __future__ import annotations

import argparse
import glob
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sitl_speed import AERO_WIND_FLAGS, VEHICLES  # noqa: E402

WARMUP_STEPS = 100


def sitl_command(vehicle: str, valgrind: list[str]) -> list[str]:
    """`quadsr sitl` for the vehicle as bench/sitl_speed.py runs it (optionally under valgrind)."""
    extra = AERO_WIND_FLAGS if vehicle == "fang-chen-aero" else ("--ground", "none",
                                                                 "--initial-position", "0,0,-100")
    return [*valgrind, sys.executable, "-m", "quadsr.cli", "sitl", "--hil", "udp:127.0.0.1:0", "--no-gcs",
            "--status-interval", "0", "--lockstep-timeout", "120", "--vehicle", vehicle, *extra]


def companion(hil: str) -> None:
    """The companion's process: connect, then for each line `N` on stdin take N steps and print `done`."""
    from bridge.lockstep import LockstepClient

    with LockstepClient(hil, timeout=120.0) as client:
        client.connect(300.0)
        for line in sys.stdin:
            for _ in range(int(line)):
                client.step((0.6, 0.6, 0.6, 0.6))
            print("done", flush=True)


def callgrind_total(out_prefix: str) -> int:
    """Instructions recorded in callgrind's output files (Ir)."""
    total = 0
    for name in glob.glob(out_prefix + "*"):
        for line in Path(name).read_text(errors="replace").splitlines():
            if line.startswith(("totals:", "summary:")):
                total = max(total, int(line.split()[1]))
    return total


def per_step(vehicle: str, steps: int, measured: str, workdir: str) -> float:
    """Instructions per step of `measured` ('sitl' or 'companion'), the other process running natively."""
    out = os.path.join(workdir, f"{measured}-{vehicle}.cg")
    valgrind = ["valgrind", "--tool=callgrind", "--instr-atstart=no", f"--callgrind-out-file={out}"]
    sitl = subprocess.Popen(sitl_command(vehicle, valgrind if measured == "sitl" else []),
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    client = None
    try:
        m = re.search(r"listening for the companion on (udp:[\d.]+:\d+)", sitl.stdout.readline())
        if m is None:
            raise RuntimeError("the SITL did not start")
        client = subprocess.Popen([*(valgrind if measured == "companion" else []), sys.executable, __file__,
                                   "--companion", m.group(1)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=subprocess.DEVNULL, text=True)
        target = sitl if measured == "sitl" else client

        def run(n: int) -> None:
            client.stdin.write(f"{n}\n")
            client.stdin.flush()
            if client.stdout.readline().strip() != "done":
                raise RuntimeError("the companion stopped")

        run(WARMUP_STEPS)
        subprocess.run(["callgrind_control", "-i", "on", str(target.pid)], capture_output=True, check=True)
        run(steps)
        subprocess.run(["callgrind_control", "-i", "off", str(target.pid)], capture_output=True, check=True)
    finally:
        if client is not None:
            client.stdin.close()
            client.wait(timeout=120)
        sitl.terminate()
        sitl.wait(timeout=120)
    return callgrind_total(out) / steps


def main() -> int:
    """Count and print instructions per step for both processes and both vehicles."""
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--companion", metavar="HIL", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.companion:
        companion(args.companion)
        return 0
    if shutil.which("valgrind") is None or shutil.which("callgrind_control") is None:
        print("bench/sitl_instructions.py needs valgrind (callgrind, callgrind_control) on PATH: "
              "install it (apt-get install valgrind) or use bench/sitl_speed.py", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as workdir:
        for vehicle in VEHICLES:
            sitl = per_step(vehicle, args.steps, "sitl", workdir)
            comp = per_step(vehicle, args.steps, "companion", workdir)
            print(f"{vehicle}: instructions per lockstep step: SITL {sitl:,.0f}, companion {comp:,.0f}, "
                  f"both {sitl + comp:,.0f} ({args.steps} steps after {WARMUP_STEPS})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
