"""certify(mesh, points): check a mesh against Theorem 6, independently of the engine, in the
plane (``plane``: the torus triangulation verified in exact arithmetic, counts, ratios, the
floor) or in space (``space``); what both share is in ``common``. Nothing here calls the
refinement kernels: counts and distances come from scipy's cKDTree."""

import time

import numpy as np

from ..errors import InputError
from ..validation import as_points
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
    samples=100_000,
    n_random=20_000,
    max_point_probes=100_000,
    seed=0,
    workers=-1,
    weights=None,
    tiles=None,
):
    """Check ``mesh`` (from ``knnrefine.refine``) against ``points`` (the same P, with the
    same ``weights`` for a weighted run: counts are then sums of weights, d_{P,k} the least
    radius holding weight k, all from scipy's cKDTree, never the engine).

    Probes: ``samples`` stratified random points inside the mesh triangles (at least 4 per
    triangle: dense where d_{P,k} is small, which is where the ratio has its extremes), every
    vertex, circumcenter and edge midpoint, up to ``max_point_probes`` input points and
    ``n_random`` uniform points of the box. Returns a Certificate; nothing is raised when a
    check fails (look at ``.passed``). ``workers`` is passed to cKDTree queries (-1: all
    cores). ``tiles``: ask every question about the points strip by strip in that many local
    processes (``certify_store``; what ``distributed.certify`` does on a cluster), same
    checks, same verdict. The checks, in order: the returned points are the mesh's (else
    InputError), the torus triangulation, the returned mesh, well-spacedness, counts, Lemma
    2's precondition, the achieved constants, the size integral, the floor."""
    if mesh.dim == 3:  # in space: space.certify3's checks
        if weights is not None or tiles is not None:
            raise InputError(
                "weights and tiles are not built for (n, 3) points yet: certify a 3-D mesh "
                "without them (refine in space takes no weights either)"
            )
        return certify3(mesh, points, samples=samples, n_random=n_random,
                        max_point_probes=max_point_probes, seed=seed, workers=workers)  # fmt: skip
    t0 = time.perf_counter()
    pts = as_points(points)
    weights = check_points_are_the_meshs(mesh, pts, weights)
    options = dict(samples=samples, n_random=n_random, max_point_probes=max_point_probes,
                   seed=seed, t0=t0)  # fmt: skip
    if tiles is None:
        return run_checks(mesh, TorusPoints(mesh, pts, workers, weights), **options)
    if isinstance(tiles, bool) or not isinstance(tiles, (int, np.integer)) or tiles < 1:
        raise InputError(f"tiles must be a positive integer (strips of points), got {tiles!r}")
    from ..engine.partition import LocalStore

    store = LocalStore(pts, weights, int(tiles))
    try:
        return run_checks(mesh, TiledTorusPoints(mesh, store, int(tiles), workers), **options)
    finally:
        store.close()
