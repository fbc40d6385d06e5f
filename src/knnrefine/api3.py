"""``knnrefine.refine`` for points in space ((n, 3) points, a box of six numbers): the
engine's 3-D run (``engine/driver3.py``) behind the same options as in the plane. Periodic
boxes first: non-periodic and mixed boxes (the plane's embedding in a larger torus) are not
built yet and are refused with a message."""

import time

import numpy as np

from . import validation as V
from .engine.driver3 import Refinement3, choose_grid3
from .engine.geometry import Q
from .engine.index3 import build_index3, holds_k_within3
from .engine.initial import reach_factor
from .engine.refine import STATUS_DONE, STATUS_MAX_VERTICES
from .engine.state import C_CELL_TESTS, C_DISK_TESTS, C_FAILED
from .errors import BudgetError, InputError
from .mesh3 import Mesh3


def check_box3(box):
    """(x0, y0, z0, x1, y1, z1), finite, each side positive."""
    try:
        b = [float(v) for v in box]
    except (TypeError, ValueError):
        raise InputError(f"box must be six numbers (x0, y0, z0, x1, y1, z1), got {box!r}") from None
    if len(b) != 6 or not np.isfinite(b).all():
        raise InputError(f"box must be six finite numbers (x0, y0, z0, x1, y1, z1), got {box!r}")
    if not all(b[a + 3] > b[a] for a in range(3)):
        raise InputError(f"box {tuple(b)} must have x0 < x1, y0 < y1 and z0 < z1")
    return tuple(b)


def _holds(index, u, x, reach, k, period):
    """Whether the closed ball of radius ``reach`` about each x holds >= k of the points u
    (the index over them answers below half the shortest period; a ball reaching every
    point of the torus holds all of them; between the two, a direct count)."""
    reach = np.asarray(reach, float)
    out = reach >= np.sqrt(((period / 2.0) ** 2).sum())  # the torus' diameter: every point
    small = ~out & (reach < 0.5 * period.min() * (1.0 - 1e-9))
    out[small] = holds_k_within3(index, x[small], reach[small] ** 2, float(k), period)
    for i in np.flatnonzero(~out & ~small):
        d = np.abs(u - x[i])
        d = np.minimum(d, period - d)
        out[i] = np.count_nonzero((d**2).sum(axis=1) <= reach[i] ** 2) >= k
    return out


def refine3(points, k, tau=3.0, *, periodic=True, box=None, min_size=None, max_vertices=None,
            time_limit=None, progress=None):  # fmt: skip
    """kNNRefine in a periodic box of three dimensions (``knnrefine.refine`` with (n, 3)
    points): a ``Mesh3`` whose vertices M satisfy alpha d_{P,k} <= d_{M,2} <= beta d_{P,k}
    on the 3-torus, tau-well-spaced, no Voronoi cell and no closed circumball holding k
    points (checked by ``certify3``). box: (x0, y0, z0, x1, y1, z1), required; points are
    wrapped into it. min_size, max_vertices, time_limit, progress: as in the plane."""
    t_start = time.monotonic()
    pts = V.as_points(points, 3)
    k = V.check_k(k, len(pts))
    tau = V.check_tau(tau)
    per = (periodic,) * 3 if isinstance(periodic, (bool, np.bool_)) else tuple(periodic)
    if len(per) != 3 or not all(bool(p) for p in per):
        raise InputError(
            "in three dimensions only boxes periodic on every axis are built so far "
            "(periodic=True); non-periodic and mixed boxes are not yet supported"
        )
    if box is None:
        raise InputError("a periodic run needs its box: box=(x0, y0, z0, x1, y1, z1)")
    box = check_box3(box)
    lo, side = np.array(box[:3]), np.array(box[3:]) - np.array(box[:3])
    if min_size is not None and not (np.isfinite(min_size) and min_size >= 0):
        raise InputError(f"min_size must be a finite number >= 0, got {min_size!r}")
    if max_vertices is not None and (
        isinstance(max_vertices, bool) or not isinstance(max_vertices, (int, np.integer))
        or max_vertices < 1
    ):  # fmt: skip
        raise InputError(f"max_vertices must be a positive integer, got {max_vertices!r}")
    if time_limit is not None and not (np.isfinite(time_limit) and time_limit > 0):
        raise InputError(f"time_limit must be a positive number of seconds, got {time_limit!r}")

    # internal units: a power-of-two scale (exact) bringing the longest side to at most 1,
    # periods on the grid Q
    scale = 2.0 ** -np.ceil(np.log2(side.max()))
    period = np.rint(side * scale / Q) * Q
    u = np.mod((pts - lo) * scale, period)
    u = np.where(u >= period, u - period, u)
    floor = (1e-6 * side.max() if min_size is None else float(min_size)) * scale
    run_index = build_index3(u)
    grid = choose_grid3(period, lambda x, reach: _holds(run_index, u, x, reach, k, period),
                        reach_factor(tau))  # fmt: skip
    if grid is None:
        raise InputError(
            f"k = {k} is too large for {len(pts):,} points in this box: no initial mesh of the "
            "3-torus satisfies Lemma 2's precondition (in some order, d_Pk at each initial "
            "vertex at most (K - 1) times its distance to the earlier ones); use a smaller k"
        )
    budget = int(max_vertices) if max_vertices is not None else max(10**6, 4 * len(pts))
    deadline = None if time_limit is None else t_start + float(time_limit)
    run = Refinement3(run_index, period, k, tau, floor, budget, grid)
    status = run.run(deadline, None if progress is None else (lambda m: progress(m, 0)))
    if status == STATUS_MAX_VERTICES:
        raise BudgetError(f"stopped at max_vertices = {budget:,} before the mesh was done")
    if status != STATUS_DONE:
        raise BudgetError(f"stopped at time_limit = {time_limit} s before the mesh was done")
    xyz, corners, offsets, kinds, cnt = run.result()
    local = xyz / scale  # exact: a power of two
    return Mesh3(
        vertices=lo + local, tetrahedra=corners, offsets=offsets, kinds=kinds, k=k, tau=tau,
        periodic=(True, True, True), box=box, min_size=floor / scale,
        origin=tuple(lo), period=tuple(period / scale), local=local,
        stats={"n": len(pts), "m_torus": len(xyz), "disk_tests": int(cnt[C_DISK_TESTS]),
               "cell_tests": int(cnt[C_CELL_TESTS]), "failed": int(cnt[C_FAILED]),
               "seconds": time.monotonic() - t_start},
    )  # fmt: skip
