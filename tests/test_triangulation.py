"""The periodic Delaunay triangulation kernel on its own: insertions keep every invariant."""

from types import SimpleNamespace

import numpy as np
import oracle
import pytest

import knnrefine
from knnrefine._domains.plane.certify import verify_triangulation
from knnrefine._engine import driver, geometry, triangulation
from knnrefine._engine.geometry import Q
from knnrefine._engine.index import build_index
from knnrefine._engine.jit import python_entry
from knnrefine._engine.state import C_NT, C_NV, INSERT_NOT_IN_SEED
from knnrefine._engine.triangulation import circumcentres

snap = python_entry(geometry.snap)
in_circumcircle = python_entry(triangulation.in_circumcircle)
insert_vertex = python_entry(triangulation.insert_vertex)
vertex_star = python_entry(triangulation.vertex_star)


def empty_torus(lx, ly):
    """A refinement state with no input points: just the initial grid on the torus."""
    return driver.Refinement(build_index(np.zeros((0, 2))), 1, lx, ly, 3.0, 0.0, 10**6)


def seed_for(state, px, py):
    """Brute force: a triangle (and periodic shift) whose circumcircle strictly holds p."""
    for t in range(int(state.cnt[C_NT])):
        for sx in (-1, 0, 1):
            for sy in (-1, 0, 1):
                if in_circumcircle(state.mesh, state.prm, t, sx, sy, px, py) > 0:
                    return t, px - sx * state.lx, py - sy * state.ly
    return None


def insert(state, x, y):
    px, py = snap(x, Q), snap(y, Q)
    found = seed_for(state, px, py)
    if found is None:
        return INSERT_NOT_IN_SEED
    t, qx, qy = found
    state.grow_if_needed()
    return insert_vertex(qx, qy, t, state.mesh, state.scratch, state.cnt, state.prm)


def validate(state):
    nv, nt = int(state.cnt[C_NV]), int(state.cnt[C_NT])
    mesh = state.mesh
    vxy, tv, to, tn = mesh.xy[:nv], mesh.corners[:nt], mesh.offsets[:nt], mesh.neighbours[:nt]
    period = np.array([state.lx, state.ly])
    problems, _, cc, r = verify_triangulation(vxy, tv, to, tn, period)
    corners = vxy[tv] + to * period
    assert not problems, problems
    if nv <= 600:  # brute force: every circumcircle against every copy of every vertex
        torus = SimpleNamespace(
            period=period, origin=(0.0, 0.0), vertices=vxy, triangles=tv, offsets=to
        )
        assert oracle.torus_facts(torus, np.zeros((0, 2)))["empty"]
    # the cached circumcircles agree with the corners
    cc_raw, r_raw = oracle.circumcircles(corners)
    centres = circumcentres(mesh, state.prm, np.arange(nt))
    np.testing.assert_allclose(centres[:, :2], cc_raw, atol=1e-12)
    np.testing.assert_array_equal(centres[:, 2], mesh.radius2[:nt])
    np.testing.assert_allclose(np.sqrt(mesh.radius2[:nt]), r_raw, rtol=1e-9)
    # validity on the torus: every circumradius below a quarter of the shorter period
    assert r.max() < min(state.lx, state.ly) / 4
    # offsets are normalised (minimum 0 on each axis)
    assert np.all(to.min(axis=1) == 0)
    # the per-vertex caches equal a fresh walk round each vertex, bit for bit
    hx, hy = np.zeros(64), np.zeros(64)
    for v in range(nv):
        outradius2, far, d_m2_sq, _ = vertex_star(v, mesh, state.prm, hx, hy)
        assert mesh.outradius2[v] == outradius2 == mesh.radius2[far]
        assert mesh.nearest2[v] == d_m2_sq


@pytest.mark.parametrize("lx,ly", [(1.0, 1.0), (0.5, 1.0), (1.0, 0.125)])
def test_initial_grid_is_delaunay(lx, ly):
    validate(empty_torus(lx, ly))


def test_random_insertions_keep_invariants():
    state = empty_torus(1.0, 0.75)
    rng = np.random.default_rng(0)
    for x, y in rng.random((400, 2)) * [1.0, 0.75]:
        assert insert(state, x, y) >= 0
    validate(state)


def test_lattice_insertions_with_cocircular_points():
    """A lattice makes nearly every quadruple cocircular; exact predicates must cope."""
    state = empty_torus(1.0, 1.0)
    g = (np.arange(16) + 0.25) / 16
    pts = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    for x, y in pts:
        assert insert(state, x, y) >= 0
    validate(state)
    # circumcenters of lattice cells: distinct triangles share them
    for x, y in pts[:40] + 0.5 / 16:
        insert(state, x, y)
    validate(state)


def test_insertion_on_an_existing_vertex_is_refused():
    state = empty_torus(1.0, 1.0)
    rng = np.random.default_rng(1)
    pts = rng.random((50, 2))
    for x, y in pts:
        insert(state, x, y)
    before = int(state.cnt[C_NV])
    for x, y in pts[:10]:
        assert insert(state, x, y) == INSERT_NOT_IN_SEED
    assert int(state.cnt[C_NV]) == before
    validate(state)


def test_points_on_the_seam_and_near_grid_resolution():
    state = empty_torus(1.0, 1.0)
    for x, y in [(0.0, 0.0), (1.0 - Q, 0.5), (0.5, 1.0 - Q), (0.3, 0.0), (0.0, 0.7)]:
        assert insert(state, x, y) >= 0
    validate(state)
    rng = np.random.default_rng(2)
    base = rng.random((20, 2))
    for x, y in np.concatenate([base, base + 2**-30, base - 2**-40]) % 1.0:
        insert(state, x, y)
    validate(state)


def test_vertex_star_gives_aspect():
    state = empty_torus(1.0, 1.0)
    rng = np.random.default_rng(3)
    for x, y in rng.random((200, 2)):
        insert(state, x, y)
    nv = int(state.cnt[C_NV])
    hx = np.zeros(64)
    hy = np.zeros(64)
    torus = SimpleNamespace(
        period=(1.0, 1.0),
        origin=(0.0, 0.0),
        vertices=state.mesh.xy[:nv],
        triangles=state.mesh.corners[: 2 * nv],
        offsets=state.mesh.offsets[: 2 * nv],
    )
    facts = oracle.torus_facts(torus, np.zeros((0, 2)))
    for v in range(nv):
        outradius2, far_corner, d_m2_sq, degree = vertex_star(v, state.mesh, state.prm, hx, hy)
        assert np.isclose(np.sqrt(outradius2), facts["R"][v])
        assert np.isclose(2 * np.sqrt(outradius2 / d_m2_sq), facts["aspect"][v])
        assert degree == np.count_nonzero(state.mesh.corners[: 2 * nv] == v)


def test_refined_meshes_are_valid_triangulations():
    rng = np.random.default_rng(4)
    for periodic in (True, False):
        pts = rng.random((2000, 2))
        mesh = knnrefine.refine(pts, 5, 3.0, periodic=periodic, box=(0, 0, 1, 1))
        t = mesh.torus
        problems = verify_triangulation(
            t.vertices, t.triangles, t.offsets, t.neighbours, np.array(t.period)
        )[0]
        assert not problems, problems
        if periodic:
            # F = 2V on the torus for the returned mesh itself
            assert len(mesh.triangles) == 2 * len(mesh.vertices)


@pytest.mark.parametrize("lattice", [False, True], ids=["random", "lattice"])
def test_local_delaunay_check_agrees_with_every_circle_against_every_vertex(lattice):
    """Issue 52: certify decides the empty-circle property edge by edge (filtered incircle,
    integers where the filter cannot tell; the Delaunay lemma on the periodic cover). Against
    the brute-force oracle (every circumcircle against every copy of every vertex, exact
    rationals), on a refined torus (cocircular vertices on a lattice included) and after a
    flip that breaks it: the same verdict, and a broken flip is caught."""
    rng = np.random.default_rng(7)
    if lattice:
        g = (np.arange(20) + 0.5) / 20
        pts = np.column_stack([np.repeat(g, 20), np.tile(g, 20)])
    else:
        pts = rng.random((1500, 2))
    mesh = knnrefine.refine(pts, 5, 3.0, periodic=True, box=(0, 0, 1, 1))
    t = mesh.torus
    period = np.array(t.period)
    tri, off, nb = (np.array(a, np.int64) for a in (t.triangles, t.offsets, t.neighbours))
    problems = verify_triangulation(t.vertices, tri, off, nb, period)[0]
    torus = SimpleNamespace(period=period, origin=(0.0, 0.0), vertices=t.vertices,
                            triangles=tri, offsets=off)  # fmt: skip
    assert not problems and oracle.torus_facts(torus, np.zeros((0, 2)))["empty"]
    # flip one edge of a convex quad whose far corner lies strictly outside: the two new
    # triangles are valid and counter-clockwise, but not Delaunay
    for f in range(len(tri)):
        i = 0
        n = nb[f, i]
        j = int(np.flatnonzero(nb[n] == f)[0])
        a, b, c = tri[f, i], tri[f, (i + 1) % 3], tri[f, (i + 2) % 3]
        shift = off[f, (i + 1) % 3] - off[n, (j + 2) % 3]
        d, od = tri[n, j], off[n, j] + shift
        pa, pb, pc = (
            t.vertices[v] + o * period
            for v, o in ((a, off[f, i]), (b, off[f, (i + 1) % 3]), (c, off[f, (i + 2) % 3]))
        )
        pd = t.vertices[d] + od * period  # fmt: skip
        cross = lambda u, v, w: (v[0] - u[0]) * (w[1] - u[1]) - (v[1] - u[1]) * (w[0] - u[0])  # noqa: E731
        if cross(pa, pb, pd) > 1e-9 and cross(pa, pd, pc) > 1e-9:
            break
    flipped = tri.copy()
    flipped_off = off.copy()
    flipped[f] = [a, b, d]
    flipped_off[f] = [off[f, i], off[f, (i + 1) % 3], od]
    flipped[n] = [a, d, c]
    flipped_off[n] = [off[f, i], od, off[f, (i + 2) % 3]]
    # neighbours rebuilt by brute force over edges with offsets
    new_nb = oracle_neighbours(flipped, flipped_off)
    problems = verify_triangulation(t.vertices, flipped, flipped_off, new_nb, period)[0]
    assert any("locally Delaunay" in p for p in problems), problems


def oracle_neighbours(tri, off):
    """The triangle across each edge, by brute force over edges and relative offsets."""
    found = {}
    for f in range(len(tri)):
        for i in range(3):
            a, b = (i + 1) % 3, (i + 2) % 3
            key = (tri[f, a], tri[f, b], *(off[f, b] - off[f, a]))
            found[key] = (f, i)
    nb = np.full(tri.shape, -1, np.int64)
    for (va, vb, *d), (f, i) in found.items():
        g = found.get((vb, va, *(-np.array(d))))
        if g is not None:
            nb[f, i] = g[0]
    return nb
