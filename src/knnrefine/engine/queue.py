"""Bucket queues of bad elements, largest first by size class.

Refinement splits the largest bad element first. Exact largest-first needs a binary heap,
whose pushes and pops on millions of entries miss the cache at every level and visit the
domain in random spatial order. A bucket queue keyed by size class does both in O(1): class
c holds the elements with squared radius in [2^-(c+1), 2^-c) (internal units, radius within a
factor sqrt(2)), the queue pops from the largest non-empty class, and within a class the most
recently pushed element first. New elements come from the insertion just made, so successive
insertions stay close together in space and in memory.

A queue is a ``state.Queue`` of four arrays: ``head[c]`` is the first entry of class c (-1 if
empty); each entry has an ``ident``, an ``aux`` word and the ``next`` entry of its class;
entries form singly linked stacks and freed entries are recycled. Its scalars live in four
consecutive slots of the counters array from ``base`` (``state.C_Q_*``): size, the smallest
class that may be non-empty, the free-list head and the entries ever allocated.
"""

import numpy as np

from .jit import kernel
from .state import Queue

N_CLASSES = 256
Q_SIZE = 0
Q_TOP = 1
Q_FREE = 2
Q_USED = 3


@kernel(inline="always")
def size_class(r2):
    """Class of a squared radius r2 in (0, 1]: 0 for the largest, larger for smaller."""
    if r2 <= 0.0:
        return N_CLASSES - 1
    c = -int(np.floor(np.log2(r2))) - 1
    if c < 0:
        return 0
    if c >= N_CLASSES:
        return N_CLASSES - 1
    return c


def new_queue(cap):
    return Queue(
        head=np.full(N_CLASSES, -1, np.int32),
        ident=np.zeros(cap, np.int32),
        aux=np.zeros(cap, np.int32),
        next=np.zeros(cap, np.int32),
    )


@kernel()
def queue_init(cnt, base):
    cnt[base + Q_SIZE] = 0
    cnt[base + Q_TOP] = N_CLASSES
    cnt[base + Q_FREE] = -1
    cnt[base + Q_USED] = 0


@kernel(inline="always")
def queue_push(q, cnt, base, cls, ident, aux):
    e = cnt[base + Q_FREE]
    if e >= 0:
        cnt[base + Q_FREE] = q.next[e]
    else:
        e = cnt[base + Q_USED]
        cnt[base + Q_USED] = e + 1
    q.ident[e] = ident
    q.aux[e] = aux
    q.next[e] = q.head[cls]
    q.head[cls] = e
    if cls < cnt[base + Q_TOP]:
        cnt[base + Q_TOP] = cls
    cnt[base + Q_SIZE] += 1


@kernel(inline="always")
def queue_pop(q, cnt, base):
    """Remove an entry of the largest class; returns (class, ident, aux). Must not be empty."""
    c = cnt[base + Q_TOP]
    while q.head[c] < 0:
        c += 1
    cnt[base + Q_TOP] = c
    e = q.head[c]
    q.head[c] = q.next[e]
    q.next[e] = cnt[base + Q_FREE]
    cnt[base + Q_FREE] = e
    cnt[base + Q_SIZE] -= 1
    return c, q.ident[e], q.aux[e]
