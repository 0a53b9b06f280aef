"""`quadsr ardupilot`: quadsr's SITL as ArduPilot's JSON physics plus the real ArduCopter, as two children.

Both children die with this process (PR_SET_PDEATHSIG, and each in its own process group so that a Ctrl-C
reaches only this process, which stops them in order: ArduCopter first, with SIGKILL, since it acts on
SIGTERM only between physics steps; then the SITL with SIGTERM, so it closes its .tlog). When either child
exits on its own, the launcher says which, how, and at what simulated time, stops the other and exits 1.
"""

from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

from bridge.errors import UserError
from bridge.shutdown import die_with_parent
from bridge.vehicle import VehicleConfig, load_vehicle
from sitl.ardupilot_params import write_parm
from sitl.ardupilot_server import LISTENING

MAVLINK_TCP_BASE = 5760  # SERIAL0; SERIAL1, SERIAL2 on +2, +3
JSON_UDP_BASE = 9002
SITL_T = re.compile(r"quadsr sitl: t=([\d.]+)s")
POLL_S = 0.1  # wall s between checks of the children


@dataclass
class LauncherOptions:
    """What `quadsr ardupilot` runs with (validated by launcher_options)."""

    binary: Path  # arducopter
    defaults: list[Path]  # ArduPilot's parameter files, before the vehicle's
    vehicle_arg: str  # as given (passed on to `quadsr sitl`)
    vehicle: VehicleConfig
    instance: int
    speedup: float
    workdir: Path
    log: Path | None = None
    sensors: str | None = None
    seed: int | None = None
    extra_params: list[Path] = field(default_factory=list)
    wipe: bool = False

    @property
    def mavlink_port(self) -> int:
        """ArduCopter's SERIAL0 MAVLink TCP port."""
        return MAVLINK_TCP_BASE + 10 * self.instance

    @property
    def json_port(self) -> int:
        """The UDP port ArduCopter sends its servo packets to (the SITL listens there)."""
        return JSON_UDP_BASE + 10 * self.instance


def launcher_options(args) -> LauncherOptions:
    """Validate `quadsr ardupilot`'s flags (UserError naming the flag)."""
    folder = Path(args.ardupilot)
    binary = folder / "arducopter"
    if not (binary.is_file() and os.access(binary, os.X_OK)):
        raise UserError(f"--ardupilot {folder}: no executable arducopter in it",
                        hint="give the folder of an ArduCopter SITL build (arducopter, copter.parm)")
    defaults = [folder / name for name in ("copter.parm", "copter-X.parm") if (folder / name).is_file()]
    if not 0 <= args.instance <= 255:
        raise UserError(f"-I must be 0..255 (ArduPilot keeps the instance in one byte), got {args.instance}")
    if not (math.isfinite(args.speedup) and args.speedup > 0):
        raise UserError(f"--speedup must be a positive number, got {args.speedup}")
    if args.seed is not None and args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    extra = [Path(p) for p in args.param]
    for p in extra:
        if not p.is_file():
            raise UserError(f"--param {p}: no such file", hint="give an ArduCopter .parm file")
    workdir = Path(args.workdir) if args.workdir else Path(f"ardupilot-I{args.instance}")
    return LauncherOptions(
        binary=binary.resolve(), defaults=[d.resolve() for d in defaults], vehicle_arg=args.vehicle,
        vehicle=load_vehicle(args.vehicle), instance=args.instance, speedup=args.speedup, workdir=workdir,
        log=Path(args.log) if args.log else None, sensors=args.sensors, seed=args.seed,
        extra_params=[p.resolve() for p in extra], wipe=args.wipe,
    )


class _Child:
    """A child process whose output lines are echoed (with a prefix) and kept (the last 200)."""

    def __init__(self, name: str, argv: list[str], cwd: Path, death_signal: int, out: TextIO | None,
                 prefix: str = ""):
        self.name = name
        self.out = out
        self.prefix = prefix
        self.lines: deque[str] = deque(maxlen=200)
        self.cond = threading.Condition()
        self.proc = subprocess.Popen(
            argv, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            text=True, errors="replace", start_new_session=True,
            preexec_fn=lambda: die_with_parent(death_signal),  # noqa: PLW1509
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        previous = None
        for line in self.proc.stdout:
            line = line.rstrip("\n")
            with self.cond:
                self.lines.append(line)
                self.cond.notify_all()
            repeated, previous = line == previous, line  # ArduCopter repeats some lines dozens of times
            if self.out is not None and not repeated:
                try:
                    print(self.prefix + line, file=self.out, flush=True)
                except (ValueError, OSError):
                    self.out = None
        with self.cond:
            self.cond.notify_all()

    def wait_for(self, text: str, timeout: float) -> bool:
        """True once a line containing text was printed; False if the child exits or timeout s pass."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                if any(text in line for line in self.lines):
                    return True
                left = deadline - time.monotonic()
                if left <= 0 or (self.proc.poll() is not None and not self.reader.is_alive()):
                    return False
                self.cond.wait(min(left, 0.1))

    def how_it_ended(self) -> str:
        """'exited with code N' or 'was killed by SIGNAME'."""
        code = self.proc.returncode
        if code is not None and code < 0:
            return f"was killed by {signal.Signals(-code).name}"
        return f"exited with code {code}"

    def stop(self, signum: int, timeout: float = 5.0) -> None:
        """Send signum to its process group; SIGKILL after timeout s."""
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signum)
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
            except ProcessLookupError:
                pass
        self.reader.join(2.0)


class Launcher:
    """Starts the SITL, then ArduCopter against it; watches both; stops both."""

    def __init__(self, options: LauncherOptions, out: TextIO | None = None):
        self.options = options
        self.out = out if out is not None else sys.stdout
        self._stop = False

    def _say(self, line: str) -> None:
        print(f"quadsr ardupilot: {line}", file=self.out, flush=True)

    def sitl_argv(self) -> list[str]:
        """The `quadsr sitl --ardupilot` command line."""
        o = self.options
        argv = [sys.executable, "-m", "quadsr.cli", "sitl", "--ardupilot", f"udp:127.0.0.1:{o.json_port}",
                "--vehicle", str(o.vehicle.source_path or o.vehicle_arg), "--no-gcs"]
        if o.log:
            argv += ["--log", str(o.log.resolve())]
        if o.sensors:
            argv += ["--sensors", o.sensors]
        if o.seed is not None:
            argv += ["--seed", str(o.seed)]
        return argv

    def arducopter_argv(self, vehicle_parm: Path) -> list[str]:
        """The arducopter command line: JSON physics here, the vehicle's home, its parameters last."""
        o = self.options
        home = o.vehicle.home
        defaults = ",".join(str(p) for p in [*o.defaults, vehicle_parm.resolve(), *o.extra_params])
        argv = [str(o.binary), "--model", "JSON:127.0.0.1", "--speedup", f"{o.speedup:g}",
                "--serial0", "tcp:0", "-I", str(o.instance),
                "--home", f"{home.lat},{home.lon},{home.alt},{math.degrees(o.vehicle.initial.yaw):g}",
                "--defaults", defaults]
        return argv + (["-w"] if o.wipe else [])

    def run(self) -> int:
        """Run until Ctrl-C/SIGTERM (exit 0) or until a child exits on its own (exit 1)."""
        o = self.options
        try:
            o.workdir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"--workdir {o.workdir}: cannot create it ({exc.strerror})") from None
        parm = o.workdir / "quadsr-vehicle.parm"
        write_parm(o.vehicle, parm)
        previous = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        sitl = copter = None
        try:
            sitl = _Child("the SITL", self.sitl_argv(), Path.cwd(), signal.SIGTERM, self.out)
            if not sitl.wait_for(LISTENING, 30.0):
                sitl.stop(signal.SIGTERM)
                raise UserError("the SITL did not start: " + " | ".join(list(sitl.lines)[-5:]))
            copter = _Child("ArduCopter", self.arducopter_argv(parm), o.workdir, signal.SIGKILL, self.out,
                            prefix="arducopter: ")
            p = o.mavlink_port
            self._say(f"ArduCopter pid {copter.proc.pid} (SITL pid {sitl.proc.pid}) in {o.workdir}; "
                      f"MAVLink tcp:127.0.0.1:{p} (SERIAL0), tcp:127.0.0.1:{p + 2}, tcp:127.0.0.1:{p + 3}; "
                      f"JSON physics udp:127.0.0.1:{o.json_port}; DataFlash logs in {o.workdir / 'logs'}; "
                      "Ctrl-C stops")
            code = self._watch(sitl, copter)
        finally:
            if copter is not None:
                copter.stop(signal.SIGKILL)
            if sitl is not None:
                sitl.stop(signal.SIGTERM)
            for s, handler in previous.items():
                signal.signal(s, handler)
        return code

    def _watch(self, sitl: _Child, copter: _Child) -> int:
        while not self._stop:
            for child, other in ((copter, sitl), (sitl, copter)):
                if child.proc.poll() is not None:
                    self._say(f"{child.name} {child.how_it_ended()} at simulated t={self._sim_time(sitl)}; "
                              f"stopping {other.name}")
                    return 1
            time.sleep(POLL_S)
        self._say("stopping ArduCopter and the SITL")
        return 0

    @staticmethod
    def _sim_time(sitl: _Child) -> str:
        with sitl.cond:
            for line in reversed(sitl.lines):
                m = SITL_T.search(line)
                if m:
                    return f"{float(m.group(1)):.1f} s (the SITL's last status line)"
        return "unknown"

    def _on_signal(self, signum, frame) -> None:
        self._stop = True
