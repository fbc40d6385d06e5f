"""A run of kNNRefine in this process: the points and options checked (``checked``), the
start (the embedding torus, the counting index, the initial mesh: ``Start``), the engine's
run, and the mesh assembled (``finish``); in space ``run3``. ``api.refine`` calls it, and
the tiled runs of ``scale.tiled`` use its start and finish."""

import inspect
import math
import sys
import time
import warnings
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from . import validation as V
from .engine import ahead, size
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


def is_spatial(points):
    """Whether points are (n, 3): a run in space."""
    shape = np.shape(points) if isinstance(points, np.ndarray) or hasattr(points, "shape") else None
    if shape is None:
        try:
            shape = np.shape(np.asarray(points, dtype=object))
        except Exception:
            return False
    return len(shape) == 2 and shape[1] == 3


def checked(points, weights, **asked) -> tuple[np.ndarray, np.ndarray | None, RunOptions]:
    """The points, weights and options of a run, checked before any work (``RunOptions``):
    (pts (n, d) float64, weights (n,) float64 or None, the options).

    Parameters
    ----------
    points : array-like (n, 2) or (n, 3)
    weights : array-like (n,), optional
    **asked
        ``k``, ``tau``, ``periodic``, ``box``, ``min_size``, ``max_vertices``,
        ``time_limit``, ``progress`` as ``knnrefine.refine`` takes them.

    Returns
    -------
    pts, weights, options
    """
    dim = 3 if is_spatial(points) else 2
    pts = V.as_points(points, dim)
    n = len(pts)
    w = None if weights is None else V.check_weights(weights, n)
    total = None if w is None else math.fsum(w)
    bounds, inside = lambda: V.default_box(pts), lambda b, p: V.check_inside(pts, b, p)
    return pts, w, RunOptions.check(n, total, bounds, inside, **asked, dim=dim)


def refine(
    points: ArrayLike,
    k: float | None = None,
    tau: float = 3.0,
    *,
    periodic: bool | tuple = False,
    box: tuple | None = None,
    weights: ArrayLike | None = None,
    min_size: float | None = None,
    max_vertices: int | None = None,
    time_limit: float | None = None,
    progress: Callable | None = None,
) -> Mesh:
    """``knnrefine.refine`` in this process, in the plane or in space: what the applications
    (the density estimator) call.

    Parameters
    ----------
    points, k, tau, periodic, box, weights, min_size, max_vertices, time_limit, progress
        As for ``knnrefine.refine``.

    Returns
    -------
    Mesh
    """
    asked = dict(k=k, tau=tau, periodic=periodic, box=box, min_size=min_size,
                 max_vertices=max_vertices, time_limit=time_limit, progress=progress)  # fmt: skip
    return refine_checked(*checked(points, weights, **asked))


def refine_checked(pts: np.ndarray, w: np.ndarray | None, opt: RunOptions) -> Mesh:
    """A run in this process on checked points, weights and options (``checked``): the
    plane's here, space's in ``run3``.

    Parameters
    ----------
    pts : ndarray (n, d)
    w : ndarray (n,) or None
    opt : RunOptions

    Returns
    -------
    Mesh
    """
    if pts.shape[1] == 3:
        from .run3 import refine3

        return refine3(pts, opt, w)
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
        return finish(
            run, status, emb, opt, (m0_order, m0_grid, estimated, budget), report, interrupts,
            kept, total, None,
        )  # fmt: skip


def finish(run, status, emb, opt, plan, report, interrupts, kept, weight, rounds):
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


class Progress:
    """The user's progress callback: progress(vertices, pending) while refining; if it takes
    a ``phase`` argument, also phase="compiling" before a first compilation,
    phase="assembling" / "done" while the mesh is assembled, and progress(count, 0, phase)
    for an application's work after it (``stage``: the density estimator's "choosing the
    smoothing", pairs scored)."""

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

    def stage(self, count, phase):
        """Work after the refinement (an application's): count done so far in ``phase``,
        reported to callbacks that take a phase."""
        if self.phases:
            self.callback(count, 0, phase=phase)

    def assembling(self, vertices, done=False):
        if self.callback is None:
            return
        if self.phases:
            self.callback(vertices, 0, phase="done" if done else "assembling")
        else:
            self.callback(vertices, 0)


def vertex_budget(estimated, opt, m0, n):
    """The vertex budget: the user's max_vertices, else ten times the estimate (at least
    10^6), but no more than the machine's memory holds. The estimate is within 5% on uniform
    points but off by up to 8x on clustered data (benchmarks/mesh_size.py), so only a run
    whose estimate exceeds twice the memory (by default) or eight times the user's budget is
    refused before any work; one expected to need more than 2 GB says so (LargeRunWarning)."""
    k, max_vertices, min_size = opt.k, opt.max_vertices, opt.min_size
    per_vertex = size.BYTES_PER_VERTEX if opt.dim == 2 else size.BYTES_PER_VERTEX3
    need = estimated * per_vertex
    memory = size.memory_bytes()
    warn_k1(k, estimated, n, min_size)
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
        fits = int(0.9 * memory / per_vertex)
        budget = int(max(10**6, 2 * m0, min(10 * estimated, fits)))
    if need > LARGE_RUN_BYTES:
        warnings.warn(
            f"this run will need about {estimated:.3g} vertices and {need / 1e9:.2g} GB of memory "
            f"(n = {n}, k = {k}, min_size = {min_size:.3g})",
            LargeRunWarning,
            stacklevel=3,
        )
    return budget


def warn_k1(k, estimated, n, min_size):
    """Up front, a FloorWarning that k = 1 refines around every input point down to the
    floor (d_{P,1} vanishes on P), with the vertices expected (``estimated``, of ``n``
    points): several per point, thousands in space. Shown at the caller's line."""
    if k != 1:
        return
    frame, stacklevel = sys._getframe(0), 1
    while frame is not None and frame.f_globals.get("__name__", "").startswith("knnrefine"):
        frame, stacklevel = frame.f_back, stacklevel + 1
    warnings.warn(
        f"k = 1 refines around every input point down to min_size = {min_size:.3g} (d_P1 is 0 "
        f"at each point): about {estimated:,.0f} vertices are expected, {estimated / n:,.0f} "
        "per point; the bounds are not claimed below the floor. Use k >= 2 or a larger "
        "min_size",
        FloorWarning,
        stacklevel=stacklevel,
    )


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
    if under > run.n / 2 and k != 1:  # k = 1 was said before the run (warn_k1)
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
