"""The initial mesh M0 and Theorem 6's precondition on it.

Lemma 2 of the paper proves the lower bound by induction over the insertion order: every
vertex v must satisfy

    d_{P,k}(v) <= (K - 1) lambda_v,        lambda_v = distance to the nearest earlier vertex,

with K = 2 tau / (tau - 2). Break and Clean insertions keep it (for a far-corner Break only if
K >= 3, hence ``reach_factor``); the initial vertices must satisfy it to begin with. The
order *among* the initial vertices is ours to choose: the first has no predecessor at all.
``precondition_order`` finds an order that works whenever one exists, by peeling: a vertex
that passes with lambda = its distance to the nearest other remaining vertex can go last
(every order of the rest leaves it that far from its predecessors); remove those, repeat on
the rest. If at some round nobody passes, nobody can be last among those vertices in any
order, so no order exists.

M0 itself is a tensor grid of the torus. Every circumradius must stay below a quarter of the
shorter period (the triangulation must be a simplicial complex, and cavities must not wrap
around; see ``triangulation.py``), so M0 cannot be arbitrarily coarse: with k close to n on a
small torus, d_{P,k} at the initial vertices can exceed what any valid M0 allows, and
``refine`` then refuses the input (``choose_initial_mesh`` returns None).
"""

import numpy as np
from scipy.spatial import cKDTree

from .geometry import Q
from .index import holds_k_within

# (vertices per shorter period, jitter amplitude, phase of the grid in cells): the first is
# the default M0 (fast: its jitter keeps the exact in-circle fallback rare); the coarser grid
# allows spacing a third of the shorter period with a jitter small enough to keep every
# circumradius below a quarter of it; the shifted copies place the vertices differently
# relative to the data
GRIDS = ((4, 0.3, 0.0), (3, 0.1, 0.0), (3, 0.1, 0.5), (4, 0.3, 0.5))


def reach_factor(tau):
    """K - 1 of Lemma 2 with K = max(2 tau / (tau - 2), 3): the induction needs
    K >= 2 tau / (tau - 2) for Clean and K >= 3 for a Break at a cell's far corner (the new
    vertex is R(v) from its nearest vertex and within 2 R(v) of the cell's k points)."""
    return max(2.0 * tau / (tau - 2.0), 3.0) - 1.0


def grid_shape(lx, ly, per_period=4):
    """Columns and rows of the grid: ``per_period`` along the shorter period (at least 3),
    the same spacing or less along the other."""
    h = min(lx, ly) / per_period
    return (
        max(per_period, int(np.ceil(lx / h - 1e-9))),
        max(per_period, int(np.ceil(ly / h - 1e-9))),
    )


def _jittered_positions(n, length, phase, jitter, shift, q):
    """n positions around a circle of the given length, gaps (1 +- jitter / 2) * length / n in
    a fixed low-discrepancy pattern, moved by ``shift`` mean gaps, snapped to the grid q."""
    gaps = 1.0 + jitter * (((np.arange(n) + phase) * 0.6180339887498949) % 1.0 - 0.5)
    edges = np.concatenate([[0.0], np.cumsum(gaps)]) * (length / gaps.sum())
    x = np.sort(np.mod(0.5 * (edges[:-1] + edges[1:]) + shift * length / n, length))
    x = np.rint(x / q) * q
    return np.where(x >= length, 0.0, x)


def initial_grid(lx, ly, per_period=4, jitter=0.3, shift=0.0, q=Q):
    """M0: a tensor grid on the torus [0, lx) x [0, ly), one diagonal per cell.

    Its cells are axis-aligned rectangles, so the four corners of each are exactly cocircular
    and the triangulation is exactly Delaunay even after snapping to the grid. Column widths
    and row heights vary by up to jitter / 2: with a perfectly regular grid the circumcenters
    of its right triangles are the cell centres, which form a finer square lattice, and so on
    at every level, so uniform regions would stay exactly cocircular and every in-circle test
    would need the slow exact fallback.

    Returns (vxy, tv, to, tn, lam) with lam each vertex's distance to its nearest neighbour
    (an axis neighbour: the cells are rectangles), or None when a circumradius would reach a
    quarter of the shorter period (too coarse to be a valid torus triangulation)."""
    nx, ny = grid_shape(lx, ly, per_period)
    gx = _jittered_positions(nx, lx, 0.0, jitter, shift, q)
    gy = _jittered_positions(ny, ly, 0.5, jitter, shift, q)
    wx = np.diff(np.append(gx, gx[0] + lx))
    wy = np.diff(np.append(gy, gy[0] + ly))
    if np.hypot(wx.max(), wy.max()) / 2.0 >= min(lx, ly) / 4.0 * (1.0 - 1e-9):
        return None
    vxy = np.stack(np.meshgrid(gx, gy, indexing="xy"), axis=-1).reshape(-1, 2)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="xy")
    i = i.ravel()
    j = j.ravel()
    i1 = (i + 1) % nx
    j1 = (j + 1) % ny
    ox = (i + 1 == nx).astype(np.int8)
    oy = (j + 1 == ny).astype(np.int8)
    v00 = j * nx + i
    v10 = j * nx + i1
    v01 = j1 * nx + i
    v11 = j1 * nx + i1
    zero = np.zeros_like(ox)
    # cell c = j * nx + i holds the lower triangle c = (v00, v10, v11) and the upper triangle
    # nc + c = (v00, v11, v01); neighbour i lies across the edge opposite corner i
    tv = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
    to = np.concatenate(
        [
            np.stack(
                [np.stack([zero, zero], 1), np.stack([ox, zero], 1), np.stack([ox, oy], 1)], 1
            ),
            np.stack(
                [np.stack([zero, zero], 1), np.stack([ox, oy], 1), np.stack([zero, oy], 1)], 1
            ),
        ]
    ).astype(np.int8)
    nc = nx * ny
    cell = j * nx + i
    right = j * nx + i1
    left = j * nx + (i - 1) % nx
    up = j1 * nx + i
    down = ((j - 1) % ny) * nx + i
    tn = np.concatenate(
        [
            np.stack([nc + right, nc + cell, nc + down], 1),  # right edge, diagonal, bottom
            np.stack([up, left, cell], 1),  # top edge, left edge, diagonal
        ]
    )
    lam_x = np.minimum(wx, np.roll(wx, 1))  # gaps on either side of each column
    lam_y = np.minimum(wy, np.roll(wy, 1))
    lam = np.minimum(lam_x[None, :], lam_y[:, None]).ravel()
    return vxy, tv.astype(np.int32), to, tn.astype(np.int32), lam


def precondition_order(vxy, lam, index, k, factor, lx, ly, check=None):
    """An order of the initial vertices in which each u satisfies d_{P,k}(u) <= factor *
    lambda_u (the distance to its nearest predecessor on the torus), by peeling (see the
    module docstring); ``lam`` holds each vertex's distance to its nearest other vertex.
    ``check()`` runs before each peeling round (deadline, Ctrl-C: a long box peels for
    seconds). Returns (order, rounds) or (None, failing) with the vertices no order can
    place."""

    def passes(xy, lam):
        if check is not None:
            check()
        # conservative: the reach is shortened by a relative 1e-9 against rounding
        return holds_k_within(index, xy, (factor * lam * (1.0 - 1e-9)) ** 2, k, lx, ly)

    return peel_order(vxy, lam, np.array([lx, ly]), passes)


def peel_order(x, lam, period, passes):
    """``precondition_order`` in any dimension: ``passes(x, lam)`` says which of the vertices
    x pass with lam their distances to the nearest other remaining vertex."""
    remaining = np.arange(len(x))
    peeled = []
    while len(remaining) > 1:
        xy = x[remaining]
        if peeled:
            lam = cKDTree(xy, boxsize=period).query(xy, k=2)[0][:, 1]
        ok = passes(xy, lam)
        if not ok.any():
            return None, remaining
        peeled.append(remaining[ok])
        remaining = remaining[~ok]
    return np.concatenate([remaining] + peeled[::-1]), len(peeled)


def candidate_grids(lx, ly, max_vertices, q=Q):
    """The initial meshes worth trying on this torus, in order: [(grid, m0), ...] for the
    ``GRIDS`` that are valid and fit in max_vertices (built lazily by the caller's loop)."""
    for grid in GRIDS:
        nx, ny = grid_shape(lx, ly, grid[0])
        if nx * ny > max_vertices:
            continue
        m0 = initial_grid(lx, ly, *grid, q=q)
        if m0 is not None:
            yield grid, m0


def choose_initial_mesh(candidates, index, k, factor, lx, ly, check=None):
    """The first of ``candidates`` [(grid, m0), ...] whose vertices can be ordered so that
    d_{P,k}(u) <= factor * lambda_u (Lemma 2's precondition with factor = K - 1, see
    ``reach_factor``). ``check()`` runs between candidates and peeling rounds (deadline,
    Ctrl-C). Returns (m0, order, grid) with m0 = (vxy, tv, to, tn), or None."""
    for grid, m0 in candidates:
        order, _ = precondition_order(m0[0], m0[4], index, k, factor, lx, ly, check)
        if order is not None:
            return m0[:4], order, grid
        if check is not None:
            check()
    return None


def tau_for_factor(factor):
    """The tau whose Lemma 2 factor K - 1 is ``factor`` (> 2): factor + 1 = 2 tau / (tau - 2)."""
    return 2.0 * (factor + 1.0) / (factor - 1.0)


def largest_passing(ok, k, factor):
    """For an input refused at (k, factor), with ``ok(k, factor)`` the acceptance test: (the
    largest k' < k accepted at this factor, 0 if none; the least factor accepted for this k,
    to a relative 1e-4, or None beyond 1e9). Both are monotone: a larger k or a smaller factor
    only makes the precondition harder."""
    lo, hi = 0, k
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if ok(mid, factor):
            lo = mid
        else:
            hi = mid
    f_lo, f_hi = factor, factor * 2.0
    while not ok(k, f_hi):
        f_lo, f_hi = f_hi, f_hi * 2.0
        if f_hi > 1e9:
            return lo, None
    while f_hi - f_lo > 1e-4 * f_hi:
        mid = 0.5 * (f_lo + f_hi)
        if ok(k, mid):
            f_hi = mid
        else:
            f_lo = mid
    return lo, f_hi


def reach_bound(index, lo, hi, k, lx, ly, cells=32):
    """An upper bound on max d_{P,k} over the box [lo, hi] (internal units; d_{P,k} in the
    torus metric, which is the box's own where the torus is the default embedding): the
    smallest r, to a relative 2^-30, at which every centre of a cells x cells grid holds k
    points within r, plus the cells' half-diagonal (d_{P,k} is 1-Lipschitz)."""
    gx = lo[0] + (np.arange(cells) + 0.5) / cells * (hi[0] - lo[0])
    gy = lo[1] + (np.arange(cells) + 0.5) / cells * (hi[1] - lo[1])
    centres = np.stack(np.meshgrid(gx, gy), -1).reshape(-1, 2)
    r_lo, r_hi = 0.0, float(np.hypot(lx, ly))  # every point is within the torus' diameter
    for _ in range(30):
        mid = 0.5 * (r_lo + r_hi)
        if holds_k_within(index, centres, np.full(len(centres), mid * mid), k, lx, ly).all():
            r_hi = mid
        else:
            r_lo = mid
    return r_hi + 0.5 * float(np.hypot(hi[0] - lo[0], hi[1] - lo[1])) / cells


# the Kuhn subdivision of a box into six tetrahedra round its diagonal from corner 000 to
# 111: one per order of the axes, each from 000 along the first axis, then the second, to 111
_KUHN = np.array(
    [
        [(0, 0, 0), tuple(int(a == p[0]) for a in range(3)),
         tuple(int(a in p[:2]) for a in range(3)), (1, 1, 1)]
        for p in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))
    ]
)  # fmt: skip
# positively oriented (orient3d > 0, det[a - d, b - d, c - d]): swap the first two corners of
# those that are not
_KUHN[np.linalg.det(_KUHN[:, :3] - _KUHN[:, 3:]) < 0] = _KUHN[
    np.linalg.det(_KUHN[:, :3] - _KUHN[:, 3:]) < 0
][:, [1, 0, 2, 3]]


GRIDS3 = ((4, 0.2, 0.0), (4, 0.2, 0.5), (3, 0.05, 0.0), (3, 0.05, 0.5))  # the candidate M0s
# in space, finest first: (grid points along the shortest period, jitter, shift)


def grid_shape3(period, per_period):
    """Grid points along each axis of the 3-torus of ``period`` for ``initial_grid3``:
    ``per_period`` along the shortest, as many of that spacing along the others."""
    period = np.asarray(period, float)
    h = period.min() / per_period
    return np.maximum(per_period, np.ceil(period / h - 1e-9).astype(np.int64))


def initial_grid3(period, per_period=4, jitter=0.2, shift=0.0, q=Q, check=None):
    """M0 in three dimensions: a tensor grid on the 3-torus of periods ``period``, each box
    cut into the six tetrahedra of its Kuhn subdivision (round the diagonal from its lowest
    to its highest corner; neighbouring boxes cut their shared face the same way).

    A box's eight corners lie on one sphere, every other grid point strictly outside it, so
    the subdivision is Delaunay exactly, also after snapping to the grid q. Widths vary by up
    to jitter / 2 per axis (as ``initial_grid``: a regular grid would keep uniform regions
    exactly cospherical at every level). Returns (xyz, corners, offsets, neighbours, lam),
    lam each vertex's distance to its nearest neighbour (an axis neighbour), or None when a
    circumradius would reach a quarter of the shortest period. ``check()`` runs between its
    steps (a large grid takes seconds: deadline, Ctrl-C)."""
    check = check or (lambda: None)
    period = np.asarray(period, float)
    n = grid_shape3(period, per_period)
    g = [
        _jittered_positions(n[a], period[a], (0.0, 0.5, 0.25)[a], jitter, shift, q)
        for a in range(3)
    ]
    w = [np.diff(np.append(g[a], g[a][0] + period[a])) for a in range(3)]
    if np.sqrt(sum(wa.max() ** 2 for wa in w)) / 2.0 >= period.min() / 4.0 * (1.0 - 1e-9):
        return None
    idx = np.stack(
        np.meshgrid(*[np.arange(na, dtype=np.int32) for na in n], indexing="ij"), -1
    ).reshape(-1, 3)
    xyz = np.stack([g[a][idx[:, a]] for a in range(3)], 1)

    # cell (i, j, k) has its lowest corner at grid point (i, j, k); its six tetrahedra are
    # rows 6 c .. 6 c + 5, built corner by corner (no (cells, 6, 4, 3) temporary)
    cells = len(idx)
    corners = np.empty((cells, 6, 4), np.int32)
    offsets = np.empty((cells, 6, 4, 3), np.int8)
    nn = n.astype(np.int32)
    for t in range(6):
        for i in range(4):
            raw = idx + _KUHN[t, i].astype(np.int32)
            wraps = raw >= nn
            offsets[:, t, i] = wraps
            raw -= wraps * nn
            corners[:, t, i] = (raw[:, 0] * nn[1] + raw[:, 1]) * nn[2] + raw[:, 2]
        check()
    corners = corners.reshape(-1, 4)
    offsets = offsets.reshape(-1, 4, 3)
    check()
    neighbours = face_neighbours(corners, offsets, check)
    lam = np.min(
        np.stack([np.minimum(w[a], np.roll(w[a], 1))[idx[:, a]] for a in range(3)], 1), axis=1
    )
    return xyz, corners, offsets, neighbours, lam


def face_neighbours(corners, offsets, check=None):
    """neighbours (t, 4): the tetrahedron across the face opposite each corner, matched by
    the face's three vertices and their offsets relative to each other (the same from either
    side); ValueError unless every face is shared by exactly two tetrahedra. Each corner of
    a face is one integer (its vertex, then its offset past the face's least, 2 bits per
    axis); the face's three, sorted, are its key, matched by one stable sort: linear in
    memory."""
    t = len(corners)
    m = int(corners.max(initial=0)) + 1
    first, second = [], []
    for i in range(4):
        other = [j for j in range(4) if j != i]
        o = offsets[:, other].astype(np.int64)
        o -= o.min(axis=1, keepdims=True)
        if o.max(initial=0) >= 4:
            raise ValueError("a tetrahedron spans more than three periods")
        c = np.sort(corners[:, other].astype(np.int64) * 64 + o @ np.array([16, 4, 1]), axis=1)
        first.append(c[:, 0] * (64 * m) + c[:, 1])
        second.append(c[:, 2])
        if check is not None:
            check()
    first, second = np.concatenate(first), np.concatenate(second)  # row f = i * t + tet
    order = np.lexsort((second, first))  # stable: a face's two rows in the order of f
    a, b = order[0::2], order[1::2]
    paired = (first[a] == first[b]) & (second[a] == second[b])
    apart = (first[b[:-1]] != first[a[1:]]) | (second[b[:-1]] != second[a[1:]])
    if len(order) % 2 or not (paired.all() and apart.all()):
        raise ValueError("a face is not shared by exactly two tetrahedra")
    out = np.empty(4 * t, np.int64)
    out[a] = b % t
    out[b] = a % t
    return out.reshape(4, t).T.astype(np.int32)


def refusal_message(n, k, tau, emb, k_max, f_min):
    """Why no initial mesh of the torus ``emb`` (plane or space) can start a run of n points
    at (k, tau), and what would: the largest k certifiable at this tau (``k_max``), the
    largest tau for this k (from the least factor ``f_min``), a longer periodic side (None
    where the search was not made)."""
    dim = len(emb.periodic)
    mode = {(True,) * dim: "periodic", (False,) * dim: "ordinary"}.get(
        tuple(emb.periodic), f"periodic={tuple(emb.periodic)}"
    )
    options = []
    if k_max is not None and k_max >= 1:
        options.append(f"use k <= {k_max} (the largest k certifiable here at tau = {tau:g})")
    if f_min is not None and tau_for_factor(f_min) >= 2.01:
        tau_max = np.floor(tau_for_factor(f_min) * 1000) / 1000
        options.append(f"use tau <= {tau_max:g} with k = {k}")
    shortest = "shorter" if dim == 2 else "shortest"
    if any(emb.periodic):
        options.append(f"make the {shortest} periodic side of the box longer")
    if not options:
        options.append("use a smaller k or a smaller tau")
    torus = "torus" if dim == 2 else "3-torus"
    return (
        f"k = {k} cannot be certified for these {n:,} points in the {mode} box "
        f"{tuple(emb.box)} at tau = {tau:g}: Theorem 6's lower bound needs d_Pk <= "
        f"{reach_factor(tau):.3g} x the distance to the nearest earlier vertex at every "
        f"initial mesh vertex, and no valid initial mesh of the {torus} meets it (its spacing "
        f"cannot exceed about a third of the torus' {shortest} period, "
        f"{min(emb.period) / 3.0:.3g}); " + ", or ".join(options)
    )
