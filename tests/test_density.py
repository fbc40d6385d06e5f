"""d_{P,k} everywhere and the kNN density: against exact values and brute-force integrals."""

import numpy as np
import oracle
import pytest

import knnrefine
from knnrefine.density import KnnDensity, KnnDistance


@pytest.fixture(scope="module", params=[True, False, (True, False)])
def case(request):
    rng = np.random.default_rng(0)
    pts = (
        np.concatenate(
            [
                rng.normal([0.3, 0.3], 0.08, (1200, 2)),
                rng.normal([0.7, 0.6], 0.01, (600, 2)),
                rng.random((600, 2)),
            ]
        )
        % 1
    )
    mesh = knnrefine.refine(pts, 20, periodic=request.param, box=(0, 0, 1, 1))
    return pts, mesh


def test_exact_at_the_nodes_and_close_everywhere(case):
    pts, mesh = case
    d = KnnDistance(mesh, pts)
    per = np.array(mesh.period)
    np.testing.assert_allclose(d.values, oracle.kth(d.nodes, pts, mesh.k, per), rtol=1e-12)
    q = np.random.default_rng(1).random((1500, 2))
    ref = oracle.kth(q, pts, mesh.k, per)
    rel = np.abs(d(q) - ref) / ref
    assert np.median(rel) < 0.03 and rel.max() < 0.3
    err = d.error()
    assert err["median"] < 0.03 and err["probes"] > 2000
    # periodic axes wrap; the estimate is continuous across the seam
    if mesh.periodic[0]:
        np.testing.assert_allclose(d(q), d(q + [1.0, 0.0]), rtol=1e-9)
        edge = np.column_stack([np.full(50, 1 - 1e-9), np.linspace(0.01, 0.99, 50)])
        np.testing.assert_allclose(d(edge), d(edge - [1 - 2e-9, 0]), rtol=1e-6)
    else:
        assert np.isnan(d([[1.5, 0.5]])).all()


def test_grid_covers_the_box(case):
    pts, mesh = case
    xs, ys, g = KnnDistance(mesh, pts).grid((64, 80))
    assert g.shape == (64, 80) and np.isfinite(g).all() and (g > 0).all()
    assert xs[0] > 0 and xs[-1] < 1 and len(ys) == 64


def test_density_integrates_to_one_and_masses_add_up(case):
    pts, mesh = case
    f = KnnDensity(mesh, pts)
    # the normalising integral against an independent one: the exact k / (n pi d^2) (scipy's
    # kd-tree, not the mesh) averaged on a fine grid of the box (mass() == 1 alone would hold
    # by construction)
    g = (np.arange(400) + 0.5) / 400
    grid = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    exact = mesh.k / (len(pts) * np.pi * f.distance.exact(grid) ** 2)
    assert f.raw_mass == pytest.approx(exact.mean(), rel=0.02)
    assert f.mass() == pytest.approx(1.0, rel=1e-9)
    parts = [f.mass((0, 0, 0.4, 1)), f.mass((0.4, 0, 1, 0.25)), f.mass((0.4, 0.25, 1, 1))]
    assert sum(parts) == pytest.approx(1.0, rel=1e-6)  # quadrature of 1/d^2 on clipped pieces
    # brute force: the mass of the dense cluster's square on a fine grid of the estimate
    region = (0.6, 0.5, 0.8, 0.7)
    g = np.linspace(0, 1, 801)[:-1] + 1 / 1600
    gx, gy = np.meshgrid(0.6 + 0.2 * g, 0.5 + 0.2 * g)
    brute = f(np.column_stack([gx.ravel(), gy.ravel()])).mean() * 0.04
    assert f.mass(region) == pytest.approx(brute, rel=0.02)
    # the unnormalised estimate is k / (n pi d^2) and integrates to about 1 anyway
    raw = KnnDensity(mesh, pts, normalized=False)
    assert 0.8 < raw.mass() < 1.3
    q = np.random.default_rng(2).random((10, 2))
    np.testing.assert_allclose(raw(q), mesh.k / (len(pts) * np.pi * raw.distance(q) ** 2))


def test_errors():
    pts = np.random.default_rng(3).random((50, 2))
    mesh = knnrefine.refine(pts, 10)
    with pytest.raises(knnrefine.InputError, match="made from 50 points but 5 were given"):
        KnnDistance(mesh, pts[:5])
    d = KnnDistance(mesh, pts)
    for bad in ((0.5, 0.5, 0.5, 0.6), (0, 0, float("nan"), 1), (1, 2, 3)):
        with pytest.raises(knnrefine.InputError, match="region"):
            d.integrate(lambda v: v, region=bad)


# -- issue 9: query shapes, one rule outside the box, regions clipped to the box --------------


def test_queries_of_any_shape_come_back_in_that_shape():
    """(2, N) in gaussian_kde's layout was silently read as N / 2 points and a (3, 4, 2) grid
    came back flat."""
    pts = np.random.default_rng(4).random((500, 2))
    mesh = knnrefine.refine(pts, 10)
    f, d = KnnDensity(mesh, pts), KnnDistance(mesh, pts)
    q = np.random.default_rng(5).random((3, 4, 2)) * 0.8 + 0.1
    for fn in (f, d, d.exact, mesh.d_m2):
        out = fn(q)
        assert out.shape == (3, 4)
        np.testing.assert_array_equal(out.ravel(), fn(q.reshape(-1, 2)))
        assert np.shape(fn([0.5, 0.5])) == ()
        with pytest.raises(knnrefine.InputError, match=r"pass x\.T"):
            fn(q.reshape(-1, 2).T)
        with pytest.raises(knnrefine.InputError, match=r"shape \(\.\.\., 2\)"):
            fn(np.zeros((4, 3)))


def test_outside_the_box_is_nan_on_every_side():
    """It was NaN past the right edge of a non-periodic box but finite past the other three."""
    pts = np.random.default_rng(6).random((2000, 2))
    mesh = knnrefine.refine(pts, 20)
    f = KnnDensity(mesh, pts)
    (x0, y0), (x1, y1) = f.distance.lo, f.distance.hi
    eps = 1e-3
    outside = [[x0 - eps, 0.5], [x1 + eps, 0.5], [0.5, y0 - eps], [0.5, y1 + eps]]
    assert np.isnan(f(outside)).all() and np.isnan(f.distance.exact(outside)).all()
    sides = [[x0, 0.5], [x1, 0.5], [0.5, y0], [0.5, y1]]
    assert np.isfinite(f(sides)).all()
    periodic = knnrefine.refine(pts, 20, periodic=(True, False), box=(0, 0, 1, 1))
    g = KnnDensity(periodic, pts)
    assert np.isfinite(g([[-0.25, 0.5], [1.25, 0.5]])).all()  # x wraps
    assert np.isnan(g([[0.5, -0.01], [0.5, 1.01]])).all()  # y does not


def test_mass_of_a_region_reaching_past_the_box():
    """KnnDensity.mass((0, 0, 0.5, 0.5)) on unit-square data failed: the default box starts
    at the data's minimum. The part in the box counts; periodic regions wrap."""
    pts = np.random.default_rng(7).random((3000, 2))
    f = KnnDensity(knnrefine.refine(pts, 20), pts)
    (x0, y0), _ = f.distance.lo, f.distance.hi
    assert x0 > 0 and y0 > 0
    assert f.mass((0, 0, 0.5, 0.5)) == pytest.approx(f.mass((x0, y0, 0.5, 0.5)), rel=1e-12)
    assert f.mass((-5, -5, 5, 5)) == pytest.approx(1.0, rel=1e-9)
    assert f.mass((2, 2, 3, 3)) == 0.0
    torus = KnnDensity(knnrefine.refine(pts, 20, periodic=True, box=(0, 0, 1, 1)), pts)
    across = torus.mass((-0.1, 0.2, 0.1, 0.4))
    parts = torus.mass((0.9, 0.2, 1.0, 0.4)) + torus.mass((0.0, 0.2, 0.1, 0.4))
    assert across == pytest.approx(parts, rel=1e-12)
    assert torus.mass((-3, 0, 7, 1)) == pytest.approx(1.0, rel=1e-9)  # a whole period or more


# -- issue 11: the grid job without a second tree or point location ---------------------------


def test_grid_is_the_interpolant_at_the_grid_centres(case):
    # rasterising the pieces gives what locating each centre gives, for odd shapes too
    pts, mesh = case
    d = KnnDistance(mesh, pts)
    for shape in ((97, 131), (1, 1), (3, 500)):
        xs, ys, g = d.grid(shape)
        gx, gy = np.meshgrid(xs, ys)
        located = d(np.stack([gx, gy], -1))
        np.testing.assert_allclose(g, located, rtol=1e-12)
    with pytest.raises(knnrefine.InputError, match="shape"):
        d.grid((0, 5))
    with pytest.raises(knnrefine.InputError, match="shape"):
        d.grid((2.5, 5))


def test_node_values_reuse_the_engine_index_and_never_trust_other_points():
    rng = np.random.default_rng(8)
    pts = np.concatenate([rng.random((2000, 2)), rng.normal(0.5, 0.01, (1000, 2))])
    mesh = knnrefine.refine(pts, 15)
    d = KnnDistance(mesh, pts)
    assert d.index is mesh.index  # no second tree
    np.testing.assert_allclose(d.values, oracle.kth(d.nodes, pts, 15, (0, 0)), rtol=1e-12)
    # other points of the same number: a new index over them, their own distances
    other = pts.copy()
    other[0] += 0.25
    d2 = KnnDistance(mesh, other)
    assert d2.index is not mesh.index
    np.testing.assert_allclose(d2.values, oracle.kth(d2.nodes, other, 15, (0, 0)), rtol=1e-12)
    # what the kept index costs (docs: about 20 bytes per input point; unweighted: the
    # permuted points, 16 bytes, and the nodes)
    big = np.random.default_rng(11).random((100_000, 2))
    kept = knnrefine.refine(big, 100).index
    assert sum(a.nbytes for a in kept.index) / len(big) < 24
    # a mesh without its index (as read from a file) builds one
    import dataclasses

    bare = dataclasses.replace(mesh, index=None)
    np.testing.assert_array_equal(KnnDistance(bare, pts).values, d.values)


def test_clip_triangles_partitions_the_rectangle_and_carries_values():
    # the pieces of a triangulated square clipped to a rectangle tile the rectangle exactly;
    # values at every clipped corner are the plane through the triangle's corners
    from knnrefine._engine.raster import clip_triangles, fans
    from knnrefine.mesh import triangle_areas

    rng = np.random.default_rng(9)
    g = np.linspace(0, 1, 9)
    nodes = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + rng.uniform(-0.02, 0.02, (81, 2))
    from scipy.spatial import Delaunay

    tri = Delaunay(nodes).simplices
    corners = nodes[tri]
    plane = rng.normal(size=3)

    def f(x):
        return plane[0] + plane[1] * x[..., 0] + plane[2] * x[..., 1]

    for rect in ((0.2, 0.3, 0.7, 0.55), (0.1, 0.1, 0.9, 0.9), (0.5, 0.5, 0.5001, 0.6)):
        poly, vals, count = clip_triangles(corners, f(corners), *rect)
        pieces, dv = fans(poly, vals, count)
        area = np.abs(triangle_areas(pieces)).sum()
        assert area == pytest.approx((rect[2] - rect[0]) * (rect[3] - rect[1]), rel=1e-9)
        np.testing.assert_allclose(dv, f(pieces), rtol=1e-9, atol=1e-12)
        assert (pieces[..., 0] >= rect[0]).all() and (pieces[..., 0] <= rect[2]).all()
        assert (pieces[..., 1] >= rect[1]).all() and (pieces[..., 1] <= rect[3]).all()
    # nothing left outside, and a triangle inside stays itself
    assert clip_triangles(corners, f(corners), 2.0, 2.0, 3.0, 3.0)[2].sum() == 0
    one = np.array([[[0.1, 0.1], [0.3, 0.1], [0.1, 0.3]]])
    poly, _, count = clip_triangles(one, np.zeros((1, 3)), 0.0, 0.0, 1.0, 1.0)
    assert count[0] == 3 and np.array_equal(poly[0, :3], one[0])


def test_edges_are_the_distinct_sorted_pairs():
    from knnrefine.mesh import edges

    rng = np.random.default_rng(10)
    t = rng.integers(0, 300, (1000, 3)).astype(np.int32)
    pairs, edge_of = edges(t)
    sides = np.sort(np.concatenate([t[:, [1, 2]], t[:, [2, 0]], t[:, [0, 1]]]), axis=1)
    ref, inverse = np.unique(sides, axis=0, return_inverse=True)
    assert np.array_equal(pairs, ref) and pairs.dtype == t.dtype
    assert np.array_equal(edge_of, inverse.reshape(3, -1).T)


def test_point_location_by_walking_equals_the_centroid_candidates(case):
    """The pieces' walk from a raster of piece indices (the fast path) finds the piece the
    kd-tree's candidates find, at random points, at the nodes, on the box's sides and
    corners and across a periodic seam, and the interpolants agree to rounding."""
    pts, mesh = case
    d = KnnDistance(mesh, pts)
    pieces = d.pieces
    rng = np.random.default_rng(3)
    q = np.concatenate(
        [
            rng.random((20000, 2)),
            d.nodes[(d.nodes >= 0).all(axis=1) & (d.nodes <= 1).all(axis=1)],
            np.column_stack([rng.random(200), np.zeros(200)]),
            np.column_stack([np.ones(200), rng.random(200)]),
            [[0.0, 0.0], [1.0, 1.0], [0.0, 1.0], [1.0, 0.0]],
        ]
    )
    tri, bary = pieces._locate(q)
    ref, ref_bary = pieces._nearest(q)
    assert (tri >= 0).all() and (ref >= 0).all()
    corners = pieces.values[pieces._pieces()]
    v = np.einsum("qc,qc->q", bary, corners[tri])
    v_ref = np.einsum("qc,qc->q", ref_bary, corners[ref])
    np.testing.assert_allclose(v, v_ref, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(bary.sum(axis=1), 1.0)
    assert (bary >= -1e-9).all()
    # the walk that interpolates as it goes (one value per node, issue 53) gives the same
    np.testing.assert_allclose(pieces.interpolate(q), v_ref, rtol=1e-12, atol=1e-15)


def test_highest_density_levels_hold_their_mass():
    """hdr_levels (issue 30's pictures): on a grid of a known density the region at or above
    each level holds its share of the grid's mass, to one cell's worth; and for a Gaussian
    the levels are the analytic ones, exp(-r_p^2 / 2) / (2 pi) with r_p^2 = -2 ln(1 - p)."""
    from knnrefine.plot import hdr_levels

    xs = np.linspace(-6, 6, 801)
    gx, gy = np.meshgrid(xs, xs)
    f = np.exp(-(gx**2 + gy**2) / 2) / (2 * np.pi)
    masses = np.array([0.5, 0.8, 0.95])
    levels = hdr_levels(f, masses)
    for p, t in zip(masses, levels, strict=True):
        held = f[f >= t].sum() / f.sum()
        assert p <= held <= p + 8 * t / f.sum() + 1e-12  # (ties: eight cells by symmetry)
    np.testing.assert_allclose(levels, (1 - masses) / (2 * np.pi), rtol=2e-3)
    with pytest.raises(knnrefine.InputError, match="0 or undefined"):
        hdr_levels(np.zeros((3, 3)))
    with pytest.raises(knnrefine.InputError, match="masses"):
        hdr_levels(f, [0.5, 1.0])


def test_plot_density_draws_the_regions_with_labels_and_title_inside(tmp_path):
    """plot_density of a fitted estimator: filled contours at the highest-density levels of
    its grid (50/80/95%), the columns' names on the axes, a colour bar naming the shares, a
    title inside the picture; style="image" a log colour scale from the 99% region's level
    to the peak; unknown styles refused."""
    import matplotlib

    matplotlib.use("Agg")
    import pandas as pd
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from knnrefine.plot import hdr_levels, plot_density

    rng = np.random.default_rng(0)
    X = pd.DataFrame(
        np.concatenate([rng.normal([0, 0], 1, (3000, 2)), rng.normal([4, 1], 0.3, (1000, 2))]),
        columns=["flipper", "mass"],
    )
    est = knnrefine.KnnDensityEstimator().fit(X)
    fig = Figure(figsize=(6, 5), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    plot_density(est, ax, shape=(200, 200))
    xs, ys, f = est.grid((200, 200))
    want = hdr_levels(f, [0.95, 0.8, 0.5])
    drawn = [c for c in ax.collections if hasattr(c, "levels")]
    np.testing.assert_allclose(drawn[0].levels[:3], want, rtol=1e-12)
    assert ax.get_xlabel() == "flipper" and ax.get_ylabel() == "mass"
    bar = fig.axes[-1] if len(fig.axes) > 1 else ax.child_axes[0]
    assert [t.get_text() for t in bar.get_yticklabels()] == ["95%", "80%", "50%"]
    assert "adaptive kernel density" in ax.get_title() and "n = 4,000" in ax.get_title()
    path = tmp_path / "d.png"
    fig.savefig(path)
    renderer = fig.canvas.get_renderer()
    box = ax.title.get_window_extent(renderer)
    assert box.x0 >= 0 and box.y1 <= fig.bbox.y1  # the title is inside the figure
    image = Figure().add_subplot()
    plot_density(est, image, shape=(100, 100), style="image")
    norm = image.images[0].norm
    _, _, g = est.grid((100, 100))
    assert norm.vmax == pytest.approx(g.max()) and norm.vmin == pytest.approx(
        min(hdr_levels(g, [0.99])[0], 0.1 * g.max())
    )
    with pytest.raises(knnrefine.InputError, match="style"):
        plot_density(est, image, style="contours")


def test_box_query_rule_read_an_axis_at_a_time_is_the_rule():
    """Issue 53: the box domains' query rule (``_domains.box.answerable``: finite, and in
    the box along its non-periodic axes, sides included) is read an axis at a time (46 ->
    3 ms at 10^6 points: numpy's row reductions over 2 columns were most of it); the same
    answers as the rule written whole, with NaN, infinities and points on and beyond the
    sides, in the plane and in space, periodic along some axes or none."""
    from types import SimpleNamespace

    from knnrefine._domains.box import answerable

    rng = np.random.default_rng(53)
    for dim in (2, 3):
        lo, hi = -rng.random(dim), 1.0 + rng.random(dim)
        x = rng.uniform(-1.5, 2.5, (4000, dim))
        x[rng.random(x.shape) < 0.05] = np.nan
        x[rng.random(x.shape) < 0.05] = np.inf
        x[rng.random(x.shape) < 0.05] = -np.inf
        sides = rng.random(x.shape) < 0.05
        x[sides] = np.where(rng.random(int(sides.sum())) < 0.5, np.broadcast_to(lo, x.shape)[sides],
                            np.broadcast_to(hi, x.shape)[sides])  # fmt: skip
        for periodic in [(False,) * dim, (True,) + (False,) * (dim - 1), (True,) * dim]:
            mesh = SimpleNamespace(box=(*lo, *hi), periodic=periodic)
            bounded = ~np.array(periodic)
            with np.errstate(invalid="ignore"):
                want = np.isfinite(x).all(axis=1) & (((x >= lo) & (x <= hi)) | ~bounded).all(1)
            got = answerable(mesh)(x)
            np.testing.assert_array_equal(got, want)
            assert want.any() and not want.all()
