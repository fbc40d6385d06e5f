"""Tiled refinement (refine(..., workers=N), _engine/tiles.py and partition.py) against the
same oracle as a run in one process: certify (the torus triangulation checked to be Delaunay
in exact arithmetic, counts and ratios from scipy's cKDTree), and the mesh size against the
single-process run's."""

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest
from conftest import DEGENERATE, DEGENERATE3, assert_certified, gaussian_clusters, on_lines, uniform
from hypothesis import given, settings
from hypothesis import strategies as st

import knnrefine
from knnrefine._engine.region import in_rectangle
from knnrefine.scale.tiled import strips

pytestmark = pytest.mark.usefixtures("tiles_always")  # the tiles at every size


def clustered(n, seed=0):
    """Forty Gaussian clusters with widths from 1e-3 to 3e-2, wrapped into the unit box."""
    return gaussian_clusters(n, seed, clusters=40)


def with_duplicates(n, seed=0):
    """Every point of a uniform sample twice (multiplicity 2 < k)."""
    x = uniform(n // 2, seed)
    return np.concatenate([x, x])


CASES = [
    ("uniform", uniform, 10, True),
    ("uniform", uniform, 10, False),
    ("clustered", clustered, 10, True),
    ("clustered", clustered, 100, False),
    ("duplicates", with_duplicates, 10, True),
    ("uniform-x-periodic", uniform, 100, (True, False)),
]


@pytest.mark.slow
@pytest.mark.parametrize("name, make, k, periodic", CASES, ids=[c[0] + str(c[2]) for c in CASES])
def test_tiled_mesh_is_certified_and_the_size_of_a_single_run(name, make, k, periodic):
    """Two workers (threads, stitched): the mesh passes certify (the triangulation across
    the strips' borders is one Delaunay triangulation, every guarantee holds) and has within
    5% of the vertices of the single-process mesh of the same input; the tiles did most of
    the work, the points were never fetched, and on the torus the tiles' meshes were
    stitched. (The last step takes what no seam could: elements wider than a seam, many on a
    coarse mesh such as k = 100's 3,700 vertices on clustered points, where the join is
    refused and one mesh of all vertices is made instead.)"""
    X = make(60000)
    box = (0, 0, 1, 1)
    single = knnrefine.refine(X, k, box=box, periodic=periodic)
    tiled = knnrefine.refine(X, k, box=box, periodic=periodic, workers=2)
    assert_certified(tiled, X, f"tiled {name} k={k}")
    assert abs(len(tiled.vertices) / len(single.vertices) - 1) < 0.05
    rounds = tiled.stats["rounds"]
    in_rounds = sum(r["new_vertices"] for r in rounds if r["round"] != "final")
    assert rounds[-1]["round"] == "final" and rounds[-1]["new_vertices"] < 0.5 * in_rounds
    assert not rounds[-1]["fetched_points"]  # one index of all points, shared by the tiles
    if periodic is True:
        assert rounds[-1]["stitched"]
    # the tiles' moves are carried to the mesh: only the initial mesh counts as initial
    assert tiled.stats["moves"]["initial"] == tiled.stats["initial_vertices"]
    assert tiled.stats["moves"]["break_circumball"] > 0


def test_three_workers_on_a_weighted_input():
    """Weights count in every tile (a point of weight w is w points): the tiled mesh of
    weighted points passes certify's weighted counts."""
    X = clustered(20000, seed=3)
    w = np.random.default_rng(3).integers(1, 4, len(X)).astype(float)
    tiled = knnrefine.refine(X, 30, box=(0, 0, 1, 1), periodic=True, weights=w, workers=3)
    cert = knnrefine.certify(tiled, X, weights=w)
    assert cert.passed, str(cert)
    single = knnrefine.refine(X, 30, box=(0, 0, 1, 1), periodic=True, weights=w)
    assert abs(len(tiled.vertices) / len(single.vertices) - 1) < 0.05


def test_strips_interleave_and_balance_the_points():
    """Each set of strips tiles the torus; each holds about 1 / T of the points; every
    border of one set lies strictly inside a strip of the other."""
    xy = clustered(40000) * [0.8, 0.5]
    for tiles in (2, 3, 5):
        first, second = strips(xy, (0.8, 0.5), tiles)
        for regions in (first, second):
            assert regions[:, 2].sum() == pytest.approx(0.8)  # the strips tile the x period
            counts = [in_rectangle(xy, *r, 0.0, 0.8, 0.5).sum() for r in regions]
            assert max(counts) <= 1.02 * len(xy) / tiles + 2
        for x in first[:, 0]:
            inside = [(x - s[0]) % 0.8 for s in second]
            assert any(1e-9 < d < s[2] - 1e-9 for d, s in zip(inside, second, strict=True))


@pytest.mark.parametrize("bad", [0, -2, 1.5, True, "2"])
def test_bad_workers_are_refused_before_work(bad):
    with pytest.raises(knnrefine.InputError, match="workers"):
        knnrefine.refine(uniform(100), 5, workers=bad)


def test_tiled_time_limit_is_kept():
    """regression: a tiled run ignored time_limit (the rounds and the last pass ran without
    the deadline). A progress callback that sleeps past the limit after the first round:
    BudgetError, as for a run in one process."""
    import time

    calls = []

    def slow(vertices, pending):
        calls.append(vertices)
        if len(calls) == 1:
            time.sleep(3.0)

    X = uniform(60000)
    with pytest.raises(knnrefine.BudgetError, match="time_limit"):
        knnrefine.refine(X, 10, box=(0, 0, 1, 1), workers=2, time_limit=2.0, progress=slow)


def test_tiled_budget_stops_with_budget_error():
    X = uniform(60000)
    with pytest.raises(knnrefine.BudgetError, match="max_vertices"):
        knnrefine.refine(X, 10, box=(0, 0, 1, 1), workers=2, max_vertices=3000)


def test_split_strips_holds_every_point_of_each_padded_strip():
    """split_strips (a counting sort on the strip cuts) against in_rectangle on each strip:
    every point of a strip widened by pad is among its rows, and no more than a few points
    beyond it; duplicates on a cut and cuts that coincide included."""
    from knnrefine.scale.tiled import split_strips

    rng = np.random.default_rng(4)
    xy = rng.random((50000, 2)) * [0.8, 0.5]
    xy[:3000] = [0.31, 0.2]  # a heavy duplicate: several quantile cuts fall on it
    pad = 1e-3
    for tiles in (2, 5, 11):
        for regions in strips(xy, (0.8, 0.5), tiles):
            rows, bounds = split_strips(xy, regions, pad, (0.8, 0.5))
            for j, region in enumerate(regions):
                want = np.flatnonzero(in_rectangle(xy, *region, pad, 0.8, 0.5))
                got = rows[bounds[j] : bounds[j + 1]]
                assert np.all(np.diff(got) > 0)
                assert np.isin(want, got).all()
                assert len(got) <= len(want) + 3000  # coinciding cuts: the duplicate twice


def test_sample_is_the_same_however_the_points_are_split():
    """sample_keys depends on a point's coordinates only: the sample of a shuffled, split
    input is the same set, and about the requested fraction."""
    from knnrefine._sampling import canonical, sample_keys

    rng = np.random.default_rng(5)
    xy = rng.random((40000, 2))
    keys = sample_keys(xy)
    a = canonical(xy[keys < 0.1], None, keys[keys < 0.1])[0]
    perm = rng.permutation(len(xy))
    parts = np.array_split(xy[perm], 7)
    got = [(p[sample_keys(p) < 0.1], sample_keys(p)[sample_keys(p) < 0.1]) for p in parts]
    b = canonical(np.concatenate([g[0] for g in got]), None, np.concatenate([g[1] for g in got]))
    np.testing.assert_array_equal(a, b[0])
    assert abs(len(a) / len(xy) - 0.1) < 0.01
    assert sample_keys(np.array([[0.0, 1.0]]))[0] == sample_keys(np.array([[-0.0, 1.0]]))[0]
    # the order: by key (then by the coordinates where keys tie: repeated points), as a
    # lexsort of all gives it, with ties or without
    sel = xy[keys < 0.1]
    np.testing.assert_array_equal(a, sel[np.lexsort((sel[:, 1], sel[:, 0], keys[keys < 0.1]))])
    dup = np.concatenate([xy[:50], xy[:50][::-1] + 0.0, rng.random((20, 2)), xy[:3]])
    k = sample_keys(dup)
    np.testing.assert_array_equal(canonical(dup, None, k)[0],
                                  dup[np.lexsort((dup[:, 1], dup[:, 0], k))])  # fmt: skip


def test_margin_bands_hold_no_point_and_settle_the_margin():
    """regression (tiled non-periodic runs fetched every point for the last step): the bands
    outside the points' extent hold none of them, and a uniform periodic-in-x run settles
    everything without the points (the last step inserts nothing and fetches nothing)."""
    from knnrefine._engine.embedding import Embedding
    from knnrefine.scale.tiled import margin_bands

    X = uniform(60000)
    emb = Embedding.make((0, 0, 1, 1), (True, False))
    bands = margin_bands(emb, X.min(axis=0), X.max(axis=0))
    assert len(bands) == 1  # only the non-periodic axis has a margin
    inside = emb.to_internal(X)
    for band in bands:
        assert not in_rectangle(inside, *band, 0.0, *emb.period_internal).any()
    # the rounds of shifted strips (an executor's path, as Dask's) use the bands
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        mesh = knnrefine.refine(X, 100, box=(0, 0, 1, 1), periodic=(True, False), workers=2,
                                executor=pool)  # fmt: skip
    last = mesh.stats["rounds"][-1]
    assert last["unsettled"] == 0 and not last["fetched_points"]


def test_seeded_vertices_are_queued_again():
    """regression: queue_all kept the 'queued' flags of the initial mesh's vertices while it
    emptied the queues, so a seeded run (a tile, the last step) never looked at their cells
    again. After seeding and running, every cell has been tested."""
    from knnrefine._engine import refine as R
    from knnrefine._engine.driver import Refinement
    from knnrefine._engine.index import build_index

    X = uniform(20000)
    run = Refinement(build_index(X.copy()), 10, 1.0, 1.0, 3.0, 0.0, 10**6)
    xy = np.random.default_rng(1).random((500, 2))
    run.seed(xy, np.full(500, 1, np.int8), np.zeros(500, np.int32), np.zeros((0, 2, 4)))
    assert (run.book.cell_state[: run.vertices] != R.GOOD).all()  # no round settled any
    assert run.run() == R.STATUS_DONE
    assert (run.book.cell_state[: run.vertices] == R.GOOD).all()  # every cell was looked at


# -- degenerate inputs through the tiled path (issue 28) ---------------------------------------


def test_tiled_run_with_most_points_on_one_line_certifies():
    """regression: 60% of the points on x = 0.5 put several strip cuts on one x; a strip of
    width 0 then meant "no region" to its tile, which refined the whole torus beside the
    others: 17,450 vertices against 2,771, two of them 4.8e-5 apart where d_Pk = 0.035, and
    certify failed it (alpha_hat 0.0007)."""
    X = on_lines(4000, 0.6, [0.5])
    box = (0, 0, 1, 1)
    one = knnrefine.refine(X, 10, periodic=True, box=box)
    tiled = knnrefine.refine(X, 10, periodic=True, box=box, workers=2)
    assert_certified(tiled, X, "tiled, 60% on a line")
    assert abs(len(tiled.vertices) / len(one.vertices) - 1) < 0.05
    assert all(r["new_vertices"] >= 0 for r in tiled.stats["rounds"])


def test_tiled_run_with_every_point_on_two_lines_at_four_workers_certifies():
    """regression: every point on x = 0.3 or x = 0.7, four workers: alpha_hat 1e-13, max
    aspect 31,949, and the last round reported new_vertices = -20,173 (the last step
    dropped vertices that two tiles had both inserted)."""
    X = on_lines(4000, 1.0, [0.3, 0.7], seed=1)
    tiled = knnrefine.refine(X, 10, periodic=True, box=(0, 0, 1, 1), workers=4)
    assert_certified(tiled, X, "tiled, two lines, 4 workers")
    assert all(r["new_vertices"] >= 0 for r in tiled.stats["rounds"])


def test_a_region_of_width_zero_holds_no_element():
    """regression: the engine read a region of width 0 as "no region" (the whole torus). A
    run whose region has width 0 inserts nothing; one without a region (NO_REGION) refines."""
    from knnrefine._engine import refine as R
    from knnrefine._engine.driver import Refinement
    from knnrefine._engine.index import build_index
    from knnrefine._engine.state import NO_REGION, P_REGION_H, P_REGION_W, P_REGION_X0

    X = uniform(5000)
    empty = Refinement(build_index(X.copy()), 10, 1.0, 1.0, 3.0, 0.0, 10**6)
    start = empty.vertices
    empty.prm[P_REGION_X0], empty.prm[P_REGION_W], empty.prm[P_REGION_H] = 0.5, 0.0, 1.0
    assert empty.run() == R.STATUS_DONE and empty.vertices == start
    whole = Refinement(build_index(X.copy()), 10, 1.0, 1.0, 3.0, 0.0, 10**6)
    assert whole.prm[P_REGION_W] == NO_REGION
    assert whole.run() == R.STATUS_DONE and whole.vertices > 10 * start


@pytest.mark.parametrize("tiles", [2, 3, 4, 7])
def test_strips_are_never_empty_when_points_share_coordinates(tiles):
    """Whatever the points (all on a cross of two lines, all at one point, none), both sets
    of strips tile the period with widths of at least twice the least gap, and each border
    of one set lies inside a strip of the other, the least gap from its borders."""
    from knnrefine.scale.tiled import MIN_GAP, regions_axis

    rng = np.random.default_rng(tiles)
    cross = rng.random((3000, 2)) * [0.8, 0.5]
    cross[:1500, 0], cross[1500:, 1] = 0.4, 0.25
    inputs = [cross, np.full((500, 2), 0.3), np.zeros((0, 2)), on_lines(2000, 0.9, [0.0])]
    for xy in inputs:
        first, second = strips(xy, (0.8, 0.5), tiles)
        axis = regions_axis(first, (0.8, 0.5))
        assert regions_axis(second, (0.8, 0.5)) == axis
        period = (0.8, 0.5)[axis]
        gap = MIN_GAP * period / (2 * tiles)
        for regions in (first, second):
            assert regions[:, 2 + axis].sum() == pytest.approx(period)
            assert (regions[:, 2 + axis] >= 2 * gap * (1 - 1e-9)).all()
            assert (regions[:, 3 - axis] == (0.5, 0.8)[axis]).all()
        for x in first[:, axis]:
            into = [((x - s[axis]) % period, s[2 + axis]) for s in second]
            assert any(gap * (1 - 1e-9) <= d <= w - gap * (1 - 1e-9) for d, w in into)


def test_strips_run_across_the_axis_that_balances_the_points():
    """Points on the line x = 0.5 cannot be balanced by cuts along x: the strips are cut
    along y (the other period), each holding about 1 / T of them."""
    from knnrefine.scale.tiled import regions_axis

    xy = on_lines(20000, 1.0, [0.5], seed=2)
    for regions in strips(xy, (1.0, 1.0), 4):
        assert regions_axis(regions, (1.0, 1.0)) == 1
        counts = [in_rectangle(xy, *r, 0.0, 1.0, 1.0).sum() for r in regions]
        assert max(counts) <= 1.1 * len(xy) / 4


def test_a_round_whose_tile_moved_outside_its_strip_is_refused():
    """The seam check: a round whose tile returned a vertex outside its strip (what a broken
    plan produced) raises EngineError instead of becoming part of a mesh."""
    from knnrefine.scale.tiled import check_seams

    regions = np.array([[0.0, 0.0, 0.5, 1.0], [0.5, 0.0, 0.5, 1.0]])
    inside = [np.array([[0.1, 0.3], [0.5, 0.9]]), np.array([[0.75, 0.2], [0.999, 0.0]])]
    check_seams(regions, inside, (1.0, 1.0))
    with pytest.raises(knnrefine.EngineError, match="outside its strip"):
        check_seams(regions, [inside[0], np.array([[0.25, 0.5]])], (1.0, 1.0))
    with pytest.raises(knnrefine.EngineError, match="do not tile"):
        check_seams(np.array([[0.0, 0.0, 1.0, 1.0], [0.5, 0.0, 0.0, 1.0]]), inside, (1.0, 1.0))


@given(
    name=st.sampled_from(sorted(DEGENERATE)),
    workers=st.integers(2, 4),
    periodic=st.sampled_from([True, False, (True, False)]),
    weighted=st.booleans(),
    seed=st.integers(0, 2**16),
)
@settings(max_examples=14)
def test_tiled_runs_on_degenerate_inputs_certify(name, workers, periodic, weighted, seed):
    """Property: points on lines, on the cuts a plan would choose, on the seam, on a
    lattice (many coinciding), weighted or not, through 2-4 workers: every mesh returned
    passes certify (conftest certifies each; checked here again with the weights)."""
    rng = np.random.default_rng(seed)
    X = DEGENERATE[name](2500, rng)
    w = rng.integers(1, 4, len(X)).astype(float) if weighted else None
    mesh = knnrefine.refine(X, 12, periodic=periodic, box=(0, 0, 1, 1), weights=w,
                            workers=workers)  # fmt: skip
    cert = knnrefine.certify(mesh, X, weights=w, samples=5_000, n_random=1_000)
    assert cert.passed, str(cert)
    assert all(r["new_vertices"] >= 0 for r in mesh.stats["rounds"])


# -- in space: slabs (engine/region3.py) -------------------------------------------------------

BOX3 = (0.0, 0.0, 0.0, 1.0, 1.0, 1.0)


@pytest.mark.parametrize(
    "periodic, workers, k, n",
    [
        pytest.param(False, 3, 10, 30000, marks=pytest.mark.slow),
        pytest.param((True, False, True), 2, 30, 30000, marks=pytest.mark.slow),
    ],
    ids=str,
)
def test_tiled_run_in_space_is_certified_and_the_size_of_a_single_run(periodic, workers, k, n):
    """Slabs in space (in threads, stitched): the mesh passes certify (one Delaunay
    tetrahedralisation across the slabs' borders, every guarantee) with within 5% of the
    single-process mesh's vertices; the tiles made most of the vertices, the last step the
    rest. At 3 x 10^4 clustered points the elements are wide against a narrow slab and its
    seams (an eighth of it), so the last step makes up to 43% of the mesh here (at 10^6
    points, a few dozen vertices of 400,000: docs/benchmarks.md); tiles start at 10^6
    points in space for that reason (``scale.tiled.TILES_FROM``)."""
    X = gaussian_clusters(n, seed=4, clusters=25, dim=3)
    single = knnrefine.refine(X, k, box=BOX3, periodic=periodic)
    tiled = knnrefine.refine(X, k, box=BOX3, periodic=periodic, workers=workers)
    assert_certified(tiled, X, f"tiled in space {periodic} k={k}")
    assert abs(len(tiled.vertices) / len(single.vertices) - 1) < 0.05
    rounds = tiled.stats["rounds"]
    in_tiles = sum(r["new_vertices"] for r in rounds if r["round"] != "final")
    assert rounds[-1]["round"] == "final" and rounds[-1]["stitched"]
    assert rounds[-1]["new_vertices"] < in_tiles


@pytest.mark.slow
def test_tiled_run_in_space_with_weights_and_an_executor():
    """Weights count in every slab (whole weights are copies: the tiled mesh of weighted
    points is certified by certify's weighted counts); an executor runs the tiles."""
    from concurrent.futures import ThreadPoolExecutor

    X = gaussian_clusters(6000, seed=5, clusters=10, dim=3)
    w = np.random.default_rng(5).integers(1, 4, len(X)).astype(float)
    with ThreadPoolExecutor(2) as pool:
        tiled = knnrefine.refine(X, 30, box=BOX3, periodic=True, weights=w, workers=2,
                                 executor=pool)  # fmt: skip
    cert = knnrefine.certify(tiled, X, weights=w)
    assert cert.passed, str(cert)
    single = knnrefine.refine(X, 30, box=BOX3, periodic=True, weights=w)
    assert abs(len(tiled.vertices) / len(single.vertices) - 1) < 0.05


def test_tiled_run_in_space_keeps_its_budgets():
    """time_limit and max_vertices hold in space's tiled path as in one process."""
    import time

    X = uniform(40000, 6, dim=3)
    with pytest.raises(knnrefine.BudgetError, match="max_vertices"):
        knnrefine.refine(X, 10, box=BOX3, workers=2, max_vertices=5000)
    calls = []

    def slow(vertices, pending):
        calls.append(vertices)
        if len(calls) == 1:
            time.sleep(3.0)

    with pytest.raises(knnrefine.BudgetError, match="time_limit"):
        knnrefine.refine(X, 10, box=BOX3, workers=2, time_limit=2.0, progress=slow)


def test_slabs_interleave_and_balance_the_points_in_space():
    """Each set of slabs tiles the torus across its longest period and spans the others;
    each holds about 1 / T of the points; every border of one set lies strictly inside a
    slab of the other."""
    from knnrefine._engine.region3 import in_box3
    from knnrefine.scale.tiled import regions_axis

    period = np.array([0.6, 0.9, 0.5])
    xyz = gaussian_clusters(30000, seed=7, dim=3) * period
    for tiles in (2, 3, 5):
        first, second = strips(xyz, tuple(period), tiles)
        assert regions_axis(first, period) == regions_axis(second, period) == 1
        for regions in (first, second):
            assert regions[:, 4].sum() == pytest.approx(0.9)
            assert (regions[:, [3, 5]] == period[[0, 2]]).all()
            counts = [in_box3(xyz, r, 0.0, period).sum() for r in regions]
            assert max(counts) <= 1.02 * len(xyz) / tiles + 2
        for y in first[:, 1]:
            inside = [((y - s[1]) % 0.9, s[4]) for s in second]
            assert any(1e-9 < d < w - 1e-9 for d, w in inside)


def test_a_seeded_run_in_space_rebuilds_the_mesh_and_finds_nothing_to_do():
    """insert_points3 (a visibility walk to each vertex) and queue_seeded3: the vertices of
    a finished run in space, seeded into a fresh run from the same initial mesh, give the
    same vertices and as many tetrahedra, and running it inserts nothing; a vertex given
    twice is skipped, and with a region of width 0 a run inserts nothing."""
    from knnrefine._domains.space.run import holds_k
    from knnrefine._engine.driver3 import Refinement3, choose_grid3
    from knnrefine._engine.index3 import build_index3
    from knnrefine._engine.initial import reach_factor
    from knnrefine._engine.state import C_NT, STATUS_DONE

    X = gaussian_clusters(8000, seed=8, clusters=6, dim=3)
    period = np.ones(3)
    index = build_index3(X)
    grid = choose_grid3(period, lambda x, r: holds_k(index, x, r, 10, period), reach_factor(3))

    def fresh():
        return Refinement3(index, period, 10, 3.0, 1e-6, 10**6, grid)

    done = fresh()
    m0 = done.vertices
    assert done.run() == STATUS_DONE
    xyz, kinds = done.new_vertices(m0)
    nt = int(done.cnt[C_NT])
    again = fresh()
    twice = np.concatenate([xyz, xyz[:50]])
    stamps = np.zeros(len(twice), np.int32)
    with pytest.raises(knnrefine.EngineError, match="coincide"):
        again.seed(twice, np.concatenate([kinds, kinds[:50]]), stamps, np.zeros((0, 2, 6)))
    again = fresh()
    again.seed(xyz, kinds, stamps[: len(xyz)], np.zeros((0, 2, 6)))
    assert again.vertices == done.vertices and int(again.cnt[C_NT]) == nt
    assert sorted(map(tuple, again.mesh.xyz[: again.vertices])) == sorted(
        map(tuple, done.mesh.xyz[: done.vertices])
    )
    assert again.run() == STATUS_DONE and again.vertices == done.vertices
    empty = fresh()
    empty.set_region(np.array([0.5, 0.0, 0.0, 0.0, 1.0, 1.0]))
    assert empty.run() == STATUS_DONE and empty.vertices == m0


@given(
    name=st.sampled_from(sorted(DEGENERATE3)),
    workers=st.integers(2, 4),
    periodic=st.sampled_from([True, False, (True, False, True)]),
    weighted=st.booleans(),
    seed=st.integers(0, 2**16),
)
@settings(max_examples=5)
def test_tiled_runs_in_space_on_degenerate_inputs_certify(name, workers, periodic, weighted,
                                                          seed):  # fmt: skip
    """Property, in space: points on planes, on the cuts a plan would choose, on the seam,
    on one line, on a lattice, weighted or not, through 2-4 workers: every mesh returned
    passes certify, and no round reports a negative count."""
    rng = np.random.default_rng(seed)
    X = DEGENERATE3[name](1500, rng)
    w = rng.integers(1, 4, len(X)).astype(float) if weighted else None
    mesh = knnrefine.refine(X, 12, periodic=periodic, box=BOX3, weights=w, workers=workers)
    cert = knnrefine.certify(mesh, X, weights=w, samples=5_000, n_random=1_000)
    assert cert.passed, str(cert)
    assert all(r["new_vertices"] >= 0 for r in mesh.stats["rounds"])


def test_workers_run_tiles_as_threads_of_this_process(monkeypatch):
    """Issue 32: workers=2 pickled each tile's points to a local process and built a counting
    index there; its rounds took 1 s each at 4 x 10^6 points. The tiles are now threads of
    this process counting in one index of all points: no child process, the process-wide
    thread setting untouched, the points never fetched again for the last step, and the
    mesh certified and within a few percent of one process' size."""
    import multiprocessing
    import os

    from knnrefine.scale import tiled

    monkeypatch.delenv("KNNREFINE_THREADS", raising=False)
    made = []
    monkeypatch.setattr(tiled, "ProcessPoolExecutor", lambda *a, **kw: made.append(a))
    pts = clustered(30_000, seed=5)
    mesh = knnrefine.refine(pts, 10, workers=2)
    assert made == [] and multiprocessing.active_children() == []
    assert "KNNREFINE_THREADS" not in os.environ
    rounds = mesh.stats["rounds"]
    assert rounds[0]["round"] == "strips" and len(rounds[0]["tiles"]) == 2
    assert rounds[-1]["fetched_points"] is False  # the shared index counts every point
    assert_certified(mesh, pts)
    one = knnrefine.refine(pts, 10)
    assert abs(len(mesh.vertices) / len(one.vertices) - 1) < 0.03


def test_tiles_on_an_executor_run_in_its_processes_in_the_plane():
    """The processes' path stays for an executor (beyond one machine's threads): rounds of
    shifted strips, certified, in the plane (space has its own test above); the threads'
    stitched run has its size within 3%."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    pts = clustered(20_000, seed=6)
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        mesh = knnrefine.refine(pts, 10, workers=2, executor=pool)
    assert_certified(mesh, pts)
    assert "stitched" not in mesh.stats["rounds"][-1]  # the rounds of shifted strips
    threads = knnrefine.refine(pts, 10, workers=2)
    assert threads.stats["rounds"][-1]["stitched"]
    assert abs(len(threads.vertices) / len(mesh.vertices) - 1) < 0.03


def test_tiles_on_an_executor_in_this_process_leave_the_thread_setting_alone(monkeypatch):
    """A tile set ``KNNREFINE_THREADS=1`` in the process that ran it, meant for a worker
    process of a pool; on an executor whose tasks run in the caller's process (threads, Dask
    in-process) it stayed set there: every later run used one core, and a first call started
    no compile-ahead helper. The tiles now tell their run to use one thread instead."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    monkeypatch.delenv("KNNREFINE_THREADS", raising=False)
    pts = clustered(20_000, seed=3)
    with ThreadPoolExecutor(2) as pool:
        mesh = knnrefine.refine(pts, 10, workers=2, executor=pool)
    assert "KNNREFINE_THREADS" not in os.environ
    assert len(mesh.stats["rounds"]) >= 2  # the tiles ran, in this process
