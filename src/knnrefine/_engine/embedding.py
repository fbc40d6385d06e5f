"""From the user's box to the engine's torus, and back.

The engine always refines a flat torus [0, lx) x [0, ly) (x [0, lz) in space) in internal
units. Along a periodic
axis the torus period is the box's side. Along a non-periodic axis the box is embedded in a
longer period, with a margin on both sides, long enough that no periodic copy of a point can be
among the k nearest of any point of the box:

    for x, p in the box, |x - (p + L e)| >= L - w > 1.05 r >= d_{P,k}(x)        (n >= k)

where w is the box's side along that axis and r a bound on d_{P,k} over the box: by default the
box's diameter D in its own metric (half the side along periodic axes, the full side along the
others), or a bound computed from the data (``initial.reach_bound``). Then on the box the
periodic k-th-neighbour distance *is* the planar one, the torus refinement's guarantee holds
verbatim for the planar d_{P,k}, and nothing is approximated. The margin holds no data, so the
mesh there coarsens quickly and costs few vertices.

Internal units: x_int = (x - origin) * scale with scale a power of two, so that the longest
period is in (1/2, 1]. Vertices live on a grid of step q (a power of two, at least 2^-50): q is
chosen so that its step in input units, g = q / scale, is no finer than the spacing of doubles
at the largest coordinate the user will receive, and the origin and the periods are multiples
of g. Every vertex then maps to input coordinates *exactly* (origin + u / scale is a multiple
of g within the range where doubles are g apart): what the user gets is the mesh the engine
certified, with no rounding and no two vertices on one row.
"""

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .geometry import FLOOR_BITS, Q
from .jit import kernel
from .threads import in_chunks

MARGIN = 1.05


@kernel(inline="always")
def wrap_offset(x, lo, period):
    """x - lo reduced into [0, period). fmod is exact, so the result is within an ulp of the
    period of the true residue however large |x| is (x - lo itself would round at the scale of
    x: 80 units off at |x| = 1e17 with a period of 360)."""
    r = np.fmod(x, period) - np.fmod(lo, period)
    while r < 0.0:
        r += period
    while r >= period:  # also when r + period rounded up to period
        r -= period
    return r


@kernel(entry=True)
def wrap_offsets(x, lo, period):
    """``wrap_offset`` over an array: x - lo reduced into [0, period), elementwise."""
    out = np.empty(x.shape[0])
    for i in range(x.shape[0]):
        out[i] = wrap_offset(x[i], lo, period)
    return out


def wrap(x, period):
    """Points (n, d) reduced into [0, period) on every axis."""
    d = len(period)
    x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, d)
    return np.stack([wrap_offsets(x[:, a].copy(), 0.0, float(period[a])) for a in range(d)], 1)


def diameter(box, periodic):
    """The box's diameter in its own metric: half the side along periodic axes."""
    d = len(box) // 2
    size = np.array(box[d:], float) - np.array(box[:d], float)
    return float(np.sqrt((np.where(np.array(periodic, bool), size / 2.0, size) ** 2).sum()))


@dataclass(frozen=True)
class Embedding:
    box: tuple  # (xmin, ymin, xmax, ymax) or (x0, y0, z0, x1, y1, z1), input units
    periodic: tuple  # one bool per axis
    origin: np.ndarray  # input coordinates of the internal origin, multiples of grid / scale
    scale: float  # internal = (input - origin) * scale
    period_internal: tuple  # (lx, ly) or (lx, ly, lz), multiples of grid
    grid: float  # q: the internal grid step, a power of two >= 2^-50

    @classmethod
    def make(cls, box, periodic, reach=None):
        """The torus for ``box``: along non-periodic axes the side plus a margin of 1.05 x
        ``reach``, which must bound d_{P,k} over the box (default: the box's diameter D)."""
        d = len(box) // 2
        lo = np.array(box[:d], float)
        size = np.array(box[d:], float) - lo
        per = np.array(periodic, bool)
        diam = diameter(box, periodic) if reach is None else float(reach)
        period = np.where(per, size, size + MARGIN * diam)
        origin = np.where(per, lo, lo - (period - size) / 2.0)
        scale = 2.0 ** -int(np.ceil(np.log2(period.max())))
        # the user receives coordinates in [origin - L, origin + 3 L) (copies of vertices
        # across non-periodic axes are shifted by -1 .. 2 periods)
        biggest = float(np.max(np.maximum(np.abs(origin - period), np.abs(origin + 3 * period))))
        g = max(Q / scale, float(np.spacing(biggest)))
        q = g * scale
        origin = np.rint(origin / g) * g
        lint = tuple(float(np.rint(p * scale / q) * q) for p in period)
        return cls(
            tuple(float(b) for b in box), tuple(bool(p) for p in per), origin, scale, lint, q
        )

    @classmethod
    def of_torus(cls, box, periodic, origin, period):
        """The embedding whose torus has this origin and period (input units): the one
        ``make`` made for a mesh (its scale and grid follow from the period as there);
        InputError when they do not make one (a file's torus edited by hand)."""
        period = np.array(period, float)
        scale = 2.0 ** -int(np.ceil(np.log2(period.max())))
        origin = np.array(origin, float)
        biggest = float(np.max(np.maximum(np.abs(origin - period), np.abs(origin + 3 * period))))
        g = max(Q / scale, float(np.spacing(biggest)))
        q = g * scale
        lint = tuple(float(p * scale) for p in period)
        off_grid = any(np.rint(x / q) * q != x for x in lint)
        if off_grid or np.any(np.rint(origin / g) * g != origin):
            raise InputError(
                "the mesh's torus is not one refine makes (its origin and period are off the "
                "engine's grid): refine its points afresh"
            )
        return cls(tuple(float(b) for b in box), tuple(bool(p) for p in periodic), origin,
                   scale, lint, q)  # fmt: skip

    @property
    def period(self):
        """Torus periods in input units."""
        return tuple(p / self.scale for p in self.period_internal)

    @property
    def resolution(self):
        """The engine's resolution floor in input units: 2^14 grid steps."""
        return self.grid * 2.0**FLOOR_BITS / self.scale

    @property
    def dim(self):
        return len(self.periodic)

    def to_internal(self, x):
        """Internal coordinates of input points (n, d), wrapped into the torus (a new array)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        return _to_internal(
            x,
            self.origin,
            self.scale,
            np.array(self.period_internal),
            np.array(self.periodic),
            True,
        )

    def to_input(self, u, copy=True):
        """Input coordinates of internal points on the grid: exact (see the module docstring).
        Along periodic axes they are wrapped into [box low, box low + period). copy=False
        converts a float64 array of the caller's in place."""
        x = np.array(u, float) if copy else u
        x /= self.scale
        x += self.origin
        for a in range(self.dim):
            if self.periodic[a]:
                lo, period = self.box[a], self.period[a]
                x[:, a] = np.where(x[:, a] < lo, x[:, a] + period, x[:, a])
                x[:, a] = np.where(x[:, a] >= lo + period, x[:, a] - period, x[:, a])
        return x

    def to_query(self, x):
        """Internal coordinates of any points (n, d) for distance queries: wrapped into the
        torus along periodic axes, unwrapped (planar, possibly outside [0, L)) along the
        others, where the index answers in the plane (``index.PointIndex``)."""
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, self.dim)
        return _to_internal(
            x,
            self.origin,
            self.scale,
            np.array(self.period_internal),
            np.array(self.periodic),
            False,
        )

    def box_internal(self):
        d = self.dim
        lo = (np.array(self.box[:d]) - self.origin) * self.scale
        hi = (np.array(self.box[d:]) - self.origin) * self.scale
        return lo, hi


@kernel(entry=True)
def _to_internal(x, origin, scale, period, periodic, into_torus):
    """(x - origin) * scale, wrapped into [0, period) along periodic axes; along the others
    too when ``into_torus`` (data, which the margin keeps inside: only rounding at the seam
    is guarded), else left planar (queries)."""
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        for a in range(x.shape[1]):
            if periodic[a]:
                u = wrap_offset(x[i, a], origin[a], period[a] / scale) * scale
            else:
                u = (x[i, a] - origin[a]) * scale
            if u >= period[a] and (periodic[a] or into_torus):  # rounding at the seam
                u = 0.0
            out[i, a] = u
    return out


UNFOLD_RANGE = 8192  # cells or vertices at least per thread's range (fewer: one thread)


def unfold(points, cells, offsets, emb, copy=True):
    """The part of the torus mesh that the box needs, as the user will see it: triangles
    (points (m, 2)) or tetrahedra (points (m, 3)).

    Along periodic axes nothing changes: vertices stay in the fundamental domain and cells
    keep their corner offsets. Along non-periodic axes vertices become planar copies: the
    cells kept are the copies (shifted by -1, 0 or 1 period) that meet the box, and the
    vertices kept are the copies within r* of the box, r* being the longest edge of a kept
    cell. That is every vertex that can be one of the two nearest to a point x of the box: x
    lies in a kept cell, whose corners are within its longest edge of x. Vertex copies are
    numbered in (vertex, shift) order.

    A cell's copies are a 3^d-bit mask (shift -1..1 per non-periodic axis), a vertex's a
    4^d-bit one (shift -1..2); a copy's output index is its vertex's first index plus the
    copies before it in the mask: 4 bytes per cell and 16 per vertex of working memory, not a
    word per copy. The passes over cells and over vertices run in ranges on the engine's
    threads (``threads.in_chunks``); marking the corners of the kept cells, whose vertices
    several cells share, and numbering the copies run on one.

    Returns (vertex ids (m',) int64, positions (m', d) internal, cells (t', d + 1) int32 into
    the returned vertices, offsets (t', d + 1, d) int8 or None when no axis is periodic), new
    arrays; when every axis is periodic and ``copy`` is False, the arrays given.
    """
    per = emb.periodic
    if all(per):
        if not copy:
            return np.arange(len(points)), points, cells, offsets
        return np.arange(len(points)), points.copy(), cells.copy(), offsets.copy()
    blo, bhi = emb.box_internal()
    L = np.array(emb.period_internal)
    free = np.array([not p for p in per])
    m, d = points.shape
    nt, nc = cells.shape
    keep = np.zeros(nt, np.uint32)
    least = UNFOLD_RANGE
    rstar2 = max(in_chunks(lambda a, b: _keep_cells(points, cells, offsets, L, blo, bhi, free,
                                                   keep, a, b), nt, least=least),
                 default=0.0)  # fmt: skip
    need = np.zeros(m, np.uint64)
    in_chunks(lambda a, b: _need_vertices(points, L, blo, bhi, free, rstar2, need, a, b), m,
              least=least)  # fmt: skip
    first = np.empty(m + 1, np.int64)
    start = np.empty(nt + 1, np.int64)
    _number_copies(cells, offsets, free, keep, need, first, start)
    out_v = np.empty(first[m], np.int64)
    pos = np.empty((first[m], d))
    in_chunks(lambda a, b: _vertex_copies(points, L, need, first, out_v, pos, a, b), m,
              least=least)  # fmt: skip
    kept = np.empty((start[nt], nc), np.int32)
    off = np.zeros((start[nt], nc, d), np.int8)
    in_chunks(lambda a, b: _cell_copies(cells, offsets, free, keep, need, first, start, kept,
                                        off, a, b), nt, least=least)  # fmt: skip
    return out_v, pos, kept, (off if any(per) else None)


@kernel(inline="always")
def _popcount64(x):
    """Set bits of a uint64 (bits summed in pairs, nibbles, then bytes)."""
    x = np.uint64(x)
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return np.int64((x * np.uint64(0x0101010101010101)) >> np.uint64(56))


@kernel(inline="always")
def _digits(code, base, d, out):
    """out[:d] = the digits of ``code`` in ``base``, most significant first, minus 1: a
    copy's shift per axis (base 3: -1..1 for a cell, base 4: -1..2 for a vertex)."""
    for a in range(d - 1, -1, -1):
        out[a] = code % base - 1
        code //= base


@kernel(inline="always")
def _vertex_bit(shift, d):
    """A vertex copy's bit in its uint64 mask: its shift per axis in -1..2, two bits each."""
    code = 0
    for a in range(d):
        code = code * 4 + shift[a] + 1
    return np.uint64(1) << np.uint64(code)


@kernel(inline="always")
def _corner_shift(offsets, t, i, s, free, out):
    """out = the shift per axis of corner i in the copy of cell t shifted by s (its offset
    plus s along non-periodic axes; 0 along periodic ones, where offsets stay offsets)."""
    for a in range(out.shape[0]):
        out[a] = (offsets[t, i, a] + s[a]) if free[a] else 0


@kernel(entry=True, nogil=True)
def _keep_cells(points, cells, offsets, L, blo, bhi, free, keep, t0, t1):
    """keep[t] = the mask of cell t's copies that meet the box, for t in [t0, t1); returns
    the squared longest edge of the kept cells there. Per axis, the shifts whose copy meets
    the box's slab; a copy meets the box when each of its shifts does (most cells: shift 0
    only, one bit)."""
    d = points.shape[1]
    nc = cells.shape[1]
    rstar2 = 0.0
    c = np.empty((nc, d))
    ok = np.empty(d, np.int64)  # per axis: bit s + 1 set when shift s meets the slab
    s = np.zeros(d, np.int64)
    centre = (3**d - 1) // 2  # the code of shift 0 on every axis (digits 1...1 in base 3)
    for t in range(t0, t1):
        for i in range(nc):
            for a in range(d):
                c[i, a] = points[cells[t, i], a] + offsets[t, i, a] * L[a]
        only_centre = True
        none = False
        for a in range(d):
            if not free[a]:
                ok[a] = 2
                continue
            lo = c[0, a]
            hi = c[0, a]
            for i in range(1, nc):
                lo = min(lo, c[i, a])
                hi = max(hi, c[i, a])
            bits = 0
            for sh in range(-1, 2):
                if hi + sh * L[a] >= blo[a] and lo + sh * L[a] <= bhi[a]:
                    bits |= 1 << (sh + 1)
            ok[a] = bits
            if bits == 0:
                none = True
            elif bits != 2:
                only_centre = False
        if none:
            continue
        if only_centre:
            mask = 1 << centre
        else:
            mask = 0
            for code in range(3**d):
                _digits(code, 3, d, s)
                meets = True
                for a in range(d):
                    if not ok[a] & (1 << (s[a] + 1)):
                        meets = False
                if meets:
                    mask |= 1 << code
        keep[t] = mask
        for i in range(nc):
            for j in range(i + 1, nc):
                e2 = 0.0
                for a in range(d):
                    e2 += (c[i, a] - c[j, a]) ** 2
                rstar2 = max(rstar2, e2)
    return rstar2


@kernel(entry=True, nogil=True)
def _need_vertices(points, L, blo, bhi, free, rstar2, need, v0, v1):
    """need[v] |= the bits of vertex v's copies within sqrt(rstar2) of the box, for v in
    [v0, v1) (shift -1..2 along non-periodic axes; the gap to the box summed over axes)."""
    d = points.shape[1]
    g2 = np.zeros((d, 4))  # per axis and shift: the squared gap to the box's slab
    s = np.zeros(d, np.int64)
    for v in range(v0, v1):
        only_centre = True
        for a in range(d):
            for j in range(4):
                if free[a]:
                    p = points[v, a] + (j - 1) * L[a]
                    g = max(blo[a] - p, 0.0, p - bhi[a])
                    g2[a, j] = g * g
                else:
                    g2[a, j] = 0.0 if j == 1 else np.inf
                if j != 1 and g2[a, j] <= rstar2:
                    only_centre = False
        if only_centre:
            gap2 = 0.0
            for a in range(d):
                gap2 += g2[a, 1]
            if gap2 <= rstar2:
                for a in range(d):
                    s[a] = 0
                need[v] |= _vertex_bit(s, d)
            continue
        for code in range(4**d):
            _digits(code, 4, d, s)
            gap2 = 0.0
            for a in range(d):
                gap2 += g2[a, s[a] + 1]
            if gap2 <= rstar2:
                need[v] |= _vertex_bit(s, d)


@kernel(entry=True)
def _number_copies(cells, offsets, free, keep, need, first, start):
    """Mark each kept cell copy's corners in ``need`` (one thread: cells share vertices),
    then number the copies: vertex v's first copy is first[v], cell t's first start[t]."""
    nt, nc = cells.shape
    m = need.shape[0]
    d = offsets.shape[2]
    s = np.zeros(d, np.int64)
    vs = np.zeros(d, np.int64)
    start[0] = 0
    for t in range(nt):
        mask = keep[t]
        start[t + 1] = start[t] + _popcount64(np.uint64(mask))
        if mask == 0:
            continue
        for code in range(3**d):
            if mask & (1 << code):
                _digits(code, 3, d, s)
                for i in range(nc):
                    _corner_shift(offsets, t, i, s, free, vs)
                    need[cells[t, i]] |= _vertex_bit(vs, d)
    first[0] = 0
    for v in range(m):
        first[v + 1] = first[v] + _popcount64(need[v])


@kernel(entry=True, nogil=True)
def _vertex_copies(points, L, need, first, out_v, pos, v0, v1):
    """The vertex copies of vertices [v0, v1): their vertex and position (internal units,
    shifted by whole periods)."""
    d = points.shape[1]
    s = np.zeros(d, np.int64)
    for v in range(v0, v1):
        j = first[v]
        for code in range(4**d):
            if need[v] & (np.uint64(1) << np.uint64(code)):
                out_v[j] = v
                _digits(code, 4, d, s)
                for a in range(d):
                    pos[j, a] = points[v, a] + s[a] * L[a]
                j += 1


@kernel(entry=True, nogil=True)
def _cell_copies(cells, offsets, free, keep, need, first, start, kept, off, t0, t1):
    """The cell copies of cells [t0, t1): corners into the vertex copies, and the offsets
    along periodic axes."""
    nc = cells.shape[1]
    d = offsets.shape[2]
    s = np.zeros(d, np.int64)
    vs = np.zeros(d, np.int64)
    for t in range(t0, t1):
        mask = keep[t]
        if mask == 0:
            continue
        n = start[t]
        for code in range(3**d):
            if mask & (1 << code):
                _digits(code, 3, d, s)
                for i in range(nc):
                    _corner_shift(offsets, t, i, s, free, vs)
                    for a in range(d):
                        if not free[a]:
                            off[n, i, a] = offsets[t, i, a]
                    v = cells[t, i]
                    bit = _vertex_bit(vs, d)
                    kept[n, i] = first[v] + _popcount64(need[v] & (bit - np.uint64(1)))
                n += 1
