"""A run of kNNRefine in the plane in this process: the points and options checked
(``checked``), the start (the embedding torus, the counting index, the initial mesh:
``Start``), the engine's run (``refine``), and the mesh assembled (``finish``). The tiled
runs of ``scale.tiled`` use its start and finish."""

import math
import time

import numpy as np

from ..._engine import ahead, size
from ..._engine import state as S
from ..._engine.driver import Refinement
from ..._engine.embedding import Embedding, diameter, unfold, wrap
from ..._engine.geometry import FLOOR_BITS
from ..._engine.index import PointIndex, build_index, grow_forest, marked_in_disks
from ..._engine.initial import (
    candidate_grids,
    choose_initial_mesh,
    largest_passing,
    reach_bound,
    reach_factor,
    refusal_message,
)
from ..._engine.interrupt import Interrupts
from ..._options import Progress, RunOptions, check_box_run, vertex_budget, warn_floor
from ...errors import BudgetError, InputError
from ...mesh import Mesh, Stats, Torus
from ..box import continued_index, start_embedding, start_mesh


def checked(points, weights, **asked) -> tuple[np.ndarray, np.ndarray | None, RunOptions]:
    """The points (n, 2), weights and options of a run in the plane, checked before any work
    (``options.check_box_run``; ``asked`` as ``knnrefine.refine`` takes them)."""
    return check_box_run(points, weights, 2, **asked)


def refine(pts: np.ndarray, w: np.ndarray | None, opt: RunOptions) -> Mesh:
    """A run in the plane in this process on checked points, weights and options
    (``checked``), through ``pipeline.refine_checked``.

    Parameters
    ----------
    pts : ndarray (n, 2)
    w : ndarray (n,) or None
    opt : RunOptions

    Returns
    -------
    Mesh
    """
    if opt.start is not None:
        return _continued(pts, w, opt)
    n = len(pts)
    total = None if w is None else math.fsum(w)
    report = Progress(opt.progress)
    with ahead.compiling("plane", report.compiling), Interrupts() as interrupts:
        start = Start(pts, opt, opt.start_budget(n), interrupts, w)
        found = start.find(opt.k, reach_factor(opt.tau))
        if found is None:
            raise InputError(start.refusal(opt.k, opt.tau))
        emb, index, (m0, m0_order, m0_grid) = found
        opt.past("setting up")
        floor = max(opt.min_size * emb.scale, emb.grid * 2.0**FLOOR_BITS)
        lo, hi = emb.box_internal()
        lx, ly = emb.period_internal
        estimated = size.estimate(index, opt.k, floor, lx, ly, float(np.prod(hi - lo)))[0]
        budget = vertex_budget(estimated, opt, len(m0_order), n)
        run = Refinement(
            index, opt.k, lx, ly, opt.tau, opt.min_size * emb.scale, budget, m0=m0,
            grid=emb.grid, expected_vertices=min(estimated, budget),
        )  # fmt: skip
        run.time_index = start.seconds
        status = run.run(deadline=opt.deadline, progress=report.refining, interrupts=interrupts)
        kept = PointIndex(emb, index, PointIndex.fingerprint_of(pts, w))
        return finish(run, status, emb, opt, n=n, weight=total, points=lambda: pts,
                      report=report, estimated=estimated, budget=budget,
                      initial=len(m0_order), interrupts=interrupts, kept=kept)  # fmt: skip


def _continued(pts, w, opt):
    """A run continued from the mesh ``opt.start`` with the new points ``pts`` and weights
    ``w`` (checked by ``pipeline.checked``; all of them: ``opt.given``): its torus
    triangulation taken as it is, every element settled but those the new points reach
    (``Refinement.reopen``), then refined on."""
    start, new_pts, new_w = opt.start, pts, w
    pts, w = opt.given, opt.given_weights  # every point, the start's first
    n, n0 = len(pts), int(start.stats.n)
    total = None if w is None else math.fsum(w)
    report = Progress(opt.progress)
    with ahead.compiling("plane", report.compiling), Interrupts() as interrupts:
        t0 = time.perf_counter()
        emb = start_embedding(start)
        new = emb.to_internal(new_pts)
        index = continued_index(start, emb, pts, w, new, new_w, grow_forest,
                                lambda x, weights: build_index(x, weights=weights))  # fmt: skip
        interrupts.check()
        run, expected, budget, reopened = continue_run(start, emb, index, new, opt, n)
        run.time_index = time.perf_counter() - t0
        opt.past("setting up")
        status = run.run(deadline=opt.deadline, progress=report.refining, interrupts=interrupts)
        kept = PointIndex(emb, index, lambda: PointIndex.fingerprint_of(pts, w))
        mesh = finish(run, status, emb, opt, n=n, weight=total, points=lambda: pts,
                      report=report, estimated=expected, budget=budget,
                      initial=start.stats.initial_vertices, interrupts=interrupts,
                      kept=kept)  # fmt: skip
    mesh.stats.continued = {"points": n - n0, "from_vertices": len(start.torus.vertices),
                            "reopened": reopened}  # fmt: skip
    return mesh


def continue_run(start, emb, index, new, opt, n):
    """(run, expected vertices, vertex budget, cells reopened): the run of ``n`` points
    continued from the mesh ``start`` (its embedding ``emb``), counting with ``index``,
    its torus triangulation taken as it is and every element settled but those the new
    points ``new`` (internal coordinates) reach, which are queued (``Refinement.reopen``;
    the start's floor points are reopened too, so that they are reported again). Every
    box domain's ``continue_run`` takes the same arguments (``scale.tiled`` continues a
    store's run with it)."""
    m0 = start_mesh(start, emb)
    m = len(m0[0])
    grown_by = max(0.0, (n - int(start.stats.n)) / max(int(start.stats.n), 1))
    expected = m * (1.0 + 2.0 * grown_by) + 64
    budget = vertex_budget(expected, opt, m, n)
    run = Refinement(
        index, opt.k, *emb.period_internal, opt.tau, opt.min_size * emb.scale, budget,
        m0=m0, grid=emb.grid, capacity=min(expected, budget), queued=False, caches="edges",
    )  # fmt: skip
    if len(start.floor_points):
        new = np.concatenate([new, emb.to_internal(start.floor_points)])
    reopened = run.reopen(new, np.asarray(start.torus.kinds, np.int8))
    return run, expected, budget, reopened


def finish(run, status, emb, opt, *, n, weight, points, report, estimated, budget, initial,
           rounds=None, interrupts=None, kept=None) -> Mesh:  # fmt: skip
    """The Mesh of a finished run (``Refinement``), or BudgetError for one stopped by a
    budget; every domain's ``finish`` takes the same arguments. ``n``, ``weight``: the
    points' number and total weight (None: unweighted); ``points()`` gives them (unused
    here: the run's index counts under the floor); ``estimated``, ``budget``: the size
    estimate (0: none) and the vertex budget; ``initial``: the initial mesh's vertices;
    ``rounds``: a tiled run's report; ``kept``: the index the mesh keeps."""
    k, tau, t_start = opt.k, opt.tau, opt.t_start
    run.n = n
    # below the engine's resolution limit nothing is split whatever min_size says
    min_size = max(opt.min_size, run.floor / emb.scale)
    if status != S.STATUS_DONE:
        what = (
            f"max_vertices={budget}"
            if status == S.STATUS_MAX_VERTICES
            else f"time_limit={opt.time_limit} s"
        )
        raise BudgetError(
            f"refinement stopped at {what} with {run.vertices} vertices and "
            f"{run.pending()} candidates still queued (about {estimated:.3g} vertices were "
            "expected); raise the budget, use a larger k, or a larger min_size",
            progress={
                "vertices": run.vertices,
                "moves": run.counters()["moves"],
                "seconds": time.perf_counter() - t_start,
            },
        )
    t_assemble = time.perf_counter()
    report.assembling(run.vertices)
    res = run.result()
    mesh = _assemble(res, emb, k, tau, min_size, run, initial, report, interrupts, kept)
    stats = mesh.stats
    stats.weight = None if weight is None else float(weight)
    stats.estimated_vertices = int(estimated)
    stats.rounds = rounds
    stats.max_vertices = int(budget)
    stats.time = {
        "setup": run.time_index,
        "refine": run.time_refine,
        "assemble": time.perf_counter() - t_assemble,
        "total": time.perf_counter() - t_start,
    }
    report.assembling(len(mesh.vertices), done=True)
    return mesh


class Start:
    """Where refinement starts: the embedding torus, the counting index over the points in it,
    and an initial mesh that satisfies Theorem 6's precondition.

    The default torus (a margin of 1.05 x the box's diameter along non-periodic axes) is
    tried first. When its initial mesh cannot be ordered to satisfy the precondition, other
    margins are tried along non-periodic axes: 1.05 x a bound on max d_Pk over the box (the
    least that keeps d_Pk exact on the box: fewer initial vertices far from the data), then
    2, 4 and 10 diameters (initial meshes coarser relative to the box). Indexes and candidate
    initial meshes are built once per torus, when first tried; the deadline and Ctrl-C are
    checked between candidates and in every peeling round."""

    LIMITS_EFFORT = 50_000  # initial vertices above which a refusal skips the limit search

    def __init__(self, pts, opt, max_vertices, interrupts, weights=None):
        self.pts, self.box, self.per, self.max_vertices = pts, opt.box, opt.periodic, max_vertices
        self.opt = opt
        self.weights = weights
        self.interrupts = interrupts
        self.tori = {}
        self.seconds = 0.0  # building indexes

    def check(self):
        self.interrupts.check()
        self.opt.past("choosing the initial mesh")

    def torus(self, reach=None):
        """(embedding, index, candidate initial meshes) of the torus with this margin."""
        if reach not in self.tori:
            t0 = time.perf_counter()
            emb = Embedding.make(self.box, self.per, reach)
            index = build_index(emb.to_internal(self.pts), weights=self.weights)
            self.seconds += time.perf_counter() - t0
            self.check()
            later = candidate_grids(*emb.period_internal, self.max_vertices, emb.grid)
            self.tori[reach] = emb, index, ([], later)
        return self.tori[reach]

    def grids(self, reach=None):
        """The torus' candidate initial meshes, each built when first asked for and kept for
        later tries (on a long box one took 0.2 s: building them all first overran a
        time_limit of 1 s by 0.8 s)."""
        built, later = self.torus(reach)[2]
        yield from list(built)
        for grid in later:
            built.append(grid)
            yield grid

    def _try(self, reach, k, factor):
        emb, index, _ = self.torus(reach)
        grids = self.grids(reach)
        choice = choose_initial_mesh(grids, index, k, factor, *emb.period_internal, self.check)
        return None if choice is None else (emb, index, choice)

    def find(self, k, factor):
        """(embedding, index, (m0, order, grid)) for the first torus that works, or None."""
        found = self._try(None, k, factor)
        if found is not None or all(self.per):
            return found
        emb, index, _ = self.torus()
        lo, hi = emb.box_internal()
        reach = reach_bound(index, lo, hi, k, *emb.period_internal) / emb.scale
        diam = diameter(self.box, self.per)
        for r in (reach, 2.0 * diam, 4.0 * diam, 10.0 * diam):
            found = self._try(r, k, factor)
            if found is not None:
                return found
        return None

    def refusal(self, k, tau):
        """The message for an input no torus can start: what failed and what would work."""
        factor = reach_factor(tau)
        emb = self.torus()[0]
        effort = sum(len(m0[0]) for _, m0 in self.grids())
        k_max, f_min = (
            largest_passing(lambda kk, f: self.find(kk, f) is not None, k, factor)
            if effort <= self.LIMITS_EFFORT
            else (None, None)
        )
        return refusal_message(len(self.pts), k, tau, emb, k_max, f_min)


def _points_under_floor(res, run):
    """How many input points lie in a floor element (a circumball, or the disk of radius R(v)
    around a cell's vertex, that holds >= k points below the floor)."""
    if not len(res.floor_radii2):
        return 0
    centres = res.floor_centres
    return marked_in_disks(run.index, centres[:, 0].copy(), centres[:, 1].copy(),
                           res.floor_radii2 * (1.0 + 1e-9), run.lx, run.ly)  # fmt: skip


def _assemble(res, emb, k, tau, min_size, run, initial, report, interrupts, index=None):
    """The Mesh the user receives, from the torus mesh (progress reported between steps)."""
    out_v, pos, tri, offsets = unfold(res.vxy, res.tv, res.to, emb)
    report.assembling(run.vertices)
    interrupts.check()
    L = np.array(emb.period_internal)
    floor_int = res.floor_centres
    floor_pts = emb.to_input(wrap(floor_int, L)) if len(floor_int) else np.zeros((0, 2))
    under = _points_under_floor(res, run)
    report.assembling(run.vertices)
    c = res.counters
    stats = Stats(
        n=run.n,
        m=int(len(out_v)),
        m_torus=int(res.vxy.shape[0]),
        cells=int(len(tri)),
        initial_vertices=int(initial),
        moves=c["moves"],
        circumball_tests=c["disk_tests"],
        cell_tests=c["cell_tests"],
        failed_insertions=c["failed_insertions"],
        floor_circumballs=int(res.floor_balls),
        floor_cells=int(len(res.floor_radii2) - res.floor_balls),
        points_under_floor=int(under),
        largest_circumball=float(np.sqrt(res.largest_radius2)) / emb.scale,
    )
    warn_floor(under, run.n, k, min_size, f"1e-6 of the box {emb.box}, not of the data")
    torus = Torus(
        origin=tuple(float(o) for o in emb.origin),
        period=emb.period,
        vertices=res.vxy / emb.scale,
        cells=res.tv,
        offsets=res.to,
        neighbours=res.tn,
        kinds=res.kind,
    )
    return Mesh(
        vertices=emb.to_input(pos, copy=False),  # unfold's arrays are new: no copies
        cells=tri,
        offsets=offsets,
        kinds=res.kind[out_v],
        order=out_v,
        k=k,
        tau=tau,
        periodic=emb.periodic,
        box=emb.box,
        min_size=min_size,
        floor_points=floor_pts,
        stats=stats,
        torus=torus,
        index=index,
    )
