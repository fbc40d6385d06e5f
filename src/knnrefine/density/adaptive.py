"""The adaptive (sample-point) kernel estimate with local bandwidths from d_{P,k}
(``AdaptiveDensity``, in the plane and in space), and the choice of its bandwidth and
sensitivity by cross-validation (``choose_smoothing``)."""

import copy

import numpy as np
from scipy.special import roots_jacobi

from .._domains.sphere.density import equal_area_radius
from .._engine import kernelsum, kernelsum3, lattice
from .._engine.binned import BinnedLevels, BinnedSums
from .._engine.kernelsum import Q11, Q12, Q22, X, Y, ball_moments, node_extents, one_leaf
from .._engine.lattice import plan_levels, read_grid
from .._engine.threads import in_chunks
from .._metric import BoxMetric, lonlat_of, unit_vectors
from .._validation import (
    as_points,
    as_queries,
    check_in_a_box,
    random_generator,
    sphere_points_of_run,
    weights_of_run,
)
from ..errors import InputError
from .distance import check_extent, grid_axes, grid_points, grid_shape
from .estimate import KnnDensity, unit_ball_volume


class AdaptiveDensity:
    """The adaptive (sample-point) kernel estimate with local bandwidths from d_{P,k}.

    f(x) = (1 - eps) sum_i (w_i / W) K_i(x) + eps f_kNN(x): one kernel per point, of extent
    h_i = c G (d_i / G)^(d alpha) in d dimensions, d_i = d_{P,k}(X_i), G their geometric
    mean. The kNN estimate f ~ 1 / d_{P,k}^d is the pilot, so h_i ~ f(X_i)^(-alpha) in the
    plane and in space alike: the sensitivity alpha = 1/2 is Abramson's square-root law
    (1982), narrow kernels where the points are dense and wide ones in the tails; alpha = 0
    is the fixed-bandwidth estimate (bandwidth c G everywhere); in between, what heavy tails
    and flat regions prefer (Silverman 1986, 5.3). The mesh gives d_{P,k} at every point at
    once (linear interpolation over its pieces).

    K_i is the triweight profile (1 - u)^3, u = (x - X_i)^T Q_i (x - X_i) < 1, normalised to
    mass 1: smooth, compactly supported (sums visit only the kernels that reach x).
    ``shape="isotropic"`` makes it a disk (in space a ball) of radius h_i; ``shape="local"``
    (the plane only) an ellipse of the same area shaped like the covariance of the points
    within d_{P,k} of X_i (measured at the mesh's nodes and interpolated; axes ratio at most
    ``max_ratio``): long along a ridge, narrow across it. In the plane or in space (the
    mesh's dimension; the kernels' code per dimension is ``engine.kernelsum`` and
    ``engine.kernelsum3``). Kernels stay in the box: periodic axes wrap, the others fold the
    mass beyond a side back into the box (reflection), so the estimate integrates to 1
    there.
    eps = 1 / W (one point's worth, W the total weight) of the kNN estimate keeps the
    estimate positive where no kernel reaches (far tails): a finite log-likelihood.

    Parameters: ``mesh``, ``points``, ``subdivide``, ``weights`` as for ``KnnDensity``;
    ``bandwidth`` > 0, the factor c, and ``sensitivity`` alpha in [0, 1]
    (``set_bandwidth`` changes both cheaply, ``loo_curve`` scores candidates by leave-one-out
    likelihood).
    """

    def __init__(
        self, mesh, points, bandwidth=1.0, shape="isotropic", weights=None, subdivide=True,
        max_ratio=10.0, knn=None, sensitivity=0.5,
    ):  # fmt: skip
        check_shape(shape)
        check_in_a_box(mesh, "the adaptive estimate")
        if not (isinstance(max_ratio, (int, float)) and 1 <= max_ratio < np.inf):
            raise InputError(f"max_ratio must be a number >= 1, got {max_ratio!r}")
        dim = mesh.dim
        if shape == "local" and dim != 2:
            raise InputError(
                'shape="local" is built for points in the plane; in space the kernels are '
                'balls: use shape="isotropic"'
            )
        pts = as_points(points, dim)
        if knn is None:
            knn = KnnDensity(mesh, pts, subdivide=subdivide, weights=weights)
        self.knn = knn
        dist = knn.distance
        weights = weights_of_run(mesh.stats, len(pts), weights)
        w = np.ones(len(pts)) if weights is None else weights
        self.k, self.shape, self.dim = mesh.k, shape, dim
        self._kernels = kernelsum if dim == 2 else kernelsum3  # the per-dimension kernels
        self.total = float(w.sum())
        self.eps = 1.0 / self.total
        self.n_eff = self.total**2 / float((w * w).sum())
        self._metric = BoxMetric(mesh.box, mesh.periodic)
        self.lo, self.hi = dist.lo, dist.hi
        self.periodic = tuple(bool(p) for p in mesh.periodic)
        # the kernels are kept in one order, the kernels' order: the points' along a Z curve
        # (``spatial_order``: neighbours near in memory, for binning and locating) until a
        # query needs the kd-tree (``_exact_tree``), the tree's then. Their centres (frame
        # coordinates) and weights are columns; the table of every kernel column that exact
        # sums read (``_rows``) is made when one asks for it: a smoothing search through
        # binned sums and a grid through lattices read the columns alone
        self._points = pts  # as given (the index counts copies by exact place)
        order = spatial_order(pts, self.lo, self.hi)  # the point of each kernel
        at = np.take(pts, order, axis=0)  # the points in the kernels' order
        self._frame = np.ascontiguousarray(self._metric.frame(at))
        self._weights = np.ones(len(pts)) if weights is None else np.asarray(w, float)[order]
        self._set_order(order)
        # the points whose kernels integrate f^2 (``square_terms``): evenly along the Z curve
        self._square_points = order[systematic_sample(len(order), SQUARE_KERNELS)]
        self._table = None
        self._tree = None  # (box, node) once built
        self._extent = None  # the tree's extents at this smoothing (``_exact_tree``)
        if shape == "local":  # the covariance at the nodes counts points in disks: the tree
            self._build_tree()
            at = np.take(pts, self._order, axis=0)
        order = self._order
        # the pilot: d_{P,k} at every point, and the local covariance for shape="local"
        if shape == "local":
            cov = self._node_covariance(dist)
            pilot = dist.interpolate(at, np.column_stack([dist.values, cov]))
            d, cov = pilot[:, 0], pilot[:, 1:]
        elif dim == 2:
            d, cov = dist.interpolate(at, dist.values), None
        else:
            d, cov = dist(at), None
        lost = ~np.isfinite(d)
        if lost.any():  # on no piece by rounding: exact
            d[lost] = dist.exact(at[lost])
        # per unit bandwidth: Q = S^-1 / d^2 (S of determinant 1: the plane's local shape,
        # else the identity), extent d sqrt(lambda_max(S)), amp w / W / (MASS d^dim) (the
        # triweight's mass is MASS / sqrt(det Q))
        # the sensitivity rescales d around its (weighted) geometric mean G:
        # G (d / G)^(dim alpha), from log_ratio = log(d / G)
        n = len(d)
        self._q = np.empty((n, 3 if dim == 2 else 1))
        self._r, self._amp, self._log_ratio = np.empty(n), np.empty(n), np.empty(n)
        with np.errstate(divide="ignore"):
            kernelsum.isotropic_units(d, self._weights, self.total, self._kernels.MASS, dim,
                                      self._q, self._r, self._amp, self._log_ratio)  # fmt: skip
        if cov is not None:  # the plane's local shapes
            d2 = d * d
            unit = unit_shapes(cov, len(pts), max_ratio)  # (n, 3): s11, s12, s22
            q = np.column_stack([unit[:, 2], -unit[:, 1], unit[:, 0]]) / d2[:, None]
            tr = unit[:, 0] + unit[:, 2]
            self._q = np.ascontiguousarray(q)
            self._r = d * np.sqrt(0.5 * tr + np.sqrt(np.maximum(0.25 * tr * tr - 1.0, 0.0)))
        self.pilot = np.empty(n)  # in the points' order
        self.pilot[order] = d
        # kernels no wider than the box along any axis (wrapping and folding stay exact)
        self._cap = float(np.min(self.hi - self.lo))
        self.sensitivity = 0.5
        self.set_bandwidth(bandwidth, sensitivity)

    def _node_covariance(self, dist):
        """Covariance (xx, xy, yy) of the points within d_{P,k} of each node of the mesh."""
        q = self._metric.frame(dist.nodes)
        out = np.empty((len(q), 6))
        lx, ly = self.hi - self.lo
        px, py = self.periodic
        qx, qy = q[:, 0].copy(), q[:, 1].copy()
        rows, (box, node) = self._table, self._tree
        radius = np.asarray(dist.values, float)
        in_chunks(
            lambda a, b: ball_moments(rows, box, node, qx, qy, radius, lx, ly, px, py, out, a, b),
            len(q),
        )
        w = np.maximum(out[:, 0], 1e-300)
        mx, my = out[:, 1] / w, out[:, 2] / w
        return np.column_stack(
            [out[:, 3] / w - mx * mx, out[:, 4] / w - mx * my, out[:, 5] / w - my * my]
        )

    def set_bandwidth(self, bandwidth, sensitivity=None):
        """Make the kernels' extents bandwidth * (their unit extents) at this sensitivity
        (None: as it is); O(n), no new tree. Returns self."""
        c = check_bandwidth(bandwidth)
        alpha = self.sensitivity if sensitivity is None else check_sensitivity(sensitivity)
        self.bandwidth, self.sensitivity = c, alpha
        self._stale = True  # the table's kernel columns: when next read (``_rows``)
        return self

    @property
    def _rows(self):
        """The kernels' table (``kernelsum``'s or ``kernelsum3``'s columns) at this
        smoothing: set_bandwidth only records it, so that a search through binned sums,
        which reads the radii alone (``_radii``), writes no table per candidate."""
        if self._table is None:
            self._table = self._kernel_table()
            self._stale = True
        if self._stale:
            self._kernels.scale_kernels(self._table, self._q, self._amp, self._r,
                                        self._log_ratio, self.bandwidth, self.sensitivity,
                                        self._cap)  # fmt: skip
            self._stale = False
            self._extent = None  # the tree's extents: at the next exact sums
        return self._table

    def _radii(self):
        """The kernels' extents at this smoothing, in the table's order, without writing the
        table: c times the unit extents at this sensitivity (kept per sensitivity), capped as
        ``scale_kernels`` caps them."""
        if self._table is not None and not self._stale:
            return np.ascontiguousarray(self._table[:, self._kernels.R])
        return np.minimum(self.bandwidth * self._unit_radii_at(self.sensitivity), self._cap)

    def _unit_radii_at(self, alpha):
        """The kernels' extents at bandwidth 1 and sensitivity alpha, uncapped (the last
        PER_SENSITIVITY_KEPT sensitivities' kept: a search's climb keeps to a few)."""
        cache = self.__dict__.setdefault("_unit_radii", {})
        if alpha not in cache:
            if len(cache) >= PER_SENSITIVITY_KEPT:
                del cache[next(iter(cache))]  # the oldest
            cache[alpha] = self._r * np.exp((self.dim * alpha - 1.0) * self._log_ratio)
        return cache[alpha]

    def _kernel_table(self):
        """The table of the kernels' columns (``kernel_table``) in the kernels' order: made
        from the centres and weights, its kernel columns zero until ``_rows`` sets them."""
        table = kernel_table(self._frame, self._weights, self._kernels)
        table[:, self._kernels.ROW] = self._order
        return table

    def _set_order(self, order):
        """The kernels' order: ``_order`` the point of each kernel, ``_row_of`` the kernel of
        each point."""
        self._order = order
        self._row_of = np.empty(len(order), np.int64)
        self._row_of[order] = np.arange(len(order))

    def _build_tree(self):
        """Order the kernels as their kd-tree (``build_centres``) and keep the tree; every
        per-kernel array follows the new order."""
        k = self._kernels
        rows, box, node = k.build_centres(self._frame, self._weights)
        order = rows[:, k.ROW].astype(np.int64)  # the kernels in the tree's order
        self._table = rows
        self._stale = True
        self._frame = np.ascontiguousarray(rows[:, : self.dim])
        for name in ("_q", "_r", "_amp", "_log_ratio", "_weights", "_order"):
            if name in self.__dict__:
                setattr(self, name, np.ascontiguousarray(getattr(self, name)[order]))
        rows[:, k.ROW] = self._order
        self._set_order(self._order)
        self._tree = (box, node)
        self._extent = None
        for cached in ("_unit_radii", "_binned_columns", "_binned_last", "_binned_levels"):
            self.__dict__.pop(cached, None)

    def _exact_tree(self, queries):
        """(rows, box, node, extent) for exact sums at ``queries`` points: the kernels'
        kd-tree, built once the calls have asked more than ONE_LEAF_QUERIES points in all (a
        tree costs about as much as summing every kernel at that many), else the table as
        one leaf (each query visits every kernel: the few points a binned search checks
        exactly need no tree, unless each pass checks some: a search's passes add up)."""
        asked = self.__dict__.get("_one_leaf_queries", 0) + queries
        self._one_leaf_queries = asked
        if self._tree is None and asked > ONE_LEAF_QUERIES:
            self._build_tree()
        rows = self._rows
        if self._tree is None:
            box, node = one_leaf(rows, self.dim)
            extent = np.array([float(rows[:, self._kernels.R].max(initial=0.0))])
            return rows, box, node, extent
        box, node = self._tree
        if self._extent is None:
            self._extent = np.zeros(len(node))
            node_extents(rows[:, self._kernels.R], node, self._extent)
        return rows, box, node, self._extent

    @property
    def unit_extents(self):
        """Each point's kernel extent per unit bandwidth (its h_i / c), in input order: the
        pilot d_{P,k}(X_i) at sensitivity 1/dim, G (d / G)^(dim alpha) otherwise."""
        rho = np.exp((self.dim * self.sensitivity - 1.0) * self._log_ratio)
        return self.pilot * rho[self._row_of]

    def _sums(self, frame, loo=False):
        """Kernel sums at points in frame coordinates, and the sums of their squares (with
        ``loo``, at centres: each sum without the centres at that place, and their weight;
        ``kernelsum.kernel_sums``)."""
        m = len(frame)
        out, out2 = np.empty(m), np.empty(m)
        period = np.asarray(self.hi - self.lo, float)
        order = z_order(frame, period)  # neighbours in turn: the tree's leaves stay cached
        q = np.ascontiguousarray(frame[order])
        periodic = np.array(self.periodic, bool)
        rows, box, node, extent = self._exact_tree(m)
        sums = self._kernels.kernel_sums

        def call(a, b):
            sums(rows, box, node, extent, q, loo, period, periodic, out, out2, a, b)

        in_chunks(call, m)
        back = np.empty_like(order)
        back[order] = np.arange(m)
        return out[back], out2[back]

    def _at(self, flat):
        """(kernel sums, their squares, the kNN estimate) at points (q, d); NaN outside."""
        knn = self.knn(flat)
        inside = np.isfinite(knn)
        s, s2 = np.full(len(flat), np.nan), np.full(len(flat), np.nan)
        s[inside], s2[inside] = self._sums(self._metric.frame(flat[inside]))
        return s, s2, knn

    def __call__(self, x):
        """The density at points x (..., d): shape (...); NaN outside the box along
        non-periodic axes."""
        flat, shape = as_queries(x, self.dim)
        s, _, knn = self._at(flat)
        return ((1.0 - self.eps) * s + self.eps * knn).reshape(shape)

    def standard_error(self, x):
        """Pointwise standard error at x (..., d) -> (...): the sample-point estimate's
        variance, (sum of squared kernel terms) - f^2 / n (bandwidths held fixed)."""
        flat, shape = as_queries(x, self.dim)
        s, s2, _ = self._at(flat)
        var = np.maximum(s2 - s * s / self.n_eff, 0.0)
        return ((1.0 - self.eps) * np.sqrt(var)).reshape(shape)

    def grid(self, shape=None, extent=None):
        """(xs, ys[, zs], values): the density at the centres of a grid over the box, or over
        ``extent`` (x0, y0[, z0], x1, y1[, z1]) in the points' units, cells per axis slowest
        first ((ny, nx) or (nz, ny, nx); default 512 per axis in the plane, 64 in space, as
        ``KnnDensity.grid``). A region within the box is summed as the box is
        (``_grid_sums``); one reaching beyond it centre by centre (periodic axes wrap; NaN
        beyond non-periodic sides)."""
        *axes, knn = self.knn.grid(shape, extent)
        within = extent is None or all(
            self.lo[a] <= axes[a][0] and axes[a][-1] <= self.hi[a] for a in range(self.dim)
        )  # fmt: skip
        if within:
            s = self._grid_sums(axes)
        else:
            s = self._at(grid_points(axes))[0].reshape(knn.shape)
        return (*axes, (1.0 - self.eps) * s + self.eps * knn)

    def _grid_sums(self, axes):
        """Kernel sums at the centres of a grid (its axes xs, ys[, zs] in the box's
        coordinates), (ny, nx) or (nz, ny, nx): through lattices (``engine.lattice``:
        kernels narrower than 2 LATTICE_SAMPLES cells drawn exactly on the grid, wider ones
        on coarser lattices through its centres, read by cubic interpolation) where that
        costs less than summing at each centre the kernels that cover it (about the mean
        coverage times the centres), that sum is long (EXACT_TERMS terms or more) and the
        kernels are disks or balls; else exactly, as at any points. Through lattices the
        values are those of exact sums at the centres where only grid-drawn kernels reach,
        and within about 1e-3 (relative) where wider ones do (``tests/test_adaptive.py``
        measures it). In the plane, where drawing would cost GRID_BINNED_CELLS grid cells a
        kernel or more (many points, kernels wide on the grid) and GRID_BINNED_COVER kernels
        or more cover a point (mean), the sums are read from the kernels' binned lattices
        instead, whatever drawing costs against exact sums (those cost a query per centre
        besides their terms: the uniform disk's 512^2 grid at 10^5 points, kernels narrower
        than the drawn lattices' cap, took 0.23 s exactly, 0.03 s binned;
        ``test_grid_of_kernels_narrow_on_the_grid_reads_the_binned_lattices``). Binned
        lattices (``engine.binned``; those a smoothing search built at this smoothing, when
        kept) cost O(n) and a read per centre: their L1
        distance to the exact sums is within 1 % (0.1-0.8 % measured), a centre's within 2.5 %
        of the peak, never below 0."""
        dim = self.dim
        shape = tuple(len(a) for a in axes[::-1])
        period = np.asarray(self.hi - self.lo, float)
        r = self._radii()
        step = np.array([a[1] - a[0] if len(a) > 1 else period[i] for i, a in enumerate(axes)])
        origin = np.array([a[0] for a in axes], float) - self.lo  # frame coordinates
        ball = unit_ball_volume(dim)
        cover = ball * float((r**dim).sum()) / float(np.prod(period))  # kernels at a point
        cells = np.minimum(r**dim / float(np.prod(step)), (2 * LATTICE_SAMPLES) ** dim)
        drawn = ball * float(cells.sum())
        exact = np.prod(shape) * cover  # kernel terms summed centre by centre
        plan = None
        binned = dim == 2 and drawn >= GRID_BINNED_CELLS * len(r) and cover >= GRID_BINNED_COVER
        if self.shape == "isotropic" and exact >= EXACT_TERMS and binned:  # O(n), whatever drawn
            sums = self._binned().grid(axes[0] - self.lo[0], axes[1] - self.lo[1])
            return np.maximum(sums, 0.0)  # (cubic reads may dip below 0)
        if self.shape == "isotropic" and exact >= EXACT_TERMS and drawn < exact:
            periodic = np.array(self.periodic, bool)
            centres = self._frame
            # isotropic kernels keep their mass w / W, capped ones too: amp from the radius
            with np.errstate(divide="ignore"):  # (radius 0: no kernel, on no level)
                amp = self._weights / (self.total * self._kernels.MASS * r**dim)
            plan = plan_levels(
                centres, r, period, periodic, (origin, step), LATTICE_SAMPLES, LATTICE_VALUES
            )
        if plan is None:  # exactly, centre by centre
            mesh = np.meshgrid(*axes[::-1], indexing="ij")  # the slowest axis first
            flat = np.column_stack([g.ravel() for g in mesh[::-1]])
            return self._sums(self._metric.frame(flat))[0].reshape(shape)
        level, levels, total = plan
        draw = lattice.draw if dim == 2 else lattice.draw3
        parts = []  # one lattice per thread (kernels overlap: no shared writes)

        def call(a, b):
            values = np.zeros(total)
            draw(centres, r, amp, level, period, periodic, levels, values, a, b)
            parts.append(values)

        least = 65536 if dim == 2 else 8192  # a ball costs some 10 times a disk
        in_chunks(call, len(r), least=least, per_thread=1)  # a lattice per range
        values = parts[0] if len(parts) == 1 else np.sum(parts, axis=0)
        return read_grid(levels, values, origin, step, np.array(shape[::-1], np.int64))

    def loo(self, sample=None, binned=False):
        """Leave-one-out log-density at the points ``sample`` (indices into the points; all
        by default): the kernels of the point and of its copies at the same place left out
        (W - their weight the total then: copies are one observation, as a point of whole
        weight is, or ties would pull the bandwidth to 0); the pilot bandwidths and the eps
        part keep them (they are smooth in one point). ``binned``: the kernel sums through
        binned lattices (``engine.binned``: within about 1 % of the exact sums, at a cost
        that does not grow with the kernels' overlap; isotropic kernels, in the plane and in
        space, where three steps a radius keep them within about 2 %)."""
        idx = np.arange(len(self._row_of)) if sample is None else np.asarray(sample)
        rows = self._row_of[idx]
        if binned:
            s, w = self._binned_loo(rows)
        else:
            s, w = self._sums(self._frame[rows], loo=True)
        rest = np.maximum(self.total - w, 1e-300)
        knn = self.knn.constant / self.pilot[idx] ** self.dim
        f = (1.0 - self.eps) * s * self.total / rest + self.eps * knn
        with np.errstate(divide="ignore"):
            return np.log(f)

    def _binned_loo(self, rows):
        """(leave-one-out kernel sums, the weight at the place) at the kernels ``rows``,
        through binned lattices (``engine.binned.BinnedSums``)."""
        if self.shape != "isotropic":
            raise InputError(
                "binned leave-one-out sums are built for isotropic kernels (disks or balls), "
                'not shape="local"; use binned=False'
            )
        w = self._copies_of_rows(rows)
        order = np.argsort(rows)  # read along the kernels' (spatial) order: near in memory
        total, own = np.empty(len(rows)), np.empty(len(rows))
        total[order], own[order] = self._binned().without(rows[order], w[order] / self.total)
        s = np.maximum(total - own, 0.0)
        # where a point's own share is most of the binned sum (few other kernels reach it),
        # the difference is mostly binning's error: those points exactly
        check = np.flatnonzero(own > OWN_SHARE * total)
        if len(check):
            s[check] = self._sums(self._frame[rows[check]], loo=True)[0]
        return s, w

    def _binned(self):
        """The binned lattices of the kernels at this smoothing (``engine.binned``), the last
        BINNED_KEPT kept (about 1 + 10 n / 10^6 MiB each): a grid at the smoothing a search
        chose reads the lattices it scored."""
        key = smoothing_key(self.sensitivity, self.bandwidth)  # as a search's Scores keys
        kept = self.__dict__.setdefault("_binned_last", {})
        if key not in kept:
            if not hasattr(self, "_binned_columns"):  # the centres and masses (w / W)
                centres = [np.ascontiguousarray(self._frame[:, j]) for j in range(self.dim)]
                self._binned_columns = (centres, self._weights / self.total)
            centres, mass = self._binned_columns
            period = np.asarray(self.hi - self.lo, float)
            periodic = np.array(self.periodic, bool)
            if len(kept) >= BINNED_KEPT:
                del kept[next(iter(kept))]  # the oldest
            unit = self._unit_radii_at(self.sensitivity)
            if self.bandwidth * float(unit.max(initial=0.0)) <= self._cap:  # none capped
                levels = self.__dict__.setdefault("_binned_levels", {})  # per sensitivity
                if self.sensitivity not in levels:
                    if len(levels) >= PER_SENSITIVITY_KEPT:
                        del levels[next(iter(levels))]  # the oldest
                    levels[self.sensitivity] = BinnedLevels(centres, unit)
                found = levels[self.sensitivity]
                kept[key] = BinnedSums(centres, None, mass, period, periodic, levels=found,
                                       scale=self.bandwidth)  # fmt: skip
            else:
                kept[key] = BinnedSums(centres, self._radii(), mass, period, periodic)
        return kept[key]

    def _copies_at(self, idx):
        """The total weight of the points at exactly the place of each point ``idx`` (indices
        into the points), itself included."""
        return self._copies_of_rows(self._row_of[np.asarray(idx)])

    def _copies_of_rows(self, rows):
        """``_copies_at`` by the table's rows: the weight at exactly each place, counted by
        the pilot's index of the points (``PointIndex.weight_at``: one descent of its tree
        per point; it counts the run's weights, here scaled to this estimate's), or, for a
        ``thinned`` estimate, among its own points; kept for the last rows asked (a search
        asks for the same sample at every smoothing)."""
        key = rows.tobytes()
        if getattr(self, "_copies", (None,))[0] != key:
            own = self.__dict__.get("_own_copies")
            if own is not None:  # in the points' order (a kd-tree may reorder the kernels)
                self._copies = (key, own[self._order[rows]])
            else:
                index = self.knn.distance.index
                held = index.weight_at(self._points[self._order[rows]])
                self._copies = (key, held * (self.total / index.total))
        return self._copies[1]

    def thinned(self, every):
        """The estimate from every ``every``-th kernel along the kernels' (spatial) order,
        each keeping its weight (the total is theirs), with the same pilot d_{P,k} (this
        estimate's, from all the points) and the same kNN part: a cheap stand-in whose best
        smoothing relates to this one's by the kernel estimate's rate (``choose_smoothing``
        climbs on it). Isotropic kernels in a box; the thinned points' copies are counted
        among themselves."""
        if self.shape != "isotropic":
            raise InputError('thinned estimates are built for isotropic kernels, not shape="local"')
        if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
            raise InputError(
                f"every must be an integer >= 1 (every k-th kernel is kept), got {every!r}"
            )
        out = copy.copy(self)
        keep = np.arange(0, len(self._order), int(every))
        out._frame = np.ascontiguousarray(self._frame[keep])
        out._weights = np.ascontiguousarray(self._weights[keep])
        out.total = float(out._weights.sum())
        out.eps = 1.0 / out.total
        out.n_eff = out.total**2 / float((out._weights**2).sum())
        out._q, out._r = self._q[keep], self._r[keep]
        out._log_ratio = self._log_ratio[keep]  # about the same G: every kernel's mean
        out._amp = self._amp[keep] * (self.total / out.total)  # w / W with the kept W
        out._points = self._points[self._order[keep]]
        out.pilot = self.pilot[self._order[keep]]  # the kept points' order: the kernels'
        out._set_order(np.arange(len(keep)))
        out._square_points = systematic_sample(len(keep), SQUARE_KERNELS)
        out._table, out._tree, out._extent = None, None, None
        for cached in ("_unit_radii", "_binned_columns", "_binned_last", "_binned_levels",
                       "_copies", "_one_leaf_queries"):  # fmt: skip
            out.__dict__.pop(cached, None)
        out._own_copies = weight_at_place(out._points, out._weights)
        return out

    def weights_of(self, idx):
        """The weights of the points ``idx`` (indices into the points)."""
        return self._weights[self._row_of[idx]]

    def loo_curve(self, bandwidths, sample=None, sensitivity=None):
        """Mean leave-one-out log-likelihood (per unit weight) of each candidate bandwidth at
        the points ``sample`` (default: all), at this sensitivity (None: as it is); the
        bandwidth is left at the last one."""
        idx = np.arange(len(self._row_of)) if sample is None else np.asarray(sample)
        w = self.weights_of(idx)  # each point's weight: its share of the score
        scores = []
        for c in bandwidths:
            self.set_bandwidth(float(c), sensitivity)
            scores.append(float((self.loo(idx) * w).sum() / w.sum()))
        return np.array(scores)

    def least_squares(self, sample=None, draws=None, seed=0):
        """The least-squares cross-validation score (Rudemo 1982, Bowman 1984) at this
        smoothing: integral f^2 - 2 (mean leave-one-out density at the points ``sample``),
        which is the integrated squared error less the constant integral of the truth^2, so
        lower is better. The integral of f^2 is ``square_terms``' (isotropic kernels: a
        cubature over the kernels, no random draws; ``draws`` (default: as many as the
        sample) and ``seed`` are the Monte Carlo integral's of ``shape="local"``)."""
        idx = np.arange(len(self._row_of)) if sample is None else np.asarray(sample)
        w = self.weights_of(idx)
        loo = float((np.exp(self.loo(idx)) * w).sum() / w.sum())
        values, weights = self.square_terms(len(idx) if draws is None else int(draws), seed)
        return float((values * weights).sum() / weights.sum()) - 2 * loo

    def square_terms(self, draws=20000, seed=0):
        """The integral of f^2 over the box as (values, weights), the integral the weighted
        mean of the values.

        Isotropic kernels: one value per kernel of a systematic sample along the points' Z
        curve (all of them up to SQUARE_KERNELS; spread over the box, the same kernels at
        every smoothing, so that scores pair kernel by kernel). With f = (1 - eps) s + eps g
        (s the kernel sum, g the kNN part) and s = sum_i (w_i / W) K_i, the integral of s^2
        is sum_i (w_i / W) (integral of K_i s): the mean of s over kernel i, by a cubature
        of the triweight on the unit disk or ball (``ball_cubature``: exact for the kernel's
        own share, a polynomial in |x|^2, and for smooth neighbours), s read through the
        binned lattices (``engine.binned``; within 0.3 % of fine grids' midpoint rules in
        the plane, folded and wrapped, and in space: ``tests/test_adaptive.py``). Nodes
        beyond a side fold back into the box as the kernels' mass does (the integral over
        the box of K_i s is that of K_i times s at the folded point); the eps parts (one
        point's worth) take g at the centres. No random draws: candidates' scores differ
        by their smoothing alone.

        ``shape="local"`` (no lattices for ellipses): f at ``draws`` points drawn from f,
        seeded by ``seed`` (Monte Carlo, the same draws moving with the kernels from one
        smoothing to the next), weights 1."""
        if self.shape != "isotropic":
            return _at_own_draws(self, draws, seed), np.ones(int(draws))
        rows = self._row_of[self._square_points]
        z, omega = ball_cubature(self.dim)
        nodes = self._kernel_points(rows, z[None]).reshape(-1, self.dim)  # rows x nodes
        nodes = self._metric.frame(self._into_box(nodes))
        s = self._binned().at(*(np.ascontiguousarray(nodes[:, a]) for a in range(self.dim)))
        mean_s = s.reshape(len(rows), len(z)) @ omega
        g = self.knn.constant / self.pilot[self._order[rows]] ** self.dim
        eps = self.eps
        return (1 - eps) ** 2 * mean_s + (2 * eps - eps * eps) * g, self._weights[rows]

    def _kernel_points(self, rows, z):
        """Points X_i + L_i z (m, q, d), frame coordinates not folded, of the kernels
        ``rows`` (m,) for unit-ball points z (m or 1, q, d): L_i L_i^T = Q_i^-1, the
        kernel's ellipse or ball."""
        table = self._rows
        if self.dim == 2:
            q11, q12, q22 = (table[rows, col][:, None] for col in (Q11, Q12, Q22))
            det = q11 * q22 - q12 * q12
            a, b, c = q22 / det, -q12 / det, q11 / det  # Q^-1
            l11 = np.sqrt(a)
            l21 = b / l11
            l22 = np.sqrt(np.maximum(c - l21 * l21, 0.0))
            x = table[rows, X][:, None] + l11 * z[..., 0]
            y = table[rows, Y][:, None] + l21 * z[..., 0] + l22 * z[..., 1]
            out = np.stack([x, y], axis=-1)
        else:
            k3 = kernelsum3
            out = table[rows, None, k3.X : k3.Z + 1] + z * table[rows, k3.R][:, None, None]
        return out

    def sample(self, n, rng):
        """n points (n, d) drawn from the estimate: a kernel chosen by weight, a point from
        it (u = |z|^2 ~ Beta(d / 2, 4) for the triweight in d dimensions), folded or wrapped
        into the box; with probability eps from the kNN part instead."""
        rows = self._rows
        out = np.empty((n, self.dim))
        from_knn = rng.random(n) < self.eps
        m = int(n - from_knn.sum())
        # a kernel chosen by weight among the points in input order (the table's order
        # depends on whether a tree was built: the draws must not)
        weight = self._weights[self._row_of]
        i = self._row_of[rng.choice(len(rows), m, p=weight / weight.sum())]
        if self.dim == 2:
            u = rng.beta(1.0, 4.0, m)
            theta = rng.random(m) * 2 * np.pi
            z = np.sqrt(u)[:, None] * np.column_stack([np.cos(theta), np.sin(theta)])
        else:  # balls: a uniform direction, the radius from u
            u = rng.beta(1.5, 4.0, m)
            z = rng.standard_normal((m, 3))
            z *= (np.sqrt(u) / np.linalg.norm(z, axis=1))[:, None]
        drawn = self._kernel_points(i, z[:, None, :])[:, 0]
        out[~from_knn] = self._into_box(drawn)
        if from_knn.any():
            out[from_knn] = self.knn.sample(int(from_knn.sum()), rng)
        return out

    def _into_box(self, frame):
        """Kernel draws (frame coordinates) as points of the box: folded back along
        non-periodic axes (mirrored in the sides, as the sums fold), wrapped along periodic
        ones (``BoxMetric.wrap``, the one wrapping rule)."""
        period = self.hi - self.lo
        for a in range(self.dim):
            if not self.periodic[a]:
                v = np.abs(frame[:, a])  # the mirror in the lower side
                frame[:, a] = np.where(v > period[a], 2 * period[a] - v, v)
        return self._metric.wrap(frame + self.lo)


def smoothing_key(alpha, c):
    """(alpha, c) to 12 digits: a smoothing reached by half steps is the grid's value."""
    return float(f"{alpha:.12g}"), float(f"{c:.12g}")


def kernel_table(frame, weights, kernels):
    """The kernels' table of ``kernels`` (``engine.kernelsum`` or ``kernelsum3``): a row per
    centre (frame coordinates (n, d)) with its weight and original row, in that order, the
    kernel columns zero."""
    n, dim = frame.shape
    rows = np.zeros((n, kernels.COLUMNS))
    rows[:, :dim] = frame
    rows[:, kernels.W] = weights
    rows[:, kernels.ROW] = np.arange(n)
    return rows


def spatial_order(points, lo, hi):
    """An order of points (n, d) of the box [lo, hi] (periodic coordinates wrapped or not:
    those outside fall in the side cells) along the Z (Morton) curve of a grid of
    2^(16 // d) cells per axis: points near each other come near each other. The keys fit
    16 bits, so that numpy's stable sort is a radix sort (O(n))."""
    dim = points.shape[1]
    bits = 16 // dim
    spread = np.zeros(1 << bits, np.uint16)  # a cell index's bits, dim - 1 zeros apart
    cells = np.arange(1 << bits)
    for b in range(bits):
        spread |= (((cells >> b) & 1) << (dim * b)).astype(np.uint16)
    key = np.zeros(len(points), np.uint16)
    top = (1 << bits) - 1
    for a in range(dim):
        scale = (1 << bits) / float(hi[a] - lo[a])
        cell = np.clip(((points[:, a] - lo[a]) * scale).astype(np.intp), 0, top)
        key |= spread[cell] << np.uint16(a)
    return np.argsort(key, kind="stable")


def z_order(frame, period, bits=10):
    """An order of points (q, d) in the box [0, period] along the Z (Morton) curve of a
    2^bits grid per axis: points near each other come near each other."""
    scale = (1 << bits) - 1
    dim = frame.shape[1]
    key = np.zeros(len(frame), np.uint64)
    for a in range(dim):
        cell = np.clip(frame[:, a] / period[a] * scale, 0, scale).astype(np.uint64)
        for b in range(bits):
            key |= ((cell >> np.uint64(b)) & np.uint64(1)) << np.uint64(dim * b + a)
    return np.argsort(key, kind="stable")


def square_integral(density, draws=20000, seed=0):
    """The integral of f^2 over the domain: the density's own where it has one
    (``AdaptiveDensity.square_terms``: a cubature over isotropic kernels, no random draws),
    else by Monte Carlo, the mean of f at ``draws`` points drawn from f (seeded, so
    repeatable)."""
    values, weights = _square_terms(density, draws, seed)
    return float((values * weights).sum() / weights.sum())


def _square_terms(density, draws, seed=0):
    """``square_integral`` as (values, weights), their weighted mean the integral: the
    density's own (``AdaptiveDensity.square_terms``) or f at ``draws`` points drawn from f."""
    if hasattr(density, "square_terms"):
        return density.square_terms(draws, seed)
    return _at_own_draws(density, draws, seed), np.ones(int(draws))


def weight_at_place(points, weights):
    """The total weight of the points (n, d) at exactly each point's place, itself included
    (a lexicographic sort groups equal points)."""
    order = np.lexsort(points.T[::-1])
    p = points[order]
    new = np.ones(len(p), bool)
    new[1:] = np.any(p[1:] != p[:-1], axis=1)
    group = np.cumsum(new) - 1
    total = np.bincount(group, weights[order])
    out = np.empty(len(points))
    out[order] = total[group]
    return out


def systematic_sample(n, most):
    """Up to ``most`` of range(n), evenly spaced (all of them if n <= most)."""
    return np.arange(n) if n <= most else np.linspace(0, n - 1, most).astype(np.int64)


def ball_cubature(dim, rings=3):
    """(z (q, dim), weights (q,)): a cubature for the triweight (1 - |z|^2)^3 on the unit
    disk (dim 2) or ball (dim 3), weights summing to 1. Radii: u = |z|^2 at the Gauss-Jacobi
    nodes of the weight (1 - u)^3 u^(dim / 2 - 1) on [0, 1] (exact for polynomials in u of
    degree 2 rings - 1, the kernel's own square among them); directions: 8 evenly spaced
    angles a ring in the plane, each ring turned half a step from the last, or the 12
    vertices of an icosahedron in space, every other ring turned a quarter turn."""
    x, w = roots_jacobi(rings, 3.0, dim / 2.0 - 1.0)
    u, w = (x + 1.0) / 2.0, w / w.sum()
    if dim == 2:
        angle = 2.0 * np.pi * np.arange(8) / 8
        ring = [np.column_stack([np.cos(angle + j * np.pi / 8), np.sin(angle + j * np.pi / 8)])
                for j in range(rings)]  # fmt: skip
    else:
        phi = (1.0 + np.sqrt(5.0)) / 2.0
        ico = np.array([(0, s, t * phi) for s in (-1, 1) for t in (-1, 1)], float)
        ico = np.concatenate([ico, np.roll(ico, 1, axis=1), np.roll(ico, 2, axis=1)])
        ico /= np.linalg.norm(ico, axis=1)[:, None]
        turned = np.column_stack([-ico[:, 1], ico[:, 0], ico[:, 2]])  # a quarter turn about z
        ring = [ico if j % 2 == 0 else turned for j in range(rings)]
    z = np.concatenate([np.sqrt(u[j]) * ring[j] for j in range(rings)])
    weights = np.concatenate([np.full(len(ring[j]), w[j] / len(ring[j])) for j in range(rings)])
    return z, weights


def _at_own_draws(density, draws, seed):
    """f at ``draws`` points drawn from f with the generator seeded by ``seed``."""
    return density(density.sample(int(draws), np.random.default_rng(seed)))


SQUARE_KERNELS = 1 << 17  # kernels in the integral of f^2 read through binned lattices
PER_SENSITIVITY_KEPT = 3  # unit radii and binned levels kept (a climb's alphas: 3 at a time)
BINNED_KEPT = 4  # binned lattices kept for later reads (a search's last candidates)
GRID_BINNED_CELLS = 16  # grid cells a kernel covers (mean) from which grids read binned sums
GRID_BINNED_COVER = 20  # and kernels covering a point (mean) from which (few: sums spiky,
# binning's error larger: 1.5 % L1 at 8, 0.5-0.7 % at 20-40 on a uniform disk)
ONE_LEAF_QUERIES = 64  # exact sums at more points than this build the kernels' kd-tree
LATTICE_SAMPLES = 5  # lattice steps per kernel radius on the coarser lattices (``engine.lattice``)
EXACT_TERMS = 2e7  # a grid's exact sums below this many kernel terms (0.1-0.2 s): exact
LATTICE_VALUES = 1 << 22  # the most values the lattices may hold (32 MiB), per thread
CRITERIA = ("likelihood", "least-squares")
BANDWIDTHS = tuple(2.0 ** (np.arange(-6, 7) / 2))  # 1/8 to 8, steps of sqrt(2)
SENSITIVITIES = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6)
COARSE = 4000  # a first climb's points, when there are more than twice as many
HALF_STEP = 2.0**0.25  # the last search's step in c: half the grid's


def choose_smoothing(
    density, alphas=SENSITIVITIES, bandwidths=BANDWIDTHS, loo_points=20000, random_state=0,
    criterion="likelihood", progress=None, binned=None,
):  # fmt: skip
    """(sensitivity, bandwidth, table): the pair of the grid alphas x bandwidths with the
    best cross-validation score of the ``AdaptiveDensity`` at up to ``loo_points`` of its
    points (chosen by ``random_state``), by climbing from the candidates nearest (1/2, 1) to
    the best grid neighbour until none is better: the score is smooth in both, so a climb
    scores a few pairs, not all. Over 2 COARSE points, a first climb on a fifth of them
    (at least COARSE) finds the region at a fifth of the cost, and the second starts there
    (exact sums only: binned ones cost about the same for any number of points).
    ``criterion``: "likelihood" (mean leave-one-out log-density, higher is better: what
    held-out likelihood rewards) or "least-squares" (``AdaptiveDensity.least_squares``,
    lower is better: an unbiased estimate of the integrated squared error less a constant,
    which favours the wider kernels that L1 and L2 errors reward). The climb ends on the
    grid's half steps in c at its alpha (``_widest_within_one_se``): the widest c whose
    score is within one standard error of the best, so the choice may lie between grid
    values. The table has a row (alpha, c, score) per pair the last climb scored, in that
    order, then the half steps (the score as defined above for the criterion). The density
    is left at the chosen pair. ``progress``: called with the number of pairs scored so far
    after each (long work shows it; a pass costs about ``loo_points`` c^2 k kernel terms
    exactly). ``binned``: score with kernel sums through binned lattices
    (``AdaptiveDensity.loo``; its error is stated in ``engine.binned``), a pass then costing
    O(n) whatever c^2 k; None: where that is faster (isotropic kernels in a box,
    loo_points * k >= BINNED_FROM) and the sample has few copies (at most ``BINNED_COPIES``
    of its points share their place: next to the share left out at a tie, binning's error
    is not small). Binned least-squares scores read every point, not ``loo_points`` of
    them: that score's noise is its weakness, and a read costs O(1) (the accuracy tables'
    LSCV column, docs/uses.md, is measured so). Binned searches over THIN_FROM points (2^15
    in the plane, 2^19 in space) climb on a thinned estimate first (``_climb_thinned``)."""
    criterion = check_criterion(criterion)
    count = [0]

    def scored_one():
        count[0] += 1
        if progress is not None:
            progress(count[0])

    n = len(density.pilot)
    m = min(n, int(loo_points))
    sample = None if m == n else np.sort(random_generator(random_state).choice(n, m, False))
    i = int(np.argmin(np.abs(np.asarray(alphas) - 0.5)))
    j = int(np.argmin(np.abs(np.log(bandwidths))))
    binned = _binned_scores(density, sample, criterion, binned)
    if binned and criterion == "least-squares":  # its noise is its weakness: every point
        sample, m = None, n  # (binned reads cost O(1) a point, against O(n) a pass)
    if m > 2 * COARSE and not binned:  # binned passes cost about O(n), whatever m
        pool = np.arange(n) if sample is None else sample
        coarse = np.sort(random_generator(random_state).choice(pool, max(COARSE, m // 5), False))
        coarse_scores = Scores(density, coarse, criterion, scored_one, binned)
        i, j, _ = _climb(coarse_scores, alphas, bandwidths, i, j)
    scores = Scores(density, sample, criterion, scored_one, binned)
    thinned = binned and n >= THIN_FROM[density.dim] and len(bandwidths) > 1
    if thinned:  # the table: every pair the full estimate scored (the climb's are another's)
        alpha, c = _climb_thinned(density, scores, alphas, bandwidths, i, j, m, random_state)
        rows = []
    else:
        i, j, scored = _climb(scores, alphas, bandwidths, i, j)
        alpha, c = float(alphas[i]), float(bandwidths[j])
        rows = [(alphas[a], bandwidths[b], v) for (a, b), v in scored.items()]
    if len(bandwidths) > 1:
        c, settled = _widest_within_one_se(scores, alpha, c, max(bandwidths))
        near = [b for a, b, _ in rows if a == alpha]
        rows += [(alpha, b, v) for b, v in settled.items() if not np.isclose(near, b).any()]
    if thinned:
        rows = [(a, b, scores(a, b)) for a, b in scores.scored()]
    sign = 1.0 if criterion == "likelihood" else -1.0  # the table has the scores as defined
    table = np.array([(a, b, sign * v) for a, b, v in rows])
    density.set_bandwidth(c, alpha)
    return alpha, c, table


# binned searches over this many points climb on a thinned estimate: a thinned pass bins an
# eighth of the kernels and reads an eighth of the sample, on the lattices of wider kernels
# (in space most of a pass falls with the kernels' number; in the plane fit + 512^2 grid at
# 10^5 points on the seven truths of density_accuracy.py went from 0.43-0.70 s to 0.31-0.61 s,
# the same L1 or lower: docs/uses.md, the time budget curve; at 10^4 the thinned estimate's
# 1,250 points moved the hole's sensitivity from 0 to 0.3 and its L1 up 14 % before the full
# estimate decided it: from 2^15 points, thinned estimates of 4,096 or more)
THIN_FROM = {2: 1 << 15, 3: 1 << 19}
THIN_EVERY = 8  # the thinned estimate's kernels: every 8th along the spatial order
THIN_LEAST = 2000  # a thinned climb's points, at least (loo_points / THIN_EVERY else: it
# finds the region, the full estimate decides; at 10^5 and 10^6 in the plane fit + grid fell
# 10-25 % on six of seven truths against reading loo_points, the L1 the same on all)


def _climb_thinned(density, scores, alphas, bandwidths, i, j, m, random_state):
    """(alpha, c) for ``choose_smoothing`` at many points, scored through binned sums: the
    climb over alphas x bandwidths from (i, j) runs on ``density.thinned(THIN_EVERY)``
    (a pass costs about its kernels' number, an eighth, and reads an eighth of the sample,
    at least THIN_LEAST points), then the climb's c, scaled by the
    kernel estimate's rate (n_eff ratio)^(1 / (d + 4)) (a bandwidth's best value goes as
    n^(-1 / (d + 4)); in the plane an eighth of the kernels is one grid step, 1 / sqrt 2),
    is walked in the grid's half steps on ``scores`` (the full estimate's) to the best
    one, at the climb's alpha; then the full estimate's neighbours in alpha at that c are
    scored, and while one is better the search moves there and walks c again. The thinned
    estimate finds the region (far optima cost its passes, not the full one's); the full
    one decides: without that last step the thinned choice of alpha stood, 0.1 off the
    full search's on three of seven truths at 10^6 points, with L1 up to 7 % higher."""
    thin = density.thinned(THIN_EVERY)
    nt = len(thin.pilot)
    mt = min(nt, max(m // THIN_EVERY, THIN_LEAST))  # its share of the sample: a region
    sub = None if mt == nt else np.sort(random_generator(random_state).choice(nt, mt, False))
    thin_scores = Scores(thin, sub, scores.criterion, scores._scored, True)
    rate = (thin.n_eff / density.n_eff) ** (1.0 / (density.dim + 4))
    j = int(np.argmin(np.abs(np.log(np.asarray(bandwidths) * rate / bandwidths[j]))))
    i, j, _ = _climb(thin_scores, alphas, bandwidths, i, j)  # from (i, j) at the thinned rate
    c = float(bandwidths[j]) * rate
    lowest, widest = min(bandwidths), max(bandwidths)

    def walk(alpha, c):
        """The best half step in c at alpha from c, up or down while the score rises."""
        while True:
            here = scores(alpha, c)
            if c / HALF_STEP >= lowest * (1 - 1e-9) and scores(alpha, c / HALF_STEP) > here:
                c /= HALF_STEP
            elif c * HALF_STEP <= widest * (1 + 1e-9) and scores(alpha, c * HALF_STEP) > here:
                c *= HALF_STEP
            else:
                return c, here

    c, best = walk(float(alphas[i]), c)
    while True:  # the full estimate's neighbours in alpha at that c, moved while better
        near = [a for a in (i - 1, i + 1) if 0 <= a < len(alphas)]
        top = max(near, key=lambda a: scores(float(alphas[a]), c), default=None)
        if top is None or not scores(float(alphas[top]), c) > best:
            break
        i = top
        c, best = walk(float(alphas[i]), c)
    return float(alphas[i]), c


OWN_SHARE = 0.5  # binned leave-one-out sums where the point's own share is less than this
BINNED_FROM = 1e6  # loo_points * k from here: binned passes faster (binned_scores.py)
BINNED_COPIES = 0.01  # binned scores only where at most this share of the sample has copies


def _binned_scores(density, sample, criterion, binned):
    """Whether ``choose_smoothing`` scores through binned lattices (``binned`` None: auto)."""
    able = density.shape == "isotropic"
    able = able and not getattr(density, "on_sphere", False)  # lattices of a box only
    if binned is not None:
        if binned and not able:
            raise InputError(
                "binned=True scores isotropic kernels in a box, the plane's or space's "
                '(not shape="local", not on the sphere); use binned=False or None'
            )
        return bool(binned)
    n = len(density.pilot)
    m = n if sample is None else len(sample)
    if not able or m * density.k < BINNED_FROM:
        return False
    idx = np.arange(n) if sample is None else np.asarray(sample)
    copies = density._copies_at(idx)
    return float(np.mean(copies > density.weights_of(idx) * (1 + 1e-9))) <= BINNED_COPIES


class Scores:
    """The cross-validation score of an ``AdaptiveDensity`` at the points ``sample`` for
    each smoothing (alpha, c) asked, each computed once (a search asks for some twice): the
    score as terms (values, weights, factor), higher is better, the sum of factor * (weighted
    mean of values); two smoothings' values pair item by item (the same points; the same
    seeded draws), so the standard error of a difference of scores comes from the
    differences of values (``difference_se``)."""

    def __init__(self, density, sample, criterion, scored=None, binned=False):
        self.density, self.criterion, self._scored = density, criterion, scored
        self.binned = binned
        n = len(density.pilot)
        self.idx = np.arange(n) if sample is None else np.asarray(sample)
        self._terms = {}

    def terms(self, alpha, c):
        key = smoothing_key(alpha, c)  # half steps meet grid values
        if key not in self._terms:
            density, idx = self.density, self.idx
            density.set_bandwidth(key[1], key[0])
            w = density.weights_of(idx)
            if self.criterion == "likelihood":
                self._terms[key] = [(density.loo(idx, self.binned), w, 1.0)]
            else:
                square, weights = _square_terms(density, len(idx))
                loo = np.exp(density.loo(idx, self.binned))
                self._terms[key] = [(square, weights, -1.0), (loo, w, 2.0)]
            if self._scored is not None:
                self._scored()
        return self._terms[key]

    def __call__(self, alpha, c):
        return float(sum(f * (v * w).sum() / w.sum() for v, w, f in self.terms(alpha, c)))

    def scored(self):
        """The smoothings (alpha, c) scored so far, in order."""
        return list(self._terms)

    def difference_se(self, one, other):
        """Standard error of the difference of the scores at smoothings one and other."""
        var = 0.0
        for (v, w, f), (v0, _, _) in zip(self.terms(*one), self.terms(*other), strict=True):
            d = v - v0
            mean = (d * w).sum() / w.sum()
            var += f * f * ((w * (d - mean)) ** 2).sum() / w.sum() ** 2
        return float(np.sqrt(var))


def _widest_within_one_se(scores, alpha, c, widest):
    """The last step of the search, on the grid's half steps in c at the climb's alpha: the
    best of c / HALF_STEP, c, c * HALF_STEP, then the widest c above it, step by step up to
    ``widest``, whose score is within one standard error of the best's (the one-standard-
    error rule of cross-validation: where the score is flat within its noise, the smoother
    estimate; at large n the likelihood's optimum is such a flat top, and L1 errors reward
    its wide side). Returns (c, {c: score} of the candidates scored here but c itself,
    higher is better)."""
    seen = {}

    def score(j):
        seen[j] = scores(alpha, c * HALF_STEP**j)
        return seen[j]

    best = max((j for j in (-1, 0, 1) if c * HALF_STEP**j <= widest), key=score)
    chosen = best
    while c * HALF_STEP ** (chosen + 1) <= widest * (1 + 1e-9):
        se = scores.difference_se(
            (alpha, c * HALF_STEP ** (chosen + 1)), (alpha, c * HALF_STEP**best)
        )
        if score(chosen + 1) < score(best) - se:
            break
        chosen += 1
    return c * HALF_STEP**chosen, {c * HALF_STEP**j: v for j, v in seen.items() if j}


def _climb(scores, alphas, cs, i, j):
    """Hill-climb of a cross-validation score (``Scores``) over the grid alphas x cs from
    (i, j): the best of the four neighbours, then on in that direction while the score
    rises (a pattern search: a far optimum costs one pair a step), until no neighbour is
    better. Returns (i, j) of the best pair found, {(i, j): score} of every pair scored
    (higher is better for both criteria: the least-squares score negated)."""
    scored = {}

    def score(a, b):
        if (a, b) not in scored:
            scored[a, b] = scores(alphas[a], cs[b])
        return scored[a, b]

    def inside(a, b):
        return 0 <= a < len(alphas) and 0 <= b < len(cs)

    best = score(i, j)
    while True:
        steps = [(i + a, j + b) for a, b in ((-1, 0), (1, 0), (0, -1), (0, 1))]
        top = max((ab for ab in steps if inside(*ab)), key=lambda ab: score(*ab))
        if not score(*top) > best:
            return i, j, scored
        di, dj = top[0] - i, top[1] - j
        (i, j), best = top, score(*top)
        # on along the step while it keeps improving (one new pair a step, not three)
        while inside(i + di, j + dj) and score(i + di, j + dj) > best:
            i, j = i + di, j + dj
            best = score(i, j)


def unit_shapes(cov, n, max_ratio):
    """Unit-determinant shapes (s11, s12, s22) per point: the identity without ``cov``,
    else cov scaled to determinant 1 with its axes ratio sqrt(l1 / l2) at most max_ratio."""
    if cov is None:
        return np.tile([1.0, 0.0, 1.0], (n, 1))
    a, b, c = cov[:, 0], cov[:, 1], cov[:, 2]
    half = 0.5 * (a + c)
    gap = np.sqrt(0.25 * (a - c) ** 2 + b * b)
    l1 = np.maximum(half + gap, 1e-300)
    l2 = np.maximum(half - gap, l1 / max_ratio**2)
    # eigenvector of l1: (b, l1 - a) or, when b == 0, the axis of the larger variance
    vx = np.where(np.abs(b) > 0, b, np.where(a >= c, 1.0, 0.0))
    vy = np.where(np.abs(b) > 0, l1 - a, np.where(a >= c, 0.0, 1.0))
    norm = np.hypot(vx, vy)
    vx, vy = vx / norm, vy / norm
    bad = ~(np.isfinite(l1) & np.isfinite(vx) & np.isfinite(vy))
    s1, s2 = np.sqrt(l1 / l2), np.sqrt(l2 / l1)  # determinant 1
    out = np.column_stack(
        [s1 * vx * vx + s2 * vy * vy, (s1 - s2) * vx * vy, s1 * vy * vy + s2 * vx * vx]
    )
    out[bad] = (1.0, 0.0, 1.0)
    return out


def check_shape(shape):
    if shape not in ("isotropic", "local"):
        raise InputError(f'shape must be "isotropic" or "local", got {shape!r}')


def check_sensitivity(alpha, alternative=""):
    """alpha: a number in [0, 1] (float), else a clear error."""
    real = (int, float, np.integer, np.floating)
    ok = not isinstance(alpha, (bool, np.bool_)) and isinstance(alpha, real)
    if not ok or not 0.0 <= float(alpha) <= 1.0:
        raise InputError(f"sensitivity must be {alternative}a number in [0, 1], got {alpha!r}")
    return float(alpha)


def check_bandwidth(c, alternative=""):
    """The adaptive estimate's factor c: a finite number > 0, as a float."""
    real = (int, float, np.integer, np.floating)
    ok = not isinstance(c, (bool, np.bool_)) and isinstance(c, real)
    if not (ok and 0 < c < np.inf):
        raise InputError(f"bandwidth must be {alternative}a finite number > 0, got {c!r}")
    return float(c)


def check_criterion(criterion):
    if not (isinstance(criterion, str) and criterion in CRITERIA):
        raise InputError(f'criterion must be "likelihood" or "least-squares", got {criterion!r}')
    return criterion


def check_cv(cv):
    if isinstance(cv, bool) or not isinstance(cv, (int, np.integer)) or cv < 2:
        raise InputError(f"cv must be an integer >= 2, got {cv!r}")


# the kernel tree holds unit vectors shifted into its box [0, 2 OFFSET)^3, far from the
# sides (kernels reach a chord of 2 at most), so that its folding never acts
SPHERE_FRAME_OFFSET = 4.0
DISK_MASS = np.pi / 4.0  # the integral of (1 - |x|^2)^3 over the unit disk


class SphereAdaptiveDensity:
    """The adaptive kernel estimate on the sphere: one triweight kernel per point,
    K_i(x) = w_i / W (1 - |x - x_i|^2 / h_i^2)^3 / (pi h_i^2 / 4), in chord distance |x - x_i|
    between unit vectors. On the unit sphere the area within chord c of a point is pi c^2
    (Archimedes), so dA = pi d(c^2) and each kernel integrates to w_i / W exactly, as the
    plane's disk kernel does, while h_i <= 2 (kernels are capped there). Extents as in the
    plane: h_i = c G (d_i / G)^(2 alpha), d_i the pilot kNN distance at point i (as a chord,
    the kNN estimate's equal-area radius), G their geometric mean; c (``bandwidth``) and alpha
    (``sensitivity``) chosen by ``choose_smoothing`` (exact leave-one-out likelihood). Kernel
    sums through the 3-D kernel tree over the unit vectors (``engine.kernelsum3``): one
    centre per point, every node knowing its widest kernel. Densities are per unit area of
    the sphere of ``radius`` (per steradian for radius 1), like ``KnnDensity``'s.

    Parameters
    ----------
    mesh : Mesh
        On the sphere (``refine(..., sphere=True)``), made from ``points``.
    points : array-like (n, 2) or (n, 3)
        Longitude and latitude in degrees, or unit vectors.
    bandwidth, sensitivity : float
        c > 0 and alpha in [0, 1].
    weights : array-like (n,), optional
        The run's weights.
    knn : KnnDensity, optional
        The pilot, when built already.
    """

    shape = "isotropic"
    dim = 2
    on_sphere = True

    def __init__(self, mesh, points, bandwidth=1.0, sensitivity=0.5, weights=None, knn=None):
        unit, weights, total = sphere_points_of_run(mesh, points, weights)
        if knn is None:
            knn = KnnDensity(mesh, unit, weights=weights)
        self.knn, self.mesh, self.k = knn, mesh, mesh.k
        self.radius = float(mesh.radius)
        w = np.ones(len(unit)) if weights is None else np.asarray(weights, float)
        self.total = float(w.sum())
        self._weights = w
        self._unit = unit
        self.eps = 1.0 / self.total  # the kNN estimate's share: the plane's defensive mixture
        self.n_eff = self.total**2 / float((w * w).sum())
        frame = unit + SPHERE_FRAME_OFFSET  # inside the kernel tree's box, far from its sides
        self._rows, self._box, self._node = kernelsum3.build_centres(frame, w)
        order = self._rows[:, kernelsum3.ROW].astype(np.int64)
        self._row_of = np.empty(len(unit), np.int64)
        self._row_of[order] = np.arange(len(unit))
        self._extent = np.zeros(len(self._node))
        # the pilot: d_Pk at the points (interpolated), as the chord of the unit sphere
        d = knn.distance.pieces.interpolate(unit)
        lost = ~np.isfinite(d)
        if lost.any():
            d[lost] = knn.distance.index.kth(unit[lost], self.k)
        chord = equal_area_radius(d, self.radius) / self.radius
        self.pilot = d
        n = len(unit)
        self._q = np.empty((n, 1))
        self._r, self._amp, self._log_ratio = np.empty(n), np.empty(n), np.empty(n)
        with np.errstate(divide="ignore"):
            kernelsum.isotropic_units(chord[order], w[order], self.total, DISK_MASS, 2, self._q,
                                      self._r, self._amp, self._log_ratio)  # fmt: skip
        self.set_bandwidth(bandwidth, sensitivity)

    def set_bandwidth(self, bandwidth, sensitivity=None):
        """Make the kernels' extents c G (d / G)^(2 alpha) (at most a chord of 2)."""
        self.bandwidth = check_bandwidth(bandwidth)
        if sensitivity is not None:
            self.sensitivity = check_sensitivity(sensitivity)
        kernelsum3.scale_surface_kernels(self._rows, self._q, self._amp, self._r,
                                         self._log_ratio, self.bandwidth, self.sensitivity,
                                         2.0)  # fmt: skip
        self._extent_stale = True

    def weights_of(self, idx):
        return self._weights[np.asarray(idx)]

    def _sums(self, unit, loo=False):
        """Kernel sums at unit vectors (per steradian); with ``loo`` (the queries are
        centres), without the centres at each query's place, and their weight."""
        m = len(unit)
        out, out2 = np.empty(m), np.empty(m)
        q = np.ascontiguousarray(unit + SPHERE_FRAME_OFFSET)
        if self._extent_stale:
            kernelsum.node_extents(self._rows[:, kernelsum3.R], self._node, self._extent)
            self._extent_stale = False
        rows, box, node, extent = self._rows, self._box, self._node, self._extent
        period = np.full(3, 2.0 * SPHERE_FRAME_OFFSET)
        periodic = np.zeros(3, bool)

        def call(a, b):
            kernelsum3.kernel_sums(rows, box, node, extent, q, loo, period, periodic, out,
                                   out2, a, b)  # fmt: skip

        in_chunks(call, m)
        return out, out2

    def _scale(self):
        """Per steradian to per unit area of the sphere of ``radius``."""
        return 1.0 / self.radius**2

    def __call__(self, x):
        """The density at lon/lat points (..., 2) (or unit vectors (..., 3)), per unit area:
        (1 - eps) the kernels' sum + eps the kNN estimate, eps = 1 / W (as in the plane:
        every point keeps a positive density)."""
        x = np.asarray(x, float)
        flat = unit_vectors(x.reshape(-1, x.shape[-1]))
        knn = self.knn(lonlat_of(flat))
        f = (1.0 - self.eps) * self._sums(flat)[0] * self._scale() + self.eps * knn
        return f.reshape(x.shape[:-1])

    def standard_error(self, x):
        """Pointwise standard error at lon/lat points (..., 2): the sample-point estimate's
        variance, (sum of squared kernel terms) - f^2 / n_eff, as in the plane."""
        x = np.asarray(x, float)
        s, s2 = self._sums(unit_vectors(x.reshape(-1, x.shape[-1])))
        var = np.maximum(s2 - s * s / self.n_eff, 0.0)
        return ((1.0 - self.eps) * np.sqrt(var) * self._scale()).reshape(x.shape[:-1])

    def loo(self, sample=None, binned=False):
        """Leave-one-out log-density at the points ``sample`` (indices; all by default): the
        kernels of the point and of its copies at its place left out (W less their weight
        the total then), as ``AdaptiveDensity.loo`` in the plane; exact sums only."""
        if binned:
            raise InputError("binned scores are built for the plane; on the sphere they are exact")
        idx = np.arange(len(self._unit)) if sample is None else np.asarray(sample)
        rows = self._row_of[idx]
        s, w = self._sums(self._rows[rows, : kernelsum3.Z + 1] - SPHERE_FRAME_OFFSET, loo=True)
        rest = np.maximum(self.total - w, 1e-300)
        knn = self.knn.at_distance(self.pilot[idx])
        f = (1.0 - self.eps) * s * self.total / rest * self._scale() + self.eps * knn
        with np.errstate(divide="ignore"):
            return np.log(f)

    def grid(self, shape=None, extent=None):
        """(longitudes, latitudes, values (ny, nx)) at the centres of a lon/lat grid over the
        whole sphere, or over ``extent`` (lon0, lat0, lon1, lat1) in degrees (longitudes
        wrap)."""
        ny, nx = (360, 720) if shape is None else grid_shape(shape, 2)
        region = (-180.0, -90.0, 180.0, 90.0) if extent is None else extent
        lon, lat = grid_axes(check_extent(region, 2, sphere=True), (ny, nx))
        return lon, lat, self(grid_points([lon, lat])).reshape(ny, nx)

    def sample(self, n, rng):
        """n lon/lat points drawn from the estimate: a kernel by its weight, then a point at
        chord c from its centre with c^2 / h^2 ~ Beta(1, 4) (the triweight's law on the
        sphere, where area grows as c^2) and a uniform direction."""
        rows = self._rows
        i = rng.choice(len(rows), int(n), p=rows[:, kernelsum3.W] / rows[:, kernelsum3.W].sum())
        centre = rows[i, kernelsum3.X : kernelsum3.Z + 1] - SPHERE_FRAME_OFFSET
        centre /= np.linalg.norm(centre, axis=1, keepdims=True)
        c = rows[i, kernelsum3.R] * np.sqrt(rng.beta(1.0, 4.0, len(i)))
        theta = 2.0 * np.arcsin(np.minimum(0.5 * c, 1.0))
        helper = np.where(np.abs(centre[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
        a = np.cross(centre, helper)
        a /= np.linalg.norm(a, axis=1, keepdims=True)
        b = np.cross(centre, a)
        phi = rng.uniform(0, 2 * np.pi, len(i))[:, None]
        x = (np.cos(theta)[:, None] * centre
             + np.sin(theta)[:, None] * (np.cos(phi) * a + np.sin(phi) * b))  # fmt: skip
        return lonlat_of(x)
