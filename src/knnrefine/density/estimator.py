"""knnrefine's density estimate as a scikit-learn estimator (``KnnDensityEstimator``)."""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from .. import _pipeline as pipeline
from .._engine import shipped
from .._metric import lonlat_of, unit_vectors
from .._validation import (
    as_points,
    as_queries,
    as_sphere_points,
    check_radius,
    check_weights,
    default_box,
    random_generator,
)
from ..errors import InputError
from .adaptive import (
    BANDWIDTHS,
    SENSITIVITIES,
    AdaptiveDensity,
    SphereAdaptiveDensity,
    check_bandwidth,
    check_criterion,
    check_cv,
    check_sensitivity,
    check_shape,
    choose_smoothing,
    square_integral,
)
from .distance import check_extent, grid_shape
from .estimate import KnnDensity, default_k, default_pilot_k


class KnnDensityEstimator:
    """knnrefine's density estimate as a scikit-learn estimator (scikit-learn itself is
    optional).

    ``fit(X)`` refines a mesh of X and builds the estimate: by default the adaptive kernel
    estimate ``AdaptiveDensity`` (bandwidths from d_{P,k}, the factor chosen by leave-one-out
    likelihood), or the plain kNN estimate ``KnnDensity`` (``method="knn"``).
    ``score_samples`` gives log-densities, ``score`` the total log-likelihood, ``sample``
    draws from the estimate. ``get_params``/``set_params`` follow scikit-learn's rules, so
    ``clone``, ``GridSearchCV(est, {"k": [...]})`` and ``cross_val_score`` work.

    Parameters
    ----------
    k : int or "cv", optional
        Which neighbour (the smoothing of the kNN estimate, the pilot's of the adaptive one:
        larger is smoother). Default ``default_pilot_k(n)`` = 2 sqrt(n) (adaptive),
        ``default_k(n)`` = sqrt(n) / 2 (kNN). ``"cv"``: the k with the best held-out
        log-likelihood in ``cv``-fold cross-validation (folds shuffled by ``random_state``,
        every fold in the same box, at most ``loo_points`` held-out points scored in all).
        Adaptive: each k's smoothing is chosen once, by the leave-one-out search over all
        the points, and its folds are fitted at it; without ``k_grid`` the candidates are
        the default k times 1/2, 1, 2, 4 and 8, walked from the default towards the better
        neighbour while the score improves; the chosen k's estimate is the one made for its
        search (about 10-15 default fits in all). kNN: every k of ``k_grid``.
    method : None, "adaptive" or "knn"
        The estimate (see above). None (default): the adaptive one, in the plane and in
        space (before issue 30 the kNN one in space). The adaptive one (default or
        ``shape="local"``) had the
        best held-out likelihood and the lowest L1 error on every truth of the project's
        study at n = 1e4 to 1e6 (``benchmarks/density_accuracy.py``, docs/uses.md).
    bandwidth : float > 0 or "cv"
        The adaptive estimate's factor c: kernel extents c G (d_i / G)^(2 alpha), d_i =
        d_{P,k}(X_i), G their geometric mean (c d_i at alpha = 1/2). ``"cv"``: chosen from
        ``BANDWIDTHS`` by leave-one-out log-likelihood at up to ``loo_points`` training
        points (chosen by ``random_state``), jointly with the sensitivity when that is
        ``"cv"`` too, then on half steps the widest within one standard error of the best
        (``choose_smoothing``). Ignored by ``method="knn"``.
    sensitivity : float in [0, 1] or "cv"
        The adaptive estimate's alpha: kernels ~ f^(-alpha). 1/2 is Abramson's law, 0 a
        fixed bandwidth; ``"cv"`` (default) chooses from ``SENSITIVITIES`` (0 to 0.6) with
        the bandwidth. Heavy tails and flat regions choose less than 1/2, narrow peaks 1/2
        (docs/uses.md).
    shape : "isotropic" or "local"
        The adaptive estimate's kernels: disks (balls in space), or ellipses shaped like the
        local covariance of the points (thin ridges, curved structure; the plane only).
    whiten : bool
        Work in coordinates divided by each axis' standard deviation (data whose axes have
        different units: millimetres against grams); densities are returned in the data's
        units. The mesh ``mesh_`` is then in the scaled coordinates.
    tau : float > 2
        Well-spacedness of the mesh (``refine``).
    periodic : bool or (bool, bool)
        Flat torus along these axes (``box`` then required).
    box : (xmin, ymin, xmax, ymax), optional
        Where the estimate lives: given, it integrates to 1 over the box and is 0 outside it
        along non-periodic axes (log-density -inf there); periodic axes wrap. Default (no
        box, no periodic axis): the estimate is built in the data's bounding box widened by
        ``margin`` of its sides on every side, and has tails everywhere, as a kernel
        estimate does: a multivariate Cauchy density about that box of one point's weight
        (1 / n_eff) is mixed in (``tail_``), so that held-out points anywhere score finitely
        and cross-validation and model comparison work.
    margin : float >= 0
        See ``box`` (ignored when a box is given).
    min_size : float, optional
        The resolution floor (``refine``).
    subdivide : bool
        Evaluate exactly at edge midpoints too (``KnnDistance``).
    cv, k_grid, random_state, loo_points
        For ``k="cv"``: the number of folds, the candidate values of k (default: the
        adaptive estimate's walk above; the kNN estimate's 10 values spaced geometrically
        from 4 to a twentieth of a fold's training points), the seed of the fold assignment
        and of the subsamples (an int or None); the size of the leave-one-out subsample of
        the smoothing search and of the held-out points scored.
    criterion : "likelihood" or "least-squares"
        What the searches ("cv" above) optimise: held-out log-likelihood (default; its
        choice wins held-out likelihood and Hellinger distance), or least-squares
        cross-validation, an estimate of the integrated squared error (``choose_smoothing``):
        it picks wider kernels, and won L1 error where likelihood's choice lost it in the
        project's study at 1e6 (docs/uses.md). ``score`` stays the log-likelihood.
    progress : callable, optional
        As ``knnrefine.refine``'s: progress(vertices, pending) while the mesh is refined;
        a callable with a ``phase`` argument also gets progress(pairs, 0, phase="choosing
        the smoothing") after each pair (alpha, c) the search scored.
    sphere : bool
        X are points on the sphere: (n, 2) longitude and latitude in degrees or (n, 3) unit
        vectors (``refine(..., sphere=True)``). Kernels in great-circle geometry
        (``density.adaptive.SphereAdaptiveDensity``: triweights in chord distance, exactly
        normalised on the sphere), densities per steradian (per unit area with ``radius``),
        no box, no tail (the sphere is bounded); ``grid`` is a longitude by latitude grid,
        ``sample`` returns points in X's form. Not with ``periodic``, ``box``, ``whiten`` or
        ``shape="local"``.
    radius : float, optional
        The sphere's radius, in the unit densities are wanted per (6371.0088: per km^2).

    Attributes after ``fit``: ``k_``, ``bandwidth_`` (adaptive), ``box_`` (data units),
    ``tail_`` (the ``CauchyTail`` mixed in when no box was given, else None),
    ``scale_`` (the whitening divisors, ones without), ``method_`` (the estimate used),
    ``n_samples_`` (the effective sample size n_eff with weights), ``n_features_in_`` (2 or
    3), ``feature_names_in_`` (the columns' names, when X was a DataFrame with names that are
    all strings, as scikit-learn keeps them), ``mesh_`` (the ``Mesh``),
    ``density_`` (the ``AdaptiveDensity`` or ``KnnDensity``), ``sensitivity_`` (adaptive); when
    either is ``"cv"``, ``loo_scores_`` (a row (alpha, c, score) for every pair the search
    scored: the leave-one-out log-likelihood per point, or the least-squares score, by
    ``criterion``) and ``bandwidths_``, ``bandwidth_scores_`` (the curve over c at the chosen
    alpha), with ``k="cv"`` ``cv_ks_`` and ``cv_scores_`` (each candidate scored: the mean
    held-out log-likelihood per point, or the least-squares score: the curve) and, adaptive,
    ``cv_smoothings_`` (each candidate's (sensitivity, bandwidth)).
    """

    BANDWIDTHS = BANDWIDTHS
    SENSITIVITIES = SENSITIVITIES

    def __init__(
        self,
        k: int | str | None = None,
        *,
        method: str | None = None,
        bandwidth: float | str = "cv",
        sensitivity: float | str = "cv",
        shape: str = "isotropic",
        whiten: bool = False,
        tau: float = 3.0,
        periodic: bool | tuple = False,
        box: tuple | None = None,
        margin: float = 0.1,
        min_size: float | None = None,
        subdivide: bool = True,
        cv: int = 5,
        k_grid: Sequence[int] | None = None,
        random_state: int | np.random.Generator | np.random.RandomState | None = 0,
        loo_points: int = 20000,
        criterion: str = "likelihood",
        progress: Callable | None = None,
        sphere: bool = False,
        radius: float | None = None,
    ) -> None:
        self.k = k
        self.method = method
        self.bandwidth = bandwidth
        self.sensitivity = sensitivity
        self.shape = shape
        self.whiten = whiten
        self.tau = tau
        self.periodic = periodic
        self.box = box
        self.margin = margin
        self.min_size = min_size
        self.subdivide = subdivide
        self.cv = cv
        self.k_grid = k_grid
        self.random_state = random_state
        self.loo_points = loo_points
        self.criterion = criterion
        self.progress = progress
        self.sphere = sphere
        self.radius = radius

    # -- scikit-learn's parameter protocol ---------------------------------------------------
    @classmethod
    def _param_names(cls):
        params = inspect.signature(cls.__init__).parameters
        return sorted(p for p in params if p != "self")

    def get_params(self, deep: bool = True) -> dict:
        """The constructor's parameters (scikit-learn's protocol).

        Parameters
        ----------
        deep : bool
            Ignored (no parameter is an estimator).

        Returns
        -------
        dict
        """
        return {name: getattr(self, name) for name in self._param_names()}

    def set_params(self, **params) -> KnnDensityEstimator:
        """Set constructor parameters (scikit-learn's protocol).

        Parameters
        ----------
        **params
            Constructor parameters by name.

        Returns
        -------
        self

        Raises
        ------
        InputError
            An unknown parameter.
        """
        valid = self._param_names()
        for name, value in params.items():
            if name not in valid:
                raise ValueError(
                    f"invalid parameter {name!r} for KnnDensityEstimator; valid ones: "
                    f"{', '.join(valid)}"
                )
            setattr(self, name, value)
        return self

    def __sklearn_tags__(self):
        """scikit-learn >= 1.6 asks estimators for their tags (imported only then)."""
        from sklearn.utils import Tags, TargetTags

        return Tags(estimator_type="DensityEstimator", target_tags=TargetTags(required=False))

    def __repr__(self):
        defaults = type(self)().get_params()
        changed = [
            f"{name}={value!r}"
            for name, value in self.get_params().items()
            if value is not defaults[name] and not _same(value, defaults[name])
        ]
        return f"KnnDensityEstimator({', '.join(changed)})"

    # -- fitting -----------------------------------------------------------------------------
    def fit(
        self, X: ArrayLike, y: None = None, sample_weight: ArrayLike | None = None
    ) -> KnnDensityEstimator:
        """Refine a mesh of X and build the estimate.

        Parameters
        ----------
        X : array-like (n, 2) or (n, 3)
            The points (pandas frames too).
        y : ignored
        sample_weight : array-like (n,), optional
            Relative weights >= 0, as scikit-learn's and scipy's gaussian_kde's: only their
            ratios matter (weights times any factor fit the same estimate). The sample counts
            as its effective size n_eff = (sum w)^2 / sum w^2 (Kish's; n without weights):
            the default k and the tail's weight follow n_eff, and k counts effective points
            (the engine counts the weights scaled to sum to n_eff). A point of weight 2 is
            therefore not two copies of it: copies are two observations, a weight is one
            observation that counts double. In both dimensions.

        Returns
        -------
        self

        Raises
        ------
        InputError
            Bad points, weights or options (``shape="local"`` for points in space).
        """
        self._fit(X, sample_weight, counted=False)
        shipped.upgrade("kernel sums in space")  # this CPU's code, for later fits
        return self

    def _fit(self, X, sample_weight, counted):
        """``fit``, the weights relative (scaled to sum to n_eff) or, with ``counted``,
        counted as they are: a bootstrap resample's counts are copies (its points repeat),
        times the fitted estimate's own weights."""
        dim = 3 if np.ndim(X) == 2 and np.shape(X)[1] == 3 else 2
        self._check_options()
        if self.sphere:  # unit vectors checked here, kept in X's own form
            as_sphere_points(X)
        pts = as_points(X, dim)
        names = feature_names(X)
        if self.shape == "local" and dim == 3 and self.method != "knn":
            raise InputError(
                'shape="local" is built for points in the plane; for points in space use '
                'shape="isotropic" (the default: balls)'
            )
        self.method_ = "adaptive" if self.method is None else self.method
        weights = None
        if sample_weight is not None:
            weights = check_weights(sample_weight, len(pts))
            pts, weights = pts[weights > 0], weights[weights > 0]
            if not counted:
                weights = relative_weights(weights)
            elif np.all(weights == 1.0):
                weights = None
        n = len(pts) if weights is None else float(weights.sum())  # n_eff
        scale = self._scale(pts, weights)
        pts = pts / scale
        box = None if self.sphere else self._box(pts, scale)
        stale_attrs = (
            "cv_ks_", "cv_scores_", "cv_smoothings_", "bandwidths_", "bandwidth_scores_",
            "bandwidth_", "sensitivity_", "loo_scores_",
        )  # fmt: skip
        for stale in stale_attrs:
            self.__dict__.pop(stale, None)  # from an earlier fit
        fitted = None  # the estimate at the chosen k, when k="cv" made it
        if isinstance(self.k, str):
            if self.k != "cv":
                raise InputError(f'k must be an integer, None or "cv", got {self.k!r}')
            self.cv_ks_, self.cv_scores_, fitted = self._cross_validate(pts, weights, box)
            pick = np.argmax if self.criterion == "likelihood" else np.argmin
            k = int(self.cv_ks_[int(pick(self.cv_scores_))])
        else:
            given = self.k
            k = (
                given
                if given is not None
                else (default_k(n) if self.method_ == "knn" else default_pilot_k(n))
            )
            if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= k <= n:
                raise InputError(f"k must be an integer in [1, n = {n:g}], got {k!r}")
        if fitted is None:
            self.density_, self.mesh_ = self._estimate(pts, weights, box, int(k))
        else:  # the chosen k's estimate and its search's record
            (self.density_, self.mesh_), searched = fitted
            self.__dict__.update(searched)
        if self.method_ == "adaptive":
            self.bandwidth_ = self.density_.bandwidth
            self.sensitivity_ = self.density_.sensitivity
        self._train = (pts, np.ones(len(pts)) if weights is None else weights)
        self.tail_ = None  # the box was given (or a torus): the estimate is 0 outside it
        if self.box is None and not np.any(self.periodic) and not self.sphere:
            w = self._train[1]
            bounds = np.asarray(self.mesh_.box, float)
            self.tail_ = CauchyTail(
                centre=0.5 * (bounds[:dim] + bounds[dim:]),
                scale=0.5 * (bounds[dim:] - bounds[:dim]),
                weight=1.0 / float(w.sum()),  # one point's worth: 1 / n_eff
            )
        self.k_ = int(k)
        self.scale_ = tuple(float(v) for v in scale)
        if self.sphere:  # longitude and latitude: the whole sphere
            self.box_ = tuple(float(b) for b in self.mesh_.extent)
        else:
            self.box_ = tuple(float(b) for b in np.array(self.mesh_.box) * np.tile(scale, 2))
        self.n_samples_ = n
        self.n_features_in_ = dim
        if names is None:
            self.__dict__.pop("feature_names_in_", None)  # from an earlier fit
        else:
            self.feature_names_in_ = names
        return self

    def _check_options(self):
        if not isinstance(self.sphere, (bool, np.bool_)):
            raise InputError(f"sphere must be True or False, got {self.sphere!r}")
        if self.sphere:
            given = {
                "periodic": self.periodic is not False,
                "box": self.box is not None,
                "whiten": bool(self.whiten),
                'shape="local"': self.shape != "isotropic",
            }
            if any(given.values()):
                names = ", ".join(name for name, on in given.items() if on)
                raise InputError(f"sphere=True takes no {names}: the sphere has no box, its "
                                 "kernels are isotropic in great-circle geometry")  # fmt: skip
            check_radius(self.radius)
        elif self.radius is not None:
            raise InputError("radius is the sphere's: give it with sphere=True")
        if self.method not in (None, "adaptive", "knn"):
            raise InputError(f'method must be None, "adaptive" or "knn", got {self.method!r}')
        check_shape(self.shape)
        if not isinstance(self.whiten, (bool, np.bool_)):
            raise InputError(f"whiten must be True or False, got {self.whiten!r}")
        if not (isinstance(self.bandwidth, str) and self.bandwidth == "cv"):
            check_bandwidth(self.bandwidth, '"cv" or ')
        if not (isinstance(self.sensitivity, str) and self.sensitivity == "cv"):
            check_sensitivity(self.sensitivity, '"cv" or ')
        check_cv(self.cv)
        check_criterion(self.criterion)
        m = self.loo_points
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 1:
            raise InputError(f"loo_points must be an integer >= 1, got {m!r}")

    def _scale(self, pts, weights):
        """Per-axis divisors: the (weighted) standard deviations with ``whiten``, else 1."""
        if not self.whiten:
            return np.ones(pts.shape[1])
        w = np.ones(len(pts)) if weights is None else weights
        mean = (pts * w[:, None]).sum(axis=0) / w.sum()
        sd = np.sqrt((((pts - mean) ** 2) * w[:, None]).sum(axis=0) / w.sum())
        if not np.all(sd > 0):
            raise InputError(
                "whiten needs points spread along every axis (a standard deviation is 0)"
            )
        return sd

    def _estimate(self, pts, weights, box, k):
        """(density, mesh) at this k: the kNN estimate, or the adaptive one with its
        bandwidth given or chosen by leave-one-out likelihood (recording the curve)."""
        from .._options import Progress

        if self.sphere:
            mesh = pipeline.refine(pts, k, self.tau, weights=weights, radius=self.radius,
                                   min_size=self.min_size, progress=self.progress,
                                   sphere=True)  # fmt: skip
        else:
            mesh = pipeline.refine(
                pts, k, self.tau, periodic=self.periodic, box=box, min_size=self.min_size,
                weights=weights, progress=self.progress,
            )  # fmt: skip
        knn = KnnDensity(mesh, pts, normalized=True, subdivide=self.subdivide, weights=weights)
        if self.method_ == "knn":
            return knn, mesh
        cs = self.BANDWIDTHS if self.bandwidth == "cv" else (float(self.bandwidth),)
        alphas = self.SENSITIVITIES if self.sensitivity == "cv" else (float(self.sensitivity),)
        if self.sphere:
            density = SphereAdaptiveDensity(mesh, pts, cs[0], alphas[0], weights=weights,
                                            knn=knn)  # fmt: skip
        else:
            density = AdaptiveDensity(
                mesh, pts, cs[0], self.shape, weights=weights, knn=knn, sensitivity=alphas[0]
            )
        if len(cs) > 1 or len(alphas) > 1:
            report = Progress(self.progress)
            alpha, _, self.loo_scores_ = choose_smoothing(
                density,
                alphas,
                cs,
                self.loo_points,
                self.random_state,
                self.criterion,
                progress=lambda count: report.stage(count, "choosing the smoothing"),
            )  # leaves the density at the chosen pair; fmt: skip
            at = self.loo_scores_[self.loo_scores_[:, 0] == alpha]
            at = at[np.argsort(at[:, 1])]
            self.bandwidths_, self.bandwidth_scores_ = at[:, 1], at[:, 2]
        return density, mesh

    def _k_candidates(self, n_train, n):
        """The candidate ks: ``k_grid``; else, for the kNN estimate, 10 geometric steps from
        4 to n_train / 20, and for the adaptive one the default pilot's k (of all n points)
        times 1/2, 1, 2, 4 and 8 (at most n_train): held-out likelihood was flat or rising
        above the default in the project's runs (docs/uses.md), while a pilot of a few
        neighbours is noise that the bandwidth has to undo, and its mesh the largest to
        make."""
        if self.k_grid is None:
            if self.method_ == "knn":
                top = max(8, n_train / 20)
                return np.unique(np.round(np.geomspace(4, top, 10)).astype(int))
            ks = np.round(default_pilot_k(n) * 2.0 ** np.arange(-1, 4)).astype(int)
            return np.unique(np.clip(ks, 1, max(1, int(n_train))))
        ks = np.unique(np.asarray(self.k_grid))
        if ks.size == 0 or not np.issubdtype(ks.dtype, np.integer) or ks[0] < 1:
            raise InputError(f"k_grid must hold integers >= 1, got {self.k_grid!r}")
        ks = ks[ks <= n_train]
        if ks.size == 0:
            raise InputError(f"no k of k_grid fits the smallest training fold ({n_train:g} points)")
        return ks

    def _box(self, pts, scale):
        """The box to refine in (scaled coordinates): the user's, else refine's default box
        of the points (``validation.default_box``) widened by ``margin``."""
        if self.box is not None:
            try:
                box = np.asarray(self.box, float)
            except (TypeError, ValueError):
                return self.box  # refine says what is wrong with it
            return tuple(box / np.tile(scale, 2)) if box.shape == (2 * len(scale),) else self.box
        if np.any(self.periodic):  # a torus needs its period: refine says so
            return None
        margin = self.margin
        if isinstance(margin, bool) or not isinstance(margin, (int, float, np.floating)):
            raise InputError(f"margin must be a number >= 0, got {margin!r}")
        if not 0 <= margin < np.inf:
            raise InputError(f"margin must be a finite number >= 0, got {margin!r}")
        dim = pts.shape[1]
        bounds = np.array(default_box(pts))
        lo, hi = bounds[:dim], bounds[dim:]
        pad = margin * (hi - lo)
        return tuple(float(v) for v in (*(lo - pad), *(hi + pad)))

    def _cross_validate(self, pts, weights, box):
        """(candidate ks, the score of each, the chosen k's estimate or None): by
        ``criterion``, the mean held-out log-likelihood per unit of weight (higher is
        better), or the mean over folds of the least-squares score integral f^2 - 2
        (weighted mean of f at the held-out points), lower is better (``square_integral``).
        Every fold is refined in the same box, so that held-out points are in it; folds
        split points, so a point is held out whole, with its weight.

        The adaptive estimate's smoothing is chosen once per k, by the leave-one-out search
        over all the points (``_estimate``), and its folds are fitted at that smoothing: a
        fold costs a mesh and a pilot, not a search, and the estimate at the chosen k is the
        one made for its search (returned with that search's record, so that no k is fitted
        twice). Leave-one-out alone does not choose k: the pilot is computed with the
        left-out point, which favours small k."""
        folds = cv_folds(len(pts), self.cv, self.random_state)
        weight = np.ones(len(pts)) if weights is None else weights
        n = float(weight.sum())
        ks = self._k_candidates(n - max(float(weight[f].sum()) for f in folds), n)
        held = held_out_points(folds, len(pts), self.loo_points, self.random_state)
        held_weight = sum(float(weight[h].sum()) for h in held)
        params = {**self.get_params(), "box": box, "whiten": False}
        adaptive = self.method_ == "adaptive"
        record = ("loo_scores_", "bandwidths_", "bandwidth_scores_")
        sign = 1.0 if self.criterion == "likelihood" else -1.0  # higher is better
        scores, smoothings, kept = {}, {}, {}

        def evaluate(i):
            """The score of ks[i] (each evaluated once); the best estimate so far kept."""
            if i in scores:
                return sign * scores[i]
            fold_params = {**params, "k": int(ks[i])}
            if adaptive:
                for name in record:
                    self.__dict__.pop(name, None)
                estimate = self._estimate(pts, weights, box, int(ks[i]))
                density = estimate[0]
                smoothings[i] = (density.sensitivity, density.bandwidth)
                fold_params.update(sensitivity=density.sensitivity, bandwidth=density.bandwidth)
            total = 0.0
            for test, scored in zip(folds, held, strict=True):
                train = np.ones(len(pts), bool)
                train[test] = False
                fold_weight = None if weights is None else weight[train]
                fold = type(self)(**fold_params)
                fold.fit(pts[train], sample_weight=fold_weight)
                w = weight[scored]
                if self.criterion == "likelihood":
                    total += (fold.score_samples(pts[scored]) * w).sum() / held_weight
                else:
                    f = np.exp(fold.score_samples(pts[scored]))
                    mean = (f * w).sum() / w.sum()
                    square = square_integral(fold.density_, self.loo_points)
                    total += (square - 2 * mean) / len(folds)
            scores[i] = total
            if adaptive and ("score" not in kept or sign * total > kept["score"]):
                kept.update(
                    score=sign * total,
                    estimate=estimate,
                    record={name: self.__dict__[name] for name in record if name in self.__dict__},
                )
            return sign * total

        if adaptive and self.k_grid is None:  # a walk along the doubling grid
            i = int(np.argmin(np.abs(ks - default_pilot_k(n))))
            step = 1 if i + 1 < len(ks) and evaluate(i + 1) > evaluate(i) else -1
            if step == 1:
                i += 1
            while 0 <= i + step < len(ks) and evaluate(i + step) > evaluate(i):
                i += step
        else:
            for i in range(len(ks)):
                evaluate(i)
        for name in record:
            self.__dict__.pop(name, None)
        done = sorted(scores)
        if adaptive:
            self.cv_smoothings_ = np.array([smoothings[i] for i in done])
        fitted = (kept["estimate"], kept["record"]) if adaptive else None
        return ks[done], np.array([scores[i] for i in done]), fitted

    # -- uncertainty -------------------------------------------------------------------------
    def standard_error(self, X: ArrayLike) -> np.ndarray:
        """Pointwise standard error of the density. kNN: f(x) / sqrt(k) (its relative error
        is about 1 / sqrt(k): the ball of radius d_{P,k}(x) holds k points, whose count
        fluctuates like a Poisson variable's); adaptive: the sample-point estimate's variance
        (``AdaptiveDensity.standard_error``).

        Parameters
        ----------
        X : array-like (..., d)

        Returns
        -------
        ndarray (...)
        """
        density = self._fitted()
        if self.method_ == "knn":
            return np.exp(self.score_samples(X)) / np.sqrt(self.k_)
        flat, shape = self._queries(X)
        return (density.standard_error(flat) / self._jacobian()).reshape(shape)

    def bootstrap(
        self,
        X: ArrayLike,
        n_boot: int = 100,
        level: float = 0.9,
        random_state: int | np.random.Generator | np.random.RandomState | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Percentile bands of the density: the estimate refitted (same k and box) on n_boot
        resamples of the training points with replacement (as weights: no copies are made),
        and the (1 - level) / 2 and (1 + level) / 2 quantiles of its values at each point.
        Weights stay with their points, which are resampled (the bootstrap of a weighted
        sample); a point drawn twice counts twice (the resample's repeats are copies, its
        weights counted as they are, not rescaled to its own n_eff).

        Parameters
        ----------
        X : array-like (..., d)
        n_boot : int
            Resamples, >= 2.
        level : float
            In (0, 1).
        random_state : None, int, numpy Generator or RandomState

        Returns
        -------
        lower, upper : ndarray (...)
        """
        density = self._fitted()
        if isinstance(n_boot, bool) or not isinstance(n_boot, (int, np.integer)) or n_boot < 2:
            raise InputError(f"n_boot must be an integer >= 2, got {n_boot!r}")
        if not 0 < level < 1:
            raise InputError(f"level must lie in (0, 1), got {level!r}")
        flat, shape = self._queries(X)
        pts, weight = self._train  # in the fitted (scaled) coordinates
        rng = random_generator(random_state)
        box = None if self.sphere else self.mesh_.box
        params = {**self.get_params(), "k": self.k_, "box": box, "whiten": False}
        if self.method_ == "adaptive":
            params["bandwidth"] = density.bandwidth
            params["sensitivity"] = density.sensitivity
        values = np.empty((int(n_boot), len(flat)))
        for b in range(int(n_boot)):
            # the points, resampled, each with its weight (the bootstrap of a weighted sample)
            draw = rng.multinomial(len(weight), np.full(len(weight), 1.0 / len(weight)))
            draw = draw * weight
            refit = type(self)(**params)._fit(pts, draw, counted=True)  # draws are copies
            values[b] = np.exp(refit.score_samples(flat)) / self._jacobian()
        lo, hi = np.quantile(values, [(1 - level) / 2, (1 + level) / 2], axis=0)
        return lo.reshape(shape), hi.reshape(shape)

    def _fitted(self):
        if not hasattr(self, "density_"):
            raise _not_fitted()
        return self.density_

    # -- evaluation ----------------------------------------------------------------------------
    def score_samples(self, X: ArrayLike) -> np.ndarray:
        """Log-density at points: finite everywhere when no box was given (``tail_``), else
        -inf outside the box along non-periodic axes (the estimate is 0 there); periodic axes
        wrap.

        Parameters
        ----------
        X : array-like (..., d)

        Returns
        -------
        ndarray (...)
        """
        density = self._fitted()
        flat, shape = self._queries(X)
        f = density(flat)
        tail = getattr(self, "tail_", None)
        if tail is not None:  # tails everywhere: finite outside the box
            f = (1.0 - tail.weight) * np.where(np.isnan(f), 0.0, f) + tail.weight * tail(flat)
        f = f / self._jacobian()
        with np.errstate(divide="ignore"):
            out = np.where(np.isnan(f), -np.inf, np.log(np.where(np.isnan(f), 1.0, f)))
        return out.reshape(shape)

    def score(self, X: ArrayLike, y: None = None) -> float:
        """Total log-likelihood of points under the estimate (-inf if one lies outside a box
        that was given).

        Parameters
        ----------
        X : array-like (n, d)
        y : ignored

        Returns
        -------
        float
        """
        return float(self.score_samples(X).sum())

    def sample(
        self,
        n_samples: int = 1,
        random_state: int | np.random.Generator | np.random.RandomState | None = None,
    ) -> np.ndarray:
        """Points drawn exactly from the estimate (``AdaptiveDensity.sample``,
        ``KnnDensity.sample``, and the tail's with its weight when no box was given).

        Parameters
        ----------
        n_samples : int
        random_state : None, int, numpy Generator or RandomState

        Returns
        -------
        ndarray (n_samples, d)
        """
        density = self._fitted()
        if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)):
            raise InputError(f"n_samples must be an integer >= 0, got {n_samples!r}")
        if n_samples < 0:
            raise InputError(f"n_samples must be >= 0, got {n_samples}")
        rng = random_generator(random_state)
        tail = getattr(self, "tail_", None)
        if self.sphere:  # lon/lat draws, as unit vectors when fitted on them
            drawn = density.sample(int(n_samples), rng)
            return unit_vectors(drawn) if self.n_features_in_ == 3 else drawn
        if tail is None:
            return density.sample(int(n_samples), rng) * self.scale_
        from_tail = rng.random(int(n_samples)) < tail.weight
        out = np.empty((int(n_samples), self.n_features_in_))
        out[~from_tail] = density.sample(int((~from_tail).sum()), rng)
        out[from_tail] = tail.sample(int(from_tail.sum()), rng)
        return out * self.scale_

    def grid(
        self, shape: int | tuple | None = None, extent: Sequence[float] | None = None
    ) -> tuple:
        """The density at the centres of a grid over the fitted box, or over any region, in
        the data's units.

        Parameters
        ----------
        shape : int or tuple of int, optional
            As for ``KnnDistance.grid``.
        extent : sequence of float, optional
            The region the grid covers, (x0, y0, x1, y1) or (x0, y0, z0, x1, y1, z1) in the
            data's units, on the sphere (lon0, lat0, lon1, lat1) in degrees; default
            ``box_`` (the whole sphere). Beyond the fitted box the density is the tail's
            (``tail_``), or 0 where the box was given (periodic axes wrap).

        Returns
        -------
        xs, ys[, zs], values : ndarray
            As ``KnnDistance.grid``'s, in the data's units: the density per unit area
            (volume) of the data, ``exp(score_samples)`` at the centres.

        Raises
        ------
        InputError
            A bad shape or extent.
        """
        density = self._fitted()
        if self.sphere:  # longitude by latitude, half a degree by default
            return density.grid((360, 720) if shape is None else grid_shape(shape, 2), extent)
        dim = self.n_features_in_
        scale = np.asarray(self.scale_)
        if extent is not None:  # in the fitted (scaled) coordinates
            extent = np.asarray(check_extent(extent, dim)) / np.tile(scale, 2)
        *axes, values = density.grid(grid_shape(shape, dim), extent)
        values = np.where(np.isnan(values), 0.0, values)  # beyond the box: no mass
        tail = getattr(self, "tail_", None)
        if tail is not None:
            values = (1.0 - tail.weight) * values + tail.weight * tail.on_grid(axes)
        return (*(np.asarray(a) * s for a, s in zip(axes, scale, strict=True)),
                values / self._jacobian())  # fmt: skip

    def _queries(self, X):
        """Query points (..., d) as flat (q, d) in the fitted (scaled) coordinates, and the
        leading shape; non-finite coordinates refused, and columns named otherwise than
        those fitted."""
        self._fitted()
        names, fitted = feature_names(X), getattr(self, "feature_names_in_", None)
        if names is not None and fitted is not None and list(names) != list(fitted):
            raise InputError(
                f"X has the columns {list(names)}, but the estimator was fitted with "
                f"{list(fitted)}: give the columns in the fitted order"
            )
        flat, shape = as_queries(X, self.n_features_in_)
        if not np.isfinite(flat).all():
            raise InputError("X holds NaN or infinite coordinates; give finite points")
        if self.sphere:  # the estimates on the sphere take longitude and latitude
            return lonlat_of(as_sphere_points(flat)), shape
        return flat / np.asarray(self.scale_), shape

    def _jacobian(self):
        """Density in scaled coordinates / density in the data's: the scales' product."""
        return float(np.prod(self.scale_))


def relative_weights(weights):
    """Weights (n,) > 0 scaled to sum to their effective sample size (sum w)^2 / sum w^2, so
    that the engine, which counts weight, counts effective points; None when all are equal
    (the unweighted sample)."""
    if np.all(weights == weights[0]):
        return None
    total = float(weights.sum())
    n_eff = total * total / float((weights * weights).sum())
    return weights * (n_eff / total)


class CauchyTail:
    """The multivariate Cauchy density (Student's t with one degree of freedom) about
    ``centre`` with per-axis ``scale``: the tail an estimate fitted without a box mixes in at
    ``weight`` (one point's worth, 1 / n_eff), so that it is positive everywhere and held-out
    points beyond the box score finitely, as every kernel estimate's tails make it; heavy
    enough for any data (it decays as |x|^-(d + 1))."""

    def __init__(self, centre, scale, weight):
        self.centre = np.asarray(centre, float)
        self.scale = np.asarray(scale, float)
        self.weight = float(weight)
        d = len(self.centre)
        self._norm = math.gamma((d + 1) / 2) / math.pi ** ((d + 1) / 2) / float(np.prod(self.scale))

    def __call__(self, x):
        """The density at points x (q, d)."""
        z = (np.asarray(x, float) - self.centre) / self.scale
        return self._norm * (1.0 + (z * z).sum(axis=1)) ** (-(len(self.centre) + 1) / 2)

    def on_grid(self, axes):
        """The density at the centres of a grid with these axes (x, y[, z]): (..., ny, nx),
        by broadcasting (no array of the centres)."""
        d = len(self.centre)
        u = 1.0
        for a, values in enumerate(axes):
            z = (np.asarray(values, float) - self.centre[a]) / self.scale[a]
            u = u + (z * z).reshape((-1,) + (1,) * a)  # axis a is the array's axis d - 1 - a
        return self._norm * u ** (-(d + 1) / 2)

    def sample(self, n, rng):
        """n points (n, d): a normal vector over the absolute value of an independent one."""
        z = rng.standard_normal((n, len(self.centre))) / np.abs(rng.standard_normal((n, 1)))
        return self.centre + self.scale * z


def feature_names(X):
    """The column names of a DataFrame X as an object array, when all are strings (as
    scikit-learn keeps them); else None."""
    columns = getattr(X, "columns", None)
    if columns is None or not all(isinstance(c, str) for c in columns):
        return None
    return np.asarray(list(columns), dtype=object)


def _same(a, b):
    try:
        return bool(a == b)
    except (TypeError, ValueError):
        return False


def held_out_points(folds, n, most, random_state):
    """The held-out points scored in each fold: all of them when the folds hold at most
    ``most`` points together, else a share of each fold (``most`` in all, each fold's in
    proportion to its size, chosen by ``random_state``): a score costs O(most), not O(n)."""
    if n <= most:
        return list(folds)
    rng = random_generator(random_state)
    return [np.sort(rng.choice(f, max(1, round(most * len(f) / n)), replace=False))
            for f in folds]  # fmt: skip


def cv_folds(n, cv, random_state):
    """The test indices of each of ``cv`` folds of n points, shuffled by random_state."""
    check_cv(cv)
    if cv > n:
        raise InputError(f"cv must be an integer in [2, n = {n}], got {cv!r}")
    order = random_generator(random_state).permutation(n)
    return np.array_split(order, int(cv))


def _not_fitted():
    """scikit-learn's NotFittedError when scikit-learn is installed, else an InputError."""
    message = "this KnnDensityEstimator is not fitted yet: call fit(X) first"
    try:
        from sklearn.exceptions import NotFittedError
    except ImportError:
        return InputError(message)
    return NotFittedError(message)
