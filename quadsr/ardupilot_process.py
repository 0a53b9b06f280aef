"""Start `quadsr ardupilot` (ArduCopter + quadsr's SITL as its JSON physics) as a child process on a free
ArduPilot instance, read its output, and stop it."""

from __future__ import annotations

import os
import random
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO

from quadsr.instance_lock import hold

PID = re.compile(r"ArduCopter pid (\d+)")
TCP_BASE, UDP_BASE = 5760, 9002  # ArduPilot's SERIAL0 MAVLink TCP port and JSON physics UDP port, + 10*N


def claim_free_instance(low: int = 100, high: int = 256) -> tuple[int, IO[bytes]]:
    """An ArduPilot instance N in [low, high) nobody else holds whose ports (TCP 5760+10N, 5762+10N,
    5763+10N; UDP 9002+10N) are free now, and its held lock (quadsr.instance_lock: parallel runs never pick
    the same N). ArduPilot keeps N in one byte (0..255); the default range keeps its ports (6760-8313,
    10002-11552) clear of PX4's 4560+N, 14540+N, 14550 and 18570+N."""
    rng = random.Random(os.getpid() ^ time.monotonic_ns())
    for _ in range(100):
        n = rng.randrange(low, high)
        lock = hold("ardupilot", n)
        if lock is None:
            continue
        socks = []
        try:
            for port in (TCP_BASE + 10 * n, TCP_BASE + 2 + 10 * n, TCP_BASE + 3 + 10 * n):
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                socks.append(s)
                s.bind(("127.0.0.1", port))
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            socks.append(s)
            s.bind(("127.0.0.1", UDP_BASE + 10 * n))
            return n, lock
        except OSError:
            lock.close()
            continue
        finally:
            for s in socks:
                s.close()
    raise RuntimeError(f"no free ArduPilot instance in [{low}, {high})")


class ArduPilotProcess:
    """`quadsr ardupilot` as a child process; its output lines are collected in `lines`."""

    def __init__(self, ardupilot: Path, workdir: Path, tlog: Path | None = None, instance: int | None = None,
                 speedup: float = 100.0, extra: list[str] | None = None):
        self._held: IO[bytes] | None = None  # the instance's lock, while this process runs it
        if instance is None:
            instance, self._held = claim_free_instance()
        self.instance = instance
        self.workdir = workdir
        self.tlog = tlog
        argv = [sys.executable, "-m", "quadsr.cli", "ardupilot", "--ardupilot", str(ardupilot),
                "-I", str(self.instance), "--speedup", f"{speedup:g}", "--workdir", str(workdir), "--wipe"]
        argv += ["--log", str(tlog)] if tlog else []
        self.proc = subprocess.Popen(argv + list(extra or []), stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True,
                                     env={**os.environ, "PYTHONUNBUFFERED": "1"})
        self.lines: list[str] = []
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    @property
    def mavlink(self) -> str:
        """ArduCopter's SERIAL0 address for pymavlink."""
        return f"tcp:127.0.0.1:{TCP_BASE + 10 * self.instance}"

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait_for(self, rx: re.Pattern, timeout: float = 60.0) -> re.Match:
        """The first output line matching rx; RuntimeError after timeout s of wall time or if it exits."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for line in list(self.lines):
                m = rx.search(line)
                if m:
                    return m
            if self.proc.poll() is not None and not self.reader.is_alive():
                break
            time.sleep(0.05)
        raise RuntimeError(f"no line matching {rx.pattern!r}; output:\n" + "\n".join(self.lines[-40:]))

    def arducopter_pid(self, timeout: float = 60.0) -> int:
        """ArduCopter's process id, as the launcher prints it."""
        return int(self.wait_for(PID, timeout).group(1))

    def stop(self) -> int:
        """SIGTERM (both children stop), wait; SIGKILL after 20 s. Returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.reader.join(5)
        if self._held is not None:
            self._held.close()
            self._held = None
        return self.proc.returncode
