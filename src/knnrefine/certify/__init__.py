"""certify(mesh, points): check a mesh against Theorem 6, independently of the engine, in the
plane (``plane``: the torus triangulation verified in exact arithmetic, counts, ratios, the
floor) or in space (``space``); what both share is in ``common``. Nothing here calls the
refinement kernels: counts and distances come from scipy's cKDTree."""

import time

import numpy as np

from ..errors import InputError
from ..validation import as_points, check_workers
from .certificate import Certificate
from .common import check_precondition, check_source
from .plane import (
    StripQuestions,
    TiledTorusPoints,
    TorusPoints,
    certify_store,
    check_points_are_the_meshs,
    run_checks,
)
from .space import certify3

__all__ = [
    "certify",
    "certify_store",
    "Certificate",
    "StripQuestions",
    "check_source",
    "check_precondition",
]


def certify(
    mesh,
    points,
    *,
    samples: int = 100_000,
    n_random: int = 20_000,
    max_point_probes: int = 100_000,
    seed: int = 0,
    weights=None,
    workers: int | None = None,
    threads: int = -1,
) -> Certificate:
    """Check a mesh against Theorem 6, independently of the engine, in the plane or in space.

    Counts and d_{P,k} come from scipy's cKDTree, never the engine (with weights, counts are
    sums of weights and d_{P,k} the least radius holding weight k). The checks, in order: the
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
        Stratified random probes inside the cells (at least 4 per cell: dense where d_{P,k}
        is small, which is where the ratio has its extremes); every vertex, circumcentre and
        edge midpoint is probed too.
    n_random : int
        Uniform probes in the box.
    max_point_probes : int
        Input points probed, at most.
    seed : int
        The probes' random seed.
    weights : array-like (n,), optional
        The weights of a weighted run (required for one, refused otherwise; the plane).
    workers : int, optional
        Processes: None or 1 asks every question in this process; N > 1 asks the questions
        about the points strip by strip in N local processes (what
        ``scale.distributed.certify`` does on a cluster): same checks, same verdict (the
        plane).
    threads : int
        Threads of the kd-tree queries (-1: all cores).

    Returns
    -------
    Certificate
        Nothing is raised when a check fails: look at ``.passed``.

    Raises
    ------
    InputError
        Points, weights or options that are not the mesh's or not valid.
    """
    workers = check_workers(workers)
    if (
        isinstance(threads, bool)
        or not isinstance(threads, (int, np.integer))
        or not (threads == -1 or threads >= 1)
    ):
        raise InputError(f"threads must be -1 (all cores) or a positive integer, got {threads!r}")
    if mesh.dim == 3:  # in space: space.certify3's checks
        if weights is not None or workers > 1:
            raise InputError(
                "weights and workers > 1 are not built for (n, 3) points yet: certify a 3-D "
                "mesh in one process without them (refine in space takes neither)"
            )
        return certify3(mesh, points, samples=samples, n_random=n_random,
                        max_point_probes=max_point_probes, seed=seed, threads=threads)  # fmt: skip
    t0 = time.perf_counter()
    pts = as_points(points)
    weights = check_points_are_the_meshs(mesh, pts, weights)
    options = dict(samples=samples, n_random=n_random, max_point_probes=max_point_probes,
                   seed=seed, t0=t0)  # fmt: skip
    if workers == 1:
        return run_checks(mesh, TorusPoints(mesh, pts, threads, weights), **options)
    from ..scale.tiled import LocalStore

    store = LocalStore(pts, weights, workers)
    try:
        return run_checks(mesh, TiledTorusPoints(mesh, store, workers, threads), **options)
    finally:
        store.close()
