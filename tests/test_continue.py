"""A mesh continued with points that arrived since (``refine(..., start=mesh)``, issue 55):
what refine guarantees for all the points, checked by ``certify`` (and by every test's
automatic certificate, conftest.py), with work only where the new points are; and every start
that cannot be continued refused before any work."""

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

import knnrefine
from knnrefine import io
from knnrefine.errors import InputError


def _clustered(rng, n, centre, spread=0.02):
    return np.clip(rng.normal(centre, spread, (n, 2)), 0.0, 1.0)


@pytest.fixture(scope="module")
def first():
    rng = np.random.default_rng(5)
    pts = np.concatenate([rng.random((6000, 2)), _clustered(rng, 2000, (0.7, 0.7))])
    return pts, knnrefine.refine(pts, 10)


def test_a_continued_mesh_certifies_and_reopens_only_where_points_arrived(first):
    pts, mesh = first
    new = _clustered(np.random.default_rng(6), 80, (0.2, 0.3), 0.01)  # 1 %, a new place
    every = np.concatenate([pts, new])
    out = knnrefine.refine(every, start=mesh)
    cert = knnrefine.certify(out, every)
    assert cert.passed, cert
    assert out.k == mesh.k and out.tau == mesh.tau and out.box == mesh.box
    assert out.stats.continued["points"] == 80
    assert out.stats.continued["from_vertices"] == mesh.stats.m_torus
    # the cavities of 80 points: a few percent of the triangles, not the mesh
    assert 0 < out.stats.continued["reopened"] < 0.05 * len(mesh.torus.cells)
    assert out.stats.m_torus > mesh.stats.m_torus  # the new cluster was split
    fresh = knnrefine.refine(every, 10)
    assert abs(out.stats.m - fresh.stats.m) <= 0.1 * fresh.stats.m
    assert out.stats.points_digest != mesh.stats.points_digest


def test_continued_with_no_new_point_is_the_start(first):
    pts, mesh = first
    out = knnrefine.refine(pts, start=mesh)
    assert np.array_equal(out.vertices, mesh.vertices)
    assert np.array_equal(out.torus.cells, mesh.torus.cells)
    assert out.stats.points_digest == mesh.stats.points_digest


def test_d_pk_of_the_continued_mesh_is_exact_for_all_points(first):
    pts, mesh = first
    every = np.concatenate([pts, _clustered(np.random.default_rng(7), 300, (0.4, 0.8))])
    out = knnrefine.refine(every, start=mesh)
    probes = np.random.default_rng(8).random((500, 2))
    exact = cKDTree(every).query(probes, k=10)[0][:, -1]
    assert np.allclose(knnrefine.KnnDistance(out, every).exact(probes), exact, rtol=1e-12)


def test_a_mesh_read_from_a_file_continues_as_the_one_in_memory(first, tmp_path):
    pts, mesh = first
    path = tmp_path / "first.npz"
    io.write_mesh(mesh, path)
    read = io.read_mesh(path)
    assert read.index is None and read.stats.points_digest == mesh.stats.points_digest
    every = np.concatenate([pts, _clustered(np.random.default_rng(9), 100, (0.1, 0.9))])
    a = knnrefine.refine(every, start=mesh)
    b = knnrefine.refine(every, start=read)
    assert np.array_equal(a.vertices, b.vertices)


@pytest.mark.parametrize(
    "options",
    [{"periodic": True, "box": (0, 0, 1, 1)}, {"periodic": (True, False), "box": (0, 0, 1, 1)}],
)
def test_tori_and_mixed_boxes_continue(options):
    rng = np.random.default_rng(10)
    pts = rng.random((4000, 2))
    mesh = knnrefine.refine(pts, 8, **options)
    every = np.concatenate([pts, _clustered(rng, 60, (0.99, 0.5), 0.01)])  # across the seam
    out = knnrefine.refine(every, start=mesh)
    assert out.periodic == mesh.periodic
    assert knnrefine.certify(out, every).passed


def test_weighted_points_continue_with_their_weights():
    rng = np.random.default_rng(11)
    pts, w = rng.random((4000, 2)), rng.random(4000) + 0.5
    mesh = knnrefine.refine(pts, 12.5, weights=w)
    every = np.concatenate([pts, _clustered(rng, 50, (0.5, 0.5), 0.01)])
    weights = np.concatenate([w, rng.random(50) + 0.5])
    out = knnrefine.refine(every, weights=weights, start=mesh)
    assert knnrefine.certify(out, every, weights=weights).passed
    with pytest.raises(InputError, match="weights"):
        knnrefine.refine(every, start=mesh)


def test_a_stream_of_batches_ends_near_a_fresh_run():
    """Ten batches of 1 % each, every one continued from the last mesh: the end certifies
    and is within 10 % of a fresh run's size."""
    rng = np.random.default_rng(12)
    pts = rng.random((5000, 2))
    mesh = knnrefine.refine(pts, 10, box=(0, 0, 1, 1))  # a box that holds what will come
    for _ in range(10):
        batch = _clustered(rng, 50, rng.random(2), 0.03)
        pts = np.concatenate([pts, batch])
        mesh = knnrefine.refine(pts, start=mesh)
    assert knnrefine.certify(mesh, pts).passed
    fresh = knnrefine.refine(pts, 10, box=(0, 0, 1, 1))
    assert abs(mesh.stats.m - fresh.stats.m) <= 0.1 * fresh.stats.m


# -- refused before any work -------------------------------------------------------------


def test_a_start_of_other_options_is_refused(first):
    pts, mesh = first
    every = np.concatenate([pts, pts[:10] * 0.5])
    for options, what in (({"k": 11}, "k=10"), ({"tau": 2.5}, "tau=3"),
                          ({"min_size": 1e-3}, "min_size="),
                          ({"box": (0, 0, 2, 2)}, "box="),
                          ({"periodic": True, "box": mesh.box}, "periodic=")):  # fmt: skip
        with pytest.raises(InputError, match=what):
            knnrefine.refine(every, start=mesh, **options)


def test_points_not_starting_with_the_starts_are_refused(first):
    pts, mesh = first
    changed = pts.copy()
    changed[17, 0] = np.nextafter(changed[17, 0], 1.0)
    with pytest.raises(InputError, match="not the ones start was refined from"):
        knnrefine.refine(np.concatenate([changed, pts[:5]]), start=mesh)
    with pytest.raises(InputError, match="not the ones start was refined from"):
        knnrefine.refine(np.concatenate([pts[::-1], pts[:5]]), start=mesh)
    with pytest.raises(InputError, match="8,000 points, this run has 7,999"):
        knnrefine.refine(pts[:-1], start=mesh)


def test_new_points_outside_an_ordinary_box_are_refused(first):
    pts, mesh = first
    outside = np.array([[0.5, mesh.box[3] + 0.1]])
    with pytest.raises(InputError, match="outside the start mesh's box along axis 1"):
        knnrefine.refine(np.concatenate([pts, outside]), start=mesh)


def test_a_start_of_another_domain_or_kind_is_refused(first):
    pts, mesh = first
    with pytest.raises(InputError, match="in the plane, these points are in space"):
        knnrefine.refine(np.random.default_rng(0).random((100, 3)), 5, start=mesh)
    cube = np.random.default_rng(1).random((400, 3))
    with pytest.raises(InputError, match="built in the plane so far, not yet in space"):
        knnrefine.refine(cube, start=knnrefine.refine(cube, 5))
    with pytest.raises(InputError, match="start must be a knnrefine.Mesh"):
        knnrefine.refine(pts, start="first.npz")
    older = dataclasses.replace(mesh, stats=dataclasses.replace(mesh.stats, points_digest=""))
    with pytest.raises(InputError, match="older knnrefine"):
        knnrefine.refine(pts, start=older)
    weighted = knnrefine.refine(pts[:2000], 10, weights=np.ones(2000))
    with pytest.raises(InputError, match="refined with weights"):
        knnrefine.refine(pts[:2100], start=weighted)


def test_the_command_line_continues_a_mesh_file(tmp_path, capsys):
    """``knnrefine refine all.csv --start old.npz``: the rows of all.csv after old.npz's
    points are new; the continued mesh certifies; another file's rows are refused (exit 1,
    the message saying why)."""
    from knnrefine.cli.main import main

    rng = np.random.default_rng(13)
    first = rng.random((3000, 2))
    every = np.concatenate([first, _clustered(rng, 40, (0.5, 0.5), 0.01)])
    np.savetxt(tmp_path / "first.csv", first, delimiter=",")
    np.savetxt(tmp_path / "all.csv", every, delimiter=",")
    np.savetxt(tmp_path / "other.csv", every[::-1], delimiter=",")
    old, new = str(tmp_path / "old.npz"), str(tmp_path / "new.npz")
    assert main(["refine", str(tmp_path / "first.csv"), "-k", "10", "--box", "0", "0", "1",
                 "1", "-o", old, "-q"]) == 0  # fmt: skip
    assert main(["refine", str(tmp_path / "all.csv"), "--start", old, "-o", new, "-q",
                 "--certify"]) == 0  # fmt: skip
    mesh = io.read_mesh(new)
    assert mesh.stats.n == 3040 and mesh.stats.continued["points"] == 40
    capsys.readouterr()
    assert main(["refine", str(tmp_path / "other.csv"), "--start", old, "-o",
                 str(tmp_path / "x.npz"), "-q"]) == 1  # fmt: skip
    assert "not the ones start was refined from" in capsys.readouterr().err


@pytest.mark.parametrize("kind", ["duplicates", "on a line", "on the box's edge"])
def test_degenerate_new_points_continue(kind):
    """New points that repeat old ones (some many times), lie on one line, or on the box's
    edge: the continued mesh certifies."""
    rng = np.random.default_rng(14)
    pts = rng.random((3000, 2))
    mesh = knnrefine.refine(pts, 10, box=(0, 0, 1, 1))
    if kind == "duplicates":
        new = np.concatenate([pts[:30], np.repeat(pts[40:41], 25, axis=0)])
    elif kind == "on a line":
        new = np.column_stack([np.linspace(0.1, 0.9, 200), np.full(200, 0.5)])
    else:
        new = np.column_stack([np.zeros(100), np.linspace(0.0, 1.0, 100)])
    every = np.concatenate([pts, new])
    out = knnrefine.refine(every, start=mesh)
    assert knnrefine.certify(out, every).passed
