"""Samples of points that depend only on the points: each point's key is a hash of its
coordinates, so the points whose key is below a fraction are the same sample however they
are split, ordered or spread over processes (one process, tiles, Dask), in an order of
their own (``canonical``). The tiled runs draw their coarse sample so, and certify its
input-point probes, so that every path (one process, tiles) probes the same points."""

import numpy as np

from ._engine.jit import kernel
from ._engine.threads import in_chunks


@kernel(inline="always")
def _mix(z):
    """SplitMix64's finaliser: a bijection of 64-bit words that scatters every input bit."""
    z = z + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


NEG_ZERO = np.uint64(1 << 63)  # -0.0's bits: keyed as 0.0's


@kernel(entry=True, nogil=True)
def _keys(bits, out, start, stop):
    d = bits.shape[1]
    for i in range(start, stop):
        b = bits[i, d - 1]
        h = _mix(np.uint64(0) if b == NEG_ZERO else b)
        for a in range(d - 2, -1, -1):
            b = bits[i, a]
            h = _mix((np.uint64(0) if b == NEG_ZERO else b) ^ h)
        out[i] = np.float64(h >> np.uint64(11)) * 1.1102230246251565e-16  # 2^-53


def sample_keys(xy):
    """A key in [0, 1) for each point (n, d) that depends only on its coordinates (0.0 and
    -0.0 alike): the points with key < f are a sample of about f n, the same one however
    the points are split or ordered."""
    bits = np.ascontiguousarray(xy, dtype=np.float64).view(np.uint64)
    out = np.empty(len(bits))
    in_chunks(lambda a, b: _keys(bits, out, a, b), len(bits), least=65536, per_thread=1)
    return out


def canonical(xy, weights, keys):
    """The sample in an order that depends only on its points: by key, then x, then y
    (then z) where keys tie (by the key alone where none do: the same order, faster)."""
    order = np.argsort(keys, kind="stable")
    ordered = keys[order]
    if len(ordered) > 1 and (ordered[1:] == ordered[:-1]).any():
        order = np.lexsort((*(xy[:, a] for a in reversed(range(xy.shape[1]))), keys))
    return xy[order], None if weights is None else weights[order], keys[order]


def key_sample(xy, fraction, weights=None):
    """(the points (n, d) whose key is below ``fraction``, their weights (None: none), their
    keys), in ``canonical`` order: the sample every path draws alike."""
    xy = np.asarray(xy)
    keys = sample_keys(xy)
    pick = keys < fraction
    return canonical(xy[pick], None if weights is None else weights[pick], keys[pick])
