"""kNNRefine on the sphere: the engine's triangulation against qhull, refinement against a
brute-force great-circle oracle (haversine distances, no kd-tree, no engine code), certify
against broken meshes, and the input checks."""

import warnings

import numpy as np
import pytest
from scipy.spatial import ConvexHull

import knnrefine
from knnrefine.datasets import earthquakes
from knnrefine.errors import BudgetError, FloorWarning, InputError

RNG = np.random.default_rng(31)


def haversine(a, b):
    """Great-circle angles (len(a), len(b)) between lon/lat degree points, written out."""
    lon1, lat1 = np.radians(a[:, 0])[:, None], np.radians(a[:, 1])[:, None]
    lon2, lat2 = np.radians(b[:, 0])[None], np.radians(b[:, 1])[None]
    h = (
        np.sin((lat2 - lat1) / 2) ** 2
        + np.cos(lat1) * np.cos(lat2) * np.sin((lon2 - lon1) / 2) ** 2
    )
    return 2 * np.arcsin(np.sqrt(np.minimum(h, 1.0)))


def uniform(n, rng=RNG):
    return np.column_stack(
        [rng.uniform(-180, 180, n), np.degrees(np.arcsin(rng.uniform(-1, 1, n)))]
    )


def clustered(n, rng=RNG):
    centres = uniform(5, rng)
    parts = [c + rng.normal(0, 2.0, (n // 5, 2)) for c in centres]
    pts = np.concatenate(parts)
    pts[:, 1] = np.clip(pts[:, 1], -90, 90)
    return pts


def polar(n, rng=RNG):
    return np.column_stack([rng.uniform(-180, 180, n), 90 - rng.exponential(3.0, n)])


def antimeridian(n, rng=RNG):
    lon = 180 + rng.normal(0, 3, n)
    return np.column_stack([(lon + 180) % 360 - 180, rng.normal(0, 10, n)])


INPUTS = {"uniform": uniform, "clustered": clustered, "polar": polar,
          "antimeridian": antimeridian}  # fmt: skip


@pytest.mark.parametrize("k", [1, 10, 100])
@pytest.mark.parametrize("name", sorted(INPUTS))
def test_sphere_mesh_meets_the_guarantee_by_brute_force(name, k):
    pts = INPUTS[name](1500, np.random.default_rng(k))
    options = {"min_size": 0.03} if k == 1 else {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FloorWarning)
        mesh = knnrefine.refine(pts, k, sphere=True, **options)
    assert mesh.on_sphere and mesh.triangles.shape == (2 * len(mesh.vertices) - 4, 3)
    # the oracle: every great-circle distance by haversine, nothing shared with the engine
    rng = np.random.default_rng(0)
    some = rng.choice(len(mesh.vertices), min(500, len(mesh.vertices)), replace=False)
    probes = np.concatenate([uniform(2000, rng), pts[:500], mesh.vertices[some]])
    d_pk = np.partition(haversine(probes, pts), k - 1, axis=1)[:, k - 1]
    d_m2 = np.partition(haversine(probes, mesh.vertices), 1, axis=1)[:, 1]
    above = d_pk >= mesh.min_size
    assert above.sum() > 500
    ratio = d_m2[above] / d_pk[above]
    assert mesh.alpha <= ratio.min() and ratio.max() <= mesh.beta
    np.testing.assert_allclose(mesh.d_m2(probes), d_m2, rtol=1e-9, atol=1e-12)
    # circumcaps above the floor hold < k points: the cap of each triangle from its corners
    xyz = mesh.xyz
    a, b, c = (xyz[mesh.triangles[:, i]] for i in range(3))
    centre = np.cross(b - a, c - a)
    centre /= np.linalg.norm(centre, axis=1, keepdims=True)
    cap = np.arccos(np.clip(np.einsum("ij,ij->i", centre, a), -1, 1))
    cen = np.column_stack([np.degrees(np.arctan2(centre[:, 1], centre[:, 0])),
                           np.degrees(np.arcsin(np.clip(centre[:, 2], -1, 1)))])  # fmt: skip
    big = np.flatnonzero(cap >= mesh.min_size)  # (at most 4,000 of them, the oracle's cost)
    big = big[rng.permutation(len(big))[:4000]]
    held = (haversine(cen[big], pts) <= cap[big, None] * (1 + 1e-9)).sum(axis=1)
    assert held.max(initial=0) < k
    cert = knnrefine.certify(mesh, pts, samples=20_000, n_random=5_000)
    assert cert.passed, str(cert)


def _sphere_of(x):
    """(mesh, counters): the Delaunay triangulation of the unit vectors x (up to 3,000),
    inserted one by one into the tetrahedron."""
    from knnrefine._engine.state import C_NT, C_NV, N_COUNTERS
    from knnrefine._engine.triangulation_sphere import (
        insert_points_sphere,
        new_sphere,
        new_sphere_scratch,
    )

    mesh, nv, nt = new_sphere(4000, 8000)
    scratch = new_sphere_scratch(4000, 8000, 4096)
    cnt = np.zeros(N_COUNTERS, np.int64)
    cnt[C_NV], cnt[C_NT] = nv, nt
    assert insert_points_sphere(x, mesh, scratch, cnt) == len(x)
    return mesh, cnt


def test_sphere_triangulation_is_the_convex_hull():
    """The engine's incremental insertion against qhull, vertex by vertex order kept."""
    from knnrefine._engine.state import C_NT, C_NV

    x = RNG.normal(size=(3000, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    mesh, cnt = _sphere_of(x)
    xyz = mesh.xyz[: cnt[C_NV]]
    tri = mesh.corners[: cnt[C_NT]]
    hull = ConvexHull(xyz)
    assert {tuple(sorted(t)) for t in tri} == {tuple(sorted(t)) for t in hull.simplices}
    det = np.einsum("ij,ij->i", xyz[tri[:, 0]], np.cross(xyz[tri[:, 1]], xyz[tri[:, 2]]))
    assert (det > 0).all()


def test_sphere_walk_steps_towards_the_point_not_its_antipode():
    """Regression: the walk crossed the edges p lies inside of, so it ended in the triangle
    antipodal to p (a scan of every triangle hid it from insertion, not from a continued
    run's reopening, which found the wrong cavity and refined nothing new)."""
    from knnrefine._engine.jit import python_entry
    from knnrefine._engine.state import C_NT
    from knnrefine._engine.triangulation_sphere import locate_sphere

    x = RNG.normal(size=(2000, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    mesh, cnt = _sphere_of(x)
    nt = int(cnt[C_NT])
    walk = python_entry(locate_sphere)
    pts = np.zeros((4, 3))
    for p in RNG.normal(size=(200, 3)):
        p /= np.linalg.norm(p)
        t = walk(p, int(RNG.integers(nt)), mesh, pts, nt, False)
        a, b, c = mesh.xyz[mesh.corners[t]]
        normal = np.cross(b - a, c - a)
        normal /= np.linalg.norm(normal)  # the circumcap's centre
        assert np.sum((p - normal) ** 2) <= mesh.chord2[t] * (1 + 1e-9)  # it holds p


def test_sphere_insertion_too_close_to_a_vertex_is_refused():
    """A point within rounding of a vertex must not swallow it: refused, nothing changed."""
    from knnrefine._engine.state import C_NT, C_NV, N_COUNTERS
    from knnrefine._engine.triangulation_sphere import (
        insert_points_sphere,
        new_sphere,
        new_sphere_scratch,
    )

    mesh, nv, nt = new_sphere(64, 128)
    scratch = new_sphere_scratch(64, 128, 4096)
    cnt = np.zeros(N_COUNTERS, np.int64)
    cnt[C_NV], cnt[C_NT] = nv, nt
    before = mesh.corners[:4].copy()
    north = np.array([[0.0, 0.0, 1.0 + 2e-16]])  # beyond the pole vertex: would swallow it
    assert insert_points_sphere(north, mesh, scratch, cnt) == 0
    assert cnt[C_NV] == 4 and (mesh.corners[:4] == before).all()


def broken(mesh, **changes):
    from dataclasses import replace

    return replace(mesh, **changes)


def test_certify_on_the_sphere_fails_broken_meshes():
    pts = uniform(3000)
    mesh = knnrefine.refine(pts, 10, sphere=True)
    assert knnrefine.certify(mesh, pts, samples=5000, n_random=2000).passed
    # a flipped triangle
    tri = mesh.triangles.copy()
    tri[0] = tri[0, ::-1]
    cert = knnrefine.certify(broken(mesh, cells=tri), pts, samples=5000, n_random=2000)
    assert not cert.passed and cert.triangulation_problems
    # a vertex moved: the triangulation is no longer Delaunay, degrees no longer the vectors
    xyz = mesh.xyz.copy()
    v = mesh.triangles[0, 0]
    xyz[v] = xyz[mesh.triangles[0, 1]] * 0.9 + xyz[v] * 0.1
    xyz[v] /= np.linalg.norm(xyz[v])
    cert = knnrefine.certify(broken(mesh, xyz=xyz), pts, samples=5000, n_random=2000)
    assert not cert.passed and cert.mesh_problems
    # a mesh refined with a larger k does not hold for a smaller one
    coarse = knnrefine.refine(pts, 40, sphere=True)
    cert = knnrefine.certify(broken(coarse, k=10), pts, samples=5000, n_random=2000)
    assert not cert.passed and cert.max_ball_count >= 10
    # points that are not the mesh's
    with pytest.raises(InputError, match="3,000 points"):
        knnrefine.certify(mesh, pts[:100])


def test_sphere_weights_and_radius():
    pts = uniform(4000)
    w = RNG.uniform(0, 3, len(pts))
    mesh = knnrefine.refine(pts, 25.5, sphere=True, weights=w, radius=6371.0088)
    cert = knnrefine.certify(mesh, pts, weights=w, samples=5000, n_random=2000)
    assert cert.passed, str(cert)
    q = uniform(300)
    d = np.sort(haversine(q, mesh.vertices), axis=1)[:, 1] * 6371.0088
    np.testing.assert_allclose(mesh.d_m2(q), d, rtol=1e-9)
    assert mesh.min_size == pytest.approx(1e-6 * np.pi * 6371.0088)
    # whole weights are repeated points: the same mesh
    twice = knnrefine.refine(pts[:1000], 10, sphere=True, weights=np.full(1000, 2.0))
    repeated = knnrefine.refine(np.repeat(pts[:1000], 2, axis=0), 10, sphere=True)
    np.testing.assert_array_equal(twice.xyz, repeated.xyz)


def test_sphere_unit_vectors_and_lonlat_give_one_mesh():
    pts = uniform(2000)
    lon, lat = np.radians(pts[:, 0]), np.radians(pts[:, 1])
    xyz = np.column_stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    a = knnrefine.refine(pts, 10, sphere=True)
    b = knnrefine.refine(xyz, 10, sphere=True)
    np.testing.assert_allclose(a.xyz, b.xyz, atol=1e-12)
    assert knnrefine.certify(b, xyz, samples=5000, n_random=2000).passed


def test_sphere_on_real_earthquakes():
    quakes = earthquakes()
    mesh = knnrefine.refine(quakes, 30, sphere=True, radius=6371.0088)
    cert = knnrefine.certify(mesh, quakes, samples=20_000, n_random=5_000)
    assert cert.passed, str(cert)
    # denser along the Pacific rim than in the middle of the Pacific: a shorter d_M2 in Japan
    japan, pacific = [[142.0, 38.0]], [[-150.0, -5.0]]
    assert mesh.d_m2(japan)[0] < 0.2 * mesh.d_m2(pacific)[0]


@pytest.mark.parametrize(
    "points, options, message",
    [
        ([[0.0, 91.0], [1.0, 2.0]], {}, "latitude"),
        ([[45.0, 120.0], [10.0, 170.0]], {}, "swapped"),
        ([[1.0, 2.0, 3.0]], {}, "unit vectors"),
        ([[0.0, 0.0]] * 5, {"box": (-180, -90, 180, 90)}, "no box"),
        ([[0.0, 0.0]] * 5, {"periodic": True}, "no box"),
        ([[0.0, 0.0]] * 5, {"workers": 2, "executor": object()}, "concurrent.futures"),
        ([[0.0, 0.0]] * 5, {"workers": 0}, "positive integer"),
        ([[0.0, 0.0]] * 5, {"radius": -1.0}, "radius"),
        ([[0.0, 0.0]] * 5, {"k": 6}, "larger than the number of points"),
        ([[0.0, np.nan]] * 5, {}, "NaN"),
    ],
)
def test_sphere_bad_input_is_refused_before_work(points, options, message):
    options = {"k": 1, **options}
    with pytest.raises(InputError, match=message):
        knnrefine.refine(points, sphere=True, **options)


def test_radius_without_sphere_is_refused():
    with pytest.raises(InputError, match="sphere=True"):
        knnrefine.refine(uniform(100), 5, radius=2.0)


def test_sphere_budget_names_k_equal_one():
    with pytest.raises(BudgetError, match="k = 1"):
        knnrefine.refine(uniform(2000), 1, sphere=True, max_vertices=5000)


def test_sphere_plane_only_methods_say_so():
    mesh = knnrefine.refine(uniform(500), 10, sphere=True)
    with pytest.raises(InputError, match="sphere"):
        mesh.flat()
    assert "sphere" in repr(mesh)
