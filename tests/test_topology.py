"""Robust persistent homology on the mesh, against cubical persistence on a fine grid."""

import numpy as np
import pytest

import knnrefine

gudhi = pytest.importorskip("gudhi")
from knnrefine.topology import (  # noqa: E402
    Persistence,
    bottleneck,
    grid_persistence,
    mesh_complex,
)


def noisy_circle(seed, n=2000, outliers=0.2):
    rng = np.random.default_rng(seed)
    t = rng.random(int((1 - outliers) * n)) * 2 * np.pi
    circle = np.stack([np.cos(t), np.sin(t)], 1) + rng.normal(0, 0.05, (len(t), 2))
    return np.concatenate([circle, rng.random((n - len(t), 2)) * 4 - 2])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_outliers_drown_the_circle_for_k1_not_for_knn(seed):
    """The showcase: 20% uniform outliers. With k = 1 (the plain distance to P) the circle's
    loop is hardly more persistent than loops among outliers; with k = 30 it stands out."""
    pts = noisy_circle(seed)
    box = (-2, -2, 2, 2)
    plain = Persistence(knnrefine.refine(pts, 1, box=box, min_size=1e-2), pts, log=False)
    top = plain.most_persistent(1, 2)
    assert top[1] / top[0] > 0.4  # drowned: the runner-up is comparable
    robust = Persistence(knnrefine.refine(pts, 30, box=box), pts, log=False)
    top = robust.most_persistent(1, 2)
    assert len(top) == 1 or top[1] / top[0] < 0.1  # stands out
    # and the loop is the circle: born on it, dying near its centre's distance
    d = robust.diagram(1)
    b, death = d[np.argmax(d[:, 1] - d[:, 0])]
    assert b < 0.3 and 0.5 < death < 1.2


@pytest.mark.parametrize("periodic", [False, True])
def test_matches_cubical_persistence_on_a_fine_grid(periodic):
    rng = np.random.default_rng(3)
    pts = np.concatenate([noisy_circle(3, 1500) * 0.3 + 0.5, rng.random((500, 2))]) % 1.0
    box = (0, 0, 1, 1)
    mesh = knnrefine.refine(pts, 10, periodic=periodic, box=box)
    ph = Persistence(mesh, pts)  # log scale
    grid = grid_persistence(pts, 10, box, periodic=(periodic, periodic), shape=(400, 400))
    err = knnrefine.KnnDistance(mesh, pts).error()
    for dim in (0, 1):
        dist = bottleneck(ph.diagram(dim), grid[dim])
        # stability: the distance is at most the sup-norm gap between the two functions (log
        # scale: about the worst relative interpolation error) plus the grid's own resolution
        assert dist < err["worst"] + 0.1, (dim, dist, err)
    # essential classes: one component; on the torus also two loops and the whole torus
    essential = [int(np.isinf(ph.diagram(d)[:, 1]).sum()) for d in (0, 1, 2)]
    assert essential == ([1, 2, 1] if periodic else [1, 0, 0])


def test_the_complex_is_simplicial_and_covers_the_box():
    pts = np.random.default_rng(4).random((800, 2))
    for periodic in (True, False, (True, False)):
        mesh = knnrefine.refine(pts, 8, periodic=periodic, box=(0, 0, 1, 1))
        pos, tri = mesh_complex(mesh)
        assert len(np.unique(tri)) == len(pos)
        edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
        uses = np.unique(edges, axis=0, return_counts=True)[1]
        assert uses.max() <= 2
        if periodic is True:
            assert np.all(uses == 2) and len(pos) - len(uses) + len(tri) == 0  # a torus


def test_betti_numbers_of_a_sublevel_set():
    pts = noisy_circle(5, 1500, outliers=0.0)
    ph = Persistence(knnrefine.refine(pts, 10, box=(-2, -2, 2, 2)), pts, log=False)
    assert ph.betti(0.3) == (1, 1, 0)  # the thickened circle: one component, one loop
