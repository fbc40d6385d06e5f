"""Leave-one-out sums of isotropic triweight kernels in the plane and in space through
binned lattices, so that scoring a smoothing costs about the same whatever the kernels'
overlap. (Below, the plane; space is the same in three dimensions, each ``*3`` kernel the
plane's one's: trilinear binning at eight lattice points, balls stamped with rows along x
spanning their chord, tricubic reads of 64 values, and SAMPLES3 = 3 steps a radius, since a
ball's stamp costs about (4/3) pi S^3 cells. Measured there against exact sums on a
three-Gaussian mixture at 10^5 points: 0.2 % (median) and 2 % (99th percentile) at S = 3,
0.05 % and 0.8 % at S = 4; ``tests/test_adaptive.py`` checks folded, wrapped, weighted,
duplicated points and the exact finest levels.)

Summing at a point the kernels that cover it costs their number: about c^2 k for the
adaptive estimate (k the pilot's, c the bandwidth factor), some 3,000 at 10^6 points. Here
a kernel of radius r goes to the lattice whose step s = step0 2^m puts r / s in [S, 2S)
(S = ``SAMPLES``; step0 the smallest radius over S; a lattice spans its kernels' centres
plus a margin, periodic axes whole where kernels reach the seam). Its mass is split among
the four lattice points around its centre (linear binning), and each lattice point keeps
the mass-weighted mean of log r of what it received. Each lattice point with mass then
carries one kernel of that radius (``stamp``: some 50 to 200 lattice points, however many
kernels were binned there; its images in the box's sides too, wrapped or folded as
``kernelsum`` does), and the sum at a point is read from every lattice by Catmull-Rom
interpolation (16 values per level). A point's own share goes through the same steps (its
four shares spread by those lattice points' kernels, read with the same weights:
``own_terms``), so leave-one-out values are the binned estimate's without the point.

This is an estimate of the kernel sum, not the sum. Binning spreads a kernel's mass by a
tent of one step (variance s^2 / 6 per axis): the kernel drawn is narrowed to keep the
triweight's r^2 / 10 (``BINNING_VARIANCE``), which cut the error about threefold; the mean
radius stands for the radii binned at a lattice point (the pilot is smooth over a step).
Measured against exact sums on the multi-scale Gaussian mixture at 10^4 to 10^6 points (three
smoothings, 20,000 points): each point's leave-one-out density within 0.1-0.3 % (median) and
0.5-1.5 % (99th percentile), the mean log-likelihood within 1e-4. Where a point's own share
is most of its binned sum, the difference keeps binning's error but not the sum's size: the
caller sums those exactly (``AdaptiveDensity``). ``tests/test_adaptive.py`` checks folded,
wrapped, weighted, collinear, duplicated, seam-crossing and real points. Costs: O(n) to bin,
O(lattice points with mass x S^2) to draw, O(1) per point read, against O(c^2 k) per point
exactly. Coordinates are relative to the box's lower corner (``BoxMetric.frame``).
"""

import numpy as np

from . import kernelsum, kernelsum3
from .jit import kernel
from .kernelsum import MASS, axis_image
from .lattice import catmull_rom
from .threads import in_chunks

SAMPLES = 4  # lattice steps per kernel radius, at least (at most twice as many)
SAMPLES3 = 3  # in space (a ball's stamp costs about (4/3) pi S^3 cells a lattice point)
LEVELS = 64  # lattices step0 2^m, m < LEVELS (radii over 2^64 smallest radii: none)
BINNING_VARIANCE = 10.0 / 6.0  # steps^2 off a radius^2: the binning's tent (see ``stamp``)
BINNING_VARIANCE3 = 11.0 / 6.0  # in space (a ball's triweight has variance r^2 / 11 an axis)
MASS3 = kernelsum3.MASS  # the integral of (1 - |x|^2)^3 over the unit ball
VALUES_PER_CENTRE = 8  # the lattices hold at most this many values per kernel,
LEAST_VALUES = 1 << 22  # or this many
READS_A_RANGE = 8192  # points read a thread's range at least (a read costs about 0.2 us)


@kernel(inline="always")
def _level(r, samples, step0):
    """(the level m of a kernel of radius r > 0: r / (step0 2^m) in [samples, 2 samples)
    within 0..LEVELS-1, the log of r in that level's steps)."""
    lr = np.log(r)
    m = int(np.floor((lr - np.log(samples * step0)) / np.log(2.0)))
    m = min(max(m, 0), LEVELS - 1)
    return m, lr - np.log(step0) - m * np.log(2.0)


@kernel(entry=True, nogil=True)
def assign_levels(cx, cy, r, samples, step0, level, steps, box):
    """level[i]: the lattice of kernel i (-1: radius 0, no kernel), steps[i] the log of its
    radius in that lattice's steps (``deposit`` reads it); box (LEVELS, 4): the least and
    greatest x and y of each level's centres (the caller fills it with +-inf first)."""
    for i in range(r.shape[0]):
        if not r[i] > 0.0:
            level[i] = -1
            continue
        m, steps[i] = _level(r[i], samples, step0)
        level[i] = m
        box[m, 0] = min(box[m, 0], cx[i])
        box[m, 1] = min(box[m, 1], cy[i])
        box[m, 2] = max(box[m, 2], cx[i])
        box[m, 3] = max(box[m, 3], cy[i])
    return 0


@kernel(entry=True, nogil=True)
def deposit(cx, cy, steps, mass, level, step0, lattices, mass_at, log_r_at):
    """Bin each kernel's mass at the four lattice points around its centre (linear
    weights), and mass * log(r / s) with it (``steps``: for the mean radius, in steps)."""
    for i in range(steps.shape[0]):
        m = level[i]
        if m < 0:
            continue
        s = step0 * 2.0**m
        lq = steps[i]
        fx = cx[i] / s - lattices[m, 0]
        fy = cy[i] / s - lattices[m, 1]
        ix = int(np.floor(fx))
        iy = int(np.floor(fy))
        tx = fx - ix
        ty = fy - iy
        nx = lattices[m, 2]
        b = lattices[m, 4] + iy * nx + ix
        w = mass[i]
        for d in range(4):
            dx = d & 1
            dy = d >> 1
            share = w * (tx if dx else 1.0 - tx) * (ty if dy else 1.0 - ty)
            mass_at[b + dy * nx + dx] += share
            log_r_at[b + dy * nx + dx] += share * lq
    return 0


@kernel(entry=True, nogil=True)
def stamp(mass_at, log_r_at, values, step0, lattices, period, periodic, start, stop):
    """Spread the mass of each lattice point start..stop-1 (over all lattices, in their
    order) by a triweight kernel of its mean radius onto its lattice's values, images in the
    box's sides included; log_r_at becomes that radius in steps (``own_terms`` reads it)."""
    for m in range(LEVELS):
        nx, ny, off = lattices[m, 2], lattices[m, 3], lattices[m, 4]
        first = max(start, off)
        last = min(stop, off + nx * ny)
        if first >= last:
            continue
        s = step0 * 2.0**m
        ox, oy = lattices[m, 0], lattices[m, 1]
        for b in range(first, last):
            mm = mass_at[b]
            if mm == 0.0:
                continue
            iy = (b - off) // nx
            ix = b - off - iy * nx
            # linear binning spreads mass by a tent of variance 1/6 step^2 per axis: the
            # kernel drawn is narrowed to keep the triweight's variance rho^2 / 10 per axis
            rho = np.sqrt(np.exp(2.0 * log_r_at[b] / mm) - BINNING_VARIANCE)
            log_r_at[b] = rho
            amp = mm / (MASS * rho * rho * s * s)
            inv = 1.0 / (rho * rho)
            reach = int(rho) + 1
            px = (ox + ix) * s
            py = (oy + iy) * s
            for ia in range(3):
                fx = axis_image(px, ia, period[0], periodic[0]) / s - ox
                if fx < -reach or fx > nx + reach:
                    continue
                for ib in range(3):
                    fy = axis_image(py, ib, period[1], periodic[1]) / s - oy
                    if fy < -reach or fy > ny + reach:
                        continue
                    cxn = int(np.floor(fx))
                    cyn = int(np.floor(fy))
                    x0, x1 = max(cxn - reach, 0), min(cxn + reach + 1, nx - 1)
                    for yy in range(max(cyn - reach, 0), min(cyn + reach + 1, ny - 1) + 1):
                        ey = yy - fy
                        uy = ey * ey * inv
                        if uy >= 1.0:
                            continue
                        row = off + yy * nx
                        for xx in range(x0, x1 + 1):
                            ex = xx - fx
                            u = ex * ex * inv + uy
                            if u < 1.0:
                                v = 1.0 - u
                                values[row + xx] += amp * v * v * v
    return 0


@kernel(entry=True, nogil=True)
def read_sums(qx, qy, values, step0, lattices, out, start, stop):
    """out[j]: the lattices' values interpolated at point j (0 off a lattice: none of its
    kernels reaches there)."""
    wx = np.empty(4)
    wy = np.empty(4)
    for j in range(start, stop):
        total = 0.0
        for m in range(LEVELS):
            nx, ny, off = lattices[m, 2], lattices[m, 3], lattices[m, 4]
            if nx == 0:
                continue
            s = step0 * 2.0**m
            fx = qx[j] / s - lattices[m, 0]
            fy = qy[j] / s - lattices[m, 1]
            ix = int(np.floor(fx))
            iy = int(np.floor(fy))
            if ix < 1 or iy < 1 or ix + 2 >= nx or iy + 2 >= ny:
                continue
            catmull_rom(fx - ix, wx)
            catmull_rom(fy - iy, wy)
            for b in range(4):
                row = off + (iy - 1 + b) * nx + ix - 1
                acc = 0.0
                for a in range(4):
                    acc += wx[a] * values[row + a]
                total += wy[b] * acc
        out[j] = total
    return 0


@kernel(entry=True, nogil=True)
def read_grid(xs, ys, values, step0, lattices, out, start, stop):
    """out[b, a] (rows start..stop-1): the lattices' values interpolated at (xs[a], ys[b]),
    as ``read_sums`` reads each point, but separably: each lattice's rows are interpolated
    at the columns xs once, then those at the rows ys (a grid of nx x ny centres costs
    about 4 (nx rows + nx ny) a lattice, not 16 nx ny)."""
    wx = np.empty((xs.shape[0], 4))
    wy = np.empty(4)
    cols = np.empty(xs.shape[0], np.int64)
    for m in range(LEVELS):
        nx, ny, off = lattices[m, 2], lattices[m, 3], lattices[m, 4]
        if nx == 0:
            continue
        s = step0 * 2.0**m
        first, last = ny, -1  # the lattice rows the grid rows start..stop-1 read
        for b in range(start, stop):
            fy = ys[b] / s - lattices[m, 1]
            iy = int(np.floor(fy))
            if iy >= 1 and iy + 2 < ny:
                first = min(first, iy - 1)
                last = max(last, iy + 2)
        if last < first:
            continue
        for a in range(xs.shape[0]):  # each column's lattice cell and weights (-1: off it)
            fx = xs[a] / s - lattices[m, 0]
            ix = int(np.floor(fx))
            if ix < 1 or ix + 2 >= nx:
                cols[a] = -1
                continue
            cols[a] = ix - 1
            catmull_rom(fx - ix, wx[a])
        rows = np.zeros((last - first + 1, xs.shape[0]))  # lattice rows read at the columns
        for r in range(first, last + 1):
            base = off + r * nx
            for a in range(xs.shape[0]):
                c = cols[a]
                if c >= 0:
                    rows[r - first, a] = (wx[a, 0] * values[base + c]
                                          + wx[a, 1] * values[base + c + 1]
                                          + wx[a, 2] * values[base + c + 2]
                                          + wx[a, 3] * values[base + c + 3])  # fmt: skip
        for b in range(start, stop):
            fy = ys[b] / s - lattices[m, 1]
            iy = int(np.floor(fy))
            if iy < 1 or iy + 2 >= ny:
                continue
            catmull_rom(fy - iy, wy)
            r0 = iy - 1 - first
            for a in range(xs.shape[0]):
                out[b, a] += (wy[0] * rows[r0, a] + wy[1] * rows[r0 + 1, a]
                              + wy[2] * rows[r0 + 2, a] + wy[3] * rows[r0 + 3, a])  # fmt: skip
    return 0


@kernel(entry=True, nogil=True)
def own_terms(qx, qy, mass, level, step0, lattices, radius_at, period, periodic, out, start,
              stop):  # fmt: skip
    """out[j]: the part of ``read_sums`` at centre j (level[j] its lattice) that mass[j] binned
    there gives: its four shares, each spread by its lattice point's kernel (images
    included) and read with the same interpolation weights."""
    wx = np.empty(4)
    wy = np.empty(4)
    for j in range(start, stop):
        m = level[j]
        if m < 0:
            out[j] = 0.0
            continue
        s = step0 * 2.0**m
        ox, oy, nx, off = lattices[m, 0], lattices[m, 1], lattices[m, 2], lattices[m, 4]
        fx = qx[j] / s - ox
        fy = qy[j] / s - oy
        ix = int(np.floor(fx))
        iy = int(np.floor(fy))
        tx = fx - ix
        ty = fy - iy
        catmull_rom(tx, wx)
        catmull_rom(ty, wy)
        total = 0.0
        for d in range(4):
            dx = d & 1
            dy = d >> 1
            rho = radius_at[off + (iy + dy) * nx + ix + dx]
            share = (tx if dx else 1.0 - tx) * (ty if dy else 1.0 - ty)
            if share == 0.0 or not rho > 0.0:  # nothing binned there (no kernel drawn)
                continue
            amp = mass[j] * share / (MASS * rho * rho * s * s)
            inv = 1.0 / (rho * rho)
            px = (ox + ix + dx) * s
            py = (oy + iy + dy) * s
            for ia in range(3):
                x = axis_image(px, ia, period[0], periodic[0]) / s - ox
                if abs(x - fx) > rho + 2.0:
                    continue
                for ib in range(3):
                    y = axis_image(py, ib, period[1], periodic[1]) / s - oy
                    if abs(y - fy) > rho + 2.0:
                        continue
                    for b in range(4):
                        ey = iy - 1 + b - y
                        for a in range(4):
                            ex = ix - 1 + a - x
                            u = (ex * ex + ey * ey) * inv
                            if u < 1.0:
                                v = 1.0 - u
                                total += wx[a] * wy[b] * amp * v * v * v
        out[j] = total
    return 0


@kernel(entry=True, nogil=True)
def assign_levels3(cx, cy, cz, r, samples, step0, level, steps, box):
    """``assign_levels`` in space: box (LEVELS, 6) the least and greatest x, y and z of each
    level's centres."""
    for i in range(r.shape[0]):
        if not r[i] > 0.0:
            level[i] = -1
            continue
        m, steps[i] = _level(r[i], samples, step0)
        level[i] = m
        box[m, 0] = min(box[m, 0], cx[i])
        box[m, 1] = min(box[m, 1], cy[i])
        box[m, 2] = min(box[m, 2], cz[i])
        box[m, 3] = max(box[m, 3], cx[i])
        box[m, 4] = max(box[m, 4], cy[i])
        box[m, 5] = max(box[m, 5], cz[i])
    return 0


@kernel(entry=True, nogil=True)
def deposit3(cx, cy, cz, steps, mass, level, step0, lattices, mass_at, log_r_at):
    """``deposit`` in space: each kernel's mass at the eight lattice points around its
    centre (trilinear weights); a lattice's row is origin (3), counts (3), offset."""
    for i in range(steps.shape[0]):
        m = level[i]
        if m < 0:
            continue
        s = step0 * 2.0**m
        lq = steps[i]
        fx = cx[i] / s - lattices[m, 0]
        fy = cy[i] / s - lattices[m, 1]
        fz = cz[i] / s - lattices[m, 2]
        ix = int(np.floor(fx))
        iy = int(np.floor(fy))
        iz = int(np.floor(fz))
        tx = fx - ix
        ty = fy - iy
        tz = fz - iz
        nx, ny = lattices[m, 3], lattices[m, 4]
        b = lattices[m, 6] + (iz * ny + iy) * nx + ix
        w = mass[i]
        for d in range(8):
            dx = d & 1
            dy = (d >> 1) & 1
            dz = d >> 2
            share = (w * (tx if dx else 1.0 - tx) * (ty if dy else 1.0 - ty)
                     * (tz if dz else 1.0 - tz))  # fmt: skip
            at = b + (dz * ny + dy) * nx + dx
            mass_at[at] += share
            log_r_at[at] += share * lq
    return 0


@kernel(entry=True, nogil=True)
def stamp3(mass_at, log_r_at, values, step0, lattices, period, periodic, start, stop):
    """``stamp`` in space: each lattice point's mass spread by a triweight ball of its mean
    radius (narrowed by the binning's variance, BINNING_VARIANCE3), images included; rows
    along x span the ball's chord."""
    for m in range(LEVELS):
        nx, ny, nz, off = lattices[m, 3], lattices[m, 4], lattices[m, 5], lattices[m, 6]
        first = max(start, off)
        last = min(stop, off + nx * ny * nz)
        if first >= last:
            continue
        s = step0 * 2.0**m
        ox, oy, oz = lattices[m, 0], lattices[m, 1], lattices[m, 2]
        for b in range(first, last):
            mm = mass_at[b]
            if mm == 0.0:
                continue
            rest = b - off
            iz = rest // (nx * ny)
            iy = (rest - iz * nx * ny) // nx
            ix = rest - (iz * ny + iy) * nx
            rho = np.sqrt(np.exp(2.0 * log_r_at[b] / mm) - BINNING_VARIANCE3)
            log_r_at[b] = rho
            amp = mm / (MASS3 * rho * rho * rho * s * s * s)
            inv = 1.0 / (rho * rho)
            reach = int(rho) + 1
            px = (ox + ix) * s
            py = (oy + iy) * s
            pz = (oz + iz) * s
            for ia in range(3):
                fx = axis_image(px, ia, period[0], periodic[0]) / s - ox
                if fx < -reach or fx > nx + reach:
                    continue
                for ib in range(3):
                    fy = axis_image(py, ib, period[1], periodic[1]) / s - oy
                    if fy < -reach or fy > ny + reach:
                        continue
                    for ic in range(3):
                        fz = axis_image(pz, ic, period[2], periodic[2]) / s - oz
                        if fz < -reach or fz > nz + reach:
                            continue
                        czn = int(np.floor(fz))
                        cyn = int(np.floor(fy))
                        for zz in range(max(czn - reach, 0), min(czn + reach + 1, nz - 1) + 1):
                            ez = zz - fz
                            uz = ez * ez * inv
                            if uz >= 1.0:
                                continue
                            for yy in range(max(cyn - reach, 0), min(cyn + reach + 1, ny - 1) + 1):
                                ey = yy - fy
                                uyz = ey * ey * inv + uz
                                if uyz >= 1.0:
                                    continue
                                half = rho * np.sqrt(1.0 - uyz)  # the row's chord of the ball
                                x0 = max(int(np.ceil(fx - half)), 0)
                                x1 = min(int(np.floor(fx + half)), nx - 1)
                                row = off + (zz * ny + yy) * nx
                                for xx in range(x0, x1 + 1):
                                    ex = xx - fx
                                    v = max(1.0 - uyz - ex * ex * inv, 0.0)
                                    values[row + xx] += amp * v * v * v
    return 0


@kernel(entry=True, nogil=True)
def read_sums3(qx, qy, qz, values, step0, lattices, out, start, stop):
    """``read_sums`` in space: every lattice read by tricubic Catmull-Rom interpolation."""
    wx = np.empty(4)
    wy = np.empty(4)
    wz = np.empty(4)
    for j in range(start, stop):
        total = 0.0
        for m in range(LEVELS):
            nx, ny, nz, off = lattices[m, 3], lattices[m, 4], lattices[m, 5], lattices[m, 6]
            if nx == 0:
                continue
            s = step0 * 2.0**m
            fx = qx[j] / s - lattices[m, 0]
            fy = qy[j] / s - lattices[m, 1]
            fz = qz[j] / s - lattices[m, 2]
            ix = int(np.floor(fx))
            iy = int(np.floor(fy))
            iz = int(np.floor(fz))
            if ix < 1 or iy < 1 or iz < 1 or ix + 2 >= nx or iy + 2 >= ny or iz + 2 >= nz:
                continue
            catmull_rom(fx - ix, wx)
            catmull_rom(fy - iy, wy)
            catmull_rom(fz - iz, wz)
            for c in range(4):
                plane = 0.0
                for b in range(4):
                    row = off + ((iz - 1 + c) * ny + iy - 1 + b) * nx + ix - 1
                    acc = 0.0
                    for a in range(4):
                        acc += wx[a] * values[row + a]
                    plane += wy[b] * acc
                total += wz[c] * plane
        out[j] = total
    return 0


@kernel(entry=True, nogil=True)
def own_terms3(qx, qy, qz, mass, level, step0, lattices, radius_at, period, periodic, out,
               start, stop):  # fmt: skip
    """``own_terms`` in space: the part of ``read_sums3`` at centre j that its own mass,
    binned at the eight lattice points around it, gives."""
    wx = np.empty(4)
    wy = np.empty(4)
    wz = np.empty(4)
    for j in range(start, stop):
        m = level[j]
        if m < 0:
            out[j] = 0.0
            continue
        s = step0 * 2.0**m
        ox, oy, oz = lattices[m, 0], lattices[m, 1], lattices[m, 2]
        nx, ny, off = lattices[m, 3], lattices[m, 4], lattices[m, 6]
        fx = qx[j] / s - ox
        fy = qy[j] / s - oy
        fz = qz[j] / s - oz
        ix = int(np.floor(fx))
        iy = int(np.floor(fy))
        iz = int(np.floor(fz))
        tx = fx - ix
        ty = fy - iy
        tz = fz - iz
        catmull_rom(tx, wx)
        catmull_rom(ty, wy)
        catmull_rom(tz, wz)
        total = 0.0
        for d in range(8):
            dx = d & 1
            dy = (d >> 1) & 1
            dz = d >> 2
            rho = radius_at[off + ((iz + dz) * ny + iy + dy) * nx + ix + dx]
            share = ((tx if dx else 1.0 - tx) * (ty if dy else 1.0 - ty)
                     * (tz if dz else 1.0 - tz))  # fmt: skip
            if share == 0.0 or not rho > 0.0:
                continue
            amp = mass[j] * share / (MASS3 * rho * rho * rho * s * s * s)
            inv = 1.0 / (rho * rho)
            px = (ox + ix + dx) * s
            py = (oy + iy + dy) * s
            pz = (oz + iz + dz) * s
            for ia in range(3):
                x = axis_image(px, ia, period[0], periodic[0]) / s - ox
                if abs(x - fx) > rho + 2.0:
                    continue
                for ib in range(3):
                    y = axis_image(py, ib, period[1], periodic[1]) / s - oy
                    if abs(y - fy) > rho + 2.0:
                        continue
                    for ic in range(3):
                        z = axis_image(pz, ic, period[2], periodic[2]) / s - oz
                        if abs(z - fz) > rho + 2.0:
                            continue
                        for c in range(4):
                            ez = iz - 1 + c - z
                            for b in range(4):
                                ey = iy - 1 + b - y
                                for a in range(4):
                                    ex = ix - 1 + a - x
                                    u = (ex * ex + ey * ey + ez * ez) * inv
                                    if u < 1.0:
                                        v = 1.0 - u
                                        total += wx[a] * wy[b] * wz[c] * amp * v * v * v
        out[j] = total
    return 0


class BinnedLevels:
    """Each kernel's lattice: its level, its radius in that level's steps and each level's
    span of centres, for kernels at ``centres`` (frame coordinates: (cx, cy) in the plane,
    (cx, cy, cz) in space) of radii r. Radii c r, for any c > 0, fall on the same levels
    with the same radii in steps (the steps scale with c): a search over c at one
    sensitivity finds its kernels' levels once (``BinnedSums(..., levels=, scale=c)``)."""

    def __init__(self, centres, r, samples=None):
        centres = [np.ascontiguousarray(c, float) for c in centres]
        dim = len(centres)
        if samples is None:
            samples = SAMPLES if dim == 2 else SAMPLES3
        self.r = np.ascontiguousarray(r, float)
        live = self.r > 0
        self.samples = samples
        self.step0 = float(self.r[live].min()) / samples if live.any() else 1.0
        n = len(self.r)
        self.level = np.empty(n, np.int8)  # LEVELS < 128
        self.steps = np.empty(n)
        assign = assign_levels if dim == 2 else assign_levels3
        parts = []  # per range of centres: each level's span of centres

        def spans(a, b):
            box = np.empty((LEVELS, 2 * dim))
            box[:, :dim], box[:, dim:] = np.inf, -np.inf
            assign(*(c[a:b] for c in centres), self.r[a:b], float(samples), self.step0,
                   self.level[a:b], self.steps[a:b], box)  # fmt: skip
            parts.append(box)

        in_chunks(spans, n, least=65536, per_thread=1)
        low = np.min([p[:, :dim] for p in parts], axis=0)
        high = np.max([p[:, dim:] for p in parts], axis=0)
        self.box = np.concatenate([low, high], axis=1)


class BinnedSums:
    """The binned lattices of kernels at ``centres`` ((cx, cy) in the plane, (cx, cy, cz) in
    space: frame coordinates in the box [0, period]) with radii r and masses ``mass``, built
    once, read as leave-one-out sums at centres (``without``) or as sums anywhere (``at``).
    ``levels``: the kernels' ``BinnedLevels`` at radii r / scale, found once for several
    scales (r is then not read: None)."""

    def __init__(self, centres, r, mass, period, periodic, samples=None, levels=None,
                 scale=1.0):  # fmt: skip
        self.centres = [np.ascontiguousarray(c, float) for c in centres]
        self.dim = dim = len(self.centres)
        self.mass = np.ascontiguousarray(mass, float)
        self.period = np.asarray(period, float)
        self.periodic = np.asarray(periodic, bool)
        if levels is None:
            levels, scale = BinnedLevels(self.centres, r, samples), 1.0
        samples = levels.samples
        self.step0 = scale * levels.step0
        self.level = levels.level
        n = len(self.level)
        lo = np.full((LEVELS, dim), 1 << 60, np.int64)
        hi = np.full((LEVELS, dim), -(1 << 60), np.int64)
        for m in np.flatnonzero(levels.box[:, 0] <= levels.box[:, dim]):
            s = self.step0 * 2.0**m
            lo[m] = np.floor(levels.box[m, :dim] / s)
            hi[m] = np.floor(levels.box[m, dim:] / s) + 1
        # the finest levels whose lattices would pass the limit are summed exactly (kernels
        # far narrower than most, spread wide: near-copies of points, say)
        limit = max(VALUES_PER_CENTRE * n, LEAST_VALUES)
        lattices, _ = self._lattices(lo, hi, samples)
        size = np.prod(lattices[:, dim : 2 * dim], axis=1)
        over = np.cumsum(size[::-1])[::-1] > limit  # this level and the coarser ones
        self.exact = None
        if over.any():
            cut = int(np.flatnonzero(over)[-1]) + 1  # levels below it: exact
            narrow = (self.level >= 0) & (self.level < cut)
            self.level = np.where(narrow, -1, self.level).astype(np.int8)
            lo[:cut], hi[:cut] = 1 << 60, -(1 << 60)
            self.exact = self._exact_tree(np.flatnonzero(narrow), scale * levels.r)
        self.lattices, total = self._lattices(lo, hi, samples)
        steps = levels.steps
        put, draw = (deposit, stamp) if dim == 2 else (deposit3, stamp3)
        binned = []  # per range of centres: (mass, mass * log r) at the lattice points

        def bin_range(a, b):
            mass_at, log_r_at = np.zeros(total), np.zeros(total)
            put(*(c[a:b] for c in self.centres), steps[a:b], self.mass[a:b], self.level[a:b],
                self.step0, self.lattices, mass_at, log_r_at)  # fmt: skip
            binned.append((mass_at, log_r_at))

        in_chunks(bin_range, n, least=65536, per_thread=1)
        mass_at, log_r_at = binned[0]
        for more, log_more in binned[1:]:
            mass_at += more
            log_r_at += log_more
        stamped = []  # per range of lattice points: values (kernels overlap the ranges)

        def stamp_range(a, b):
            values = np.zeros(total)
            draw(mass_at, log_r_at, values, self.step0, self.lattices, self.period,
                 self.periodic, a, b)  # fmt: skip
            stamped.append(values)

        in_chunks(stamp_range, total, least=65536 if dim == 2 else 8192, per_thread=1)
        self.values = stamped[0]
        for more in stamped[1:]:
            self.values += more
        self.radius_at = log_r_at

    def _exact_tree(self, which, r):
        """The kd-tree (``kernelsum`` or ``kernelsum3``) of kernels ``which``, summed
        exactly."""
        k = kernelsum if self.dim == 2 else kernelsum3
        rows, box, node = k.build_centres(np.column_stack([c[which] for c in self.centres]),
                                          self.mass[which])  # fmt: skip
        rr = r[which][rows[:, k.ROW].astype(np.int64)]
        if self.dim == 2:
            rows[:, k.Q11] = rows[:, k.Q22] = 1.0 / (rr * rr)
        else:
            rows[:, k.Q] = 1.0 / (rr * rr)
        rows[:, k.AMP] = rows[:, k.W] / (k.MASS * rr**self.dim)
        rows[:, k.R] = rr
        extent = np.zeros(len(node))
        kernelsum.node_extents(rows[:, k.R], node, extent)  # the column itself, as every caller
        return rows, box, node, extent

    def _lattices(self, lo, hi, samples):
        """((LEVELS, 2 dim + 1) int64: each lattice's origin index and counts per axis and
        offset; the lattices' total size)."""
        dim = self.dim
        out = np.zeros((LEVELS, 2 * dim + 1), np.int64)
        pad = 2 * samples + 4  # a stamp (radius < 2S + 1) and an interpolation's reach
        offset = 0
        for m in range(LEVELS):
            if hi[m, 0] < lo[m, 0]:
                continue
            s = self.step0 * 2.0**m
            a, b = lo[m] - pad, hi[m] + pad
            for axis in range(dim):
                cells = int(np.ceil(self.period[axis] / s))
                if self.periodic[axis] and (a[axis] < pad or b[axis] > cells - pad):
                    a[axis], b[axis] = min(a[axis], -pad), max(b[axis], cells + pad)
            out[m, :dim] = a
            out[m, dim : 2 * dim] = b - a + 1
            out[m, 2 * dim] = offset
            offset += int(np.prod(out[m, dim : 2 * dim]))
        return out, offset

    def _exact_sums(self, q, loo):
        """The narrowest kernels' exact sums at points q (m, dim), left out at their places
        with ``loo``."""
        rows, box, node, extent = self.exact
        sums = (kernelsum if self.dim == 2 else kernelsum3).kernel_sums
        more, ignored = np.empty(len(q)), np.empty(len(q))
        in_chunks(lambda a, b: sums(rows, box, node, extent, q, loo, self.period, self.periodic,
                                    more, ignored, a, b), len(q))  # fmt: skip
        return more

    def at(self, *q):
        """The binned sums at any points of the box (frame coordinates, one array per axis):
        every lattice read there, and the narrowest kernels' exact sums where they were
        kept apart."""
        q = [np.ascontiguousarray(c, float) for c in q]
        sums = np.empty(len(q[0]))
        read = read_sums if self.dim == 2 else read_sums3
        in_chunks(lambda a, b: read(*q, self.values, self.step0, self.lattices, sums, a, b),
                  len(sums), least=READS_A_RANGE)  # fmt: skip
        if self.exact is not None:
            sums += self._exact_sums(np.column_stack(q), False)
        return sums

    def grid(self, xs, ys):
        """The binned sums at the centres of a grid (``at`` at every (xs[a], ys[b]), frame
        coordinates; in the plane), (len(ys), len(xs)): the lattices read separably
        (``read_grid``)."""
        xs, ys = np.ascontiguousarray(xs, float), np.ascontiguousarray(ys, float)
        out = np.zeros((len(ys), len(xs)))
        in_chunks(lambda a, b: read_grid(xs, ys, self.values, self.step0, self.lattices, out,
                                         a, b), len(ys), least=16)  # fmt: skip
        if self.exact is not None:
            gx, gy = np.meshgrid(xs, ys)
            out += self._exact_sums(np.column_stack([gx.ravel(), gy.ravel()]), False).reshape(
                out.shape
            )
        return out

    def without(self, idx, copies):
        """(sums, own) at centres ``idx``: the binned sums there, and the share in them of the
        centres at that place (``copies``: their total mass). sums - own is the leave-one-out
        sum; where own is most of sums, that difference keeps binning's error but not the
        sum's size (check it exactly)."""
        idx = np.asarray(idx, np.int64)
        q = [c[idx] for c in self.centres]
        sums = np.empty(len(idx))
        own = np.empty(len(idx))
        mass, level = np.ascontiguousarray(copies, float), self.level[idx]
        read, mine = (read_sums, own_terms) if self.dim == 2 else (read_sums3, own_terms3)

        def call(a, b):
            read(*q, self.values, self.step0, self.lattices, sums, a, b)
            mine(*q, mass, level, self.step0, self.lattices, self.radius_at, self.period,
                 self.periodic, own, a, b)  # fmt: skip

        in_chunks(call, len(idx), least=READS_A_RANGE)
        if self.exact is not None:  # the narrowest kernels' sums, their copies left out
            sums += self._exact_sums(np.column_stack(q), True)
        return sums, own
