"""A mesh as a folder of parts (knnrefine.partitioned): put back together it is the same
Mesh, array for array; part by part its d_{M,2} equals the whole mesh's (cKDTree over all
vertices) at random points and on the strips' borders; written atomically."""

import os

import numpy as np
import pytest
from conftest import gaussian_clusters

import knnrefine
from knnrefine.errors import InputError
from knnrefine.partitioned import FINISHED, PartitionedMesh, write_partitioned


def assert_same_mesh(a, b):
    for name in ("vertices", "triangles", "offsets", "kinds", "order", "floor_points"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype and np.array_equal(x, y), name
    for name in ("vertices", "triangles", "offsets", "neighbors", "kinds"):
        x, y = getattr(a.torus, name), getattr(b.torus, name)
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
    from knnrefine import partitioned

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
