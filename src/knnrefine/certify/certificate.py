"""The certificate ``certify`` returns, the same in the plane and in space, and what builds
it in both: floor sites grouped, probe positions put back in input coordinates."""

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .._metric import BoxMetric


@dataclass
class Certificate:
    """What ``certify`` measured, in the plane or in space (``dim``, from the box).

    ``passed`` is True when every guarantee of Theorem 6 holds above the resolution floor:
    the torus mesh is a Delaunay triangulation (``triangulation_ok``) and the returned one is
    it (``mesh_problems`` empty), Lemma 2's precondition holds, the aspect is at most tau, no
    Voronoi cell or circumball holds k points (or weight k), and the achieved constants
    ``alpha_hat``/``beta_hat`` of d_{M,2} / d_{P,k} lie within Theorem 6's [alpha, beta].
    ``str(certificate)`` is the report; ``to_dict()`` the fields as plain Python.

    Attributes
    ----------
    n, m, k, tau, periodic, box, min_size
        The points' number, the mesh's vertices, and the run's options.
    triangulation_ok, triangulation_problems
        The torus mesh verified exactly, and what failed.
    max_aspect : float
        The largest 2 R(v) / d_{M,2}(v); at most tau.
    max_cell_count, max_ball_count
        The most points (weight) in a Voronoi cell and a circumball above the floor; < k.
    alpha, beta, alpha_hat, beta_hat, alpha_hat_at, beta_hat_at, n_probes
        Theorem 6's constants, the extremes of d_{M,2} / d_{P,k} measured at ``n_probes``
        probes and where they were found.
    size_integral, size_integral_stderr, size_ratio
        The integral of 1 / d_{P,k}^dim over the box (Monte Carlo) and m over it.
    floor_circumballs, floor_cells, floor_sites, under_floor
        Elements left holding k points below ``min_size``, their sites ((coordinates...,
        elements), largest first), the share of the points where d_{P,k} < min_size.
    mesh_problems, precondition_ok, precondition_note
        The returned mesh against the torus mesh; Lemma 2's precondition.
    seconds, weight, count_slack
        Time taken; the total weight of a weighted run and the rounding allowed its sums.
    """

    n: int
    m: int
    k: int
    tau: float
    periodic: tuple
    box: tuple
    min_size: float
    triangulation_ok: bool
    triangulation_problems: list
    max_aspect: float
    max_cell_count: int | float  # over cells with outradius >= min_size (a weight if weighted)
    max_ball_count: int | float  # over circumballs with radius >= min_size (weighted: a weight)
    alpha: float
    beta: float
    alpha_hat: float
    beta_hat: float
    alpha_hat_at: tuple
    beta_hat_at: tuple
    n_probes: int
    size_integral: float  # Monte Carlo estimate of the integral of 1 / d_{P,k}^dim over the box
    size_integral_stderr: float
    size_ratio: float  # m / size_integral
    floor_circumballs: int  # circumballs holding >= k points left alone below min_size
    floor_cells: int
    floor_sites: list = field(default_factory=list)  # [(*x, elements), ...] largest first
    under_floor: float = 0.0  # fraction of the input points where d_Pk < min_size
    mesh_problems: list = field(default_factory=list)  # returned mesh vs the certified torus
    precondition_ok: bool = True  # Lemma 2's precondition on the initial vertices
    precondition_note: str = ""
    seconds: float = 0.0
    weight: float | None = None  # the points' total weight, for a weighted run
    # sums of real weights are rounded (compensated: within two ulps, engine and certify
    # alike): a weighted count passes below k plus this, 0 for counts of points
    count_slack: float = 0.0
    domain: str = (
        "plane"  # "plane", "space" or "sphere" (circumcaps, great-circle distances, no box)
    )

    @property
    def dim(self) -> int:
        """2 in the plane, 3 in space."""
        return 3 if self.domain == "space" else 2

    @property
    def total(self):
        """What the points hold in all: their number, or their total weight."""
        return self.n if self.weight is None else self.weight

    @property
    def passed(self):
        return bool(
            self.triangulation_ok
            and not self.mesh_problems
            and self.precondition_ok
            and self.total >= self.k
            and self.max_aspect <= self.tau
            and self.max_cell_count < self.k + self.count_slack
            and self.max_ball_count < self.k + self.count_slack
            and (np.isnan(self.alpha_hat) or self.alpha <= self.alpha_hat)
            and (np.isnan(self.beta_hat) or self.beta_hat <= self.beta)
        )

    @property
    def warnings(self):
        """What holds but deserves attention: the guarantee is claimed only above the floor."""
        out = []
        if self.under_floor > 0.5:
            out.append(
                f"{100 * self.under_floor:.0f}% of the input points lie where d_Pk < min_size = "
                f"{self.min_size:.3g}: the bounds are not claimed there"
                + (
                    " (k = 1: d_Pk is 0 at every input point)"
                    if self.k == 1
                    else "; pass a smaller min_size, or a box fitted to the data"
                )
            )
        return out

    def to_dict(self) -> dict:
        """The fields and ``passed`` as plain Python (for JSON).

        Returns
        -------
        dict
        """
        d = asdict(self)
        d["passed"] = self.passed
        return {key: plain(v) for key, v in d.items()}

    def __str__(self):
        def verdict(ok):
            return "ok" if ok else "FAILED"

        mode = (
            "periodic"
            if all(self.periodic)
            else "non-periodic"
            if not any(self.periodic)
            else f"periodic={tuple(self.periodic)}"
        )
        cells = "triangulation     " if self.dim == 2 else "tetrahedralisation"
        held = "count" if self.weight is None else "weight"
        sphere = self.domain == "sphere"
        where = "on the sphere" if sphere else f"{mode}, box {tuple(round(b, 6) for b in self.box)}"
        lines = [
            f"knnrefine certificate: n = {self.n}"
            + ("" if self.weight is None else f" (total weight {self.weight:.6g})")
            + f", m = {self.m}, k = {self.k}, "
            f"tau = {self.tau:g}, {where}",
            f"  {cells} Delaunay"
            + (
                " on the sphere (the vectors' convex hull)"
                if sphere
                else " on the torus"
                if all(self.periodic)
                else " (of the torus embedding the box)"
            )
            + f": {verdict(self.triangulation_ok)}"
            + ("" if self.triangulation_ok else f" ({'; '.join(self.triangulation_problems)})"),
            (
                "  returned mesh      degrees are the certified unit vectors: "
                if sphere
                else "  returned mesh      the certified torus mesh, exactly, no repeated vertex: "
            )
            + f"{verdict(not self.mesh_problems)}"
            + ("" if not self.mesh_problems else f" ({'; '.join(self.mesh_problems)})"),
            f"  initial mesh       Lemma 2's precondition d_Pk <= (K - 1) lambda: "
            f"{verdict(self.precondition_ok)}"
            + (f" ({self.precondition_note})" if self.precondition_note else ""),
            f"  well-spaced        max aspect {self.max_aspect:.4f} <= tau {self.tau:g}: "
            f"{verdict(self.max_aspect <= self.tau)}",
            f"  Voronoi cells      max {held} {self.max_cell_count:.8g} < k: "
            f"{verdict(self.max_cell_count < self.k + self.count_slack)}",
            f"  {'circumcaps ' if sphere else 'circumballs'}        max {held} "
            f"{self.max_ball_count:.8g} < k: "
            f"{verdict(self.max_ball_count < self.k + self.count_slack)}",
            f"  d_M2 / d_Pk        in [{self.alpha_hat:.4f}, {self.beta_hat:.4f}] over "
            f"{self.n_probes} probes; Theorem 6 allows [{self.alpha:.4f}, {self.beta:.2f}]: "
            f"{verdict(self.alpha <= self.alpha_hat and self.beta_hat <= self.beta)}"
            if self.total >= self.k and not np.isnan(self.alpha_hat)
            else (
                "  d_M2 / d_Pk        FAILED: n < k, d_Pk is infinite"
                if self.total < self.k
                else "  d_M2 / d_Pk        nothing measured: every probe lies where d_Pk < "
                f"min_size = {self.min_size:.3g}"
            ),
            f"  size               m / integral(1 / d_Pk^{self.dim}) = {self.size_ratio:.3f} "
            f"(integral {self.size_integral:.4g} +- {self.size_integral_stderr:.2g})",
        ]
        if self.floor_circumballs or self.floor_cells:
            sites = ", ".join(
                "(" + ", ".join(f"{x:.6g}" for x in s[:-1]) + f") x{s[-1]}"
                for s in self.floor_sites[:5]
            )
            more = f" and {len(self.floor_sites) - 5} more" if len(self.floor_sites) > 5 else ""
            lines.append(
                f"  resolution floor   {self.floor_circumballs} circumballs and "
                f"{self.floor_cells} cells hold >= k points below min_size = {self.min_size:.3g}"
                f", at {len(self.floor_sites)} site(s): {sites}{more}; the bounds hold wherever "
                f"d_Pk >= min_size ({100 * self.under_floor:.1f}% of the points lie below it)"
            )
        else:
            lines.append("  resolution floor   not reached")
        verdict_line = "PASSED" if self.passed else "FAILED"
        if self.passed and self.warnings:
            verdict_line = "PASSED above the resolution floor only: " + "; ".join(self.warnings)
        lines.append(f"  verdict            {verdict_line} ({self.seconds:.2f} s)")
        return "\n".join(lines)


def to_input(x, origin, mesh):
    """Input coordinates of points given relative to the torus origin, periodic axes wrapped
    into the box by the package's one rule."""
    x = np.asarray(x, float).reshape(-1, mesh.dim) + origin
    return BoxMetric(mesh.box, mesh.periodic).wrap(x)


def floor_sites(points, radius, period, origin, mesh):
    """Group floor elements (points relative to the torus origin) that lie within ``radius``
    of each other: [(*x, count), ...] in input coordinates, largest group first."""
    if len(points) == 0:
        return []
    pairs = cKDTree(points, boxsize=period).query_pairs(radius, output_type="ndarray")
    graph = coo_matrix(
        (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points), len(points))
    )
    ncomp, label = connected_components(graph, directed=False)
    counts = np.bincount(label, minlength=ncomp)
    order = np.argsort(-counts, kind="stable")
    first = np.array([np.flatnonzero(label == c)[0] for c in order])
    where = to_input(points[first], origin, mesh)
    return [(*(float(v) for v in x), int(counts[c])) for x, c in zip(where, order, strict=True)]


def plain(v):
    """numpy scalars and tuples as plain Python (for JSON)."""
    if isinstance(v, (np.floating, np.integer, np.bool_)):
        return v.item()
    if isinstance(v, (tuple, list)):
        return [plain(x) for x in v]
    return v
