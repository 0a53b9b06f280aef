"""The C heap kept for reuse while identification runs (glibc's malloc; elsewhere nothing changes).

A target's fit allocates and frees numpy temporaries of a few MB thousands of times (15,000 rows x a few
columns). glibc's malloc gives a freed block at the top of its heap back to the kernel once more than
M_TRIM_THRESHOLD is free there, and maps a block above M_MMAP_THRESHOLD afresh each time; either way the
next temporary's pages are faulted in and zeroed by the kernel again. On seed 71's heavy closed loop that
was 1.4 million page faults and some 50 s of system time over its 300 s of CPU. Inside `reused_heap`
blocks up to 32 MiB (glibc's largest M_MMAP_THRESHOLD) come from the heap and freed memory stays there;
on leaving, glibc's documented defaults are set back and the free memory returned (malloc_trim).
Only where memory comes from changes: the arithmetic, and so every model, is the same to the bit.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import platform
from collections.abc import Iterator

# mallopt(3) parameters (malloc.h)
M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3

KEPT_MMAP_THRESHOLD = 32 * 1024 * 1024  # bytes: glibc's largest (HEAP_MAX_SIZE / 2 on 64-bit)
KEPT_TRIM_THRESHOLD = 2**31 - 1  # bytes (mallopt takes an int): in effect never trimmed while kept
KEPT_TOP_PAD = 64 * 1024 * 1024  # bytes the heap grows by beyond each request (fewer brk calls)
DEFAULT = 128 * 1024  # bytes: glibc's default for all three (mallopt(3))


def _libc() -> ctypes.CDLL | None:
    """The C library when it is glibc (the one with mallopt and malloc_trim), else None."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
    return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None


def _set(libc: ctypes.CDLL, settings: dict[int, int]) -> list[bool]:
    """mallopt each (parameter, value), every one tried; whether glibc took each."""
    return [bool(libc.mallopt(ctypes.c_int(p), ctypes.c_int(v))) for p, v in settings.items()]


@contextlib.contextmanager
def reused_heap() -> Iterator[bool]:
    """Keep freed C heap memory for reuse inside the block (module docstring); yields whether it could
    (False off glibc, where nothing changes). Processes forked inside the block inherit the setting."""
    libc = _libc()
    took = [] if libc is None else _set(libc, {M_MMAP_THRESHOLD: KEPT_MMAP_THRESHOLD,
                                               M_TRIM_THRESHOLD: KEPT_TRIM_THRESHOLD,
                                               M_TOP_PAD: KEPT_TOP_PAD})
    try:
        yield bool(took) and all(took)
    finally:
        if any(took):
            # glibc's defaults (its threshold no longer rises by itself once set: 128 KiB as at start)
            _set(libc, {M_MMAP_THRESHOLD: DEFAULT, M_TRIM_THRESHOLD: DEFAULT, M_TOP_PAD: DEFAULT})
            libc.malloc_trim(ctypes.c_size_t(0))
