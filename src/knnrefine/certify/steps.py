"""certify's steps, written once for every domain: what a mesh promises (Theorem 6), checked
in order against its domain's answers.

A domain gives two objects (``plane.py``, ``space.py``, ``sphere.py``, the same names in
each): its ``Geometry``, the questions about the mesh itself (its triangulation checked
exactly, the cells the user received, circumballs, the probes of the achieved constants,
d_{M,2}, the size integral, Theorem 6's constants), and its ``Points``, the questions about
the input points (what balls and Voronoi cells hold, d_{P,k}, some of the points), answered
in this process or, where the points stay in worker processes, strip by strip
(``scale.checks``). Lengths are the geometry's own: input units in a box, angles on the
sphere, where ``Geometry.floor`` is the resolution floor.

The steps: the triangulation, exactly; the returned cells; the aspect 2 R(v) / d_{M,2}(v);
the points in every closed circumball and Voronoi cell, below k above the floor (elements
below it that hold k are floor elements, reported); Lemma 2's precondition on the initial
vertices; d_{M,2} / d_{P,k} at the probes where d_{P,k} >= the floor, within [alpha, beta];
the size integral; the floor's sites.
"""

import math
from collections import namedtuple
from typing import Protocol

import numpy as np

from .._validation import random_generator
from .certificate import Certificate

# the triangulation as a geometry checked it: its problems, each cell's circumcentre and
# circumradius, each vertex's outradius R(v), and what else its later steps read (``extra``)
Triangulation = namedtuple("Triangulation", ["problems", "centres", "radii", "outradii", "extra"])
# the probes of the achieved constants, in the geometry's frame: ``x`` all of them (only
# those in the domain), ``points`` the mask of the input points among them, ``d_m2``
# d_{M,2} where the mesh gives it (at a vertex: its nearest neighbour's distance; NaN
# elsewhere: asked), ``extra`` what the geometry's size integral reads of them (their first
# rows, say). They are asked along a Morton curve of their own (``Tree.kth`` sorts them):
# faster than in the order of their cells, measured in every domain.
#
# Why these probes: d_{M,2} / d_{P,k} is smallest where d_{M,2} is: on an edge's midpoint,
# where the two nearest vertices are its ends, at half its length; it is largest where
# d_{P,k} is small against the vertex spacing: at the vertices (d_{M,2} there is the
# nearest neighbour's distance, its largest near them) and among the input points. So the
# probes are every vertex and every edge midpoint (their number grows with the mesh, not
# with n), input points (up to 2 m, drawn at random), uniform points and the size
# integral's samples (one point in each of up to ``samples`` cells). On uniform, clustered
# and k = 100 meshes of 2 x 10^5 points the extremes were at midpoints (alpha_hat) and at
# vertices or input points (beta_hat), never at a circumcentre, a cell's sample or a
# uniform point; circumcentres are no longer probed. Both bounds are checked where they
# are attained, not proven between probes (Theorem 6 proves them).
#
# ``near``: for each probe the indices (a row) of other probes near it whose d_{P,k} is asked
# first (an edge's midpoint: its two vertices; a uniform point: its nearest vertex; a cell's
# further random points, beyond the size integral's: the cell's corners; -1: none, and
# where a row is shorter than the widest). d_{P,k} is 1-Lipschitz in its metric,
# so within ``geometry.separation`` s of that probe it lies in [d - s, d + s]; a probe whose
# ratio d_{M,2} / d_{P,k} then lies strictly between the extremes found so far (and whose
# d_{P,k} is above the floor), by those bounds or by two ball counts, cannot be an extreme
# and is not asked (``bounded_d_pk``). ``exact``: the probes whose d_{P,k} the size integral
# reads (its samples, the vertices), always asked.
# The achieved constants, where they lie and the number of probes are those of asking all.
Probes = namedtuple("Probes", ["x", "points", "d_m2", "extra", "near", "exact"])
# the closed Voronoi cells as certify counts them: each vertex (``sites``, the points' frame),
# its Delaunay neighbours (rows first[v]:first[v + 1] of ``neighbours``, their indices, and
# of ``shift`` (e, d), the whole periods from v to each; (e, 0) where the sites do not
# wrap: an edge's vector is worked out where it is read, ``_tree.edge_at``), its outradius
# R(v) (the cell lies within it), and the tie tolerance: a point p counts for v when
# |p - v|^2 <= |p - u|^2 (1 + relative) + slack2 for every neighbour u (one as near as its
# nearest counts for each) (``period``: the sites' per axis, 0 where none; ``walkable``: the
# triangulation was verified, so a walk along the neighbours finds a point's nearest site)
Cells = namedtuple(
    "Cells",
    ["sites", "first", "shift", "outradii", "relative", "slack2", "neighbours", "period",
     "walkable"],
    defaults=(None, False),
)  # fmt: skip


class PointQuestions(Protocol):
    """What certify asks of the input points (each domain's ``Points``, or a tiled one)."""

    n: int
    total: float
    weighted: bool

    def held(self, centres: np.ndarray, radii: np.ndarray, stop=np.inf) -> np.ndarray:
        """What each closed ball holds: a count, or a weight; exact below ``stop`` (a
        number, or one per ball), at least ``stop`` otherwise."""

    def fewer(
        self, centres: np.ndarray, radii: np.ndarray, k: float, mostly: bool = True
    ) -> np.ndarray:
        """Whether each closed ball, in d_{P,k}'s metric, holds less than weight k (then
        d_{P,k} > its radius at its centre, and <= it otherwise): no count is exact, so,
        where most are expected to (``mostly``), a ball far below k may be settled by the
        cells it meets."""

    def cell_counts(self, cells: Cells, stop=np.inf) -> np.ndarray:
        """What each vertex's closed Voronoi cell holds; exact below ``stop``."""

    def d_pk(self, x: np.ndarray) -> np.ndarray:
        """d_{P,k} at x, in the geometry's lengths."""

    def sample_points(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """Up to ``count`` of the points, drawn at random."""


class Geometry(Protocol):
    """What certify asks of a mesh in its domain (each domain's ``Geometry``)."""

    floor: float
    no_position: tuple

    def triangulation(self) -> Triangulation:
        """The triangulation checked exactly, its circumballs and outradii."""

    def returned_problems(self) -> list:
        """What is wrong with the cells and vertices the user received."""

    def vertex_d_m2(self) -> np.ndarray:
        """d_{M,2} at the mesh's vertices."""

    def cells(self, tri: Triangulation) -> Cells:
        """The Voronoi cells counted, in the points' frame."""

    def held(self, points: PointQuestions, tri: Triangulation, stop=np.inf) -> np.ndarray:
        """What each closed circumball holds; exact below ``stop``."""

    def precondition(self, points: PointQuestions, k: float, tau: float) -> tuple:
        """Lemma 2's precondition on the initial vertices: (ok, note)."""

    def probes(self, tri: Triangulation, points: PointQuestions, samples: int, n_random: int,
               max_point_probes: int, rng: np.random.Generator) -> Probes:  # fmt: skip
        """The probes of the achieved constants."""

    def returned_d_m2(self, x: np.ndarray, tri: Triangulation) -> tuple:
        """(d_{M,2} at x from the vertices returned, what is wrong with them); ``tri``
        says whether the triangulation may be walked (verified: no problems)."""

    def release(self) -> None:
        """Drop what only the steps up to d_{M,2} at the probes read (the Voronoi cells,
        a tree of the vertices), so that d_{P,k}'s bounds at the probes are not held
        beside them."""

    def separation(self, x: np.ndarray, rows: np.ndarray, refs: np.ndarray) -> np.ndarray:
        """Distances from x[rows] to x[refs] (refs (r, w); NaN where -1) in d_{P,k}'s
        metric."""

    def size(self, probes: Probes, d_pk: np.ndarray, points: PointQuestions,
             rng: np.random.Generator) -> tuple:  # fmt: skip
        """The integral of 1 / d_{P,k}^dim over the domain and its standard error."""

    def constants(self, tri: Triangulation) -> tuple:
        """Theorem 6's (alpha, beta) for this mesh."""

    def floor_sites(self, centres: np.ndarray, vertices: np.ndarray) -> list:
        """The floor elements grouped by site, in input coordinates."""

    def to_input(self, x: np.ndarray) -> np.ndarray:
        """Positions in input coordinates."""


def run_checks(
    mesh,
    geometry: Geometry,
    points: PointQuestions,
    *,
    samples,
    n_random,
    max_point_probes,
    random_state,
    t0,
):
    """The certificate of ``mesh``: every step above, with ``geometry`` the domain's
    questions about the mesh and ``points`` about the input points.

    Parameters
    ----------
    mesh : Mesh
    geometry : the domain's Geometry
    points : the domain's Points (or a tiled one)
    samples, n_random, max_point_probes, random_state
        As for ``knnrefine.certify``.
    t0 : float
        When the call began (``time.perf_counter()``).

    Returns
    -------
    Certificate
    """
    import time

    k, tau, floor = mesh.k, mesh.tau, geometry.floor
    tri = geometry.triangulation()
    mesh_problems = geometry.returned_problems()
    max_aspect = float(np.max(2.0 * tri.outradii / geometry.vertex_d_m2()))
    # counts: below k above the floor; elements below it holding k are floor elements
    # counts stop at k (all a passing mesh needs); where one reaches k, counted again in full
    held = _counted(lambda stop: geometry.held(points, tri, stop), k)
    voronoi = geometry.cells(tri)
    cells = _counted(lambda stop: points.cell_counts(voronoi, stop), k)
    floor_balls = (held >= k) & (tri.radii < floor)
    floor_cells = (cells >= k) & (tri.outradii < floor)
    exact = float if points.weighted else int
    above_balls, above_cells = tri.radii >= floor, tri.outradii >= floor
    max_ball = exact(held[above_balls].max()) if above_balls.any() else exact(0)
    max_cell = exact(cells[above_cells].max()) if above_cells.any() else exact(0)
    precondition_ok, precondition_note = geometry.precondition(points, k, tau)
    alpha, beta = geometry.constants(tri)
    sites = geometry.floor_sites(tri.centres[floor_balls], voronoi.sites[floor_cells])
    problems = tri.problems
    n_floor_balls, n_floor_cells = int(floor_balls.sum()), int(floor_cells.sum())
    # what follows reads neither the circumballs nor the counts: not held beside the probes
    tri = tri._replace(centres=None, radii=None)
    del held, cells, floor_balls, floor_cells, above_balls, above_cells
    # the achieved constants at the probes where d_Pk >= the floor
    rng = random_generator(random_state)
    probes = geometry.probes(tri, points, samples, n_random, max_point_probes, rng)
    nan = float("nan")
    alpha_hat = beta_hat = nan
    alpha_at = beta_at = geometry.no_position
    n_probes, under_floor = 0, 0.0
    if points.total >= k:
        d_m2 = probes.d_m2  # (the probes' own, filled in place)
        ask = np.flatnonzero(np.isnan(d_m2))
        late: list = []
        for start in range(0, len(ask), CHUNK):  # a chunk at a time: no copy of every x
            rows = ask[start : start + CHUNK]
            d_m2[rows], found = geometry.returned_d_m2(probes.x[rows], tri)
            late += [p for p in found if p not in late]
        mesh_problems += late
        del ask, tri, voronoi  # (what follows reads neither: not held beside its bounds)
        geometry.release()
        d_pk, settled = bounded_d_pk(points, geometry, probes, d_m2, floor, k)
        at_points = d_pk[probes.points]
        under_floor = float(np.mean(at_points < floor)) if len(at_points) else 0.0
        asked = d_pk >= floor
        n_probes = int(asked.sum()) + settled
        if n_probes:
            ratio = d_m2[asked] / d_pk[asked]
            i, j = int(np.argmin(ratio)), int(np.argmax(ratio))
            alpha_hat, beta_hat = float(ratio[i]), float(ratio[j])
            at = geometry.to_input(probes.x[asked][[i, j]])
            alpha_at, beta_at = (tuple(float(v) for v in x) for x in at)
        integral, stderr = geometry.size(probes, d_pk, points, rng)
    else:
        integral, stderr = 0.0, 0.0
    m = len(mesh.vertices)
    return Certificate(
        n=points.n,
        m=m,
        k=k,
        tau=tau,
        periodic=tuple(mesh.periodic),
        box=tuple(mesh.box),
        min_size=mesh.min_size,
        triangulation_ok=not problems,
        triangulation_problems=problems,
        max_aspect=max_aspect,
        max_cell_count=max_cell,
        max_ball_count=max_ball,
        alpha=alpha,
        beta=beta,
        alpha_hat=alpha_hat,
        beta_hat=beta_hat,
        alpha_hat_at=alpha_at,
        beta_hat_at=beta_at,
        n_probes=n_probes,
        size_integral=integral,
        size_integral_stderr=stderr,
        size_ratio=m / integral if integral > 0 else nan,
        floor_circumballs=n_floor_balls,
        floor_cells=n_floor_cells,
        floor_sites=sites,
        under_floor=under_floor,
        mesh_problems=mesh_problems,
        precondition_ok=bool(precondition_ok),
        precondition_note=precondition_note,
        seconds=time.perf_counter() - t0,
        weight=points.total if points.weighted else None,
        count_slack=4.0 * float(np.spacing(float(k))) if points.weighted else 0.0,
        domain=mesh.domain,
    )


def _counted(ask, k):
    """``ask(stop)``'s counts, asked to stop at k, then in full where they reached it."""
    counts = np.asarray(ask(float(k)), float)
    over = counts >= k
    if over.any():
        counts[over] = np.asarray(ask(np.where(over, np.inf, 0.0)), float)[over]
    return counts


SEED = 0.01  # of the bounded probes, asked first at each end (their bounds most extreme)
TIE = 1e-9  # relative: a radius a count decides moved this far from an extreme's


def bounded_d_pk(points, geometry, probes, d_m2, floor, k):
    """(d_{P,k} at the probes, NaN where it cannot change the certificate; the number of
    those, d_{P,k} shown there to be at or above the floor). Asked first at the probes
    whose value the size integral reads (``Probes.exact``) and those others are bounded
    from; then, from each bounded probe's bounds [d - s, d + s] (``Probes``: d its near
    probe's, s their separation), at the SEED share with the lowest and the highest ratio
    bounds, and at the SEED share of the unbounded others: the extremes alpha, beta found
    so far move out. A probe whose upper bound lies below the floor is no probe and is not
    asked. A probe not yet asked cannot be an extreme where its ratio d_{M,2} / d_{P,k}
    lies strictly between them and d_{P,k} at or above the floor: where its bounds do not
    show that, two counts may: a ball of radius r holds less than k (weight) exactly where
    d_{P,k} > r, at least k where d_{P,k} <= r, so fewer than k in the ball of d_{M,2} /
    beta (or the floor) and k in the ball of d_{M,2} / alpha settle it (each radius moved
    TIE towards the middle, and a weighted count by TIE past k, so that rounding decides
    nothing). It is asked where neither does. The extremes, where they lie and the number
    of probes are those of asking every probe.

    The probes are read CHUNK at a time, and a probe's bounds are worked out from its
    references where they are read (twice: for the seeds, then to settle it; the
    references' d_{P,k} is asked first and does not change), so that what is held for
    each probe is its d_{P,k} and a few flags."""
    x, near, exact = probes.x, probes.near, probes.exact
    n = len(x)
    d_pk = np.full(n, np.nan)
    extremes = [np.inf, -np.inf]  # alpha, beta so far

    def ask(rows):
        d_pk[rows] = points.d_pk(x[rows])
        use = rows[d_pk[rows] >= floor]
        if len(use):
            r = d_m2[use] / d_pk[use]
            extremes[:] = min(extremes[0], float(r.min())), max(extremes[1], float(r.max()))

    chunks = [(a, min(a + CHUNK, n)) for a in range(0, n, CHUNK)]
    bounded = (near >= 0).any(axis=1)
    first = np.array(exact, bool, copy=True)
    for a, b in chunks:  # the references of the others
        refs = near[a:b][bounded[a:b] & ~exact[a:b]]
        first[refs[refs >= 0]] = True
    ask(np.flatnonzero(first))
    if first.all():
        return d_pk, 0

    def later_of(a, b):
        return a + np.flatnonzero(~first[a:b])

    def bounds(rows):
        """(lower, upper bounds of d_{P,k} at the probes ``rows``, from their references)."""
        low, up = np.full(len(rows), -np.inf), np.full(len(rows), np.inf)
        if len(rows) == 0:
            return low, up
        refs = near[rows]  # (-1: none in that column)
        reach = geometry.separation(x, rows, refs).T
        for ref, s in zip(refs.T, reach, strict=True):  # each column of references
            d = d_pk[ref]  # (where ref is -1, s is NaN: the bounds stay as they were)
            slack = 1e-9 * (d + s)  # rounding in d_{P,k} and the separation
            np.fmax(low, d - s - slack, out=low)
            np.fmin(up, d + s + slack, out=up)
        return low, up

    def ratios(rows, low, up):
        with np.errstate(divide="ignore"):
            return d_m2[rows] / up, np.where(low > 0, d_m2[rows] / low, np.inf)

    groups = [int((bounded & ~first).sum()), int((~bounded & ~first).sum())]
    seeds = [min(max(16, int(math.ceil(SEED * g))), g) for g in groups]
    lowest, highest, unbounded = _Seeds(seeds[0]), _Seeds(seeds[0]), [np.zeros(0, np.int64)]
    taken = 0
    for a, b in chunks:  # each probe's bounds [d - s, d + s] from its references
        later = later_of(a, b)
        if len(later) == 0:
            continue
        by_bounds = bounded[later]
        rows = later[by_bounds]
        ratio_lo, ratio_hi = ratios(rows, *bounds(rows))
        lowest.offer(ratio_lo, rows)
        highest.offer(-ratio_hi, rows)
        if taken < seeds[1]:  # unbounded (input points, drawn at random): the first seed
            free = later[~by_bounds][: seeds[1] - taken]
            unbounded.append(free)
            taken += len(free)
    pick = np.zeros(n, bool)
    pick[lowest.rows()] = pick[highest.rows()] = True
    pick[np.concatenate(unbounded)] = True
    ask(np.flatnonzero(pick))
    del pick
    alpha, beta = extremes  # with the seeds asked, the rest settled against them
    weighted = bool(points.weighted)
    unsettled = [np.zeros(0, np.int64)]
    settled = 0
    for a, b in chunks:
        rest = later_of(a, b)
        rest = rest[np.isnan(d_pk[rest])]  # (the seeds asked)
        if len(rest) == 0:
            continue
        low, up = bounds(rest)
        ratio_lo, ratio_hi = ratios(rest, low, up)
        under = up < floor  # below the floor: no probe
        below = (low >= floor) & (ratio_hi < beta)  # d_pk above floor and d_m2 / beta
        above = ratio_lo > alpha  # d_pk below d_m2 / alpha
        if alpha < beta and np.isfinite(beta):
            # fewer than k in the closed ball of radius r: d_pk > r
            r_lo = np.maximum(d_m2[rest] / beta * (1.0 + TIE), floor)
            r_hi = d_m2[rest] / alpha * (1.0 - TIE) if alpha > 0 else np.full(len(rest), np.inf)
            hopeful = (r_lo < r_hi) & ~under
            count = np.flatnonzero(hopeful & ~below)
            if len(count):
                need = k * (1.0 - TIE) if weighted else k
                ok = count[points.fewer(x[rest[count]], r_lo[count], need)]
                below[ok] = True  # (d_pk > r_lo >= the floor there)
            count = np.flatnonzero(hopeful & below & ~above)
            if len(count):
                need = k * (1.0 + TIE) if weighted else k
                far = ~points.fewer(x[rest[count]], r_hi[count], need, mostly=False)
                above[count[far]] = True
        done = below & above  # (d_pk at or above the floor: ``below`` says so)
        settled += int(done.sum())
        unsettled.append(rest[~(done | under)])
    ask(np.concatenate(unsettled))
    return d_pk, settled


CHUNK = 1 << 17  # probes bounded and settled at once (``bounded_d_pk``)


class _Seeds:
    """The ``size`` rows of least value among those offered, kept as they come."""

    def __init__(self, size):
        self.size = size
        self.values, self.at = np.zeros(0), np.zeros(0, np.int64)

    def offer(self, values, rows):
        values, rows = np.concatenate([self.values, values]), np.concatenate([self.at, rows])
        if len(values) > self.size:
            keep = np.argpartition(values, self.size - 1)[: self.size] if self.size else []
            values, rows = values[keep], rows[keep]
        self.values, self.at = values, rows

    def rows(self):
        return self.at
