"""``knnrefine.refine(..., sphere=True)``: kNNRefine on the sphere S^2, behind the same
options as in the plane. Points come as (longitude, latitude) in degrees or as unit vectors;
the engine (``_engine/refine_sphere.py``) refines the spherical Delaunay triangulation from
the regular tetrahedron, counting the points' unit vectors with the 3-D index, in bounded
steps (progress, time limit and Ctrl-C between them), and the result is the one ``Mesh``
with ``domain="sphere"``.

Lemma 2's precondition holds for the tetrahedron whatever the data: its vertices are
109.47 degrees (1.91 rad) apart, and (K - 1) 1.91 >= 3.82 > pi >= d_{P,k} for K >= 3, so
no input is refused for it (docs/algorithm.md, "On the sphere").
"""

import math
import time

import numpy as np
from scipy.spatial import cKDTree

from ..._engine import ahead
from ..._engine.geometry import RESOLUTION_ANGLE
from ..._engine.index import forest_of, points_in
from ..._engine.index3 import build_index3, grow_forest3
from ..._engine.interrupt import Interrupts
from ..._engine.queue import Q_SIZE, Q_USED, new_queue
from ..._engine.refine_sphere import (
    MAX_CAVITY_SPHERE,
    N_PARAMS_SPHERE,
    PS_CLEAN_FLOOR2,
    PS_FLOOR2,
    PS_INFLATE,
    PS_K,
    PS_SLACK2,
    PS_TAU2,
    QUEUE_HEADROOM,
    SLACK2,
    queue_all_sphere,
    queue_unsettled_sphere,
    refine_steps_sphere,
)
from ..._engine.region3 import spatial_order3
from ..._engine.reopen import reopen_by_caps, reopen_sphere
from ..._engine.size import floored_per_site
from ..._engine.state import (
    C_CELL_TESTS,
    C_DISK_TESTS,
    C_ERROR,
    C_FAILED,
    C_MAX_VERTICES,
    C_NT,
    C_NV,
    C_STAMP,
    ERRORS,
    FLOOR,
    GOOD,
    N_COUNTERS,
    STATUS_DONE,
    STATUS_ERROR,
    STATUS_GROW,
    STATUS_MAX_VERTICES,
    STATUS_STEPS,
    UNTESTED,
    Bookkeeping,
    Queues,
    grown,
)
from ..._engine.triangulation_sphere import neighbours_of, new_sphere, new_sphere_scratch
from ..._metric import angle_to_chord, chord_to_angle, lonlat_of, points_in_balls, unit_vectors
from ..._options import Progress, SphereOptions, check_size, check_sphere_run, warn_floor
from ..._validation import as_sphere_points
from ...errors import BudgetError, EngineError
from ...mesh import Mesh, Stats, moves_of
from .. import MERGE_UP_TO

STEPS = 20_000  # insertions per kernel call
MAX_DEGREE = 256
STAMP_LIMIT_SPHERE = 2**30  # a kernel call makes at most STEPS insertions: far below 2^31
CAPS_FROM = 0.5  # new points per triangle above which a continuation tests every circumcap


class SphereRun:
    """The engine's arrays for one run (grown in place of their fields)."""

    def __init__(self, cap_v, cap_t, cap_q):
        self.mesh, nv, nt = new_sphere(cap_v, cap_t)
        self.book = Bookkeeping(
            ball_state=np.zeros(cap_t, np.int8),
            kinds=np.zeros(cap_v, np.int8),
            cell_state=np.zeros(cap_v, np.int8),
            flags=np.zeros(cap_v, np.int8),
        )
        self.queues = Queues(new_queue(cap_q), new_queue(cap_q), new_queue(cap_q))
        self.scratch = new_sphere_scratch(cap_v, cap_t, MAX_CAVITY_SPHERE, MAX_DEGREE)
        self.cnt = np.zeros(N_COUNTERS, np.int64)
        self.cnt[C_NV] = nv
        self.cnt[C_NT] = nt

    def grow(self):
        """Double whatever is nearly full: the vertex and triangle arrays, the queues."""
        cap_v = self.mesh.xyz.shape[0]
        cap_t = self.mesh.corners.shape[0]
        if self.cnt[C_NV] + 64 > cap_v or self.cnt[C_NT] + 128 > cap_t:
            v2, t2 = 2 * cap_v, 2 * cap_t
            self.mesh = self.mesh._replace(
                **{f: grown(getattr(self.mesh, f), t2)
                   for f in ("corners", "neighbours", "chord2", "gen")},
                **{f: grown(getattr(self.mesh, f), v2) for f in ("xyz", "star")},
            )  # fmt: skip
            self.book = self.book._replace(
                ball_state=grown(self.book.ball_state, t2),
                **{f: grown(getattr(self.book, f), v2) for f in ("kinds", "cell_state", "flags")},
            )
            self.scratch = self.scratch._replace(
                mark=grown(self.scratch.mark, t2),
                vmark=grown(self.scratch.vmark, v2),
                vnext=grown(self.scratch.vnext, v2),
            )
        queues = []
        for q in self.queues:
            cap = q.ident.shape[0]
            if q.scalars[Q_USED] + 2 * QUEUE_HEADROOM > cap:
                q = q._replace(
                    **{f: grown(getattr(q, f), 2 * cap) for f in ("ident", "aux", "next")}
                )
            queues.append(q)
        self.queues = Queues(*queues)

    def restart_stamps(self):
        """Past STAMP_LIMIT_SPHERE insertions the 32-bit stamps start again from 0."""
        if self.cnt[C_STAMP] > STAMP_LIMIT_SPHERE:
            self.scratch.mark[:] = 0
            self.scratch.vmark[:] = 0
            self.cnt[C_STAMP] = 0

    def pending(self):
        return int(sum(q.scalars[Q_SIZE] for q in self.queues))

    def step(self, prm, index, steps):
        return refine_steps_sphere(self.mesh, self.book, self.queues, self.scratch, self.cnt,
                                   prm, index, steps)  # fmt: skip


def checked(points, weights, **asked) -> tuple[np.ndarray, np.ndarray | None, SphereOptions]:
    """The points as unit vectors (n, 3), weights and options of a run on the sphere,
    checked before any work (``options.check_sphere_run``; ``asked`` as ``knnrefine.refine``
    takes them)."""
    return check_sphere_run(points, weights, **asked)


def refine(xyz_p: np.ndarray, w: np.ndarray | None, opt: SphereOptions) -> Mesh:
    """A run on the sphere in this process on checked unit vectors, weights and options
    (``checked``), through ``pipeline.refine_checked``.

    Returns
    -------
    Mesh
    """
    report = Progress(opt.progress)
    with ahead.compiling("sphere", report.compiling):
        return _refine(xyz_p, w, opt, report)


def _refine(xyz_p, w, opt, report):
    """``refine`` in the compiling notice's scope (a continued run's ``xyz_p`` and ``w``
    are its new points alone: ``_continued``)."""
    every, w_all = (lambda: xyz_p), w
    if opt.start is not None:
        every, w_all = _every_point(xyz_p, opt), opt.given_weights
    total = None if w_all is None else math.fsum(w_all)
    n = len(xyz_p) if opt.start is None else len(opt.given)
    budget = opt.max_vertices if opt.max_vertices is not None else max(10**6, 4 * n)
    mass = n if total is None else total
    estimated = estimate_sphere(n, mass, opt)
    check_size(estimated, opt, n)  # the k = 1 notice, refusals and warnings of every domain
    prm = np.zeros(N_PARAMS_SPHERE)
    prm[PS_TAU2] = opt.tau**2 * (1.0 - 1e-12)
    prm[PS_FLOOR2] = angle_to_chord(opt.floor_angle) ** 2
    prm[PS_CLEAN_FLOOR2] = angle_to_chord(RESOLUTION_ANGLE) ** 2
    prm[PS_INFLATE] = 1.0 + 1e-9
    prm[PS_K] = float(opt.k)
    prm[PS_SLACK2] = SLACK2
    continued = None
    if opt.start is None:
        index = forest_of(build_index3(xyz_p, copy=False, weights=w))  # over unit vectors
        # room for 3 (n / k) vertices, a little more than the estimate, grown when short
        first = int(max(1024, min(budget, 3.0 * mass / max(opt.k, 1e-300) + 1024)))
        run = SphereRun(first, 2 * first, first + 4 * QUEUE_HEADROOM)
        queue_all_sphere(run.mesh, run.book, run.queues, run.scratch, run.cnt)
    else:
        index, run, continued = _continued(xyz_p, w, opt, every)
    run.cnt[C_MAX_VERTICES] = budget
    t0 = time.perf_counter()
    with Interrupts() as interrupts:
        while True:
            run.restart_stamps()
            status = run.step(prm, index, STEPS)
            interrupts.check()
            if status == STATUS_GROW:
                run.grow()
                continue
            if status == STATUS_STEPS:
                report.refining(int(run.cnt[C_NV]), run.pending())
                if opt.deadline is not None and time.perf_counter() > opt.deadline:
                    raise BudgetError(
                        f"time_limit reached with {int(run.cnt[C_NV]):,} vertices; raise "
                        "time_limit, or use a larger k or min_size",
                        progress=_progress(run, t0),
                    )
                continue
            if status == STATUS_MAX_VERTICES:
                hint = (
                    "k = 1 refines every input point down to min_size: use k >= 2 or a larger "
                    "min_size"
                    if opt.k == 1
                    else "use a larger k or min_size"
                )
                raise BudgetError(
                    f"the mesh reached max_vertices={budget:,}; {hint}, or raise max_vertices",
                    progress=_progress(run, t0),
                )
            if status == STATUS_ERROR:
                code = int(run.cnt[C_ERROR])
                raise EngineError(
                    f"the refinement on the sphere broke an invariant: "
                    f"{ERRORS.get(code, code)}; please report it with the input"
                )
            if status == STATUS_DONE:
                break
    t1 = time.perf_counter()
    report.assembling(int(run.cnt[C_NV]))
    times = {"setup": t0 - opt.t_start, "refine": t1 - t0}
    mesh = _assemble(run, opt, index, times, n, every, total, budget, estimated)
    if continued is not None:
        mesh.stats.continued = continued
    mesh.stats.time = {**times, "assemble": time.perf_counter() - t1,
                       "total": time.perf_counter() - opt.t_start}  # fmt: skip
    report.assembling(len(mesh.vertices), done=True)
    return mesh


def _continued(new, w, opt, every):
    """(index, run, the stats' ``continued``) of a run continued from the mesh ``opt.start``
    with the new points ``new`` (unit vectors) and weights ``w`` (checked by
    ``pipeline.checked``; ``every()`` gives all the points' unit vectors), as in the
    plane: the start's index with the new points in its second tree (``index.grow_forest``;
    built afresh for a mesh read from a file), its triangulation taken as it is, every
    element settled but those the new points reach (``reopen.reopen_sphere``, or
    ``reopen_by_caps`` for many), which are queued."""
    start = opt.start
    n0 = int(start.stats.n)
    kept = None if start.index is None else forest_of(start.index)
    index = None
    if kept is not None and points_in(kept) == n0:
        if not len(new):
            index = kept
        elif len(new) <= MERGE_UP_TO * n0:  # the new points in a second tree
            index = grow_forest3(kept, new, w)
    if index is None:
        index = forest_of(build_index3(every().copy(), copy=False, weights=opt.given_weights))
    xyz = np.ascontiguousarray(start.xyz, np.float64)
    tri = np.ascontiguousarray(start.cells, np.int32)
    nv, nt = len(xyz), len(tri)
    grown_by = len(new) / max(n0, 1)
    cap_v = int(max(1024, nv * (1.0 + 2.0 * grown_by) + 1024))
    run = SphereRun(max(cap_v, nv + 64), max(2 * cap_v, nt + 128), nt + cap_v + 4 * QUEUE_HEADROOM)
    mesh = run.mesh
    mesh.xyz[:nv] = xyz
    mesh.corners[:nt] = tri
    mesh.neighbours[:nt] = neighbours_of(tri)
    mesh.chord2[:nt] = circumcap_chords2(xyz, tri)
    mesh.gen[:nt] = 0
    mesh.star[tri[:, 0]] = np.arange(nt, dtype=np.int32)
    mesh.star[tri[:, 1]] = np.arange(nt, dtype=np.int32)
    mesh.star[tri[:, 2]] = np.arange(nt, dtype=np.int32)
    run.cnt[C_NV], run.cnt[C_NT] = nv, nt
    run.book.kinds[:nv] = start.kinds
    run.book.ball_state[:nt] = GOOD
    run.book.cell_state[:nv] = GOOD
    if len(start.floor_points):  # reopened too: they stay at the floor, reported again
        new = np.concatenate([new, unit_vectors(start.floor_points)])
    reopened = 0
    if len(new) > CAPS_FROM * nt:  # many points a triangle: test each circumcap
        reopened = reopen_by_caps(mesh, run.book, run.scratch, build_index3(new), nt)
    elif len(new):
        order = spatial_order3(np.ascontiguousarray(new + 1.0), np.full(3, 2.0))
        reopened = reopen_sphere(np.ascontiguousarray(new[order]), mesh, run.book, run.scratch,
                                 run.cnt)  # fmt: skip
        if reopened < 0:  # a lost walk or a huge cavity: look at everything again
            run.book.ball_state[:nt] = UNTESTED
            run.book.cell_state[:nv] = UNTESTED
            reopened = nt
        run.restart_stamps()
    queue_unsettled_sphere(mesh, run.book, run.queues, run.scratch, run.cnt)
    return index, run, {"points": len(new), "from_vertices": nv, "reopened": int(reopened)}


def _every_point(new, opt):
    """A function giving the unit vectors of every point of a run continued with the new
    ones ``new`` (``opt.given``: all of them as given), converted when first asked for."""
    kept = []

    def every():
        if not kept:
            n0 = int(opt.start.stats.n)
            kept.append(np.concatenate([as_sphere_points(opt.given[:n0]), new]))
        return kept[0]

    return every


def circumcap_chords2(xyz, tri):
    """Each triangle's squared circumcap chord as ``triangulation_sphere.set_circumcap``
    finds it (the same arithmetic, in numpy): the largest squared distance from the cap's
    centre to a corner."""
    a, b, c = xyz[tri[:, 0]], xyz[tri[:, 1]], xyz[tri[:, 2]]
    ba, ca = b - a, c - a
    normal = np.stack([ba[:, 1] * ca[:, 2] - ba[:, 2] * ca[:, 1],
                       ba[:, 2] * ca[:, 0] - ba[:, 0] * ca[:, 2],
                       ba[:, 0] * ca[:, 1] - ba[:, 1] * ca[:, 0]], axis=1)  # fmt: skip
    norm = np.sqrt(normal[:, 0] ** 2 + normal[:, 1] ** 2 + normal[:, 2] ** 2)
    centre = normal / norm[:, None]
    out = np.zeros(len(tri))
    for p in (a, b, c):
        d = p - centre
        out = np.maximum(out, d[:, 0] ** 2 + d[:, 1] ** 2 + d[:, 2] ** 2)
    return out


def estimate_sphere(n, mass, opt):
    """The vertices a run on the sphere is expected to make: about 2.5 (n / k) on uniform
    points (1.8x more at k = 3, right from k = 10), and for k = 1 every point refined
    around down to the floor (the plane's count of it)."""
    if opt.k == 1:
        spacing = math.sqrt(4.0 * math.pi / n)
        octaves = max(1.0, math.log2(max(spacing / opt.floor_angle, 2.0)))
        return n * floored_per_site(octaves, 2) + 64.0
    return 2.5 * mass / opt.k


def _points_under_floor(points, xyz, corners, chord2, normal, floor_t, floor_v):
    """How many input points (unit vectors: ``points()``) lie in a floor element: a floor circumcap
    (centre ``normal``), or the cap of chord R(v) about a floor cell's vertex (R(v): the
    largest circumcap chord of the triangles at v, whose caps cover v's Voronoi cell): the
    rule of every domain (``metric.points_in_balls``)."""
    if not len(floor_t) and not len(floor_v):
        return 0
    reach2 = np.zeros(len(xyz))
    for i in range(3):
        np.maximum.at(reach2, corners[:, i], chord2)
    centres = np.concatenate([normal, xyz[floor_v]])
    radii = np.sqrt(np.concatenate([chord2[floor_t], reach2[floor_v]]))
    return points_in_balls(cKDTree(points()), centres, radii)


def _progress(run, t0):
    nv = int(run.cnt[C_NV])
    kinds = run.book.kinds[:nv]
    return {
        "vertices": nv,
        "moves": moves_of(kinds),
        "seconds": time.perf_counter() - t0,
    }


def _assemble(run, opt, index, times, n, points, total, budget, estimated):
    """The Mesh of a finished run: ``n`` points, ``points()`` their unit vectors (asked
    only when elements were left below the floor)."""
    nv, nt = int(run.cnt[C_NV]), int(run.cnt[C_NT])
    xyz = run.mesh.xyz[:nv].copy()
    kinds = run.book.kinds[:nv].copy()
    floor_t = np.flatnonzero(run.book.ball_state[:nt] == FLOOR)
    floor_v = np.flatnonzero(run.book.cell_state[:nv] == FLOOR)
    a, b, c = (xyz[run.mesh.corners[floor_t, i]] for i in range(3))
    normal = np.cross(b - a, c - a)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    sites = np.concatenate([normal, xyz[floor_v]])
    chord2 = run.mesh.chord2[:nt]
    under = _points_under_floor(points, xyz, run.mesh.corners[:nt], chord2, normal, floor_t,
                                floor_v)  # fmt: skip
    warn_floor(under, n, opt.k, opt.min_size, "pi 1e-6 radians (20 m on the Earth)")
    stats = Stats(
        n=n, weight=total, m=nv, m_torus=nv, cells=nt,
        initial_vertices=int(np.count_nonzero(kinds == 0)),
        moves=moves_of(kinds),
        circumball_tests=int(run.cnt[C_DISK_TESTS]), cell_tests=int(run.cnt[C_CELL_TESTS]),
        failed_insertions=int(run.cnt[C_FAILED]),
        floor_circumballs=int(len(floor_t)), floor_cells=int(len(floor_v)),
        points_under_floor=under,
        largest_circumball=float(chord_to_angle(np.sqrt(chord2.max()))) * opt.radius,
        estimated_vertices=int(estimated),
        max_vertices=int(budget),
    )  # fmt: skip
    return Mesh(
        vertices=lonlat_of(xyz),
        cells=run.mesh.corners[:nt].copy(),
        offsets=None,
        kinds=kinds,
        order=np.arange(nv, dtype=np.int64),
        k=opt.k,
        tau=opt.tau,
        periodic=(),
        box=(),
        min_size=opt.min_size,
        floor_points=lonlat_of(sites).reshape(-1, 2),
        stats=stats,
        torus=None,
        index=index,
        domain="sphere",
        radius=opt.radius,
        xyz=xyz,
    )
