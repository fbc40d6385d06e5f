"""Python side of the engine: owns the flat arrays, takes the initial mesh, runs the kernels.

Everything here is O(1) Python per kernel call; the work happens in the ``kernel``s.
Coordinates are internal: the torus is [0, lx) x [0, ly) with lx, ly <= 1 multiples of the
grid step q (``geometry``).
"""

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import EngineError
from . import refine as R
from . import state as S
from .geometry import FLOOR_BITS, Q
from .index import LEAF_SIZE, STACK_SIZE, build_index, forest_of, points_in
from .initial import initial_grid
from .queue import Q_SIZE, Q_USED, new_queue
from .region import WALK_LOST, insert_points, mark_settled, spatial_order
from .reopen import reopen, reopen_by_balls, set_nearest_from_edges, settle_all
from .state import (
    C_CELL_TESTS,
    C_DISK_TESTS,
    C_ERROR,
    C_FAILED,
    C_MAX_VERTICES,
    C_NT,
    C_NV,
    C_SWEEP_MIN,
    ERRORS,
    N_COUNTERS,
    N_PARAMS,
    NO_REGION,
    P_CLEAN_FLOOR2,
    P_FLOOR2,
    P_GRID,
    P_INFLATE,
    P_K,
    P_LX,
    P_LY,
    P_REGION_H,
    P_REGION_W,
    P_REGION_X0,
    P_REGION_Y0,
    P_TAU2,
    TRIANGLE_FIELDS,
    VERTEX_FIELDS,
    Bookkeeping,
    Probe,
    Queues,
    Scratch,
    TorusMesh,
    grow,
    grown,
)
from .threads import in_chunks, run_all
from .threads import workers as thread_count
from .tile import TileRun
from .triangulation import (
    LINK_SIZE,
    MAX_CAVITY,
    circumcentres,
    set_all_circumcircles,
    set_outradii,
    set_vertex_caches,
)

MAX_DEGREE = 4096  # scratch for a vertex's neighbours; a well-spaced mesh has degree < 20


@dataclass
class RunResult:
    """What a refinement produced, in internal coordinates (views of the engine's arrays)."""

    vxy: np.ndarray  # (m, 2) vertices
    kind: np.ndarray  # (m,) int8, refine.INITIAL ... refine.CLEAN
    tv: np.ndarray  # (2m, 3) triangle corners
    tn: np.ndarray  # (2m, 3) neighbours
    to: np.ndarray  # (2m, 3, 2) corner offsets
    floor_centres: np.ndarray  # (f, 2) centres of the floor circumballs, then floor cells' vertices
    floor_radii2: np.ndarray  # (f,) their squared radii (circumradius; R(v) for a cell)
    floor_balls: int  # how many of them are circumballs
    clean_floor: int  # vertices whose Clean was below the Clean floor
    largest_radius2: float  # the largest squared circumradius
    counters: dict = field(default_factory=dict)
    status: str = "done"


def new_probe():
    """A counting query's working arrays (one per thread that counts)."""
    return Probe(
        hx=np.zeros(MAX_DEGREE),
        hy=np.zeros(MAX_DEGREE),
        hc=np.zeros(MAX_DEGREE),
        stack=np.zeros(STACK_SIZE, np.int64),
        mask=np.zeros(LEAF_SIZE, np.bool_),
    )


class Refinement(TileRun):
    """The state of one kNNRefine run: triangulation, queues, scratch and counters."""

    MIN_CAPACITY = 128  # vertices the arrays have room for at first, at least
    GROWTH = 1.25  # capacity factor when an array runs full
    SWEEP_MIN = 1024  # cells newly queued that make a bulk sweep worthwhile (refine.py)
    SWEEP_PER_THREAD = 4096  # fewer cells than this per thread are swept by one
    BALLS_FROM = 1.0  # new points per triangle above which ``reopen`` tests every circumball

    def __init__(
        self, index, k, lx, ly, tau, min_size, max_vertices, m0=None, grid=Q, expected_vertices=0,
        capacity=None, queued=True, caches=None,
    ):  # fmt: skip
        """index: the counting kd-tree over P in internal coordinates (``build_index``); m0:
        the initial mesh (xy, corners, offsets, neighbours) on the grid step ``grid``, by
        default ``initial.initial_grid(lx, ly)``, or any Delaunay triangulation of the torus
        to go on from (a stitched one: ``scale/shared.py``); expected_vertices: the size
        estimate, which sizes the arrays (``size.estimate``); capacity: the vertices the
        arrays have room for at first instead (``capacity`` >= the mesh's); queued: every
        element queued (else the caller queues: ``queue_unsettled``); caches: m0's triangles'
        squared circumradii and its vertices' d_{M,2}(v)^2 where known (a mask; the others
        are computed; R(v)^2 always comes from these circumradii), or "edges" for a whole
        Delaunay triangulation (a finished run's, continued: ``reopen``), whose vertex caches
        come from its triangles in one pass (``reopen.set_nearest_from_edges``) rather
        than a walk round each vertex. Elements smaller than
        2^14 grid (the resolution floor) or than min_size are never split."""
        self.lx = lx
        self.ly = ly
        self.index = index
        self.time_index = 0.0  # seconds building the index (set by the caller)
        self.threads = None  # threads of a bulk sweep; None: ``threads.workers()``
        self.n = points_in(self.index)
        xy, corners, offsets, neighbours = initial_grid(lx, ly, q=grid)[:4] if m0 is None else m0
        self.grid = grid
        clean_floor = grid * 2.0**FLOOR_BITS
        m0 = xy.shape[0]
        # first sizes: 0.6 of the estimate (an overestimate of up to 1.7x costs nothing),
        # then growth by a quarter; small first sizes keep small runs small
        cap_v = max(self.MIN_CAPACITY, 4 * m0, int(0.6 * expected_vertices))
        if capacity is not None:
            cap_v = max(self.MIN_CAPACITY, m0, int(capacity))
        cap_t = 2 * cap_v
        star = np.zeros(cap_v, np.int32)
        for c in (2, 1, 0):  # a triangle at each vertex, whichever corner it is of them
            star[corners[:, c]] = np.arange(corners.shape[0], dtype=np.int32)
        self.mesh = TorusMesh(
            corners=grown(corners, cap_t),
            neighbours=grown(neighbours, cap_t),
            offsets=grown(offsets, cap_t),
            radius2=np.zeros(cap_t),
            xy=grown(xy, cap_v),
            star=star,
            outradius2=np.zeros(cap_v),
            nearest2=np.zeros(cap_v),
        )
        self.book = Bookkeeping(
            ball_state=np.zeros(cap_t, np.int8),
            kinds=np.zeros(cap_v, np.int8),
            cell_state=np.zeros(cap_v, np.int8),
            flags=np.zeros(cap_v, np.int8),
        )
        self.scratch = Scratch(
            mark=np.zeros(cap_t, np.int32),
            cavity=np.zeros(MAX_CAVITY + 2, np.int32),
            cavity_shift=np.zeros((MAX_CAVITY + 2, 2), np.int64),
            boundary=np.zeros((MAX_CAVITY + 2, 4), np.int32),
            boundary_offsets=np.zeros((MAX_CAVITY + 2, 4), np.int64),
            link=np.zeros((LINK_SIZE, 2), np.int64),
        )
        # a queue keeps room for one insertion's pushes (R.HEADROOM) beyond its entries
        self.queues = Queues(
            balls=new_queue(max(cap_v, corners.shape[0]) + R.HEADROOM),  # queue_all's below
            cells=new_queue(cap_v + R.HEADROOM),
            cleans=new_queue(R.HEADROOM + 256),
        )
        self.probe = new_probe()
        self.sweep_probes = []  # the other sweeping threads' probes, made on first use
        self.cnt = np.zeros(N_COUNTERS, np.int64)
        self.cnt[C_NV] = m0
        self.cnt[C_NT] = corners.shape[0]
        self.cnt[C_MAX_VERTICES] = max_vertices
        self.cnt[C_SWEEP_MIN] = self.SWEEP_MIN
        self.prm = np.zeros(N_PARAMS)
        self.prm[P_LX] = lx
        self.prm[P_LY] = ly
        self.prm[P_TAU2] = tau * tau * (1.0 - 1e-12)
        self.floor = max(float(min_size), clean_floor)  # the Break floor in internal units
        self.prm[P_FLOOR2] = self.floor * self.floor
        self.prm[P_CLEAN_FLOOR2] = clean_floor * clean_floor
        self.prm[P_GRID] = grid
        self.prm[P_K] = k
        self.prm[P_INFLATE] = 1.0 + 1e-9
        self.prm[P_REGION_W] = NO_REGION
        if caches is None:
            set_all_circumcircles(self.mesh, self.prm, corners.shape[0])
            self._set_vertex_caches(np.arange(m0))
        elif isinstance(caches, str) and caches == "edges":  # every vertex's star is whole
            set_all_circumcircles(self.mesh, self.prm, corners.shape[0])
            set_outradii(self.mesh, corners.shape[0], m0)
            set_nearest_from_edges(self.mesh, self.prm, corners.shape[0], m0)
        else:  # a stitched triangulation's, where its tiles knew them (``scale/shared.py``)
            radius2, nearest2, known = caches
            self.mesh.radius2[: corners.shape[0]] = radius2
            set_outradii(self.mesh, corners.shape[0], m0)  # from these radius2, exactly
            self.mesh.nearest2[:m0] = nearest2
            self._set_vertex_caches(np.flatnonzero(~known))
        if queued:
            R.queue_all(self.mesh, self.book, self.queues, self.cnt, self.prm)

    def _set_vertex_caches(self, vertices):
        """R(v)^2 and d_{M,2}(v)^2 of these vertices, on the engine's threads when many."""
        m = len(vertices)
        if m < self.SWEEP_PER_THREAD:
            set_vertex_caches(self.mesh, self.prm, vertices, 0, m, self.probe.hx, self.probe.hy)
            return
        threads = thread_count() if self.threads is None else self.threads
        probes = [new_probe() for _ in range(threads)]
        free = list(range(len(probes)))

        def fill(start, stop):
            j = free.pop()  # one probe per range running at once (list.pop is atomic)
            try:
                set_vertex_caches(self.mesh, self.prm, vertices, start, stop, probes[j].hx,
                                  probes[j].hy)  # fmt: skip
            finally:
                free.append(j)

        in_chunks(fill, m, threads, least=self.SWEEP_PER_THREAD)

    def grow_if_needed(self):
        """Grow, by GROWTH, every array that could overflow during the next insertion: the
        vertex and triangle fields of every structure (``state.VERTEX_FIELDS``,
        ``TRIANGLE_FIELDS``), and a queue's entries when its headroom runs out."""
        nv, nt = self.cnt[C_NV], self.cnt[C_NT]
        cap_v = self.mesh.xy.shape[0]
        if nv + 1 > cap_v:
            grow(self, VERTEX_FIELDS, int(self.GROWTH * cap_v) + 1)
        if nt + 2 > self.mesh.corners.shape[0]:
            grow(self, TRIANGLE_FIELDS, 2 * self.mesh.xy.shape[0])
        self.reserve_queues(R.HEADROOM)

    def reserve_queues(self, entries):
        """Room in every queue for ``entries`` more pushes: a queue short of it grows by
        GROWTH plus HEADROOM, or to what it needs if that is more (a requeue of a whole
        mesh, ``partition.seed``)."""
        queues = {}
        for name in Queues._fields:
            q = getattr(self.queues, name)
            used, size = int(q.scalars[Q_USED]), q.ident.shape[0]
            if used + entries > size:
                n = max(int(self.GROWTH * size) + R.HEADROOM, used + entries)
                for part in ("ident", "aux", "next"):
                    q = q._replace(**{part: grown(getattr(q, part), n)})
            queues[name] = q
        self.queues = Queues(**queues)

    def run(self, deadline=None, progress=None, interrupts=None):
        """Refine to completion, in kernel calls of about 50 ms. Returns a STATUS_* code:
        DONE, MAX_VERTICES, or STEPS when ``deadline`` (a time.perf_counter() value) passed.
        After every call: progress(vertices, queued), then ``interrupts.check()`` (Ctrl-C),
        then the deadline; the next call is sized not to overshoot it."""
        t0 = time.perf_counter()
        steps = 2000
        rate = None  # insertions per second, measured
        while True:
            before = int(self.cnt[C_NV])
            t1 = time.perf_counter()
            status = R.refine_steps(
                self.mesh,
                self.book,
                self.queues,
                self.scratch,
                self.probe,
                self.cnt,
                self.prm,
                self.index,
                steps,
            )
            now = time.perf_counter()
            done = int(self.cnt[C_NV]) - before
            if done > 0:  # calls cut short (GROW) measure the rate too, never inflate it
                rate = done / max(now - t1, 1e-6)
                steps = int(min(max(rate * 0.05, 100), 200000))
            if progress is not None:
                progress(int(self.cnt[C_NV]), self.pending())
            if interrupts is not None:
                interrupts.check()
            if status == S.STATUS_SWEEP:
                status = self._sweep(progress, interrupts, deadline)
            if status == S.STATUS_ERROR:
                code = int(self.cnt[C_ERROR])
                raise EngineError(
                    "refinement stopped on a broken invariant: "
                    f"{ERRORS.get(code, f'unknown error code {code}')} (after "
                    f"{int(self.cnt[C_NV])} vertices); please report it with the input"
                )
            if status in (S.STATUS_DONE, S.STATUS_MAX_VERTICES):
                self.time_refine = time.perf_counter() - t0
                return status
            if status == S.STATUS_GROW:
                self.grow_if_needed()
            if deadline is not None:
                now = time.perf_counter()
                if now >= deadline:
                    self.time_refine = now - t0
                    return S.STATUS_STEPS
                if rate is not None:
                    steps = max(1, min(steps, int(rate * (deadline - now)) + 1))

    def _sweep(self, progress, interrupts, deadline, chunk=50_000):
        """Settle the queued cells in bulk (``refine.sweep_cells``), a chunk per kernel call,
        each chunk split between the engine's threads (``threads.workers()``): the sweep only
        reads the mesh, so the result is the same with any number of threads. Returns
        STATUS_ERROR (with the code in the counters) or STATUS_STEPS."""
        order = R.cells_to_sweep(self.mesh, self.book, self.queues, self.cnt, self.prm)
        most = thread_count() if self.threads is None else self.threads
        threads = min(most, max(1, len(order) // self.SWEEP_PER_THREAD))
        while len(self.sweep_probes) < threads - 1:
            self.sweep_probes.append(new_probe())
        probes = [self.probe] + self.sweep_probes
        for i in range(0, len(order), chunk):
            parts = np.array_split(order[i : i + chunk], threads)
            before = self.cnt.copy()
            counts = [before.copy() for _ in range(threads)]

            def sweep(j, parts=parts, counts=counts):
                return R.sweep_cells(
                    parts[j], self.mesh, self.book, probes[j], counts[j], self.prm, self.index
                )

            codes = run_all(sweep, threads)
            for c in counts:  # what each thread added to the counters
                self.cnt += c - before
            code = min(codes)
            if code < 0:
                self.cnt[C_ERROR] = code
                return S.STATUS_ERROR
            if progress is not None:
                progress(int(self.cnt[C_NV]), self.pending())
            if interrupts is not None:
                interrupts.check()
            if deadline is not None and time.perf_counter() >= deadline:
                break
        return S.STATUS_STEPS

    # -- a tile of a tiled run (``_engine/region.py``; the same methods as ``Refinement3``) --

    @property
    def period(self):
        """The torus' periods, internal units."""
        return np.array([self.lx, self.ly])

    def set_region(self, region):
        """Move only for elements inside ``region`` (x0, y0, w, h) of the torus; None: the
        whole torus again."""
        if region is None:
            self.prm[P_REGION_W] = NO_REGION
            return
        self.prm[P_REGION_X0], self.prm[P_REGION_Y0] = region[0], region[1]
        self.prm[P_REGION_W], self.prm[P_REGION_H] = region[2], region[3]

    # the hooks of ``TileRun``
    _lost = WALK_LOST

    @property
    def positions(self):
        return self.mesh.xy

    @property
    def _tau2(self):
        return self.prm[P_TAU2]

    def _order(self, xy):
        return spatial_order(xy, self.lx, self.ly)

    def _insert_given(self, pts, ids, done):
        return insert_points(pts, ids, done, self.mesh, self.book, self.scratch, self.cnt,
                             self.prm)  # fmt: skip

    def _grow(self):
        self.grow_if_needed()

    def _mark_settled(self, stamps, regions):
        return mark_settled(self.mesh, self.book, self.cnt, self.prm, stamps, regions)

    def requeue(self):
        """Queue every element again, those deferred by another region included."""
        balls = self.book.ball_state[: int(self.cnt[C_NT])]
        balls[balls == S.DEFERRED] = S.UNTESTED
        self.reserve_queues(3 * self.vertices + R.HEADROOM)
        R.queue_all(self.mesh, self.book, self.queues, self.cnt, self.prm)

    def queue_synced(self, ids):
        """Queue what inserting the vertices ``ids`` (a tile's sync between its turns)
        changed: in the plane everything not settled again (``queue_unsettled``; its
        turns after the first are a few percent of a run, space's ``queue_synced3`` only
        what the insertions touched)."""
        self.queue_unsettled()

    def queue_unsettled(self):
        """Queue only what is not settled (a triangulation made of settled parts:
        ``refine.queue_unsettled``), the queues made just large enough for it."""
        nt, nv = int(self.cnt[C_NT]), self.vertices
        balls = self.book.ball_state[:nt]
        open_balls = int(np.count_nonzero((balls == S.UNTESTED) | (balls == S.DEFERRED)))
        need = {"balls": open_balls, "cells": nv, "cleans": nv}  # after the kernel's clear
        queues = {}
        for name in Queues._fields:
            q = getattr(self.queues, name)
            n = need[name] + R.HEADROOM
            if q.ident.shape[0] < n:
                q = q._replace(
                    **{part: grown(getattr(q, part), n) for part in ("ident", "aux", "next")}
                )
            queues[name] = q
        self.queues = Queues(**queues)
        R.queue_unsettled(self.mesh, self.book, self.queues, self.cnt, self.prm)

    def reopen(self, xy, kinds):
        """Continue a finished run's mesh (this one's ``m0``, its vertices' ``kinds``) with
        more points, the index holding them all: every element settled but those the points
        ``xy`` (internal coordinates) reach, which are queued (``_engine/reopen.py``).
        Returns the triangles reopened (every one when a cavity was out of reach)."""
        nv = self.vertices
        self.book.kinds[:nv] = kinds
        settle_all(self.book, self.cnt, nv)
        reopened = 0
        nt = int(self.cnt[C_NT])
        if len(xy) > self.BALLS_FROM * nt:  # many points a triangle: test each ball
            new = forest_of(build_index(np.array(xy, dtype=np.float64)))
            stack = np.empty(STACK_SIZE, np.int64)
            reopened = reopen_by_balls(self.mesh, self.book, self.prm, new, nt, stack)
        elif len(xy):
            xy = np.ascontiguousarray(xy[spatial_order(xy, self.lx, self.ly)])
            reopened = reopen(xy, self.mesh, self.book, self.scratch, self.cnt, self.prm)
            if reopened < 0:  # a broken walk or a huge cavity: look at everything again
                self.book.ball_state[:nt] = S.UNTESTED
                self.book.cell_state[:nv] = S.UNTESTED
                reopened = nt
        self.queue_unsettled()
        return int(reopened)

    def pending(self):
        """Queued candidates (an upper bound on the work left, not a promise)."""
        return int(sum(q.scalars[Q_SIZE] for q in self.queues))

    def outradii(self):
        """An upper bound on R(v) (the distance from v to its Voronoi cell's farthest
        corner) for every vertex, inf where the cache does not know it: the cache is R(v)
        itself, -1 while unknown."""
        r2 = self.mesh.outradius2[: self.vertices]
        return np.sqrt(np.where(r2 < 0.0, np.inf, r2))

    @property
    def vertices(self):
        return int(self.cnt[C_NV])

    def counters(self):
        """Moves of each kind (from the vertices' kinds) and the counting tests so far."""
        nv = self.vertices
        kinds = np.bincount(self.book.kinds[:nv], minlength=len(S.KIND_NAMES))
        return {
            "moves": {name: int(kinds[i]) for i, name in enumerate(S.KIND_NAMES)},
            "disk_tests": int(self.cnt[C_DISK_TESTS]),
            "cell_tests": int(self.cnt[C_CELL_TESTS]),
            "failed_insertions": int(self.cnt[C_FAILED]),
        }

    def result(self):
        """The mesh as views of the engine's arrays, which are given up: the queues, scratch
        and caches are freed here, before the caller assembles its copies."""
        nv, nt = self.vertices, int(self.cnt[C_NT])
        counters = self.counters()
        mesh, book = self.mesh, self.book
        floor_t = np.flatnonzero(book.ball_state[:nt] == S.FLOOR)
        floor_v = np.flatnonzero(book.cell_state[:nv] == S.FLOOR)
        centres = circumcentres(mesh, self.prm, floor_t)
        res = RunResult(
            vxy=mesh.xy[:nv],
            kind=book.kinds[:nv],
            tv=mesh.corners[:nt],
            tn=mesh.neighbours[:nt],
            to=mesh.offsets[:nt],
            floor_centres=np.concatenate([centres[:, :2], mesh.xy[floor_v]]),
            floor_radii2=np.concatenate([centres[:, 2], mesh.outradius2[floor_v]]),
            floor_balls=len(floor_t),
            clean_floor=int(np.count_nonzero(book.flags[:nv] & S.CLEAN_BELOW_FLOOR)),
            largest_radius2=float(mesh.radius2[:nt].max()) if nt else 0.0,
            counters=counters,
        )
        self.mesh = self.book = self.queues = self.scratch = self.probe = None
        self.sweep_probes = []
        return res
