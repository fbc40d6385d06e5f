"""The share of a tetrahedron where a linear function lies below a level.

A uniform point of a tetrahedron whose corners carry the values d_0 < d_1 < d_2 < d_3 has
the linear interpolant's value distributed as the cubic B-spline with those knots (the
volume below r is a piecewise cubic in r). ``domains.space.density`` adds these shares over
the mesh's pieces for the kNN-CDF; each knot interval is evaluated from its stable side (the
near end's truncated power), so that close knots do not cancel.
"""

from .jit import kernel


@kernel(inline="always")
def share_below(d0, d1, d2, d3, r):
    """The share of the tetrahedron with sorted, distinct corner values d0..d3 where the
    linear function is <= r."""
    if r <= d0:
        return 0.0
    if r <= d1:
        return (r - d0) ** 3 / ((d1 - d0) * (d2 - d0) * (d3 - d0))
    if r <= d2:
        if d1 - d0 >= d3 - d2:
            return (r - d0) ** 3 / ((d1 - d0) * (d2 - d0) * (d3 - d0)) - (r - d1) ** 3 / (
                (d1 - d0) * (d2 - d1) * (d3 - d1)
            )
        return 1.0 - (
            (d3 - r) ** 3 / ((d3 - d0) * (d3 - d1) * (d3 - d2))
            - (d2 - r) ** 3 / ((d3 - d2) * (d2 - d0) * (d2 - d1))
        )
    if r <= d3:
        return 1.0 - (d3 - r) ** 3 / ((d3 - d0) * (d3 - d1) * (d3 - d2))
    return 1.0


@kernel(entry=True, nrt=False)
def shares_below(d, r, out):
    """out[i] = ``share_below`` of piece i (knots d (t, 4), sorted, distinct) at r."""
    for i in range(d.shape[0]):
        out[i] = share_below(d[i, 0], d[i, 1], d[i, 2], d[i, 3], r)


@kernel(inline="always")
def _first_above(r, x, strict):
    """The first index j of the sorted r with r[j] > x (``strict``) or r[j] >= x."""
    lo = 0
    hi = r.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if r[mid] > x or (not strict and r[mid] == x):
            hi = mid
        else:
            lo = mid + 1
    return lo


@kernel(entry=True, nrt=False)
def weighted_shares(d, w, r, out, whole):
    """out[j] = sum_i w[i] share_i(r[j]) for the sorted radii r: each piece adds its share
    only at the radii inside its knot span (found by bisection) and its whole weight from
    its top knot on (``whole``, len(r) + 1 zeros, summed up at the end), so the cost is the
    pieces plus the (piece, radius) pairs that cut."""
    nr = r.shape[0]
    for i in range(d.shape[0]):
        j0 = _first_above(r, d[i, 0], True)
        j3 = _first_above(r, d[i, 3], False)
        whole[j3] += w[i]
        for j in range(j0, j3):
            out[j] += w[i] * share_below(d[i, 0], d[i, 1], d[i, 2], d[i, 3], r[j])
    total = 0.0
    for j in range(nr):
        total += whole[j]
        out[j] += total
