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

from . import _validation as V
from ._domains import domain_of, part
from .certify import steps
from .certify.certificate import Certificate
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


def checked(
    domain: str, points: ArrayLike, weights: ArrayLike | None, start: Mesh | None = None,
    **asked,
) -> tuple:  # fmt: skip
    """The points, weights and options of a run in ``domain``, checked before any work by
    the domain's ``run.checked``: (pts, weights or None, options), the options' ``domain``
    the domain's name.

    Parameters
    ----------
    domain : str
        From ``domains.domain_of``.
    points, weights
        As ``knnrefine.refine`` takes them.
    start : Mesh, optional
        Continue this mesh (``refine``'s ``start``): its k, tau, box, periodic axes, floor
        and radius are the run's (options given must be the same), its points the first
        rows of ``points`` (by count and ``Stats.points_digest``), weighted as they are.
        Those rows were checked when the start was refined and are not checked again: the
        run's checked points and weights are then the new rows alone, the options carrying
        all of them as given (``RunOptions.given``).
    **asked
        ``k``, ``tau``, ``periodic``, ``box``, ``min_size``, ``max_vertices``,
        ``time_limit``, ``progress``, ``radius``.

    Raises
    ------
    InputError
        Bad points or options; a start that cannot be continued with them (saying why and
        what to do).
    """
    run = part(domain, "run")
    rows = V.as_rows(points)
    if start is None or rows is None or rows.ndim != 2:
        pts, w, opt = run.checked(points, weights, **asked)
        if rows is None or rows.ndim != 2 or len(rows) != len(pts):
            rows = pts
        return pts, w, opt.continuing(None, points_digest(rows, w))
    asked = start_options(start, domain, asked)
    n0 = int(start.stats.n)
    w_rows = None if weights is None else V.as_rows(weights)
    if w_rows is not None and w_rows.shape != (len(rows),):  # the domain's check says so
        run.checked(points, weights, **asked)
    digest = _check_start_points(start, rows, w_rows)
    if not start.on_sphere:
        check_in_start_box(start, rows[n0:])
    # the first n0 rows are the start's, checked when it was refined: only the new ones here
    new = None if w_rows is None else w_rows[n0:]
    pts, w, opt = run.checked(rows[n0:], new, before=(n0, start.stats.weight), **asked)
    return pts, w, opt.continuing(start, digest, rows, w_rows)


def points_digest(pts: np.ndarray, w: np.ndarray | None) -> str:
    """``Stats.points_digest``: a hash of the points as given, as float64 rows (and of the
    weights), in their order (``_engine/digest.py``)."""
    return digest_of_hashes(_hashes(pts, w))


DIGEST_FORM = "h64:"  # what a digest starts with (an older form is refused, not misread)


def _hashes(pts, w, rows=None, position=0):
    """The hashes (ints) of the rows ``rows`` (a slice; all by default) of the points and
    weights, their first row at row ``position``: ranges of rows add up."""
    from ._engine.digest import digest_of

    rows = slice(None) if rows is None else rows
    d = pts.shape[1]
    h = digest_of(pts[rows], position * d)
    return h, None if w is None else digest_of(w[rows], position)


def digest_of_hashes(hashes) -> str:
    """``Stats.points_digest`` of the hashes (points, weights or None) of all the rows."""
    h, hw = hashes
    return DIGEST_FORM + f"{h:016x}" + ("" if hw is None else f"{hw:016x}")


_AFRESH = "refine all the points afresh (without start=)"


def start_options(start: Mesh, domain: str, asked: dict) -> dict:
    """The options of a run continued from ``start``: the start's k, tau, box, periodic
    axes, floor and radius where not given; InputError where one given differs, or where
    new points lie outside an ordinary box (a continued mesh keeps its torus)."""
    if not isinstance(start, Mesh):
        raise InputError(f"start must be a knnrefine.Mesh (from refine or io.read_mesh), got "
                         f"{type(start).__name__}")  # fmt: skip
    if start.domain != domain:
        raise InputError(
            f"start is a mesh {_IN[start.domain]}, these points are {_IN[domain]}: continue "
            "a mesh with points of its own domain"
        )
    if start.torus is None and not start.on_sphere:
        raise InputError(f"start has no torus mesh to continue (a file without it): {_AFRESH}")
    asked = dict(asked)
    given: dict[str, object] = {"k": start.k, "tau": start.tau, "min_size": start.min_size}
    if start.on_sphere:
        given["radius"] = start.radius
    elif asked.get("box") is None and asked.get("periodic") in (False, None):
        asked["box"], asked["periodic"] = tuple(start.box), tuple(start.periodic)
    else:
        given.update(box=tuple(start.box), periodic=tuple(start.periodic))
        if isinstance(asked.get("periodic"), bool):
            asked["periodic"] = (asked["periodic"],) * len(start.periodic)
        if asked.get("box") is not None:
            asked["box"] = tuple(float(b) for b in asked["box"])
    for name, value in given.items():
        if asked.get(name) is None:
            asked[name] = value
        elif asked[name] != value:
            raise InputError(f"start was refined with {name}={value!r}, this run asks for "
                             f"{name}={asked[name]!r}: a continued mesh keeps its options "
                             f"(give {name}={value!r}, or {_AFRESH})")  # fmt: skip
    return asked


_IN = {"plane": "in the plane", "space": "in space", "sphere": "on the sphere"}


def check_in_start_box(start: Mesh, pts: np.ndarray) -> None:
    """InputError when a new point lies outside the start's box along a non-periodic axis
    (``pts`` float64 rows)."""
    d = len(start.periodic)
    if pts.shape[1] != d:
        return  # the domain's own check says what is wrong
    for a in range(d):
        if start.periodic[a] or not len(pts):
            continue
        lo, hi = start.box[a], start.box[a + d]
        outside = int(np.count_nonzero((pts[:, a] < lo) | (pts[:, a] > hi)))
        if outside:
            raise InputError(
                f"{outside:,} points lie outside the start mesh's box along axis {a} "
                f"[{lo:g}, {hi:g}]: a continued mesh keeps the box of its first run; "
                f"{_AFRESH}, with a box that holds them all (box=...) to continue later"
            )


def _check_start_points(start, pts, w):
    """InputError unless the first rows of ``pts`` (and ``w``), float64 as given, are the
    start's points; else the digest of all of them."""

    def hashes(n0):
        return _hashes(pts, w, slice(None, n0)), _hashes(pts, w, slice(n0, None), n0)

    return continued_digest(start, len(pts), w is not None, hashes)


def continued_digest(start: Mesh, n: int, weighted: bool, hashes: Callable) -> str:
    """The digest of the points of a run continued from ``start`` (n of them, weighted or
    not), whose first rows must be the start's, checked cheaply first (their count, the
    weights rule, the digest's form), then by their hashes: ``hashes(n0)`` gives ((points,
    weights) before row n0, the same from it on), weights None when unweighted (a store
    sums them where its points lie). InputError saying why and what to do otherwise."""
    n0 = int(start.stats.n)
    if not start.stats.points_digest:
        raise InputError(f"start does not record the points it was refined from (a mesh of "
                         f"an older knnrefine): {_AFRESH}")  # fmt: skip
    if (start.stats.weight is not None) != weighted:
        had = "with weights" if not weighted else "without weights"
        raise InputError(f"start was refined {had}: continue it the same way, or {_AFRESH}")
    if n < n0:
        raise InputError(
            f"start was refined from {n0:,} points, this run has {n:,}: give the "
            "start's points first, in their order, then the new ones"
        )
    if not start.stats.points_digest.startswith(DIGEST_FORM):
        raise InputError(f"start records its points' digest in an older form (a mesh of an "
                         f"older knnrefine): {_AFRESH}")  # fmt: skip
    old, new = hashes(n0)
    if digest_of_hashes(old) != start.stats.points_digest:
        raise InputError(f"the first {n0:,} points (and weights) are not the ones start was "
                         f"refined from: give the start's points first, in their order, then "
                         f"the new ones, or {_AFRESH}")  # fmt: skip
    mod = 1 << 64
    both = [None if a is None else (a + b) % mod for a, b in zip(old, new, strict=True)]
    return digest_of_hashes(both)


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
    digest = opt.points_digest or points_digest(pts, w)  # before a run reorders them
    mesh = part(opt.domain, "run").refine(pts, w, opt)
    mesh.stats.points_digest = digest
    return mesh


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
