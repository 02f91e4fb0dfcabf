"""The builders' array passes spread over threads.

NumPy releases the GIL inside its array loops (ufuncs, reductions, sorts, ``bincount``,
most gathers), so independent passes over large arrays run in parallel on threads of one
process: a plane tree's split search is per node (the level's nodes are cut into runs,
one per thread), the kd-tree's clipping of the straddlers is per side, and the BVH's split
search is per group of nodes of one size (large groups cut into runs). Measured on 2
cores (AMD EPYC, 2026-12-07): ufuncs, sorts and gathers on arrays of 100k float64 1.7-2x
faster on two threads, ``np.bincount`` 1.4x, ``np.repeat`` 1.1x; a whole build less (the
Python between the calls holds the GIL): the camel's kd-tree 1.15x, its BSP tree 1.1x;
the 1.1M-triangle herd's BVH 7.7 s against 8.8 s with its search on one thread
(2026-12-08). Every
result is computed exactly as on one thread (the same operations on the same values, only
in other threads), so a structure's arrays do not depend on the thread count;
``tests/test_build_threads.py`` checks that byte for byte.

The thread count is ``JRT_BUILD_THREADS`` when set (1: everything in the calling thread),
else the cores this process may run on, at most :data:`DEFAULT_MAX_THREADS`. The pool is
made on first use (importing accel starts no thread) and shared by every build; a pass
started from one of its threads runs in that thread (no nested waits on the pool).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numpy as np

ENV_VARIABLE = "JRT_BUILD_THREADS"
#: Threads by default, at most: beyond a few, a level's passes are too short to share.
DEFAULT_MAX_THREADS = 8
#: Rows (a level's references, a side's straddlers) each thread must get for a pass to be
#: spread: below it, handing the work to the pool (about 0.1 ms a pass) and the GIL between
#: NumPy calls on small arrays cost more than the second core saves (2 cores, 2026-12-07:
#: 16384 kept most of the camel's kd-tree levels on one thread, 0.90 s a build against
#: 0.77 s with 4096; the teapot, 6k triangles, stays on one thread either way).
MIN_ROWS_PER_THREAD = 4096

_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None
_pool_threads = 0
_in_pool = threading.local()

T = TypeVar("T")
R = TypeVar("R")


def build_threads() -> int:
    """The threads a build uses (``JRT_BUILD_THREADS``, else the usable cores, at most
    :data:`DEFAULT_MAX_THREADS`); a ValueError naming the variable for a bad value."""
    value = os.environ.get(ENV_VARIABLE, "").strip()
    if not value:
        cores = (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                 else os.cpu_count() or 1)
        return max(1, min(cores, DEFAULT_MAX_THREADS))
    try:
        threads = int(value)
    except ValueError:
        threads = 0
    if threads < 1:
        raise ValueError(f"{ENV_VARIABLE} must be a positive integer (the threads a "
                         f"structure's build uses), got {value!r}")
    return threads


def _worker(fn: Callable[[T], R]) -> Callable[[T], R]:
    def run(item: T) -> R:
        _in_pool.active = True
        try:
            return fn(item)
        finally:
            _in_pool.active = False
    return run


def threads_for(rows: int) -> int:
    """The threads to spread a pass over ``rows`` rows: :func:`build_threads`, or 1 below
    :data:`MIN_ROWS_PER_THREAD` rows a thread (there, handing the work to the pool costs
    more than it saves)."""
    return max(1, min(build_threads(), rows // MIN_ROWS_PER_THREAD))


def thread_map(fn: Callable[[T], R], items: Iterable[T], threads: int | None = None) -> list[R]:
    """``[fn(item) for item in items]``, the items spread over ``threads`` threads
    (default :func:`build_threads`); in the calling thread when there is one thread, one
    item, or the call comes from a pass already on the pool. Exceptions propagate as from
    the loop."""
    global _pool, _pool_threads
    items = list(items)
    threads = build_threads() if threads is None else threads
    if threads == 1 or len(items) < 2 or getattr(_in_pool, "active", False):
        return [fn(item) for item in items]
    with _lock:
        if _pool is None or _pool_threads != threads:
            if _pool is not None:
                _pool.shutdown(wait=False)
            _pool = ThreadPoolExecutor(threads, thread_name_prefix="accel-build")
            _pool_threads = threads
        pool = _pool
    return list(pool.map(_worker(fn), items))


def node_chunks(counts: np.ndarray, size: int | None = None, parts: int = 1):
    """Consecutive runs of at most ``size`` nodes (None: any number) of a level whose
    references (rows) are sorted by node (``counts`` per node): (first node, end node,
    first reference, end reference).

    With ``parts`` > 1 the runs are also cut where the references reach each ``1/parts`` of
    the level (at a node boundary), so that a level of few large nodes still gives a run to
    each of ``parts`` threads.
    """
    k = counts.shape[0]
    if k == 0:
        return
    ends = np.cumsum(counts)
    cuts = set(range(0, k, size or k))
    if parts > 1 and k > 1:
        share = ends[-1] * np.arange(1, parts) / parts
        cuts.update(int(i) for i in np.searchsorted(ends, share, side="right") if 0 < i < k)
    starts = sorted(cuts)
    for first, end in zip(starts, starts[1:] + [k], strict=True):
        yield first, end, int(ends[first] - counts[first]), int(ends[end - 1])
