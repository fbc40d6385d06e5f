"""Every use of a mesh in space, with the plane's names: ToMATo clusters, persistence (H0-H3),
and the command line's density, cluster, persistence and plot on three columns. Oracles:
the truth of synthetic clusters, the homology of a sphere shell and of the 3-torus, the
files the commands write read back and checked against the library."""

import numpy as np
import pytest
from conftest import assert_lattice_close, sphere_shell
from scipy.spatial import cKDTree

import knnrefine
from knnrefine import InputError, KnnDensity
from knnrefine.cli.main import main

gudhi = pytest.importorskip("gudhi")
from sklearn.metrics import adjusted_rand_score  # noqa: E402

from knnrefine.cluster import cluster  # noqa: E402
from knnrefine.topology import Persistence  # noqa: E402

BOX3 = (0.0, 0.0, 0.0, 1.0, 1.0, 1.0)


def blobs3(seed, n=1500, noise=600):
    rng = np.random.default_rng(seed)
    centres = np.array([[0.25, 0.25, 0.3], [0.75, 0.3, 0.7], [0.4, 0.75, 0.6]])
    pts = np.concatenate([rng.normal(c, 0.05, (n, 3)) for c in centres] + [rng.random((noise, 3))])
    truth = np.concatenate([np.full(n, i) for i in range(3)] + [np.full(noise, -1)])
    return np.clip(pts, 0.0, 1.0 - 1e-12), truth


def test_cluster_in_space_finds_the_blobs():
    pts, truth = blobs3(0)
    mesh = knnrefine.refine(pts, 30, box=BOX3)
    cl = cluster(mesh, pts)
    assert cl.n_clusters == 3
    core = truth >= 0
    assert adjusted_rand_score(truth[core], cl.labels[core]) > 0.97
    assert cl.vertex_labels.shape == (len(mesh.vertices),)


def test_cluster_in_space_across_the_periodic_seams_is_one_cluster():
    rng = np.random.default_rng(1)
    across = rng.normal([0.0, 0.0, 0.5], 0.05, (2000, 3)) % 1.0  # split by two seams
    other = rng.normal([0.5, 0.5, 0.5], 0.05, (2000, 3))
    pts = np.concatenate([across, other, rng.random((300, 3))])
    mesh = knnrefine.refine(pts, 30, periodic=True, box=BOX3)
    cl = cluster(mesh, pts)
    assert cl.n_clusters == 2
    assert adjusted_rand_score(np.repeat([0, 1], 2000), cl.labels[:4000]) > 0.97


def test_cluster_checks_the_points_are_the_meshs():
    """cluster() took any points, and a weighted mesh's points without their weights."""
    pts, _ = blobs3(2, n=300, noise=100)
    mesh = knnrefine.refine(pts, 20, box=BOX3)
    with pytest.raises(InputError, match="made from 1,000 points but 999"):
        cluster(mesh, pts[:-1])
    with pytest.raises(InputError, match="shape \\(n, 3\\)"):
        cluster(mesh, pts[:, :2])
    plane = np.random.default_rng(3).random((800, 2))
    weighted = knnrefine.refine(plane, 20, weights=np.full(len(plane), 2.0))
    with pytest.raises(InputError, match="refined with weights"):
        cluster(weighted, plane)
    # with its weights, the weighted mesh of copies clusters as the copies do
    doubled = knnrefine.refine(np.repeat(plane, 2, axis=0), 20)
    a = cluster(weighted, plane, weights=np.full(len(plane), 2.0))
    b = cluster(doubled, np.repeat(plane, 2, axis=0))
    assert a.threshold == pytest.approx(b.threshold)


@pytest.mark.slow
def test_persistence_of_a_sphere_shell_has_one_void():
    pts = np.clip(sphere_shell(6000, 4), 0.0, 1.0 - 1e-12)
    mesh = knnrefine.refine(pts, 10, box=BOX3)
    ph = Persistence(mesh, pts)
    life = ph.most_persistent(2, 2)
    assert life[0] > 1.0 and life[1] < 0.3 * life[0]  # one void, far above the rest
    assert len(ph.betti(np.inf)) == 4 and ph.cells.shape[1] == 4


def test_persistence_on_the_3_torus_has_its_betti_numbers():
    pts = np.random.default_rng(5).random((3000, 3))
    mesh = knnrefine.refine(pts, 10, periodic=True, box=BOX3)
    ph = Persistence(mesh, pts)
    essential = [int(np.isinf(ph.diagram(d)[:, 1]).sum()) for d in range(4)]
    assert essential == [1, 3, 3, 1]  # the 3-torus: 1, 3, 3, 1
    assert ph.betti(np.inf) == (1, 3, 3, 1)  # regression: classes that never die counted 0
    d_m2 = Persistence(mesh, pts, function="d_m2", subdivide=False)
    assert [int(np.isinf(d_m2.diagram(d)[:, 1]).sum()) for d in range(4)] == [1, 3, 3, 1]


# -- the command line on three columns ---------------------------------------------------


@pytest.fixture()
def csv3(tmp_path):
    pts, _ = blobs3(6, n=800, noise=300)
    path = tmp_path / "halos.csv"
    header = "id,px,py,pz\n"
    rows = "".join(f"{i},{x!r},{y!r},{z!r}\n" for i, (x, y, z) in enumerate(pts.tolist()))
    path.write_text(header + rows)
    return path, pts


def run(*argv):
    return main([str(a) for a in argv])


def test_cli_density_cluster_persistence_plot_in_space(tmp_path, csv3, capsys):
    path, pts = csv3
    box = ["--box", 0, 0, 0, 1, 1, 1]
    assert run("refine", path, "--columns", "px,py,pz", "-k", 20, *box,
               "-o", tmp_path / "m.npz", "--plot", tmp_path / "m.png") == 0  # fmt: skip
    mesh = knnrefine.io.read_mesh(tmp_path / "m.npz")
    assert mesh.dim == 3
    # density: the kNN estimate, its grid as the library's
    assert run("density", path, "--columns", "px,py,pz", "--mesh", tmp_path / "m.npz",
               "--method", "knn", "--grid", 6, 5, 4, "-o", tmp_path / "d.npz",
               "-o", tmp_path / "d.csv", "--plot", tmp_path / "d.png") == 0  # fmt: skip
    with np.load(tmp_path / "d.npz") as z:
        assert z["density"].shape == (4, 5, 6) and len(z["zs"]) == 4
        expected = KnnDensity(mesh, pts).grid((4, 5, 6))
        np.testing.assert_allclose(z["density"], expected[3], rtol=1e-9)
        np.testing.assert_allclose(z["xs"], expected[0])
    table = knnrefine.io.read_points_named(tmp_path / "d.csv", "px,py,pz")[0]
    assert len(table) == 120 and np.allclose(table[:6, 0], expected[0])
    # cluster and persistence with the mesh in space: three columns read without --columns
    assert run("cluster", path, "--mesh", tmp_path / "m.npz", "--columns", "px,py,pz",
               "-o", tmp_path / "l.csv", "--plot", tmp_path / "l.png") == 0  # fmt: skip
    assert "3 clusters" in capsys.readouterr().out
    assert run("persistence", path, "--columns", "px,py,pz", "--mesh", tmp_path / "m.npz",
               "-o", tmp_path / "p.csv", "--plot", tmp_path / "p.png") == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "H3:" in out and "tetrahedra" in out
    assert run("plot", tmp_path / "m.npz", "-o", tmp_path / "s.png", "--points", path,
               "--columns", "px,py,pz") == 0  # fmt: skip
    for picture in "m.png", "d.png", "l.png", "p.png", "s.png":
        assert (tmp_path / picture).stat().st_size > 10_000


def test_a_mesh_in_space_is_written_in_parts(tmp_path):
    """regression: write_partitioned of a mesh in space failed deep inside with a numpy
    broadcast error (then it was refused); now it writes slabs, read back as the same mesh
    (the whole check: test_partitioned.py)."""
    pts = np.random.default_rng(8).random((800, 3))
    mesh = knnrefine.refine(pts, 10, periodic=True, box=BOX3)
    parts = knnrefine.write_partitioned(mesh, tmp_path / "parts", 2)
    np.testing.assert_array_equal(parts.to_mesh().tetrahedra, mesh.tetrahedra)
    np.testing.assert_array_equal(parts.d_m2(pts), mesh.d_m2(pts))


def test_cli_adaptive_density_in_space(tmp_path, csv3, capsys):
    """knnrefine density on three columns: the adaptive estimate by default (issue 30), its
    grid the library's at the smoothing it reports, integrating to 1 over the box, drawn as
    projections."""
    from knnrefine.density import AdaptiveDensity

    path, pts = csv3
    box = ["--box", 0, 0, 0, 1, 1, 1]
    assert run("density", path, "--columns", "px,py,pz", *box, "-k", 20, "--grid", 12,
               "-o", tmp_path / "d.npz", "--plot", tmp_path / "d.png") == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "adaptive kernel density" in out and "bandwidth c =" in out
    with np.load(tmp_path / "d.npz") as z:
        assert str(z["method"]) == "adaptive" and z["density"].shape == (12, 12, 12)
        mesh = knnrefine.refine(pts, 20, box=(0, 0, 0, 1, 1, 1))
        ad = AdaptiveDensity(mesh, pts, float(z["bandwidth"]), sensitivity=float(z["sensitivity"]))
        np.testing.assert_allclose(z["density"], ad.grid(12)[3], rtol=1e-9)
        assert z["density"].sum() / 12**3 == pytest.approx(1.0, abs=0.03)
        knn_grid = knnrefine.KnnDistance(mesh, pts).grid(12)[3]
        np.testing.assert_allclose(z["d_pk"], knn_grid, rtol=1e-9)  # the mesh's d_Pk
    assert (tmp_path / "d.png").stat().st_size > 10_000


def test_cli_in_space_refuses_what_is_built_for_the_plane(tmp_path, csv3, capsys):
    path, _ = csv3
    box = ["--box", 0, 0, 0, 1, 1, 1]
    assert run("density", path, "--columns", "px,py,pz", *box, "-k", 20,
               "--shape", "local", "-o", tmp_path / "d.npz") == 2  # fmt: skip
    assert "--shape local is built for points in the plane" in capsys.readouterr().err
    assert run("refine", path, "--columns", "px,py,pz", "-k", 20, *box,
               "-o", tmp_path / "m.npz") == 0  # fmt: skip
    assert run("plot", tmp_path / "m.npz", "-o", tmp_path / "s.png", "--cells", "voronoi") == 2
    assert "a mesh in space is drawn as slices" in capsys.readouterr().err
    assert not (tmp_path / "s.png").exists()


def test_points_of_neither_dimension_name_both():
    """refine and the estimator take (n, 2) or (n, 3): four columns were refused as not
    (n, 2) alone."""
    four = np.random.default_rng(9).random((100, 4))
    from knnrefine import KnnDensityEstimator

    with pytest.raises(InputError, match=r"\(n, 2\) in the plane or \(n, 3\) in space"):
        knnrefine.refine(four, 10)
    with pytest.raises(InputError, match=r"\(n, 2\) in the plane or \(n, 3\) in space"):
        KnnDensityEstimator(k=10).fit(four)


@pytest.mark.parametrize("case", ["coplanar", "duplicates", "on a seam"])
def test_uses_in_space_on_degenerate_points(case):
    """The uses added for space on points on a plane, repeated points and points on the
    periodic seams: d_Pk exact at the mesh's vertices, the density's mass 1 and its samples
    in the box, clusters and persistence computed, the mesh certified."""
    rng = np.random.default_rng(12)
    pts = rng.random((3000, 3))
    if case == "coplanar":
        pts[:, 2] = 0.5
    elif case == "duplicates":
        pts = np.repeat(pts[:300], 10, axis=0)
    else:
        pts[:1500, 0] = 0.0  # half on the seam x = 0 of the 3-torus
    mesh = knnrefine.refine(pts, 12, periodic=True, box=BOX3)
    assert knnrefine.certify(mesh, pts, samples=20_000).passed
    dist = knnrefine.KnnDistance(mesh, pts)
    v = mesh.vertices[:200]
    np.testing.assert_allclose(dist(v), dist.exact(v), rtol=1e-9)
    density = KnnDensity(mesh, pts)
    assert density.mass() == pytest.approx(1.0, rel=1e-9)
    draws = density.sample(2000, rng)
    assert ((draws >= 0) & (draws <= 1)).all()
    assert cluster(mesh, pts).n_clusters >= 1
    h0 = Persistence(mesh, pts).diagram(0)
    assert np.isinf(h0[:, 1]).sum() == 1  # one component never dies (the 3-torus)
    # the adaptive estimate in space (issue 30): the smoothing chosen, its leave-one-out
    # values finite, its draws in the box where it is positive, its grid the estimate at the
    # cells' centres, to the lattices' accuracy where they serve (no mass check: on a plane
    # or at repeated points the kernels are thinner than a cell and the centres miss them, as
    # in the plane)
    from knnrefine.density import AdaptiveDensity, choose_smoothing

    ad = AdaptiveDensity(mesh, pts, bandwidth=1.5)
    choose_smoothing(ad, loo_points=500)
    assert np.isfinite(ad.loo(np.arange(0, 3000, 7))).all()
    draws = ad.sample(2000, rng)
    assert ((draws >= 0) & (draws <= 1)).all() and (ad(draws) > 0).all()
    *axes, values = ad.grid(24)
    centres = np.stack(np.meshgrid(*axes[::-1], indexing="ij")[::-1], axis=-1)
    assert_lattice_close(values.ravel(), ad(centres).ravel(), worst=3e-3)  # exact or lattices
    # exact d_Pk by the counting tree's windows, whatever k: scipy's
    q = np.concatenate([rng.random((500, 3)), pts[:100]])
    want = cKDTree(pts, boxsize=1.0).query(q, k=[120])[0][:, 0]
    np.testing.assert_allclose(dist.index.windows(q, 120), want, rtol=1e-12)
