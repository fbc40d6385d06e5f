"""certify's own geometric predicates, filtered: a floating-point determinant with a bound on
its rounding error first, exact integer arithmetic only where that bound cannot decide.

The signs follow Shewchuk's conventions ("Adaptive precision floating-point arithmetic and
fast robust geometric predicates", 1997), whose first-stage error bounds these are:
``orient2d(a, b, c)`` > 0 when a, b, c turn counter-clockwise; ``incircle(a, b, c, d)`` > 0
when d lies inside the circle through a, b, c (counter-clockwise); ``orient3d(a, b, c, d)``
> 0 when d lies below the plane of a, b, c (counter-clockwise seen from above);
``insphere(a, b, c, d, e)`` > 0 when e lies inside the sphere through a, b, c, d (with
``orient3d(a, b, c, d)`` > 0). The kernels return the sign, or ``UNSURE`` (2) where the float
value lies within its error bound of zero; ``exact_sign`` then decides in Python integers:
every double is an integer times a power of two, so the points scaled by one power of two
are integers and the determinant's sign is the integer determinant's. The engine has its
own predicates; certify does not ask them.
"""

from .._engine.jit import kernel

UNSURE = 2
_EPS = 2.0**-53
# the first-stage error bounds (relative to each determinant's permanent)
_ORIENT2D = (3.0 + 16.0 * _EPS) * _EPS
_INCIRCLE = (10.0 + 96.0 * _EPS) * _EPS
_ORIENT3D = (7.0 + 56.0 * _EPS) * _EPS
_INSPHERE = (16.0 + 224.0 * _EPS) * _EPS


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _decide(det, bound):
    if det > bound:
        return 1
    if -det > bound:
        return -1
    if bound == 0.0:  # every product exactly zero: the determinant is zero
        return 0
    return UNSURE


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def orient2d(ax, ay, bx, by, cx, cy):
    """The sign of orient2d, or UNSURE."""
    left = (ax - cx) * (by - cy)
    right = (ay - cy) * (bx - cx)
    return _decide(left - right, _ORIENT2D * (abs(left) + abs(right)))


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def incircle(ax, ay, bx, by, cx, cy, dx, dy):
    """The sign of incircle, or UNSURE."""
    adx, ady, bdx, bdy, cdx, cdy = ax - dx, ay - dy, bx - dx, by - dy, cx - dx, cy - dy
    bdxcdy, cdxbdy = bdx * cdy, cdx * bdy
    cdxady, adxcdy = cdx * ady, adx * cdy
    adxbdy, bdxady = adx * bdy, bdx * ady
    alift = adx * adx + ady * ady
    blift = bdx * bdx + bdy * bdy
    clift = cdx * cdx + cdy * cdy
    det = alift * (bdxcdy - cdxbdy) + blift * (cdxady - adxcdy) + clift * (adxbdy - bdxady)
    permanent = ((abs(bdxcdy) + abs(cdxbdy)) * alift + (abs(cdxady) + abs(adxcdy)) * blift
                 + (abs(adxbdy) + abs(bdxady)) * clift)  # fmt: skip
    return _decide(det, _INCIRCLE * permanent)


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def orient3d(p, a, b, c, d):
    """The sign of orient3d of rows a, b, c, d of p (n, 3), or UNSURE."""
    return orient3d_at(p[a, 0], p[a, 1], p[a, 2], p[b, 0], p[b, 1], p[b, 2], p[c, 0], p[c, 1],
                       p[c, 2], p[d, 0], p[d, 1], p[d, 2])  # fmt: skip


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def orient3d_at(ax, ay, az, bx, by, bz, cx, cy, cz, dx, dy, dz):
    """The sign of orient3d of the points (ax, ay, az), ..., or UNSURE."""
    adx, ady, adz = ax - dx, ay - dy, az - dz
    bdx, bdy, bdz = bx - dx, by - dy, bz - dz
    cdx, cdy, cdz = cx - dx, cy - dy, cz - dz
    bdxcdy, cdxbdy = bdx * cdy, cdx * bdy
    cdxady, adxcdy = cdx * ady, adx * cdy
    adxbdy, bdxady = adx * bdy, bdx * ady
    det = adz * (bdxcdy - cdxbdy) + bdz * (cdxady - adxcdy) + cdz * (adxbdy - bdxady)
    permanent = ((abs(bdxcdy) + abs(cdxbdy)) * abs(adz) + (abs(cdxady) + abs(adxcdy)) * abs(bdz)
                 + (abs(adxbdy) + abs(bdxady)) * abs(cdz))  # fmt: skip
    return _decide(det, _ORIENT3D * permanent)


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def insphere(p, a, b, c, d, e):
    """The sign of insphere of rows a, b, c, d, e of p (n, 3), or UNSURE."""
    aex, aey, aez = p[a, 0] - p[e, 0], p[a, 1] - p[e, 1], p[a, 2] - p[e, 2]
    bex, bey, bez = p[b, 0] - p[e, 0], p[b, 1] - p[e, 1], p[b, 2] - p[e, 2]
    cex, cey, cez = p[c, 0] - p[e, 0], p[c, 1] - p[e, 1], p[c, 2] - p[e, 2]
    dex, dey, dez = p[d, 0] - p[e, 0], p[d, 1] - p[e, 1], p[d, 2] - p[e, 2]
    aexbey, bexaey = aex * bey, bex * aey
    bexcey, cexbey = bex * cey, cex * bey
    cexdey, dexcey = cex * dey, dex * cey
    dexaey, aexdey = dex * aey, aex * dey
    aexcey, cexaey = aex * cey, cex * aey
    bexdey, dexbey = bex * dey, dex * bey
    ab, bc, cd, da = aexbey - bexaey, bexcey - cexbey, cexdey - dexcey, dexaey - aexdey
    ac, bd = aexcey - cexaey, bexdey - dexbey
    abc = aez * bc - bez * ac + cez * ab
    bcd = bez * cd - cez * bd + dez * bc
    cda = cez * da + dez * ac + aez * cd
    dab = dez * ab + aez * bd + bez * da
    alift = aex * aex + aey * aey + aez * aez
    blift = bex * bex + bey * bey + bez * bez
    clift = cex * cex + cey * cey + cez * cez
    dlift = dex * dex + dey * dey + dez * dez
    det = (dlift * abc - clift * dab) + (blift * cda - alift * bcd)
    az, bz, cz, dz = abs(aez), abs(bez), abs(cez), abs(dez)
    p_ab, p_bc = abs(aexbey) + abs(bexaey), abs(bexcey) + abs(cexbey)
    p_cd, p_da = abs(cexdey) + abs(dexcey), abs(dexaey) + abs(aexdey)
    p_ac, p_bd = abs(aexcey) + abs(cexaey), abs(bexdey) + abs(dexbey)
    permanent = ((p_cd * bz + p_bd * cz + p_bc * dz) * alift
                 + (p_da * cz + p_ac * dz + p_cd * az) * blift
                 + (p_ab * dz + p_bd * az + p_da * bz) * clift
                 + (p_bc * az + p_ac * bz + p_ab * cz) * dlift)  # fmt: skip
    return _decide(det, _INSPHERE * permanent)


def _integers(points):
    """The coordinates (lists of floats) as integers, all scaled by one power of two."""
    ratios = [float(v).as_integer_ratio() for row in points for v in row]
    scale = max(d for _, d in ratios)  # every denominator is a power of two
    flat = [n * (scale // d) for n, d in ratios]
    width = len(points[0])
    return [flat[i : i + width] for i in range(0, len(flat), width)]


def _det(rows):
    """The determinant of a small square matrix of Python integers (Laplace expansion)."""
    if len(rows) == 1:
        return rows[0][0]
    total = 0
    for j, head in enumerate(rows[0]):
        if head:
            minor = [row[:j] + row[j + 1 :] for row in rows[1:]]
            total += (-1) ** j * head * _det(minor)
    return total


def exact_sign(kind, points):
    """The exact sign of ``kind`` ("orient2d", "incircle", "orient3d", "insphere") of
    ``points`` (a sequence of coordinate rows, in the kernels' order)."""
    p = _integers([list(map(float, row)) for row in points])
    last = p[-1]
    rel = [[v - w for v, w in zip(row, last, strict=True)] for row in p[:-1]]
    if kind in ("incircle", "insphere"):
        rel = [row + [sum(v * v for v in row)] for row in rel]
    det = _det(rel)
    return (det > 0) - (det < 0)
