"""Small floating-point geometry shared by the kernels: circumcircles and the snapping grid."""

import numpy as np
from numba import njit

# Internal coordinates live on the grid Q * Z^2 inside [0, 1): every vertex is snapped to it and
# every period is a multiple of Q, so a translation by a period is exact and the exact
# predicates see the same configuration from every periodic copy.
GRID_BITS = 50
Q = 2.0**-GRID_BITS


@njit(cache=True, inline="always")
def snap(x):
    return np.rint(x * (1.0 / Q)) * Q


@njit(cache=True, inline="always")
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
