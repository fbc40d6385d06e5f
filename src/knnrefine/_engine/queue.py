"""Bucket queues of bad elements, largest first by size class.

Refinement splits the largest bad element first. Exact largest-first needs a binary heap,
whose pushes and pops on millions of entries miss the cache at every level and visit the
domain in random spatial order. A bucket queue keyed by size class does both in O(1): class
c holds the elements with squared radius in [2^-(c+1), 2^-c) (internal units, radius within a
factor sqrt(2)), the queue pops from the largest non-empty class, and within a class the most
recently pushed element first. New elements come from the insertion just made, so successive
insertions stay close together in space and in memory.

A queue is a ``state.Queue`` of five arrays: ``head[c]`` is the first entry of class c (-1 if
empty); each entry has an ``ident``, an ``aux`` word and the ``next`` entry of its class;
entries form singly linked stacks and freed entries are recycled. ``scalars`` holds the
queue's size, the smallest class that may be non-empty, the free-list head and the entries
ever allocated (slots Q_SIZE, Q_TOP, Q_FREE, Q_USED).
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


def new_queue(cap, zeros=np.zeros):
    """An empty queue with room for cap entries (``zeros(shape, dtype)`` makes its entry
    arrays: ``state.mapped`` for the 3-D run's)."""
    return Queue(
        head=np.full(N_CLASSES, -1, np.int32),
        ident=zeros((cap,), np.int32),
        aux=zeros((cap,), np.int32),
        next=zeros((cap,), np.int32),
        scalars=np.array([0, N_CLASSES, -1, 0], np.int64),
    )


@kernel(nrt=False)
def queue_clear(q):
    """Empty the queue (its arrays keep their size)."""
    q.head[:] = -1
    q.scalars[Q_SIZE] = 0
    q.scalars[Q_TOP] = N_CLASSES
    q.scalars[Q_FREE] = -1
    q.scalars[Q_USED] = 0


@kernel(inline="always")
def queue_size(q):
    return q.scalars[Q_SIZE]


@kernel(nrt=False)
def queue_push(q, cls, ident, aux):
    """Add (ident, aux) to class cls."""
    e = q.scalars[Q_FREE]
    if e >= 0:
        q.scalars[Q_FREE] = q.next[e]
    else:
        e = q.scalars[Q_USED]
        q.scalars[Q_USED] = e + 1
    q.ident[e] = ident
    q.aux[e] = aux
    q.next[e] = q.head[cls]
    q.head[cls] = e
    if cls < q.scalars[Q_TOP]:
        q.scalars[Q_TOP] = cls
    q.scalars[Q_SIZE] += 1


@kernel(nrt=False)
def queue_pop(q):
    """Remove an entry of the largest class; returns (class, ident, aux). Must not be empty."""
    c = q.scalars[Q_TOP]
    while q.head[c] < 0:
        c += 1
    q.scalars[Q_TOP] = c
    e = q.head[c]
    q.head[c] = q.next[e]
    q.next[e] = q.scalars[Q_FREE]
    q.scalars[Q_FREE] = e
    q.scalars[Q_SIZE] -= 1
    return c, q.ident[e], q.aux[e]
