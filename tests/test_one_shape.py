"""Issue 51: what one domain records, warns and certifies, every domain does. One suite over
a ``domain`` fixture (the plane, space, the sphere): one stats record with one key set, one
FloorWarning rule, the same certify verdicts on tampered meshes."""

import dataclasses
import os
import warnings

import numpy as np
import pytest
from conftest import degenerate_in, gaussian_clusters, points_in, refine_in

import knnrefine
from knnrefine import io
from knnrefine.mesh import Stats

KEYS = tuple(f.name for f in dataclasses.fields(Stats))


def test_stats_have_one_key_set_in_every_domain(domain, tmp_path):
    pts = points_in(domain, 1000)
    w = np.random.default_rng(1).integers(1, 3, len(pts)).astype(float)
    for mesh, weight in ((refine_in(domain, pts), None), (refine_in(domain, pts, weights=w), w)):
        st = mesh.stats
        assert isinstance(st, Stats) and tuple(st) == KEYS
        assert st.n == len(pts) and st.m == len(mesh.vertices) and st.cells == len(mesh.cells)
        assert st.weight == (None if weight is None else pytest.approx(weight.sum()))
        assert sum(st.moves.values()) == st.m_torus
        assert st.initial_vertices == st.moves["initial"] > 0
        assert st.circumball_tests > 0 and st.cell_tests > 0
        assert st.estimated_vertices > 0 and st.max_vertices >= st.m_torus
        assert 0 < st.largest_circumball < np.inf
        assert set(st.time) == {"setup", "refine", "assemble", "total"}
        assert st.seconds == st.time["total"] >= st.time["refine"]
        assert st.rounds is None
        path = tmp_path / f"{domain}.npz"
        io.write_mesh(mesh, path, force=True)
        assert io.read_mesh(path).stats == st


def test_tiled_runs_keep_the_key_set(tiles_always):
    for dim in (2, 3):
        pts = gaussian_clusters(3000, 3, dim=dim)
        mesh = knnrefine.refine(pts, 10, workers=2)
        assert tuple(mesh.stats) == KEYS and mesh.stats.rounds
        assert set(mesh.stats.time) == {"setup", "refine", "assemble", "total"}


def test_files_of_the_per_domain_keys_still_read():
    """knnrefine 0.1 wrote seconds / failed / disk_tests / floor_circumcaps / m0 ..."""
    old_space = {"n": 5, "m": 3, "m_torus": 4, "disk_tests": 7, "failed": 1, "seconds": 2.0}
    st = Stats.from_dict(old_space)
    assert (st.circumball_tests, st.failed_insertions, st.seconds) == (7, 1, 2.0)
    old_sphere = {"circumcap_tests": 3, "floor_circumcaps": 2, "largest_circumcap": 0.1,
                  "triangles": 9, "vertices": 4}  # fmt: skip
    st = Stats.from_dict(old_sphere, radius=10.0)
    assert (st.circumball_tests, st.floor_circumballs, st.cells) == (3, 2, 9)
    assert st.largest_circumball == pytest.approx(1.0)
    old_plane = {"m0": {"vertices": 20}, "time": {"index": 0.1, "total": 0.3}}
    st = Stats.from_dict(old_plane)
    assert st.initial_vertices == 20 and st.time == {"setup": 0.1, "total": 0.3}
    with pytest.raises(KeyError, match="Mesh.stats has"):
        st["seconds"]  # noqa: B018


def test_one_floor_warning_rule_in_every_domain(domain):
    """Most points under the floor: a FloorWarning naming how many, in every domain; a few
    floor elements among many points: none (the rule of the plane, now everyone's)."""
    pts = points_in(domain, 1000)
    crowd = np.repeat(pts[:1], 100, axis=0)
    with pytest.warns(knnrefine.FloorWarning, match="100 of the 100 points"):
        mesh = refine_in(domain, crowd, 10)
    assert mesh.stats.points_under_floor == 100 and len(mesh.floor_points)
    some = np.concatenate([pts, crowd[:30]])
    with warnings.catch_warnings():
        warnings.simplefilter("error", knnrefine.FloorWarning)
        mesh = refine_in(domain, some, 10)
    assert 30 <= mesh.stats.points_under_floor < len(some) / 2
    assert mesh.stats.floor_circumballs + mesh.stats.floor_cells > 0


@pytest.mark.parametrize("tamper", ["drop", "copy", "move"])
def test_certify_fails_the_same_tampering_in_every_domain(domain, tamper):
    pts = points_in(domain, 800)
    mesh = refine_in(domain, pts)
    assert knnrefine.certify(mesh, pts, samples=1000).passed
    cells = mesh.cells.copy()
    if tamper == "drop":
        cells = cells[1:]
    elif tamper == "copy":
        cells = np.concatenate([cells, cells[:1]])
    bad = dataclasses.replace(mesh, cells=cells)
    if tamper == "move":  # two vertices trade places: the cells no longer fit them
        swap = np.arange(len(mesh.vertices))
        swap[[0, len(swap) // 2]] = swap[[len(swap) // 2, 0]]
        moved = {"vertices": mesh.vertices[swap]}
        if domain == "sphere":
            moved["xyz"] = mesh.xyz[swap]
        bad = dataclasses.replace(mesh, **moved)
    offsets = None if mesh.offsets is None else (
        mesh.offsets[1:] if tamper == "drop" else np.concatenate([mesh.offsets, mesh.offsets[:1]])
        if tamper == "copy" else mesh.offsets)  # fmt: skip
    if mesh.offsets is not None:
        bad = dataclasses.replace(bad, offsets=offsets)
    cert = knnrefine.certify(bad, pts, samples=1000)
    assert not cert.passed, str(cert)
    assert cert.triangulation_problems or cert.mesh_problems or cert.max_aspect > mesh.tau


def test_the_stats_and_the_floor_rule_hold_on_degenerate_points(domain):
    """Points on a line (a seam, the equator, the antimeridian) and duplicates: the same key
    set, and the points under the floor counted as in every domain."""
    pts = degenerate_in(domain, 900)
    mesh = refine_in(domain, pts, 10)
    assert tuple(mesh.stats) == KEYS
    assert mesh.stats.points_under_floor <= len(pts) / 2  # no FloorWarning was due
    assert knnrefine.certify(mesh, pts, samples=1000).passed


def test_the_command_line_takes_weights_on_degenerate_points(tmp_path, capsys):
    """--weights with duplicated rows and points on a line: the API's mesh, certified."""
    from knnrefine.cli.main import main

    pts = degenerate_in("plane")
    w = np.random.default_rng(3).integers(0, 3, len(pts)).astype(float)
    path = tmp_path / "p.csv"
    np.savetxt(path, np.column_stack([pts, w]), delimiter=",", header="x,y,w", comments="")
    out = tmp_path / "m.npz"
    argv = ["refine", str(path), "--weights", "w", "-k", "10", "-o", str(out), "--certify"]
    assert main(argv + ["--quiet"]) == 0
    np.testing.assert_array_equal(
        io.read_mesh(out).vertices, knnrefine.refine(pts, 10, weights=w).vertices
    )
    capsys.readouterr()


def test_every_domain_refuses_a_run_far_beyond_its_budget_or_memory(domain, monkeypatch):
    """The up-front promises of a run's size, once (options.check_size) for every domain:
    a run expected far beyond max_vertices, or (without it) beyond twice the memory, is
    refused before any work with the same message; one expected to need more than 2 GB
    says so (LargeRunWarning), shown outside knnrefine. The sphere had none of them."""
    from knnrefine._engine import size

    pts = points_in(domain, 2000)
    expected = refine_in(domain, pts, 10).stats.estimated_vertices
    with pytest.raises(knnrefine.BudgetError, match="far beyond max_vertices=60;"):
        refine_in(domain, pts, 10, max_vertices=60)  # above every initial mesh
    per_vertex = {"plane": size.BYTES_PER_VERTEX, "space": size.BYTES_PER_VERTEX3,
                  "sphere": size.BYTES_PER_VERTEX_SPHERE}[domain]  # fmt: skip
    memory = expected * per_vertex // 3  # the run needs 3 times the memory
    monkeypatch.setattr(size, "memory_bytes", lambda: memory)
    with pytest.raises(knnrefine.BudgetError, match="far more than this machine's"):
        refine_in(domain, pts, 10)
    monkeypatch.setattr(size, "memory_bytes", lambda: 10**12)
    monkeypatch.setattr("knnrefine._options.LARGE_RUN_BYTES", 1.0)
    with pytest.warns(knnrefine.LargeRunWarning, match="GB of memory") as caught:
        refine_in(domain, pts, 10)
    shown = [w.filename for w in caught if w.category is knnrefine.LargeRunWarning]
    package = os.path.join("src", "knnrefine", "")
    assert shown and all(package not in f for f in shown), shown


def test_a_mesh_names_its_domain_and_carries_no_stand_ins(domain, tmp_path):
    """Issue 51: ``Mesh.domain`` is the domain's name in every domain ("box", the
    constructor's default, resolves by dimension), and a sphere mesh has no box and no
    periodic axes (0.x gave it a stand-in box and periodic=(True, False)); ``extent`` is the
    region its coordinates span. The same after a round trip through a file, and 0.x's
    sphere files read without the stand-ins."""
    pts = points_in(domain, 1500)
    mesh = refine_in(domain, pts)
    assert mesh.domain == domain
    if domain == "sphere":
        assert mesh.box == () and mesh.periodic == () and mesh.period == ()
        assert mesh.extent == (-180.0, -90.0, 180.0, 90.0)
    else:
        assert mesh.extent == mesh.box and len(mesh.box) == 2 * mesh.dim
        assert dataclasses.replace(mesh, domain="box").domain == domain
    io.write_mesh(mesh, tmp_path / "m.npz")
    back = io.read_mesh(tmp_path / "m.npz")
    assert (back.domain, back.box, back.periodic) == (mesh.domain, mesh.box, mesh.periodic)
    assert knnrefine.certify(back, pts, samples=2000, n_random=500).passed
    if domain == "sphere":  # a file of 0.x, with the stand-ins
        with np.load(tmp_path / "m.npz") as d:
            arrays = dict(d)
        arrays.update(periodic=np.array([True, False]), box=np.array([-180.0, -90, 180, 90]))
        np.savez(tmp_path / "old.npz", **arrays)
        old = io.read_mesh(tmp_path / "old.npz")
        assert (old.box, old.periodic, old.domain) == ((), (), "sphere")
    with pytest.raises(knnrefine.InputError, match="domain must be"):
        dataclasses.replace(mesh, domain="torus")


def test_the_uses_ask_the_domain_on_degenerate_points(domain):
    """Issue 51's review: d_Pk, persistence and clustering build from the domain's parts
    (``_domains.<domain>.density``: points, exact index, frame, query rule), on points on a
    line or seam, on the antimeridian and duplicated. Exact d_Pk against a brute-force
    k-nearest distance (great-circle on the sphere), NaN only off the domain, and the
    persistence's d_Pk at its nodes the same brute force."""
    from scipy.spatial import cKDTree

    from knnrefine.density import KnnDistance
    from knnrefine.topology import Persistence

    def unit_vectors(lonlat):  # the oracle's own
        lon, lat = np.radians(lonlat[:, 0]), np.radians(lonlat[:, 1])
        return np.column_stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])

    pts = degenerate_in(domain, 1200)
    mesh = refine_in(domain, pts)
    dist = KnnDistance(mesh, pts)
    rng = np.random.default_rng(3)
    if domain == "sphere":
        q = np.column_stack([rng.uniform(-180, 180, 300), rng.uniform(-89, 89, 300)])
        chord = cKDTree(unit_vectors(pts)).query(unit_vectors(q), k=[10])[0][:, 0]
        want = 2 * np.arcsin(np.minimum(chord / 2, 1.0))
        off = np.array([[0.0, 95.0], [np.nan, 0.0]])
    else:
        lo, hi = np.array(mesh.box[: mesh.dim]), np.array(mesh.box[mesh.dim :])
        q = lo + rng.random((300, mesh.dim)) * (hi - lo)
        want = cKDTree(pts).query(q, k=[10])[0][:, 0]
        off = np.stack([hi + 1.0, np.full(mesh.dim, np.nan)])
    np.testing.assert_allclose(dist.exact(q), want, rtol=1e-12)
    assert np.isfinite(dist(q)).all() and np.isnan(dist(off)).all()
    assert np.isnan(dist.exact(off)).all()
    pytest.importorskip("gudhi")
    persistence = Persistence(mesh, pts, log=False, subdivide=False)
    nodes = persistence.positions
    if domain == "sphere":
        chord = cKDTree(unit_vectors(pts)).query(unit_vectors(nodes), k=[10])[0][:, 0]
        at_nodes = 2 * np.arcsin(np.minimum(chord / 2, 1.0))
    else:
        at_nodes = cKDTree(pts).query(nodes, k=[10])[0][:, 0]
    np.testing.assert_allclose(persistence.values, at_nodes, rtol=1e-9, atol=1e-12)
    clusters = knnrefine.cluster(mesh, pts)
    assert len(clusters.labels) == len(pts) and clusters.n_clusters >= 1
