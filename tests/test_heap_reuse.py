"""The C heap kept for reuse while identification runs (identification.heap_reuse)."""

import platform
import resource

import numpy as np

from identification.heap_reuse import reused_heap

MB = 1024 * 1024
PAGE = resource.getpagesize()


def _faults_per_page(size: int, rounds: int) -> float:
    """Minor page faults per page touched over `rounds` rounds of two arrays of `size` bytes each filled,
    then both freed (the top of the heap then holds both: glibc's default trims it or maps them anew)."""
    count = size // 8
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(rounds):
        a = np.ones(count)
        b = np.ones(count)
        del a, b
    after = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    return (after - before) / (rounds * 2 * size / PAGE)


def test_freed_memory_is_reused_inside_and_returned_after():
    glibc = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"
    size = 2 * MB  # under numpy's 4 MiB, above which it asks for huge pages (fewer faults either way)
    with reused_heap() as kept:
        assert kept == glibc
    if not glibc:
        return
    # after a block, glibc's documented defaults (a fixed 128 KiB threshold): 2 MiB blocks are mapped, and
    # faulted in, anew each time
    outside = _faults_per_page(size, 10)
    assert outside > 0.9, f"{outside:.3f} page faults per page touched after reused_heap"
    with reused_heap():
        _faults_per_page(size, 1)  # the heap grows once
        inside = _faults_per_page(size, 10)
    assert inside < 0.05, f"{inside:.3f} page faults per page touched inside reused_heap"
    again = _faults_per_page(size, 10)
    assert again > 0.9, f"{again:.3f} page faults per page touched after reused_heap"


def test_nothing_else_changes():
    with reused_heap():
        x = np.linspace(0.0, 1.0, 100_001)
        inside = float(np.sum(np.sin(x) * np.cos(3 * x)))
    assert inside == float(np.sum(np.sin(x) * np.cos(3 * x)))
