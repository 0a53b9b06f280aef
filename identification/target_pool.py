"""Independent targets fitted side by side: forked worker processes, each result as it comes in.

identify fits each target from the same rows with the same seed and nothing shared, so a target's model is
the same whether it is fitted alone, after another or beside one; only the wall time changes. The workers
are forked (they inherit the rows and the settings, nothing is pickled on the way in; only the results
come back), die with the parent (PR_SET_PDEATHSIG), and are joined before the results are used.

What comes back is pickled, and sympy rebuilds a pickled expression by evaluating it: a number times a sum,
kept as written (c*(u1**2 + u2**2), identification.sparse), would come back multiplied out. Expressions
travel as `frozen` trees instead and are rebuilt unevaluated (`thawed`), node for node.

A fork is only safe from a process with one thread (another thread may hold a lock the child would wait
on forever), and a daemonic process (a Dask or multiprocessing worker) may not have children: there, and
where fork does not exist, the targets are fitted one after another (`processes_for` says why).
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import sympy

from bridge.shutdown import die_with_parent

_JOB: Callable[[str], Any] | None = None  # the job the forked workers run (set before the fork)


def default_jobs() -> int:
    """The processes identify uses by default: the cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def processes_for(jobs: int, targets: int) -> tuple[int, str]:
    """(worker processes to use for `targets` targets with at most `jobs`, why fewer when 1 is used)."""
    n = min(int(jobs), int(targets))
    if n <= 1:
        return 1, ""
    if not sys.platform.startswith("linux"):
        return 1, "one process: worker processes are forked, on Linux only"
    if multiprocessing.current_process().daemon:
        return 1, "one process: this process is a daemonic worker (Dask, multiprocessing), which may not fork"
    if threading.active_count() > 1:
        return 1, "one process: this process runs other threads, and a fork beside them is unsafe"
    return n, ""


def frozen(expr: sympy.Expr) -> Any:
    """expr as nested (sympy class, args) tuples, its atoms as they are: pickled without re-evaluation."""
    if not expr.args:
        return expr
    return (expr.func, tuple(frozen(a) for a in expr.args))


def thawed(tree: Any) -> sympy.Expr:
    """The expression `frozen` gave, rebuilt node for node (unevaluated: the same tree, the same text)."""
    if not isinstance(tree, tuple):
        return tree
    func, args = tree
    return func(*(thawed(a) for a in args), evaluate=False)


def _worker_start() -> None:
    """In each worker: die with the parent; leave Ctrl-C to the parent (it ends the pool), and let the pool's
    SIGTERM end the worker (not the parent's inherited handler, which would raise in the job)."""
    die_with_parent(signal.SIGKILL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _run(name: str) -> tuple[str, Any]:
    assert _JOB is not None
    return name, _JOB(name)


def map_targets(job: Callable[[str], Any], names: Sequence[str], processes: int,
                first: Sequence[str] = ()) -> Iterator[tuple[str, Any]]:
    """(name, job(name)) for each name: on `processes` forked workers when > 1, as each finishes; else in
    the order of names, one after another.

    first: names the workers start before the others (the targets expected to take longest: started last,
    one of them would leave the other workers idle at the end)."""
    global _JOB
    if processes <= 1:
        for name in names:
            yield name, job(name)
        return
    started = [n for n in first if n in names] + [n for n in names if n not in first]
    _JOB = job
    pool = multiprocessing.get_context("fork").Pool(processes, initializer=_worker_start)
    try:
        yield from pool.imap_unordered(_run, started)
        pool.close()
    finally:
        pool.terminate()
        pool.join()  # reaped: their CPU time counts as this process's children's
        _JOB = None
