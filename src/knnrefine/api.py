"""knnrefine.refine: the public entry point."""

import time

import numpy as np

from . import validation as V
from .engine import refine as R
from .engine.driver import Refinement
from .engine.embedding import Embedding, diameter, unfold, wrap
from .engine.index import build_index
from .engine.initial import (
    GRIDS,
    choose_initial_mesh,
    grid_shape,
    largest_passing,
    reach_bound,
    reach_factor,
    tau_for_factor,
)
from .errors import BudgetError, InputError
from .mesh import Mesh, Torus

DEFAULT_MIN_SIZE = 1e-6  # resolution floor, relative to the box's longer side


def refine(
    points,
    k,
    tau=3.0,
    *,
    periodic=False,
    box=None,
    min_size=None,
    max_vertices=None,
    time_limit=None,
    progress=None,
):
    """kNNRefine (Gardner & Sheehy, CCCG 2016): mesh vertices M with
    alpha d_{P,k} <= d_{M,2} <= beta d_{P,k} everywhere in the box.

    Parameters
    ----------
    points : array-like, shape (n, 2)
        The input points P (a multiset: duplicates count with their multiplicity).
    k : int >= 1
        Which nearest neighbour: d_{P,k}(x) is the distance from x to its k-th nearest point.
    tau : float > 2
        Well-spacedness: every Voronoi cell of the output has aspect 2 R(v) / d_{M,2}(v) <= tau.
    periodic : bool or (bool, bool)
        True: the box is a flat torus (the paper's setting, e.g. angles). False (default): an
        ordinary box; the result is exact for the planar d_{P,k} in the box. A pair makes only
        one axis periodic.
    box : (xmin, ymin, xmax, ymax), optional
        Required if any axis is periodic (points are wrapped into it). Defaults to the points'
        bounding box; points outside an explicit box are an error on non-periodic axes.
    min_size : float, optional
        Resolution floor in input units: circumballs and cells smaller than this are not split
        even if they hold >= k points (where k or more points coincide d_{P,k} is 0 and
        refinement could not stop). Default: 1e-6 times the box's longer side. Where it acts is
        reported in ``Mesh.floor_points``; everywhere d_{P,k} >= min_size the bounds hold.
        Values below the engine's resolution (2^-36 of the torus period) act as that
        resolution, which ``Mesh.min_size`` then reports.
    max_vertices : int, optional
        Budget: stop with BudgetError beyond this many vertices. Default max(10^6, 2 n).
    time_limit : float, optional
        Budget in seconds for the refinement itself; BudgetError when exceeded.
    progress : callable(vertices, pending), optional
        Called about every 50 ms with the number of vertices so far and the queued candidates.

    Returns
    -------
    Mesh
    """
    t_start = time.perf_counter()
    pts = V.as_points(points)
    k = V.check_k(k, len(pts))
    tau = V.check_tau(tau)
    per = V.check_periodic(periodic)
    if box is None:
        if any(per):
            raise InputError(
                "a periodic run needs box=(xmin, ymin, xmax, ymax): the periods are its sides "
                "(for angles in degrees, e.g. box=(-180, -180, 180, 180))"
            )
        box = V.default_box(pts)
    else:
        box = V.check_box(box)
        V.check_inside(pts, box, per)
    side = max(box[2] - box[0], box[3] - box[1])
    if min_size is None:
        min_size = DEFAULT_MIN_SIZE * side
    elif isinstance(min_size, bool) or not np.isfinite(min_size) or min_size < 0:
        raise InputError(f"min_size must be a finite number >= 0, got {min_size!r}")
    min_size = float(min_size)
    if max_vertices is None:
        max_vertices = max(10**6, 2 * len(pts))
    elif isinstance(max_vertices, bool) or int(max_vertices) != max_vertices or max_vertices < 1:
        raise InputError(f"max_vertices must be a positive integer, got {max_vertices!r}")
    if time_limit is not None and not (time_limit > 0):
        raise InputError(f"time_limit must be a positive number of seconds, got {time_limit!r}")

    _check_resolution(box, per)
    _check_initial_budget(box, per, int(max_vertices))
    start = _Start(pts, box, per, int(max_vertices))
    found = start.find(k, reach_factor(tau))
    if found is None:
        raise InputError(start.refusal(k, tau))
    emb, index, (m0, m0_order, m0_grid) = found
    run = Refinement(
        index,
        k,
        *emb.period_internal,
        tau,
        min_size * emb.scale,
        int(max_vertices),
        m0=m0,
        grid=emb.grid,
    )
    run.time_index = start.seconds
    # below the engine's resolution limit nothing is split whatever min_size says
    min_size = max(min_size, run.floor / emb.scale)
    status = run.run(time_limit=time_limit, progress=progress)
    if status != R.STATUS_DONE:
        what = (
            f"max_vertices={max_vertices}"
            if status == R.STATUS_MAX_VERTICES
            else f"time_limit={time_limit} s"
        )
        raise BudgetError(
            f"refinement stopped at {what} with {run.vertices} vertices and {run.pending()} "
            "candidates still queued; raise the budget, use a larger k, or a larger min_size",
            progress={
                "vertices": run.vertices,
                "moves": run.counters()["moves"],
                "seconds": time.perf_counter() - t_start,
            },
        )
    res = run.result()
    t_assemble = time.perf_counter()
    m0_stats = {
        "vertices": int(len(m0_order)),
        "per_period": int(m0_grid[0]),
        "shift": float(m0_grid[2]),
        "reach_factor": reach_factor(tau),
    }
    mesh = _assemble(res, emb, k, tau, min_size, run, m0_stats)
    stats = mesh.stats
    stats["time"] = {
        "index": run.time_index,
        "refine": run.time_refine,
        "assemble": time.perf_counter() - t_assemble,
        "total": time.perf_counter() - t_start,
    }
    return mesh


RESOLUTION_BITS = 24  # a box must span at least 2^24 grid steps: the floor is 2^14 of them


def _check_resolution(box, per):
    """The box must be wide compared with the spacing of doubles at its coordinates: the
    engine works on a grid no finer than that spacing (so that every vertex is returned
    exactly), and its resolution floor is 2^14 grid steps."""
    emb = Embedding.make(box, per)
    step = emb.grid / emb.scale
    side = max(box[2] - box[0], box[3] - box[1])
    if side < step * 2.0**RESOLUTION_BITS:
        big = float(np.max(np.abs(box)))
        raise InputError(
            f"the box {box} is too small for its coordinates' magnitude: near {big:.6g} doubles "
            f"are {step:.3g} apart, and knnrefine needs at least 2^{RESOLUTION_BITS} such steps "
            f"across the box (its side is {side:.3g}, about {side / step:.3g} steps); subtract "
            "an offset first, for example points - points.min(axis=0)"
        )


def _check_initial_budget(box, per, max_vertices):
    """The smallest initial mesh of the default torus must fit in max_vertices."""
    lx, ly = Embedding.make(box, per).period_internal
    nx, ny = min((grid_shape(lx, ly, g[0]) for g in GRIDS), key=lambda s: s[0] * s[1])
    if nx * ny <= max_vertices:
        return
    if max(nx, ny) <= 4 * min(nx, ny):
        raise InputError(
            f"max_vertices={max_vertices} is too small: the initial mesh alone has {nx * ny} "
            "vertices; raise max_vertices"
        )
    raise InputError(
        f"the box {box} is too elongated: the initial mesh of the torus alone needs "
        f"{nx} x {ny} vertices (max_vertices={max_vertices}); rescale the coordinates, use "
        "a less elongated periodic box, or raise max_vertices"
    )


def _initial(emb, index, k, factor, max_vertices):
    return choose_initial_mesh(index, k, factor, *emb.period_internal, max_vertices, emb.grid)


class _Start:
    """Where refinement starts: the embedding torus, the counting index over the points in it,
    and an initial mesh that satisfies Theorem 6's precondition.

    The default torus (a margin of 1.05 x the box's diameter along non-periodic axes) is
    tried first. When its initial mesh cannot be ordered to satisfy the precondition, other
    margins are tried along non-periodic axes: 1.05 x a bound on max d_Pk over the box (the
    least that keeps d_Pk exact on the box: fewer initial vertices far from the data), then
    2, 4 and 10 diameters (initial meshes coarser relative to the box). Indexes are built once
    per torus."""

    def __init__(self, pts, box, per, max_vertices):
        self.pts, self.box, self.per, self.max_vertices = pts, box, per, max_vertices
        self.tori = {}
        self.seconds = 0.0  # building indexes

    def torus(self, reach=None):
        if reach not in self.tori:
            t0 = time.perf_counter()
            emb = Embedding.make(self.box, self.per, reach)
            self.tori[reach] = emb, build_index(emb.to_internal(self.pts))
            self.seconds += time.perf_counter() - t0
        return self.tori[reach]

    def find(self, k, factor):
        """(embedding, index, (m0, order, grid)) for the first torus that works, or None."""
        emb, index = self.torus()
        choice = _initial(emb, index, k, factor, self.max_vertices)
        if choice is not None:
            return emb, index, choice
        if all(self.per):
            return None
        lo, hi = emb.box_internal()
        reach = reach_bound(index, lo, hi, k, *emb.period_internal) / emb.scale
        diam = diameter(self.box, self.per)
        for r in (reach, 2.0 * diam, 4.0 * diam, 10.0 * diam):
            emb, index = self.torus(r)
            choice = _initial(emb, index, k, factor, self.max_vertices)
            if choice is not None:
                return emb, index, choice
        return None

    def refusal(self, k, tau):
        """The message for an input no torus can start: what failed and what would work."""
        factor = reach_factor(tau)
        k_max, f_min = largest_passing(lambda kk, f: self.find(kk, f) is not None, k, factor)
        emb = self.torus()[0]
        mode = {(True, True): "periodic", (False, False): "ordinary"}.get(
            emb.periodic, f"periodic={emb.periodic}"
        )
        options = []
        if k_max >= 1:
            options.append(f"use k <= {k_max} (the largest k certifiable here at tau = {tau:g})")
        if f_min is not None and tau_for_factor(f_min) > 2.0:
            options.append(
                f"use tau <= {np.floor(tau_for_factor(f_min) * 1000) / 1000:g} with k = {k}"
            )
        if any(self.per):
            options.append("make the shorter periodic side of the box longer")
        return (
            f"k = {k} cannot be certified for these {len(self.pts)} points in the {mode} box "
            f"{emb.box} at tau = {tau:g}: Theorem 6's lower bound needs d_Pk <= {factor:.3g} "
            "x the distance to the nearest earlier vertex at every initial mesh vertex, and no "
            "valid initial mesh of the torus meets it (its spacing cannot exceed about a third "
            f"of the torus' shorter period, {min(emb.period) / 3.0:.3g}); " + ", or ".join(options)
        )


def _assemble(res, emb, k, tau, min_size, run, m0_stats):
    out_v, out_s, pos, tri, offsets = unfold(res.vxy, res.tv, res.to, emb)
    L = np.array(emb.period_internal)
    floor_t = res.tstate == R.FLOOR
    floor_v = res.vcell == R.FLOOR
    floor_int = np.concatenate([res.tcc[floor_t], res.vxy[floor_v]])
    floor_pts = emb.to_input(wrap(floor_int, L)) if len(floor_int) else np.zeros((0, 2))
    stats = {
        "n": run.n,
        "m": int(len(out_v)),
        "m_torus": int(res.vxy.shape[0]),
        "triangles": int(len(tri)),
        **res.counters,
        "floor_circumballs": int(floor_t.sum()),
        "floor_cells": int(floor_v.sum()),
        "clean_floor": int(np.count_nonzero(res.vflag & R.CLEAN_FLOOR)),
        "m0": m0_stats,
    }
    torus = Torus(
        origin=tuple(float(o) for o in emb.origin),
        period=emb.period,
        vertices=res.vxy / emb.scale,
        triangles=res.tv,
        offsets=res.to,
        neighbors=res.tn,
        kinds=res.kind,
    )
    return Mesh(
        vertices=emb.to_input(pos),
        triangles=tri.astype(np.int32),
        offsets=None if offsets is None else offsets.astype(np.int8),
        kinds=res.kind[out_v],
        order=out_v.astype(np.int64),
        k=k,
        tau=tau,
        periodic=emb.periodic,
        box=emb.box,
        min_size=min_size,
        floor_points=floor_pts,
        stats=stats,
        torus=torus,
    )
