"""Checks at the public boundary: every message says what was wrong and what to do."""

import math
import numbers
import warnings

import numpy as np

from ._metric import unit_vectors
from .errors import InputError, WrapWarning

# squared distances of coordinates up to 1e100 stay far from overflow and underflow
MAX_COORDINATE = 1e100
MIN_SIDE = 1e-100


def _nullable(x):
    """A pandas object (nullable Float64 / Int64 columns included, whose NumPy array has
    dtype object) as float64 with missing values NaN; anything else unchanged."""
    to_numpy = getattr(x, "to_numpy", None)
    if to_numpy is None:
        return x
    try:
        return to_numpy(dtype=np.float64, na_value=np.nan)
    except (TypeError, ValueError):
        return x


def as_rows(x):
    """Points or weights as given, as a C-contiguous float64 array (no copy of one that is
    already): what ``Stats.points_digest`` hashes; None when they cannot be read as numbers
    (the domain's check then says why)."""
    try:
        return np.ascontiguousarray(np.asarray(_nullable(x)), dtype=np.float64)
    except (TypeError, ValueError):
        return None


def as_points(points, dim=2):
    """(n, dim) float64 array from lists, numpy arrays of any real dtype, pandas frames
    (nullable Float64 / Int64 columns included: a missing value is then a NaN, refused)."""
    try:
        arr = np.asarray(_nullable(points))
    except Exception as exc:  # ragged lists and the like
        raise InputError(f"points could not be read as an (n, {dim}) array: {exc}") from None
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise InputError(
            f"points must be numeric, got dtype {arr.dtype}; convert the columns to numbers "
            "first (for example with pandas.to_numeric)"
        )
    if np.iscomplexobj(arr):
        raise InputError("points must be real numbers, got complex values")
    if arr.ndim != 2 or arr.shape[1] != dim:
        axes = "x and y" if dim == 2 else "x, y and z"
        # neither the plane's nor space's: say that both are taken (where the caller's
        # dimension came from the points themselves, as refine's and the estimator's)
        both = arr.ndim == 2 and arr.shape[1] not in (2, 3)
        what = "(n, 2) in the plane or (n, 3) in space" if both else f"(n, {dim})"
        raise InputError(
            f"points must have shape {what}, got {arr.shape}; pass one row per point with "
            f"its {'coordinates' if both else axes + ' coordinates'}"
        )
    if arr.shape[0] == 0:
        raise InputError("points is empty: give at least one point")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    # reductions without temporaries first (the sum of finite doubles <= 1e100 is finite;
    # one that overflows is looked at again, quietly)
    with np.errstate(over="ignore", invalid="ignore"):
        total = arr.sum()
    if not np.isfinite(total) and not np.isfinite(arr).all():
        bad = ~np.isfinite(arr).all(axis=1)
        first = int(np.argmax(bad))
        raise InputError(
            f"points holds {int(bad.sum())} row(s) with NaN or infinite coordinates, the first "
            f"at index {first} ({arr[first].tolist()}); drop or fill them first"
        )
    big = max(float(arr.max()), -float(arr.min()))
    if big > MAX_COORDINATE:
        raise InputError(
            f"coordinates reach {big:.3g}; knnrefine works with |x| <= {MAX_COORDINATE:g} "
            "(squared distances must stay finite): rescale the data first"
        )
    return arr


def default_k(n: float) -> int:
    """The default k, for the mesh (``refine`` without k: clustering and persistence users need
    not pick one) and the kNN density estimate: sqrt(n) / 2, at least 10 and at most n (on 5
    points, 5), after the paper's k ~ sqrt(n) (k / n -> 0 and k / log n -> infinity): a
    cluster or a class of persistence holding fewer than about k points is smoothed over,
    and about k outliers together are what it takes to make a feature.

    Parameters
    ----------
    n : float
        The points' number or total weight.

    Returns
    -------
    int
    """
    return min(max(10, int(round(0.5 * math.sqrt(n)))), max(1, int(n)))


def check_k(k, n=None):
    """k is a positive integer, at most the number of points n when given (beyond it d_{P,k}
    is infinite everywhere and there is nothing to sample)."""
    if isinstance(k, numbers.Real) and not isinstance(k, (bool, numbers.Integral)):
        # a float with a whole value is that integer (5.0 from a computation or a file)
        if np.isfinite(k) and float(k).is_integer() and abs(float(k)) < 2.0**53:
            k = int(k)
        else:
            raise InputError(
                f"k must be a whole number >= 1, got {k!r} (a fractional k is a weight: give "
                "weights to count weight)"
            )
    if isinstance(k, bool) or not isinstance(k, numbers.Integral):
        raise InputError(f"k must be an integer >= 1, got {k!r}")
    if k < 1:
        raise InputError(f"k must be an integer >= 1, got {k}")
    if n is not None and k > n:
        raise InputError(
            f"k = {k} is larger than the number of points, {n}: d_Pk would be infinite "
            f"everywhere; use k <= {n}"
        )
    return int(k)


def check_weights(weights, n, positive=True):
    """Point weights: n finite numbers >= 0 with a positive total (``positive``; a continued
    run's new weights may all be 0), as float64 (n,), from any array-like (lists, tuples,
    NumPy arrays, pandas Series, nullable ones included)."""
    try:
        arr = np.asarray(_nullable(weights))
    except Exception:
        raise InputError(f"weights must be {n} numbers, one per point") from None
    if np.iscomplexobj(arr):
        raise InputError(f"weights must be {n} real numbers, one per point; got complex ones")
    try:
        w = np.asarray(arr, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"weights must be {n} numbers, one per point") from None
    if w.shape != (n,):
        raise InputError(f"weights must have shape ({n},), one per point; got {w.shape}")
    if not np.isfinite(w).all() or (w < 0).any():
        bad = int(np.flatnonzero(~np.isfinite(w) | (w < 0))[0])
        raise InputError(
            f"weights must be finite and >= 0; weight {bad} is {w[bad]!r} (drop such points "
            "or set their weight to 0)"
        )
    if positive and n and not w.sum() > 0:
        raise InputError("the weights sum to 0: no point counts")
    return np.ascontiguousarray(w)


def weights_of_run(stats, n, weights):
    """The weights to use the points of a run again with (certify, evaluation): those it was
    refined with. A weighted run (``stats["weight"]``, the total) needs them and a run
    without weights refuses them; the total must match. Returns float64 (n,) or None."""
    total = stats.get("weight")
    if weights is None:
        if total is not None:
            raise InputError(
                f"the mesh was refined with weights (total {total:.6g}): pass the same weights"
            )
        return None
    if total is None and "n" in stats:
        raise InputError(
            "the mesh was refined without weights: use it without them (or refine with weights=...)"
        )
    weights = check_weights(weights, n)
    if total is not None and not np.isclose(weights.sum(), total, rtol=1e-9, atol=0):
        raise InputError(
            f"the weights sum to {weights.sum():.6g} but the mesh was refined with a total "
            f"weight of {total:.6g}: pass the weights it was refined with"
        )
    return weights


def check_made_from(stats, n, advice):
    """InputError unless ``n`` points are as many as the run with these stats was refined
    from; ``advice`` ends the message ("use a mesh with", "certify a mesh against")."""
    made_from = stats.get("n")
    if made_from is not None and int(made_from) != n:
        raise InputError(
            f"the mesh was made from {int(made_from):,} points but {n:,} were given: "
            f"{advice} the points it was refined from"
        )


def points_of_run(mesh, points, weights=None):
    """The points (and weights) a mesh was refined from, to use them again (evaluation,
    clustering, persistence): (pts (n, d) float64, weights or None, total: n or the total
    weight). Refused with an InputError: points of another dimension or number than the
    run's, weights that are not the run's (``weights_of_run``), less than k in all."""
    check_in_a_box(mesh, "this use")
    return _of_run(mesh, as_points(points, mesh.dim), weights)


def _of_run(mesh, pts, weights):
    """(pts, the run's weights or None, their total), refused when they are not the run's
    or hold less than k."""
    check_made_from(mesh.stats, len(pts), "use a mesh with")
    weights = weights_of_run(mesh.stats, len(pts), weights)
    total = len(pts) if weights is None else float(weights.sum())
    if total < mesh.k:
        what = f"{len(pts)} points" if weights is None else f"a total weight of {total:.6g}"
        raise InputError(f"{what} but k = {mesh.k}: d_Pk is infinite")
    return pts, weights, total


def sphere_points_of_run(mesh, points, weights=None):
    """``points_of_run`` for a mesh on the sphere: (unit vectors (n, 3), weights or None,
    total: n or the total weight), refused as there when they are not the run's (or the
    mesh's radius is not one lengths and densities can be given in: ``check_radius``)."""
    check_radius(mesh.radius)
    return _of_run(mesh, as_sphere_points(points), weights)


RADIUS_RANGE = (1e-100, 1e100)


def check_radius(radius):
    """The sphere's radius as a float, or InputError: a finite number in RADIUS_RANGE, so
    that every length (up to pi radius), area (4 pi radius^2) and density (per unit area)
    knnrefine gives in its unit is a finite double. None: 1 (radians)."""
    if radius is None:
        return 1.0
    lo, hi = RADIUS_RANGE
    if (
        isinstance(radius, bool)
        or not isinstance(radius, (int, float, np.integer, np.floating))
        or not (lo <= float(radius) <= hi)
    ):
        raise InputError(
            f"radius must be a number from {lo:g} to {hi:g}, got {radius!r}: the sphere's "
            "radius in the length unit wanted (1 for radians, 6371.0088 for kilometres on "
            "the Earth); beyond that range areas and densities overflow"
        )
    return float(radius)


def check_in_a_box(mesh, what):
    """InputError for a mesh on the sphere where ``what`` is built for the plane and space
    only (rather than treat longitude and latitude as a plane)."""
    if getattr(mesh, "on_sphere", False):
        raise InputError(
            f"{what} is built for meshes in a box (the plane or space); this mesh lies on the "
            "sphere: use knnrefine.density.adaptive.SphereAdaptiveDensity (or "
            "KnnDensityEstimator(sphere=True))"
        )


def check_weighted_k(k, total):
    """With weights, k is a weight: a positive number, at most the total weight."""
    if isinstance(k, bool) or not isinstance(k, numbers.Real) or not np.isfinite(k) or k <= 0:
        raise InputError(f"k must be a positive number (a weight), got {k!r}")
    if k > total:
        raise InputError(
            f"k = {k} is larger than the total weight, {total:.6g}: d_Pk would be infinite "
            f"everywhere; use k <= {total:.6g}"
        )
    # a whole k is kept an integer only where int64 holds it exactly (k = 1e20 with weights
    # of 1e19 is a weight, not a count the kernels could type)
    return int(k) if float(k).is_integer() and abs(float(k)) < 2.0**53 else float(k)


def check_tau(tau):
    if isinstance(tau, bool) or not isinstance(tau, numbers.Real) or not np.isfinite(tau):
        raise InputError(f"tau must be a finite number > 2, got {tau!r}")
    if tau <= 2:
        raise InputError(
            f"tau must be > 2, got {tau}: at tau = 2 Theorem 6's lower bound alpha is 0 "
            "(3 is the usual choice)"
        )
    return float(tau)


MAX_VERTICES_CAP = 2**62  # a vertex budget beyond this is no budget (and beyond int64)


def check_max_vertices(max_vertices):
    """A vertex budget: None, or a positive whole number; one beyond 2^62 (no machine holds
    that many vertices) means no budget and is capped there, not an OverflowError."""
    if max_vertices is None:
        return None
    if (
        isinstance(max_vertices, bool)
        or not isinstance(max_vertices, numbers.Real)
        or not math.isfinite(max_vertices)
        or int(max_vertices) != max_vertices
        or max_vertices < 1
    ):
        raise InputError(f"max_vertices must be a positive integer, got {max_vertices!r}")
    return min(int(max_vertices), MAX_VERTICES_CAP)


def check_workers(workers):
    """None or 1 (one run in this process), or the number of tiles (threads, or an
    executor's tasks) of a tiled run."""
    if workers is None:
        return 1
    if isinstance(workers, bool) or not isinstance(workers, numbers.Integral) or workers < 1:
        raise InputError(
            f"workers must be a positive integer (threads of this process), got {workers!r}"
        )
    return int(workers)


def check_executor(executor, workers, domain):
    """An executor (anything with a ``map``) for the tiles or strips of a call with
    ``workers`` >= 2, in a box: the sphere has neither."""
    if executor is None:
        return
    if not callable(getattr(executor, "map", None)):
        raise InputError(
            f"executor must be a concurrent.futures.Executor (with a map method), got {executor!r}"
        )
    if domain == "sphere":
        raise InputError(
            "the sphere runs in this process (its workers are threads): drop executor= with "
            "sphere=True"
        )
    if workers < 2:
        raise InputError("an executor runs the tiles (strips) of a call: give workers >= 2 with it")


def random_generator(random_state):
    """The numpy Generator of a ``random_state`` as scikit-learn takes one (None, an int, a
    Generator or a RandomState): the one seed argument of every call that draws."""
    if isinstance(random_state, np.random.RandomState):
        return np.random.default_rng(random_state.randint(0, 2**63 - 1, dtype=np.int64))
    ok = random_state is None or isinstance(random_state, np.random.Generator) or (
        isinstance(random_state, numbers.Integral) and not isinstance(random_state, bool)
        and random_state >= 0
    )  # fmt: skip
    if not ok:
        raise InputError(
            f"random_state must be None, an int >= 0, a numpy Generator or RandomState, got "
            f"{random_state!r}"
        )
    return np.random.default_rng(random_state)


def check_periodic(periodic, dim=2):
    """(bool,) * dim from a bool or one bool per axis."""
    axes = "(x, y)" if dim == 2 else "(x, y, z)"
    what = "a pair" if dim == 2 else "a triple"
    if isinstance(periodic, (bool, np.bool_)):
        return (bool(periodic),) * dim
    try:
        flags = tuple(periodic)
    except TypeError:
        flags = ()
    if len(flags) != dim or not all(isinstance(p, (bool, np.bool_)) for p in flags):
        raise InputError(f"periodic must be a bool or {what} of bools {axes}, got {periodic!r}")
    return tuple(bool(p) for p in flags)


def check_box(box, dim=2):
    """(low corner, high corner) as 2 * dim finite numbers, each side positive."""
    names = "(xmin, ymin, xmax, ymax)" if dim == 2 else "(x0, y0, z0, x1, y1, z1)"
    count = "four" if dim == 2 else "six"
    try:
        vals = [float(b) for b in box]
    except (TypeError, ValueError):
        raise InputError(f"box must be {count} numbers {names}, got {box!r}") from None
    if len(vals) != 2 * dim or not np.all(np.isfinite(vals)):
        raise InputError(f"box must be {count} finite numbers {names}, got {box!r}")
    if not all(vals[dim + a] > vals[a] for a in range(dim)):
        rule = "xmin < xmax and ymin < ymax" if dim == 2 else "x0 < x1, y0 < y1 and z0 < z1"
        raise InputError(
            f"box {tuple(vals)} has a zero or negative width, height or depth; it must "
            f"satisfy {rule}"
        )
    check_box_scale(vals)
    return tuple(vals)


def check_box_scale(box):
    """A box whose sides or corners leave [1e-100, 1e100] cannot be meshed in double
    precision without overflow or underflow of squared distances."""
    dim = len(box) // 2
    big = max(abs(b) for b in box)
    side = min(box[dim + a] - box[a] for a in range(dim))
    if big > MAX_COORDINATE or side < MIN_SIDE:
        raise InputError(
            f"box {tuple(box)} is out of range: corners must satisfy |x| <= {MAX_COORDINATE:g} "
            f"and sides >= {MIN_SIDE:g}; rescale the data first"
        )


def default_box(points):
    """The points' bounding box; a zero side (collinear or identical points) is widened to the
    other side, or to 1 when all points coincide, centred on the data."""
    # column by column: numpy reduces an (n, 2) array along axis 0 about 50x slower
    dim = points.shape[1]
    lo = np.array([points[:, a].min() for a in range(dim)])
    hi = np.array([points[:, a].max() for a in range(dim)])
    size = hi - lo
    side = size.max()
    if side == 0.0:  # all points coincide
        side = max(1.0, float(np.abs(lo).max()) * 2.0**-30)
    elif side < MIN_SIDE:
        raise InputError(
            f"the points span only {side:.3g}; knnrefine needs a box side >= {MIN_SIDE:g}: "
            "rescale the data first"
        )
    for a in range(dim):
        if size[a] == 0.0:
            mid = lo[a]
            lo[a] = mid - side / 2.0
            hi[a] = mid + side / 2.0
    return tuple(float(v) for v in lo) + tuple(float(v) for v in hi)


PERIOD_BITS = 24  # a periodic coordinate must resolve 2^-24 of its period


def fold_warning(lo, hi, box, periodic, outside=None, stacklevel=4):
    """Warn (WrapWarning) where the points' extent [lo, hi] along a periodic axis is longer
    than the period: wrapping then lays points of different periods over each other (points
    in [0, 1] with a periodic box [0, 0.5]). Within one period, wrapping is what periodic
    data asks for (angles in [0, 360) with the box [-180, 180)) and says nothing.
    ``outside``: how many points lie outside the box along each axis, if known."""
    dim = len(box) // 2
    for a in range(dim):
        period = box[a + dim] - box[a]
        if not periodic[a] or not hi[a] - lo[a] > period:
            continue
        count = "" if outside is None else f"{int(outside[a]):,} "
        warnings.warn(
            f"{count}points lie outside the periodic box along {'xyz'[a]} [{box[a]:g}, "
            f"{box[a + dim]:g}) and were wrapped into it: the points span "
            f"[{lo[a]:g}, {hi[a]:g}], more than the period {period:g}, so points from "
            "different periods now lie on each other; if that is not meant, give the box of "
            "the data (or make the axis non-periodic)",
            WrapWarning,
            stacklevel=stacklevel,
        )


def check_inside(points, box, periodic, warn=True):
    """Points must lie in the box along non-periodic axes. Periodic axes wrap, exactly, but a
    coordinate so large that doubles near it are coarser than 2^-24 of the period has lost
    its position within the period; with ``warn``, points spanning more than a period say so
    (``fold_warning``)."""
    dim = len(box) // 2
    if warn and any(periodic):
        lo = [float(points[:, a].min()) for a in range(dim)]
        hi = [float(points[:, a].max()) for a in range(dim)]
        outside = [
            int(((points[:, a] < box[a]) | (points[:, a] >= box[a + dim])).sum())
            if periodic[a] and hi[a] - lo[a] > box[a + dim] - box[a]
            else 0
            for a in range(dim)
        ]
        fold_warning(lo, hi, box, periodic, outside, stacklevel=6)
    for a in range(dim):
        if periodic[a]:
            period = box[a + dim] - box[a]
            big = max(float(points[:, a].max()), -float(points[:, a].min()))
            if np.spacing(big) > period * 2.0**-PERIOD_BITS:
                axis = "xyz"[a]
                raise InputError(
                    f"coordinates along {axis} reach {big:.3g}, where doubles are "
                    f"{np.spacing(big):.3g} apart, coarser than 2^-{PERIOD_BITS} of the period "
                    f"{period:g}: the position within the period is lost at that magnitude; "
                    f"keep periodic coordinates below about {period * 2.0**28:.3g} in magnitude"
                )
            continue
        lo, hi = box[a], box[a + dim]
        if points[:, a].min() >= lo and points[:, a].max() <= hi:
            continue
        out = (points[:, a] < lo) | (points[:, a] > hi)
        if out.any():
            first = int(np.argmax(out))
            axis = "xyz"[a]
            raise InputError(
                f"{int(out.sum())} point(s) lie outside the box along {axis} "
                f"[{lo}, {hi}], the first at index {first} ({points[first].tolist()}); enlarge "
                "the box, drop those points, or make that axis periodic"
            )


def as_queries(x, dim=2):
    """Query points of any shape (..., dim): returns (flat (q, dim) float64, the leading
    shape); none at all, (0, dim), is a valid empty query.
    Anything else is refused (a (2, N) array in scipy's gaussian_kde layout is the classic
    mistake: it would silently be read as N / 2 points)."""
    arr = np.asarray(x, dtype=np.float64) if not isinstance(x, np.ndarray) else x
    if arr.dtype == object or not np.issubdtype(arr.dtype, np.number):
        raise InputError(f"query points must be numbers, got dtype {arr.dtype}")
    if arr.ndim == 0 or arr.shape[-1] != dim:
        hint = (
            f"; for the ({dim}, N) layout of scipy's gaussian_kde pass x.T"
            if arr.ndim == 2 and arr.shape[0] == dim
            else ""
        )
        axes = "x and y" if dim == 2 else "x, y and z"
        raise InputError(
            f"query points must have shape (..., {dim}), {axes} on the last axis, got "
            f"{arr.shape}{hint}"
        )
    arr = np.asarray(arr, dtype=np.float64)
    return arr.reshape(-1, dim), arr.shape[:-1]


def answerable(flat, on_sphere=False):
    """The one rule of every query method (``Mesh.d_m2``, ``KnnDistance``, ``KnnDensity``,
    the partitioned meshes): which query points (q, d) get an answer; the others get NaN.
    Non-finite coordinates get none, nor on the sphere latitudes beyond +-90 degrees (no
    point of the sphere; longitudes wrap). Box limits are each method's own (d_M2 is defined
    everywhere, the interpolated d_Pk in the box)."""
    ok = np.isfinite(flat).all(axis=1)
    if on_sphere:
        ok &= np.abs(np.where(ok, flat[:, 1], 0.0)) <= 90.0
    return ok


RESOLUTION_BITS = 24  # a box must span at least 2^24 grid steps: the floor is 2^14 of them


def check_resolution(box, per):
    """The box must be wide compared with the spacing of doubles at its coordinates: the
    engine works on a grid no finer than that spacing (so that every vertex is returned
    exactly), and its resolution floor is 2^14 grid steps."""
    from ._engine.embedding import Embedding

    emb = Embedding.make(box, per)
    step = emb.grid / emb.scale
    dim = len(box) // 2
    side = max(box[dim + a] - box[a] for a in range(dim))
    if side < step * 2.0**RESOLUTION_BITS:
        big = float(np.max(np.abs(box)))
        raise InputError(
            f"the box {box} is too small for its coordinates' magnitude: near {big:.6g} doubles "
            f"are {step:.3g} apart, and knnrefine needs at least 2^{RESOLUTION_BITS} such steps "
            f"across the box (its side is {side:.3g}, about {side / step:.3g} steps); subtract "
            "an offset first, for example points - points.min(axis=0)"
        )


def as_sphere_points(points):
    """Unit vectors (n, 3) of points given as (longitude, latitude) degrees (n, 2) or as
    vectors (n, 3) of length 1 (within 1e-6); InputError otherwise, naming what is wrong."""
    shape = np.shape(points if hasattr(points, "shape") else np.asarray(points, dtype=object))
    dim = 3 if len(shape) == 2 and shape[1] == 3 else 2
    try:
        pts = as_points(points, dim)
    except InputError as exc:
        raise InputError(
            f"{exc} (on the sphere: (n, 2) longitude and latitude in degrees, or (n, 3) unit "
            "vectors)"
        ) from None
    if dim == 3:
        norm = np.linalg.norm(pts, axis=1)
        bad = np.abs(norm - 1.0) > 1e-6
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(
                f"points of shape (n, 3) on the sphere must be unit vectors; point {i} has "
                f"length {norm[i]:.9g} (normalise them, or give longitude and latitude)"
            )
        return pts / norm[:, None]
    lat = pts[:, 1]
    bad = (lat > 90.0) | (lat < -90.0)
    if bad.any():
        i = int(np.argmax(bad))
        lon = pts[:, 0]
        past = np.abs(lat[bad]).max() - 90.0
        if past <= 0.01:  # rounding past a pole, not another column
            advice = (f" (past the pole by {past:.3g} degrees: rounding? clip the latitudes to "
                      "[-90, 90])")  # fmt: skip
        elif (np.abs(lon) <= 90.0).all() and (np.abs(lat) <= 360.0).all():
            advice = (
                " (the longitudes look like latitudes: are the columns swapped? give "
                "longitude first)"
            )
        else:
            advice = ""
        raise InputError(
            f"latitudes must lie in [-90, 90] degrees; point {i} has latitude "
            f"{float(lat[i])!r}{advice}"
        )
    return unit_vectors(pts)
