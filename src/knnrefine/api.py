"""knnrefine.refine: the public entry point."""

import inspect
import math
import time
import warnings
from collections.abc import Callable
from concurrent.futures import Executor
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from . import validation as V
from .engine import jit, size
from .engine import refine as R
from .engine import state as S
from .engine.driver import Refinement
from .engine.embedding import Embedding, diameter, unfold, wrap
from .engine.geometry import FLOOR_BITS
from .engine.index import PointIndex, build_index, mark_in_disks
from .engine.initial import (
    candidate_grids,
    choose_initial_mesh,
    largest_passing,
    reach_bound,
    reach_factor,
    refusal_message,
)
from .engine.interrupt import Interrupts
from .errors import BudgetError, FloorWarning, InputError, LargeRunWarning
from .mesh import Mesh, Torus
from .options import RunOptions

LARGE_RUN_BYTES = 2e9  # runs expected to need more memory than this say so up front


def _is_spatial(points):
    """Whether points are (n, 3): a run in space."""
    shape = np.shape(points) if isinstance(points, np.ndarray) or hasattr(points, "shape") else None
    if shape is None:
        try:
            shape = np.shape(np.asarray(points, dtype=object))
        except Exception:
            return False
    return len(shape) == 2 and shape[1] == 3


def refine(
    points: ArrayLike,
    k: float,
    tau: float = 3.0,
    *,
    periodic: bool | tuple = False,
    box: tuple | None = None,
    weights: ArrayLike | None = None,
    min_size: float | None = None,
    max_vertices: int | None = None,
    time_limit: float | None = None,
    progress: Callable | None = None,
    workers: int | None = None,
    executor: Executor | None = None,
) -> Mesh:
    """kNNRefine (Gardner & Sheehy, CCCG 2016): mesh vertices M with
    alpha d_{P,k} <= d_{M,2} <= beta d_{P,k} everywhere in the box.

    The guarantee and its conditions. Every mesh returned is tau-well-spaced, no Voronoi cell
    and no closed circumball holds k points of P, and at every x of the box with
    d_{P,k}(x) >= min_size (the resolution floor)

        alpha d_{P,k}(x) <= d_{M,2}(x) <= beta d_{P,k}(x),

    with beta of Theorem 5 and alpha = 1 / (2 K + 1), K = max(2 tau / (tau - 2), 3): Theorem
    6's (tau - 2) / (5 tau - 2) for tau <= 6, and 1/7 for tau > 6, where the paper's proof
    needs K >= 3 (``Mesh.alpha``, ``Mesh.beta``). The lower bound rests on Lemma 2's
    precondition: each initial vertex u has d_{P,k}(u) <= (K - 1) lambda_u. refine chooses the
    initial mesh (and, for non-periodic axes, the embedding torus) so that it holds; where no
    valid initial mesh can (k close to n, or sparse data, on a small or thin torus) it raises
    InputError naming the largest k and tau that can be certified. It also raises InputError
    for k > n (d_{P,k} would be infinite) and for coordinates too large for their box (the
    returned vertices are exact, never rounded). ``knnrefine.certify`` checks all of this
    independently; a FloorWarning says when most points lie below the floor.

    Parameters
    ----------
    points : array-like, shape (n, 2)
        The input points P (a multiset: duplicates count with their multiplicity).
    k : int, 1 <= k <= n
        Which nearest neighbour: d_{P,k}(x) is the distance from x to its k-th nearest point.
    tau : float > 2
        Well-spacedness: every Voronoi cell of the output has aspect 2 R(v) / d_{M,2}(v) <= tau.
    periodic : bool or (bool, bool)
        True: the box is a flat torus (the paper's setting, e.g. angles). False (default): an
        ordinary box; the result is exact for the planar d_{P,k} in the box. A pair makes only
        one axis periodic.
    weights : array-like, shape (n,), optional
        Point weights (finite, >= 0): a region "holds k points" when the weights of the points
        in it sum to k or more, and d_{P,k}(x) is the least radius whose closed disk about x
        holds weight >= k. k may then be any positive number up to the total weight. Whole
        weights are repeated points (the same mesh); aggregated counts and survey weights are
        the real-valued uses. Sums of real weights are rounded: a disk whose weight is k to
        within rounding may count either way.
    box : (xmin, ymin, xmax, ymax), optional
        Required if any axis is periodic (points are wrapped into it, exactly). Defaults to
        the points' bounding box; points outside an explicit box are an error on non-periodic
        axes.
    min_size : float, optional
        Resolution floor in input units: circumballs and cells smaller than this are not split
        even if they hold >= k points (where k or more points coincide d_{P,k} is 0 and
        refinement could not stop). Default: 1e-6 times the box's longer side. Where it acts is
        reported in ``Mesh.floor_points`` and ``Mesh.stats["points_under_floor"]``. Values
        below the engine's resolution (2^14 grid steps, the grid being 2^-50 of the torus
        period or the spacing of doubles at the coordinates, whichever is coarser) act as that
        resolution, which ``Mesh.min_size`` then reports.
    max_vertices : int, optional
        Budget: stop with BudgetError beyond this many vertices. Default: ten times the size
        estimated before refining (at least 10^6, at most what memory holds); a run whose
        estimate exceeds twice the machine's memory (by default) or eight times max_vertices
        is refused before any work, and one expected to need more than 2 GB says so
        (LargeRunWarning).
    time_limit : float, optional
        Budget in seconds for the whole call (setup and refinement); BudgetError when
        exceeded.
    progress : callable(vertices, pending[, phase]), optional
        Called about every 50 ms with the number of vertices so far and the queued candidates;
        while the mesh is assembled, with pending = 0 and, if it accepts ``phase``,
        phase="assembling", then phase="done". If it accepts ``phase`` and the kernels were
        never compiled in this environment, it is first called once with (0, 0,
        phase="compiling"): the compilation that follows takes 10-60 s, once.
    workers : int, optional
        None or 1: refine in this process. N > 1: in N local processes (forked on Linux;
        elsewhere the calling script needs the ``if __name__ == "__main__":`` guard): a plan
        from a sample of the points (the same whatever their order), a coarse pass on part of
        it, then rounds of N strips of the torus, balanced by point count, each refining only
        what lies inside it, alternating with strips shifted by half; whatever no round
        settled is finished here (``engine/region.py`` and docs/algorithm.md say why the
        result is a kNNRefine run: the same guarantees, certified by ``certify``). The mesh
        differs from a one-process run's in the order of its moves, and its size by a few
        percent. ``stats["rounds"]`` reports each round and the last step; ``time_limit``
        and ``max_vertices`` hold in every tile. Not faster than one process on 2 cores
        (docs/benchmarks.md).
    executor : concurrent.futures.Executor, optional
        Where the tiles of a run with ``workers`` > 1 run: its ``map`` is called once per
        round with that round's tiles (a Dask client's ``get_executor()``:
        ``knnrefine.scale.distributed.refine``). None: a pool of ``workers`` local processes.

    Returns
    -------
    Mesh

    Ctrl-C raises KeyboardInterrupt within about 50 ms of refinement (within the current
    kernel call during setup).

    Points in space ((n, 3), a box of six numbers, ``periodic`` a bool or three) are refined
    by ``api3.refine3`` into the same ``Mesh`` type; weights, workers and executor do not
    apply there yet.
    """
    asked: dict[str, Any] = dict(k=k, tau=tau, periodic=periodic, box=box, min_size=min_size,
                 max_vertices=max_vertices, time_limit=time_limit, progress=progress)  # fmt: skip
    if _is_spatial(points):
        from .api3 import refine3

        if weights is not None or workers not in (None, 1) or executor is not None:
            raise InputError("weights, workers and executor are not built for (n, 3) points yet")
        pts = V.as_points(points, 3)
        bounds, inside = lambda: V.default_box(pts), lambda b, p: V.check_inside(pts, b, p)
        return refine3(pts, RunOptions.check(len(pts), None, bounds, inside, **asked, dim=3))
    pts = V.as_points(points)
    n = len(pts)
    w = None if weights is None else V.check_weights(weights, n)
    total = None if w is None else math.fsum(w)
    bounds, inside = lambda: V.default_box(pts), lambda b, p: V.check_inside(pts, b, p)
    opt = RunOptions.check(n, total, bounds, inside, **asked)
    workers = V.check_workers(workers)
    if executor is not None and not callable(getattr(executor, "map", None)):
        raise InputError(
            f"executor must be a concurrent.futures.Executor (with a map method), got {executor!r}"
        )
    if executor is not None and workers < 2:
        raise InputError("an executor runs the tiles of a tiled run: give workers >= 2 with it")
    if workers > 1:
        from .scale.tiled import LocalStore

        store = LocalStore(pts, w, workers, executor)
        try:
            return refine_store(store, opt, workers)
        finally:
            store.close()
    report = _Progress(opt.progress)
    if not jit.is_ready(R.refine_steps):
        report.compiling()
    with Interrupts() as interrupts:
        start = _Start(pts, opt, opt.start_budget(n), interrupts, w)
        found = start.find(opt.k, reach_factor(opt.tau))
        if found is None:
            raise InputError(start.refusal(opt.k, opt.tau))
        emb, index, (m0, m0_order, m0_grid) = found
        opt.past("setting up")
        floor = max(opt.min_size * emb.scale, emb.grid * 2.0**FLOOR_BITS)
        lo, hi = emb.box_internal()
        lx, ly = emb.period_internal
        estimated = size.estimate(index, opt.k, floor, lx, ly, float(np.prod(hi - lo)))[0]
        budget = _budget(estimated, opt, len(m0_order), n)
        run = Refinement(
            index, opt.k, lx, ly, opt.tau, opt.min_size * emb.scale, budget, m0=m0,
            grid=emb.grid, expected_vertices=min(estimated, budget),
        )  # fmt: skip
        run.time_index = start.seconds
        status = run.run(deadline=opt.deadline, progress=report.refining, interrupts=interrupts)
        kept = PointIndex(emb, index, PointIndex.fingerprint_of(pts, w))
        return _finish(
            run, status, emb, opt, (m0_order, m0_grid, estimated, budget), report, interrupts,
            kept, total, None,
        )  # fmt: skip


def refine_store(store, opt, workers):
    """A tiled run (``scale/tiled.py``) on the points of ``store`` (``LocalStore``, or
    ``distributed.DaskStore``) with the checked options ``opt`` (``RunOptions``) in
    ``workers`` strips: the plan from a sample of the points (initial mesh, size, strips), a
    coarse pass on part of it, rounds of tiles, then whatever no round settled on the index
    of all points, fetched only then."""
    from .scale import tiled as T

    n = store.n
    k, tau, min_size = opt.k, opt.tau, opt.min_size
    deadline = opt.deadline
    start_budget = opt.start_budget(n)
    report = _Progress(opt.progress)
    if not jit.is_ready(R.refine_steps):
        report.compiling()
    with Interrupts() as interrupts:
        t0 = time.perf_counter()
        coarse_f = min(1.0 / (T.COARSE_SHARE * workers), T.COARSE_MAX / n)
        sx, sw, keys = store.sample(max(coarse_f, min(1.0, T.SAMPLE_MIN / n)))
        share = len(sx) / n if sw is None else float(sw.sum()) / store.weight
        factor = reach_factor(tau)
        # d_{S,k} >= d_{P,k} for a subset S: an initial mesh the sample accepts is accepted
        start = _Start(sx, opt, start_budget, interrupts, sw)
        found = start.find(k, factor)
        if found is None and len(sx) < n:  # the sample may be too sparse: ask all points
            every, w_every = store.points()
            start = _Start(every, opt, start_budget, interrupts, w_every)
            found = start.find(k, factor)
        if found is None:
            raise InputError(start.refusal(k, tau))
        emb, s_index, (m0, m0_order, m0_grid) = found
        opt.past("setting up")
        lx, ly = emb.period_internal
        floor = max(min_size * emb.scale, emb.grid * 2.0**FLOOR_BITS)
        lo, hi = emb.box_internal()
        estimated = size.estimate(s_index, k, floor, lx, ly, float(np.prod(hi - lo)))[0] / share
        budget = _budget(estimated, opt, len(m0_order), n)
        internal = emb.to_internal(sx)
        sets = T.strips(internal, lx, ly, workers)
        common = {
            "k": k, "lx": lx, "ly": ly, "tau": tau, "min_size": min_size * emb.scale,
            "max_vertices": budget, "m0": m0, "grid": emb.grid,
        }  # fmt: skip
        coarse = keys < coarse_f
        xy, kinds = T.coarse_pass(
            internal[coarse], None if sw is None else sw[coarse], k, lx, ly, tau,
            min_size * emb.scale, budget, m0, emb.grid,
        )  # fmt: skip
        store.prepare(emb, sets, 4 * emb.grid)
        setup = time.perf_counter() - t0
        xy, kinds, stamps, history, rounds, stopped = T.run_rounds(
            store, sets, xy, kinds, common, min(estimated, budget), len(m0[0]), report.refining,
            interrupts, deadline,
        )  # fmt: skip
        t1 = time.perf_counter()
        args = (xy, kinds, stamps, history, k, lx, ly, tau, min_size * emb.scale, budget, m0,
                emb.grid)  # fmt: skip
        bands = T.margin_bands(emb, *store.bounds)
        run, status, unsettled = T.settle(s_index, *args, bands=bands, deadline=deadline)
        before, fetched = len(m0[0]) + len(xy), False
        if stopped is not None:
            status = stopped
        elif status == S.STATUS_DONE and unsettled:
            pts, w = store.points()  # what is left needs the counts of all points
            fetched = True
            run, _, unsettled = T.settle(build_index(emb.to_internal(pts), weights=w), *args)
            status = run.run(deadline=deadline, progress=report.refining, interrupts=interrupts)
        run.n = n
        rounds.append({
            "round": "final", "new_vertices": run.vertices - before,
            "seconds": time.perf_counter() - t1, "unsettled": unsettled, "fetched_points": fetched,
        })  # fmt: skip
        run.time_index = setup
        run.time_refine = time.perf_counter() - t0 - setup
        return _finish(
            run, status, emb, opt, (m0_order, m0_grid, estimated, budget), report, interrupts,
            None, store.weight, rounds,
        )  # fmt: skip


def _finish(run, status, emb, opt, plan, report, interrupts, kept, weight, rounds):
    """The Mesh of a finished run, or BudgetError for one stopped by a budget. ``plan``:
    (the initial mesh's order and grid, the estimated size, the vertex budget)."""
    m0_order, m0_grid, estimated, budget = plan
    k, tau, t_start = opt.k, opt.tau, opt.t_start
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
    m0_stats = {
        "vertices": int(len(m0_order)),
        "per_period": int(m0_grid[0]),
        "shift": float(m0_grid[2]),
        "reach_factor": reach_factor(tau),
    }
    mesh = _assemble(res, emb, k, tau, min_size, run, m0_stats, report, interrupts, kept)
    stats = mesh.stats
    if weight is not None:
        stats["weight"] = float(weight)
    stats["estimated_vertices"] = int(estimated)
    if rounds is not None:
        stats["rounds"] = rounds
    stats["max_vertices"] = budget
    stats["time"] = {
        "index": run.time_index,
        "refine": run.time_refine,
        "assemble": time.perf_counter() - t_assemble,
        "total": time.perf_counter() - t_start,
    }
    report.assembling(len(mesh.vertices), done=True)
    return mesh


class _Progress:
    """The user's progress callback: progress(vertices, pending) while refining; if it takes
    a ``phase`` argument, also phase="compiling" before a first compilation and
    phase="assembling" / "done" while the mesh is assembled."""

    def __init__(self, callback):
        self.callback = callback
        self.phases = False
        if callback is not None:
            try:
                params = inspect.signature(callback).parameters.values()
                self.phases = any(
                    p.name == "phase" or p.kind is inspect.Parameter.VAR_KEYWORD for p in params
                )
            except (TypeError, ValueError):
                pass

    def compiling(self):
        if self.phases:
            self.callback(0, 0, phase="compiling")

    def refining(self, vertices, pending):
        if self.callback is not None:
            self.callback(vertices, pending)

    def assembling(self, vertices, done=False):
        if self.callback is None:
            return
        if self.phases:
            self.callback(vertices, 0, phase="done" if done else "assembling")
        else:
            self.callback(vertices, 0)


def _budget(estimated, opt, m0, n):
    """The vertex budget: the user's max_vertices, else ten times the estimate (at least
    10^6), but no more than the machine's memory holds. The estimate is within 5% on uniform
    points but off by up to 8x on clustered data (benchmarks/mesh_size.py), so only a run
    whose estimate exceeds twice the memory (by default) or eight times the user's budget is
    refused before any work; one expected to need more than 2 GB says so (LargeRunWarning)."""
    k, max_vertices, min_size = opt.k, opt.max_vertices, opt.min_size
    need = estimated * size.BYTES_PER_VERTEX
    memory = size.memory_bytes()
    hint = (
        "k = 1 refines every input point down to min_size: use k >= 2 or a larger min_size"
        if k == 1
        else "use a larger k or a larger min_size"
    )
    if max_vertices is not None:
        if estimated > 8 * max_vertices:
            raise BudgetError(
                f"this run needs about {estimated:.3g} vertices, far beyond "
                f"max_vertices={max_vertices}; {hint}, or raise max_vertices",
                progress={"vertices": 0, "moves": {}, "seconds": 0.0},
            )
        budget = int(max_vertices)
    else:
        if need > 2 * memory:
            raise BudgetError(
                f"this run needs about {estimated:.3g} vertices, about {need / 1e9:.3g} GB, far "
                f"more than this machine's {memory / 1e9:.3g} GB; {hint}, or pass max_vertices "
                "to insist",
                progress={"vertices": 0, "moves": {}, "seconds": 0.0},
            )
        fits = int(0.9 * memory / size.BYTES_PER_VERTEX)
        budget = int(max(10**6, 2 * m0, min(10 * estimated, fits)))
    if need > LARGE_RUN_BYTES:
        warnings.warn(
            f"this run will need about {estimated:.3g} vertices and {need / 1e9:.2g} GB of memory "
            f"(n = {n}, k = {k}, min_size = {min_size:.3g})",
            LargeRunWarning,
            stacklevel=3,
        )
    return budget


class _Start:
    """Where refinement starts: the embedding torus, the counting index over the points in it,
    and an initial mesh that satisfies Theorem 6's precondition.

    The default torus (a margin of 1.05 x the box's diameter along non-periodic axes) is
    tried first. When its initial mesh cannot be ordered to satisfy the precondition, other
    margins are tried along non-periodic axes: 1.05 x a bound on max d_Pk over the box (the
    least that keeps d_Pk exact on the box: fewer initial vertices far from the data), then
    2, 4 and 10 diameters (initial meshes coarser relative to the box). Indexes and candidate
    initial meshes are built once per torus; the deadline and Ctrl-C are checked between
    candidates."""

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
            grids = list(candidate_grids(*emb.period_internal, self.max_vertices, emb.grid))
            self.tori[reach] = emb, index, grids
        return self.tori[reach]

    def _try(self, reach, k, factor):
        emb, index, grids = self.torus(reach)
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
        emb, _, grids = self.torus()
        effort = sum(len(m0[0]) for _, m0 in grids)
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
    mark = np.zeros(run.n, np.bool_)
    return int(
        mark_in_disks(
            run.index,
            res.floor_centres[:, 0].copy(),
            res.floor_centres[:, 1].copy(),
            res.floor_radii2 * (1.0 + 1e-9),
            run.lx,
            run.ly,
            mark,
        )
    )


def _assemble(res, emb, k, tau, min_size, run, m0_stats, report, interrupts, index=None):
    """The Mesh the user receives, from the torus mesh (progress reported between steps)."""
    out_v, pos, tri, offsets = unfold(res.vxy, res.tv, res.to, emb)
    report.assembling(run.vertices)
    interrupts.check()
    L = np.array(emb.period_internal)
    floor_int = res.floor_centres
    floor_pts = emb.to_input(wrap(floor_int, L)) if len(floor_int) else np.zeros((0, 2))
    under = _points_under_floor(res, run)
    report.assembling(run.vertices)
    stats = {
        "n": run.n,
        "m": int(len(out_v)),
        "m_torus": int(res.vxy.shape[0]),
        "triangles": int(len(tri)),
        **res.counters,
        "floor_circumballs": res.floor_balls,
        "floor_cells": len(res.floor_radii2) - res.floor_balls,
        "clean_floor": res.clean_floor,
        "points_under_floor": under,
        "m0": m0_stats,
    }
    if under > run.n / 2:
        warnings.warn(
            f"{under} of the {run.n} points ({100 * under / run.n:.0f}%) lie in circumballs or "
            f"cells smaller than min_size = {min_size:.3g} that still hold k = {k} points: the "
            "bounds are not claimed there"
            + (
                " (k = 1 makes every input point such a place; use k >= 2)"
                if k == 1
                else f"; min_size defaults to 1e-6 of the box {emb.box}, not of the data: pass a "
                "smaller min_size or a box fitted to the data"
            ),
            FloorWarning,
            stacklevel=3,
        )
    torus = Torus(
        origin=tuple(float(o) for o in emb.origin),
        period=emb.period,
        vertices=res.vxy / emb.scale,
        cells=res.tv,
        offsets=res.to,
        neighbors=res.tn,
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
