"""Process life cycle: SIGINT/SIGTERM handled once (later ones absorbed), children that die with their parent.

`StopSignals` is the one place a long-lived process installs its SIGINT/SIGTERM handlers. The first signal
asks to stop (a flag, or a KeyboardInterrupt raised in the main thread); every later one is absorbed until
the process exits, so a second SIGTERM sent while the process is already shutting down (writing its logs,
stopping its children) cannot kill it half-way. After a stop was asked for, leaving the block ignores both
signals for the rest of the process's life: restoring the default handlers (or letting Python reset them at
interpreter exit) would make a signal that arrives during the rest of the shutdown fatal.

`die_with_parent` is a `preexec_fn` for subprocess.Popen: on Linux the child gets SIGTERM when its parent
dies (prctl PR_SET_PDEATHSIG), even if the parent is killed with SIGKILL.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
from collections.abc import Callable
from types import FrameType

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
PR_SET_PDEATHSIG = 1  # linux/prctl.h
# Looked up once here, in the parent: a preexec_fn runs between fork and exec and should do nothing heavy.
_PRCTL = ctypes.CDLL(None).prctl if sys.platform.startswith("linux") else None


class StopSignals:
    """Context manager: the first SIGINT/SIGTERM asks to stop, later ones are absorbed (idempotent shutdown).

    raise_interrupt=False: the first signal only sets `.requested` (a loop polls it).
    on_stop: called (in the main thread, from the handler) on the first signal.
    raise_interrupt=True: the first signal also raises KeyboardInterrupt in the main thread (as Ctrl-C does).
    Outside the main thread nothing is installed (Python delivers signals to the main thread only).
    """

    def __init__(self, raise_interrupt: bool = False, on_stop: Callable[[], None] | None = None):
        self.raise_interrupt = raise_interrupt
        self.on_stop = on_stop
        self.requested = False
        self.signum: int | None = None
        self._previous: dict[int, object] = {}

    @property
    def exit_code(self) -> int:
        """The shell's exit code for the signal received: 128 + its number (130 SIGINT, 143 SIGTERM)."""
        return 128 + (self.signum or signal.SIGINT)

    @property
    def name(self) -> str:
        """The received signal's name (SIGINT when none was received)."""
        return signal.Signals(self.signum or signal.SIGINT).name

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.requested:  # already stopping: a repeated signal must not interrupt the shutdown
            return
        self.requested = True
        self.signum = signum
        if self.on_stop is not None:
            self.on_stop()
        if self.raise_interrupt:
            raise KeyboardInterrupt

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in STOP_SIGNALS}
        return self

    def __exit__(self, *exc: object) -> None:
        if self.requested:
            # On its way out: ignore later signals in the kernel. Python's own handlers would be reset to
            # the (fatal) defaults during interpreter finalization, after this block.
            for s in STOP_SIGNALS:
                signal.signal(s, signal.SIG_IGN)
            return
        for s, handler in self._previous.items():
            # A nested StopSignals that received a signal kept its handler: the process is stopping, leave it.
            if signal.getsignal(s) == self._handle:
                signal.signal(s, handler)  # type: ignore[arg-type]
        self._previous = {}


def die_with_parent(signum: int = signal.SIGTERM) -> None:
    """In a child before exec (Popen preexec_fn): get `signum` when the parent process dies (Linux only).

    SIGTERM (default) lets a quadsr child stop cleanly; pass SIGKILL (functools.partial) for a third-party
    child that may ignore SIGTERM.
    """
    if _PRCTL is None:
        return
    _PRCTL(PR_SET_PDEATHSIG, signum, 0, 0, 0)
    if os.getppid() == 1:  # the parent died before prctl took effect
        os.kill(os.getpid(), signum)
