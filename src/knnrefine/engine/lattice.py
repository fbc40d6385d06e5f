"""Sums of isotropic triweight kernels, one radius per centre, on a grid: each kernel is drawn
exactly onto the lattice of its scale, and the lattices are read at the grid's centres.

Along each axis a kernel of radius r goes to the lattice whose step is the grid's times 2^m,
m >= 0 the largest with r / step >= S: kernels narrower than 2S cells are drawn on the grid
itself, wider ones on coarser lattices through the same centres, each with at most about
pi (2S)^2 values whatever its radius and however many other kernels overlap it. A grid
then costs O(n S^2) to draw and O(levels) per centre to read, where summing at each centre
the kernels that cover it costs their number (about c^2 k per centre for the adaptive
estimate, which grows with n). The grid's own lattice is read exactly; coarser ones by
Catmull-Rom interpolation (4 x 4 values), exact at their points and third-order between:
a lattice holds kernels at least S steps wide only, so the error is a small fixed fraction
of them (``tests/test_adaptive.py`` measures it against the exact sums).

The box is handled as ``kernelsum`` does: along periodic axes kernels wrap (their images one
period away are drawn too), along the others the mass beyond a side folds back (the kernel's
mirror image in the side is drawn), so that a lattice holds the even extension across a
folded side and the interpolation stays smooth there. Coordinates are relative to the box's
lower corner. A lattice covers its kernels' supports within two steps of the box.
"""

import numpy as np

from .jit import kernel

LEVEL_COLUMNS = 7  # per level: origin x, origin y, steps x and y, nx, ny, offset in values
OX, OY, SX, SY, NX, NY, OFFSET = range(LEVEL_COLUMNS)


def plan_levels(cx, cy, r, lx, ly, px, py, grid, samples, max_values):
    """(level of each kernel (-1: none, radius 0), levels (L, LEVEL_COLUMNS), total values)
    for kernels at (cx, cy) of radii r in the box [0, lx] x [0, ly], read on the grid
    ``grid`` = (x0, y0, dx, dy) (the cells' centres x0 + i dx, y0 + j dy). Along each axis a
    kernel's step is the grid's times 2^m, m >= 0 the largest with r / step >= ``samples``:
    kernels narrower than 2 samples cells are drawn on the grid itself (read exactly there),
    wider ones on coarser lattices through the same centres (read by interpolation between
    them). None when the lattices would hold more than ``max_values`` values."""
    x0, y0, dx, dy = grid
    live = r > 0
    mx = np.zeros(len(r), np.int64)
    my = np.zeros(len(r), np.int64)
    with np.errstate(divide="ignore"):
        mx[live] = np.maximum(np.floor(np.log2(r[live] / (samples * dx))), 0)
        my[live] = np.maximum(np.floor(np.log2(r[live] / (samples * dy))), 0)
    key = np.where(live, mx * 64 + my, -1)
    keys, level = np.unique(key, return_inverse=True)
    level = level.astype(np.int64)
    if len(keys) and keys[0] < 0:
        level -= 1  # the dead kernels' key sorts first
        keys = keys[1:]
    rows, total = [], 0
    for j, kk in enumerate(keys):
        mine = level == j
        spans = []
        for c, ext, periodic, first, step in (
            (cx, lx, px, x0, dx * 2.0 ** (kk // 64)),
            (cy, ly, py, y0, dy * 2.0 ** (kk % 64)),
        ):
            pad = 2.0 * step
            cm, rm = c[mine], r[mine]
            lo = max(float(np.min(cm - rm)), -pad)
            hi = min(float(np.max(cm + rm)), ext + pad)
            if periodic and np.any((cm < rm + pad) | (cm > ext - rm - pad)):
                lo, hi = -pad, ext + pad  # images one period away reach into the box
            if not periodic and np.any(cm < rm + pad):
                lo = -pad  # mirror images in the lower side
            if not periodic and np.any(cm > ext - rm - pad):
                hi = ext + pad
            i0 = np.floor((lo - first) / step)
            spans.append((first + i0 * step, step, int(np.floor((hi - first) / step) - i0) + 1))
        (ox, sx, nx), (oy, sy, ny) = spans
        rows.append((ox, oy, sx, sy, nx, ny, total))
        total += nx * ny
        if total > max_values:
            return None
    return level, np.array(rows, float).reshape(-1, LEVEL_COLUMNS), total


@kernel(inline="always")
def _image(c, j, period, periodic):
    """A centre's j-th image along one axis: itself, then one period down and up (periodic)
    or its mirror images in the two sides (folded)."""
    if j == 0:
        return c
    if periodic:
        return c - period if j == 1 else c + period
    return -c if j == 1 else 2.0 * period - c


@kernel(entry=True, nogil=True)
def draw(cx, cy, r, amp, level, lx, ly, px, py, levels, values, start, stop):
    """Add kernels start..stop-1, amp_i (1 - |x - c_i|^2 / r_i^2)^3, and their images in the
    box's sides, to the values of their level's lattice (``plan_levels``)."""
    for i in range(start, stop):
        lev = level[i]
        if lev < 0:
            continue
        ox, oy, sx, sy = levels[lev, OX], levels[lev, OY], levels[lev, SX], levels[lev, SY]
        nx, ny, off = int(levels[lev, NX]), int(levels[lev, NY]), int(levels[lev, OFFSET])
        rad = r[i]
        inv = 1.0 / (rad * rad)
        a = amp[i]
        for ia in range(3):
            x = _image(cx[i], ia, lx, px)
            i0 = max(int(np.ceil((x - rad - ox) / sx)), 0)
            i1 = min(int(np.floor((x + rad - ox) / sx)), nx - 1)
            if i0 > i1:
                continue
            for ib in range(3):
                y = _image(cy[i], ib, ly, py)
                j0 = max(int(np.ceil((y - rad - oy) / sy)), 0)
                j1 = min(int(np.floor((y + rad - oy) / sy)), ny - 1)
                for j in range(j0, j1 + 1):
                    ey = oy + j * sy - y
                    row = off + j * nx
                    for ii in range(i0, i1 + 1):
                        ex = ox + ii * sx - x
                        u = (ex * ex + ey * ey) * inv
                        if u < 1.0:
                            v = 1.0 - u
                            values[row + ii] += a * v * v * v
    return 0


@kernel(inline="always")
def _catmull_rom(t, w):
    """The four Catmull-Rom weights of the values at -1, 0, 1, 2 for a point at t in [0, 1)."""
    t2 = t * t
    t3 = t2 * t
    w[0] = 0.5 * (-t3 + 2.0 * t2 - t)
    w[1] = 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0)
    w[2] = 0.5 * (-3.0 * t3 + 4.0 * t2 + t)
    w[3] = 0.5 * (t3 - t2)


@kernel(entry=True, nogil=True)
def read(qx, qy, levels, values, out, start, stop):
    """out[q] = the sum over levels of the lattice values interpolated at query q
    (Catmull-Rom; values beyond a lattice count as 0: no kernel of its level reaches there)."""
    wx = np.empty(4)
    wy = np.empty(4)
    for q in range(start, stop):
        s = 0.0
        for lev in range(levels.shape[0]):
            ox, oy, sx, sy = levels[lev, OX], levels[lev, OY], levels[lev, SX], levels[lev, SY]
            nx, ny, off = int(levels[lev, NX]), int(levels[lev, NY]), int(levels[lev, OFFSET])
            fx = (qx[q] - ox) / sx
            fy = (qy[q] - oy) / sy
            i = int(np.floor(fx))
            j = int(np.floor(fy))
            if i + 2 < 0 or i - 1 >= nx or j + 2 < 0 or j - 1 >= ny:
                continue
            _catmull_rom(fx - i, wx)
            _catmull_rom(fy - j, wy)
            for b in range(4):
                jj = j - 1 + b
                if jj < 0 or jj >= ny:
                    continue
                row = off + jj * nx
                acc = 0.0
                for a in range(4):
                    ii = i - 1 + a
                    if 0 <= ii < nx:
                        acc += wx[a] * values[row + ii]
                s += wy[b] * acc
        out[q] = max(s, 0.0)  # (interpolation may dip below 0 beside a steep rim)
    return 0
