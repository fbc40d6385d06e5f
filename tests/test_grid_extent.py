"""Grids over any region (issue 53: ``grid(shape, extent=...)``), in the plane, in space
and on the sphere, for d_{P,k}, the kNN estimate, the adaptive one and the estimator: the
values at the centres are the estimate's own there (its call, or ``exp(score_samples)``),
within the box as through the box's grid, beyond it the tail's or 0, periodic axes and
longitudes wrapped; bad regions refused before any work."""

import numpy as np
import pytest
from conftest import two_blobs, unit_box

import knnrefine
from knnrefine import InputError, KnnDensity, KnnDensityEstimator, KnnDistance
from knnrefine.density.distance import grid_points


def centres(axes):
    return grid_points([np.asarray(a) for a in axes])


@pytest.mark.parametrize("periodic", [False, True], ids=["box", "torus"])
def test_distance_and_knn_grids_over_a_region_are_their_values_at_the_centres(dim, periodic):
    pts = two_blobs(dim, 3000, 2)
    mesh = knnrefine.refine(pts, 10, box=unit_box(dim), periodic=periodic)
    d = KnnDistance(mesh, pts)
    knn = KnnDensity(mesh, pts)
    extent = (0.2, 0.1, 0.3)[:dim] + (0.7, 1.4, 0.6)[:dim]  # beyond the box along y
    shape = (5, 7, 6)[:dim]
    *axes, got = d.grid(shape, extent=extent)
    assert got.shape == shape and [len(a) for a in axes] == list(shape[::-1])
    np.testing.assert_allclose(axes[0], 0.2 + (np.arange(shape[-1]) + 0.5) * 0.5 / shape[-1])
    want = d(centres(axes)).reshape(shape)
    np.testing.assert_array_equal(got, want)
    beyond = (centres(axes)[:, 1] > 1.0).reshape(shape)
    assert beyond.any()
    if periodic:  # the torus wraps: the centres a period down give the same values
        shifted = centres(axes) - np.eye(dim)[1] * (centres(axes)[:, 1:2] > 1.0)
        np.testing.assert_allclose(got.ravel(), d(shifted), rtol=1e-12)
    else:
        assert np.isnan(got[beyond]).all() and np.isfinite(got[~beyond]).all()
    *_, f = knn.grid(shape, extent=extent)
    np.testing.assert_array_equal(f, knn(centres(axes)).reshape(shape))


def test_adaptive_grid_over_a_region_within_the_box_is_the_box_grids_sums(dim):
    """Within the box a region is summed as the box is: against exact sums at its
    centres, to the lattices' tolerance; reaching beyond it, centre by centre, exactly."""
    pts = two_blobs(dim, 4000, 3)
    est = KnnDensityEstimator(box=unit_box(dim), k=40, bandwidth=1.0, sensitivity=0.5).fit(pts)
    extent = (0.25, 0.3, 0.2)[:dim] + (0.55, 0.8, 0.6)[:dim]
    shape = (40, 30, 20)[:dim]
    *axes, got = est.grid(shape, extent=extent)
    exact = np.exp(est.score_samples(centres(axes))).reshape(shape)
    np.testing.assert_allclose(got, exact, rtol=2e-3)
    # beyond the given box: no mass there, and the estimate's own value inside it
    extent = (-0.5,) * dim + (0.6,) * dim
    *axes, got = est.grid(8, extent=extent)
    exact = np.exp(est.score_samples(centres(axes))).reshape(got.shape)
    np.testing.assert_allclose(got, exact, rtol=1e-10)
    assert (got[(centres(axes) < 0).any(axis=1).reshape(got.shape)] == 0).all()


def test_estimator_grid_beyond_the_data_box_is_the_tail():
    """No box given: beyond the fitted box the estimate is its Cauchy tail alone, and the
    grid there is exp(score_samples) at the centres; whitened coordinates are the data's."""
    rng = np.random.default_rng(4)
    X = rng.normal([10.0, -3.0], [2.0, 0.5], (3000, 2))
    est = KnnDensityEstimator(k=50, whiten=True).fit(X)
    xs, ys, f = est.grid((30, 40), extent=(0.0, -8.0, 20.0, 2.0))
    np.testing.assert_allclose(xs, np.linspace(0, 20, 41)[:-1] + 0.25)
    np.testing.assert_allclose(ys, np.linspace(-8, 2, 31)[:-1] + 1 / 6)
    exact = np.exp(est.score_samples(centres([xs, ys]))).reshape(f.shape)
    np.testing.assert_allclose(f, exact, rtol=1e-10)
    outside = ~((xs[None, :] >= est.box_[0]) & (xs[None, :] <= est.box_[2])
                & (ys[:, None] >= est.box_[1]) & (ys[:, None] <= est.box_[3]))  # fmt: skip
    assert outside.any() and (f[outside] > 0).all()
    # the default region is the fitted box, the same as given explicitly
    a, b = est.grid(16), est.grid(16, extent=est.box_)
    for u, v in zip(a, b, strict=True):
        np.testing.assert_allclose(u, v, rtol=1e-12)


def test_sphere_grids_over_a_region_wrap_the_longitudes():
    rng = np.random.default_rng(5)
    lon = rng.normal(175.0, 8.0, 1500)
    lat = np.clip(rng.normal(10.0, 6.0, 1500), -89.0, 89.0)
    pts = np.column_stack([(lon + 180.0) % 360.0 - 180.0, lat])
    est = KnnDensityEstimator(sphere=True, k=30, bandwidth=1.0, sensitivity=0.5).fit(pts)
    extent = (160.0, -5.0, 200.0, 25.0)  # across the antimeridian
    lon_c, lat_c, f = est.grid((15, 20), extent=extent)
    assert f.shape == (15, 20) and lon_c[-1] > 180.0
    exact = np.exp(est.score_samples(centres([lon_c, lat_c]))).reshape(f.shape)
    np.testing.assert_allclose(f, exact, rtol=1e-10)
    mesh = knnrefine.refine(pts, 20, sphere=True)
    d = KnnDistance(mesh, pts)
    *axes, got = d.grid((6, 9), extent=extent)
    np.testing.assert_array_equal(got, d(centres(axes)).reshape(6, 9))


@pytest.mark.parametrize(
    "extent, match",
    [
        ((0, 0, 1), "four finite numbers"),
        ((0, 0, 1, np.nan), "four finite numbers"),
        ((0, 1, 1, 0), "low corner below"),
        ("abcd", "four numbers"),
    ],
)
def test_bad_regions_are_refused(extent, match):
    pts = two_blobs(2, 1500, 6)
    est = KnnDensityEstimator(k=30, box=(0, 0, 1, 1)).fit(pts)
    with pytest.raises(InputError, match=match):
        est.grid(8, extent=extent)
    with pytest.raises(InputError, match=match):
        est.density_.knn.grid(8, extent=extent)


def test_sphere_regions_keep_latitudes_within_the_poles():
    rng = np.random.default_rng(7)
    pts = np.column_stack([rng.uniform(-180, 180, 1500), rng.uniform(-60, 60, 1500)])
    est = KnnDensityEstimator(sphere=True, k=30).fit(pts)
    with pytest.raises(InputError, match="latitudes"):
        est.grid(8, extent=(0, -95, 10, 10))
