"""The run of kNNRefine in this process, one path for every domain: the domain decided once
from what ``refine`` is given (``domain_of``: ``sphere``, the points' columns), the points
and options checked before any work, then the domain's run. ``api.refine`` calls it (and
``scale`` where workers or an executor run tiles); the applications that refine (the
density estimator, the kNN-CDF) call it too.

The domains' runs sit below it: the plane's in ``run``, space's in ``run3``, the sphere's in
``run_sphere``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from . import run
from .errors import InputError
from .mesh import Mesh
from .options import RunOptions
from .run import checked  # noqa: F401  (a run in a box: its points and options checked)


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
    if domain_of(points, sphere, radius) == "sphere":
        return refine_on_sphere(points, k, tau, periodic=periodic, box=box, weights=weights,
                                min_size=min_size, max_vertices=max_vertices,
                                time_limit=time_limit, progress=progress,
                                radius=radius)  # fmt: skip
    return refine_checked(*checked(points, weights, k=k, tau=tau, periodic=periodic, box=box,
                                   min_size=min_size, max_vertices=max_vertices,
                                   time_limit=time_limit, progress=progress))  # fmt: skip


def domain_of(points, sphere=False, radius=None):
    """The domain a run is in, decided once: "sphere" when asked (``radius`` is refused
    without it), else "space" for points of three columns, else "plane"."""
    if not isinstance(sphere, (bool, np.bool_)):
        raise InputError(f"sphere must be True or False, got {sphere!r}")
    if sphere:
        return "sphere"
    if radius is not None:
        raise InputError("radius is the sphere's: give it with sphere=True")
    return "space" if run.is_spatial(points) else "plane"


def refine_checked(pts: np.ndarray, w: np.ndarray | None, opt: RunOptions) -> Mesh:
    """A run in this process on checked points, weights and options (``run.checked``): the
    plane's (``run.refine_plane``) or space's (``run3.refine3``).

    Parameters
    ----------
    pts : ndarray (n, d)
    w : ndarray (n,) or None
    opt : RunOptions

    Returns
    -------
    Mesh
    """
    if opt.dim == 3:
        from .run3 import refine3

        return refine3(pts, opt, w)
    return run.refine_plane(pts, w, opt)


def check_sphere_options(periodic, box):
    """The options a sphere has no use for, refused before any work."""
    if periodic is not False or box is not None:
        raise InputError(
            "the sphere has no box and no periodic axes: drop box= and periodic= with "
            "sphere=True (longitudes wrap by themselves)"
        )


def refine_on_sphere(points, k, tau, *, periodic, box, weights, min_size, max_vertices,
                     time_limit, progress, radius) -> Mesh:  # fmt: skip
    """``refine`` on the sphere: the options it has no use for refused, then its run."""
    check_sphere_options(periodic, box)
    from .run_sphere import refine_sphere

    return refine_sphere(points, k, tau, weights=weights, radius=radius, min_size=min_size,
                         max_vertices=max_vertices, time_limit=time_limit,
                         progress=progress)  # fmt: skip
