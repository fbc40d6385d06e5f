"""knnrefine.refine: the public entry point."""

import time

import numpy as np

from . import validation as V
from .engine import refine as R
from .engine.driver import Refinement, grid_shape
from .engine.embedding import Embedding, unfold, wrap
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
    k = V.check_k(k)
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

    emb = Embedding.make(box, per)
    nx, ny = grid_shape(*emb.period_internal)
    if nx * ny > max_vertices:
        raise InputError(
            f"the box {box} is too elongated: the initial mesh of the torus alone needs "
            f"{nx} x {ny} vertices (max_vertices={max_vertices}); rescale the coordinates, use "
            "a less elongated periodic box, or raise max_vertices"
        )
    internal = emb.to_internal(pts)
    run = Refinement(
        internal, k, *emb.period_internal, tau, min_size * emb.scale, int(max_vertices)
    )
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
    mesh = _assemble(res, emb, k, tau, min_size, run)
    stats = mesh.stats
    stats["time"] = {
        "index": run.time_index,
        "refine": run.time_refine,
        "assemble": time.perf_counter() - t_assemble,
        "total": time.perf_counter() - t_start,
    }
    return mesh


def _assemble(res, emb, k, tau, min_size, run):
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
        "m0_violations": run.m0_violations,
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
