"""Tiles in threads, stitched (``scale/shared.py``, ``_engine/stitch.py``): the stitch against
the mesh it should give back, its refusals, and the runs through it against certify."""

import os
import subprocess
import sys
import textwrap
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import as_tile, assert_certified, gaussian_clusters, simplices_of, uniform

import knnrefine
from knnrefine._engine import state as S
from knnrefine._engine.driver import Refinement
from knnrefine._engine.index import build_index
from knnrefine.scale import shared

pytestmark = pytest.mark.usefixtures("tiles_always")  # the tiles at every size


def refined(n=4000, k=10, seed=3):
    """A finished run on the unit torus, in this process."""
    run = Refinement(build_index(uniform(n, seed).copy()), k, 1.0, 1.0, 3.0, 0.0, 10**6)
    assert run.run() == S.STATUS_DONE
    return run


def test_stitching_two_complete_meshes_gives_the_mesh_back():
    """Two tiles that both hold the whole mesh (their areas the whole torus) hand in the
    triangles of their cores (x < 0.3 or >= 0.7, and the rest): the stitched triangulation
    is the mesh's own, triangle for triangle, with every neighbour across the matching edge,
    and the circumballs' and cells' settled states carried."""
    run = refined()
    nv, nt = run.vertices, int(run.cnt[S.C_NT])
    whole = (0.0, 0.0, 1.0, 1.0, 1)
    tiles = [as_tile(run, 0, whole), as_tile(run, 1, whole)]
    bounds = np.array([0.3, 0.7])  # core 0: [0.3, 0.7), core 1: [0.7, 1.3)
    data = np.array([0.0, 0.0, 1.0, 1.0])
    vertices = SimpleNamespace(count=nv)
    got = shared.stitch(tiles, bounds, 0, [1, 0], data, vertices)
    assert got is not None
    corners, offsets, neighbours, balls, cells, (radius2, nearest2, known) = got
    mesh = run.mesh
    assert simplices_of(corners, offsets) == simplices_of(mesh.corners[:nt], mesh.offsets[:nt])
    for t in range(len(corners)):  # the neighbour across edge i holds it the other way round
        for i in range(3):
            a, b = corners[t, (i + 1) % 3], corners[t, (i + 2) % 3]
            n = neighbours[t, i]
            edges = {(corners[n, (j + 1) % 3], corners[n, (j + 2) % 3]) for j in range(3)}
            assert (b, a) in edges
    assert (balls == S.GOOD).all()  # a finished run settled every circumball
    np.testing.assert_array_equal(cells, run.book.cell_state[:nv] == S.GOOD)  # vertex by vertex
    assert known.all()  # every star lies in the whole torus: the caches are the run's
    np.testing.assert_array_equal(nearest2, mesh.nearest2[:nv])
    assert np.isclose(np.sort(radius2), np.sort(mesh.radius2[:nt]), rtol=1e-12).all()


def test_stitch_refuses_what_a_tile_cannot_vouch_for():
    """A tile whose area is narrower than the disks of its share's triangles (here a tenth
    of the torus around its core) cannot vouch for them: no stitch, but how far past each
    tile's area its disks reach (the run widens those tiles' areas and tries again)."""
    run = refined()
    tiles = [as_tile(run, 0, (0.0, 0.0, 1.0, 1.0, 1)), as_tile(run, 1, (0.65, 0.0, 0.1, 1.0, 1))]
    got = shared.stitch(tiles, np.array([0.3, 0.7]), 0, [1, 0], np.array([0.0, 0.0, 1.0, 1.0]),
                        SimpleNamespace(count=run.vertices))  # fmt: skip
    assert isinstance(got, list)
    assert got[0] == 0.0 and got[1] > 0.0  # the first tile's area is the whole torus
    assert got[1] <= np.sqrt(run.mesh.radius2[: int(run.cnt[S.C_NT])].max())


def test_a_tile_under_the_reach_rule_vouches_for_its_whole_share():
    """A tile whose area's flag is -1 holds, by the reach rule, every vertex whose star
    reaches its region: the stitch takes its share whatever the box (the same narrow one
    as above), and the mesh comes back whole."""
    run = refined()
    nt = int(run.cnt[S.C_NT])
    tiles = [as_tile(run, 0, (0.0, 0.0, 1.0, 1.0, 1)), as_tile(run, 1, (0.65, 0.0, 0.1, 1.0, -1))]
    got = shared.stitch(tiles, np.array([0.3, 0.7]), 0, [1, 0], np.array([0.0, 0.0, 1.0, 1.0]),
                        SimpleNamespace(count=run.vertices))  # fmt: skip
    assert isinstance(got, tuple)
    assert simplices_of(got[0], got[1]) == simplices_of(run.mesh.corners[:nt],
                                                        run.mesh.offsets[:nt])  # fmt: skip


def test_outradii_are_the_largest_circumradius_at_each_vertex():
    """``Refinement.outradii``, the reach rule's bound on R(v), against the triangles:
    the largest circumradius among the triangles at v, exactly (the plane's cache is R(v)
    itself)."""
    run = refined()
    nv, nt = run.vertices, int(run.cnt[S.C_NT])
    outer = np.full(nv, -1.0)
    corners = run.mesh.corners[:nt]
    np.maximum.at(outer, corners.ravel(), np.repeat(run.mesh.radius2[:nt], 3))
    np.testing.assert_array_equal(run.outradii(), np.sqrt(outer))


def test_distance_to_a_box_on_the_torus():
    """``shared.distance_to`` against the nearest of the box's periodic copies (the box
    clipped per axis)."""
    rng = np.random.default_rng(4)
    period = (1.0, 2.0)
    x = rng.random((500, 2)) * period
    box = np.array([0.8, 0.5, 0.4, 0.3, 1])  # wraps across x = 1
    got = shared.distance_to(x, box, period)
    best = np.full(len(x), np.inf)
    for sx in (-1, 0, 1):
        for sy in (-1, 0, 1):
            y = x + np.array([sx, sy]) * period
            gap = np.maximum(np.maximum(box[:2] - y, 0.0), y - (box[:2] + box[2:4]))
            best = np.minimum(best, np.hypot(gap[:, 0], gap[:, 1]))
    np.testing.assert_allclose(got, best, atol=1e-12)
    band = np.array([0.0, 0.5, 1.0, 1.0, 1])  # the whole period along x: a band in y
    gap = np.maximum(np.maximum(0.5 - x[:, 1], x[:, 1] - 1.5), 0.0)
    np.testing.assert_allclose(shared.distance_to(x, band, period), gap)


def test_join_refuses_an_edge_without_its_twin():
    """The join of two shares: an edge whose twin is missing (a triangle dropped) fails."""
    corners = np.array([[0, 1, 2], [2, 1, 3]], np.int32)
    offsets = np.zeros((2, 3, 2), np.int8)
    neighbours = np.full((2, 3), -1, np.int32)
    t, i = np.nonzero(neighbours < 0)
    assert not shared._join(t, i, corners, offsets[t], neighbours)  # outer edges: no twins
    neighbours = np.full((2, 3), -1, np.int32)
    t, i = np.array([0, 1]), np.array([0, 2])  # the shared edge 1-2, both ways
    assert shared._join(t, i, corners, offsets[t], neighbours)
    assert neighbours[0, 0] == 1 and neighbours[1, 2] == 0


@pytest.mark.parametrize(
    ("name", "points", "periodic"),
    [
        ("uniform", lambda: uniform(60000, 1), False),
        ("clustered", lambda: gaussian_clusters(60000, 2, clusters=40), False),
        ("uniform, torus", lambda: uniform(60000, 3), True),
        (
            "clustered, periodic in x",
            lambda: gaussian_clusters(60000, 4, clusters=40),
            (True, False),
        ),
    ],
)
def test_runs_in_threads_are_stitched_and_certified(name, points, periodic):
    """Issue 32: a run in two threads keeps its tiles' meshes and stitches them (no
    re-triangulation), certified, its size within 3% of one process'."""
    pts = points()
    box = (0, 0, 1, 1) if periodic is not False else None
    mesh = knnrefine.refine(pts, 10, workers=2, periodic=periodic, box=box)
    last = mesh.stats["rounds"][-1]
    assert last["stitched"], (name, last)
    assert_certified(mesh, pts, f"threads, {name}")
    one = knnrefine.refine(pts, 10, periodic=periodic, box=box)
    assert abs(len(mesh.vertices) / len(one.vertices) - 1) < 0.03


def test_a_stitch_that_fails_falls_back_to_one_mesh(monkeypatch):
    """When the shares do not join, the run's vertices (valid moves all) are inserted into
    one mesh and refinement goes on there: the same guarantees."""
    monkeypatch.setattr(shared, "stitch", lambda *args: None)
    pts = gaussian_clusters(30000, 5, clusters=40)
    mesh = knnrefine.refine(pts, 10, workers=2)
    assert mesh.stats["rounds"][-1]["stitched"] is False
    assert_certified(mesh, pts, "threads, stitch refused")


def test_progress_is_reported_while_the_tiles_refine():
    """The strips' turn is most of the run: progress comes every ~50 ms from this thread
    while the tiles work, with growing counts."""
    import threading

    seen = []

    def progress(vertices, pending, phase="refining"):
        seen.append((vertices, phase, threading.current_thread() is threading.main_thread()))

    knnrefine.refine(uniform(300000, 7), 5, workers=2, progress=progress)
    refining = [v for v, phase, _ in seen if phase == "refining"]
    assert all(main for _, _, main in seen)
    assert len(refining) >= 5 and refining[-1] > refining[0]


def test_ctrl_c_stops_every_tile():
    """Ctrl-C during a run in threads: a KeyboardInterrupt within a second, and the tiles'
    threads stop (the interpreter can refine again at once)."""
    script = """
        import os, signal, threading, time
        import numpy as np
        import knnrefine
        knnrefine.refine(np.random.default_rng(0).random((5000, 2)), 3, workers=2)  # warm
        pts = np.random.default_rng(1).random((1000000, 2))
        sent = []
        def interrupt():
            sent.append(time.perf_counter())
            os.kill(os.getpid(), signal.SIGINT)
        threading.Timer(1.0, interrupt).start()
        try:
            knnrefine.refine(pts, 2, workers=2)
            print("not interrupted")
        except KeyboardInterrupt:
            print("interrupted after", time.perf_counter() - sent[0])
        t0 = time.perf_counter()
        mesh = knnrefine.refine(np.random.default_rng(2).random((3000, 2)), 5, workers=2)
        print("still works", len(mesh.vertices) > 0, time.perf_counter() - t0)
    """
    out = subprocess.run(
        [sys.executable, "-c", "import signal\nsignal.signal(signal.SIGINT, "
         "signal.default_int_handler)\n" + textwrap.dedent(script)],
        capture_output=True, text=True, timeout=300, env=dict(os.environ),
    )  # fmt: skip
    assert "interrupted after" in out.stdout and "still works True" in out.stdout, (
        out.stdout + out.stderr
    )
    assert float(out.stdout.split("interrupted after")[1].split()[0]) < 1.0


def test_stitched_outradii_are_their_triangles_circumradii_bit_for_bit():
    """regression (a stitched run of points on a cross, on the torus, made 4,744 vertices
    where one process makes 2,007, aspect 4.3 and vertices a grid step apart): R(v)^2 was
    carried from the tile holding v's star while the circumradii came from the tiles
    holding the triangles, computed in other frames, 1e-15 apart. The insertions forget
    R(v)^2 only when a leaving triangle's radius2 reaches it, so a value above all of them
    never went: the aspect stayed over tau and Clean inserted the same far corner again
    and again. R(v)^2 is now the largest radius2 at v, bit for bit."""
    from conftest import DEGENERATE

    from knnrefine._engine import driver

    made = []
    init = driver.Refinement.__init__

    def keep(self, *args, **kwargs):
        init(self, *args, **kwargs)
        if kwargs.get("caches") is not None:  # the last step's run, made from the stitch
            nt, nv = int(self.cnt[S.C_NT]), self.vertices
            made.append((self.mesh.corners[:nt].copy(), self.mesh.radius2[:nt].copy(),
                         self.mesh.outradius2[:nv].copy()))  # fmt: skip

    pts = DEGENERATE["cross"](2500, np.random.default_rng(0))
    try:
        driver.Refinement.__init__ = keep
        mesh = knnrefine.refine(pts, 12, periodic=True, box=(0, 0, 1, 1), workers=2)
    finally:
        driver.Refinement.__init__ = init
    assert mesh.stats["rounds"][-1]["stitched"]
    assert_certified(mesh, pts, "threads, cross on the torus")
    one = knnrefine.refine(pts, 12, periodic=True, box=(0, 0, 1, 1))
    assert abs(len(mesh.vertices) / len(one.vertices) - 1) < 0.03
    corners, radius2, outradius2 = made[0]  # each R(v)^2 is one of its radius2
    largest = np.full(len(outradius2), -1.0)
    np.maximum.at(largest, corners.ravel(), np.repeat(radius2, 3))
    np.testing.assert_array_equal(outradius2, largest)


@pytest.mark.parametrize("name", ["circle", "two far clusters"])
def test_hostile_inputs_are_stitched_under_the_reach_rule(name):
    """Points on a circle and two tight clusters far apart (elements of every size beside
    a cut, voids between): the tiles take what the reach rule asks, the stitch holds at its
    one try, and the mesh is certified."""
    rng = np.random.default_rng(11)
    n = 8000
    if name == "circle":
        t = rng.random(n) * 2 * np.pi
        pts = np.c_[0.5 + 0.3 * np.cos(t), 0.5 + 0.3 * np.sin(t)]
    else:
        pts = np.r_[0.01 * rng.standard_normal((n // 2, 2)) + 0.1,
                    0.01 * rng.standard_normal((n // 2, 2)) + 0.9]  # fmt: skip
    mesh = knnrefine.refine(pts, 10, workers=2)
    assert mesh.stats["rounds"][-1]["stitched"]
    assert_certified(mesh, pts, f"threads, {name}")
