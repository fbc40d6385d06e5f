"""Exact geometric predicates: orient2d and incircle.

Each predicate first evaluates its determinant in floating point and returns the sign when
the value clears a forward error bound (Shewchuk's "stage A" bounds). Otherwise it recomputes
the determinant exactly with floating-point expansions (sums of non-overlapping doubles built
from error-free transformations) and returns the sign of the exact value.

Refinement terminates only if in-circle decisions are consistent, so these kernels must never
be compiled with ``fastmath``: reassociation or FMA contraction breaks the error-free
transformations below. Exactness holds while no intermediate product overflows or
underflows: coordinates that are zero or of magnitude in [1e-50, 1e50]. The engine's are
multiples of 2^-50 in [-1, 3).
"""

import numpy as np

from .jit import kernel

EPS = 2.0**-53  # half an ulp of 1.0: the unit roundoff
_SPLITTER = 2.0**27 + 1.0
# Forward error bounds of the floating-point determinants (Shewchuk 1997, stage A).
CCW_ERRBOUND = (3.0 + 16.0 * EPS) * EPS
ICC_ERRBOUND = (10.0 + 96.0 * EPS) * EPS


# --- error-free transformations -------------------------------------------------------------


@kernel(inline="always")
def two_sum(a, b):
    """x + y == a + b exactly, with x = fl(a + b)."""
    x = a + b
    bv = x - a
    av = x - bv
    return x, (a - av) + (b - bv)


@kernel(inline="always")
def two_diff(a, b):
    """x + y == a - b exactly, with x = fl(a - b)."""
    x = a - b
    bv = a - x
    av = x + bv
    return x, (a - av) + (bv - b)


@kernel(inline="always")
def _split(a):
    c = _SPLITTER * a
    hi = c - (c - a)
    return hi, a - hi


@kernel(inline="always")
def two_product(a, b):
    """x + y == a * b exactly, with x = fl(a * b) (Dekker's product)."""
    x = a * b
    ahi, alo = _split(a)
    bhi, blo = _split(b)
    err = x - ahi * bhi
    err -= alo * bhi
    err -= ahi * blo
    return x, alo * blo - err


# --- expansions: arrays of non-overlapping doubles, increasing magnitude, zeros dropped ---------


@kernel()
def expansion_sum(e, elen, f, flen, h):
    """h = e + f; returns the length of h (h must hold elen + flen doubles)."""
    i = 0
    j = 0
    # merge the components of e and f by increasing magnitude, then accumulate
    if i < elen and (j >= flen or abs(e[i]) <= abs(f[j])):
        q = e[i]
        i += 1
    else:
        q = f[j]
        j += 1
    n = 0
    while i < elen or j < flen:
        if i < elen and (j >= flen or abs(e[i]) <= abs(f[j])):
            g = e[i]
            i += 1
        else:
            g = f[j]
            j += 1
        q, t = two_sum(q, g)
        if t != 0.0:
            h[n] = t
            n += 1
    if q != 0.0 or n == 0:
        h[n] = q
        n += 1
    return n


@kernel()
def expansion_scale(e, elen, b, h):
    """h = e * b for a double b; returns the length of h (h must hold 2 * elen doubles)."""
    q, t = two_product(e[0], b)
    n = 0
    if t != 0.0:
        h[n] = t
        n += 1
    for i in range(1, elen):
        p1, p0 = two_product(e[i], b)
        s, t = two_sum(q, p0)
        if t != 0.0:
            h[n] = t
            n += 1
        q, t = two_sum(p1, s)
        if t != 0.0:
            h[n] = t
            n += 1
    if q != 0.0 or n == 0:
        h[n] = q
        n += 1
    return n


@kernel()
def expansion_product(e, elen, f, flen, h):
    """h = e * f; returns the length of h (h must hold 2 * elen * flen doubles)."""
    part = np.empty(2 * elen)
    acc = np.empty(2 * elen * flen)
    n = expansion_scale(e, elen, f[0], h)
    for j in range(1, flen):
        m = expansion_scale(e, elen, f[j], part)
        n = expansion_sum(h, n, part, m, acc)
        for i in range(n):
            h[i] = acc[i]
    return n


@kernel()
def expansion_sign(e, elen):
    """Sign of the exact value: the sign of its largest (last non-zero) component."""
    for i in range(elen - 1, -1, -1):
        if e[i] > 0.0:
            return 1
        if e[i] < 0.0:
            return -1
    return 0


@kernel(inline="always")
def diff_expansion(a, b, out):
    hi, lo = two_diff(a, b)
    if lo == 0.0:
        out[0] = hi
        return 1
    out[0] = lo
    out[1] = hi
    return 2


# --- orient2d ---------------------------------------------------------------------------------


@kernel()
def _orient2d_exact(ax, ay, bx, by, cx, cy):
    acx = np.empty(2)
    bcy = np.empty(2)
    acy = np.empty(2)
    bcx = np.empty(2)
    n1 = diff_expansion(ax, cx, acx)
    n2 = diff_expansion(by, cy, bcy)
    n3 = diff_expansion(ay, cy, acy)
    n4 = diff_expansion(bx, cx, bcx)
    left = np.empty(8)
    right = np.empty(8)
    nl = expansion_product(acx, n1, bcy, n2, left)
    nr = expansion_product(acy, n3, bcx, n4, right)
    for i in range(nr):
        right[i] = -right[i]
    det = np.empty(16)
    nd = expansion_sum(left, nl, right, nr, det)
    return expansion_sign(det, nd)


@kernel()
def orient2d(ax, ay, bx, by, cx, cy):
    """Sign of the signed area of (a, b, c): +1 counter-clockwise, -1 clockwise, 0 collinear."""
    detleft = (ax - cx) * (by - cy)
    detright = (ay - cy) * (bx - cx)
    det = detleft - detright
    bound = CCW_ERRBOUND * (abs(detleft) + abs(detright))
    if det > bound:
        return 1
    if -det > bound:
        return -1
    return _orient2d_exact(ax, ay, bx, by, cx, cy)


# --- incircle ---------------------------------------------------------------------------------


@kernel()
def _lift_times_cross(px, npx, py, npy, qx, nqx, qy, nqy, rx, nrx, ry, nry, out):
    """out = (px^2 + py^2) * (qx * ry - qy * rx), all operands expansions; returns length."""
    t1 = np.empty(8)
    t2 = np.empty(8)
    n1 = expansion_product(px, npx, px, npx, t1)
    n2 = expansion_product(py, npy, py, npy, t2)
    lift = np.empty(16)
    nl = expansion_sum(t1, n1, t2, n2, lift)
    n1 = expansion_product(qx, nqx, ry, nry, t1)
    n2 = expansion_product(qy, nqy, rx, nrx, t2)
    for i in range(n2):
        t2[i] = -t2[i]
    cross = np.empty(16)
    nc = expansion_sum(t1, n1, t2, n2, cross)
    return expansion_product(lift, nl, cross, nc, out)


@kernel()
def _incircle_exact(ax, ay, bx, by, cx, cy, dx, dy):
    adx = np.empty(2)
    ady = np.empty(2)
    bdx = np.empty(2)
    bdy = np.empty(2)
    cdx = np.empty(2)
    cdy = np.empty(2)
    nax = diff_expansion(ax, dx, adx)
    nay = diff_expansion(ay, dy, ady)
    nbx = diff_expansion(bx, dx, bdx)
    nby = diff_expansion(by, dy, bdy)
    ncx = diff_expansion(cx, dx, cdx)
    ncy = diff_expansion(cy, dy, cdy)
    ta = np.empty(512)
    tb = np.empty(512)
    tc = np.empty(512)
    na = _lift_times_cross(adx, nax, ady, nay, bdx, nbx, bdy, nby, cdx, ncx, cdy, ncy, ta)
    nb = _lift_times_cross(bdx, nbx, bdy, nby, cdx, ncx, cdy, ncy, adx, nax, ady, nay, tb)
    nc = _lift_times_cross(cdx, ncx, cdy, ncy, adx, nax, ady, nay, bdx, nbx, bdy, nby, tc)
    ab = np.empty(1024)
    nab = expansion_sum(ta, na, tb, nb, ab)
    det = np.empty(1536)
    nd = expansion_sum(ab, nab, tc, nc, det)
    return expansion_sign(det, nd)


@kernel()
def incircle(ax, ay, bx, by, cx, cy, dx, dy):
    """+1 if d lies strictly inside the circle through a, b, c (counter-clockwise), -1 if
    strictly outside, 0 if on it. For a clockwise triangle the sign is reversed."""
    adx = ax - dx
    ady = ay - dy
    bdx = bx - dx
    bdy = by - dy
    cdx = cx - dx
    cdy = cy - dy
    bdxcdy = bdx * cdy
    cdxbdy = cdx * bdy
    alift = adx * adx + ady * ady
    cdxady = cdx * ady
    adxcdy = adx * cdy
    blift = bdx * bdx + bdy * bdy
    adxbdy = adx * bdy
    bdxady = bdx * ady
    clift = cdx * cdx + cdy * cdy
    det = alift * (bdxcdy - cdxbdy) + blift * (cdxady - adxcdy) + clift * (adxbdy - bdxady)
    permanent = (
        (abs(bdxcdy) + abs(cdxbdy)) * alift
        + (abs(cdxady) + abs(adxcdy)) * blift
        + (abs(adxbdy) + abs(bdxady)) * clift
    )
    bound = ICC_ERRBOUND * permanent
    if det > bound:
        return 1
    if -det > bound:
        return -1
    return _incircle_exact(ax, ay, bx, by, cx, cy, dx, dy)
