"""``knnrefine.refine`` for points in space ((n, 3) points, a box of six numbers): the
engine's 3-D run (``engine/driver3.py``) behind the same options as in the plane. Along
non-periodic axes the box is embedded in a longer torus, as in the plane
(``engine/embedding.py``), and the mesh unfolded back (``embedding.unfold``)."""

import time

import numpy as np

from . import validation as V
from .api import _past, check_options
from .engine.driver3 import Refinement3, choose_grid3
from .engine.embedding import Embedding, diameter, unfold
from .engine.index3 import build_index3, holds_k_within3
from .engine.initial import reach_factor
from .engine.refine import STATUS_DONE, STATUS_MAX_VERTICES
from .engine.state import C_CELL_TESTS, C_DISK_TESTS, C_FAILED
from .errors import BudgetError, InputError
from .mesh3 import Mesh3, Torus3
from .metric import BoxMetric


def _holds(index, x, reach, k, period):
    """Whether the closed ball of radius ``reach`` about each x holds >= k of the index's
    points (the index answers below half the shortest period; a ball reaching every point
    of the torus holds all of them; between the two, a direct count over its points)."""
    u = index[0]
    reach = np.asarray(reach, float)
    out = reach >= np.sqrt(((period / 2.0) ** 2).sum())  # the torus' diameter: every point
    small = ~out & (reach < 0.5 * period.min() * (1.0 - 1e-9))
    out[small] = holds_k_within3(index, x[small], reach[small] ** 2, float(k), period)
    for i in np.flatnonzero(~out & ~small):
        d = np.abs(u - x[i])
        d = np.minimum(d, period - d)
        out[i] = np.count_nonzero((d**2).sum(axis=1) <= reach[i] ** 2) >= k
    return out


def _reach(pts, box, per, k):
    """An upper bound on max d_{P,k} over the box in its own metric: d_{P,k} at the centres
    of 16^3 cells plus half a cell's diagonal (d_{P,k} is 1-Lipschitz)."""
    g = 16
    lo, hi = np.array(box[:3]), np.array(box[3:])
    cell = (hi - lo) / g
    axes = [lo[a] + (np.arange(g) + 0.5) * cell[a] for a in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return float(BoxMetric(box, per).kth(pts, centres, k).max() + 0.5 * np.linalg.norm(cell))


def _start(pts, box, per, k, tau):
    """(embedding, index, M0) for the first torus whose initial mesh meets
    Lemma 2's precondition: the default margin (1.05 x the box's diameter along
    non-periodic axes), then, as in the plane, 1.05 x a bound on max d_Pk over the box and 2,
    4 and 10 diameters. None when none does."""

    def reaches():  # the data bound costs a kd-tree: only when the default torus fails
        yield None
        if not all(per):
            diam = diameter(box, per)
            yield from (_reach(pts, box, per, k), 2.0 * diam, 4.0 * diam, 10.0 * diam)

    for reach in reaches():
        emb = Embedding.make(box, per, reach)
        index = build_index3(emb.to_internal(pts), copy=False)  # the index owns them
        period = np.array(emb.period_internal)

        def holds(x, r, index=index, period=period):
            return _holds(index, x, r, k, period)

        grid = choose_grid3(period, holds, reach_factor(tau), emb.grid)
        if grid is not None:
            return emb, index, grid
    return None


def refine3(points, k, tau=3.0, *, periodic=True, box=None, min_size=None, max_vertices=None,
            time_limit=None, progress=None):  # fmt: skip
    """kNNRefine in a box of three dimensions (``knnrefine.refine`` with (n, 3) points): a
    ``Mesh3`` whose vertices M satisfy alpha d_{P,k} <= d_{M,2} <= beta d_{P,k} in the box,
    tau-well-spaced, no Voronoi cell and no closed circumball holding k points (checked by
    ``certify3``). periodic: a bool or one per axis; box: (x0, y0, z0, x1, y1, z1), required
    when an axis is periodic (points are wrapped into it), else the points' bounding box by
    default. min_size, max_vertices, time_limit, progress: as in the plane."""
    pts = V.as_points(points, 3)
    k, tau, per, box, min_size, deadline, t_start = check_options(
        len(pts), None, lambda: V.default_box(pts), lambda b, p: V.check_inside(pts, b, p), k,
        tau, periodic, box, min_size, max_vertices, time_limit, progress, dim=3,
    )  # fmt: skip

    found = _start(pts, box, per, k, tau)
    if found is None:
        raise InputError(
            f"k = {k} is too large for {len(pts):,} points in this box: no initial mesh of the "
            "3-torus satisfies Lemma 2's precondition (in some order, d_Pk at each initial "
            "vertex at most (K - 1) times its distance to the earlier ones); use a smaller k"
        )
    emb, run_index, grid = found
    del found  # the index must go with the run (take_result), not live on in this tuple
    _past(deadline, "setting up", t_start)
    budget = int(max_vertices) if max_vertices is not None else max(10**6, 4 * len(pts))
    run = Refinement3(run_index, emb.period_internal, k, tau, min_size * emb.scale, budget,
                      grid, emb.grid)  # fmt: skip
    status = run.run(deadline, None if progress is None else (lambda m: progress(m, 0)))
    if status != STATUS_DONE:
        what = (
            f"max_vertices = {budget:,}"
            if status == STATUS_MAX_VERTICES
            else f"time_limit = {time_limit} s"
        )
        raise BudgetError(
            f"stopped at {what} before the mesh was done; raise it, or use a larger k or min_size",
            progress={**run.progress(), "seconds": time.perf_counter() - t_start},
        )
    xyz, corners, offsets, kinds, cnt = run.take_result()
    del run, run_index
    out_v, pos, tetrahedra, out_offsets = unfold(xyz, corners, offsets, emb, copy=False)
    local = pos / emb.scale  # exact: a power of two
    torus = None
    if not all(per):
        torus = Torus3(local=xyz / emb.scale, tetrahedra=corners, offsets=offsets, kinds=kinds)
    return Mesh3(
        vertices=emb.to_input(pos, copy=False), tetrahedra=tetrahedra, offsets=out_offsets,
        kinds=kinds[out_v], k=k, tau=tau, periodic=per, box=box,
        min_size=max(min_size, emb.resolution), origin=tuple(float(o) for o in emb.origin),
        period=emb.period, local=local, order=None if torus is None else out_v, embedded=torus,
        stats={"n": len(pts), "m": len(out_v), "m_torus": len(xyz),
               "disk_tests": int(cnt[C_DISK_TESTS]), "cell_tests": int(cnt[C_CELL_TESTS]),
               "failed": int(cnt[C_FAILED]), "seconds": time.perf_counter() - t_start},
    )  # fmt: skip
