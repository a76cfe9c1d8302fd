"""Threads: how many this process may use, and the pools voxtool's kernels run on.

Kernels release the GIL, so plain threads run them on every core. One pool per thread count
is shared by every map of the process (ray casting and tree updates take turns on it).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

from voxtool.errors import ParameterError

MAX_THREADS = 1024

# The hash map casts each scan in an OpenMP parallel region (numba's omp layer). Between scans
# OpenMP's idle worker spins, 300,000 rounds by default: with another process busy on the same
# cores it takes that process's core and every scan waits for the preempted thread (quick_shack,
# one busy process beside it on 2 cores: median 7.4 ms, p95 23.4 ms a scan, worse than one thread's
# 3.8 / 5.4). A short spin gives the core back: 3.5 / 4.7 ms under that load, and 2.39-2.52 ms idle
# against 2.29-2.46 (docs/design/backends.md). Set before libgomp starts (at numba's first
# parallel region); a user's own OMP_WAIT_POLICY or GOMP_SPINCOUNT wins.
if "OMP_WAIT_POLICY" not in os.environ:
    os.environ.setdefault("GOMP_SPINCOUNT", "1000")


def usable_cores() -> int:
    """Cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def resolve_threads(threads: int | None) -> int:
    """A thread count as given (`--threads`), or the usable cores for None / 0."""
    if threads is None or threads == 0:
        return usable_cores()
    if not 1 <= threads <= MAX_THREADS:
        raise ParameterError(f"threads={threads} must lie in 1..{MAX_THREADS} (0: the usable cores)")
    return int(threads)


_POOLS: dict[int, ThreadPoolExecutor] = {}


def thread_pool(threads: int) -> ThreadPoolExecutor:
    """The shared pool of `threads` worker threads."""
    pool = _POOLS.get(threads)
    if pool is None:
        pool = _POOLS[threads] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="voxtool-worker")
    return pool


def _forget_pools_in_child() -> None:
    # a forked child inherits the pools but none of their threads: work submitted to one would
    # wait forever (a multiprocessing worker casting rays hung). The child starts pools anew.
    _POOLS.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pools_in_child)


def run_parts(threads: int, work, parts: list) -> list:
    """[work(p) for p in parts], spread over the pool (on this thread when one thread or part)."""
    if threads <= 1 or len(parts) <= 1:
        return [work(p) for p in parts]
    return list(thread_pool(threads).map(work, parts))


def one_blas_thread():
    """One BLAS thread until restore_original_limits() (or the end of a `with` block): numpy's
    threaded BLAS (a scan's points times its rotation) would spin on every core the kernels
    run on, whoever imported numpy first. The command line also sets OPENBLAS_NUM_THREADS; a
    library caller or a `dask worker` did not: clean of a 64-beam street took 1.64-1.83 s in a
    Python session against 1.14-1.18 s with one BLAS thread. Every scan loop runs under it."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


def ordered_map(work, items, threads: int, ahead: int = 8):
    """work(item) for each item of an iterable, in order, computed up to `ahead` items in advance
    on the shared pool (work that releases the GIL: numba kernels, zstd), as a generator: memory
    is bounded by the items in flight, not the stream."""
    from collections import deque

    if threads <= 1:
        yield from map(work, items)
        return
    pool = thread_pool(threads)
    pending: deque = deque()
    for item in items:
        pending.append(pool.submit(work, item))
        if len(pending) >= ahead:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()
