"""The kNN-CDF of cosmology for several k in one call (``knn_cdf``): CDF_k(r), the share of
the box where d_{P,k} <= r (Banerjee & Abel 2021), by the mesh where it pays and by Monte
Carlo where it cannot.

Two ways, chosen per k:

* "mesh": the CDF of the mesh's interpolated d_{P,k}, integrated exactly over its pieces
  (``KnnDistance.cdf``), corrected by a control sample: at M uniform points the exact
  d_{P,k} (one kd-tree query for every k at once) and the interpolated one are both known,
  and the mean of 1[d <= r] - 1[d_interpolated <= r] is the interpolation's effect on the
  CDF. The correction is unbiased and its terms are 0 wherever the two agree on which side
  of r a point falls (all but about 5% of the box on a Thomas process), so M = queries / 4
  points give about plain Monte Carlo's noise at ``queries`` points, for a quarter of its
  exact queries and the mesh. Its 95% band is the estimate +- 1.96
  standard errors of the correction; the mesh's rigorous bounds (``cdf_bounds``: d_{P,k} is
  1-Lipschitz over each piece) come with it, wide because pieces are about as wide as d.
* "monte-carlo": exact d_{P,k} at ``queries`` uniform points (scipy's periodic kd-tree, the
  way cosmologists compute it), the empirical CDF, and its 95% band +- 1.96 sqrt(F (1 - F)
  / queries). A mesh cannot win at small k: its size grows as n / k (at k = 1 it holds
  several vertices per point), while one kd-tree query answers every k.

"auto" takes the mesh from k = MESH_K sqrt((n / 10^5) / (queries / 10^6)) on, the
break-even measured at 10^5 points and 10^6 queries (``benchmarks/knn_cdf3.py``): on a
Thomas process the mesh wins from k = 48 on (Monte Carlo 5.9 against 4.8 s at k = 48),
but on clustered points not yet at k = 64 (9.5 against 9.9-11.1 s in three runs) and by
1.4x at k = 128, so "auto" takes it from k = 80, scaled as the two costs scale; in space
only (the plane has no exact CDF integral over pieces: Monte Carlo there).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from .. import _pipeline as pipeline
from .._validation import as_points, check_box, check_k, random_generator
from ..errors import BudgetError, InputError

MESH_K = 80  # "auto": the mesh from this k on at n = 10^5 points and 10^6 queries (space)
METHODS = ("auto", "mesh", "monte-carlo")
CONTROL = 4  # the mesh's control sample: queries / CONTROL points
Z95 = 1.959963984540054  # the normal's 97.5% quantile: two-sided 95% bands


@dataclass
class KnnCdf:
    """CDF_k(r) for each k (rows) at each radius (columns), with 95% bands.

    Attributes
    ----------
    ks : ndarray (K,)
    radii : ndarray (R,)
    cdf : ndarray (K, R)
        The estimates.
    lower, upper : ndarray (K, R)
        Their 95% bands (pointwise).
    method : list of str
        Per k, "mesh" or "monte-carlo".
    bounds : dict
        Per k done by the mesh, its rigorous (lower, upper) bounds.
    seconds : dict
        Per k, the time it took (the shared kd-tree query's share included once, at the
        first k using it).
    vertices : dict
        Per k done by the mesh, its vertex count.
    """

    ks: np.ndarray
    radii: np.ndarray
    cdf: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    method: list = field(default_factory=list)
    bounds: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)
    vertices: dict = field(default_factory=dict)


def knn_cdf(
    points: ArrayLike,
    ks: Sequence[int],
    radii: ArrayLike,
    box: Sequence[float],
    *,
    periodic: bool = True,
    queries: int = 1_000_000,
    method: str = "auto",
    random_state: int | np.random.Generator | None = 0,
) -> KnnCdf:
    """The kNN-CDF, CDF_k(r) = vol{x in the box : d_{P,k}(x) <= r} / vol(box), for several k.

    Parameters
    ----------
    points : array-like (n, 3) or (n, 2)
    ks : sequence of int
        Which neighbours, each in [1, n].
    radii : array-like (R,)
        Radii >= 0.
    box : (x0, y0, z0, x1, y1, z1) or (x0, y0, x1, y1)
    periodic : bool
        The box is a torus (the cosmologists' periodic box) or an ordinary box.
    queries : int
        Monte Carlo's uniform points (the mesh's control sample is a quarter of them).
    method : "auto", "mesh" or "monte-carlo"
        See the module docstring; "mesh" is for points in space.
    random_state : int, numpy Generator or None
        The uniform points' seed.

    Returns
    -------
    KnnCdf

    Raises
    ------
    InputError
        Bad points, ks, radii, box or options, before any work.
    """
    pts = as_points(points, 3 if np.ndim(points) == 2 and np.shape(points)[1] == 3 else 2)
    n, dim = pts.shape
    asked = [ks] if isinstance(ks, (int, np.integer)) else ks
    try:
        wanted = np.unique(np.asarray([check_k(k, n) for k in asked], np.int64))
    except TypeError:
        raise InputError(f"ks must be a sequence of integers in [1, n = {n}], got {ks!r}") from None
    if len(wanted) == 0:
        raise InputError("ks is empty: give at least one k")
    r = np.asarray(radii, float)
    if r.ndim != 1 or len(r) == 0 or not np.all(np.isfinite(r)) or np.any(r < 0):
        raise InputError("radii must be a non-empty 1-D array of finite numbers >= 0")
    corners = np.asarray(check_box(box, dim))
    lo, hi = corners[:dim], corners[dim:]
    if not isinstance(periodic, (bool, np.bool_)):
        raise InputError(f"periodic must be True or False (every axis or none), got {periodic!r}")
    if isinstance(queries, bool) or not isinstance(queries, (int, np.integer)) or queries < 100:
        raise InputError(f"queries must be an integer >= 100, got {queries!r}")
    if method not in METHODS:
        raise InputError(f'method must be "auto", "mesh" or "monte-carlo", got {method!r}')
    if method == "mesh" and dim == 2:
        raise InputError('method="mesh" is built for points in space; use "monte-carlo"')
    side = hi - lo
    if periodic:
        pts = lo + np.mod(pts - lo, side)
    elif np.any(pts < lo) or np.any(pts > hi):
        raise InputError("points lie outside the box: enlarge the box or use periodic=True")
    rng = random_generator(random_state)

    # the mesh's cost grows as n / k (its vertices), Monte Carlo's as queries * k: even at
    # k = MESH_K sqrt((n / 10^5) / (queries / 10^6)) (the module docstring's measures)
    even = MESH_K * np.sqrt((n / 1e5) / (int(queries) / 1e6))

    def by_mesh(k):
        return method == "mesh" or (method == "auto" and dim == 3 and k >= even)

    mesh_ks = [int(k) for k in wanted if by_mesh(k)]
    for k in mesh_ks:  # memory, before any work: a mesh at small k holds several vertices a point
        _check_mesh_memory(n, k, dim, periodic)
    mc_ks = [int(k) for k in wanted if not by_mesh(k)]
    out = KnnCdf(wanted, r, *np.zeros((3, len(wanted), len(r))))
    out.method = ["mesh" if by_mesh(k) else "monte-carlo" for k in wanted]
    t0 = time.perf_counter()
    tree = cKDTree(pts - lo, boxsize=side if periodic else None)
    row = {int(k): j for j, k in enumerate(wanted)}
    if mc_ks:  # one query answers every k
        q = rng.random((int(queries), dim)) * side
        d = tree.query(q, k=mc_ks, workers=-1)[0]
        for j, k in enumerate(mc_ks):
            f = np.searchsorted(np.sort(d[:, j]), r, side="right") / len(q)
            se = np.sqrt(f * (1 - f) / len(q))
            i = row[k]
            out.cdf[i], out.lower[i], out.upper[i] = f, f - Z95 * se, f + Z95 * se
            out.seconds[k] = time.perf_counter() - t0 if j == 0 else 0.0
    if mesh_ks:
        t0 = time.perf_counter()
        q = rng.random((max(int(queries) // CONTROL, 100), dim)) * side
        exact = tree.query(q, k=mesh_ks, workers=-1)[0].reshape(len(q), len(mesh_ks))
        shared = time.perf_counter() - t0
        for j, k in enumerate(mesh_ks):
            t0 = time.perf_counter()
            f, band, bounds, m = _by_mesh(pts, k, r, lo, hi, periodic, q + lo, exact[:, j])
            i = row[k]
            out.cdf[i], out.lower[i], out.upper[i] = f, f - band, f + band
            out.bounds[k], out.vertices[k] = bounds, m
            out.seconds[k] = time.perf_counter() - t0 + (shared if j == 0 else 0.0)
    out.lower = np.clip(out.lower, 0.0, 1.0)
    out.upper = np.clip(out.upper, 0.0, 1.0)
    return out


# peak memory of the mesh's way per mesh vertex: the run, the pieces (eight per tetrahedron,
# cut at the box), their locator for the control sample (measured: 31-48 KB at n = 2 x 10^4
# and 4 x 10^4 uniform points, k = 2 to 16, R = 50 radii, 10^5 queries)
MESH_BYTES_PER_VERTEX = 48_000
ORDINARY_BOX = 1.3  # an ordinary box's mesh holds its margins' vertices too


def _check_mesh_memory(n, k, dim, periodic):
    """InputError, before any work, when the mesh's way at k would need more than half of
    this machine's memory (``size.expected_vertices`` vertices at MESH_BYTES_PER_VERTEX),
    saying which options do the job instead."""
    from .._engine import size

    vertices = size.expected_vertices(n, k, dim) * (1.0 if periodic else ORDINARY_BOX)
    need = vertices * MESH_BYTES_PER_VERTEX
    memory = size.memory_bytes()
    if need > 0.5 * memory:
        raise InputError(
            f'method="mesh" at k = {k} needs a mesh of about {vertices:,.0f} vertices from '
            f"{n:,} points, and about {need / 1e9:.3g} GB for its pieces, more than half of "
            f"this machine's {memory / 1e9:.3g} GB (a mesh at small k holds several vertices "
            'per point): use method="monte-carlo" (one kd-tree query answers every k) or '
            'method="auto" (the mesh only where it pays), or fewer points'
        )


def _by_mesh(pts, k, r, lo, hi, periodic, q, exact):
    """(CDF, its 95% half-band, rigorous bounds, vertices) at radii r by the mesh at k with
    the control sample q (exact d_{P,k} there: ``exact``)."""
    from .distance import KnnDistance

    try:
        mesh = pipeline.refine(pts, k, periodic=periodic, box=(*lo, *hi))
    except BudgetError as exc:  # its advice names refine's options, which knn_cdf has not
        raise BudgetError(
            f"the mesh at k = {k} stopped at its budget ({exc.progress.get('vertices', 0):,} "
            'vertices): use method="monte-carlo" or "auto" for this k (one kd-tree query '
            "answers every k), or fewer points",
            progress=exc.progress,
        ) from None
    dist = KnnDistance(mesh, pts)
    f = dist.cdf(r)
    approx = dist(q)
    miss = ~np.isfinite(approx)  # on no piece by rounding (none expected): exact there
    approx[miss] = exact[miss]
    # the interpolation's effect on the CDF, per control point and radius: -1, 0 or 1
    below_exact = exact[:, None] <= r[None, :]
    below_approx = approx[:, None] <= r[None, :]
    delta = below_exact.astype(np.int8) - below_approx.astype(np.int8)
    m = len(q)
    mean = delta.mean(axis=0)
    # Var(delta) <= P(delta != 0), estimated as (c + 1) / (m + 2) from the c disagreements:
    # where none was seen the band still allows a few (the sample cannot rule them out)
    floor = ((delta != 0).sum(axis=0) + 1.0) / (m + 2.0)
    se = np.sqrt(np.maximum(delta.var(axis=0), floor) / m)
    return np.clip(f + mean, 0.0, 1.0), Z95 * se, dist.cdf_bounds(r), len(mesh.vertices)
