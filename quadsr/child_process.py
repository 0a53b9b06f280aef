"""A child process whose output lines are kept (and optionally logged) as it prints, waited on by pattern."""

from __future__ import annotations

import functools
import os
import re
import signal
import subprocess
import threading
import time
from pathlib import Path

from bridge.shutdown import die_with_parent


class OutputProcess:
    """A child (killed when this process dies) with stdout+stderr read line by line into `lines`."""

    def __init__(self, args: list[str], cwd: Path | None = None, env: dict[str, str] | None = None,
                 log_path: Path | None = None):
        self.args = args
        self.log_path = log_path
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self.proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, cwd=cwd,
                                     env=env if env is not None else {**os.environ, "PYTHONUNBUFFERED": "1"},
                                     preexec_fn=functools.partial(die_with_parent, signal.SIGKILL))
        self._reader = threading.Thread(target=self._pump, daemon=True)
        self._reader.start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        log = open(self.log_path, "a", buffering=1, encoding="utf-8") if self.log_path else None
        try:
            for raw in self.proc.stdout:
                line = raw.decode("utf-8", "replace").rstrip("\n")
                if log is not None:
                    log.write(line + "\n")
                with self._cond:
                    self.lines.append(line)
                    self._cond.notify_all()
        finally:
            if log is not None:
                log.close()
            with self._cond:
                self._cond.notify_all()

    @property
    def output(self) -> str:
        """Everything printed so far."""
        with self._cond:
            return "\n".join(self.lines)

    def tail(self, n: int = 15) -> str:
        """The last n output lines."""
        with self._cond:
            return "\n".join(self.lines[-n:])

    def find(self, pattern: str | re.Pattern, timeout: float, start: int = 0) -> re.Match | None:
        """The first line (from index start) matching pattern within timeout s wall; None on timeout/exit."""
        rx = re.compile(pattern) if isinstance(pattern, str) else pattern
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for line in self.lines[start:]:
                    m = rx.search(line)
                    if m:
                        return m
                start = max(start, len(self.lines))
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (self.proc.poll() is not None and not self._reader.is_alive()):
                    return None
                self._cond.wait(min(remaining, 0.1))

    def stop(self, timeout: float = 10.0) -> int:
        """SIGTERM, wait (SIGKILL after timeout s), the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._reader.join(5.0)
        return self.proc.returncode
