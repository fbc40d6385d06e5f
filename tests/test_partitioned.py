"""A mesh as a folder of parts (knnrefine.scale.parts): put back together it is the same
Mesh, array for array; part by part its d_{M,2} equals the whole mesh's (cKDTree over all
vertices) at random points and on the strips' borders; written atomically."""

import os

import numpy as np
import pytest
from conftest import gaussian_clusters

import knnrefine
from knnrefine.errors import InputError
from knnrefine.scale.parts import FINISHED, PartitionedMesh, write_partitioned


def assert_same_mesh(a, b):
    for name in ("vertices", "cells", "offsets", "kinds", "order", "floor_points"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype and np.array_equal(x, y), name
    for name in ("vertices", "cells", "offsets", "neighbours", "kinds"):
        x, y = getattr(a.torus, name), getattr(b.torus, name)
        assert (x is None) == (y is None), name  # the torus in space keeps no neighbours
        if x is not None:
            assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert (a.k, a.tau, a.periodic, a.box, a.min_size) == (
        b.k,
        b.tau,
        b.periodic,
        b.box,
        b.min_size,
    )


PERIODIC = [True, False, (True, False), (False, True)]


@pytest.mark.parametrize("periodic", PERIODIC, ids=str)
@pytest.mark.parametrize("parts", [1, 3, 8])
def test_parts_give_back_the_mesh_and_its_d_m2(tmp_path, periodic, parts):
    pts = gaussian_clusters(30000, 1)
    box = (0, 0, 1, 1) if periodic else None
    mesh = knnrefine.refine(pts, 15, periodic=periodic, box=box)
    pm = write_partitioned(mesh, tmp_path / "mesh", parts)
    assert len(pm) == parts and os.path.exists(tmp_path / "mesh" / FINISHED)
    assert_same_mesh(mesh, PartitionedMesh(tmp_path / "mesh").to_mesh())
    rng = np.random.default_rng(2)
    lo, hi = np.array(mesh.box[:2]), np.array(mesh.box[2:])
    on_cuts = np.zeros((200 * parts, 2))
    axis = pm.manifest["axis"]
    cuts = np.clip(np.array(pm.manifest["cuts"]) + lo[axis], lo[axis], hi[axis])  # in the box
    on_cuts[:, axis] = np.repeat(cuts, 200)
    on_cuts[:, 1 - axis] = lo[1 - axis] + rng.random(len(on_cuts)) * (hi - lo)[1 - axis]
    q = np.concatenate([lo + rng.random((50000, 2)) * (hi - lo), on_cuts, [lo, hi]])
    np.testing.assert_array_equal(pm.d_m2(q), mesh.d_m2(q))
    beyond = np.array([[lo[0] - 1.0, lo[1]], [lo[0], hi[1] + 1.0]])
    got = pm.d_m2(beyond)
    for i, a in enumerate((0, 1)):  # beyond the box: NaN along a non-periodic axis
        assert np.isnan(got[i]) == (not mesh.periodic[a])
        if mesh.periodic[a]:
            assert got[i] == mesh.d_m2(beyond[i : i + 1])[0]
    own = sum(p["vertices"] for p in pm.manifest["parts"])
    assert own == len(mesh.vertices)


@pytest.mark.parametrize(
    "periodic, parts",
    [
        (True, 4),
        pytest.param(False, 3, marks=pytest.mark.slow),
        pytest.param((True, False, True), 1, marks=pytest.mark.slow),
    ],
    ids=str,
)
def test_parts_in_space_give_back_the_mesh_and_its_d_m2(tmp_path, periodic, parts):
    """A mesh in space in slabs: put back together it is the same Mesh (no neighbour links
    in the torus, as refine's), its d_{M,2} part by part equals the whole mesh's at random
    points, on every cut plane, at the box's corners and beyond the box (NaN along
    non-periodic axes), each part exact at its own tetrahedra's centroids; its picture (three
    slices of d_M2 asked part by part) is the whole mesh's, pixel for pixel."""
    pts = gaussian_clusters(6000, 2, clusters=12, dim=3)
    mesh = knnrefine.refine(pts, 15, periodic=periodic, box=(0, 0, 0, 1, 1, 1))
    pm = write_partitioned(mesh, tmp_path / "mesh", parts)
    assert len(pm) == parts and pm.dim == 3
    back = PartitionedMesh(tmp_path / "mesh").to_mesh()
    assert_same_mesh(mesh, back)
    rng = np.random.default_rng(3)
    lo, hi = np.array(mesh.box[:3]), np.array(mesh.box[3:])
    axis = pm.manifest["axis"]
    on_cuts = lo + rng.random((300 * parts, 3)) * (hi - lo)
    cuts = np.clip(np.array(pm.manifest["cuts"]) + lo[axis], lo[axis], hi[axis])  # in the box
    on_cuts[:, axis] = np.repeat(cuts, 300)
    corners = np.array(np.meshgrid(*zip(lo, hi, strict=True))).reshape(3, -1).T
    q = np.concatenate([lo + rng.random((30000, 3)) * (hi - lo), on_cuts, corners])
    np.testing.assert_array_equal(pm.d_m2(q), mesh.d_m2(q))
    beyond = (lo + hi) / 2 + np.eye(3) * (hi - lo)
    got = pm.d_m2(beyond)
    for a in range(3):
        assert np.isnan(got[a]) == (not mesh.periodic[a])
        if mesh.periodic[a]:
            assert got[a] == mesh.d_m2(beyond[a : a + 1])[0]
    for j in range(len(pm)):
        part = pm.part(j)
        c = part.corners().mean(axis=1)
        np.testing.assert_array_equal(part.d_m2(c), mesh.d_m2(c))
    assert sum(p["vertices"] for p in pm.manifest["parts"]) == len(mesh.vertices)
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    from knnrefine.plot import plot_slices

    axes = pm.plot(points=pts, shape=64)  # three slices, d_M2 asked part by part
    whole = plot_slices(mesh.d_m2, mesh, plt.subplots(1, 3)[1], "d_M2", points=pts, shape=64)
    for a, b in zip(axes, whole, strict=True):
        np.testing.assert_array_equal(a.images[0].get_array(), b.images[0].get_array())
    plt.close("all")
    with pytest.raises(InputError, match="three Axes"):
        pm.plot(ax=plt.subplots()[1])


def test_each_part_is_exact_in_its_own_triangles(tmp_path):
    """A part's d_{M,2} at its own triangles' centroids (where the picture colours them)
    equals the whole mesh's, also where a centroid lies in the next strip."""
    pts = gaussian_clusters(20000, 3)
    mesh = knnrefine.refine(pts, 10, periodic=True, box=(0, 0, 1, 1))
    pm = write_partitioned(mesh, tmp_path / "m", 6)
    for j in range(len(pm)):
        part = pm.part(j)
        c = part.corners().mean(axis=1)
        np.testing.assert_array_equal(part.d_m2(c), mesh.d_m2(c))


def test_the_picture_draws_every_triangle_once(tmp_path):
    pytest.importorskip("matplotlib")
    from matplotlib.collections import PolyCollection

    pts = gaussian_clusters(10000, 4)
    mesh = knnrefine.refine(pts, 10, periodic=True, box=(0, 0, 1, 1))
    pm = write_partitioned(mesh, tmp_path / "m", 4)
    ax = pm.plot(show_points=False)
    drawn = sum(len(c.get_paths()) for c in ax.collections if isinstance(c, PolyCollection))
    assert drawn == len(mesh.covering()[1])
    assert len(ax.child_axes) == 1  # one colour bar (an inset) for all parts


def test_the_folder_is_written_whole_or_not_at_all(tmp_path, monkeypatch):
    from knnrefine.scale import parts as partitioned

    pts = gaussian_clusters(5000, 5)
    mesh = knnrefine.refine(pts, 10)
    target = tmp_path / "m"
    write_partitioned(mesh, target, 2)
    with pytest.raises(InputError, match="exists; use force=True"):
        write_partitioned(mesh, target, 3)

    def fail(*args):
        raise OSError("disk full")

    monkeypatch.setattr(partitioned, "_write_parts", fail)
    with pytest.raises(OSError):
        write_partitioned(mesh, target, 3, force=True)
    assert len(PartitionedMesh(target)) == 2  # the old folder is untouched
    assert os.listdir(tmp_path) == ["m"]  # no temporary folder left behind
    monkeypatch.undo()
    assert len(write_partitioned(mesh, target, 3, force=True)) == 3
    os.remove(target / FINISHED)
    with pytest.raises(InputError, match="no _SUCCESS marker"):
        PartitionedMesh(target)
    with pytest.raises(InputError, match="no such folder"):
        PartitionedMesh(tmp_path / "missing")
    for bad in (0, 2.5, True):
        with pytest.raises(InputError, match="parts must be a positive integer"):
            write_partitioned(mesh, tmp_path / "other", bad)


def _queries(pm, rng, count=20000):
    """Random points of the box, points on every cut, the box's corners and points beyond
    it on every side."""
    lo, hi = np.array(pm.box[:2]), np.array(pm.box[2:])
    axis = pm.manifest["axis"]
    cuts = np.clip(np.array(pm.manifest["cuts"]) + lo[axis], lo[axis], hi[axis])
    on_cuts = np.zeros((100 * len(cuts), 2))
    on_cuts[:, axis] = np.repeat(cuts, 100)
    on_cuts[:, 1 - axis] = lo[1 - axis] + rng.random(len(on_cuts)) * (hi - lo)[1 - axis]
    beyond = (lo + hi) / 2 + np.array([[-1, 0], [1, 0], [0, -1], [0, 1]]) * (hi - lo)
    return np.concatenate([lo + rng.random((count, 2)) * (hi - lo), on_cuts, [lo, hi], beyond])


@pytest.mark.parametrize("periodic", PERIODIC, ids=str)
@pytest.mark.parametrize("parts", [1, 4])
def test_density_part_by_part_equals_the_whole_meshs(tmp_path, periodic, parts):
    """PartitionedMesh.density answers as KnnDensity on the whole mesh (itself checked
    against exact d_Pk in test_density): at random points, on the cuts, beyond the box
    (NaN along non-periodic axes), its masses over the box and a region across the seam,
    its grid."""
    pts = gaussian_clusters(20000, 6)
    box = (0, 0, 1, 1) if periodic else None
    mesh = knnrefine.refine(pts, 15, periodic=periodic, box=box)
    pm = write_partitioned(mesh, tmp_path / "m", parts)
    got, want = pm.density(pts), knnrefine.KnnDensity(mesh, pts)
    q = _queries(pm, np.random.default_rng(7))
    a, b = got(q), want(q)
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(a, b, rtol=1e-12)
    assert np.isnan(a[-4:]).tolist() == [not mesh.periodic[0]] * 2 + [not mesh.periodic[1]] * 2
    assert got.raw_mass == pytest.approx(want.raw_mass, rel=1e-12)
    lo, hi = np.array(mesh.box[:2]), np.array(mesh.box[2:])
    region = (*(lo + 0.6 * (hi - lo)), *(hi + 0.3 * (hi - lo)))  # past the upper sides
    assert got.mass(region) == pytest.approx(want.mass(region), rel=1e-12)
    np.testing.assert_allclose(got.grid((48, 64))[2], want.grid((48, 64))[2], rtol=1e-12)
    # a grid over any region (issue 53), across the cuts and past the upper sides
    g, h = got.grid((9, 11), extent=region)[2], want.grid((9, 11), extent=region)[2]
    np.testing.assert_array_equal(np.isnan(g), np.isnan(h))
    np.testing.assert_allclose(g, h, rtol=1e-12)


@pytest.mark.parametrize("periodic", [True, False])
def test_partitioned_d_pk_is_exact_at_every_parts_nodes(tmp_path, periodic):
    """The value each part keeps at each node of its pieces (vertices, halo, midpoints, seam
    copies) is the k-th distance from a brute cKDTree (periodic: boxsize), weighted too."""
    from scipy.spatial import cKDTree

    pts = gaussian_clusters(15000, 8)
    w = np.random.default_rng(8).integers(1, 4, len(pts)).astype(float)
    for weights, k in ((None, 12), (w, 30.0)):
        mesh = knnrefine.refine(pts, k, periodic=periodic, box=(0, 0, 1, 1), weights=weights)
        pm = write_partitioned(mesh, tmp_path / f"m{k}", 3)
        dist = pm.distance(pts, weights=weights)
        tree = cKDTree(pts, boxsize=1.0 if periodic else None)
        for j in range(len(pm)):
            part = dist.part(j)
            x = part.nodes % 1.0 if periodic else part.nodes
            if weights is None:
                exact = tree.query(x, k=[k])[0][:, 0]
            else:  # the least radius whose disk holds weight k
                dd, ii = tree.query(x, k=60)
                exact = dd[np.arange(len(x)), np.argmax(np.cumsum(w[ii], axis=1) >= k, axis=1)]
            np.testing.assert_allclose(part.values, exact, rtol=1e-12)


def test_partitioned_density_samples_by_mass_and_runs_in_processes(tmp_path):
    """Samples fall in regions as often as their mass says (5 sigma); strips in two local
    processes give the same estimate as in this process."""
    pts = gaussian_clusters(20000, 9)
    mesh = knnrefine.refine(pts, 20, periodic=True, box=(0, 0, 1, 1))
    pm = write_partitioned(mesh, tmp_path / "m", 3)
    dens = pm.density(pts)
    draws = dens.sample(40000, np.random.default_rng(1))
    assert draws.shape == (40000, 2) and ((draws >= 0) & (draws <= 1)).all()
    for region in ((0, 0, 0.5, 1), (0.2, 0.1, 0.45, 0.8), (0.6, 0.55, 1, 1)):
        p = dens.mass(region)
        inside = np.all((draws >= region[:2]) & (draws <= region[2:]), axis=1).mean()
        assert abs(inside - p) < 5 * np.sqrt(p * (1 - p) / len(draws))
    q = np.random.default_rng(2).random((5000, 2))
    np.testing.assert_allclose(pm.density(pts, workers=2)(q), dens(q), rtol=1e-12)


def test_partitioned_density_refuses_other_points_and_old_folders(tmp_path):
    import json

    pts = gaussian_clusters(8000, 10)
    mesh = knnrefine.refine(pts, 10)
    pm = write_partitioned(mesh, tmp_path / "m", 2)
    with pytest.raises(InputError, match="8,000 points"):
        pm.density(pts[:-1])
    with pytest.raises(InputError, match="weights"):
        pm.density(pts, weights=np.ones(len(pts)))
    for bad in (0, 1.5, True):
        with pytest.raises(InputError, match="workers must be a positive integer"):
            pm.density(pts, workers=bad)
    manifest = tmp_path / "m" / "manifest.json"
    old = json.loads(manifest.read_text())
    old["format"] = 1
    manifest.write_text(json.dumps(old))
    with pytest.raises(InputError, match="older knnrefine"):
        PartitionedMesh(tmp_path / "m").density(pts)


@pytest.mark.parametrize(
    "periodic, weighted",
    [pytest.param((True, False, True), True, marks=pytest.mark.slow), (False, False)],
)
def test_density_in_space_part_by_part_equals_the_whole_meshs(tmp_path, periodic, weighted):
    """In space, PartitionedMesh.density answers as KnnDensity on the whole mesh: at random
    points, on the cut planes, beyond the box (NaN along non-periodic axes), its mass over
    the box and over a region across the seams, its grid; weighted; strips in two local
    processes give the same; samples fall in a region as often as its mass says (5 sigma)."""
    pts = gaussian_clusters(4000, 11, clusters=12, dim=3)
    weights = np.random.default_rng(11).integers(1, 3, len(pts)).astype(float) if weighted else None
    k = 25.0 if weighted else 15
    rng = np.random.default_rng(12)
    mesh = knnrefine.refine(pts, k, periodic=periodic, box=(0, 0, 0, 1, 1, 1), weights=weights)
    pm = write_partitioned(mesh, tmp_path / "m", 3)
    got = pm.density(pts, weights=weights)
    want = knnrefine.KnnDensity(mesh, pts, weights=weights)
    axis = pm.manifest["axis"]
    on_cuts = rng.random((300, 3))
    on_cuts[:, axis] = np.repeat(np.clip(pm.manifest["cuts"], 0.0, 1.0), 100)
    beyond = 0.5 + np.concatenate([-np.eye(3), np.eye(3)])
    q = np.concatenate([rng.random((20000, 3)), on_cuts, beyond])
    a, b = got(q), want(q)
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_allclose(a, b, rtol=1e-12)
    assert np.isnan(a[-6:]).tolist() == [not p for p in mesh.periodic] * 2
    assert got.raw_mass == pytest.approx(want.raw_mass, rel=1e-12)
    region = (0.6, 0.7, 0.2, 1.3, 1.2, 0.9)  # past the upper sides along x and y
    assert got.mass(region) == pytest.approx(want.mass(region), rel=1e-12)
    np.testing.assert_allclose(got.grid((6, 7, 8))[3], want.grid((6, 7, 8))[3], rtol=1e-12)
    g, h = got.grid(5, extent=region)[3], want.grid(5, extent=region)[3]  # any region
    np.testing.assert_array_equal(np.isnan(g), np.isnan(h))
    np.testing.assert_allclose(g, h, rtol=1e-12)
    if weighted:
        np.testing.assert_allclose(pm.density(pts, weights=weights, workers=2)(q), a, rtol=1e-12)
        return
    draws = got.sample(20000, np.random.default_rng(1))
    assert draws.shape == (20000, 3) and ((draws >= 0) & (draws <= 1)).all()
    p = got.mass((0.0, 0.0, 0.0, 0.5, 1.0, 1.0))
    inside = (draws[:, 0] <= 0.5).mean()
    assert abs(inside - p) < 5 * np.sqrt(p * (1 - p) / len(draws))


@pytest.mark.parametrize(
    "dim, name",
    [
        (2, "line"),
        (2, "seam"),
        (3, "plane"),
        (3, "seam"),
        pytest.param(3, "lattice", marks=pytest.mark.slow),
    ],
)
def test_parts_of_degenerate_inputs_answer_as_the_whole_mesh(tmp_path, dim, name):
    """Points sharing a coordinate put many vertices on one cut (the cuts are quantiles of
    the vertices' coordinate): on a line (a plane in space) across the box, on the seam, on a
    lattice, the parts still give back the mesh, and d_M2 and the density part by part
    equal the whole mesh's at the points themselves and at random points."""
    from conftest import DEGENERATE, DEGENERATE3, unit_box

    rng = np.random.default_rng(31)
    pts = (DEGENERATE if dim == 2 else DEGENERATE3)[name](3000 if dim == 2 else 2000, rng)
    mesh = knnrefine.refine(pts, 12, periodic=True, box=unit_box(dim))
    pm = write_partitioned(mesh, tmp_path / "m", 3)
    assert_same_mesh(mesh, pm.to_mesh())
    q = np.concatenate([pts, rng.random((5000, dim))])
    np.testing.assert_array_equal(pm.d_m2(q), mesh.d_m2(q))
    want = knnrefine.KnnDensity(mesh, pts)(q)
    np.testing.assert_allclose(pm.density(pts)(q), want, rtol=1e-12)
