"""Independent fits side by side: ``WORKERS`` forked processes where the platform has fork (the benchmark's budget is
two cores). Shared by forward selection (:mod:`.pipeline`) and the joint refit (:mod:`.joint_step`)."""

from __future__ import annotations

import multiprocessing
import os
import time
from typing import Callable

#: Processes scoring candidates side by side (the benchmark's budget is two cores).
WORKERS = 2

_TASK: Callable[[int], object] | None = None  # the task of the forked workers (inherited, not pickled)


def _run_task(i: int):
    return _TASK(i)


def fork_map(task: Callable[[int], object], n: int) -> list:
    """``[task(i) for i in range(n)]``, in ``WORKERS`` forked processes where the platform has fork
    (the tasks are independent fits; the results are the same as in one process)."""
    global _TASK
    workers = min(WORKERS, n, _cores())
    if workers < 2 or "fork" not in multiprocessing.get_all_start_methods():
        return [task(i) for i in range(n)]
    _TASK = task
    try:
        with multiprocessing.get_context("fork").Pool(workers) as pool:
            return pool.map(_run_task, range(n), chunksize=1)
    finally:
        _TASK = None


def _cores() -> int:
    """Cores this process may run on (its affinity where the platform has one: ``identify_time --threads 1`` pins the
    process to one core, and two workers there would only take turns)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def cpu_seconds() -> float:
    """CPU seconds of this process and of its finished child processes (the forked scoring workers)."""
    own = time.process_time()
    try:
        import resource  # POSIX only
    except ImportError:  # pragma: no cover - without it the workers' time is not counted
        return own
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own + children.ru_utime + children.ru_stime
