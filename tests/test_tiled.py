"""Tiled refinement (refine(..., workers=N), engine/tiles.py and partition.py) against the
same oracle as a run in one process: certify (the torus triangulation checked to be Delaunay
in exact arithmetic, counts and ratios from scipy's cKDTree), and the mesh size against the
single-process run's."""

import numpy as np
import pytest
from conftest import assert_certified

import knnrefine
from knnrefine.engine.partition import strips
from knnrefine.engine.tiles import in_rectangle


def uniform(n, seed=0):
    return np.random.default_rng(seed).random((n, 2))


def clustered(n, seed=0):
    """Forty Gaussian clusters with widths from 1e-3 to 3e-2, wrapped into the unit box."""
    rng = np.random.default_rng(seed)
    centres = rng.random((40, 2))
    widths = 10 ** rng.uniform(-3, -1.5, 40)
    j = rng.integers(0, 40, n)
    return np.mod(centres[j] + rng.normal(size=(n, 2)) * widths[j, None], 1.0)


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


@pytest.mark.parametrize("name, make, k, periodic", CASES, ids=[c[0] + str(c[2]) for c in CASES])
def test_tiled_mesh_is_certified_and_the_size_of_a_single_run(name, make, k, periodic):
    """Two workers: the mesh passes certify (the triangulation across the strips' borders is
    one Delaunay triangulation, every guarantee holds) and has within 5% of the vertices of
    the single-process mesh of the same input; the rounds did the work, not the final pass."""
    X = make(60000)
    box = (0, 0, 1, 1)
    single = knnrefine.refine(X, k, box=box, periodic=periodic)
    tiled = knnrefine.refine(X, k, box=box, periodic=periodic, workers=2)
    assert_certified(tiled, X, f"tiled {name} k={k}")
    assert abs(len(tiled.vertices) / len(single.vertices) - 1) < 0.05
    rounds = tiled.stats["rounds"]
    in_rounds = sum(r["new_vertices"] for r in rounds if r["round"] != "final")
    assert rounds[-1]["round"] == "final" and rounds[-1]["new_vertices"] < 0.05 * in_rounds
    # the tiles' moves are carried to the mesh: only the initial mesh counts as initial
    assert tiled.stats["moves"]["initial"] == tiled.stats["m0"]["vertices"]
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
        first, second = strips(xy, 0.8, 0.5, tiles)
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
