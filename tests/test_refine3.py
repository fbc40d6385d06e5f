"""kNNRefine in space (knnrefine.refine with (n, 3) points in a box periodic on all, some or
none of its axes): the oracle matrix of the plane, in 3-D. Every mesh is certified by certify3
(exact tetrahedralisation checks, cKDTree(boxsize) counts of every circumball and cell,
aspect, and the achieved d_M2 / d_Pk at dense probes of the box, in its own metric, within
Theorem 6's [alpha, beta]); and the checks themselves are shown to fail on wrong meshes."""

import dataclasses
import os

import numpy as np
import pytest
from conftest import assert_unfolding_keeps_every_copy, multiscale, torus_frame
from conftest import uniform as uniform_in
from scipy.spatial import cKDTree

import knnrefine
from knnrefine.errors import InputError
from knnrefine.mesh import Mesh, Torus

BOX = (0.0, 0.0, 0.0, 1.0, 1.0, 1.0)


def uniform(n, seed):
    return uniform_in(n, seed, dim=3)


def lattice(n, seed):
    m = max(2, round(n ** (1 / 3)))
    g = np.arange(m) / m
    return np.array(np.meshgrid(g, g, g)).reshape(3, -1).T


def coplanar(n, seed):
    """All points on the plane z = 0.25 (and a few on x = 0.5)."""
    rng = np.random.default_rng(seed)
    pts = rng.random((n, 3))
    pts[:, 2] = 0.25
    pts[: n // 10, 0] = 0.5
    return pts


def duplicates(n, seed, k=10):
    """Each point repeated k - 1 times (multiplicity below k)."""
    base = uniform(n // (k - 1) + 1, seed)
    return np.repeat(base, k - 1, axis=0)[:n]


def on_faces(n, seed):
    """Points on the box's faces, edges and corners (the periodic seams; upper and lower
    faces, which a periodic axis identifies)."""
    rng = np.random.default_rng(seed)
    pts = rng.random((n, 3))
    face = rng.integers(0, 3, n)
    pts[np.arange(n), face] = rng.integers(0, 2, n).astype(float)
    pts[:8] = np.array(np.meshgrid([0, 0.5], [0, 0.5], [0, 0.5])).reshape(3, -1).T
    return pts


INPUTS = {
    "uniform": uniform,
    "multiscale": multiscale,
    "lattice": lattice,
    "coplanar": coplanar,
    "duplicates": duplicates,
    "faces": on_faces,
}


def assert_certified(mesh, pts):
    cert = knnrefine.certify(mesh, pts)
    assert cert.triangulation_ok and not cert.triangulation_problems
    assert cert.max_aspect <= mesh.tau * (1 + 1e-9)
    assert cert.max_ball_count < mesh.k and cert.max_cell_count < mesh.k
    assert mesh.alpha <= cert.alpha_hat and cert.beta_hat <= mesh.beta
    assert cert.passed
    return cert


PERIODICITIES = [True, False, (True, False, True)]


@pytest.mark.slow
@pytest.mark.parametrize("periodic", PERIODICITIES, ids=["torus", "box", "mixed"])
@pytest.mark.parametrize("name", sorted(INPUTS))
@pytest.mark.parametrize("k", [10, 100])
def test_the_matrix_is_certified(name, k, periodic):
    pts = INPUTS[name](6000, 1)
    mesh = knnrefine.refine(pts, k, 3.0, periodic=periodic, box=BOX)
    assert isinstance(mesh, Mesh) and mesh.dim == 3 and mesh.vertices.shape[1] == 3
    assert mesh.tetrahedra.shape[1] == 4
    if periodic is False:
        assert mesh.offsets is None
    else:
        assert mesh.offsets.shape[1:] == (4, 3)
        assert not mesh.offsets[:, :, ~np.array(mesh.periodic)].any()
    assert_certified(mesh, pts)


@pytest.mark.slow
@pytest.mark.parametrize("tau", [2.5, 4.0])
def test_other_taus_are_certified(tau):
    pts = multiscale(5000, 2)
    mesh = knnrefine.refine(pts, 10, tau, periodic=True, box=BOX)
    assert_certified(mesh, pts)


@pytest.mark.slow
@pytest.mark.parametrize("periodic", PERIODICITIES, ids=["torus", "box", "mixed"])
def test_k_1_refines_down_to_the_floor_and_says_so(periodic):
    """d_{P,1} vanishes on P: the elements round each point stop at the floor, and certify
    exempts exactly those (counted), checking the ratio where d_Pk >= min_size."""
    pts = uniform(150, 3)
    mesh = knnrefine.refine(pts, 1, 3.0, periodic=periodic, box=BOX, min_size=1e-2)
    cert = assert_certified(mesh, pts)
    assert cert.floor_circumballs + cert.floor_cells > 0


def test_a_box_of_other_sides_and_origin():
    """A box away from the origin with three different sides: certified, d_M2 answered in
    input units against a brute periodic kd-tree over the vertices."""
    box = (-2.0, 10.0, 0.5, 0.0, 11.0, 3.5)
    lo, hi = np.array(box[:3]), np.array(box[3:])
    pts = lo + multiscale(8000, 4) * (hi - lo)
    mesh = knnrefine.refine(pts, 20, periodic=True, box=box)
    assert_certified(mesh, pts)
    q = lo + np.random.default_rng(5).random((2000, 3)) * (hi - lo)
    tree = cKDTree(mesh.vertices - lo, boxsize=hi - lo)
    np.testing.assert_allclose(mesh.d_m2(q), tree.query(q - lo, k=2)[0][:, 1], rtol=1e-12)


def test_certify_fails_wrong_meshes():
    """A mesh of other points fails; so does a mesh with one tetrahedron reoriented, in the
    returned tetrahedra (they are no longer the torus' copies) or in the torus itself (its
    orientation check)."""
    pts = uniform(4000, 6)
    mesh = knnrefine.refine(pts, 10, periodic=True, box=BOX)
    other = knnrefine.refine(multiscale(4000, 7), 10, periodic=True, box=BOX)
    assert not knnrefine.certify(other, pts).passed
    flipped = mesh.tetrahedra.copy()
    flipped[0, [0, 1]] = flipped[0, [1, 0]]
    offsets = mesh.offsets.copy()
    offsets[0, [0, 1]] = offsets[0, [1, 0]]
    returned = dataclasses.replace(mesh, cells=flipped, offsets=offsets)
    cert = knnrefine.certify(returned, pts)
    assert not cert.passed and cert.triangulation_ok
    assert any("tetrahedra" in p for p in cert.mesh_problems)
    torus = dataclasses.replace(mesh.torus, cells=flipped, offsets=offsets)
    cert = knnrefine.certify(dataclasses.replace(returned, torus=torus), pts)
    assert not cert.passed and not cert.triangulation_ok


def test_bad_input_is_refused_before_work():
    pts = uniform(100, 8)
    with pytest.raises(InputError, match="triple of bools"):
        knnrefine.refine(pts, 10, periodic=(True, False), box=BOX)
    outside = pts.copy()
    outside[7, 2] = 1.5
    with pytest.raises(InputError, match="outside the box along z"):
        knnrefine.refine(outside, 10, periodic=(True, True, False), box=BOX)
    mesh = knnrefine.refine(outside, 10, periodic=(False, False, True), box=BOX)  # z wraps
    with pytest.raises(InputError, match="made from 100 points"):
        knnrefine.certify(mesh, outside[:-1])
    with pytest.raises(InputError, match="outside the mesh.s box along x"):
        knnrefine.certify(mesh, outside + [1.0, 0.0, 0.0])
    with pytest.raises(InputError, match=r"needs box=\(x0, y0, z0, x1, y1, z1\)"):
        knnrefine.refine(pts, 10, periodic=True)
    with pytest.raises(InputError, match="six"):
        knnrefine.refine(pts, 10, periodic=True, box=(0, 0, 1, 1))
    with pytest.raises(InputError, match="x0 < x1"):
        knnrefine.refine(pts, 10, periodic=True, box=(0, 0, 0, 1, -1, 1))
    with pytest.raises(InputError, match="k"):
        knnrefine.refine(pts, 101, periodic=True, box=BOX)
    with pytest.raises(InputError, match="tau"):
        knnrefine.refine(pts, 10, 2.0, periodic=True, box=BOX)
    bad = pts.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        knnrefine.refine(bad, 10, periodic=True, box=BOX)
    with pytest.raises(InputError, match=r"weights must have shape \(100,\)"):
        knnrefine.refine(pts, 10, periodic=True, box=BOX, weights=np.ones(99))
    # the plane's option checks (options.RunOptions), not a looser copy: a bool is no time
    # limit, a number no progress callback
    with pytest.raises(InputError, match="time_limit"):
        knnrefine.refine(pts, 10, periodic=True, box=BOX, time_limit=True)
    with pytest.raises(InputError, match="progress"):
        knnrefine.refine(pts, 10, periodic=True, box=BOX, progress=5)
    with pytest.raises(InputError, match="min_size"):
        knnrefine.refine(pts, 10, periodic=True, box=BOX, min_size=-1.0)
    with pytest.raises(InputError, match="max_vertices"):
        knnrefine.refine(pts, 10, periodic=True, box=BOX, max_vertices=2.5)


def test_time_limit_and_budget_stop_the_run(monkeypatch):
    """A run in space stops at its deadline, during setup or between kernel calls (the
    driver reads the clock the options' check set the deadline on), and at its vertex
    budget, with BudgetError and how far it got (regression: that BudgetError lacked its
    progress and raised TypeError instead); progress reports growing vertex counts."""
    import time

    from knnrefine._engine import driver3
    from knnrefine._engine.refine import STATUS_DONE, STATUS_STEPS
    from knnrefine.errors import BudgetError

    pts = multiscale(20000, 23)
    with pytest.raises(BudgetError, match="time_limit reached while (setting up|choosing)"):
        knnrefine.refine(pts, 10, box=BOX, time_limit=1e-6)
    with pytest.raises(BudgetError, match="max_vertices = 3,000") as stopped:
        knnrefine.refine(pts, 10, box=BOX, max_vertices=3000)
    got = stopped.value.progress
    assert got["vertices"] == 3000 == sum(got["moves"].values()) and got["seconds"] > 0
    monkeypatch.setattr(driver3, "STEPS", 200)
    run = _start_run(pts)
    nv0 = int(run.cnt[0])
    assert run.run(deadline=time.perf_counter() - 1.0) == STATUS_STEPS
    assert nv0 < run.cnt[0] <= nv0 + 200  # one kernel call of 200 insertions, then the clock
    seen = []
    done = run.run(deadline=time.perf_counter() + 600, progress=lambda m, q: seen.append(m))
    assert done == STATUS_DONE
    assert len(seen) > 10 and seen == sorted(seen)


@pytest.mark.slow
@pytest.mark.parametrize("k", [10, 50])
def test_methionine_torsions_on_the_3_torus(k):
    """Real data: 18,417 methionine side-chain torsion triples (chi1, chi2, chi3) in degrees,
    periodic with period 360 on every axis (../shared/data README: Top8000, CC BY 4.0)."""
    from conftest import load_shared

    pts = load_shared("rota_top8000_met_chi1_chi2_chi3.csv")
    mesh = knnrefine.refine(pts, k, periodic=True, box=(0, 0, 0, 360, 360, 360))
    cert = assert_certified(mesh, pts)
    assert cert.beta_hat < 3.0  # far inside Theorem 6's beta = 36 (typically about 1.5)


def test_the_initial_mesh_check_counts_balls_of_every_size():
    """run3.holds_k (does the closed ball of radius r about x hold k points?) against a
    periodic kd-tree, for radii below half the period (the index), up to the torus'
    diameter (a direct count) and beyond it (every point)."""
    from knnrefine._domains.space.run import holds_k
    from knnrefine._engine.index3 import build_index3

    period = np.array([1.0, 0.5, 2.0])
    u = np.mod(multiscale(5000, 9) * period, period)
    index = build_index3(u)
    rng = np.random.default_rng(10)
    x = rng.random((600, 3)) * period
    reach = rng.random(600) * 1.4  # up to past the diameter, 1.15
    tree = cKDTree(u, boxsize=period)
    for k in (1, 37, 2500, 5000):
        want = tree.query_ball_point(x, reach, return_length=True) >= k
        np.testing.assert_array_equal(holds_k(index, x, reach, k, period), want)


def test_tau_beyond_6_is_certified():
    """tau = 8: K = 3 (the far-corner Break's need), the initial check's first reach half a
    period (the direct count)."""
    pts = uniform(3000, 11)
    assert_certified(knnrefine.refine(pts, 10, 8.0, periodic=True, box=BOX), pts)


@pytest.mark.slow
@pytest.mark.parametrize(
    "flags, periodic",
    [(["--periodic"], True), (["--periodic-z"], (False, False, True)), ([], False)],
    ids=["torus", "z", "box"],
)
def test_command_line_in_space_writes_vtu_and_npz(tmp_path, flags, periodic):
    """knnrefine refine with three --columns and a six-number box: .vtu (ParaView: every
    tetrahedron positively oriented where its offsets put its corners, d_M2 per point) and
    .npz (read back array for array, certified again by 'knnrefine certify'); outputs the
    3-D writers lack and a five-number box are refused before work; --plot draws three
    slices of the mesh (refused before issue 29)."""
    import meshio

    from knnrefine import io
    from knnrefine.cli.main import main

    pts = multiscale(5000, 12) * 360.0
    csv = tmp_path / "chi.csv"
    np.savetxt(csv, pts, delimiter=",", header="chi1,chi2,chi3", comments="")
    box = ["--box", "0", "0", "0", "360", "360", "360"]
    args = ["refine", str(csv), "--columns", "chi1,chi2,chi3", "-k", "20", *flags, *box]
    out = [str(tmp_path / "m.vtu"), str(tmp_path / "m.npz")]
    assert main([*args, "-o", out[0], "-o", out[1], "--certify", "--quiet"]) == 0
    mesh = io.read_mesh(out[1])
    assert isinstance(mesh, Mesh) and mesh.dim == 3 and len(mesh.vertices) > 100
    again = knnrefine.refine(pts, 20, periodic=periodic, box=(0, 0, 0, 360, 360, 360))
    assert mesh.periodic == again.periodic
    for name in ("vertices", "tetrahedra", "offsets", "kinds", "order"):
        np.testing.assert_array_equal(getattr(mesh, name), getattr(again, name))
    for name in ("vertices", "tetrahedra", "offsets", "kinds"):
        np.testing.assert_array_equal(getattr(mesh.torus, name), getattr(again.torus, name))
    vtu = meshio.read(out[0])
    tets = vtu.cells_dict["tetra"]
    assert len(tets) == len(mesh.tetrahedra)
    c = vtu.points[tets]
    assert (np.linalg.det(c[:, :3] - c[:, 3:]) > 0).all()  # orient3d > 0 (module convention)
    assert np.abs(c.sum(axis=1) / 4 - mesh.corners().mean(axis=1)).max() < 1e-9
    np.testing.assert_allclose(vtu.point_data["d_m2"], mesh.d_m2(vtu.points))
    assert main(["certify", out[1], str(csv), "--columns", "chi1,chi2,chi3"]) == 0

    def code(argv):
        try:
            return main(argv)
        except SystemExit as exc:
            return exc.code

    bad = ["-o", str(tmp_path / "m.geojson")]
    assert code([*args, *bad]) == 1
    assert not os.path.exists(bad[1])
    picture = tmp_path / "m.png"
    assert code([*args, "-o", str(tmp_path / "again.npz"), "--plot", str(picture)]) == 0
    assert picture.stat().st_size > 10_000
    assert code([*args[:-6], "--box", "0", "0", "0", "360", "360"]) == 2
    plane = ["refine", str(csv), "--columns", "chi1,chi2", "-k", "5", "--box", "0", "0", "9", "9"]
    assert code([*plane, "--periodic-z"]) == 2  # z is for points in space


def _start_run(pts, k=10):
    from knnrefine._domains.space.run import holds_k
    from knnrefine._engine.driver3 import Refinement3, choose_grid3
    from knnrefine._engine.index3 import build_index3
    from knnrefine._engine.initial import reach_factor

    period = np.ones(3)
    index = build_index3(pts)
    grid = choose_grid3(period, lambda x, r: holds_k(index, x, r, k, period), reach_factor(3))
    return Refinement3(index, period, k, 3.0, 1e-6, 10**6, grid)


def _finish(run, pts, k=10):
    assert run.run() == 0  # STATUS_DONE
    xyz, corners, offsets, kinds, cnt, _, neighbours = run.take_result()
    torus = Torus(origin=(0.0,) * 3, period=(1.0,) * 3, vertices=xyz, cells=corners,
                  offsets=offsets, kinds=kinds, neighbours=neighbours)  # fmt: skip
    return Mesh(vertices=xyz, cells=corners, offsets=offsets, kinds=kinds,
                order=np.arange(len(xyz)), k=k, tau=3.0, periodic=(True,) * 3, box=BOX,
                min_size=1e-6, floor_points=np.zeros((0, 3)), stats={"n": len(pts)},
                torus=torus)  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("steps", [1, 700, 3000])
def test_every_untested_circumball_is_queued_at_one_of_its_corners(steps):
    """The circumball queue holds vertices: each untested tetrahedron has a corner queued at
    its size class or a larger ball's, so none is forgotten; and the queue holds at most an
    entry per vertex beyond the initial mesh's (not one per tetrahedron). Then the run
    finishes certified."""
    from knnrefine._engine.jit import python_entry
    from knnrefine._engine.queue import N_CLASSES, size_class
    from knnrefine._engine.refine import UNTESTED
    from knnrefine._engine.refine3 import refine_steps3

    classify = python_entry(size_class)
    pts = multiscale(20000, 13)
    run = _start_run(pts)
    nt0 = int(run.cnt[1])
    refine_steps3(run.mesh, run.book, run.queues, run.scratch, run.probe, run.cnt, run.prm,
                  run.index, steps)  # fmt: skip
    q = run.queues.balls
    due = {}  # vertex -> the largest class it is queued at (the smallest number)
    size = 0
    for c in range(N_CLASSES):
        e = q.head[c]
        while e >= 0:
            v = int(q.ident[e])
            due[v] = min(due.get(v, N_CLASSES), c)
            size += 1
            e = q.next[e]
    nt, nv = int(run.cnt[1]), int(run.cnt[0])
    untested = np.flatnonzero(run.book.ball_state[:nt] == UNTESTED)
    assert len(untested) > 0
    for t in untested:
        cls = classify(run.mesh.radius2[t])
        assert min(due.get(int(v), N_CLASSES) for v in run.mesh.corners[t]) <= cls, t
    assert size <= nt0 + nv
    assert_certified(_finish(run, pts), pts)


def test_mesh_independent_of_growth_policy(monkeypatch):
    """Regression: a 3-D mesh depended on when the arrays grew (the circumball queue of
    tetrahedra was purged of stale entries as it grew, and an entry for a reused slot could
    test a new tetrahedron early). With a queue of vertices nothing refers to a capacity:
    growing by 1/64 from the smallest start gives the mesh that growing by 1/8 gives."""
    from knnrefine._engine import driver3

    pts = multiscale(20000, 17)
    meshes = []
    for growth in (8, 64):
        monkeypatch.setattr(driver3, "GROWTH", growth)
        run = _start_run(pts)
        grown = []
        orig = run._grow
        monkeypatch.setattr(run, "_grow", lambda g=grown, o=orig: (g.append(1), o()))
        meshes.append(_finish(run, pts))
        assert len(grown) > 3  # it did grow, more often with the finer step
    a, b = meshes
    assert len(a.vertices) == len(b.vertices) > 2000
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.tetrahedra, b.tetrahedra)
    np.testing.assert_array_equal(a.offsets, b.offsets)


@pytest.mark.parametrize("periodic", [False, (False, True, False), (True, True, False)])
def test_boxes_not_periodic_everywhere(periodic):
    """A box away from the origin with three different sides, periodic on some or no axes:
    certified (in the box's own metric); d_M2 in the box equals a brute kd-tree's over the
    returned vertices (straight along non-periodic axes); the returned tetrahedra are copies
    that meet the box, and their vertices lie on the grid (local exact)."""
    box = (-2.0, 10.0, 0.5, 0.0, 11.0, 3.5)
    lo, hi = np.array(box[:3]), np.array(box[3:])
    pts = lo + multiscale(8000, 14) * (hi - lo)
    mesh = knnrefine.refine(pts, 20, periodic=periodic, box=box)
    assert_certified(mesh, pts)
    per = np.array(mesh.periodic)
    t = mesh.torus
    assert mesh.stats["m_torus"] == len(t.vertices) < mesh.stats["m"] * 2
    q = lo + np.random.default_rng(15).random((3000, 3)) * (hi - lo)
    frame = torus_frame(mesh)
    tree = cKDTree(frame(mesh.vertices), boxsize=np.where(per, hi - lo, 0.0))
    want = tree.query(frame(q), k=2)[0][:, 1]
    np.testing.assert_allclose(mesh.d_m2(q), want, rtol=1e-12)
    c = mesh.corners()
    meets = ((c.max(axis=1) >= lo) & (c.min(axis=1) <= hi)) | per
    assert meets.all()
    # each vertex a torus vertex moved by whole periods, exactly (on the engine's grid)
    origin, period = np.array(t.origin), np.array(t.period)
    shift = (mesh.vertices - origin - t.vertices[mesh.order]) / period
    np.testing.assert_array_equal(shift, np.rint(shift))


def test_default_box_is_the_points_bounding_box():
    pts = multiscale(3000, 16) * [2.0, 1.0, 0.5]
    mesh = knnrefine.refine(pts, 10)
    np.testing.assert_array_equal(mesh.box, [*pts.min(axis=0), *pts.max(axis=0)])
    assert mesh.periodic == (False, False, False) and mesh.offsets is None
    assert_certified(mesh, pts)


def test_certify_fails_a_box_mesh_missing_its_copies():
    """The returned vertices must hold, near the box, every copy that can be among the two
    nearest: a mesh missing one fails (the copies' check), as does a copy moved off its
    torus vertex's place."""
    pts = uniform(3000, 17)
    mesh = knnrefine.refine(pts, 10, periodic=False, box=BOX)
    assert knnrefine.certify(mesh, pts).passed
    v = mesh.vertices
    inside = np.flatnonzero(((v >= 0) & (v <= 1)).all(axis=1))
    keep = np.ones(len(v), bool)
    keep[inside[0]] = False
    renumber = np.cumsum(keep) - 1  # the cells without that vertex, renumbered
    kept = ~np.isin(mesh.cells, inside[0]).any(axis=1)
    fewer = dataclasses.replace(mesh, order=mesh.order[keep], vertices=v[keep],
                                kinds=mesh.kinds[keep], cells=renumber[mesh.cells[kept]],
                                offsets=None)  # fmt: skip
    cert = knnrefine.certify(fewer, pts)
    assert not cert.passed and any("d_M2" in p for p in cert.mesh_problems)
    assert any("hole" in p for p in cert.mesh_problems)
    moved = v.copy()
    moved[inside[1], 0] += 1e-9
    cert = knnrefine.certify(dataclasses.replace(mesh, vertices=moved), pts)
    assert not cert.passed and "1 vertices differ from their torus vertex" in cert.mesh_problems


@pytest.mark.parametrize("periodic", [False, (True, False, True)])
def test_unfolding_in_space_keeps_every_copy_the_box_needs(periodic):
    """embedding.unfold in space (its passes on the engine's threads) against a brute numpy
    oracle on the torus mesh: the tetrahedron copies (shifts -1..1 along non-periodic axes)
    whose bounding boxes meet the box, and every vertex copy within r* (the longest kept
    edge) of the box, each exactly once."""
    pts = multiscale(5000, 18)
    mesh = knnrefine.refine(pts, 10, periodic=periodic, box=BOX)
    assert_unfolding_keeps_every_copy(mesh, BOX)


def test_restarting_the_32_bit_stamps_changes_nothing(monkeypatch):
    """The tetrahedra's marks are 32-bit stamps that the driver restarts past STAMP_LIMIT
    (clearing the marks but the free slots' and the link table): restarted after every
    call of 50 insertions, the run gives the same mesh, array for array."""
    from knnrefine._engine import driver3

    pts = multiscale(4000, 19)
    want = knnrefine.refine(pts, 10, periodic=True, box=BOX)
    restarts = []
    original = driver3.Refinement3._restart_stamps

    def counted(self):
        restarts.append(int(self.cnt[driver3.C_STAMP]))
        original(self)

    monkeypatch.setattr(driver3, "STEPS", 50)
    monkeypatch.setattr(driver3, "STAMP_LIMIT", 10)
    monkeypatch.setattr(driver3.Refinement3, "_restart_stamps", counted)
    got = knnrefine.refine(pts, 10, periodic=True, box=BOX)
    assert len(restarts) > 20
    for name in ("vertices", "tetrahedra", "offsets", "kinds"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))


def test_growing_in_place_keeps_the_rows_and_zero_fills():
    """state.grow(in_place=True) (the 3-D run's growth) keeps every row and zero-fills the
    new ones: an array not yet in a mapping is copied into one, one in a mapping grows in
    that same mapping (moved, not copied), and one whose view is held elsewhere is copied
    into a new mapping, the view still reading the old rows; nested fields (a queue's)
    too."""
    from types import SimpleNamespace

    from knnrefine._engine.state import Queue, _mapping, grow

    for rows in (6, 3_000_000):
        owner = SimpleNamespace(s=Queue(head=None, ident=None, aux=None, next=None,
                                        scalars=np.arange(rows * 4, dtype=np.int32)
                                        .reshape(rows, 4)))  # fmt: skip
        sizes = [rows + rows // 4 + 3, 2 * rows + 5, 3 * rows]
        for step, size in enumerate(sizes):
            before = _mapping(owner.s.scalars)
            if step == 2:
                view = owner.s.scalars[:2]
            grow(owner, [("s", "scalars")], size, in_place=True)
            got = owner.s.scalars
            assert got.shape == (size, 4) and got.dtype == np.int32
            np.testing.assert_array_equal(got[:rows].ravel(), np.arange(rows * 4))
            assert not got[rows:].any()
            assert _mapping(got) is not None
            assert (_mapping(got) is before) == (step == 1)  # grown in its own mapping
            del got  # (a view held here would make the next step copy)
        np.testing.assert_array_equal(view.ravel(), np.arange(8))
    holder = SimpleNamespace(
        queues=Queue(
            head=None,
            ident=None,
            aux=None,
            next=None,
            scalars=Queue(head=None, ident=np.arange(5.0), aux=None, next=None, scalars=None),
        )
    )
    grow(holder, [("queues", "scalars", "ident")], 9, in_place=True)
    np.testing.assert_array_equal(holder.queues.scalars.ident, [0, 1, 2, 3, 4, 0, 0, 0, 0])


@pytest.mark.slow
def test_growing_without_mremap_or_mappings_copies(monkeypatch):
    """Where a mapping cannot move (macOS has no mremap: resize raises SystemError) growth
    copies the rows into a new mapping; where the system has no anonymous mappings
    (Windows) ``mapped`` gives plain arrays and growth copies them. Either way the rows are
    kept and a run that grows gives the same mesh."""
    from collections import namedtuple
    from types import SimpleNamespace

    from knnrefine._engine import driver3, state

    def cannot(mm, nbytes):
        raise SystemError("mmap: resizing not available--no mremap()")

    holder = namedtuple("Holder", ["a"])
    pts = multiscale(20000, 22)
    want = knnrefine.refine(pts, 10, box=BOX)
    for patch in ("_resize", "_PRIVATE"):
        with monkeypatch.context() as m:
            m.setattr(state, patch, cannot if patch == "_resize" else None)
            owner = SimpleNamespace(s=holder(a=state.mapped((5, 2), np.int64)))
            owner.s.a[:] = np.arange(10).reshape(5, 2)
            before = state._mapping(owner.s.a)
            state.grow(owner, [("s", "a")], 8, in_place=True)
            np.testing.assert_array_equal(owner.s.a[:5].ravel(), np.arange(10))
            assert owner.s.a.shape == (8, 2) and not owner.s.a[5:].any()
            assert (state._mapping(owner.s.a) is None) == (patch == "_PRIVATE")
            assert before is None or state._mapping(owner.s.a) is not before  # copied
            grown = []

            def counted(*args, grown=grown, **kwargs):
                grown.append(1)
                state.grow(*args, **kwargs)

            m.setattr(driver3, "grow", counted)
            got = knnrefine.refine(pts, 10, box=BOX)
            assert len(grown) > 2
        np.testing.assert_array_equal(got.vertices, want.vertices)
        np.testing.assert_array_equal(got.tetrahedra, want.tetrahedra)


def test_the_data_bound_on_d_pk_is_computed_only_when_the_default_torus_fails(monkeypatch):
    """run3.Start3 tries the default margin first and builds the data bound on max d_Pk (a
    kd-tree over all points) only if that torus cannot start; the bound is >= d_Pk at 20,000
    random points of the box (a brute kd-tree, straight metric)."""
    from knnrefine._domains.space import run as api3
    from knnrefine._engine.initial import reach_factor
    from knnrefine._engine.interrupt import Interrupts
    from knnrefine._options import RunOptions

    def start(pts, box, per, k, tau):
        opt = RunOptions.check(len(pts), None, lambda: box, lambda b, p: None, k=k, tau=tau,
                               periodic=per, box=box, dim=3)  # fmt: skip
        return api3.Start(pts, opt, 10**6, Interrupts()).find(k, reach_factor(tau))

    pts = multiscale(3000, 20)
    calls = []
    original = api3._reach

    def counted(*args):
        calls.append(original(*args))
        return calls[-1]

    monkeypatch.setattr(api3, "_reach", counted)
    assert start(pts, BOX, (False,) * 3, 10, 3.0) is not None
    assert calls == []  # the default torus started: no kd-tree built
    choose = api3.choose_grid3
    tries = []

    def first_fails(*args):
        tries.append(args[0])
        return None if len(tries) == 1 else choose(*args)

    monkeypatch.setattr(api3, "choose_grid3", first_fails)
    emb = start(pts, BOX, (False,) * 3, 10, 3.0)[0]
    assert len(calls) == 1 and len(tries) == 2
    q = np.random.default_rng(21).random((20_000, 3))
    assert calls[0] >= cKDTree(pts).query(q, k=[10])[0].max()
    np.testing.assert_allclose(emb.period, 1.0 + 1.05 * calls[0], rtol=1e-6)


@pytest.mark.parametrize("periodic", [True, False])
def test_the_counting_index_lives_on_only_in_the_mesh(monkeypatch, periodic):
    """Regression: the tuple run3's start returned kept the counting index (28 bytes a point)
    alive until refine3 returned, through the unfolding, where an ordinary box's run then
    peaked. The mesh now keeps the index on purpose (``Mesh.index``: a continued run grows
    it instead of building it again, as in the plane), so it lives through the unfolding,
    but nothing else holds it: every array of it is gone with the mesh."""
    import gc
    import weakref

    from knnrefine._domains.space import run as api3

    refs = []
    build = api3.build_index3

    def built(*args, **kwargs):
        index = build(*args, **kwargs)
        refs.extend(weakref.ref(a) for a in index)
        return index

    monkeypatch.setattr(api3, "build_index3", built)
    pts = multiscale(3000, 21)
    mesh = knnrefine.refine(pts, 10, periodic=periodic, box=BOX)
    assert len(refs) == 5 and all(r() is a for r, a in zip(refs, mesh.index.index, strict=True))
    gc.collect()
    assert len(gc.get_referrers(mesh.index.index)) == 1  # the mesh's PointIndex alone


@pytest.mark.parametrize("kind", ["uniform", "clustered", "coplanar", "duplicates"])
def test_sweeps_count_in_bulk_and_change_no_move(kind):
    """The bulk counts (``refine3.sweep_balls3``, ``sweep_cells3`` on two threads) only
    settle elements the refinement would find settled when it pops them: the run with them
    makes exactly the mesh of the run without (one thread, no sweep), vertex by vertex, on
    random, clustered and degenerate points (all on the torus' seam z = 0; each four
    times), and in uniform points they take a good part of the counting off the sequential
    path."""
    from knnrefine._engine.state import C_CELL_TESTS, C_DISK_TESTS

    rng = np.random.default_rng(31)
    pts = rng.random((20000, 3)) if kind == "uniform" else multiscale(20000, 31)
    if kind == "coplanar":  # every point on the plane z = 0, the torus' seam
        pts = pts[:8000].copy()
        pts[:, 2] = 0.0
    elif kind == "duplicates":  # each point four times
        pts = np.repeat(pts[:2500], 4, axis=0)
    made = {}
    for threads in (1, 2):
        run = _start_run(pts)
        run.threads = threads
        swept = []

        def sweep(run=run, plain=run._sweep, swept=swept):
            before = int(run.cnt[C_DISK_TESTS] + run.cnt[C_CELL_TESTS])
            status = plain()
            swept.append(int(run.cnt[C_DISK_TESTS] + run.cnt[C_CELL_TESTS]) - before)
            return status

        run._sweep = sweep
        mesh = _finish(run, pts)
        made[threads] = (mesh, swept, int(run.cnt[C_DISK_TESTS] + run.cnt[C_CELL_TESTS]))
    (one, swept1, tests1), (two, swept2, tests2) = made[1], made[2]
    assert swept1 == [] and len(swept2) >= (5 if kind in ("uniform", "clustered") else 1)
    np.testing.assert_array_equal(one.vertices, two.vertices)
    np.testing.assert_array_equal(one.cells, two.cells)
    if kind == "uniform":  # the sequential path counted at most 3/4 of what it counts alone
        assert tests2 - sum(swept2) <= 0.75 * tests1
    elif kind == "clustered":  # scales mixed in every class: the samples stop most sweeps
        # (a loss of 1/16 at most)
        assert sum(swept2) <= tests1 / 8 and tests2 <= 1.0625 * tests1
    assert_certified(two, pts)
