"""What users do with a mesh on the sphere: d_Pk and the kNN density against brute-force
great-circle oracles and known densities (von Mises-Fisher, a band, a cap), files (npz,
vtu, csv, GeoJSON that tiles the sphere), the command line and the maps."""

import json
import os
import warnings

import numpy as np
import pytest
from test_sphere import haversine, uniform

import knnrefine
from knnrefine import io
from knnrefine._metric import lonlat_of
from knnrefine.cli.main import main
from knnrefine.datasets import earthquakes
from knnrefine.density import KnnDensity, KnnDistance

RNG = np.random.default_rng(311)


def vmf(n, mu_lonlat, kappa, rng):
    """n draws of the von Mises-Fisher distribution about mu (Wood's method on S^2)."""
    mu = knnrefine._metric.unit_vectors(np.array([mu_lonlat], float))[0]
    u = rng.random(n)
    w = 1.0 + np.log(u + (1.0 - u) * np.exp(-2.0 * kappa)) / kappa
    phi = rng.uniform(0, 2 * np.pi, n)
    a = np.cross(mu, [0.0, 0.0, 1.0] if abs(mu[2]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(mu, a)
    s = np.sqrt(np.maximum(1 - w * w, 0))[:, None]
    x = w[:, None] * mu + s * (np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * b)
    return lonlat_of(x)


def vmf_pdf(lonlat, mu_lonlat, kappa):
    """Per steradian."""
    x = knnrefine._metric.unit_vectors(np.asarray(lonlat, float))
    mu = knnrefine._metric.unit_vectors(np.array([mu_lonlat], float))[0]
    return kappa / (2 * np.pi * (1 - np.exp(-2 * kappa))) * np.exp(kappa * (x @ mu - 1))


class Mixture:
    """Two von Mises-Fisher components, one across the antimeridian, one near a pole."""

    parts = (((175.0, 10.0), 40.0, 0.6), ((30.0, 75.0), 150.0, 0.4))

    def sample(self, n, rng):
        counts = rng.multinomial(n, [w for *_, w in self.parts])
        return np.concatenate(
            [vmf(c, mu, k, rng) for (mu, k, _), c in zip(self.parts, counts, strict=True)]
        )

    def pdf(self, x):
        return sum(w * vmf_pdf(x, mu, k) for mu, k, w in self.parts)


def band(n, rng, half_width=20.0):
    """Uniform on the band |lat| <= half_width: density 1 / (4 pi sin(half_width))."""
    z = rng.uniform(-np.sin(np.radians(half_width)), np.sin(np.radians(half_width)), n)
    return np.column_stack([rng.uniform(-180, 180, n), np.degrees(np.arcsin(z))])


def cap(n, rng, radius=30.0):
    """Uniform on the polar cap of angular radius ``radius`` about the north pole."""
    z = rng.uniform(np.cos(np.radians(radius)), 1.0, n)
    return np.column_stack([rng.uniform(-180, 180, n), np.degrees(np.arcsin(z))])


def test_knn_distance_on_the_sphere_against_haversine():
    pts = Mixture().sample(6000, RNG)
    mesh = knnrefine.refine(pts, 40, sphere=True)
    dist = KnnDistance(mesh, pts)
    probes = np.concatenate([uniform(3000, RNG), pts[:1000]])
    exact = np.sort(haversine(probes, pts), axis=1)[:, 39]
    np.testing.assert_allclose(dist.exact(probes), exact, rtol=1e-9)
    rel = np.abs(dist(probes) - exact) / exact
    assert np.median(rel) < 0.03 and np.percentile(rel, 99) < 0.3
    # nodes are exact; the sphere's area from the quadrature
    assert dist.integrate(np.ones_like) == pytest.approx(4 * np.pi, rel=1e-5)  # the rule
    # a query at the antimeridian from either side, and at the poles
    edge = dist(np.array([[180.0, 10.0], [-180.0, 10.0], [0.0, 90.0], [77.0, 90.0]]))
    assert edge[0] == pytest.approx(edge[1], rel=1e-9) and edge[2] == pytest.approx(edge[3])


@pytest.mark.parametrize("truth", ["mixture", "band", "cap"])
def test_knn_density_on_the_sphere_against_known_densities(truth):
    n = 20000
    if truth == "mixture":
        pts, pdf = Mixture().sample(n, RNG), Mixture().pdf
    elif truth == "band":
        pts = band(n, RNG)

        def pdf(x):
            inside = np.abs(np.asarray(x)[:, 1]) <= 20.0
            return inside / (4 * np.pi * np.sin(np.radians(20.0)))
    else:
        pts = cap(n, RNG)

        def pdf(x):
            inside = np.asarray(x)[:, 1] >= 60.0
            return inside / (2 * np.pi * (1 - np.cos(np.radians(30.0))))

    mesh = knnrefine.refine(pts, None, sphere=True)
    f = KnnDensity(mesh, pts)
    assert f.mass() == pytest.approx(1.0, rel=1e-6)
    # L1 error at draws from the truth: inside the supports, away from their edges
    draws = pts[:4000] if truth != "mixture" else Mixture().sample(4000, np.random.default_rng(1))
    l1 = np.mean(np.abs(f(draws) / pdf(draws) - 1))
    assert l1 < {"mixture": 0.2, "band": 0.15, "cap": 0.15}[truth], l1
    # draws from the estimate: as many in a region as its mass there (the kNN estimate's
    # 1 / d^2 tails hold about a tenth of the mass outside a sharp support)
    s = f.sample(40000, np.random.default_rng(2))
    assert s.shape == (40000, 2) and np.all(np.abs(s[:, 1]) <= 90)
    region = {"mixture": (150, -20, 200, 40), "band": (-180, -21, 180, 21),
              "cap": (-180, 59, 180, 90)}[truth]  # fmt: skip
    lon = (s[:, 0] - region[0]) % 360 <= region[2] - region[0]
    inside = lon & (s[:, 1] >= region[1]) & (s[:, 1] <= region[3])
    assert np.mean(inside) == pytest.approx(f.mass(region), abs=0.01)
    assert f.mass(region) > 0.5


def test_knn_density_per_unit_area_with_radius():
    pts = uniform(20000, RNG)
    a = knnrefine.refine(pts, 100, sphere=True)
    b = knnrefine.refine(pts, 100, sphere=True, radius=6371.0088)
    fa, fb = KnnDensity(a, pts), KnnDensity(b, pts)
    q = uniform(500, RNG)
    np.testing.assert_allclose(fb(q) * 6371.0088**2, fa(q), rtol=1e-9)
    assert np.median(fa(q)) == pytest.approx(1 / (4 * np.pi), rel=0.05)
    assert fb.mass((-180, 0, 180, 90)) == pytest.approx(0.5, abs=0.02)
    assert fb.mass((170, -90, 190, 90)) == pytest.approx(20 / 360, abs=0.01)  # across 180


def cylindrical_area(poly):
    """The area on the unit sphere of a lon/lat polygon in Lambert's equal-area cylinder."""
    x, y = np.radians(poly[:, 0]), np.sin(np.radians(poly[:, 1]))
    return 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)


def check_geojson_tiles_the_sphere(path, mesh):
    g = json.load(open(path))
    assert g["properties"]["domain"] == "sphere"
    total = 0.0
    for feature in g["features"]:
        ring = np.array(feature["geometry"]["coordinates"][0])
        assert (ring[0] == ring[-1]).all()
        assert (np.abs(ring[:, 0]) <= 180).all() and (np.abs(ring[:, 1]) <= 90).all()
        area = cylindrical_area(ring[:-1])
        assert area > 0  # counter-clockwise, as RFC 7946 asks of exterior rings
        total += area
    # the pieces cover the sphere once: no overlap, no gap
    assert total == pytest.approx(4 * np.pi, rel=1e-9)
    assert len(g["features"]) >= len(mesh.triangles)
    try:  # what a GIS reads: every geometry valid for shapely (GEOS), when it is installed
        from shapely.geometry import shape
    except ImportError:
        return
    invalid = [f for f in g["features"] if not shape(f["geometry"]).is_valid]
    assert not invalid, invalid[:3]


def test_geojson_on_the_sphere_tiles_it(tmp_path):
    """Also a regression: a triangle with a corner exactly on the antimeridian (longitude
    180) was cut into its piece and a degenerate one of three equal corners, zero area."""
    pts = np.concatenate([uniform(3000, RNG), np.array([[0.0, 90.0], [120.0, -90.0]])])
    mesh = knnrefine.refine(pts, 10, sphere=True)
    io.write_mesh(mesh, tmp_path / "m.geojson")
    check_geojson_tiles_the_sphere(tmp_path / "m.geojson", mesh)


def test_geojson_triangle_with_a_corner_at_a_pole(tmp_path):
    """Regression: a triangle with a vertex exactly at a pole was taken as holding the pole
    and split in three overlapping pieces (the pieces covered 4% more than the sphere)."""
    quakes = earthquakes()
    mesh = knnrefine.refine(quakes, 30, sphere=True)
    assert (np.abs(mesh.vertices[:, 1]) == 90).any()  # the tetrahedron's pole vertex
    io.write_mesh(mesh, tmp_path / "q.geojson")
    check_geojson_tiles_the_sphere(tmp_path / "q.geojson", mesh)


def test_sphere_mesh_files_round_trip(tmp_path):
    import meshio
    import pandas as pd

    pts = uniform(3000, RNG)
    mesh = knnrefine.refine(pts, 10, sphere=True, radius=2.0)
    io.write_mesh(mesh, tmp_path / "m.npz")
    back = io.read_mesh(tmp_path / "m.npz")
    assert back.on_sphere and back.radius == 2.0
    np.testing.assert_array_equal(back.xyz, mesh.xyz)
    np.testing.assert_array_equal(back.triangles, mesh.triangles)
    assert knnrefine.certify(back, pts, samples=5000, n_random=2000).passed
    io.write_mesh(mesh, tmp_path / "m.vtu")
    vtu = meshio.read(tmp_path / "m.vtu")
    np.testing.assert_allclose(np.linalg.norm(vtu.points, axis=1), 1.0, rtol=1e-12)
    io.write_mesh(mesh, tmp_path / "m.csv")
    table = pd.read_csv(tmp_path / "m.csv")
    assert list(table.columns) == ["vertex", "lon", "lat", "kind", "order"]
    assert len(table) == len(mesh.vertices)


def run(*argv):
    return main([str(a) for a in argv])


def write_lonlat(path, pts, names=("name", "Longitude", "LAT")):
    with open(path, "w") as f:
        f.write(",".join(names) + "\n")
        for i, (x, y) in enumerate(pts.tolist()):
            f.write(f"p{i},{x!r},{y!r}\n")


@pytest.mark.slow
def test_cli_on_the_sphere(tmp_path, capsys):
    pts = Mixture().sample(5000, RNG)
    csv = tmp_path / "pts.csv"
    write_lonlat(csv, pts)  # columns found by name, in any case
    out = tmp_path / "m.npz"
    assert (
        run(
            "refine",
            csv,
            "--sphere",
            "-k",
            20,
            "--radius",
            6371.0088,
            "-o",
            out,
            "-o",
            tmp_path / "m.geojson",
            "--plot",
            tmp_path / "m.png",
            "--certify",
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "on the sphere" in text and "PASSED" in text
    mesh = io.read_mesh(out)
    direct = knnrefine.refine(pts, 20, sphere=True, radius=6371.0088)
    np.testing.assert_array_equal(mesh.xyz, direct.xyz)
    assert run("certify", out, csv) == 0
    assert (
        run("density", csv, "--sphere", "--grid", "240", "120", "-o", tmp_path / "d.npz",
            "--plot", tmp_path / "d.png") == 0
    )  # fmt: skip
    grid = np.load(tmp_path / "d.npz")
    assert grid["density"].shape == (120, 240)
    cell = np.outer(np.cos(np.radians(grid["ys"])), np.ones(240)) * (np.pi / 120) ** 2
    assert (grid["density"] * cell).sum() == pytest.approx(1.0, rel=0.02)
    assert run("cluster", csv, "--sphere", "-k", 30, "-o", tmp_path / "labels.csv", "--plot",
               tmp_path / "c.png") == 0  # fmt: skip
    for picture in ("m.png", "d.png", "c.png"):
        assert os.path.getsize(tmp_path / picture) > 50_000


@pytest.mark.parametrize(
    "argv, message",
    [
        (["refine", "{csv}", "--sphere", "--box", "0", "0", "1", "1", "-k", "3"], "no --box"),
        (["refine", "{csv}", "--radius", "2", "-k", "3"], "--radius"),
        (
            ["density", "{csv}", "--sphere", "--shape", "local", "-o", "{tmp}/d.npz"],
            "--shape local",
        ),
        (["refine", "{bad}", "--sphere", "-k", "3"], "no longitude and latitude columns"),
    ],
)
def test_cli_sphere_refusals(tmp_path, capsys, argv, message):
    csv, bad = tmp_path / "p.csv", tmp_path / "bad.csv"
    write_lonlat(csv, uniform(100, RNG))
    write_lonlat(bad, uniform(100, RNG), names=("id", "x", "y"))
    argv = [a.format(csv=csv, bad=bad, tmp=tmp_path) for a in argv]
    assert run(*argv) in (1, 2)
    assert message in capsys.readouterr().err


@pytest.mark.slow
def test_maps_of_the_sphere(tmp_path):
    from matplotlib.figure import Figure

    from knnrefine.plot import plot_density, plot_mesh, plot_orthographic, save_figure

    pts = Mixture().sample(4000, RNG)
    mesh = knnrefine.refine(pts, 20, sphere=True)
    f = KnnDensity(mesh, pts)
    for style in ("hdr", "image"):
        path = tmp_path / f"{style}.png"
        save_figure(path, (10, 5.6), lambda ax, s=style: plot_density(f, ax, shape=(90, 180),
                                                                      style=s),
                    projection="mollweide")  # fmt: skip
        assert os.path.getsize(path) > 30_000
    ax = plot_orthographic(mesh, centre=(175.0, 10.0), points=pts)
    assert len(ax.collections) >= 2
    with pytest.raises(knnrefine.errors.InputError, match="geographic axes"):
        plot_mesh(mesh, ax=Figure().add_subplot())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        plot_mesh(mesh, pts)  # a new Mollweide figure


def _on_the_seam(n, rng):
    """Degenerate points for a map: on the antimeridian (the map's cut), at both poles, and
    each point twice."""
    lat = rng.uniform(-89.0, 89.0, n // 2)
    pts = np.column_stack([np.where(rng.random(n // 2) < 0.5, -180.0, 180.0), lat])
    pts[:20] = [[0.0, 90.0]] * 10 + [[0.0, -90.0]] * 10
    return np.repeat(pts, 2, axis=0)


@pytest.mark.parametrize("projection", ["mollweide", "hammer"])
@pytest.mark.parametrize("points", ["mixture", "on the seam"])
def test_a_map_of_the_sphere_projects_its_triangles_once(projection, points):
    """regression: ``knnrefine refine quakes.csv --sphere ... --plot world.png`` (the README)
    spent 21 s drawing 8,910 triangles, matplotlib projecting them path by path twice. The
    triangles now reach the map already projected, in one call: the collection's transform
    is affine, and every corner of every piece lands where the map's own projection puts it;
    long edges are cut so that they bend with the map."""
    from matplotlib.figure import Figure
    from matplotlib.path import Path

    from knnrefine.plot import plot_mesh

    rng = np.random.default_rng(5)
    pts = Mixture().sample(3000, rng) if points == "mixture" else _on_the_seam(3000, rng)
    mesh = knnrefine.refine(pts, 20, sphere=True)
    ax = plot_mesh(mesh, ax=Figure().add_subplot(projection=projection))
    coll = ax.collections[0]
    assert coll.get_transform().is_affine
    pieces = mesh.pieces_in_box()
    paths = coll.get_paths()
    assert len(paths) == len(pieces)
    drawn_corners = 0
    for path, (_, polygon) in zip(paths, pieces, strict=True):
        drawn = coll.get_transform().transform(path.vertices)
        want = ax.transData.transform(np.radians(polygon))
        gap = np.linalg.norm(drawn[None, :, :] - want[:, None, :], axis=-1).min(axis=1)
        assert gap.max() < 1e-6, gap.max()  # in pixels
        drawn_corners += len(polygon)
        # the cut points lie on the curve matplotlib draws for the piece, within a pixel
        ring = np.radians(np.vstack([polygon, polygon[:1]]))
        theirs = ax.transData.transform_path(Path(ring)).vertices
        off = np.linalg.norm(drawn[:, None, :] - theirs[None, :, :], axis=-1).min(axis=1)
        assert off.max() < 1.0, off.max()
    assert sum(len(p.vertices) for p in paths) > drawn_corners  # long edges were cut


def test_a_density_map_of_the_sphere_projects_its_grid_once(monkeypatch):
    """The highest-density regions on a map of the sphere are contoured on the grid projected
    once (matplotlib projected every contour path by path: 2.8 s of a 4,457-vertex world
    map's density, now 1.3 s): an affine transform, and the same picture as matplotlib's own
    contours of the grid in longitude and latitude, but for the odd pixel."""
    from unittest import mock

    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from knnrefine.plot import HDR_MASSES, hdr_levels, plot_density

    pts = Mixture().sample(3000, np.random.default_rng(6))
    f = KnnDensity(knnrefine.refine(pts, 20, sphere=True), pts)
    lon, lat, values = f.grid((90, 180))
    monkeypatch.setattr(Figure, "colorbar", mock.MagicMock())  # the maps alone are compared

    def picture(draw):
        fig = Figure(figsize=(6, 3.4), dpi=80)
        FigureCanvasAgg(fig)
        ax = fig.add_subplot(projection="mollweide")
        ax.set_longitude_grid(30)
        ax.set_latitude_grid(30)
        ax.grid(True, color="0.5", linewidth=0.4, alpha=0.6)
        ax.tick_params(labelsize="small")
        draw(ax)
        ax.set_title("")
        fig.canvas.draw()
        return ax, np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(int)

    def theirs(ax):
        masses = np.sort(HDR_MASSES)[::-1]
        levels = hdr_levels(values, masses, areas=np.cos(np.radians(lat))[:, None])
        bounds = np.append(levels, values.max() * (1 + 1e-9))
        colours = colormaps["Blues"](np.linspace(0.35, 0.95, len(levels)))
        ax.contourf(np.radians(lon), np.radians(lat), values, levels=bounds, colors=colours)
        ax.contour(np.radians(lon), np.radians(lat), values, levels=levels,
                   colors=[colours[-1]], linewidths=0.6)  # fmt: skip

    ax, mine = picture(lambda ax: plot_density(f, ax, grid=(lon, lat, values)))
    assert ax.collections[0].get_transform().is_affine
    _, other = picture(theirs)
    differ = np.abs(mine - other).max(axis=-1) > 40
    assert differ.mean() < 0.005, differ.mean()


def test_adaptive_leave_one_out_on_the_sphere_against_direct_sums():
    """The sphere's adaptive estimate: kernels in chord distance, exactly normalised (mass 1
    by Monte Carlo), and its leave-one-out log-density against sums written out here."""
    from knnrefine.density.adaptive import SphereAdaptiveDensity

    pts = Mixture().sample(3000, RNG)
    pts = np.concatenate([pts, pts[:5]])  # copies: left out with the point
    mesh = knnrefine.refine(pts, 60, sphere=True)
    a = SphereAdaptiveDensity(mesh, pts, bandwidth=1.2, sensitivity=0.3)
    u = knnrefine._metric.unit_vectors(pts)
    d = a.pilot  # great-circle d_Pk at the points (radius 1): chords 2 sin(d / 2)
    chord = 2 * np.sin(d / 2)
    g = np.exp(np.mean(np.log(chord)))
    h = np.minimum(1.2 * g * (chord / g) ** (2 * 0.3), 2.0)
    idx = np.array([0, 1, 2, 10, 400, 2999, 3000])
    c2 = ((u[idx, None, :] - u[None, :, :]) ** 2).sum(-1)
    kern = np.clip(1 - c2 / h**2, 0, None) ** 3 / (np.pi * h**2 / 4)
    same = c2 == 0
    n = len(pts)
    rest = n - same.sum(axis=1)
    s = np.where(same, 0.0, kern).sum(axis=1) / n
    knn = a.knn.at_distance(d[idx])
    expected = np.log((1 - 1 / n) * s * n / rest + knn / n)
    np.testing.assert_allclose(a.loo(idx), expected, rtol=1e-9)
    draws = uniform(200_000, np.random.default_rng(3))
    assert 4 * np.pi * np.mean(a(draws)) == pytest.approx(1.0, abs=0.02)


def test_the_box_adaptive_estimate_refuses_a_mesh_on_the_sphere():
    from knnrefine.density import AdaptiveDensity

    pts = uniform(2000, RNG)
    mesh = knnrefine.refine(pts, 20, sphere=True)
    with pytest.raises(knnrefine.errors.InputError, match="SphereAdaptiveDensity"):
        AdaptiveDensity(mesh, pts)


def test_estimator_on_the_sphere():
    """KnnDensityEstimator(sphere=True): the adaptive estimate in great-circle geometry,
    against the truth and against the kNN estimate; unit vectors or lon/lat; per km^2 with
    a radius; refusals."""
    truth = Mixture()
    pts = truth.sample(20000, RNG)
    est = knnrefine.KnnDensityEstimator(sphere=True).fit(pts)
    probes = truth.sample(4000, np.random.default_rng(5))
    l1 = np.mean(np.abs(np.exp(est.score_samples(probes)) / truth.pdf(probes) - 1))
    knn = knnrefine.KnnDensityEstimator(sphere=True, method="knn").fit(pts)
    l1_knn = np.mean(np.abs(np.exp(knn.score_samples(probes)) / truth.pdf(probes) - 1))
    assert l1 < 0.1 and l1 < 0.7 * l1_knn, (l1, l1_knn)
    assert est.score(probes) > knn.score(probes)
    unit = knnrefine._metric.unit_vectors(pts)
    km = knnrefine.KnnDensityEstimator(sphere=True, radius=6371.0088).fit(unit)
    np.testing.assert_allclose(
        np.exp(km.score_samples(unit[:50])) * 6371.0088**2,
        np.exp(est.score_samples(pts[:50])), rtol=1e-9,
    )  # fmt: skip
    drawn = km.sample(100, 0)
    assert drawn.shape == (100, 3)
    np.testing.assert_allclose(np.linalg.norm(drawn, axis=1), 1.0)
    lon, lat, grid = est.grid((90, 180))
    assert grid.shape == (90, 180) and np.isfinite(grid).all()
    assert np.isfinite(est.score_samples([[0.0, -89.9], [-179.9, 0.0]])).all()  # no -inf
    for bad in ({"box": (0, 0, 1, 1)}, {"periodic": True}, {"whiten": True}):
        with pytest.raises(knnrefine.errors.InputError, match="sphere=True takes no"):
            knnrefine.KnnDensityEstimator(sphere=True, **bad).fit(pts)
    with pytest.raises(knnrefine.errors.InputError, match="radius"):
        knnrefine.KnnDensityEstimator(radius=2.0).fit(pts)


def test_cluster_on_the_sphere_finds_the_caps_across_the_antimeridian():
    pytest.importorskip("gudhi")
    rng = np.random.default_rng(7)
    parts = [vmf(3000, (178.0, 0.0), 300.0, rng), vmf(3000, (60.0, 70.0), 300.0, rng),
             vmf(3000, (-60.0, -30.0), 300.0, rng), uniform(1000, rng)]  # fmt: skip
    pts = np.concatenate(parts)
    mesh = knnrefine.refine(pts, 30, sphere=True)
    result = knnrefine.cluster(mesh, pts)
    assert result.n_clusters == 3
    truth = np.repeat([0, 1, 2], 3000)
    labels = result.labels[:9000]
    # each cap one label (the cap across 180 degrees is one cluster, not two), all different
    majority = [np.bincount(labels[truth == c]).argmax() for c in range(3)]
    assert len(set(majority)) == 3
    agree = np.mean([np.mean(labels[truth == c] == majority[c]) for c in range(3)])
    assert agree > 0.95


def test_persistence_on_the_sphere_sees_a_ring_and_reports_the_sphere():
    """A ring of points round a pole with outliers: H1 has one long-lived class (the empty
    polar cap it encloses); H2 holds the sphere's one essential class, born at the
    filtration's largest value."""
    pytest.importorskip("gudhi")
    from knnrefine.topology import Persistence

    rng = np.random.default_rng(8)
    ring = np.column_stack([rng.uniform(-180, 180, 3000), 60 + rng.normal(0, 1.0, 3000)])
    pts = np.concatenate([ring, uniform(300, rng)])
    mesh = knnrefine.refine(pts, 20, sphere=True)
    pers = Persistence(mesh, pts)
    h1 = pers.most_persistent(1, 2)
    assert h1[0] > 1.0 and (len(h1) < 2 or h1[1] < 0.3 * h1[0])
    h2 = pers.diagram(2)
    assert len(h2) == 1 and np.isinf(h2[0, 1])
    assert h2[0, 0] == pytest.approx(pers.values.max())
    assert pers.positions.shape[1] == 2 and np.abs(pers.positions[:, 1]).max() <= 90


@pytest.mark.parametrize("case", ["great circle", "duplicates", "antimeridian seam"])
def test_estimator_on_the_sphere_on_degenerate_inputs(case):
    """Points on one great circle (the sphere's line), repeated points, and points exactly
    on the antimeridian (the seam of longitude): the adaptive estimate fits, every score is
    finite, and its mass is 1 (Monte Carlo)."""
    rng = np.random.default_rng(12)
    if case == "great circle":
        pts = np.column_stack([rng.uniform(-180, 180, 3000), np.zeros(3000)])
    elif case == "duplicates":
        pts = np.repeat(Mixture().sample(600, rng), 5, axis=0)
    else:
        pts = np.column_stack([np.full(3000, 180.0), rng.uniform(-60, 60, 3000)])
        pts[::2, 0] = -180.0  # the same meridian written both ways
    est = knnrefine.KnnDensityEstimator(sphere=True).fit(pts)
    assert np.isfinite(est.score_samples(pts[:200])).all()
    assert np.isfinite(est.score_samples(uniform(200, rng))).all()
    draws = uniform(100_000, np.random.default_rng(4))
    assert 4 * np.pi * np.mean(np.exp(est.score_samples(draws))) == pytest.approx(1.0, abs=0.05)
