"""From the user's box to the engine's torus, and back.

The engine always refines a flat torus [0, lx) x [0, ly) in internal units. Along a periodic
axis the torus period is the box's side. Along a non-periodic axis the box is embedded in a
longer period, with a margin on both sides, long enough that no periodic copy of a point can be
among the k nearest of any point of the box:

    for x, p in the box, |x - (p + L e)| >= L - w > D >= d_{P,k}(x)        (n >= k)

where w is the box's side along that axis and D the box's diameter in its own metric (half the
side along periodic axes, the full side along the others). We take L = w + 1.05 D. Then on the
box the periodic k-th-neighbour distance *is* the planar one, the torus refinement's guarantee
holds verbatim for the planar d_{P,k}, and nothing is approximated. The margin holds no data,
so the mesh there coarsens quickly and costs few vertices.

Internal units: x_int = (x - origin) * scale with scale a power of two (exact), so that the
longest period is in (1/2, 1]; periods are rounded to the grid Q (a relative change < 1e-15).
"""

from dataclasses import dataclass

import numpy as np
from numba import njit

from .geometry import Q

MARGIN = 1.05


def wrap(x, period):
    """x mod period in [0, period), guarding the rounding case (-1e-17) % 1.0 == 1.0."""
    x = np.mod(x, period)
    return np.where(x >= period, 0.0, x)


@dataclass(frozen=True)
class Embedding:
    box: tuple  # (xmin, ymin, xmax, ymax), input units
    periodic: tuple  # (bool, bool)
    origin: np.ndarray  # input coordinates of the internal origin
    scale: float  # internal = (input - origin) * scale
    period_internal: tuple  # (lx, ly), multiples of Q

    @classmethod
    def make(cls, box, periodic):
        lo = np.array(box[:2], float)
        size = np.array(box[2:], float) - lo
        per = np.array(periodic, bool)
        diam = float(np.hypot(*np.where(per, size / 2.0, size)))
        period = np.where(per, size, size + MARGIN * diam)
        origin = np.where(per, lo, lo - (period - size) / 2.0)
        scale = 2.0 ** -int(np.ceil(np.log2(period.max())))
        lint = tuple(float(np.rint(p * scale / Q) * Q) for p in period)
        return cls(tuple(float(b) for b in box), tuple(bool(p) for p in per), origin, scale, lint)

    @property
    def period(self):
        """Torus periods in input units."""
        return tuple(p / self.scale for p in self.period_internal)

    def to_internal(self, x):
        """Internal coordinates of input points (n, 2), wrapped into the torus (a new array)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        return _to_internal(x, self.origin, self.scale, np.array(self.period_internal))

    def to_input(self, u):
        u = np.asarray(u, float)
        x = u / self.scale + self.origin
        for a in range(2):
            if self.periodic[a]:
                lo, hi = self.box[a], self.box[a + 2]
                x[:, a] = lo + wrap(u[:, a] / self.scale, hi - lo)
        return x

    def box_internal(self):
        lo = (np.array(self.box[:2]) - self.origin) * self.scale
        hi = (np.array(self.box[2:]) - self.origin) * self.scale
        return lo, hi


@njit(cache=True)
def _to_internal(x, origin, scale, period):
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        for a in range(2):
            u = (x[i, a] - origin[a]) * scale
            u -= np.floor(u / period[a]) * period[a]
            out[i, a] = u if u < period[a] else 0.0  # (-1e-17) % 1.0 rounds to 1.0
    return out


def unfold(vxy, tv, to, emb):
    """The part of the torus mesh that the box needs, as the user will see it.

    Along periodic axes nothing changes: vertices stay in the fundamental domain and triangles
    keep their corner offsets. Along non-periodic axes vertices become planar copies: the
    triangles kept are the copies that meet the box, and the vertices kept are the copies
    within r* of the box, r* being the longest edge of a kept triangle. That is every vertex
    that can be one of the two nearest to a point x of the box: x lies in a kept triangle, whose
    three corners are within its longest edge of x.

    Returns (vertex ids (m',), vertex shifts (m', 2) in periods, positions (m', 2) internal,
    triangles (t', 3) into the returned vertices, offsets (t', 3, 2) or None).
    """
    per = emb.periodic
    if all(per):
        m = vxy.shape[0]
        return np.arange(m), np.zeros((m, 2), np.int64), vxy, tv, to
    blo, bhi = emb.box_internal()
    L = np.array(emb.period_internal)
    nonper = np.array([not p for p in per])
    out_v, out_s, tri, offsets = _unfold(vxy, tv, to, L, blo, bhi, nonper)
    pos = vxy[out_v] + out_s * L
    return out_v, out_s, pos, tri, (offsets if any(per) else None)


@njit(cache=True)
def _unfold(vxy, tv, to, L, blo, bhi, nonper):
    m = vxy.shape[0]
    nt = tv.shape[0]
    sx_lo = -1 if nonper[0] else 0
    sy_lo = -1 if nonper[1] else 0
    sx_hi = 1 if nonper[0] else 0
    sy_hi = 1 if nonper[1] else 0
    # pass 1: triangle copies that meet the box along the non-periodic axes
    keep = np.zeros((nt, 9), np.bool_)
    nkeep = 0
    rstar2 = 0.0
    for t in range(nt):
        x0 = vxy[tv[t, 0], 0] + to[t, 0, 0] * L[0]
        x1 = vxy[tv[t, 1], 0] + to[t, 1, 0] * L[0]
        x2 = vxy[tv[t, 2], 0] + to[t, 2, 0] * L[0]
        y0 = vxy[tv[t, 0], 1] + to[t, 0, 1] * L[1]
        y1 = vxy[tv[t, 1], 1] + to[t, 1, 1] * L[1]
        y2 = vxy[tv[t, 2], 1] + to[t, 2, 1] * L[1]
        xlo, xhi = min(x0, x1, x2), max(x0, x1, x2)
        ylo, yhi = min(y0, y1, y2), max(y0, y1, y2)
        e2 = max(
            (x1 - x0) ** 2 + (y1 - y0) ** 2,
            (x2 - x1) ** 2 + (y2 - y1) ** 2,
            (x0 - x2) ** 2 + (y0 - y2) ** 2,
        )
        for sx in range(sx_lo, sx_hi + 1):
            for sy in range(sy_lo, sy_hi + 1):
                ok = True
                if nonper[0] and (xhi + sx * L[0] < blo[0] or xlo + sx * L[0] > bhi[0]):
                    ok = False
                if nonper[1] and (yhi + sy * L[1] < blo[1] or ylo + sy * L[1] > bhi[1]):
                    ok = False
                if ok:
                    keep[t, (sx + 1) * 3 + sy + 1] = True
                    nkeep += 1
                    rstar2 = max(rstar2, e2)
    # pass 2: vertex copies needed; a copy's shift per axis is in [-1, 2] (code 0..3)
    need = np.zeros((m, 16), np.bool_)
    for v in range(m):
        for sx in range(sx_lo, sx_hi + 1):
            for sy in range(sy_lo, sy_hi + 1):
                gap2 = 0.0
                for a in range(2):
                    if nonper[a]:
                        p = vxy[v, a] + (sx if a == 0 else sy) * L[a]
                        g = max(blo[a] - p, 0.0, p - bhi[a])
                        gap2 += g * g
                if gap2 <= rstar2:
                    need[v, (sx + 1) * 4 + sy + 1] = True
    for t in range(nt):
        for c in range(9):
            if keep[t, c]:
                sx = c // 3 - 1
                sy = c % 3 - 1
                for i in range(3):
                    vx = (to[t, i, 0] + sx) if nonper[0] else 0
                    vy = (to[t, i, 1] + sy) if nonper[1] else 0
                    need[tv[t, i], (vx + 1) * 4 + vy + 1] = True
    # number the copies in (vertex, shift) order
    index = np.full((m, 16), -1, np.int64)
    nout = 0
    for v in range(m):
        for c in range(16):
            if need[v, c]:
                index[v, c] = nout
                nout += 1
    out_v = np.empty(nout, np.int64)
    out_s = np.empty((nout, 2), np.int64)
    for v in range(m):
        for c in range(16):
            if need[v, c]:
                j = index[v, c]
                out_v[j] = v
                out_s[j, 0] = c // 4 - 1
                out_s[j, 1] = c % 4 - 1
    tri = np.empty((nkeep, 3), np.int64)
    off = np.zeros((nkeep, 3, 2), np.int8)
    n = 0
    for t in range(nt):
        for c in range(9):
            if keep[t, c]:
                sx = c // 3 - 1
                sy = c % 3 - 1
                for i in range(3):
                    vx = (to[t, i, 0] + sx) if nonper[0] else 0
                    vy = (to[t, i, 1] + sy) if nonper[1] else 0
                    tri[n, i] = index[tv[t, i], (vx + 1) * 4 + vy + 1]
                    for a in range(2):
                        if not nonper[a]:
                            off[n, i, a] = to[t, i, a]
                n += 1
    return out_v, out_s, tri, off
