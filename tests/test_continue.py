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


@pytest.mark.parametrize("d", [2, 3], ids=["plane", "space"])
def test_a_continued_mesh_continues_again_on_its_two_trees(d):
    """A continued mesh keeps the start's tree and a small one over the new points
    (``index.grow_forest``); continued again, the small tree grows, and is merged into the
    large one once it passes 1/8 of it; every mesh certifies, and d_Pk of the last (which
    merges its trees when first asked, in the plane) is exact."""
    rng = np.random.default_rng(13)
    pts = rng.random((4000, d))
    mesh = knnrefine.refine(pts, 10, box=(0,) * d + (1,) * d)
    extra = []
    for b in (100, 150, 400):  # 250 <= 4000 / 8 < 650
        batch = np.clip(rng.normal(rng.random(d), 0.03, (b, d)), 0.0, 1.0)
        pts = np.concatenate([pts, batch])
        mesh = knnrefine.refine(pts, start=mesh)
        assert knnrefine.certify(mesh, pts).passed
        extra.append(len(mesh.index.forest.extra.pts))
    assert extra == [100, 250, 0]
    pts = np.concatenate([pts, np.clip(rng.normal(0.5, 0.02, (120, d)), 0.0, 1.0)])
    mesh = knnrefine.refine(pts, start=mesh)
    assert len(mesh.index.forest.extra.pts) == 120
    probes = rng.random((400, d))
    exact = cKDTree(pts).query(probes, k=10)[0][:, -1]
    assert np.allclose(knnrefine.KnnDistance(mesh, pts).exact(probes), exact, rtol=1e-12)
    assert mesh.index.n == len(pts) and len(mesh.index.index.pts) == len(pts)
    assert len(mesh.index.forest.extra.pts) == 0


def test_a_continued_mesh_on_the_sphere_continues_again_on_its_two_trees():
    """On the sphere too the start's tree is kept and the new points go into a second one,
    merged into the first past 1/8 of its points; every mesh certifies."""
    rng = np.random.default_rng(15)
    pts = np.column_stack([rng.uniform(-180, 180, 4000),
                           np.degrees(np.arcsin(rng.uniform(-1, 1, 4000)))])  # fmt: skip
    mesh = knnrefine.refine(pts, 10, sphere=True)
    extra = []
    for b in (100, 150, 400):
        centre = rng.uniform(-60, 60, 2)
        pts = np.concatenate([pts, np.clip(rng.normal(centre, 2.0, (b, 2)), -89, 89)])
        mesh = knnrefine.refine(pts, start=mesh)
        assert knnrefine.certify(mesh, pts).passed
        extra.append(len(mesh.index.extra.pts))
    assert extra == [100, 250, 0] and len(mesh.index.main.pts) == len(pts)


@pytest.mark.parametrize("domain", ["plane", "space", "sphere"])
def test_reopening_by_balls_finds_what_the_walks_find(domain, monkeypatch):
    """A large batch reopens by testing every circumball (circumcap) against a tree of the
    new points (``reopen.reopen_by_balls``, ``reopen_by_balls3``, ``reopen_by_caps``), a
    small one by a walk and a cavity per point: both reopen the same elements (the
    loosened cavities) and give the same mesh, which certifies; the batch holds duplicates
    and points on a line."""
    from knnrefine._domains.sphere import run as sphere_run
    from knnrefine._engine.driver import Refinement
    from knnrefine._engine.driver3 import Refinement3

    owner, name = {"plane": (Refinement, "BALLS_FROM"), "space": (Refinement3, "BALLS_FROM"),
                   "sphere": (sphere_run, "CAPS_FROM")}[domain]  # fmt: skip
    rng = np.random.default_rng(14)
    d = 3 if domain == "space" else 2
    pts = rng.random((3000, d))
    new = np.clip(rng.normal(0.3, 0.05, (1500, d)), 0.0, 1.0)
    new[1000:1200] = new[:200]  # duplicates of new points
    new[1200:1400] = pts[:200]  # and of old ones
    new[1400:, 0] = 0.5  # on a line
    if domain == "sphere":  # longitude, latitude
        pts, new = pts * [360, 180] - [180, 90], new * [360, 180] - [180, 90]
        mesh = knnrefine.refine(pts, 10, sphere=True)
    else:
        mesh = knnrefine.refine(pts, 10, box=(0,) * d + (1,) * d)
    every = np.concatenate([pts, new])
    out = {}
    for how, above in (("walk", 1e9), ("balls", 0.0)):
        monkeypatch.setattr(owner, name, above)
        out[how] = knnrefine.refine(every, start=mesh)
    walk, balls = out["walk"], out["balls"]
    assert walk.stats.continued["reopened"] == balls.stats.continued["reopened"] > 0
    assert np.array_equal(walk.vertices, balls.vertices)
    assert knnrefine.certify(balls, every).passed


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
    with pytest.raises(InputError, match="in space, these points are on the sphere"):
        knnrefine.refine(cube, sphere=True, start=knnrefine.refine(cube, 5))
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


# -- space and the sphere: the same continuation over the domain protocol ----------------

SPACE_BOX = (0.0, 0.0, 0.0, 1.0, 1.0, 1.0)


def _domain_points(domain, rng, n):
    """n points of the domain: uniform in the unit box, or on the sphere (lon, lat)."""
    if domain == "space":
        return rng.random((n, 3))
    lon = rng.uniform(-180.0, 180.0, n)
    lat = np.degrees(np.arcsin(rng.uniform(-1.0, 1.0, n)))
    return np.column_stack([lon, lat])


def _domain_cluster(domain, rng, n, spread=0.02):
    """n points clustered in one new place of the domain."""
    if domain == "space":
        return np.clip(rng.normal(rng.uniform(0.2, 0.8, 3), spread, (n, 3)), 0.0, 1.0)
    centre = (rng.uniform(-170, 170), rng.uniform(-60, 60))
    lon = rng.normal(centre[0], 100 * spread, n)
    lat = np.clip(rng.normal(centre[1], 100 * spread, n), -90.0, 90.0)
    return np.column_stack([lon, lat])


def _domain_refine(domain, pts, k, **options):
    if domain == "space":
        options.setdefault("box", SPACE_BOX)
    else:
        options["sphere"] = True
    return knnrefine.refine(pts, k, **options)


def _exact_d_pk(domain, pts, probes, k):
    """d_{P,k} by brute force: Euclidean in space, great-circle (radians x radius) on the
    sphere."""
    if domain == "space":
        return cKDTree(pts).query(probes, k=k)[0][:, -1]
    from knnrefine._metric import unit_vectors

    chord = cKDTree(unit_vectors(pts)).query(unit_vectors(probes), k=k)[0][:, -1]
    return 2.0 * np.arcsin(np.minimum(chord / 2.0, 1.0))  # radians: the default radius 1


@pytest.fixture(scope="module", params=["space", "sphere"])
def first_of(request):
    domain = request.param
    rng = np.random.default_rng(21)
    pts = _domain_points(domain, rng, 6000)
    return domain, pts, _domain_refine(domain, pts, 12)


def test_space_and_the_sphere_continue_and_certify(first_of):
    domain, pts, mesh = first_of
    new = _domain_cluster(domain, np.random.default_rng(22), 120)  # 2 %, a new place
    every = np.concatenate([pts, new])
    out = knnrefine.refine(every, start=mesh)
    assert out.domain == domain and out.k == mesh.k and out.tau == mesh.tau
    cert = knnrefine.certify(out, every)
    assert cert.passed, cert
    cells = len(mesh.cells) if domain == "sphere" else len(mesh.torus.cells)
    assert 0 < out.stats.continued["reopened"] < 0.1 * cells
    assert out.stats.m > mesh.stats.m  # the new cluster was split
    fresh = _domain_refine(domain, every, 12)
    assert abs(out.stats.m - fresh.stats.m) <= 0.1 * fresh.stats.m


def test_space_and_the_sphere_with_no_new_point_give_the_start(first_of):
    domain, pts, mesh = first_of
    out = knnrefine.refine(pts, start=mesh)
    assert np.array_equal(out.vertices, mesh.vertices)
    assert np.array_equal(out.cells, mesh.cells)
    assert out.stats.continued == {"points": 0, "from_vertices": mesh.stats.m_torus,
                                   "reopened": 0}  # fmt: skip


def test_d_pk_of_a_continued_mesh_in_space_and_on_the_sphere_is_exact(first_of):
    domain, pts, mesh = first_of
    every = np.concatenate([pts, _domain_cluster(domain, np.random.default_rng(23), 200)])
    out = knnrefine.refine(every, start=mesh)
    probes = _domain_points(domain, np.random.default_rng(24), 300)
    got = knnrefine.KnnDistance(out, every).exact(probes)
    assert np.allclose(got, _exact_d_pk(domain, every, probes, 12), rtol=1e-9)


def test_a_file_start_in_space_and_on_the_sphere_continues_as_in_memory(first_of, tmp_path):
    domain, pts, mesh = first_of
    io.write_mesh(mesh, tmp_path / "first.npz")
    read = io.read_mesh(tmp_path / "first.npz")
    assert read.index is None
    every = np.concatenate([pts, _domain_cluster(domain, np.random.default_rng(25), 90)])
    a = knnrefine.refine(every, start=mesh)
    b = knnrefine.refine(every, start=read)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.cells, b.cells)


@pytest.mark.parametrize("domain", ["space", "sphere"])
def test_weighted_points_continue_in_space_and_on_the_sphere(domain):
    rng = np.random.default_rng(26)
    pts = _domain_points(domain, rng, 3000)
    w = rng.random(3000) + 0.5
    mesh = _domain_refine(domain, pts, 12.5, weights=w)
    every = np.concatenate([pts, _domain_cluster(domain, rng, 60)])
    weights = np.concatenate([w, rng.random(60) + 0.5])
    out = knnrefine.refine(every, weights=weights, start=mesh)
    assert knnrefine.certify(out, every, weights=weights).passed
    with pytest.raises(InputError, match="weights"):
        knnrefine.refine(every, start=mesh)


@pytest.mark.parametrize("domain", ["space", "sphere"])
def test_a_stream_in_space_and_on_the_sphere_ends_near_a_fresh_run(domain):
    rng = np.random.default_rng(27)
    pts = _domain_points(domain, rng, 4000)
    mesh = _domain_refine(domain, pts, 10)
    for _ in range(8):
        pts = np.concatenate([pts, _domain_cluster(domain, rng, 40, 0.03)])
        mesh = knnrefine.refine(pts, start=mesh)
    assert knnrefine.certify(mesh, pts).passed
    fresh = _domain_refine(domain, pts, 10)
    assert abs(mesh.stats.m - fresh.stats.m) <= 0.1 * fresh.stats.m


def test_a_periodic_cube_continues_across_its_seam():
    rng = np.random.default_rng(28)
    pts = rng.random((4000, 3))
    mesh = knnrefine.refine(pts, 10, box=SPACE_BOX, periodic=True)
    new = np.column_stack([np.full(80, 0.999), rng.normal(0.5, 0.01, (80, 2))]) % 1.0
    every = np.concatenate([pts, new])
    out = knnrefine.refine(every, start=mesh)
    assert out.periodic == (True, True, True)
    assert knnrefine.certify(out, every).passed


@pytest.mark.parametrize("kind", ["duplicates", "on a line", "on the box's edge or the seam"])
@pytest.mark.parametrize("domain", ["space", "sphere"])
def test_degenerate_new_points_continue_in_space_and_on_the_sphere(domain, kind):
    """New points that repeat old ones, lie on one line (a meridian on the sphere), or on
    the box's edge (the date line and a pole on the sphere): the continued mesh
    certifies."""
    rng = np.random.default_rng(29)
    pts = _domain_points(domain, rng, 3000)
    mesh = _domain_refine(domain, pts, 10)
    line = np.linspace(0.1, 0.9, 150)
    if kind == "duplicates":
        new = np.concatenate([pts[:30], np.repeat(pts[40:41], 25, axis=0)])
    elif domain == "space":
        new = (np.column_stack([line, np.full(150, 0.5), np.full(150, 0.5)])
               if kind == "on a line" else
               np.column_stack([np.zeros(150), line, np.ones(150)]))  # fmt: skip
    elif kind == "on a line":
        new = np.column_stack([np.full(150, 30.0), 160 * line - 80])
    else:
        new = np.concatenate([np.column_stack([np.full(140, 180.0), 160 * line[:140] - 80]),
                              np.tile([[0.0, 90.0]], (10, 1))])  # fmt: skip
    every = np.concatenate([pts, new])
    out = knnrefine.refine(every, start=mesh)
    assert knnrefine.certify(out, every).passed


def test_refusals_in_space_and_on_the_sphere(first_of):
    domain, pts, mesh = first_of
    every = np.concatenate([pts, pts[:10]])
    with pytest.raises(InputError, match="k=12"):
        knnrefine.refine(every, 13, start=mesh)
    with pytest.raises(InputError, match="tau=3"):
        knnrefine.refine(every, tau=2.5, start=mesh)
    with pytest.raises(InputError, match="not the ones start was refined from"):
        knnrefine.refine(np.concatenate([pts[::-1], pts[:5]]), start=mesh)
    if domain == "space":
        with pytest.raises(InputError, match="outside the start mesh's box along axis 2"):
            knnrefine.refine(np.concatenate([pts, [[0.5, 0.5, 1.5]]]), start=mesh)
        bare = dataclasses.replace(mesh, torus=dataclasses.replace(mesh.torus, neighbours=None))
        with pytest.raises(InputError, match="no neighbours"):
            knnrefine.refine(every, start=bare)
    else:
        with pytest.raises(InputError, match="radius=1.0"):
            knnrefine.refine(every, radius=2.0, start=mesh)
        plane = knnrefine.refine(np.random.default_rng(0).random((500, 2)), 5)
        with pytest.raises(InputError, match="in the plane, these points are on the sphere"):
            knnrefine.refine(every, sphere=True, start=plane)


def test_sphere_digest_is_of_the_points_as_given():
    """Regression: the sphere's index reorders its unit vectors in place, and the digest was
    taken after the run, of the reordered ones: no start on the sphere could continue. The
    digest is now taken at the check, of the points as given."""
    from knnrefine._pipeline import points_digest

    pts = _domain_points("sphere", np.random.default_rng(30), 2000)
    mesh = _domain_refine("sphere", pts, 10)
    assert mesh.stats.points_digest == points_digest(pts, None)  # (lon, lat) as given


# -- the points' digest (``_engine/digest.py``) ------------------------------------------


def _digest_oracle(a, position=0):
    """The digest's definition in plain Python integers: each 64-bit word, mixed with its
    position, summed modulo 2^64."""
    mask = (1 << 64) - 1
    total = 0
    for i, w in enumerate(np.ascontiguousarray(a, np.float64).reshape(-1).view(np.uint64)):
        x = int(w) ^ (((position + i) * 0x9E3779B97F4A7C15) & mask)
        x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & mask
        x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & mask
        total = (total + (x ^ (x >> 31))) & mask
    return total


def test_the_digest_is_its_definition_and_ranges_add_up():
    from knnrefine._engine.digest import digest_of

    rng = np.random.default_rng(40)
    pts = rng.random((700, 2)) * 1e3 - 500
    assert digest_of(pts) == _digest_oracle(pts)
    first, rest = digest_of(pts[:300]), digest_of(pts[300:], 600)  # at its words' position
    assert (first + rest) % (1 << 64) == digest_of(pts)
    big = rng.random((600_000, 3))  # ranges on threads: the same sum
    assert digest_of(big) == (digest_of(big[:1]) + digest_of(big[1:], 3)) % (1 << 64)


@pytest.mark.parametrize(
    "change", ["one bit", "two rows swapped", "a sign", "a row dropped", "a row added"]
)
def test_the_digest_tells_changed_points(change):
    from knnrefine._pipeline import points_digest

    pts = np.random.default_rng(41).random((1000, 2))
    other = pts.copy()
    if change == "one bit":
        other[517, 1] = np.nextafter(other[517, 1], 2.0)
    elif change == "two rows swapped":
        other[[3, 900]] = other[[900, 3]]
    elif change == "a sign":
        other[20, 0] = -other[20, 0]
    elif change == "a row dropped":
        other = other[:-1]
    else:
        other = np.concatenate([other, [[0.0, 0.0]]])
    assert points_digest(other, None) != points_digest(pts, None)
    w = np.ones(len(pts))
    assert points_digest(pts, w) != points_digest(pts, w * 2) != points_digest(pts, None)


def test_a_start_with_a_digest_of_an_older_form_is_refused(first):
    pts, mesh = first
    crc = dataclasses.replace(mesh.stats, points_digest="1a2b3c4d")  # a CRC-32's
    older = dataclasses.replace(mesh, stats=crc)
    with pytest.raises(InputError, match="older form"):
        knnrefine.refine(pts, start=older)


@pytest.mark.parametrize("domain", ["plane", "space", "sphere"])
def test_a_continuation_with_workers_or_an_executor_is_the_one_of_one_process(domain):
    """A continued run's work is where the new points are: ``workers`` (threads on the
    sphere) and an executor give the mesh of one process, which certifies."""
    from concurrent.futures import ThreadPoolExecutor

    rng = np.random.default_rng(42)
    if domain == "plane":
        pts, new = rng.random((5000, 2)), _clustered(rng, 60, (0.3, 0.6), 0.01)
        mesh = knnrefine.refine(pts, 10, box=(0, 0, 1, 1))
    else:
        pts, new = _domain_points(domain, rng, 5000), _domain_cluster(domain, rng, 60)
        mesh = _domain_refine(domain, pts, 10)
    every = np.concatenate([pts, new])
    one = knnrefine.refine(every, start=mesh)
    two = knnrefine.refine(every, start=mesh, workers=2)
    assert np.array_equal(one.vertices, two.vertices) and np.array_equal(one.cells, two.cells)
    if domain != "sphere":
        with ThreadPoolExecutor(2) as pool:
            pooled = knnrefine.refine(every, start=mesh, workers=2, executor=pool)
        assert np.array_equal(one.vertices, pooled.vertices)
    assert knnrefine.certify(two, every).passed
