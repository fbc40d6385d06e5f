"""The 3-D refinement's Python side (``driver.py`` in the plane): builds the state, calls
``refine3.refine_steps3`` in bounded steps (progress, deadline, Ctrl-C between them), grows
the arrays when the kernel asks, and returns the final triangulation."""

import numpy as np

from ..errors import EngineError
from .geometry import FLOOR_BITS, Q
from .index import STACK_SIZE, forest_of
from .index3 import build_index3
from .initial import GRIDS3, grid_shape3, initial_grid3, peel_order
from .interrupt import Interrupts
from .queue import Q_SIZE, new_queue
from .refine3 import (
    HEADROOM3,
    N_PARAMS3,
    NO_SWEEPS,
    P3_CLEAN_FLOOR2,
    P3_FLOOR2,
    P3_GRID,
    P3_INFLATE,
    P3_K,
    P3_REGION,
    P3_REGION_W,
    P3_TAU2,
    queue_all3,
    queue_seeded3,
    queue_synced3,
    refine_steps3,
    sweep_balls3,
    sweep_cells3,
)
from .region3 import WALK_LOST3, insert_points3, mark_settled3, spatial_order3
from .reopen import reopen3, reopen_by_balls3, settle_all
from .state import (
    C_BALLS_SWEPT,
    C_CELL_TESTS,
    C_DISK_TESTS,
    C_ERROR,
    C_FAILED,
    C_MAX_VERTICES,
    C_NT,
    C_NV,
    C_STAMP,
    C_SWEEP_CELLS,
    ERRORS,
    FLOOR,
    KIND_NAMES,
    NO_REGION,
    STATUS_DONE,
    STATUS_ERROR,
    STATUS_GROW,
    STATUS_MAX_VERTICES,
    STATUS_STEPS,
    STATUS_SWEEP,
    UNTESTED,
    Bookkeeping,
    Probe3,
    Queues,
    grow,
    mapped,
)
from .threads import in_chunks, workers
from .tile import TileRun
from .triangulation3 import new_torus3, refresh_outradii3, unpack_offsets

STEPS = 20_000  # insertions per kernel call
# the tetrahedra's marks are 32-bit stamps: between kernel calls, past this many stamps,
# they start again (a call uses far fewer than 2^31 - STAMP_LIMIT)
STAMP_LIMIT = 2**30
VERTEX_FIELDS3 = (
    ("mesh", "xyz"),
    ("mesh", "star"),
    ("mesh", "outradius2"),
    ("mesh", "nearest2"),
    ("book", "kinds"),
    ("book", "cell_state"),
    ("book", "flags"),
)
TETRAHEDRON_FIELDS3 = (
    ("mesh", "corners"),
    ("mesh", "neighbours"),
    ("mesh", "offsets"),
    ("mesh", "radius2"),
    ("book", "ball_state"),
    ("scratch", "mark"),
)


GROWTH = 8  # arrays grow by 1/GROWTH of their size (+ 4096): the slack left at the end


def _grown(cap):
    return cap + cap // GROWTH + 4096


class Refinement3(TileRun):
    """One 3-D run on the torus of ``period`` (internal units, multiples of the grid step q,
    a power of two >= Q: ``embedding.Embedding.grid``) over the points of ``index``
    (``index3.build_index3``, internal coordinates in [0, period))."""

    # circumballs swept in bulk (``refine3.sweep_balls3``) on this many threads (None:
    # ``threads.workers()``); with one thread there is no sweep (a tile of a tiled run,
    # itself one of several threads, sets 1)
    threads = None
    SWEEP_SLOTS = 16384  # the least slots a thread sweeps at once
    SAMPLE_STRIDE = 16  # a sweep counts every 16th slot first ...
    SWEEP_GOOD = 0.95  # ... and the rest if this share of those held < k
    BALLS_FROM = 0.25  # new points per tetrahedron above which ``reopen`` tests every ball

    def __init__(
        self, index, period, k, tau, floor, max_vertices, grid, q=Q, queued=True, capacity=None
    ):
        self.period = np.asarray(period, float)
        self.index = index  # a PointForest (``index.forest_of``)
        self.time_index = 0.0  # seconds of the setup (set by the caller), as in the plane
        self.time_refine = 0.0  # seconds in ``run``
        estimate = max(4096, len(grid[0]) * 4) if capacity is None else capacity
        self.mesh, self.scratch, self.cnt = new_torus3(self.period, grid, estimate, 7 * estimate)
        t_cap = self.mesh.corners.shape[0]
        v_cap = self.mesh.xyz.shape[0]
        self.book = Bookkeeping(
            ball_state=mapped((t_cap,), np.int8),
            kinds=mapped((v_cap,), np.int8),
            cell_state=mapped((v_cap,), np.int8),
            flags=mapped((v_cap,), np.int8),
        )
        balls = int(self.cnt[C_NT]) + v_cap // 2 + 4 * HEADROOM3
        self.queues = Queues(
            balls=new_queue(balls, mapped),
            cells=new_queue(v_cap // 2 + 2 * HEADROOM3, mapped),
            cleans=new_queue(v_cap // 2 + 2 * HEADROOM3, mapped),
        )
        self.probe = Probe3(
            h=np.zeros((1024, 3)),
            ids=np.zeros(1024, np.int64),
            hc=np.zeros(1024),
            stack=np.zeros(128, np.int64),
        )
        prm = np.zeros(N_PARAMS3)
        prm[:3] = self.period
        prm[P3_TAU2] = tau * tau * (1.0 - 1e-12)
        prm[P3_FLOOR2] = max(floor, 2.0**FLOOR_BITS * q) ** 2
        prm[P3_CLEAN_FLOOR2] = (2.0**FLOOR_BITS * q) ** 2
        prm[P3_INFLATE] = 1.0 + 1e-9
        prm[P3_GRID] = q
        prm[P3_K] = float(k)
        prm[P3_REGION_W] = NO_REGION
        self.prm = prm
        self.cnt[C_MAX_VERTICES] = int(max_vertices)
        if queued:  # else the caller sets the states and queues (``queue_unsettled``)
            queue_all3(self.mesh, self.book, self.queues, self.scratch, self.cnt, self.prm)

    def run(self, deadline=None, progress=None, interrupts=None):
        """Refine until done, the vertex budget, or the deadline (a ``time.perf_counter()``
        value); returns the status. Kernel calls are sized to last about 50 ms; after every
        one (growth included): progress(vertices, queued), Ctrl-C (``interrupts``, or a handler of
        its own), then the deadline."""
        import contextlib
        import time

        steps = min(2000, STEPS)
        t0 = time.perf_counter()
        with contextlib.ExitStack() as stack:
            if interrupts is None:
                interrupts = stack.enter_context(Interrupts())
            while True:
                if self._sweep_threads() < 2:
                    self.cnt[C_BALLS_SWEPT] = NO_SWEEPS
                before, t1 = int(self.cnt[C_NV]), time.perf_counter()
                status = refine_steps3(
                    self.mesh, self.book, self.queues, self.scratch, self.probe, self.cnt,
                    self.prm, self.index, steps,
                )  # fmt: skip
                now = time.perf_counter()
                done = int(self.cnt[C_NV]) - before
                if done > 0:  # calls cut short (GROW) measure the rate too
                    rate = done / max(now - t1, 1e-6)
                    steps = int(min(max(rate * 0.05, 100), STEPS))
                if self.cnt[C_STAMP] > STAMP_LIMIT:
                    self._restart_stamps()
                # a sweep asked for before any insertion: the deadline waits for a call that
                # makes some (a run always moves on)
                idle = status == STATUS_SWEEP and done == 0
                if status == STATUS_SWEEP:
                    status = self._sweep()
                if progress is not None:
                    progress(int(self.cnt[C_NV]), self.pending())
                if status == STATUS_ERROR:
                    code = int(self.cnt[C_ERROR])
                    raise EngineError(
                        "refinement in space stopped on a broken invariant: "
                        f"{ERRORS.get(code, f'engine error {code}')} (after "
                        f"{int(self.cnt[C_NV])} vertices); please report it with the input"
                    )
                if status in (STATUS_DONE, STATUS_MAX_VERTICES):
                    self.time_refine = time.perf_counter() - t0
                    return status
                interrupts.check()
                if status == STATUS_GROW:
                    self._grow()
                if not idle and deadline is not None and time.perf_counter() > deadline:
                    self.time_refine = time.perf_counter() - t0
                    return STATUS_STEPS

    def _sweep_threads(self):
        return workers() if self.threads is None else int(self.threads)

    def _sweep(self):
        """Count in bulk what ``refine_steps3`` asked for: the untested circumballs of the
        class just reached (``sweep_balls3``: every SAMPLE_STRIDE-th slot first, the rest
        only if SWEEP_GOOD of those held < k, for a class whose tetrahedra the coming Breaks
        would mostly destroy is not worth counting ahead), or the cells queued since the
        last sweep (``sweep_cells3``); in ranges over the engine's threads (Ctrl-C waits
        for the ranges running only)."""
        threads = self._sweep_threads()
        if self.cnt[C_SWEEP_CELLS]:

            def cells(start, stop):
                return sweep_cells3(self.mesh, self.book, self.prm, self.index, start, stop)

            parts = in_chunks(cells, self.vertices, threads, self.SWEEP_SLOTS // 8)
            if min(parts) < 0:
                self.cnt[C_ERROR] = min(parts)
                return STATUS_ERROR
            self.cnt[C_CELL_TESTS] += sum(parts)
            return STATUS_STEPS
        cls = int(self.cnt[C_BALLS_SWEPT]) - 1
        made = good = 0
        for stride in (self.SAMPLE_STRIDE, 1):

            def balls(start, stop, stride=stride):
                return sweep_balls3(self.mesh, self.book, self.prm, self.index, cls, start,
                                    stop, stride)  # fmt: skip

            parts = in_chunks(balls, int(self.cnt[C_NT]), threads, self.SWEEP_SLOTS)
            made += sum(p[0] for p in parts)
            good += sum(p[1] for p in parts)
            self.cnt[C_DISK_TESTS] += sum(p[0] for p in parts)
            if good < self.SWEEP_GOOD * made:
                break
        return STATUS_STEPS

    def pending(self):
        """Queued candidates (an upper bound on the work left, not a promise)."""
        return int(sum(q.scalars[Q_SIZE] for q in self.queues))

    def reopen(self, xyz, kinds):
        """Continue a finished run's mesh (this one's ``grid``, its vertices' ``kinds``)
        with more points, the index holding them all: every element settled but those the
        points ``xyz`` (internal coordinates) reach, which are queued
        (``_engine/reopen.py``). Returns the tetrahedra reopened (every one when a cavity
        was out of reach)."""
        nv, nt = self.vertices, int(self.cnt[C_NT])
        self.book.kinds[:nv] = kinds
        settle_all(self.book, self.cnt, nv)
        reopened = 0
        if len(xyz) > self.BALLS_FROM * nt:  # many points a tetrahedron: test each ball
            new = forest_of(build_index3(xyz))
            stack = np.empty(STACK_SIZE, np.int64)
            reopened = reopen_by_balls3(self.mesh, self.book, self.scratch, new, nt, self.period,
                                        stack)  # fmt: skip
        elif len(xyz):
            xyz = np.ascontiguousarray(xyz[spatial_order3(np.ascontiguousarray(xyz),
                                                          self.period)])  # fmt: skip
            reopened = reopen3(xyz, self.mesh, self.book, self.scratch, self.cnt, self.period)
            if reopened < 0:  # a broken walk or a huge cavity: look at everything again
                self.book.ball_state[:nt] = UNTESTED
                self.book.cell_state[:nv] = UNTESTED
                reopened = nt
            if self.cnt[C_STAMP] > STAMP_LIMIT:
                self._restart_stamps()
        self.requeue()
        return int(reopened)

    def outradii(self):
        """An upper bound on R(v) (the distance from v to its Voronoi cell's farthest
        corner) for every vertex: the cache holds R(v) or, negated, a bound on it
        (``triangulation3``)."""
        return np.sqrt(np.abs(self.mesh.outradius2[: self.vertices]))

    # -- a tile of a tiled run (``_engine/region3.py``; the same methods as ``Refinement``) --

    @property
    def vertices(self):
        return int(self.cnt[C_NV])

    def set_region(self, region):
        """Move only for elements inside ``region`` (corner (3), widths (3)) of the torus;
        None: the whole torus again."""
        if region is None:
            self.prm[P3_REGION_W] = NO_REGION
            return
        self.prm[P3_REGION : P3_REGION + 3] = region[:3]
        self.prm[P3_REGION_W : P3_REGION_W + 3] = region[3:]

    def _fresh_queues(self):
        """Empty queues with room for every tetrahedron and vertex (and the headroom)."""
        nt, nv = int(self.cnt[C_NT]), self.vertices
        size = max(self.mesh.xyz.shape[0], nv) + 4 * HEADROOM3
        self.queues = Queues(
            balls=new_queue(nt + size, mapped),
            cells=new_queue(size, mapped),
            cleans=new_queue(size, mapped),
        )

    # the hooks of ``TileRun``
    _lost = WALK_LOST3

    @property
    def positions(self):
        return self.mesh.xyz

    @property
    def _tau2(self):
        return self.prm[P3_TAU2]

    def _order(self, xyz):
        return spatial_order3(xyz, self.period)

    def _insert_given(self, pts, ids, done):
        done = insert_points3(pts, ids, done, self.mesh, self.book, self.scratch, self.cnt,
                              self.period)  # fmt: skip
        if self.cnt[C_STAMP] > STAMP_LIMIT:
            self._restart_stamps()
        return done

    def _mark_settled(self, stamps, regions):
        balls, cells = mark_settled3(self.mesh, self.book, self.scratch, self.cnt, self.prm,
                                     stamps, regions)  # fmt: skip
        if balls < 0:
            raise EngineError("a vertex has more neighbours than a tile's scratch holds")
        return balls, cells

    def unsettled(self):
        """``TileRun.unsettled``, on R(v) itself (the run keeps bounds: ``triangulation3``)."""
        refresh_outradii3(self.mesh, self.scratch, self.cnt, self.vertices)
        return super().unsettled()

    def requeue(self):
        """Queue every element not settled again, those deferred by a region included."""
        self._fresh_queues()
        queue_seeded3(self.mesh, self.book, self.queues, self.scratch, self.cnt, self.prm)

    queue_unsettled = requeue  # a triangulation of settled parts (a stitched one): the same

    def queue_synced(self, ids):
        """Queue only what inserting the vertices ``ids`` into this finished run changed
        (``refine3.queue_synced3``; a tile's sync between its turns)."""
        ids = np.ascontiguousarray(ids, np.int64)
        nv = self.vertices  # a vertex is at most once in the cells' and Cleans' queues
        for name, need in (("balls", len(ids)), ("cells", nv), ("cleans", nv)):
            q = getattr(self.queues, name)
            cap = q.ident.shape[0]
            size = int(q.scalars[Q_SIZE]) + need + 4 * HEADROOM3
            if size > cap:
                del q
                parts = [("queues", name, part) for part in ("ident", "aux", "next")]
                grow(self, parts, _grown(size), in_place=True)
        if queue_synced3(self.mesh, self.book, self.queues, self.scratch, self.cnt, self.prm,
                         ids) < 0:  # fmt: skip
            raise EngineError("a vertex's star overflowed the walk's stack")

    def counters(self):
        """Moves of each kind and the counting tests so far (``Refinement.counters``)."""
        return {
            "moves": self.progress()["moves"],
            "disk_tests": int(self.cnt[C_DISK_TESTS]),
            "cell_tests": int(self.cnt[C_CELL_TESTS]),
            "failed_insertions": int(self.cnt[C_FAILED]),
        }

    def progress(self):
        """How far the run got: its vertices and how each came (``refine.KIND_NAMES``)."""
        nv = int(self.cnt[C_NV])
        kinds = np.bincount(self.book.kinds[:nv], minlength=len(KIND_NAMES))
        return {"vertices": nv, "moves": {name: int(kinds[i]) for i, name in enumerate(KIND_NAMES)}}

    def _restart_stamps(self):
        """Stamps start again at 1: every mark but the free slots' (-1) and every link
        table entry (keyed by its insertion's stamp) cleared."""
        mark = self.scratch.mark
        mark[mark != -1] = 0
        self.scratch.link[:, 0] = 0
        self.cnt[C_STAMP] = 0

    def _grow(self):
        """Each array that could overflow in the next insertion grows by ``GROWTH``; the mesh
        made does not depend on when (nothing in the run refers to a capacity)."""
        if self.cnt[C_NV] + 1 > self.mesh.xyz.shape[0]:
            grow(self, VERTEX_FIELDS3, _grown(self.mesh.xyz.shape[0]), in_place=True)
        if self.cnt[C_NT] + 2 * HEADROOM3 > self.mesh.corners.shape[0]:
            grow(self, TETRAHEDRON_FIELDS3, _grown(self.mesh.corners.shape[0]), in_place=True)
        for name in ("balls", "cells", "cleans"):
            q = getattr(self.queues, name)
            cap = q.ident.shape[0]
            if q.scalars[Q_SIZE] + 4 * HEADROOM3 > cap:
                del q
                parts = [("queues", name, part) for part in ("ident", "aux", "next")]
                grow(self, parts, _grown(cap), in_place=True)

    def take_result(self):
        """(xyz (m, 3), corners (t, 4), offsets (t, 4, 3), kinds (m,), counters, floor,
        neighbours (t, 4)),
        consuming the run: the index, scratch, queues and bookkeeping are let go first, and
        each mesh array as soon as its trimmed copy exists, so that the copies never sit
        beside the whole state (the peak memory of a run). ``floor``: (centres (f, 3),
        squared radii (f,), circumballs among them) of the elements left below the floor
        holding k points: circumballs, then the balls of radius R(v) about cells' vertices."""
        nv, nt = int(self.cnt[C_NV]), int(self.cnt[C_NT])
        cnt = self.cnt.copy()
        kinds = self.book.kinds[:nv].copy()
        self.largest_radius2 = float(self.mesh.radius2[:nt].max()) if nt else 0.0
        balls = np.flatnonzero(self.book.ball_state[:nt] == FLOOR)
        cells = np.flatnonzero(self.book.cell_state[:nv] == FLOOR)
        c = self.mesh.xyz[self.mesh.corners[balls]] + unpack_offsets(
            self.mesh.offsets[balls]
        ) * self.period  # fmt: skip
        floor = (
            np.concatenate([circumcentres3(c), self.mesh.xyz[cells]]) % self.period,
            np.concatenate([self.mesh.radius2[balls], np.abs(self.mesh.outradius2[cells])]),
            len(balls),
        )
        arrays = self.mesh._asdict()
        self.mesh = self.book = self.queues = self.scratch = self.probe = self.index = None
        for name in ("radius2", "star", "outradius2", "nearest2"):
            del arrays[name]
        xyz = arrays.pop("xyz")[:nv].copy()
        corners = arrays.pop("corners")[:nt].copy()
        offsets = unpack_offsets(arrays.pop("offsets")[:nt])
        neighbours = arrays.pop("neighbours")[:nt].copy()
        return xyz, corners, offsets, kinds, cnt, floor, neighbours


def circumcentres3(c):
    """The circumcentres of the tetrahedra with corners c (t, 4, 3)."""
    if len(c) == 0:
        return np.zeros((0, 3))
    m = c[:, 1:] - c[:, :1]
    rhs = 0.5 * (m**2).sum(axis=2)
    return c[:, 0] + np.linalg.solve(m, rhs[..., None])[..., 0]


def choose_grid3(period, holds, factor, q=Q, max_vertices=None, check=None, cache=None):
    """The first candidate M0 (``initial.GRIDS3``, finest first) whose vertices can be
    ordered so that each u has d_{P,k}(u) <= factor * lambda_u (Lemma 2's precondition,
    factor = K - 1: ``initial.reach_factor``; the order is found by peeling,
    ``initial.peel_order``): ``holds(x, r)`` says whether the closed ball of radius r about
    each x holds k points. Candidates with more than ``max_vertices`` vertices are skipped
    (never built); ``check()`` runs between candidates and peeling rounds (deadline,
    Ctrl-C); ``cache`` (a dict) keeps the candidates built, for a caller that asks again.
    None when no candidate passes."""
    cache = {} if cache is None else cache
    for per, jitter, shift in GRIDS3:
        if max_vertices is not None and int(np.prod(grid_shape3(period, per))) > max_vertices:
            continue
        key = (per, jitter, shift)
        if key not in cache:
            cache[key] = initial_grid3(period, per, jitter, shift, q, check)
            if check is not None:
                check()
        grid = cache[key]
        if grid is None:
            continue

        def passes(x, lam):
            # conservative: the reach is shortened by a relative 1e-9 against rounding
            if check is not None:
                check()
            return holds(x, factor * lam * (1.0 - 1e-9))

        if peel_order(grid[0], grid[4], period, passes)[0] is not None:
            return grid
    return None
