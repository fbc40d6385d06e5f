"""``knnrefine.refine`` for points in space ((n, 3) points, a box of six numbers): the
engine's 3-D run (``_engine/driver3.py``) behind the same options as in the plane. Along
non-periodic axes the box is embedded in a longer torus, as in the plane
(``_engine/embedding.py``), and the mesh unfolded back (``embedding.unfold``)."""

import math
import time

import numpy as np
from scipy.spatial import cKDTree

from ..._engine import ahead, size
from ..._engine.driver3 import Refinement3, choose_grid3
from ..._engine.embedding import Embedding, diameter, unfold
from ..._engine.geometry import FLOOR_BITS
from ..._engine.index import PointIndex
from ..._engine.index3 import build_index3, grow_forest3, holds_k_within3, merge_index3
from ..._engine.initial import GRIDS3, grid_shape3, largest_passing, reach_factor, refusal_message
from ..._engine.interrupt import Interrupts
from ..._engine.state import (
    C_CELL_TESTS,
    C_DISK_TESTS,
    C_FAILED,
    C_MAX_VERTICES,
    C_NV,
    STATUS_DONE,
    STATUS_MAX_VERTICES,
)
from ..._metric import BoxMetric, held_in_balls, points_in_balls, weighted_kth
from ..._options import Progress, RunOptions, check_box_run, vertex_budget, warn_floor
from ...errors import BudgetError, InputError
from ...mesh import Mesh, Stats, Torus, moves_of
from ..box import continued_index, start_embedding, start_mesh


def holds_k(index, x, reach, k, period):
    """Whether the closed ball of radius ``reach`` about each x holds >= k of the index's
    points, or weight k for weighted ones (the index answers below half the shortest period;
    beyond it, a periodic kd-tree over its points, built only then, counts each point once,
    at its nearest image)."""
    reach = np.asarray(reach, float)
    out = np.zeros(len(x), bool)
    small = reach < 0.5 * period.min() * (1.0 - 1e-9)
    out[small] = holds_k_within3(index, x[small], reach[small] ** 2, float(k), period)
    if not small.all():
        weights = index.pts[:, 3] if len(index.weight) else None
        tree = cKDTree(index.pts[:, :3], boxsize=period)
        far = ~small
        out[far] = held_in_balls(tree, weights, x[far] % period, reach[far]) >= k
    return out


def _reach(pts, box, per, k, weights=None):
    """An upper bound on max d_{P,k} over the box in its own metric: d_{P,k} (for weighted
    points the least radius holding weight k) at the centres of 16^3 cells plus half a
    cell's diagonal (d_{P,k} is 1-Lipschitz)."""
    g = 16
    lo, hi = np.array(box[:3]), np.array(box[3:])
    cell = (hi - lo) / g
    axes = [lo[a] + (np.arange(g) + 0.5) * cell[a] for a in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    metric = BoxMetric(box, per)
    if weights is None:
        far = metric.kth(pts, centres, k)
    else:
        far = weighted_kth(metric.tree(pts), weights, metric.frame(centres), k, -1)
    return float(far.max() + 0.5 * np.linalg.norm(cell))


LIMITS_EFFORT3 = 300_000  # initial vertices above which a refusal skips the limits search


class Start:
    """Where a run in space starts (as the plane's): the embedding torus, the
    counting index over the points in it, and an initial mesh that satisfies Lemma 2's
    precondition. The default torus (a margin of 1.05 x the box's diameter along
    non-periodic axes) first, then, as in the plane, 1.05 x a bound on max d_Pk over the box
    and 2, 4 and 10 diameters; a torus whose shortest period is the default's and that is no
    smaller is skipped (its initial meshes have the same spacing and only more vertices far
    from the data, where d_Pk is larger). Candidates beyond the vertex budget are never
    built; indexes and candidates are kept per torus (the refusal asks again); the deadline
    and Ctrl-C are checked between every step."""

    def __init__(self, pts, opt, budget, interrupts, weights=None):
        self.pts, self.box, self.per, self.budget = pts, opt.box, opt.periodic, budget
        self.weights = weights
        self.opt, self.interrupts = opt, interrupts
        self.tori = {}  # reach -> (embedding, index, candidate cache)
        self.reach_of_k = {}

    def check(self):
        self.interrupts.check()
        self.opt.past("choosing the initial mesh")

    def torus(self, reach=None):
        if reach not in self.tori:
            emb = Embedding.make(self.box, self.per, reach)
            index = build_index3(emb.to_internal(self.pts), copy=False, weights=self.weights)
            self.check()
            self.tori[reach] = emb, index, {}
        return self.tori[reach]

    def _reaches(self, k):
        yield None
        if all(self.per):
            return
        if k not in self.reach_of_k:  # the data bound costs a kd-tree: only when asked
            self.reach_of_k[k] = _reach(self.pts, self.box, self.per, k, self.weights)
            self.check()
        diam = diameter(self.box, self.per)
        default = np.array(Embedding.make(self.box, self.per).period_internal)
        for reach in (self.reach_of_k[k], 2.0 * diam, 4.0 * diam, 10.0 * diam):
            period = np.array(Embedding.make(self.box, self.per, reach).period_internal)
            if period.min() == default.min() and (period >= default).all():
                continue
            yield reach

    def find(self, k, factor):
        """(embedding, index, M0) for the first torus that works, or None."""
        for reach in self._reaches(k):
            emb = Embedding.make(self.box, self.per, reach)
            if min(int(np.prod(grid_shape3(emb.period_internal, g[0]))) for g in GRIDS3) > (
                self.budget
            ):
                continue
            emb, index, cache = self.torus(reach)
            period = np.array(emb.period_internal)

            def holds(x, r, index=index, period=period):
                return holds_k(index, x, r, k, period)

            grid = choose_grid3(period, holds, factor, emb.grid, self.budget, self.check, cache)
            if grid is not None:
                return emb, index, grid
        return None

    def release(self):
        """Let the indexes and candidates go (the run keeps the one it uses)."""
        self.tori = {}

    def refusal(self, k, tau):
        """The message for an input no torus can start: what failed and what would work."""
        factor = reach_factor(tau)
        effort = sum(
            int(
                np.prod(grid_shape3(Embedding.make(self.box, self.per, r).period_internal, g[0]))
            )  # fmt: skip
            for r in self._reaches(k)
            for g in GRIDS3
        )
        k_max, f_min = (
            largest_passing(lambda kk, f: self.find(kk, f) is not None, k, factor)
            if effort <= LIMITS_EFFORT3
            else (None, None)
        )
        emb = Embedding.make(self.box, self.per)
        return refusal_message(len(self.pts), k, tau, emb, k_max, f_min)


def _points_under_floor(points, floor, emb, n):
    """How many input points lie in a floor element (``Refinement3.take_result``): a
    circumball, or the ball of radius R(v) about a cell's vertex, that holds >= k points
    below the floor; 0 without any (the points are not asked for, no kd-tree is built)."""
    centres, radii2, _ = floor
    if len(radii2) == 0:
        return 0
    period = np.array(emb.period_internal)
    tree = cKDTree(emb.to_internal(points()) % period, boxsize=period)
    return points_in_balls(tree, centres % period, np.sqrt(radii2))


def checked(points, weights, **asked) -> tuple[np.ndarray, np.ndarray | None, RunOptions]:
    """The points (n, 3), weights and options of a run in space, checked before any work
    (``options.check_box_run``; ``asked`` as ``knnrefine.refine`` takes them)."""
    return check_box_run(points, weights, 3, **asked)


def refine(pts: np.ndarray, w: np.ndarray | None, opt: RunOptions) -> Mesh:
    """kNNRefine in a box of three dimensions (``knnrefine.refine`` with (n, 3) points, its
    its points, their weights or None and its options checked by ``checked``):
    a ``Mesh`` whose vertices M satisfy
    alpha d_{P,k} <= d_{M,2} <= beta d_{P,k} in the box, tau-well-spaced, no Voronoi cell
    and no closed circumball holding k points (checked by ``certify``). As in the plane:
    an initial mesh that cannot fit is refused before any work (``RunOptions.check``),
    time_limit and Ctrl-C hold during the setup too, a refusal names the largest k and tau
    that would certify, and a FloorWarning says when most points lie below the floor."""
    if opt.start is not None:
        return _continued(pts, w, opt)
    k, tau, min_size = opt.k, opt.tau, opt.min_size
    report = Progress(opt.progress)
    budget = opt.start_budget(len(pts))
    with ahead.compiling("space", report.compiling), Interrupts() as interrupts:
        start = Start(pts, opt, budget, interrupts, w)
        found = start.find(k, reach_factor(tau))
        if found is None:
            raise InputError(start.refusal(k, tau))
        emb, run_index, grid = found
        del found  # the index must go with the run or the mesh, not live on in this tuple
        kept = PointIndex(emb, run_index, PointIndex.fingerprint_of(pts, w), merge_index3)
        start.release()
        opt.past("setting up")
        floor = max(min_size * emb.scale, emb.grid * 2.0**FLOOR_BITS)
        lo, hi = emb.box_internal()
        estimated = size.estimate3(run_index, k, floor, np.array(emb.period_internal),
                                   float(np.prod(np.asarray(hi) - np.asarray(lo))))[0]  # fmt: skip
        budget = vertex_budget(estimated, opt, len(grid[0]) if len(grid) else 0, len(pts))
        run = Refinement3(run_index, emb.period_internal, k, tau, min_size * emb.scale, budget,
                          grid, emb.grid)  # fmt: skip
        del run_index, grid
        run.time_index = time.perf_counter() - opt.t_start
        status = run.run(opt.deadline, report.refining, interrupts)
    total = None if w is None else math.fsum(w)
    return finish(run, status, emb, opt, n=len(pts), weight=total, points=lambda: pts,
                  report=report, estimated=estimated, budget=budget, initial=0,
                  kept=kept)  # fmt: skip


def _continued(pts, w, opt):
    """A run continued from the mesh ``opt.start`` with the new points ``pts`` and weights
    ``w`` (all of them: ``opt.given``), as in the plane: its torus triangulation taken as it
    is, every element settled but those the new points reach (``Refinement3.reopen``), then
    refined on."""
    start, new_pts, new_w = opt.start, pts, w
    pts, w = opt.given, opt.given_weights  # every point, the start's first
    n, n0 = len(pts), int(start.stats.n)
    report = Progress(opt.progress)
    with ahead.compiling("space", report.compiling), Interrupts() as interrupts:
        t0 = time.perf_counter()
        emb = start_embedding(start)
        new = emb.to_internal(new_pts)
        index = continued_index(start, emb, pts, w, new, new_w, grow_forest3,
                                lambda x, weights: build_index3(x, copy=False,
                                                                weights=weights))  # fmt: skip
        interrupts.check()
        run, expected, budget, reopened = continue_run(start, emb, index, new, opt, n)
        run.time_index = time.perf_counter() - t0
        opt.past("setting up")
        status = run.run(opt.deadline, report.refining, interrupts)
        kept = PointIndex(emb, index, lambda: PointIndex.fingerprint_of(pts, w), merge_index3)
        del index
    total = None if w is None else math.fsum(w)
    mesh = finish(run, status, emb, opt, n=n, weight=total, points=lambda: pts, report=report,
                  estimated=expected, budget=budget, initial=0, kept=kept)  # fmt: skip
    mesh.stats.continued = {"points": n - n0, "from_vertices": len(start.torus.vertices),
                            "reopened": reopened}  # fmt: skip
    return mesh


def continue_run(start, emb, index, new, opt, n):
    """The plane's ``continue_run`` in space: (run, expected vertices, vertex budget,
    tetrahedra reopened) of ``n`` points continued from ``start``, counting with ``index``,
    every element settled but those the new points ``new`` (internal coordinates) and the
    start's floor points reach (``Refinement3.reopen``)."""
    grid = start_mesh(start, emb)
    m = len(grid[0])
    grown_by = max(0.0, (n - int(start.stats.n)) / max(int(start.stats.n), 1))
    expected = m * (1.0 + 2.0 * grown_by) + 64
    budget = vertex_budget(expected, opt, m, n)
    run = Refinement3(index, emb.period_internal, opt.k, opt.tau, opt.min_size * emb.scale,
                      budget, grid, emb.grid, queued=False,
                      capacity=int(min(expected, budget)))  # fmt: skip
    if len(start.floor_points):
        new = np.concatenate([new, emb.to_internal(start.floor_points)])
    reopened = run.reopen(new, np.asarray(start.torus.kinds, np.int8))
    return run, expected, budget, reopened


def finish(run, status, emb, opt, *, n, weight, points, report, estimated, budget, initial,
           rounds=None, interrupts=None, kept=None) -> Mesh:  # fmt: skip
    """The Mesh of a finished run in space (``Refinement3``, consumed), or BudgetError for
    one stopped by a budget; the plane's ``finish`` arguments. ``points()`` gives the input
    points, asked only when elements were left below the floor (to count the points in
    them); ``n`` their number, ``weight`` their total weight (None: unweighted);
    ``estimated`` (0: none) and ``budget`` are reported in the stats; ``initial``,
    ``interrupts`` and ``kept`` are the plane's (the initial vertices are counted from the
    kinds here), ``rounds`` a tiled run's report."""
    k, tau, per, box, min_size = opt.k, opt.tau, opt.periodic, opt.box, opt.min_size
    t_start, time_limit = opt.t_start, opt.time_limit
    if status != STATUS_DONE:
        what = (
            f"max_vertices = {int(run.cnt[C_MAX_VERTICES]):,}"
            if status == STATUS_MAX_VERTICES
            else f"time_limit = {time_limit} s"
        )
        raise BudgetError(
            f"stopped at {what} before the mesh was done; raise it, or use a larger k or min_size",
            progress={**run.progress(), "seconds": time.perf_counter() - t_start},
        )
    t_assemble = time.perf_counter()
    report.assembling(int(run.cnt[C_NV]))
    setup, refined = run.time_index, run.time_refine
    xyz, corners, offsets, kinds, cnt, floor, neighbours = run.take_result()
    largest = float(np.sqrt(run.largest_radius2))
    del run
    under = _points_under_floor(points, floor, emb, n)
    warn_floor(under, n, k, min_size, f"1e-6 of the box {tuple(box)}, not of the data")
    out_v, pos, tetrahedra, out_offsets = unfold(xyz, corners, offsets, emb, copy=False)
    # the torus' vertices first: when every axis is periodic pos is xyz, converted in place
    torus = Torus(
        origin=tuple(float(o) for o in emb.origin), period=emb.period,
        vertices=xyz / emb.scale, cells=corners, offsets=offsets, kinds=kinds,
        neighbours=neighbours,
    )  # fmt: skip
    floor_points = emb.to_input(floor[0]) if len(floor[0]) else np.zeros((0, 3))
    stats = Stats(
        n=int(n), weight=None if weight is None else float(weight), m=int(len(out_v)),
        m_torus=int(len(xyz)), cells=int(len(tetrahedra)),
        initial_vertices=int(np.count_nonzero(kinds == 0)),
        moves=moves_of(kinds),
        circumball_tests=int(cnt[C_DISK_TESTS]), cell_tests=int(cnt[C_CELL_TESTS]),
        failed_insertions=int(cnt[C_FAILED]), floor_circumballs=int(floor[2]),
        floor_cells=int(len(floor[1]) - floor[2]), points_under_floor=int(under),
        largest_circumball=largest / emb.scale, rounds=rounds,
        estimated_vertices=int(estimated), max_vertices=int(budget),
        time={"setup": setup, "refine": refined,
              "assemble": time.perf_counter() - t_assemble,
              "total": time.perf_counter() - t_start},
    )  # fmt: skip
    mesh = Mesh(
        vertices=emb.to_input(pos, copy=False), cells=tetrahedra, offsets=out_offsets,
        kinds=kinds[out_v], order=out_v, k=k, tau=tau, periodic=per, box=box,
        min_size=max(min_size, emb.resolution), floor_points=floor_points, torus=torus,
        stats=stats, index=kept,
    )  # fmt: skip
    report.assembling(len(mesh.vertices), done=True)
    return mesh
