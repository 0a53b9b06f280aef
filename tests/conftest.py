"""Shared fixtures: free UDP ports, `quadsr sitl` as a subprocess, a raw HIL companion (real UDP), and the
paper's vehicle with its true model and the in-process model plant (per test module)."""

from __future__ import annotations

import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from quadsr.child_process import OutputProcess

REPO = Path(__file__).resolve().parent.parent
LISTENING = re.compile(r"(?:listening for the (?:companion|autopilot) on|sending to the autopilot at) "
                       r"((?:udp|tcp):[\d.]+:(\d+))")


def run_watched(cmd: list[str], stall_s: float, cap_s: float = 1800.0,
                **popen) -> subprocess.CompletedProcess:
    """Run cmd to its end, its output captured (text); fails only when it prints nothing for stall_s seconds
    (a hang) or runs past cap_s: a long pipeline on a loaded machine is slow, not stuck, so a budget on its
    whole wall time would make the test depend on the machine's load."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **popen)
    out: dict[str, list[str]] = {"stdout": [], "stderr": []}
    last = [time.monotonic()]

    def pump(name: str, stream) -> None:
        for line in stream:
            out[name].append(line)
            last[0] = time.monotonic()

    pumps = [threading.Thread(target=pump, args=(n, getattr(proc, n)), daemon=True) for n in out]
    for t in pumps:
        t.start()
    start = time.monotonic()
    while proc.poll() is None:
        now = time.monotonic()
        if now - last[0] > stall_s or now - start > cap_s:
            proc.kill()
            proc.wait()
            stalled = now - last[0] > stall_s
            why = f"printed nothing for {stall_s:.0f} s" if stalled else f"ran past {cap_s:.0f} s"
            raise AssertionError(f"{' '.join(cmd)} {why}:\n{''.join(out['stdout'])[-3000:]}"
                                 f"{''.join(out['stderr'])[-3000:]}")
        time.sleep(0.2)
    for t in pumps:
        t.join()
    return subprocess.CompletedProcess(cmd, proc.returncode, "".join(out["stdout"]), "".join(out["stderr"]))


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def udp_port() -> int:
    """A free UDP port on 127.0.0.1."""
    return free_udp_port()


def altitude_sitl_args(seed: int) -> list[str]:
    """`quadsr sitl` flags for open-loop identification flights: a free HIL port, no GCS, no ground, 200 m up,
    ideal sensors, this seed, no status lines."""
    return ["--hil", "udp:127.0.0.1:0", "--no-gcs", "--ground", "none", "--initial-position", "0,0,-200",
            "--sensors", "ideal", "--seed", str(seed), "--status-interval", "0"]


class SitlProcess(OutputProcess):
    """A running `quadsr sitl` subprocess: its HIL address, its output lines, and how to stop it."""

    def __init__(self, args: list[str], timeout: float = 20.0):
        super().__init__([sys.executable, "-m", "quadsr.cli", "sitl", *args], cwd=REPO)
        match = self.wait_for(LISTENING, timeout)
        self.hil = match.group(1)
        self.hil_port = int(match.group(2))

    def wait_for(self, pattern: str | re.Pattern, timeout: float = 10.0, start: int = 0) -> re.Match:
        """The first output line (from index start) matching pattern; fails the test after timeout s."""
        m = self.find(pattern, timeout, start)
        if m is None:
            rx = re.compile(pattern) if isinstance(pattern, str) else pattern
            raise AssertionError(f"SITL printed no line matching {rx.pattern!r} within {timeout} s "
                                 f"(exit code {self.proc.poll()}); output:\n{self.output}")
        return m

    def status_lines(self) -> list[str]:
        """The status lines printed so far."""
        with self._cond:
            return [line for line in self.lines if " steps=" in line]

    def signal(self, signum: int) -> None:
        """Send a signal to the SITL."""
        self.proc.send_signal(signum)


@pytest.fixture
def start_sitl() -> Iterator[Callable[..., SitlProcess]]:
    """Factory: start_sitl(*flags) runs `quadsr sitl --hil udp:127.0.0.1:0 ...` and waits until it listens.

    Unless the flags name a ground link, the GCS link goes to a free port nobody listens on. Every SITL
    started is stopped at teardown.
    """
    started: list[SitlProcess] = []

    def start(*flags: str, timeout: float = 20.0) -> SitlProcess:
        args = list(flags)
        if "--hil" not in args:
            args += ["--hil", "udp:127.0.0.1:0"]
        if "--gcs" not in args and "--no-gcs" not in args:
            args += ["--gcs", f"udp:127.0.0.1:{free_udp_port()}"]
        sitl = SitlProcess(args, timeout)
        started.append(sitl)
        return sitl

    yield start
    for sitl in started:
        sitl.stop()


class RawCompanion:
    """A companion speaking raw MAVLink over bridge.link.UdpLink: whole datagrams, raw frames, no cleaning."""

    def __init__(self, hil: str, signing=None):
        from bridge.link import UdpLink

        self.link = UdpLink(remote=hil, system_id=1, component_id=1, signing=signing)
        self.frames: list[tuple[object, bytes]] = []  # the last step received

    def hello(self) -> None:
        """Send a HEARTBEAT (connects to the SITL)."""
        from bridge.messages import encode_heartbeat

        self.link.send([encode_heartbeat()])

    def datagram(self, timeout: float = 2.0) -> list[tuple[object, bytes]]:
        """The (message, raw frame) pairs of the next datagram with valid frames; fails after timeout s."""
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError(f"no datagram from the SITL within {timeout} s")
            frames = self.link.recv_frames(remaining)
            if frames:
                return frames

    def step_datagram(self, timeout: float = 2.0, after: int = -1) -> list[tuple[object, bytes]]:
        """The next datagram that ends with a HIL_SENSOR of time_usec > after (a step; skips re-sent ones)."""
        deadline = time.monotonic() + timeout
        while True:
            frames = self.datagram(max(deadline - time.monotonic(), 0.0))
            if frames[-1][0].get_type() == "HIL_SENSOR" and frames[-1][0].time_usec > after:
                self.frames = frames
                return frames

    def step(self, throttles, timeout: float = 2.0) -> list[tuple[object, bytes]]:
        """Answer the current step with these throttles (sent as given) and return the next step's frames."""
        t = self.frames[-1][0].time_usec
        self.reply(t, throttles)
        return self.step_datagram(timeout, after=t)

    def reply(self, time_usec: int, throttles, lockstep: bool = True) -> None:
        """Send HIL_ACTUATOR_CONTROLS with controls[0..3] = throttles exactly as given (NaN, 2.0, ...)."""
        from bridge.messages import encode_hil_actuator_controls

        self.link.send([encode_hil_actuator_controls(time_usec, list(throttles), lockstep)])

    def connect(self, timeout: float = 5.0) -> list[tuple[object, bytes]]:
        """HEARTBEAT until the time-0 datagram arrives; return it."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.hello()
            try:
                frames = self.step_datagram(0.2)
            except AssertionError:
                continue
            return frames
        raise AssertionError(f"the SITL did not answer within {timeout} s")

    def close(self) -> None:
        """Close the socket."""
        self.link.close()


@pytest.fixture
def raw_companion() -> Iterator[Callable[..., RawCompanion]]:
    """Factory: raw_companion(hil, signing=None) -> RawCompanion; closed at teardown."""
    made: list[RawCompanion] = []

    def make(hil: str, signing=None) -> RawCompanion:
        c = RawCompanion(hil, signing)
        made.append(c)
        return c

    yield make
    for c in made:
        c.close()


@pytest.fixture(scope="module")
def vehicle():
    """The paper's vehicle (sitl/vehicles/fang-chen-buaa.yaml) as a VehicleConfig."""
    from bridge.vehicle import load_vehicle

    return load_vehicle("fang-chen-buaa")


@pytest.fixture(scope="module")
def model(vehicle):
    """The exact model (identification.true_model) of the `vehicle` fixture."""
    from identification.true_model import true_model

    return true_model(vehicle)


@pytest.fixture(scope="module")
def plant(model, vehicle):
    """The in-process simulator of `model` with the vehicle's motor lag (controller.simulate.ModelPlant)."""
    from controller.simulate import ModelPlant

    return ModelPlant(model, motor_time_constant=vehicle.motor.time_constant)


def assert_case2_tracked(folder: Path, settle_s: float, tolerance_m: float) -> None:
    """A Case II flight through a real autopilot wrote steps.csv with setpoints at >= 50 Hz of the autopilot's
    clock, no gap an offboard/GUIDED loss timeout would end the flight on (>= 1 s: shorter ones come from this
    process being descheduled on a loaded machine), the truth within tolerance_m (m) of (2, 4, -0.3 t) from
    settle_s (s) on, and metrics.md and tracking.png."""
    import csv
    import math

    rows = list(csv.DictReader((folder / "steps.csv").open()))
    times = [float(r["t"]) for r in rows]
    assert len(rows) >= 50 * (settle_s + 0.5)
    assert max(b - a for a, b in zip(times, times[1:], strict=False)) < 1.0
    late = [r for r in rows if float(r["t"]) >= settle_s]
    assert late
    for r in late:
        t = float(r["t"])
        truth = (float(r["true_x"]), float(r["true_y"]), float(r["true_z"]))
        assert math.dist(truth, (2.0, 4.0, -0.3 * t)) < tolerance_m, (t, truth)
    assert (folder / "metrics.md").is_file() and (folder / "tracking.png").is_file()
