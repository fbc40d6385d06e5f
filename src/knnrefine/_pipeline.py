"""The run of kNNRefine and its certificate in this process, one path for every domain.

A run: the domain decided once from what ``refine`` is given (``domains.domain_of``:
``sphere``, the points' columns), the points and options checked before any work (the
domain's ``run.checked``), then the domain's run (its ``run.refine``: start, engine,
assembled ``Mesh``). ``api.refine`` calls it (and ``scale`` where workers or an executor
run tiles); the applications that refine (the density estimator, the kNN-CDF) call it too.

A certificate: the points checked to be the mesh's (the domain's
``certify.checked_points``), then certify's steps (``certify.steps.run_checks``) over the
domain's ``Geometry`` and ``Points`` (``certify_points``, which ``api.certify`` calls).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from ._domains import domain_of, part
from .certify import steps
from .certify.certificate import Certificate
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
    sphere: bool = False,
    radius: float | None = None,
) -> Mesh:
    """``knnrefine.refine`` in this process (``api.refine`` documents it; its workers and
    executor run tiles, ``scale``): the domain decided, everything checked before any work,
    then the run.

    Returns
    -------
    Mesh
    """
    domain = domain_of(points, sphere, radius)
    return refine_checked(*checked(domain, points, weights, k=k, tau=tau, periodic=periodic,
                                   box=box, min_size=min_size, max_vertices=max_vertices,
                                   time_limit=time_limit, progress=progress,
                                   radius=radius))  # fmt: skip


def checked(domain: str, points: ArrayLike, weights: ArrayLike | None, **asked) -> tuple:
    """The points, weights and options of a run in ``domain``, checked before any work by
    the domain's ``run.checked``: (pts, weights or None, options), the options' ``domain``
    the domain's name.

    Parameters
    ----------
    domain : str
        From ``domains.domain_of``.
    points, weights
        As ``knnrefine.refine`` takes them.
    **asked
        ``k``, ``tau``, ``periodic``, ``box``, ``min_size``, ``max_vertices``,
        ``time_limit``, ``progress``, ``radius``.
    """
    return part(domain, "run").checked(points, weights, **asked)


def refine_checked(pts: np.ndarray, w: np.ndarray | None, opt) -> Mesh:
    """A run in this process on checked points, weights and options (``checked``): the run
    of the options' domain.

    Parameters
    ----------
    pts : ndarray (n, d)
    w : ndarray (n,) or None
    opt : RunOptions or SphereOptions

    Returns
    -------
    Mesh
    """
    return part(opt.domain, "run").refine(pts, w, opt)


def certify_points(
    mesh, points, *, samples=100_000, n_random=20_000, max_point_probes=100_000,
    random_state=0, weights=None, workers=-1,
) -> Certificate:  # fmt: skip
    """``knnrefine.certify`` in this process: the points checked to be the mesh's, then
    ``certify.steps.run_checks`` with the mesh's domain's geometry and points; the caller
    has checked ``workers`` (threads: -1 for every core).

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
