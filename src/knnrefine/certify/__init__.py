"""Checks of a mesh against Theorem 6, independently of the engine, in the plane (``plane``:
the torus triangulation verified in exact arithmetic, counts, ratios, the floor) or in space
(``space``) or on the sphere (``sphere``); what they share is in ``common``, the
``Certificate`` in ``certificate``. Nothing here calls the refinement kernels: counts and
distances come from scipy's cKDTree. ``knnrefine.certify`` (``api.certify``) checks its
options and calls ``certify_points`` in this process, or ``scale.checks`` strip by strip in
worker processes."""

import time

from ..validation import as_points
from .certificate import Certificate
from .common import check_points_are_the_meshs, check_precondition, check_source
from .plane import TorusPoints, run_checks
from .space import certify3
from .sphere import certify_sphere

__all__ = [
    "certify_points",
    "Certificate",
    "check_source",
    "check_precondition",
]


def certify_points(
    mesh, points, *, samples=100_000, n_random=20_000, max_point_probes=100_000, seed=0,
    weights=None, threads=-1,
) -> Certificate:  # fmt: skip
    """``knnrefine.certify`` in this process, in the plane (``plane.run_checks``) or in
    space (``space.certify3``); the caller has checked ``threads``.

    Parameters
    ----------
    mesh, points, samples, n_random, max_point_probes, seed, weights, threads
        As for ``knnrefine.certify``.

    Returns
    -------
    Certificate
    """
    if getattr(mesh, "on_sphere", False):  # on the sphere: sphere.certify_sphere's checks
        return certify_sphere(mesh, points, samples=samples, n_random=n_random,
                              max_point_probes=max_point_probes, seed=seed, weights=weights,
                              threads=threads)  # fmt: skip
    if mesh.dim == 3:  # in space: space.certify3's checks
        return certify3(mesh, points, samples=samples, n_random=n_random,
                        max_point_probes=max_point_probes, seed=seed, weights=weights,
                        threads=threads)  # fmt: skip
    t0 = time.perf_counter()
    pts = as_points(points)
    weights = check_points_are_the_meshs(mesh, pts, weights)
    return run_checks(
        mesh, TorusPoints(mesh, pts, threads, weights), samples=samples, n_random=n_random,
        max_point_probes=max_point_probes, seed=seed, t0=t0,
    )  # fmt: skip
