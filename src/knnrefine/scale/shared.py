"""A tiled run in threads of this process, its tiles' meshes stitched (the plane and space).

``refine(points, k, workers=N)``. The plan is any tiled run's (``tiled.plan``: the sample,
the initial mesh, the strips, a coarse pass), then:

* **Strips.** N tiles, each a thread refining its strip of the torus (a slab in space) in
  its own mesh, all of them counting in one index of all points (the kernels release the
  GIL). The plan's second set of cuts is used: inner quantiles of the data, so a margin
  lies inside a strip. A tile keeps its mesh from turn to turn.
* **Seams.** What a strip left (elements crossing its borders: ``_engine/region.py``'s rule,
  ``region3.py`` in space) lies near the N cuts. Each cut gets a seam, SEAM_SIZES times the
  largest element the strips settled near it (``stitch.largest_near``), refined by a tile
  of its own from the vertices near it. Seams and strips then take turns, each first
  inserting the vertices the others made that it must have (``Tile.sync``), until the
  strips add nothing.
* **Reach.** Besides every vertex within a pad of its region, a tile has every vertex v
  within 2 R(v) of its region, R(v) bounded from above by any tile's mesh that has v
  (``Vertices.reach``; the reach rule, ``Tile``): then its stars of the vertices in its
  region are the run's. The
  reach is each vertex's own, so the large elements of a void reach far and the small ones
  beside them do not (a margin as wide as the largest element near a cut took every
  vertex of a plane of points in space into every tile).
* **Stitch.** The run's Delaunay triangulation is the union of the tiles' shares
  (``_engine/stitch.py``, ``_engine/stitch3.py``): the cores of the strips and seams (the
  middle half of each seam) partition the torus, margins included, and each simplex is
  handed in by the tile whose core holds its corner of lowest id, whose star there is the
  run's. The join is checked (each facet has one twin; 2 m triangles on the torus, the
  torus' volume in space); a join that fails is rebuilt by inserting every vertex into one
  mesh, as the rounds of shifted strips do.
* **Last step.** One run over the stitched mesh, with what the tiles settled marked so (a
  circumball's count does not depend on the tile, and a cell only shrinks), finishes
  whatever is left (elements wider than a seam, which no tile could take) and is the mesh
  returned.

Nothing is triangulated twice but the vertices near the seams.
"""

import time

import numpy as np

from .._domains import part
from .._engine import ahead
from .._engine import state as S
from .._engine.driver import Refinement
from .._engine.driver3 import Refinement3
from .._engine.interrupt import Interrupts
from .._engine.stitch import hand_in, largest_near, owned_triangles
from .._engine.stitch3 import (
    hand_in3,
    largest_near3,
    owned_tetrahedra,
    settled_table3,
    take_settled3,
)
from .._engine.threads import run_all
from .._engine.triangulation3 import unpack_offsets
from .._options import Progress
from ..errors import EngineError
from ..mesh import Mesh
from .tiled import (
    LocalStore,
    ThreadStore,
    in_region,
    new_run,
    plan,
    refine_store,
    regions_axis,
    settle,
)

SEAM_SIZES = 3.0  # a seam reaches this many of the largest elements near its cut, each side,
SEAM_SPACINGS = 8.0  # and at least this many of the mesh's mean spacings, ...
SEAM_SHARE = 1 / 8  # ... but no more than this share of the narrower strip it borders
COARSE_SHARE = 32  # the plan's coarse pass refines 1 / (32 T) of the points: strips are wide
CORE_SHARE = 0.5  # a seam's core: this share of its region's width, about the cut
MAX_TURNS = 4  # turns of strips and seams before the last step takes what is left


class Tile:
    """A tile's kept mesh: its run, each vertex's global id, its region (where it moves: a
    box, its lower corner then its widths), its box (the region and a pad, where it has
    every vertex of the run: a box, then 1) and how many of the run's vertices it has
    looked at (``synced``).

    The reach rule: a tile has every vertex v of the run within 2 R(v) of its region (R(v)
    the distance from v to its Voronoi cell's farthest corner, a bound from any tile's
    mesh: ``Vertices.reach``). Then it has every Delaunay neighbour u of every vertex v in
    its region (the edge uv lies in the circumball of a simplex at u, of radius <= R(u), so
    |uv| <= 2 R(u)), and the balls of v's star are empty of the run's vertices, so its
    stars of the vertices in its region are the run's, whatever its mesh elsewhere: it
    vouches for every simplex whose corner of lowest id lies in its core (its ``area`` for
    the stitch is the whole torus). A vertex's reach is local: beside a plane of points in space the
    large elements of the empty side reach far but are few, where a margin as wide as the
    largest element near a cut took most of the plane's vertices into every tile. Nor does a
    tile need the frame's tile it once had around the data's box: a strip's band crosses
    the margins, and the rule holds there too."""

    def __init__(self, number, common, index, region, box, expected):
        self.number = number
        self.run = new_run(index, common, expected)
        self.run.threads = 1  # its sweeps: the other tiles hold the other cores
        self.region = region
        self.run.set_region(region)
        self.box = np.asarray(box, float)
        period = self.run.period
        self.area = np.array([0.0] * len(period) + list(period) + [-1.0])  # the reach rule
        m0 = self.run.vertices
        self.gid = np.arange(m0, dtype=np.int64)  # the initial mesh: the same ids in all
        self.synced = m0
        self.start = None  # its vertices when its refinement began (for progress)
        self.known = []  # other tiles' settled tetrahedra (``stitch3.settled_table3``)
        self.seconds = 0.0

    def sync(self, vertices):
        """Insert the run's vertices made since the last sync by other tiles (or the coarse
        pass) that lie in this tile's box or reach its region (``Vertices.reach``);
        returns their ids in this tile's run (None when there were none)."""
        t0 = time.perf_counter()
        new = np.arange(self.synced, vertices.count)
        self.synced = vertices.count
        new = new[vertices.maker[new] != self.number]
        new = new[self._holds(vertices.xy[new], vertices.reach[new])]
        if len(new) == 0:
            return None
        ids = self.run.insert(vertices.xy[new], vertices.kinds[new])
        self.gid = _grown(self.gid, self.run.vertices)
        self.gid[ids] = new
        self.run.book.cell_state[ids[vertices.settled[new]]] = S.GOOD  # counted by others
        self.seconds += time.perf_counter() - t0
        return ids

    def _holds(self, x, reach):
        """Mask of the positions x (with their reach) this tile must have: in its box, or
        within reach of its region."""
        period = tuple(self.run.period)
        inside = in_region(x, self.box[:-1], 0.0, period)
        return inside | (distance_to(x, self.region, period) <= reach)

    def step(self, vertices, first, deadline, stop):
        """Sync, then refine the region: (status, the new vertices' positions and kinds)."""
        ids = self.sync(vertices)
        for table in self.known:  # counted already by the tiles that made them (space)
            take_settled3(self.run.mesh, self.run.book, int(self.run.cnt[S.C_NT]), self.gid,
                          table)  # fmt: skip
        self.known = []
        if first:
            self.run.queue_unsettled()  # what the sync made, and what others' regions kept
        elif ids is not None:  # a finished run: what the sync changed
            self.run.queue_synced(ids)
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


def distance_to(x, box, period):
    """Distance on the torus of ``period`` from each position x to ``box`` (its corner, then
    its widths)."""
    d = len(period)
    x = np.asarray(x, float).reshape(-1, d)
    total = np.zeros(len(x))
    for a in range(d):
        lo, w, length = box[a], box[d + a], period[a]
        if w >= length:  # the whole circle: no gap to it
            continue
        s = np.mod(x[:, a] - lo, length)
        gap = np.where(s <= w, 0.0, np.minimum(s - w, length - s))
        total += gap * gap
    return np.sqrt(total)


def _grown(a, n):
    if len(a) >= n:
        return a
    out = np.full(max(n, int(1.25 * len(a))), -1, np.int64)
    out[: len(a)] = a
    return out


class Vertices:
    """The run's vertices so far, in the order they got their ids: positions (internal),
    kinds, the tile that made each (-1: the initial mesh and the coarse pass), whether
    some tile found its cell to hold < k points (settled for good: a cell only shrinks as
    vertices come) and its reach: 2 R(v) (R(v) the distance to its Voronoi cell's farthest
    corner) bounded from above by the meshes of the tiles that have it (the cell of v among
    fewer vertices holds its cell among all), widened by a relative 1e-6 and ``slack``; inf
    until a tile told. Views of arrays that grow by a quarter when full (a turn appends each
    tile's vertices)."""

    def __init__(self, xy, kinds, slack):
        self._xy, self._kinds = xy, kinds
        self._maker = np.full(len(xy), -1, np.int64)
        self._settled = np.zeros(len(xy), np.bool_)
        self._reach = np.full(len(xy), np.inf)
        self.slack = slack
        self.count = len(xy)

    xy = property(lambda self: self._xy[: self.count])
    kinds = property(lambda self: self._kinds[: self.count])
    maker = property(lambda self: self._maker[: self.count])
    settled = property(lambda self: self._settled[: self.count])
    reach = property(lambda self: self._reach[: self.count])

    def settle(self, tile):
        """Note the cells ``tile`` settled, and its bounds on the reach of its vertices."""
        run = tile.run
        nv = run.vertices
        gid = tile.gid[:nv]
        self._settled[gid[run.book.cell_state[:nv] == S.GOOD]] = True
        reach = 2.0 * (1.0 + 1e-6) * run.outradii() + self.slack
        self._reach[gid] = np.minimum(self._reach[gid], reach)  # a tile's ids are distinct

    def add(self, xy, kinds, maker):
        """Append; returns the new vertices' ids."""
        first, last = self.count, self.count + len(xy)
        if last > len(self._xy):
            size = max(last, int(1.25 * len(self._xy)))
            self._xy, self._kinds, self._maker, self._settled, self._reach = (
                S.grown(a, size)
                for a in (self._xy, self._kinds, self._maker, self._settled, self._reach)
            )
        self._xy[first:last] = xy
        self._kinds[first:last] = kinds
        self._maker[first:last] = maker
        self._reach[first:last] = np.inf
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
        vertices.settle(tile)
        added += len(xy)
        if status != S.STATUS_DONE and stopped is None:
            stopped = status
    report.refining(vertices.count, 0)
    return stopped, added, {"new_vertices": added, "seconds": time.perf_counter() - t0,
                            "tiles": [float(t.seconds) for t in tiles]}  # fmt: skip


def sizes_near(tiles, slabs, data):
    """The largest settled circumradius centred in the data's box ``data`` and meeting each
    slab (axis, lo, width) in any of the tiles' meshes (``stitch.largest_near``,
    ``stitch3.largest_near3`` in space; a thread per tile)."""
    slabs = np.ascontiguousarray(slabs, float)
    found = [np.zeros(len(slabs)) for _ in tiles]
    largest = largest_near if len(data) == 4 else largest_near3

    def measure(j):
        run = tiles[j].run
        largest(run.mesh, run.book, int(run.cnt[S.C_NT]), slabs, data, run.prm, found[j])

    run_all(measure, len(tiles))
    return np.max(found, axis=0)


def seam_widths(strips, cuts, axis, length, spacing, data):
    """Half the width of the seam at each cut (of a period ``length``): SEAM_SIZES times
    the largest element the strips settled near it, at least SEAM_SPACINGS times the mesh's
    mean spacing ``spacing``, at most SEAM_SHARE of the narrower strip it borders."""
    least = SEAM_SPACINGS * spacing
    near = sizes_near(strips, [(axis, c - least, 2 * least) for c in cuts], data)
    widths = np.diff(np.append(cuts, cuts[0] + length))
    most = SEAM_SHARE * np.minimum(widths, np.roll(widths, 1))
    return np.minimum(np.maximum(SEAM_SIZES * near, least), most)


def stitch(tiles, bounds, axis, cores, data, vertices):
    """The run's triangulation from the tiles' shares, each tile on a thread: (corners,
    offsets, neighbours, the circumballs' states, the cells settled, the caches the tiles
    knew: ``Refinement``'s ``caches``; in space the squared circumradii); or, when some
    tiles cannot vouch for their share, a list: the largest radius of a ball past each
    tile's area (0: none); or None when the shares do not join (a face lacks its twin, or
    the shares do not fill the torus: 2 m triangles in the plane, the torus' volume in
    space). ``cores``: each tile's core in ``bounds`` along ``axis`` inside the box
    ``data`` (its corner, then its widths; the whole torus in a run), or, for -1, the
    frame outside that box (the kernels' other reading, kept for their tests)."""
    nv = vertices.count
    d = len(tiles[0].run.period)
    shares = [None] * len(tiles)
    owned_by = owned_triangles if d == 2 else owned_tetrahedra

    def own(j):
        run = tiles[j].run
        gid = np.ascontiguousarray(tiles[j].gid[: run.vertices])
        if gid.min() < 0:
            raise EngineError("a tile's vertex has no id in the run (a broken tile)")
        mine = np.zeros(int(run.cnt[S.C_NT]), np.bool_)
        bad = owned_by(run.mesh, len(mine), gid, bounds, axis, cores[j], data, tiles[j].area,
                       run.prm, mine)  # fmt: skip
        shares[j] = (gid, mine)
        return bad, int(np.count_nonzero(mine))

    owned = run_all(own, len(tiles))
    if any(bad for (bad, _), _ in owned):  # balls past some areas: by how far at most
        return [largest if bad else 0.0 for (bad, largest), _ in owned]
    total = sum(c for _, c in owned)
    if d == 2 and total != 2 * nv:
        return None
    bases = np.concatenate([[0], np.cumsum([c for _, c in owned])])
    out = (
        np.empty((total, d + 1), np.int32),  # corners (the engine's types: ``initial_grid``)
        np.empty((total, 3, 2), np.int8) if d == 2 else np.empty(total, np.uint32),  # offsets
        np.empty((total, d + 1), np.int32),  # neighbours
        np.empty(total, np.int8),  # circumball states
        np.empty(total),  # squared circumradii
        np.zeros(nv, np.bool_),  # cells settled
    )
    caches = (np.zeros(nv), np.zeros(nv, np.bool_)) if d == 2 else None  # the plane's
    volumes = np.zeros(len(tiles))

    def write(j):
        run = tiles[j].run
        gid, mine = shares[j]
        if d == 2:
            hand_in(run.mesh, run.book, len(mine), run.vertices, gid, mine, bases[j], bounds,
                    axis, cores[j], data, tiles[j].area, run.prm, out, caches)  # fmt: skip
        else:
            volumes[j] = hand_in3(run.mesh, run.book, len(mine), run.vertices, gid, mine,
                                  bases[j], run.prm, out)[1]  # fmt: skip

    run_all(write, len(tiles))
    corners, offsets, neighbours, balls, radius2, cells = out
    if d == 3:  # no count of tetrahedra follows from m: the volumes must fill the torus
        torus = float(np.prod(tiles[0].run.period))
        if abs(volumes.sum() - torus) > 1e-9 * torus:
            return None
    t, i = np.nonzero(neighbours < 0)
    facets = offsets[t] if d == 2 else unpack_offsets(offsets[t])
    if not _join(t, i, corners, facets, neighbours):
        return None
    if np.bincount(corners.ravel(), minlength=nv).min() == 0:
        return None
    if d == 3:
        return corners, offsets, neighbours, balls, cells, radius2
    return corners, offsets, neighbours, balls, cells, (radius2, *caches)


def _join(t, i, corners, offsets, neighbours):
    """Set the neighbours across the facets (simplex t, opposite corner i) that join two
    tiles' shares: edges in the plane, triangles in space; ``offsets`` (len(t), d + 1, d)
    are the simplices t's. Each facet meets its twin: the same vertices at the same
    offsets from one another. False when some facet has no twin, or more than one."""
    if len(t) == 0:
        return True
    d = corners.shape[1] - 1
    others = (i[:, None] + np.arange(1, d + 1)[None, :]) % (d + 1)  # the facet's corners
    ids = corners[t[:, None], others].astype(np.int64)
    offs = np.take_along_axis(offsets, others[:, :, None], axis=1).astype(np.int64)
    order = np.argsort(ids, axis=1, kind="stable")  # by vertex: the same in both twins
    ids = np.take_along_axis(ids, order, axis=1)
    offs = np.take_along_axis(offs, order[:, :, None], axis=1)
    rel = offs[:, 1:] - offs[:, :1]  # the others' offsets from the first's
    if np.abs(rel).max() > 3:
        return False
    columns = [ids[:, c] for c in range(d)] + [(rel + 3).reshape(len(t), -1) @ (
        7 ** np.arange((d - 1) * d, dtype=np.int64))]  # fmt: skip
    by = np.lexsort(columns[::-1])
    keys = np.stack(columns, axis=1)[by]
    if len(by) % 2 or not np.array_equal(keys[0::2], keys[1::2]):
        return False
    if len(by) > 2 and np.any(np.all(keys[2::2] == keys[1:-1:2], axis=1)):
        return False  # three or more alike
    a, b = by[0::2], by[1::2]
    neighbours[t[a], i[a]] = t[b]
    neighbours[t[b], i[b]] = t[a]
    return True


def refine_threads(pts, w, opt, workers) -> Mesh:
    """``knnrefine.refine(points, k, workers=N)`` in this process: the module's run, in the
    plane or in space.

    Parameters
    ----------
    pts : ndarray (n, 2) or (n, 3)
    w : ndarray (n,) or None
    opt : RunOptions
        Checked (``pipeline.checked``).
    workers : int
        Threads, and strips (slabs in space).

    Returns
    -------
    Mesh
    """
    store = ThreadStore(pts, w, workers)
    report = Progress(opt.progress)
    dim = pts.shape[1]
    with ahead.compiling(opt.domain, report.compiling), Interrupts() as interrupts:
        t0 = time.perf_counter()
        p = plan(store, opt, workers, interrupts, COARSE_SHARE)
        emb, common = p.emb, p.common
        store.prepare(emb, p.sets, 4 * emb.grid)
        index = store.index
        setup = time.perf_counter() - t0
        period = tuple(emb.period_internal)
        grid = emb.grid
        m0 = p.m0
        pad = 4 * grid
        kinds = np.concatenate([np.zeros(len(m0[0]), np.int8), p.kinds])
        vertices = Vertices(np.concatenate([m0[0], p.xy]), kinds, pad)
        stop = Stop(interrupts)
        deadline = opt.deadline
        # the strips of the plan's second set: its cuts are inner quantiles of the data, so
        # a margin (no data, large elements) lies inside a strip, never at a cut
        axis = regions_axis(p.sets[1], period)
        cuts, widths = p.sets[1][:, axis], p.sets[1][:, dim + axis]
        length = period[axis]
        data = _data_box(emb, period)
        expected = min(p.estimated, p.budget)
        spacing = (np.prod(data[dim:]) / max(p.estimated, 1.0)) ** (1.0 / dim)

        def band(start, width, inside=None):
            """The strip [start, start + width] across ``axis`` as a box (corner, widths),
            with an area's flag when given."""
            box = [0.0] * dim + list(period)
            box[axis], box[dim + axis] = start, width
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
        half = seam_widths(strips, cuts, axis, length, spacing, data)
        # beyond its region a tile has what the reach rule asks (``Tile``), no margin
        seams = [
            Tile(workers + j, common, index, band(cuts[j] - half[j], 2 * half[j]),
                 band(cuts[j] - half[j] - pad, 2 * half[j] + 2 * pad, 1),
                 expected * 2 * half[j] / length)
            for j in range(workers)
        ]  # fmt: skip
        if dim == 3:  # the seams' circumballs the strips counted: not counted again
            boxes = np.array([seam.region for seam in seams])

            def settled(j):
                run = strips[j].run
                return settled_table3(run.mesh, run.book, int(run.cnt[S.C_NT]), strips[j].gid,
                                      run.prm, boxes)  # fmt: skip

            tables = run_all(settled, workers)
            for seam in seams:
                seam.known = tables
        for turn in range(MAX_TURNS):  # seams, then strips with their vertices, until the
            if stopped is not None:  # strips add nothing
                break
            for name, group in (("seams", seams), ("strips", strips)):
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
        # a seam's core is the middle half of its region: on both sides of a core's
        # boundary the tile owning it and its neighbour have half a seam to settle what
        # crosses it (a core as wide as the seam's region left the seam's elements near its
        # edge unsettled, for the last step to count again)
        bounds, owners = _cores(cuts, CORE_SHARE * half, length)
        cores = [int(np.flatnonzero(owners == t.number)[0]) for t in tiles]
        joined = None
        if stopped is None:
            # every tile gets every vertex the reach rule asks (after a turn that added
            # none: few or none); the cores cross the margins (the whole torus)
            run_all(lambda j, tiles=tiles: tiles[j].sync(vertices), len(tiles))
            whole = np.array([0.0] * dim + list(period))
            joined = stitch(tiles, bounds, axis, cores, whole, vertices)
            if not isinstance(joined, tuple):  # refused: every vertex in one mesh below
                joined = None
        counts = np.sum([t.run.cnt for t in tiles], axis=0)
        seconds = [float(t.seconds) for t in tiles]
        tiles = strips = seams = []  # their meshes go before the last step's is made
        budget = p.budget
        if joined is not None:
            run = _stitched_run(joined, vertices, index, common, budget)
        else:  # the vertices are a run's moves: one mesh of them all, everything requeued
            x = vertices.xy[len(m0[0]) :]
            kinds = vertices.kinds[len(m0[0]) :]
            run, _, _ = settle(index, x, kinds, np.zeros(len(x), np.int32),
                               np.zeros((0, workers, 2 * dim)), common)  # fmt: skip
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
        run.time_index = setup  # the tiles and rounds count as the refinement
        run.time_refine = time.perf_counter() - t0 - setup
        finish = part(opt.domain, "run").finish
        return finish(run, status, emb, opt, n=store.n, weight=store.weight,
                      points=lambda: pts, report=report, estimated=p.reported_estimate,
                      budget=budget, initial=len(p.m0_order), rounds=rounds,
                      interrupts=interrupts)  # fmt: skip


def _stitched_run(joined, vertices, index, common, budget):
    """The last step's run over the stitched triangulation: what the tiles settled marked
    so, the rest queued."""
    corners, offsets, neighbours, balls, cells, caches = joined
    nt, nv = len(corners), vertices.count
    capacity = nv + nv // 8 + 1024
    k, tau, floor, grid = common["k"], common["tau"], common["min_size"], common["grid"]
    period = common["period"]
    m0 = (vertices.xy, corners, offsets, neighbours)
    if len(period) == 3:
        run = Refinement3(index, period, k, tau, floor, budget, m0, grid, queued=False,
                          capacity=capacity)  # fmt: skip
    else:
        run = Refinement(index, k, *period, tau, floor, budget, m0=m0, grid=grid,
                         capacity=capacity, queued=False, caches=caches)  # fmt: skip
    run.book.ball_state[:nt] = balls
    run.book.cell_state[:nv] = np.where(cells, S.GOOD, S.UNTESTED)
    run.book.kinds[:nv] = vertices.kinds
    run.queue_unsettled()
    return run


def _data_box(emb, period):
    """The box of the data in torus coordinates (its corner, then its widths; a periodic
    axis' whole period)."""
    lo, hi = emb.box_internal()
    d = len(period)
    box = [(0.0, period[a]) if emb.periodic[a] else (float(lo[a]), float(hi[a] - lo[a]))
           for a in range(d)]  # fmt: skip
    return np.array([b[0] for b in box] + [b[1] for b in box])


def _cores(cuts, half, lx):
    """The cores' lower bounds along the cut axis (sorted, in [0, lx): lx its period) and
    the tile owning each: seam j (number T + j) owns [cut_j - h_j, cut_j + h_j), strip j
    (number j) the rest of its strip, [cut_j + h_j, cut_{j+1} - h_{j+1})."""
    t = len(cuts)
    lows = np.concatenate([cuts - half, cuts + half])
    owners = np.concatenate([np.arange(t, 2 * t), np.arange(t)])
    lows = lows - np.floor(lows / lx) * lx
    lows = np.where(lows >= lx, lows - lx, lows)
    order = np.argsort(lows, kind="stable")
    return np.ascontiguousarray(lows[order]), owners[order]


def refine_local(pts, w, opt, workers, executor=None) -> Mesh:
    """``knnrefine.refine`` with ``workers`` > 1: refined in strips (slabs in space) by that
    many threads of this process over one index of all points, their meshes stitched
    (``scale/shared.py``), or, given ``executor``, in rounds on its processes, each with a
    copy of its strip's points (``LocalStore``, ``refine_store``).

    Parameters
    ----------
    pts : ndarray (n, 2) or (n, 3)
    w : ndarray (n,) or None
    opt : RunOptions
        Checked (``pipeline.checked``).
    workers : int
    executor : concurrent.futures.Executor, optional

    Returns
    -------
    Mesh
    """
    if executor is None:
        return refine_threads(pts, w, opt, workers)
    store = LocalStore(pts, w, workers, executor)
    try:
        return refine_store(store, opt, workers)
    finally:
        store.close()
