"""Start `quadsr sitl` as a child process on free loopback ports, and stop it cleanly."""

from __future__ import annotations

import os
import queue
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

from bridge.errors import UserError
from bridge.shutdown import die_with_parent


def free_udp_port(host: str = "127.0.0.1") -> int:
    """Return a UDP port on `host` that was free a moment ago (bound once, then released)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((host, 0))
        return sock.getsockname()[1]


class SitlProcess:
    """A `quadsr sitl` child process on free ports, its output echoed to a log file, stopped on exit."""

    READY_MARKS = ("listening for the companion", "listening for the autopilot", "sending to the autopilot")

    def __init__(self, extra_args: list[str] | None = None, log_path: Path | None = None,
                 hil_port: int | None = None, gcs: str | None = None, hil: str | None = None):
        self.hil_port = hil_port or free_udp_port()
        self.hil = hil or f"udp:127.0.0.1:{self.hil_port}"
        self.args = [sys.executable, "-m", "quadsr.cli", "sitl", "--hil", self.hil]
        self.args += ["--gcs", gcs] if gcs else ["--no-gcs"]
        self.args += list(extra_args or [])
        self.log_path = log_path
        self.proc: subprocess.Popen | None = None
        self._lines: queue.Queue[str] = queue.Queue()
        self.output: list[str] = []
        self._pump_thread: threading.Thread | None = None

    def start(self, timeout: float = 20.0) -> SitlProcess:
        """Start the SITL and wait until it says it is listening; raise UserError if it does not."""
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        if self.log_path:
            Path(self.log_path).parent.mkdir(parents=True, exist_ok=True)
        self.proc = subprocess.Popen(self.args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, env=env, preexec_fn=die_with_parent)
        self._pump_thread = threading.Thread(target=self._pump, daemon=True)
        self._pump_thread.start()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self._lines.get(timeout=0.1)
            except queue.Empty:
                if self.proc.poll() is not None:
                    break
                continue
            if any(mark in line for mark in self.READY_MARKS):
                return self
        code = self.proc.poll()
        self.stop()
        why = f"exited with code {code}" if code is not None else f"did not start within {timeout:.0f} s"
        raise UserError(f"the SITL {why}: {' '.join(self.args)}\n" + "".join(self.output[-20:]))

    def _pump(self) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        log = open(self.log_path, "a", buffering=1) if self.log_path else None
        try:
            for line in self.proc.stdout:
                self.output.append(line)
                self._lines.put(line)
                if log:
                    log.write(line)
        finally:
            if log:
                log.close()

    def stop(self, timeout: float = 5.0) -> int | None:
        """Stop the SITL (SIGTERM, then SIGKILL after `timeout` s); return its exit code."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self._pump_thread is not None:  # its last lines reach the log before this process may exit
            self._pump_thread.join(timeout)
        return self.proc.returncode

    def __enter__(self) -> SitlProcess:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
