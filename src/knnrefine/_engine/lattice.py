"""Sums of isotropic triweight kernels, one radius per centre, on a grid (plane or space):
each kernel is drawn exactly onto the lattice of its scale, and the lattices are read at the
grid's centres.

Along each axis a kernel of radius r goes to the lattice whose step is the grid's times 2^m,
m >= 0 the largest with r / step >= S: kernels narrower than 2S cells are drawn on the grid
itself, wider ones on coarser lattices through the same centres, each with at most about
the volume of a ball of 2S steps whatever its radius and however many other kernels overlap
it (``draw``, ``draw3``). A grid then costs O(n S^d) to draw and a few operations per centre
and level to read, where summing at each centre the kernels that cover it costs their
number (about c^d k per centre for the adaptive estimate, which grows with n). The grid's
own lattice is read exactly; coarser ones by Catmull-Rom interpolation along each axis in
turn (``read_grid``), exact at their points and third-order between: a lattice holds
kernels at least S steps wide only, so the error is a small fixed fraction of them
(``tests/test_adaptive.py`` measures it against the exact sums).

The box is handled as ``kernelsum`` does: along periodic axes kernels wrap (their images one
period away are drawn too), along the others the mass beyond a side folds back (the kernel's
mirror image in the side is drawn), so that a lattice holds the even extension across a
folded side and the interpolation stays smooth there. Coordinates are relative to the box's
lower corner. A lattice covers its kernels' supports within two steps of the box.
"""

import numpy as np
from scipy.sparse import csr_matrix

from .jit import kernel
from .kernelsum import axis_image

LEVEL_COLUMNS = 7  # per level in the plane: origin x, y, steps x, y, nx, ny, offset in values
OX, OY, SX, SY, NX, NY, OFFSET = range(LEVEL_COLUMNS)  # in space: ``draw3``'s layout


def plan_levels(centres, r, period, periodic, grid, samples, max_values):
    """(level of each kernel (-1: none, radius 0), levels (L, 3 d + 1), total values) for
    kernels at ``centres`` (n, d) of radii r in the box [0, period] (d,), read on the grid
    ``grid`` = (origin (d,), step (d,)) (the cells' centres origin + i step). A kernel's
    lattice steps are the grid's times 2^m, m >= 0 the largest with r / (the widest step)
    >= ``samples`` (one m for all axes: few lattices to read): kernels narrower than 2
    samples of the widest cell side are drawn on the grid itself (read exactly there), wider
    ones on coarser lattices through the same centres (read by interpolation between them).
    A level's row: its origin (d), steps (d), counts (d) and the offset of its values (the x
    axis fastest). None when the lattices would hold more than ``max_values``."""
    origin, step = (np.asarray(v, float) for v in grid)
    dim = len(origin)
    live = r > 0
    key = np.full(len(r), -1, np.int64)  # m, the same on every axis (few levels to read)
    with np.errstate(divide="ignore"):
        key[live] = np.maximum(np.floor(np.log2(r[live] / (samples * step.max()))), 0)
    # the levels present, in order, and each kernel's among them (-1: dead), by counting:
    # a few dozen keys at most (np.unique's sort took 0.2 s at 10^6 kernels)
    present = np.bincount(key + 1)  # (the dead kernels' key -1 at 0)
    keys = np.flatnonzero(present[1:])
    remap = np.full(len(present), -1, np.int64)
    remap[keys + 1] = np.arange(len(keys))
    level = remap[key + 1]
    pads = 2.0 * step[None, :] * 2.0 ** keys[:, None]  # (L, d): two steps of each lattice
    low, high, near_lo, near_hi = _level_bounds(
        np.ascontiguousarray(centres, float), np.ascontiguousarray(r, float), level,
        np.asarray(period, float), pads,
    )  # fmt: skip
    rows, total = [], 0
    for j, kk in enumerate(keys):
        spans = []
        for a in range(dim):
            ext, first = float(period[a]), origin[a]
            s = step[a] * 2.0 ** int(kk)
            pad = 2.0 * s
            lo = max(float(low[j, a]), -pad)
            hi = min(float(high[j, a]), ext + pad)
            if periodic[a] and (near_lo[j, a] or near_hi[j, a]):
                lo, hi = -pad, ext + pad  # images one period away reach into the box
            if not periodic[a] and near_lo[j, a]:
                lo = -pad  # mirror images in the lower side
            if not periodic[a] and near_hi[j, a]:
                hi = ext + pad
            i0 = np.floor((lo - first) / s)
            spans.append((first + i0 * s, s, int(np.floor((hi - first) / s) - i0) + 1))
        origins, steps, counts = zip(*spans, strict=True)
        rows.append((*origins, *steps, *counts, total))
        total += int(np.prod(counts))
        if total > max_values:
            return None
    return level, np.array(rows, float).reshape(-1, 3 * dim + 1), total


@kernel(entry=True, nogil=True)
def _level_bounds(centres, r, level, period, pads):
    """Per level j and axis a, over its kernels (``level``: -1 none): the least c - r, the
    greatest c + r, and whether one lies within r + pads[j, a] of the lower side, of the
    upper (``plan_levels``' lattice spans; one pass, no per-level copies)."""
    levels, d = pads.shape
    low = np.full((levels, d), np.inf)
    high = np.full((levels, d), -np.inf)
    near_lo = np.zeros((levels, d), np.bool_)
    near_hi = np.zeros((levels, d), np.bool_)
    for i in range(r.shape[0]):
        j = level[i]
        if j < 0:
            continue
        for a in range(d):
            c, rad = centres[i, a], r[i]
            low[j, a] = min(low[j, a], c - rad)
            high[j, a] = max(high[j, a], c + rad)
            if c < rad + pads[j, a]:
                near_lo[j, a] = True
            if c > period[a] - rad - pads[j, a]:
                near_hi[j, a] = True
    return low, high, near_lo, near_hi


@kernel(entry=True, nogil=True)
def draw(centres, r, amp, level, period, periodic, levels, values, start, stop):
    """Add kernels start..stop-1 (centres (n, 2)), amp_i (1 - |x - c_i|^2 / r_i^2)^3, and
    their images in the box's sides (``period`` (2,) its widths, ``periodic`` (2,)
    booleans), to the values of their level's lattice (``plan_levels``)."""
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
            x = axis_image(centres[i, 0], ia, period[0], periodic[0])
            i0 = max(int(np.ceil((x - rad - ox) / sx)), 0)
            i1 = min(int(np.floor((x + rad - ox) / sx)), nx - 1)
            if i0 > i1:
                continue
            for ib in range(3):
                y = axis_image(centres[i, 1], ib, period[1], periodic[1])
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


@kernel(entry=True, nogil=True)
def draw3(centres, r, amp, level, period, periodic, levels, values, start, stop):
    """``draw`` in space: add kernels start..stop-1, amp_i (1 - |x - c_i|^2 / r_i^2)^3, and
    their images in the box's sides, to their level's lattice; a level's row is origin (3),
    steps (3), counts (3), offset (``plan_levels``), x fastest in the values."""
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for i in range(start, stop):
        lev = level[i]
        if lev < 0:
            continue
        nx, ny, nz = int(levels[lev, 6]), int(levels[lev, 7]), int(levels[lev, 8])
        off = int(levels[lev, 9])
        rad = r[i]
        inv = 1.0 / (rad * rad)
        amp_i = amp[i]
        for a in range(3):
            x = axis_image(centres[i, 0], a, period[0], periodic[0])
            if not _span(x, rad, levels[lev, 0], levels[lev, 3], nx, lo, hi, 0):
                continue
            for b in range(3):
                y = axis_image(centres[i, 1], b, period[1], periodic[1])
                if not _span(y, rad, levels[lev, 1], levels[lev, 4], ny, lo, hi, 1):
                    continue
                for e in range(3):
                    z = axis_image(centres[i, 2], e, period[2], periodic[2])
                    if not _span(z, rad, levels[lev, 2], levels[lev, 5], nz, lo, hi, 2):
                        continue
                    ox, sx = levels[lev, 0], levels[lev, 3]
                    for kz in range(lo[2], hi[2] + 1):
                        ez = levels[lev, 2] + kz * levels[lev, 5] - z
                        for ky in range(lo[1], hi[1] + 1):
                            ey = levels[lev, 1] + ky * levels[lev, 4] - y
                            uyz = (ey * ey + ez * ez) * inv
                            if uyz >= 1.0:
                                continue
                            half = rad * np.sqrt(1.0 - uyz)  # the row's chord of the ball
                            k0 = max(int(np.ceil((x - half - ox) / sx)), lo[0])
                            k1 = min(int(np.floor((x + half - ox) / sx)), hi[0])
                            row = off + (kz * ny + ky) * nx
                            for kx in range(k0, k1 + 1):
                                ex = ox + kx * sx - x
                                v = max(1.0 - uyz - ex * ex * inv, 0.0)
                                values[row + kx] += amp_i * v * v * v
    return 0


@kernel(inline="always")
def _span(c, rad, origin, step, count, lo, hi, a):
    """The lattice indices [lo[a], hi[a]] along axis a within rad of c; False when none."""
    lo[a] = max(int(np.ceil((c - rad - origin) / step)), 0)
    hi[a] = min(int(np.floor((c + rad - origin) / step)), count - 1)
    return lo[a] <= hi[a]


def read_grid(levels, values, origin, step, counts):
    """The sum over levels of the lattices' values interpolated at the centres of the grid
    origin + i * step (counts (d,) per axis, x first), as an array (..., ny, nx), clipped at
    0 (interpolation may dip below it beside a steep rim). Catmull-Rom along each axis in
    turn (``axis_weights``: four weights per centre, sparse), so a level costs a few
    multiply-adds per centre, not 4^d; values beyond a lattice count as 0 (no kernel of its
    level reaches there); the grid's own lattice is read exactly (one weight, 1)."""
    dim = len(counts)
    out = np.zeros(tuple(int(c) for c in counts[::-1]))
    for row in levels:
        lat_origin, lat_step = row[:dim], row[dim : 2 * dim]
        lat_counts = row[2 * dim : 3 * dim].astype(np.int64)
        off = int(row[3 * dim])
        v = values[off : off + int(np.prod(lat_counts))].reshape(lat_counts[::-1])
        shift = (lat_origin - origin) / step
        if np.allclose(lat_step, step) and np.allclose(shift, np.round(shift), atol=1e-9):
            _add_block(out, v, np.round(shift).astype(np.int64))  # the grid's own: exact
            continue
        for a in range(dim - 1, -1, -1):  # array axis 0 is lattice axis a: z (y), ..., x
            at = origin[a] + np.arange(counts[a]) * step[a]
            m = axis_weights(lat_origin[a], lat_step[a], lat_counts[a], at)
            v = (m @ v.reshape(v.shape[0], -1)).reshape(len(at), *v.shape[1:])
            v = np.moveaxis(v, 0, -1)  # the next axis first; after d turns, as they were
        out += v
    return np.maximum(out, 0.0, out=out)


def _add_block(out, v, shift):
    """out += v placed with its first cell at grid index ``shift`` (x first), the part
    beyond the grid dropped (no kernel there reaches a centre)."""
    target, source = [], []
    for a in range(len(shift) - 1, -1, -1):  # array axes: the slowest first
        n, m = out.shape[len(shift) - 1 - a], v.shape[len(shift) - 1 - a]
        lo, hi = max(int(shift[a]), 0), min(int(shift[a]) + m, n)
        if lo >= hi:
            return
        target.append(slice(lo, hi))
        source.append(slice(lo - int(shift[a]), hi - int(shift[a])))
    out[tuple(target)] += v[tuple(source)]


@kernel(inline="always")
def catmull_rom(t, out):
    """The four Catmull-Rom weights of the lattice points i - 1, i, i + 1, i + 2 at i + t
    (0 <= t < 1): cubic, exact at the lattice points, reproducing quadratics."""
    t2 = t * t
    t3 = t2 * t
    out[0] = 0.5 * (-t3 + 2.0 * t2 - t)
    out[1] = 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0)
    out[2] = 0.5 * (-3.0 * t3 + 4.0 * t2 + t)
    out[3] = 0.5 * (t3 - t2)


@kernel(entry=True)
def catmull_rom_rows(t, out):
    """out[j] = ``catmull_rom`` weights at t[j]."""
    for j in range(t.shape[0]):
        catmull_rom(t[j], out[j])
    return 0


def axis_weights(origin, step, count, at):
    """The (len(at), count) sparse matrix of Catmull-Rom weights that interpolates values at
    origin + i * step (i < count; 0 beyond) at the points ``at``; a point within 1e-9 steps
    of a lattice point takes its value alone."""
    f = (np.asarray(at, float) - origin) / step
    near = np.round(f)
    f = np.where(np.abs(f - near) < 1e-9, near, f)
    i = np.floor(f)
    w = np.empty((len(f), 4))
    catmull_rom_rows(f - i, w)
    cols = i.astype(np.int64)[:, None] - 1 + np.arange(4)
    rows = np.repeat(np.arange(len(f)), 4).reshape(-1, 4)
    keep = (cols >= 0) & (cols < count) & (w != 0.0)
    return csr_matrix((w[keep], (rows[keep], cols[keep])), shape=(len(f), int(count)))
