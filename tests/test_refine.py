"""kNNRefine against the independent oracle, over the issue's matrix of inputs and parameters."""

import zlib

import numpy as np
import pytest
from conftest import assert_certified, load_shared
from scipy.spatial import cKDTree

import knnrefine
from knnrefine._engine import driver


def uniform(rng, n=400):
    return rng.random((n, 2)) * [3.0, 2.0] + [10.0, -5.0]


def mixture(rng, n=400):
    """Gaussian clusters whose scales differ by four orders of magnitude."""
    parts = [
        rng.normal([0, 0], 1.0, (n // 2, 2)),
        rng.normal([4, 4], 1e-2, (n // 4, 2)),
        rng.normal([-3, 4], 1e-4, (n - n // 2 - n // 4, 2)),
    ]
    return np.concatenate(parts)


def lattice(rng, n=400):
    side = int(np.sqrt(n))
    g = np.arange(side, dtype=float)
    return np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)


def collinear(rng, n=400):
    t = rng.random(n)
    return np.stack([3 * t, 1 + 2 * t], 1)


def duplicates(rng, n=400):
    """Every point three times: multiplicity < k for k >= 4 (k = 1, 2 exercise the floor)."""
    return np.repeat(rng.random((n // 3, 2)), 3, axis=0)


def boundary(rng, n=400):
    """Points on the sides and corners of the box [0, 1]^2, plus interior points."""
    s = rng.random(n // 4)
    edge = np.concatenate(
        [np.stack([s, 0 * s], 1), np.stack([s, 0 * s + 1], 1), np.stack([0 * s, s], 1)]
    )
    corners = np.array([[0, 0], [1, 0], [0, 1], [1, 1.0]])
    return np.concatenate([edge, corners, rng.random((n - len(edge) - 4, 2))])


INPUTS = {
    "uniform": uniform,
    "mixture": mixture,
    "lattice": lattice,
    "collinear": collinear,
    "duplicates": duplicates,
    "boundary": boundary,
}
MODES = [False, True, (True, False), (False, True)]


def box_for(points, periodic):
    lo = points.min(0)
    hi = points.max(0)
    pad = 0.05 * (hi - lo).max()
    return tuple(lo - pad) + tuple(hi + pad) if np.any(periodic) else None


@pytest.mark.parametrize("name", list(INPUTS))
@pytest.mark.parametrize("k", [1, 2, 10, 100])
@pytest.mark.parametrize("tau", [2.5, 3.0, 4.0, 6.0], ids=["tau2_5", "tau3", "tau4", "tau6"])
def test_matrix(name, k, tau):
    rng = np.random.default_rng(zlib.crc32(f"{name} {k} {tau}".encode()))
    n = 120 if k == 1 else 400  # k = 1 refines every point down to the floor
    points = INPUTS[name](rng, n)
    # the periodic mode cycles with tau so the whole matrix stays quick
    periodic = MODES[[2.5, 3.0, 4.0, 6.0].index(tau)]
    # boundary points sit exactly on the sides (and, when periodic, on the seam) of the box
    box = (0.0, 0.0, 1.0, 1.0) if name == "boundary" else box_for(points, periodic)
    side = np.ptp(points, axis=0).max() if box is None else max(box[2] - box[0], box[3] - box[1])
    min_size = 1e-3 * side if k <= 2 else None
    mesh = knnrefine.refine(points, k, tau, periodic=periodic, box=box, min_size=min_size)
    assert_certified(mesh, points, label=f"{name}")


@pytest.mark.parametrize("periodic", MODES)
@pytest.mark.parametrize("k", [2, 10])
def test_every_mode_at_tau3(periodic, k):
    rng = np.random.default_rng(k)
    points = mixture(rng, 600)
    mesh = knnrefine.refine(points, k, 3.0, periodic=periodic, box=box_for(points, periodic))
    assert_certified(mesh, points, label=f"mixture {periodic}")


def test_k1_is_floor_limited_everywhere():
    """d_{P,1} vanishes at every input point: refinement stops at the floor around each one,
    and the guarantee holds wherever d_{P,1} >= min_size."""
    rng = np.random.default_rng(5)
    points = rng.random((50, 2))
    mesh = knnrefine.refine(points, 1, 3.0, min_size=1e-4)
    assert mesh.stats["floor_circumballs"] > 0
    assert len(mesh.floor_points) > 0
    # every floor element sits at an input point (within the floor size)
    d, _ = cKDTree(points).query(mesh.floor_points)
    assert d.max() < 1e-3
    assert_certified(mesh, points, label="k=1 floor")


def test_multiplicity_at_least_k_terminates_and_is_flagged():
    rng = np.random.default_rng(6)
    points = np.concatenate([rng.random((300, 2)), np.repeat([[0.25, 0.75]], 12, axis=0)])
    mesh = knnrefine.refine(points, 10, 3.0)
    assert mesh.stats["floor_circumballs"] + mesh.stats["floor_cells"] > 0
    d = np.hypot(*(mesh.floor_points - [0.25, 0.75]).T)
    assert d.max() < 1e-4
    assert_certified(mesh, points, label="multiplicity 12, k=10")


def test_size_is_proportional_to_n_over_k():
    """|M| tracks the integral of 1 / d_{P,k}^2 (about 2.4 n / k for uniform data)."""
    rng = np.random.default_rng(7)
    points = rng.random((20000, 2))
    sizes = {
        k: len(knnrefine.refine(points, k, periodic=True, box=(0, 0, 1, 1)).vertices)
        for k in (10, 40, 160)
    }
    for k, m in sizes.items():
        assert 1.0 * 20000 / k < m < 5.0 * 20000 / k, sizes


REAL = {
    # file: (periodic, box) -- torsion angles are periodic; the others are planar
    "old_faithful.csv": (False, None),
    "bci_bei_trees.csv": (False, None),
    "clm_forest_fires.csv": (False, None),
    "shapley_galaxies.csv": (False, None),
    "mopsi_finland.csv": (False, None),
    "franti_s1.csv": (False, None),
    "franti_birch1.csv": (False, None),
    "franti_worms2.csv": (False, None),
    "uber_nyc_pickups_apr2014.csv": (False, None),
    "earthquakes_global_1965_2016.csv": ((True, False), (-180, -90, 180, 90)),
    "rama_top8000_phi_psi.csv": (True, (-180, -180, 180, 180)),
    "rota_top8000_trp_chi1_chi2.csv": (True, (0, 0, 360, 360)),
    "rama_sars_cov2_spike_chainB.csv": (True, (0, 0, 360, 360)),
    "delaunator_ukraine.csv": (False, None),
    "delaunator_issue44.csv": (False, None),
    "delaunator_robustness1.csv": (False, None),
    "delaunator_robustness2.csv": (False, None),
    "delaunator_robustness3.csv": (False, None),
    "delaunator_robustness4.csv": (False, None),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(REAL))
def test_real_data(name):
    points = load_shared(name)
    periodic, box = REAL[name]
    k = 10 if len(points) < 50000 else 100
    k = min(k, max(2, len(points) // 4))
    mesh = knnrefine.refine(points, k, 3.0, periodic=periodic, box=box)
    assert_certified(mesh, points, label=name.removesuffix(".csv"))


@pytest.mark.parametrize("kind", ["uniform", "clustered"])
def test_cell_sweep_leaves_the_mesh_unchanged(kind, monkeypatch):
    """Settling cells in bulk (refine.sweep_cells) is an optimisation only: the same vertices,
    in the same order, as counting every cell when it is popped."""
    rng = np.random.default_rng(5)
    if kind == "uniform":
        points = rng.random((20000, 2))
    else:
        centres = rng.random((8, 2))
        points = np.clip(centres[rng.integers(0, 8, 20000)] + rng.normal(0, 0.01, (20000, 2)), 0, 1)
    swept = knnrefine.refine(points, 5)
    monkeypatch.setattr(driver.Refinement, "SWEEP_MIN", 2**62)
    unswept = knnrefine.refine(points, 5)
    assert swept.stats["cell_tests"] != unswept.stats["cell_tests"]  # the sweep did run
    np.testing.assert_array_equal(swept.vertices, unswept.vertices)
    np.testing.assert_array_equal(swept.triangles, unswept.triangles)


@pytest.mark.parametrize("threads", ["1", "3"])
def test_threads_leave_the_mesh_unchanged(threads, monkeypatch):
    """The index is built and cells are swept by threads (engine.threads): any number of them
    gives the same mesh and the same counts as the default."""
    import knnrefine._engine.index as I

    rng = np.random.default_rng(6)
    centres = rng.random((8, 2))
    points = np.clip(centres[rng.integers(0, 8, 20000)] + rng.normal(0, 0.01, (20000, 2)), 0, 1)
    monkeypatch.setattr(I, "PARALLEL_MIN", 0)
    monkeypatch.setattr(driver.Refinement, "SWEEP_PER_THREAD", 16)
    default = knnrefine.refine(points, 5)
    monkeypatch.setenv("KNNREFINE_THREADS", threads)
    other = knnrefine.refine(points, 5)
    np.testing.assert_array_equal(default.vertices, other.vertices)
    np.testing.assert_array_equal(default.triangles, other.triangles)
    for key in ("circumball_tests", "cell_tests", "moves"):
        assert default.stats[key] == other.stats[key], key


def test_knnrefine_threads_must_be_a_number(monkeypatch):
    from knnrefine._engine.threads import workers

    monkeypatch.setenv("KNNREFINE_THREADS", "two")
    with pytest.raises(ValueError, match="KNNREFINE_THREADS"):
        workers()
    monkeypatch.setenv("KNNREFINE_THREADS", "0")
    assert workers() == 1


@pytest.mark.parametrize("workers", [1, 2])
@pytest.mark.parametrize("periodic", [False, (True, False), (False, True)])
def test_unfolding_in_threads_keeps_every_copy_the_box_needs(periodic, workers, monkeypatch):
    """embedding.unfold in the plane (its passes over cells and vertices run in ranges on
    the engine's threads) against a brute numpy oracle on the torus mesh: the triangle
    copies (shifts -1..1 along non-periodic axes) whose bounding boxes meet the box, and
    every vertex copy within r* (the longest kept edge) of the box, each exactly once; a
    tenth of the points on one line, through one process and the stitched threads."""
    from conftest import assert_unfolding_keeps_every_copy

    monkeypatch.setenv("KNNREFINE_TILES", "always")  # the stitched tiles at this size too
    rng = np.random.default_rng(33)
    pts = rng.random((30000, 2)) ** 2
    pts[:3000, 0] = 0.5
    box = (0.0, 0.0, 1.0, 1.0)
    mesh = knnrefine.refine(pts, 10, periodic=periodic, box=box, workers=workers)
    if workers > 1:
        assert mesh.stats["rounds"][-1]["stitched"]
    assert_unfolding_keeps_every_copy(mesh, box)


def test_workers_below_the_tiles_size_run_one_process(monkeypatch):
    """Issue 32: refine(workers=2) on 10^6 points ran 0.75-0.9x as fast as one process (the
    stitched strips' plan, seams and stitch outweigh halving the refinement; one process
    uses every core for its index, sweeps and assembly already). Below
    ``scale.tiled.TILES_FROM`` (in the plane and in space) workers > 1 runs that one process: the
    very mesh of workers=None, vertex by vertex; KNNREFINE_TILES=always tiles anyway, and a
    value it does not know is refused before any work."""
    from knnrefine.errors import InputError
    from knnrefine.scale import tiled

    monkeypatch.delenv("KNNREFINE_TILES", raising=False)
    pts = np.random.default_rng(34).random((20000, 2))
    one = knnrefine.refine(pts, 10)
    two = knnrefine.refine(pts, 10, workers=2)
    assert two.stats["rounds"] is None
    np.testing.assert_array_equal(one.vertices, two.vertices)
    np.testing.assert_array_equal(one.cells, two.cells)
    xyz = np.random.default_rng(35).random((3000, 3))
    box3 = (0, 0, 0, 1, 1, 1)
    a = knnrefine.refine(xyz, 10, periodic=True, box=box3)
    b = knnrefine.refine(xyz, 10, periodic=True, box=box3, workers=3)
    assert b.stats["rounds"] is None
    np.testing.assert_array_equal(a.vertices, b.vertices)
    monkeypatch.setitem(tiled.TILES_FROM, "plane", 10000)  # at and above it: the tiles
    assert knnrefine.refine(pts, 10, workers=2).stats["rounds"]
    monkeypatch.setitem(tiled.TILES_FROM, "space", 3000)  # in space too: the stitched slabs
    assert knnrefine.refine(xyz, 10, periodic=True, box=box3, workers=2).stats["rounds"][-1][
        "stitched"
    ]
    assert knnrefine.refine(xyz[:2999], 10, periodic=True, box=box3,
                            workers=2).stats["rounds"] is None  # fmt: skip
    assert knnrefine.refine(pts[:9999], 10, workers=2).stats["rounds"] is None
    monkeypatch.setitem(tiled.TILES_FROM, "plane", 2_000_000)
    monkeypatch.setenv("KNNREFINE_TILES", "always")
    assert knnrefine.refine(pts, 10, workers=2).stats["rounds"]
    monkeypatch.setenv("KNNREFINE_TILES", "sometimes")
    with pytest.raises(InputError, match="KNNREFINE_TILES"):
        knnrefine.refine(pts, 10, workers=2)
