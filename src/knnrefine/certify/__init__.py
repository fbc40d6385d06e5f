"""Checks of a mesh against Theorem 6, independently of the refinement: the steps written once
(``steps.run_checks``) over each domain's answers (``domains.<domain>.certify``: a
``Geometry`` of the mesh and the ``Points``' questions in each); what the box domains share
is in ``common``, the ``Certificate`` in ``certificate``. Nothing here calls the refinement
kernels: counts and distances come from kd-trees. ``knnrefine.certify`` (``api.certify``)
checks its options and calls ``certify_points`` in this process, or ``scale.checks`` strip
by strip in worker processes (the same steps, the points' questions asked where they are)."""

import time

from ..domains import part
from . import steps
from .certificate import Certificate
from .common import check_precondition, check_source

__all__ = [
    "certify_points",
    "Certificate",
    "check_source",
    "check_precondition",
]


def certify_points(
    mesh, points, *, samples=100_000, n_random=20_000, max_point_probes=100_000,
    random_state=0, weights=None, workers=-1,
) -> Certificate:  # fmt: skip
    """``knnrefine.certify`` in this process: the points checked to be the mesh's, then
    ``steps.run_checks`` with the mesh's domain's geometry and points; the caller has
    checked ``workers`` (threads: -1 for every core).

    Parameters
    ----------
    mesh, points, samples, n_random, max_point_probes, random_state, weights, workers
        As for ``knnrefine.certify``.

    Returns
    -------
    Certificate
    """
    t0 = time.perf_counter()
    domain = part(mesh.domain, "certify")
    pts, weights = domain.checked_points(mesh, points, weights)
    geometry: steps.Geometry = domain.Geometry(mesh, workers)
    answers: steps.PointQuestions = domain.Points(mesh, pts, weights, workers)
    return steps.run_checks(mesh, geometry, answers, samples=samples, n_random=n_random,
                            max_point_probes=max_point_probes, random_state=random_state,
                            t0=t0)  # fmt: skip
