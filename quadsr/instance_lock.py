"""Hold a simulator instance number for this process, so that parallel runs (and parallel test sessions)
never pick the same one between choosing it and binding its ports: an exclusive lock on a file in the temp
folder, released when the returned file is closed or the process ends."""

from __future__ import annotations

import fcntl
import tempfile
from pathlib import Path
from typing import IO


def hold(kind: str, n: int) -> IO[bytes] | None:
    """Hold instance n of kind ('px4', 'ardupilot') for this process; None when another process holds it."""
    path = Path(tempfile.gettempdir()) / f"quadsr-{kind}-instance-{n}.lock"
    lock = open(path, "ab")  # noqa: SIM115 (held open: the lock lives as long as the file)
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        lock.close()
        return None
    return lock
