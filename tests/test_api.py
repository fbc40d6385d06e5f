"""The public API: accepted inputs, clear errors, the Mesh it returns."""

import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

import knnrefine
from knnrefine import BudgetError, InputError


def signed_area2(corners):
    e1 = corners[:, 1] - corners[:, 0]
    e2 = corners[:, 2] - corners[:, 0]
    return e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]


@pytest.fixture(scope="module")
def points():
    return np.random.default_rng(0).random((500, 2)) * [4.0, 2.0]


def test_accepts_lists_float32_ints_and_frames(points):
    ref = knnrefine.refine(points, 5)
    same = knnrefine.refine(points.tolist(), 5)
    np.testing.assert_array_equal(ref.vertices, same.vertices)
    m32 = knnrefine.refine(points.astype(np.float32), 5)
    assert len(m32.vertices) > 0
    ints = np.round(points * 100).astype(np.int64)
    assert len(knnrefine.refine(ints, 5).vertices) > 0
    pd = pytest.importorskip("pandas")
    frame = pd.DataFrame(points, columns=["lon", "lat"])
    np.testing.assert_array_equal(knnrefine.refine(frame, 5).vertices, ref.vertices)


def test_mesh_contents(points):
    mesh = knnrefine.refine(points, 10, 3.0)
    m = len(mesh.vertices)
    assert mesh.vertices.shape == (m, 2) and mesh.vertices.dtype == np.float64
    assert mesh.triangles.ndim == 2 and mesh.triangles.shape[1] == 3
    assert mesh.triangles.min() >= 0 and mesh.triangles.max() < m
    assert mesh.offsets is None
    assert mesh.kinds.shape == (m,) and set(np.unique(mesh.kinds)) <= {0, 1, 2, 3}
    assert np.all(np.diff(mesh.order) >= 0)
    assert (mesh.k, mesh.tau, mesh.periodic) == (10, 3.0, (False, False))
    assert mesh.box == tuple(points.min(0)) + tuple(points.max(0))
    a, b = knnrefine.theorem6_constants(3.0)
    assert (mesh.alpha, mesh.beta) == (a, b)
    assert np.isclose(a, 1 / 13) and np.isclose(b, 35.97, atol=0.01)
    st = mesh.stats
    assert sum(st["moves"].values()) == st["m_torus"]
    assert st["moves"]["break_circumball"] > 0
    assert set(st["time"]) >= {"setup", "refine", "assemble", "total"}
    # triangles are counter-clockwise
    c = mesh.vertices[mesh.triangles]
    cross = signed_area2(c)
    assert np.all(cross > 0)
    assert "Mesh" in repr(mesh)


def test_periodic_mesh_is_the_whole_torus(points):
    box = (0.0, 0.0, 4.0, 2.0)
    mesh = knnrefine.refine(points, 10, periodic=True, box=box)
    assert mesh.offsets.shape == mesh.triangles.shape + (2,)
    assert len(mesh.triangles) == 2 * len(mesh.vertices)
    assert np.all((mesh.vertices >= [0, 0]) & (mesh.vertices < [4, 2]))
    c = mesh.vertices[mesh.triangles] + mesh.offsets * np.array(mesh.period)
    cross = signed_area2(c)
    assert np.all(cross > 0)
    assert np.isclose(0.5 * cross.sum(), 8.0)  # the triangles tile the torus
    # d_{M,2} is periodic
    q = np.random.default_rng(1).random((100, 2)) * [4, 2]
    np.testing.assert_allclose(mesh.d_m2(q), mesh.d_m2(q + [4.0, -2.0]))
    np.testing.assert_allclose(
        mesh.d_m2(q), cKDTree(mesh.vertices, boxsize=[4, 2]).query(q, 2)[0][:, 1]
    )


def test_points_are_wrapped_into_a_periodic_box():
    rng = np.random.default_rng(2)
    pts = rng.random((300, 2)) * 360 - 180
    a = knnrefine.refine(pts, 5, periodic=True, box=(-180, -180, 180, 180))
    b = knnrefine.refine(pts + [360, -720], 5, periodic=True, box=(-180, -180, 180, 180))
    np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-9)


def test_partially_periodic(points):
    mesh = knnrefine.refine(points, 10, periodic=(True, False), box=(0, 0, 4, 2))
    assert mesh.periodic == (True, False)
    assert np.all(mesh.offsets[..., 1] == 0)
    assert np.all((mesh.vertices[:, 0] >= 0) & (mesh.vertices[:, 0] < 4))
    assert mesh.period == (4.0, 0.0)


def test_deterministic(points):
    a = knnrefine.refine(points, 7, 3.5)
    b = knnrefine.refine(points, 7, 3.5)
    for name in ("vertices", "triangles", "kinds", "order"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_deterministic_across_processes(points, tmp_path):
    np.save(tmp_path / "p.npy", points)
    code = (
        "import numpy as np, knnrefine, sys; p = np.load(sys.argv[1]); "
        "m = knnrefine.refine(p, 7, 3.5); np.save(sys.argv[2], m.vertices)"
    )
    for name in ("a.npy", "b.npy"):
        subprocess.run(
            [sys.executable, "-c", code, str(tmp_path / "p.npy"), str(tmp_path / name)], check=True
        )
    np.testing.assert_array_equal(np.load(tmp_path / "a.npy"), np.load(tmp_path / "b.npy"))
    np.testing.assert_array_equal(
        np.load(tmp_path / "a.npy"), knnrefine.refine(points, 7, 3.5).vertices
    )


@pytest.mark.parametrize(
    "bad, message",
    [
        ([[0.0, np.nan], [1.0, 1.0]], "NaN or infinite"),
        ([[0.0, 1.0], [np.inf, 1.0], [2.0, np.inf]], "2 row"),
        (np.zeros((0, 2)), "empty"),
        (np.zeros((5, 4)), "shape"),  # (n, 3) is a run in space (test_refine3)
        (np.zeros(6), "shape"),
        ([["a", "b"], ["c", "d"]], "numeric"),
        ([[1, 2], [3]], "could not be read"),
        ([[1 + 1j, 2], [3, 4]], "complex"),
    ],
)
def test_bad_points(bad, message):
    with pytest.raises(InputError, match=message):
        knnrefine.refine(bad, 2)


def test_nan_message_names_the_first_index():
    pts = np.random.default_rng(0).random((10, 2))
    pts[7, 1] = np.nan
    with pytest.raises(ValueError, match="index 7"):
        knnrefine.refine(pts, 2)


@pytest.mark.parametrize(
    "kw, message",
    [
        ({"k": 0}, "k must be an integer >= 1"),
        ({"k": 2.5}, "k must be a whole number"),
        ({"k": True}, "k must be an integer"),
        ({"k": "3"}, "k must be an integer"),
        ({"tau": 2.0}, "tau must be > 2"),
        ({"tau": 1.0}, "tau must be > 2"),
        ({"tau": float("nan")}, "tau must be a finite number"),
        ({"periodic": True}, "needs box"),
        ({"periodic": "yes"}, "periodic must be"),
        ({"box": (0, 0, 0, 1)}, "zero or negative width"),
        ({"box": (0, 0, 1)}, "four"),
        ({"box": (0.2, 0.2, 0.5, 0.5)}, "outside the box"),
        ({"min_size": -1.0}, "min_size"),
        ({"max_vertices": 0}, "max_vertices"),
    ],
)
def test_bad_parameters(points, kw, message):
    args = {"k": 3, **kw}
    k = args.pop("k")
    with pytest.raises(InputError, match=message):
        knnrefine.refine(points / 4.0, k, **args)


def test_elongated_periodic_boxes():
    rng = np.random.default_rng(8)
    pts = rng.random((2000, 2)) * [100.0, 1.0]
    mesh = knnrefine.refine(pts, 10, periodic=True, box=(0, 0, 100, 1))
    assert mesh.stats["moves"]["initial"] == 400 * 4  # spacing a quarter of the short period
    with pytest.raises(InputError, match="too elongated"):
        knnrefine.refine(pts, 10, periodic=True, box=(0, 0, 1e6, 1))


def test_numpy_integer_k_is_fine(points):
    assert len(knnrefine.refine(points, np.int64(5)).vertices) > 0


def test_max_vertices_budget_ends_a_runaway_refinement():
    # ten coincident points with k = 3: d_{P,k} is 0 there; without a floor this never ends
    pts = np.concatenate([np.random.default_rng(3).random((50, 2)), np.zeros((10, 2)) + 0.5])
    # far below what the run needs: refused before any work
    with pytest.raises(BudgetError, match="far beyond max_vertices=200") as info:
        knnrefine.refine(pts, 3, min_size=0.0, max_vertices=200)
    assert info.value.progress["vertices"] == 0
    # somewhat below (it needs about 950): the run starts and stops at the budget
    with pytest.raises(BudgetError, match="max_vertices=600") as info:
        knnrefine.refine(pts, 3, min_size=0.0, max_vertices=600)
    assert info.value.progress["vertices"] >= 600


def test_time_limit_budget():
    pts = np.random.default_rng(4).random((200_000, 2))
    with pytest.raises(BudgetError, match="time_limit"):
        knnrefine.refine(pts, 2, time_limit=0.05)


def test_progress_callback(points):
    seen = []
    knnrefine.refine(points, 2, progress=lambda v, pending: seen.append((v, pending)))
    assert seen and seen[-1][0] > 0


def test_one_point_and_fewer_points_than_k():
    one = knnrefine.refine([[0.5, 0.5]], 1, min_size=1e-3)
    assert len(one.vertices) > 0
    with pytest.raises(InputError, match="larger than the number of points, 5: .*k <= 5"):
        knnrefine.refine(np.random.default_rng(5).random((5, 2)), 10)


def test_collinear_default_box_is_widened():
    pts = np.stack([np.linspace(0, 1, 50), np.zeros(50)], 1)
    mesh = knnrefine.refine(pts, 3)
    xmin, ymin, xmax, ymax = mesh.box
    assert (xmin, xmax) == (0.0, 1.0) and np.isclose(ymax - ymin, 1.0)


def test_demo_data_ships_with_the_package():
    angles = knnrefine.datasets.trp_chi1_chi2()
    assert angles.shape == (18748, 2)
    assert angles.min() >= 0 and angles.max() < 360


def test_refine_has_a_default_k(dim):
    """Issue 30: refine without k uses sqrt(n) / 2 (at least 10, at most n; of the total
    weight with weights), the rule knnrefine.density.default_k states, in both dimensions."""
    from knnrefine.density import default_k

    rng = np.random.default_rng(0)
    pts = rng.random((4000, dim))
    assert knnrefine.refine(pts).k == default_k(4000) == 32
    assert knnrefine.refine(pts[:30]).k == 10 and knnrefine.refine(pts[:7]).k == 7
    w = np.full(4000, 2.5)
    assert knnrefine.refine(pts, weights=w).k == default_k(10000) == 50
