"""The periodic 3-D Delaunay triangulation (engine/triangulation3.py), checked from scratch
after insertions of random points, circumcentres and a whole cubic lattice (cospherical
everywhere): faces matched again independently of the engine, every tetrahedron positively
oriented and locally Delaunay (exact predicates, themselves checked against rationals in
test_predicates3.py), the volumes adding up to the torus' once, Euler's relation of the
3-torus, and the caches (circumradii, R(v), d_{M,2}(v)) against brute force."""

import numpy as np
import pytest
from numba import njit
from scipy.spatial import cKDTree

from knnrefine._engine import predicates3
from knnrefine._engine.geometry import Q
from knnrefine._engine.initial import face_neighbours, initial_grid3
from knnrefine._engine.jit import python_entry
from knnrefine._engine.triangulation3 import (
    circumspheres,
    insert_largest3,
    insert_points3,
    new_torus3,
    outradius2_at3,
    pack_offsets,
    refresh_outradii3,
    unpack_offsets,
)

_orient3d = python_entry(predicates3.orient3d)
_insphere = python_entry(predicates3.insphere)
_outradius2_at3 = python_entry(outradius2_at3)


@njit(cache=False)
def _exact_checks(corners, neighbours, offsets, xyz, period, nt):
    """(tetrahedra not positively oriented, faces not locally Delaunay, faces whose
    neighbour does not point back)."""
    bad_orient = 0
    bad_delaunay = 0
    bad_link = 0
    pts = np.empty((5, 3))
    for t in range(nt):
        for i in range(4):
            v = corners[t, i]
            for a in range(3):
                pts[i, a] = xyz[v, a] + offsets[t, i, a] * period[a]
        if _orient3d(pts[:4].copy()) <= 0:
            bad_orient += 1
        for i in range(4):
            n = neighbours[t, i]
            jj = -1
            for k in range(4):
                if neighbours[n, k] == t:
                    jj = k
            if jj < 0:
                bad_link += 1
                continue
            # n's frame relative to t's, through a shared vertex
            a_ = corners[t, (i + 1) % 4]
            ia = -1
            for k in range(4):
                if corners[n, k] == a_:
                    ia = k
            if ia < 0:
                bad_link += 1
                continue
            u = corners[n, jj]
            for a in range(3):
                s = offsets[t, (i + 1) % 4, a] - offsets[n, ia, a]
                pts[4, a] = xyz[u, a] + (offsets[n, jj, a] + s) * period[a]
            if _insphere(pts) > 0:
                bad_delaunay += 1
    return bad_orient, bad_delaunay, bad_link


def check_triangulation(mesh, cnt, period):
    nv, nt = int(cnt[0]), int(cnt[1])
    corners = mesh.corners[:nt]
    offsets = unpack_offsets(mesh.offsets[:nt])  # two bits per corner and axis
    np.testing.assert_array_equal(pack_offsets(offsets), mesh.offsets[:nt])
    assert corners.max() < nv and corners.min() >= 0
    assert len(np.unique(corners)) == nv  # every vertex is a corner
    assert (offsets.min(axis=1) == 0).all()  # normalised
    # the faces matched again from the corners and offsets alone
    np.testing.assert_array_equal(face_neighbours(corners, offsets), mesh.neighbours[:nt])
    assert _exact_checks(mesh.corners, mesh.neighbours, offsets, mesh.xyz, period, nt) == (
        0,
        0,
        0,
    )
    p = mesh.xyz[corners] + offsets * period
    volume = np.abs(np.linalg.det(p[:, :3] - p[:, 3:])).sum() / 6.0
    assert volume == pytest.approx(np.prod(period), rel=1e-9)  # covers the torus once
    # Euler: V - E + F - T = 0 on the 3-torus, F = 2 T
    pairs = []
    for i in range(4):
        for j in range(i + 1, 4):
            a, b = corners[:, i].astype(np.int64), corners[:, j].astype(np.int64)
            d = offsets[:, j].astype(np.int64) - offsets[:, i]
            d = np.where((a > b)[:, None], -d, d)
            pairs.append(np.column_stack([np.minimum(a, b), np.maximum(a, b), d]))
    edges = len(np.unique(np.concatenate(pairs), axis=0))
    assert nv - edges + 2 * nt - nt == 0
    # caches against brute force
    cs = circumspheres(mesh, period, np.arange(nt))
    np.testing.assert_allclose(mesh.radius2[:nt], cs[:, 3], rtol=1e-9)
    outer = np.zeros(nv)
    np.maximum.at(outer, corners.ravel(), np.repeat(cs[:, 3], 4))
    # R(v)^2 itself where the cache holds it, else (negated) a bound on it
    cached = mesh.outradius2[:nv]
    known = cached >= 0
    np.testing.assert_allclose(cached[known], outer[known], rtol=1e-9)
    assert (-cached[~known] >= outer[~known] * (1 - 1e-9)).all()
    d = cKDTree(mesh.xyz[:nv], boxsize=period).query(mesh.xyz[:nv], k=2)[0][:, 1]
    np.testing.assert_allclose(mesh.nearest2[:nv], d**2, rtol=1e-9)
    for v in np.random.default_rng(0).choice(nv, min(nv, 200), replace=False):
        assert v in corners[mesh.star[v]]


def _seeds(mesh, cnt, period, p):
    """For each point, a tetrahedron whose open circumball holds it and the point in that
    tetrahedron's frame (brute force over all tetrahedra and shifts), or -1."""
    nt = int(cnt[1])
    cs = circumspheres(mesh, period, np.arange(nt))
    shifts = np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1])).reshape(3, -1).T
    seeds = np.full(len(p), -1)
    framed = p.copy()
    for s in shifts:
        q = p + s * period
        d2 = ((q[:, None, :] - cs[None, :, :3]) ** 2).sum(-1)
        inside = d2 < cs[None, :, 3] * (1 - 1e-9)
        hit = inside.any(axis=1) & (seeds < 0)
        seeds[hit] = np.argmax(inside[hit], axis=1)
        framed[hit] = q[hit]
    return seeds, framed


def _grid_points(rng, count, period):
    return np.rint(rng.random((count, 3)) * period / Q) * Q


@pytest.mark.parametrize("period", [(1.0, 1.0, 1.0), (1.0, 0.75, 1.5)], ids=str)
def test_random_insertions_keep_a_delaunay_triangulation_of_the_torus(period):
    period = np.array(period)
    grid = initial_grid3(period)
    check_triangulation(*new_torus3(period, grid, 0, 0)[::2], period)
    mesh, scratch, cnt = new_torus3(period, grid, 2000, 20000)
    rng = np.random.default_rng(1)
    for _ in range(40):  # batches: seeds found for the mesh as it is
        p = _grid_points(rng, 1, period)
        seeds, framed = _seeds(mesh, cnt, period, p)
        assert (seeds >= 0).all()
        assert insert_points3(framed, seeds, mesh, scratch, cnt, period) == 1
    check_triangulation(mesh, cnt, period)


def test_circumcentre_refinement_keeps_it_valid_and_grows_as_expected():
    """Largest circumball first, 3,000 insertions: still a valid Delaunay triangulation,
    with about 6.5 tetrahedra per vertex (Euler and the typical degree of 3-D Delaunay)."""
    period = np.array([1.0, 1.0, 1.0])
    mesh, scratch, cnt = new_torus3(period, initial_grid3(period), 4000, 40000)
    first = mesh.radius2[: cnt[1]].max()
    assert insert_largest3(mesh, scratch, cnt, period, Q, 3000, 0.0) == 3000
    check_triangulation(mesh, cnt, period)
    assert 5.5 < cnt[1] / cnt[0] < 7.5
    assert mesh.radius2[: cnt[1]].max() < first / 4  # the largest balls were split


def test_r_v_left_with_a_cavity_is_a_bound_until_asked_for():
    """An insertion that destroys the tetrahedron realising R(v) leaves R(v)^2 as a bound
    (negated) instead of walking v's star again: the cache holds bounds after refinement,
    ``outradius2_at3`` walks one and keeps R(v)^2 itself, ``refresh_outradii3`` all."""
    period = np.array([1.0, 1.0, 1.0])
    mesh, scratch, cnt = new_torus3(period, initial_grid3(period), 4000, 40000)
    insert_largest3(mesh, scratch, cnt, period, Q, 2000, 0.0)
    nv, nt = int(cnt[0]), int(cnt[1])
    outer = np.zeros(nv)
    np.maximum.at(outer, mesh.corners[:nt].ravel(), np.repeat(mesh.radius2[:nt], 4))
    bounds = np.flatnonzero(mesh.outradius2[:nv] < 0)
    assert 0 < len(bounds) < nv
    assert (-mesh.outradius2[bounds] >= outer[bounds]).all()
    assert (-mesh.outradius2[bounds] > outer[bounds]).any()  # a bound, not the value
    v = bounds[0]
    assert _outradius2_at3(v, mesh, scratch, cnt) == outer[v] == mesh.outradius2[v]
    refresh_outradii3(mesh, scratch, cnt, nv)
    np.testing.assert_array_equal(mesh.outradius2[:nv], outer)
    check_triangulation(mesh, cnt, period)


def test_a_cubic_lattice_is_inserted_without_loops_or_crashes():
    """Every point of an 6 x 6 x 6 lattice (cospherical everywhere: each cube's eight
    corners), in a random order; points that land on a vertex are refused, nothing else.
    Some cavities here have more tetrahedra than boundary faces: the arrays are compacted
    (the tetrahedron count falls), and the result still checks."""
    period = np.array([1.0, 1.0, 1.0])
    mesh, scratch, cnt = new_torus3(period, initial_grid3(period), 1000, 10000)
    lattice = np.array(np.meshgrid(*[np.arange(6) / 6] * 3)).reshape(3, -1).T
    lattice = np.rint(lattice / Q) * Q
    rng = np.random.default_rng(6)
    inserted = 0
    fell = 0
    for p in lattice[rng.permutation(len(lattice))]:
        seeds, framed = _seeds(mesh, cnt, period, p[None])
        if seeds[0] < 0:  # on a vertex already
            assert cKDTree(mesh.xyz[: cnt[0]], boxsize=1.0).query(p)[0] < 1e-12
            continue
        before = cnt[1]
        assert insert_points3(framed, seeds, mesh, scratch, cnt, period) == 1
        fell += cnt[1] < before
        inserted += 1
    assert inserted >= len(lattice) - 8 and fell > 0
    check_triangulation(mesh, cnt, period)
