"""Threads for the engine's read-only bulk work (building the index, sweeping cells).

Kernels that only read shared state and write disjoint slots run with numba's ``nogil`` in a
pool of Python threads. The count comes from ``KNNREFINE_THREADS`` when set (1 turns threads
off, as a Dask worker that runs one task per core wants), else from the cores this process
may use, at most MAX_THREADS.
"""

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

MAX_THREADS = 8
_pool: list = []
# a forked child has the pool object but none of its threads: it makes its own
os.register_at_fork(after_in_child=_pool.clear)


def workers():
    """How many threads the engine may use."""
    env = os.environ.get("KNNREFINE_THREADS", "").strip()
    if env:
        try:
            return max(1, min(int(env), MAX_THREADS))
        except ValueError:
            raise ValueError(
                f"KNNREFINE_THREADS must be a whole number of threads, got {env!r}"
            ) from None
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_THREADS))


def run_all(task, count):
    """[task(0), ..., task(count - 1)], on the pool's threads when count > 1."""
    if count <= 1:
        return [task(j) for j in range(count)]
    if not _pool:
        _pool.append(ThreadPoolExecutor(MAX_THREADS, thread_name_prefix="knnrefine"))
    return list(_pool[0].map(task, range(count)))


def in_chunks(call, m, threads=None, least=256):
    """call(start, stop) over ranges that split [0, m) evenly among ``threads`` (default
    ``workers()``), each at least ``least`` long (one range when m is small)."""
    chunks = max(1, min(workers() if threads is None else int(threads), m // least))
    edges = np.linspace(0, m, chunks + 1).astype(np.int64)
    return run_all(lambda j: call(edges[j], edges[j + 1]), chunks)
