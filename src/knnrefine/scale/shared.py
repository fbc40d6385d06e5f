"""A tiled run in threads of this process, its tiles' meshes stitched (the plane).

``refine(points, k, workers=N)`` in the plane. The plan is any tiled run's (``tiled.plan``:
the sample, the initial mesh, the strips, a coarse pass), then:

* **Strips.** N tiles, each a thread refining its strip of the torus in its own mesh, all of
  them counting in one index of all points (the kernels release the GIL). The plan's second
  set of cuts is used: inner quantiles of the data, so a margin lies inside a strip. A tile
  keeps its mesh from turn to turn.
* **Seams.** What a strip left (elements crossing its borders: ``engine/region.py``'s rule)
  lies near the N cuts. Each cut gets a seam, SEAM_SIZES times the largest element the
  strips settled near it (``stitch.largest_near``), refined by a tile of its own from the
  vertices near it. Seams and strips then take turns, each first inserting the vertices the
  others made in its area (``Tile.sync``), until the strips add nothing. A tile without a
  region gathers the vertices of the frame around the data's box (the margins).
* **Stitch.** Every tile has every vertex of the run in its area, so the run's Delaunay
  triangulation is the union of the tiles' shares (``engine/stitch.py``): the cores of the
  strips, seams and frame partition the torus, and each triangle is handed in by the tile
  whose core holds its corner of lowest id, which checks that its disk lies in its area. The
  join is checked (each edge has one twin, 2 m triangles, every vertex used); a join that
  fails is rebuilt by inserting every vertex into one mesh, as the rounds of shifted strips
  do.
* **Last step.** One run over the stitched mesh, with what the tiles settled marked so (a
  circumball's count does not depend on the tile, and a cell only shrinks), finishes
  whatever is left (elements wider than a seam, which no tile could take) and is the mesh
  returned.

Nothing is triangulated twice but the few percent of vertices near the seams. Space keeps the
rounds of shifted strips (``tiled.ThreadStore``).
"""

import time

import numpy as np

from ..engine import jit
from ..engine import refine as R
from ..engine import state as S
from ..engine.driver import Refinement
from ..engine.interrupt import Interrupts
from ..engine.region import in_rectangle
from ..engine.stitch import hand_in, largest_near, owned_triangles
from ..engine.threads import run_all
from ..errors import EngineError
from ..mesh import Mesh
from ..run import Progress, finish
from .tiled import ThreadStore, new_run, plan, regions_axis, settle

SEAM_SIZES = 3.0  # a seam reaches this many of the largest elements near its cut, each side,
SEAM_SPACINGS = 8.0  # and at least this many of the mesh's mean spacings, ...
SEAM_SHARE = 1 / 8  # ... but no more than this share of the narrower strip it borders
FRAME_SIZES = 3.0  # the frame's tile has the vertices this many elements into the data's box
COARSE_SHARE = 32  # the plan's coarse pass refines 1 / (32 T) of the points: strips are wide
MAX_TURNS = 4  # turns of strips and seams before the last step takes what is left


class Tile:
    """A tile's kept mesh: its run, each vertex's global id, its region (where it moves: x0,
    y0, w, h), its area (where it has every vertex of the run: the rectangle (x0, y0, w, h),
    or everything outside it when the fifth number is 0) and how many of the run's vertices
    it has looked at (``synced``)."""

    def __init__(self, number, common, index, region, area, expected):
        self.number = number
        self.run = new_run(index, common, expected)
        self.run.threads = 1  # its sweeps: the other tiles hold the other cores
        self.region = region  # None: a tile that only has the vertices of its area
        if region is not None:
            self.run.set_region(region)
        self.area = np.asarray(area, float)
        self.m0 = m0 = self.run.vertices
        self.gid = np.arange(m0, dtype=np.int64)  # the initial mesh: the same ids in all
        self.synced = m0
        self.pending = np.zeros(0, np.int64)  # vertices of a widened area, to insert
        self.start = None  # its vertices when its refinement began (for progress)
        self.seconds = 0.0

    def sync(self, vertices):
        """Insert the run's vertices made since the last sync by other tiles (or the coarse
        pass) that lie in this tile's area; True when there were some."""
        t0 = time.perf_counter()
        new = np.arange(self.synced, vertices.count)
        self.synced = vertices.count
        new = new[vertices.maker[new] != self.number]
        x0, y0, w, h, inside = self.area
        lx, ly = self.run.period
        mask = in_rectangle(vertices.xy[new], x0, y0, w, h, 0.0, lx, ly)
        new = np.concatenate([self.pending, new[mask if inside else ~mask]])
        self.pending = new[:0]
        if len(new) == 0:
            return False
        ids = self.run.insert(vertices.xy[new], vertices.kinds[new])
        self.gid = _grown(self.gid, self.run.vertices)
        self.gid[ids] = new
        self.seconds += time.perf_counter() - t0
        return True

    def widen(self, area, vertices):
        """Make ``area`` (a rectangle holding the present one) this tile's area: the run's
        vertices in the part it adds are inserted at its next sync."""
        x0, y0, w, h, _ = self.area
        lx, ly = self.run.period
        old = np.arange(self.m0, self.synced)  # the initial mesh is in every tile already
        old = old[vertices.maker[old] != self.number]
        known = in_rectangle(vertices.xy[old], x0, y0, w, h, 0.0, lx, ly)
        x0, y0, w, h, _ = area
        added = in_rectangle(vertices.xy[old], x0, y0, w, h, 0.0, lx, ly) & ~known
        self.area = np.asarray(area, float)
        self.pending = old[added]

    def step(self, vertices, first, deadline, stop):
        """Sync, then refine the region (a tile without one only syncs): (status, the new
        vertices' positions and kinds)."""
        if self.region is None:
            self.sync(vertices)
            return S.STATUS_DONE, self.run.vertices, self.run.positions[:0], np.zeros(0, np.int8)
        if self.sync(vertices) or first:
            self.run.queue_unsettled()  # what the sync made, and what others' regions kept
        t0 = time.perf_counter()
        start = self.start = self.run.vertices
        status = self.run.run(deadline=deadline, interrupts=stop)
        xy, kinds = self.run.new_vertices(start)
        self.seconds += time.perf_counter() - t0
        return status, start, xy, kinds

    def adopt(self, start, ids):
        """The run's ids of this tile's vertices from ``start`` on."""
        self.gid = _grown(self.gid, self.run.vertices)
        self.gid[start : start + len(ids)] = ids


def _grown(a, n):
    if len(a) >= n:
        return a
    out = np.full(max(n, int(1.25 * len(a))), -1, np.int64)
    out[: len(a)] = a
    return out


class Vertices:
    """The run's vertices so far, in the order they got their ids: positions (internal),
    kinds, and the tile that made each (-1: the initial mesh and the coarse pass). Views of
    arrays that grow by a quarter when full (a turn appends each tile's vertices)."""

    def __init__(self, xy, kinds):
        self._xy, self._kinds = xy, kinds
        self._maker = np.full(len(xy), -1, np.int64)
        self.count = len(xy)

    xy = property(lambda self: self._xy[: self.count])
    kinds = property(lambda self: self._kinds[: self.count])
    maker = property(lambda self: self._maker[: self.count])

    def add(self, xy, kinds, maker):
        """Append; returns the new vertices' ids."""
        first, last = self.count, self.count + len(xy)
        if last > len(self._xy):
            size = max(last, int(1.25 * len(self._xy)))
            self._xy, self._kinds, self._maker = (
                S.grown(a, size) for a in (self._xy, self._kinds, self._maker)
            )
        self._xy[first:last] = xy
        self._kinds[first:last] = kinds
        self._maker[first:last] = maker
        self.count = last
        return np.arange(first, last)


class Stop:
    """What a tile's thread checks between kernel calls: Ctrl-C (seen, not consumed: every
    tile stops; the caller raises it) or another tile's failure."""

    def __init__(self, interrupts):
        self.interrupts = interrupts
        self.failed = False

    def check(self):
        if self.failed or (self.interrupts is not None and self.interrupts.hit):
            raise KeyboardInterrupt


def run_turn(tiles, vertices, first, deadline, stop, report):
    """Every tile's step, on threads; the new vertices get their ids, tile by tile (so the
    ids do not depend on which thread finished first). Returns (status of a tile stopped by
    a budget or None, the vertices added, the turn's report)."""
    t0 = time.perf_counter()
    for tile in tiles:
        tile.start = None

    def meanwhile():  # in this thread: the vertices so far (the tiles' read as they grow)
        made = sum(t.run.vertices - t.start for t in tiles if t.start is not None)
        report.refining(vertices.count + max(made, 0), 0)
        stop.check()  # Ctrl-C

    try:
        results = run_all(lambda j: tiles[j].step(vertices, first, deadline, stop), len(tiles),
                          meanwhile)  # fmt: skip
    except BaseException:
        stop.failed = True
        raise
    added = 0
    stopped = None
    for tile, (status, start, xy, kinds) in zip(tiles, results, strict=True):
        tile.adopt(start, vertices.add(xy, kinds, tile.number))
        added += len(xy)
        if status != S.STATUS_DONE and stopped is None:
            stopped = status
    report.refining(vertices.count, 0)
    return stopped, added, {"new_vertices": added, "seconds": time.perf_counter() - t0,
                            "tiles": [float(t.seconds) for t in tiles]}  # fmt: skip


def sizes_near(tiles, slabs, data):
    """The largest settled circumradius centred in the data's box ``data`` and meeting each
    slab (axis, lo, width) in any of the tiles' meshes (``stitch.largest_near``, a thread
    per tile)."""
    slabs = np.ascontiguousarray(slabs, float)
    found = [np.zeros(len(slabs)) for _ in tiles]

    def measure(j):
        run = tiles[j].run
        largest_near(run.mesh, run.book, int(run.cnt[S.C_NT]), slabs, data, run.prm, found[j])

    run_all(measure, len(tiles))
    return np.max(found, axis=0)


def seam_widths(strips, cuts, axis, length, spacing, data, periodic):
    """Half the width of the seam at each cut (of a period ``length``), the largest element
    the strips settled near it, and how far into the data's box the frame's tile must have
    every vertex. A seam is SEAM_SIZES times its element, at least SEAM_SPACINGS times the
    mesh's mean spacing ``spacing``, at most SEAM_SHARE of the narrower strip it borders; the
    frame's band FRAME_SIZES times the largest element the strips settled near the box's
    sides along its non-periodic axes (at least SEAM_SPACINGS spacings). One pass over the
    strips' meshes measures both."""
    least = SEAM_SPACINGS * spacing
    sides = [(a, data[a] + side * data[2 + a] - least, 2 * least)
             for a in range(2) if not periodic[a] for side in (0, 1)]  # fmt: skip
    near = sizes_near(strips, [(axis, c - least, 2 * least) for c in cuts] + sides, data)
    near, frame = near[: len(cuts)], near[len(cuts) :]
    widths = np.diff(np.append(cuts, cuts[0] + length))
    most = SEAM_SHARE * np.minimum(widths, np.roll(widths, 1))
    band = max(FRAME_SIZES * float(frame.max(initial=0.0)), least)
    return np.minimum(np.maximum(SEAM_SIZES * near, least), most), near, band


def stitch(tiles, bounds, axis, cores, data, vertices):
    """The run's triangulation from the tiles' shares, each tile on a thread: (corners,
    offsets, neighbours, the circumballs' states, the cells settled, the caches the tiles
    knew: ``Refinement``'s ``caches``), or None when the
    shares do not join (a tile cannot vouch for its share, or an edge lacks its twin, or
    the count is not 2 m). ``cores``: each tile's core in ``bounds`` along ``axis`` (-1:
    the frame's tile); ``data``: the box of the data (x0, y0, w, h), the frame around it."""
    nv = vertices.count
    shares = [None] * len(tiles)

    def own(j):
        run = tiles[j].run
        gid = np.ascontiguousarray(tiles[j].gid[: run.vertices])
        if gid.min() < 0:
            raise EngineError("a tile's vertex has no id in the run (a broken tile)")
        mine = np.zeros(int(run.cnt[S.C_NT]), np.bool_)
        bad = owned_triangles(run.mesh, len(mine), gid, bounds, axis, cores[j], data,
                              tiles[j].area, run.prm, mine)  # fmt: skip
        shares[j] = (gid, mine)
        return bad, int(np.count_nonzero(mine))

    owned = run_all(own, len(tiles))
    total = sum(c for _, c in owned)
    if any(bad for bad, _ in owned) or total != 2 * nv:
        return None
    bases = np.concatenate([[0], np.cumsum([c for _, c in owned])])
    out = (
        np.empty((total, 3), np.int32),  # corners (the engine's types: ``initial_grid``)
        np.empty((total, 3, 2), np.int8),  # offsets
        np.empty((total, 3), np.int32),  # neighbours
        np.empty(total, np.int8),  # circumball states
        np.empty(total),  # squared circumradii
        np.zeros(nv, np.bool_),  # cells settled
    )
    caches = (np.zeros(nv), np.zeros(nv, np.bool_))

    def write(j):
        run = tiles[j].run
        gid, mine = shares[j]
        hand_in(run.mesh, run.book, len(mine), run.vertices, gid, mine, bases[j], bounds, axis,
                cores[j], data, tiles[j].area, run.prm, out, caches)  # fmt: skip

    run_all(write, len(tiles))
    corners, offsets, neighbours, balls, radius2, cells = out
    t, i = np.nonzero(neighbours < 0)
    if not _join(t, i, corners, offsets, neighbours, nv):
        return None
    if np.bincount(corners.ravel(), minlength=nv).min() == 0:
        return None
    return corners, offsets, neighbours, balls, cells, (radius2, *caches)


def _join(t, i, corners, offsets, neighbours, nv):
    """Set the neighbours across the edges (triangle t, opposite corner i) that join two
    tiles' shares: each edge a -> b (with b's offset from a) meets its twin b -> a. False
    when some edge has no twin, or more than one."""
    if len(t) == 0:
        return True
    if nv >= 1 << 29:  # the keys below would overflow
        return False
    a = corners[t, (i + 1) % 3].astype(np.int64)
    b = corners[t, (i + 2) % 3].astype(np.int64)
    d = offsets[t, (i + 2) % 3].astype(np.int64) - offsets[t, (i + 1) % 3]
    if np.abs(d).max() > 2:
        return False

    def key(u, v, dx, dy):
        return ((u * nv + v) * 5 + (dx + 2)) * 5 + (dy + 2)

    fwd = key(a, b, d[:, 0], d[:, 1])
    back = key(b, a, -d[:, 0], -d[:, 1])
    order = np.argsort(fwd)
    sorted_fwd = fwd[order]
    if np.any(sorted_fwd[1:] == sorted_fwd[:-1]):
        return False
    at = np.searchsorted(sorted_fwd, back)
    at = np.minimum(at, len(fwd) - 1)
    if not np.array_equal(sorted_fwd[at], back):
        return False
    neighbours[t, i] = t[order[at]]
    return True


def refine_threads(pts, w, opt, workers) -> Mesh:
    """``knnrefine.refine(points, k, workers=N)`` in the plane: the module's run.

    Parameters
    ----------
    pts : ndarray (n, 2)
    w : ndarray (n,) or None
    opt : RunOptions
        Checked (``run.checked``).
    workers : int
        Threads, and strips.

    Returns
    -------
    Mesh
    """
    store = ThreadStore(pts, w, workers)
    report = Progress(opt.progress)
    if not jit.is_ready(R.refine_steps):
        report.compiling()
    with Interrupts() as interrupts:
        t0 = time.perf_counter()
        p = plan(store, opt, workers, interrupts, COARSE_SHARE)
        emb, common = p.emb, p.common
        store.prepare(emb, p.sets, 4 * emb.grid)
        index = store.index
        setup = time.perf_counter() - t0
        lx, ly = period = tuple(emb.period_internal)
        grid = emb.grid
        m0 = p.m0
        vertices = Vertices(np.concatenate([m0[0], p.xy]),
                            np.concatenate([np.zeros(len(m0[0]), np.int8), p.kinds]))  # fmt: skip
        stop = Stop(interrupts)
        deadline = opt.deadline
        # the strips of the plan's second set: its cuts are inner quantiles of the data, so
        # a margin (no data, large elements) lies inside a strip, never at a cut
        axis = regions_axis(p.sets[1], period)
        cuts, widths = p.sets[1][:, axis], p.sets[1][:, 2 + axis]
        length = period[axis]
        data = _data_box(emb, period)
        spacing = np.sqrt(data[2] * data[3] / max(p.estimated, 1.0))
        expected = min(p.estimated, p.budget)
        pad = 4 * grid

        def band(start, width, inside=None):
            """The strip [start, start + width] across ``axis`` as (x0, y0, w, h), with an
            area's flag when given."""
            box = [0.0, 0.0, lx, ly]
            box[axis], box[2 + axis] = start, width
            return tuple(box) if inside is None else (*box, inside)

        strips = [
            Tile(j, common, index, band(cuts[j], widths[j]),
                 band(cuts[j] - pad, widths[j] + 2 * pad, 1), expected / workers)
            for j in range(workers)
        ]  # fmt: skip
        rounds = []
        stopped, _, rep = run_turn(strips, vertices, True, deadline, stop, report)
        rounds.append({"round": "strips", **rep})
        interrupts.check()
        half, near, frame_w = seam_widths(strips, cuts, axis, length, spacing, data, emb.periodic)
        # a tile vouches for the triangles of its core whose disks lie in its area: beyond
        # its region, seams and strips have every vertex as far again as the largest element
        # near their cut spans
        reach = half + 2.0 * near
        seams = [
            Tile(workers + j, common, index, band(cuts[j] - half[j], 2 * half[j]),
                 band(cuts[j] - reach[j] - pad, 2 * reach[j] + 2 * pad, 1),
                 expected * 2 * reach[j] / length)
            for j in range(workers)
        ]  # fmt: skip
        for j, tile in enumerate(strips):
            k = (j + 1) % workers
            lo, hi = 2.0 * near[j], 2.0 * near[k]
            tile.widen(band(cuts[j] - lo - pad, widths[j] + lo + hi + 2 * pad, 1), vertices)
        frame = _frame(emb, period, data, frame_w)
        framed = []  # the frame's tile: every vertex in the margins and near them, gathered
        if frame is not None:  # with the seams' turns (it makes none)
            framed = [Tile(2 * workers, common, index, None, frame, 0)]
        for turn in range(MAX_TURNS):  # seams, then strips with their vertices, until the
            if stopped is not None:  # strips add nothing
                break
            for name, group in (("seams", seams + framed), ("strips", strips)):
                stopped, added, rep = run_turn(group, vertices, turn == 0 and name == "seams",
                                               deadline, stop, report)  # fmt: skip
                rounds.append({"round": name, **rep})
                interrupts.check()
                if stopped is not None:
                    break
            if added == 0:
                break
        t1 = time.perf_counter()
        tiles = strips + seams
        bounds, owners = _cores(cuts, half, length)
        cores = [int(np.flatnonzero(owners == t.number)[0]) for t in tiles] + [-1] * len(framed)
        tiles += framed
        joined = None
        if stopped is None:
            # every tile gets every vertex of its area (after a turn that added none: only the
            # frame's tile inserts some)
            run_all(lambda j, tiles=tiles: tiles[j].sync(vertices), len(tiles))
            joined = stitch(tiles, bounds, axis, cores, data, vertices)
        counts = np.sum([t.run.cnt for t in tiles], axis=0)
        seconds = [float(t.seconds) for t in tiles]
        tiles = strips = seams = framed = []  # their meshes go before the last step's is made
        budget = p.budget
        if joined is not None:
            corners, offsets, neighbours, balls, cells, caches = joined
            run = Refinement(index, common["k"], lx, ly, common["tau"], common["min_size"],
                             budget, m0=(vertices.xy, corners, offsets, neighbours), grid=grid,
                             capacity=vertices.count + vertices.count // 8 + 1024,
                             queued=False, caches=caches)  # fmt: skip
            nt, nv = len(corners), vertices.count
            run.book.ball_state[:nt] = balls
            run.book.cell_state[:nv] = np.where(cells, S.GOOD, S.UNTESTED)
            run.book.kinds[:nv] = vertices.kinds
            run.queue_unsettled()
        else:  # the vertices are a run's moves: one mesh of them all, everything requeued
            x = vertices.xy[len(m0[0]) :]
            kinds = vertices.kinds[len(m0[0]) :]
            run, _, _ = settle(index, x, kinds, np.zeros(len(x), np.int32),
                               np.zeros((0, workers, 4)), common)  # fmt: skip
        for c in (S.C_DISK_TESTS, S.C_CELL_TESTS, S.C_FAILED):
            run.cnt[c] += counts[c]
        before, unsettled = run.vertices, run.pending()
        status = stopped
        if status is None:
            status = run.run(deadline=deadline, progress=report.refining, interrupts=interrupts)
        rounds.append({"round": "final", "new_vertices": run.vertices - before,
                       "seconds": time.perf_counter() - t1, "stitched": joined is not None,
                       "unsettled": unsettled,
                       "tile_seconds": seconds, "seams": [float(h / emb.scale) for h in half],
                       "fetched_points": False})  # fmt: skip
        run.n = store.n
        run.time_index = setup
        run.time_refine = time.perf_counter() - t0 - setup
        return finish(
            run, status, emb, opt, (p.m0_order, p.m0_grid, p.estimated, budget), report,
            interrupts, None, store.weight, rounds,
        )  # fmt: skip


def _data_box(emb, period):
    """The box of the data in torus coordinates (x0, y0, w, h; a periodic axis' whole
    period)."""
    lo, hi = emb.box_internal()
    box = [(0.0, period[a]) if emb.periodic[a] else (float(lo[a]), float(hi[a] - lo[a]))
           for a in range(2)]  # fmt: skip
    return np.array([box[0][0], box[1][0], box[0][1], box[1][1]])


def _frame(emb, period, data, band):
    """The frame's tile's area: everything outside the data's box shrunk by ``band`` along
    its non-periodic axes (None when both axes are periodic: no frame)."""
    if all(emb.periodic):
        return None
    x0, y0, w, h = data
    inner = []
    for a, (lo, size) in enumerate(((x0, w), (y0, h))):
        inner.append((lo, size) if emb.periodic[a] else (lo + band, max(size - 2 * band, 0.0)))
    return (inner[0][0], inner[1][0], inner[0][1], inner[1][1], 0)


def _cores(cuts, half, lx):
    """The cores' lower bounds along the cut axis (sorted, in [0, lx): lx its period) and
    the tile owning each: seam j
    (number T + j) owns [cut_j - h_j, cut_j + h_j), strip j (number j) the rest of its strip,
    [cut_j + h_j, cut_{j+1} - h_{j+1})."""
    t = len(cuts)
    lows = np.concatenate([cuts - half, cuts + half])
    owners = np.concatenate([np.arange(t, 2 * t), np.arange(t)])
    lows = lows - np.floor(lows / lx) * lx
    lows = np.where(lows >= lx, lows - lx, lows)
    order = np.argsort(lows, kind="stable")
    return np.ascontiguousarray(lows[order]), owners[order]
