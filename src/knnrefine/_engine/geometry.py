"""Small floating-point geometry shared by the kernels: circumcircles and the snapping grid."""

import numpy as np

from .jit import kernel

# Internal coordinates live on a grid q Z^2 inside [0, 1): every vertex is snapped to it and
# every period is a multiple of q, so a translation by a period is exact and the exact
# predicates see the same configuration from every periodic copy. q is a power of two, at
# least Q, and coarse enough that every vertex maps exactly to a double in the user's
# coordinates (``embedding.Embedding.grid``).
GRID_BITS = 50
Q = 2.0**-GRID_BITS
FLOOR_BITS = 14  # the engine's resolution floor is 2^14 q: elements below it are never split
# The smallest cap or cell the engine refines (radians, 2^-20: 0.95 micro-radians, 6.1 m on
# the Earth): there refine_sphere's slack inflates a cap's radius by 0.2%, and a cap is 2^-41 deep
# (its centre that far above the plane of its corners), 2^12 times the rounding of a unit
# vector, so an inserted centre is strictly inside its cap. Below it the vectors' rounding
# is the size of the caps themselves: the hull of rounded vectors is no longer the sphere's
# Delaunay triangulation of the points they stand for.
RESOLUTION_ANGLE = 2.0**-20


@kernel(inline="always")
def plus_compensated(s, c, x):
    """s + x with the rounding error gathered in c (Neumaier's compensated summation): the
    running total s + c of weights >= 0 stays within two ulps of the exact sum whatever the
    order, where plain addition loses a weight of 1 beside one of 1e16. Counts (whole
    numbers below 2^53) are added exactly and c stays 0. Returns (s + x, c)."""
    t = s + x
    if abs(s) >= abs(x):
        c += (s - t) + x
    else:
        c += (x - t) + s
    return t, c


@kernel(inline="always")
def snap(x, q):
    """x rounded to the nearest multiple of the grid step q (a power of two: exact scaling)."""
    return np.rint(x / q) * q


@kernel(inline="always")
def circumcircle(ax, ay, bx, by, cx, cy):
    """Circumcenter (x, y) and squared circumradius of a counter-clockwise triangle."""
    bx -= ax
    by -= ay
    cx -= ax
    cy -= ay
    b2 = bx * bx + by * by
    c2 = cx * cx + cy * cy
    d = 2.0 * (bx * cy - by * cx)
    ux = (cy * b2 - by * c2) / d
    uy = (bx * c2 - cx * b2) / d
    return ax + ux, ay + uy, ux * ux + uy * uy


@kernel(inline="always")
def _spread_bits(x):
    """The low 16 bits of x spread to the even bit positions."""
    x &= 0xFFFF
    x = (x | (x << 8)) & 0x00FF00FF
    x = (x | (x << 4)) & 0x0F0F0F0F
    x = (x | (x << 2)) & 0x33333333
    return (x | (x << 1)) & 0x55555555


@kernel(inline="always")
def morton_key(u, v):
    """Position of (u, v) in [0, 1)^2 along the Z-order curve on a 2^16 x 2^16 grid: sorting
    by it puts points close in the plane mostly close in the order (a cache-friendly sweep)."""
    i = min(max(int(u * 65536.0), 0), 65535)
    j = min(max(int(v * 65536.0), 0), 65535)
    return _spread_bits(i) | (_spread_bits(j) << 1)


@kernel(inline="always")
def circumsphere(p):
    """Circumcentre (x, y, z) and squared circumradius of the tetrahedron with corners the
    rows p[0], ..., p[3] (either orientation; infinite for a flat one)."""
    ax, ay, az = p[0, 0], p[0, 1], p[0, 2]
    bx, by, bz = p[1, 0] - ax, p[1, 1] - ay, p[1, 2] - az
    cx, cy, cz = p[2, 0] - ax, p[2, 1] - ay, p[2, 2] - az
    dx, dy, dz = p[3, 0] - ax, p[3, 1] - ay, p[3, 2] - az
    b2 = bx * bx + by * by + bz * bz
    c2 = cx * cx + cy * cy + cz * cz
    d2 = dx * dx + dy * dy + dz * dz
    # c x d, d x b, b x c
    cdx, cdy, cdz = cy * dz - cz * dy, cz * dx - cx * dz, cx * dy - cy * dx
    dbx, dby, dbz = dy * bz - dz * by, dz * bx - dx * bz, dx * by - dy * bx
    bcx, bcy, bcz = by * cz - bz * cy, bz * cx - bx * cz, bx * cy - by * cx
    den = 2.0 * (bx * cdx + by * cdy + bz * cdz)
    ux = (b2 * cdx + c2 * dbx + d2 * bcx) / den
    uy = (b2 * cdy + c2 * dby + d2 * bcy) / den
    uz = (b2 * cdz + c2 * dbz + d2 * bcz) / den
    return ax + ux, ay + uy, az + uz, ux * ux + uy * uy + uz * uz
