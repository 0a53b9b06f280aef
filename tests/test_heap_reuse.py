"""The C heap kept for reuse while identification runs (identification.heap_reuse)."""

import platform
import resource

import numpy as np

from identification.heap_reuse import reused_heap

MB = 1024 * 1024
PAGE = resource.getpagesize()


def _faults_per_page(size: int, rounds: int) -> float:
    """Minor page faults per page touched over `rounds` rounds of two arrays of `size` bytes each filled,
    then both freed."""
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
    # above glibc's default 128 KiB mmap threshold, under a huge page's 2 MiB (a kernel with transparent huge
    # pages "always" maps a 2 MiB-aligned block in one fault, and numpy asks for them from 4 MiB)
    size = MB
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


def test_an_error_inside_sets_the_defaults_back():
    glibc = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"
    try:
        with reused_heap():
            _faults_per_page(MB, 1)
            raise RuntimeError("a fit that fails")
    except RuntimeError:
        pass
    if glibc:
        after = _faults_per_page(MB, 10)
        assert after > 0.9, f"{after:.3f} page faults per page touched after a failed block"
