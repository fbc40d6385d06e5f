"""Threads for the engine's read-only bulk work (building the index, sweeping cells).

Kernels that only read shared state and write disjoint slots run with numba's ``nogil`` in a
pool of Python threads. The count comes from ``KNNREFINE_THREADS`` when set (1 turns threads
off, as a Dask worker that runs one task per core wants), else from the cores this process
may use, at most MAX_THREADS.
"""

import os
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait

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


def run_all(task, count, meanwhile=None, every=0.05):
    """[task(0), ..., task(count - 1)], on the pool's threads when count > 1; the calling
    thread calls ``meanwhile()`` every ``every`` seconds while it waits (progress, Ctrl-C:
    what it raises is raised here, the tasks left to finish or to stop by themselves)."""
    if count <= 1 and meanwhile is None:
        return [task(j) for j in range(count)]
    if not _pool:
        _pool.append(ThreadPoolExecutor(MAX_THREADS, thread_name_prefix="knnrefine"))
    if meanwhile is None:
        return list(_pool[0].map(task, range(count)))
    futures = [_pool[0].submit(task, j) for j in range(count)]
    while True:
        done, pending = wait(futures, timeout=every, return_when=FIRST_EXCEPTION)
        failed = [f for f in done if f.exception() is not None]
        if failed:  # at once: the caller tells the others to stop
            raise failed[0].exception()
        if not pending:
            return [f.result() for f in futures]
        meanwhile()


PER_THREAD = 16  # ranges per thread: an interrupt waits for the ranges running only
KTH_WORK = 400_000  # neighbours gathered per range of a k-th distance search (~0.1 s)


def kth_range(k):
    """Queries per range of a k-th distance search at ``k``: a query's work grows with k, so
    that at k = 400, 1/16 of a thread's queries took 0.5 s on a quiet core and a Ctrl-C
    waited that long (3.7 s on a loaded one); ranges of KTH_WORK / k queries keep it short."""
    return max(64, int(KTH_WORK / max(float(k), 1.0)))


def thread_count(threads=None):
    """How many threads ``threads`` asks for: None or -1 (scipy's "every core")
    ``workers()``, else N (at least 1)."""
    return workers() if threads is None or int(threads) < 0 else max(1, int(threads))


def in_chunks(call, m, threads=None, least=256, per_thread=PER_THREAD, most=None):
    """[call(start, stop)] over ranges that split [0, m) evenly, ``per_thread`` ranges for
    each of ``threads`` (``thread_count``: None or -1 every core), each at least ``least``
    long (one range when m is small) and, when ``most`` is given, at most ``most`` long, run
    by at most ``threads`` threads at once: many short calls rather than one long one per
    thread, so that an interrupt (Ctrl-C) waits only for the ranges running, about
    1 / per_thread of the work (the threads take no new range once it came)."""
    threads = thread_count(threads)
    chunks = max(1, min(threads * int(per_thread), m // least))
    if most is not None:
        chunks = max(chunks, -(-m // max(int(most), 1)))
    edges = np.linspace(0, m, chunks + 1).astype(np.int64)
    out = [None] * chunks
    if threads == 1 or chunks == 1:  # here, between ranges Ctrl-C is raised at once
        for j in range(chunks):
            out[j] = call(edges[j], edges[j + 1])
        return out
    stop = []

    def take(t):
        for j in range(t, chunks, threads):
            if stop:
                return
            out[j] = call(edges[j], edges[j + 1])

    try:
        run_all(take, min(threads, chunks))
    except BaseException:
        stop.append(True)
        raise
    return out
