"""knnrefine's two entry points, ``refine`` and ``certify``, documented here: refine runs
the pipeline (``pipeline.refine``: the domain decided, everything checked, then a run in
this process, in threads or on an executor); certify checks its options and runs in this
process (``certify``) or over worker processes (``scale``)."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Executor

import numpy as np
from numpy.typing import ArrayLike

from . import _pipeline as pipeline
from . import _validation as V
from ._domains import domain_of
from .certify import Certificate
from .errors import InputError
from .mesh import Mesh


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
    workers: int | None = None,
    executor: Executor | None = None,
    sphere: bool = False,
    radius: float | None = None,
    start: Mesh | None = None,
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
    k : int, 1 <= k <= n, optional
        Which nearest neighbour: d_{P,k}(x) is the distance from x to its k-th nearest point.
        Default: sqrt(n) / 2, at least 10 and at most n (n the total weight with weights;
        ``knnrefine.density.default_k``), what clustering and persistence need not tune.
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
        resolution, which ``Mesh.min_size`` then reports. On the sphere: a great-circle
        length in ``radius`` units, default pi 1e-6 radians (20 m on the Earth), and the
        engine's resolution is 2^-20 radians (6.1 m on the Earth: below it the rounding of
        unit vectors is the size of the caps).
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
        None or 1: one run in this process, whose kernels use every core for the index, the
        bulk counts and the assembly (``KNNREFINE_THREADS`` caps them); the mesh does not
        depend on the cores. N > 1: a tiled run in N threads of this process where tiles
        pay, all counting in one index of all points (the kernels release the GIL): from
        ``scale.tiled.TILES_FROM`` points on (2 x 10^6 in the plane, 3 x 10^5 in space), N
        strips of the torus (slabs in space), balanced by point count, each refining only
        what lies inside it (``_engine/region.py``), then a seam at each cut, in turns, each
        tile keeping its mesh and inserting only the others' vertices near it; the meshes
        are stitched into one triangulation (checked: every facet has its twin) and one last
        run finishes what no tile could decide (docs/algorithm.md, "In threads, stitched":
        the same guarantees, certified by ``certify``). Below that size N > 1 runs the one
        process of None, which is faster there (docs/benchmarks.md, "Workers in threads");
        ``KNNREFINE_TILES=always`` tiles at every size. A tiled mesh differs from
        a one-process run's in the order of its moves, and its size by a few percent;
        ``stats["rounds"]`` reports each turn and the last step; ``time_limit`` and
        ``max_vertices`` hold in every tile. On this project's 2-core machine the stitched
        strips are 1.04-1.14x faster than one process at 4 x 10^6 points and 1.23-1.48x
        faster than one core (``KNNREFINE_THREADS=1``); the slabs in space
        1.15-1.41x faster than one process at 10^6 points (k = 10 and 100), 1.09x faster on
        10^6 points on a plane in space (docs/benchmarks.md).
        On the sphere there are no tiles yet: N > 1 runs the one process of None.
    executor : concurrent.futures.Executor, optional
        Run the tiles of a run with ``workers`` > 1 on this executor instead (processes or
        machines, each tile with a copy of its strip's points): its ``map`` is called once
        per round with that round's tiles (a ``ProcessPoolExecutor``, or a Dask client's
        ``get_executor()``: ``knnrefine.scale.distributed.refine``).

    sphere : bool
        Refine on the sphere S^2 (geographic or sky data): points are (n, 2) longitude and
        latitude in degrees (or (n, 3) unit vectors), every distance is great-circle, and the
        guarantee holds on the whole sphere (no box, no periodic axes; docs/algorithm.md, "On
        the sphere"). The mesh has ``domain="sphere"``, vertices in longitude/latitude,
        ``xyz`` unit vectors and ``triangles`` over them. In this process (``workers`` are
        its threads; ``executor`` is refused).
    radius : float, optional
        On the sphere, its radius in the unit lengths are wanted in (``min_size``,
        ``Mesh.d_m2``): 1 (the default) gives angles in radians, 6371.0088 kilometres on the
        Earth.
    start : Mesh, optional
        Continue this mesh with points that arrived since: ``points`` are the ones it was
        refined from, in the order given then (with their weights), followed by the new
        ones. Adding points only lowers d_{P,k}, so every move the start made is one a run
        on all the points may make; the run goes on from the start's mesh, looking again
        only at the circumballs and cells the new points lie in, and returns what refine
        guarantees for all the points (``certify`` checks it). The run keeps the start's k,
        tau, box, periodic axes, floor (and radius): options left out are the start's, one
        given must be the same. InputError, before any work, for a start of another domain
        or options, first rows that are not its points (``Stats.points_digest``), and new
        points outside an ordinary box (give the first run a box that holds what will
        come). In every domain; the start's first rows are verified by their digest, not
        checked again, and its kd-tree is kept and grown, not built again. A continued
        run's work is where the new points are: it runs in this process (``workers`` and
        ``executor`` are not used; its index, sweeps and assembly use the threads they
        always do); ``distributed.refine`` does not continue a start yet.

    Returns
    -------
    Mesh

    Ctrl-C raises KeyboardInterrupt within about 50 ms of refinement (within the current
    kernel call during setup).

    Points in space ((n, 3), a box of six numbers, ``periodic`` a bool or three) are refined
    by ``domains.space.run`` into the same ``Mesh`` type, weights, workers and executor (slabs)
    included.
    """
    if isinstance(start, Mesh) and start.on_sphere:  # a start on the sphere says where
        sphere = True
    domain = domain_of(points, sphere, radius)
    tiles = V.check_workers(workers)
    V.check_executor(executor, tiles, domain)
    pts, w, opt = pipeline.checked(domain, points, weights, k=k, tau=tau, periodic=periodic,
                                   box=box, min_size=min_size, max_vertices=max_vertices,
                                   time_limit=time_limit, progress=progress,
                                   radius=radius, start=start)  # fmt: skip
    if tiles > 1 and start is None:  # tiles where they pay
        from .scale.shared import refine_local
        from .scale.tiled import tiles_pay

        if executor is not None or tiles_pay(domain, len(pts)):
            mesh = refine_local(pts, w, opt, tiles, executor)
            mesh.stats.points_digest = opt.points_digest
            return mesh
    return pipeline.refine_checked(pts, w, opt)


def certify(
    mesh: Mesh,
    points: ArrayLike,
    *,
    samples: int = 100_000,
    n_random: int = 20_000,
    max_point_probes: int = 100_000,
    random_state: int | np.random.Generator | np.random.RandomState | None = 0,
    weights: ArrayLike | None = None,
    workers: int | None = None,
    executor: Executor | None = None,
) -> Certificate:
    """Check a mesh against Theorem 6, independently of the engine, in every domain.

    Counts and d_{P,k} come from certify's own kd-tree over the points, never the engine's
    index (with weights, counts are sums of weights and d_{P,k} the least radius holding
    weight k; with ``executor``, strip by strip from scipy's cKDTree). The checks, in order: the
    points are the mesh's (else InputError), the torus triangulation, the returned mesh,
    well-spacedness, counts, Lemma 2's precondition, the achieved constants, the size
    integral, the floor.

    Parameters
    ----------
    mesh : Mesh
        From ``knnrefine.refine``.
    points : array-like (n, d)
        The points it was refined from.
    samples : int
        Random probes inside the cells: one in each of ``samples`` cells of a large mesh,
        ``samples`` // t in each of the t cells of a small one (the size integral reads one
        in each of ``samples`` // 4 cells, all where fewer, beside its control variate, the
        integrand's mean over each cell's corners; the others probe the ratio, asked only
        where their bounds could reach an extreme); every vertex and edge midpoint is probed
        too.
    n_random : int
        Uniform probes in the box (on the sphere, on the whole sphere).
    max_point_probes : int
        Input points probed, at most.
    random_state : None, int, numpy Generator or RandomState
        Where the probes' random draws come from (0: the same probes every call).
    weights : array-like (n,), optional
        The weights of a weighted run (required for one, refused otherwise).
    workers : int, optional
        Threads of this process for the kd-tree questions, as refine's and scipy's
        ``workers``: None (every core) or N. With ``executor``, the number of strips the
        points' questions are asked in.
    executor : concurrent.futures.Executor, optional
        Ask the questions about the points strip by strip (``workers`` >= 2 strips), each a
        task of this executor (local processes; ``scale.distributed.certify`` on a Dask
        cluster): the same checks, the same verdict. In a box only: the sphere has no strips.

    Returns
    -------
    Certificate
        Nothing is raised when a check fails: look at ``.passed``.

    Raises
    ------
    InputError
        Points, weights or options that are not the mesh's or not valid.
    """
    _check_certifiable(mesh)
    rng = V.random_generator(random_state)  # refused before any work, drawn from once
    strips = V.check_workers(workers)
    V.check_executor(executor, strips, getattr(mesh, "domain", None))
    options = dict(samples=samples, n_random=n_random, max_point_probes=max_point_probes,
                   random_state=rng)  # fmt: skip
    if executor is None:
        threads = -1 if workers is None else strips
        return pipeline.certify_points(mesh, points, weights=weights, workers=threads, **options)
    from .scale.checks import certify_local

    return certify_local(mesh, points, weights, strips, executor, **options)


def _check_certifiable(mesh):
    """A Mesh that carries what certify checks: in a box its torus mesh (what the engine
    refined, which refine returns with every mesh and .npz files keep), on the sphere its
    unit vectors; else InputError, before any work."""
    if not isinstance(mesh, Mesh):
        raise InputError(
            f"certify takes a knnrefine.Mesh (from refine or io.read_mesh), got "
            f"{type(mesh).__name__}"
        )
    if mesh.on_sphere:
        V.check_radius(mesh.radius)
        if mesh.xyz is None:
            raise InputError(
                "this sphere mesh has no unit vectors (Mesh.xyz is None): certify checks the "
                "vectors the engine triangulated; use the mesh refine returned or its .npz file"
            )
    elif mesh.torus is None:
        raise InputError(
            "this mesh has no torus mesh (Mesh.torus is None): certify checks the torus "
            "triangulation the engine refined, which refine returns with every mesh and .npz "
            "files keep; use that mesh, or io.read_mesh of its .npz file (.vtu and .geojson "
            "files do not carry it)"
        )
