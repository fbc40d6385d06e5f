"""certify's own kernels (issue 52) against independent oracles: its kd-tree's counts, k-th
distances and Voronoi cells against brute force over all points (periodic axes, weights,
duplicates, a k beyond a leaf), and its filtered predicates against exact rationals."""

from fractions import Fraction

import numpy as np
import pytest

from knnrefine._engine.jit import python_entry
from knnrefine.certify import _predicates as P
from knnrefine.certify._tree import Tree, spatial_order


def _brute_d2(x, pts, period):
    g = np.abs(x[:, None, :] - pts[None, :, :])
    if period is not None:
        g = np.where(period > 0, np.minimum(g, period - g), g)
    return (g**2).sum(-1)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("periodic", [False, True], ids=["box", "torus"])
def test_tree_answers_equal_brute_force(dim, periodic):
    rng = np.random.default_rng(dim + 2 * periodic)
    pts = rng.random((1500, dim))
    pts[:40] = pts[0]  # duplicates: a node of coinciding points
    period = np.ones(dim) if periodic else None
    x = np.concatenate([rng.random((400, dim)), pts[:50]])
    d2 = _brute_d2(x, pts, period)
    tree = Tree(pts, None, period, 2)
    for k in (1, 7, 45, 200):
        want = np.sqrt(np.sort(d2, axis=1)[:, k - 1])
        np.testing.assert_allclose(tree.kth(x, k), want, rtol=1e-12)
        # in the order given (each query bounding the next), the same
        order = spatial_order(x)
        np.testing.assert_allclose(tree.kth(x[order], k, sort=False), want[order], rtol=1e-12)
    r = rng.random(len(x)) * 0.3
    held = (d2 <= r[:, None] ** 2).sum(1)
    np.testing.assert_array_equal(tree.held(x, r), held)
    stopped = tree.held(x, r, stop=5)
    assert ((stopped >= 5) == (held >= 5)).all() and (stopped[held < 5] == held[held < 5]).all()
    # weighted, a third of the points weightless (left out, as certify does)
    w = rng.random(len(pts))
    w[::3] = 0
    heavy = w > 0
    wt = Tree(pts[heavy], w[heavy], period, 2)
    order = np.argsort(d2, axis=1)
    run = np.cumsum(w[order], axis=1)
    for k in (0.5, 3.3, 40.0):
        first = np.argmax(run >= k, axis=1)
        want = np.sqrt(np.take_along_axis(d2, order, 1)[np.arange(len(x)), first])
        np.testing.assert_allclose(wt.kth(x, k), want, rtol=1e-12)
    np.testing.assert_allclose(wt.held(x, r), (w * (d2 <= r[:, None] ** 2)).sum(1), rtol=1e-12)


def _brute_kth(x, pts, period, k, w=None):
    """The least radius about each x holding weight k, by brute force in chunks."""
    return _brute_kths(x, pts, period, [k], w)[0]


def _brute_kths(x, pts, period, ks, w=None):
    """``_brute_kth`` for each k of ``ks``, the distances sorted once: of each row only the
    nearest points whose weights can reach max(ks) (max(ks) / the least weight of them, by
    numpy's partition), then those sorted and their weights summed in order."""
    weight = np.ones(len(pts)) if w is None else np.asarray(w, float)
    least = float(weight.min()) if len(weight) else 0.0
    most = len(pts)
    if least > 0:
        most = min(len(pts), int(np.ceil(max(ks) * (1 - 1e-9) / least)))
    out = np.empty((len(ks), len(x)))
    for a in range(0, len(x), 100):
        d2 = _brute_d2(x[a : a + 100], pts, period)
        if most < len(pts):
            idx = np.argpartition(d2, most - 1, axis=1)[:, :most]
            d2 = np.take_along_axis(d2, idx, 1)
        else:
            idx = np.broadcast_to(np.arange(len(pts)), d2.shape)
        order = np.argsort(d2, axis=1)
        run = np.cumsum(weight[np.take_along_axis(idx, order, 1)], axis=1)
        near = np.take_along_axis(d2, order, 1)
        for j, k in enumerate(ks):
            first = np.argmax(run >= k - 1e-9 * k, axis=1)
            out[j, a : a + 100] = np.sqrt(near[np.arange(len(d2)), first])
    return out


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("periodic", [False, True], ids=["box", "torus"])
def test_kth_read_from_bucketed_windows_equals_brute_force(dim, periodic):
    """Issue 52: a k-th query reads the ball of (1 + GUESS) times the answer before it from
    a window sorted into buckets. Windows of hundreds of points (k up to 150, so that
    buckets are used), points and queries on the cut (0 and just below the period), in
    clusters and coinciding: the distances are brute force's."""
    rng = np.random.default_rng(17 + dim + 2 * periodic)
    n = 12_000
    centres = rng.random((20, dim))
    pts = np.concatenate([
        rng.random((n // 2, dim)),
        np.mod(centres[rng.integers(0, 20, n // 4)] + rng.normal(0, 0.01, (n // 4, dim)), 1),
        np.column_stack([rng.choice([0.0, 1.0 - 2**-40], n // 4),
                         rng.random((n // 4, dim - 1))]),
    ])  # fmt: skip
    pts[:30] = pts[-1]  # coinciding, on the cut
    period = np.ones(dim) if periodic else None
    x = np.concatenate([rng.random((600, dim)), pts[rng.integers(0, n, 400)]])
    x[:50, 0] = 0.0
    tree = Tree(pts, None, period, 2)
    for k, expected in zip((60, 150), _brute_kths(x, pts, period, (60, 150)), strict=True):
        np.testing.assert_allclose(tree.kth(x, k), expected, rtol=1e-12)
    w = rng.random(n) + 0.01
    np.testing.assert_allclose(Tree(pts, w, period, 2).kth(x, 40.0),
                               _brute_kth(x, pts, period, 40.0, w), rtol=1e-12)  # fmt: skip


@pytest.mark.parametrize("layout", ["random", "lattice"])
def test_cells_held_equals_each_points_nearest_sites(layout):
    """Closed Voronoi cells from each site's Delaunay neighbours (scipy's triangulation of
    the sites here) against every point's nearest sites by brute force, ties counted for
    each: asked of the tree cell by cell (``cells_held``) and, issue 52, walked point by
    point to the nearest site with its ties (``nearest_counts``). On a lattice every point
    at a square's centre ties with four sites, two of them not neighbours of the other
    two (the square's other diagonal), and the points on its edges with two; weighted
    too."""
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(3)
    if layout == "random":
        sites = rng.random((300, 2)) * 1.2 - 0.1
        pts = np.concatenate([rng.random((5000, 2)), sites[:20]])  # points on sites, too
    else:
        g = np.arange(-2, 23) / 20
        sites = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
        h = np.arange(0, 40) / 40  # the sites, the squares' centres and edges' midpoints
        pts = np.concatenate([np.stack(np.meshgrid(h, h), -1).reshape(-1, 2),
                              rng.random((2000, 2))])  # fmt: skip
    tri = Delaunay(sites).simplices
    a = np.concatenate([tri[:, i] for i in range(3) for _ in range(2)])
    b = np.concatenate([tri[:, (i + s) % 3] for i in range(3) for s in (1, 2)])
    key = np.unique(a * len(sites) + b)
    a, b = key // len(sites), key % len(sites)
    first = np.searchsorted(a, np.arange(len(sites) + 1))
    d2 = _brute_d2(pts, sites, None)
    near = d2 <= d2.min(1, keepdims=True) * (1 + 2e-12)
    assert layout == "random" or near.sum(1).max() == 4
    w = rng.random(len(pts))
    for weights in (None, w):
        tree = Tree(pts, weights, None, 2)
        want = near.sum(0) if weights is None else (near * w[:, None]).sum(0)
        none = np.zeros((len(b), 0), np.int16)  # (no shifts: the sites do not wrap)
        got = tree.cells_held(sites, first, b, none, np.zeros(2), np.full(len(sites), 3.0))
        np.testing.assert_allclose(got, want, rtol=1e-12)
        walked = tree.nearest_counts(sites, first, b, np.zeros(2))
        np.testing.assert_allclose(walked, want, rtol=1e-12)


def _exact(kind, rows):
    """The sign from Fractions: the determinant of the rows less the last (lifted for the
    in-circle and in-sphere tests), as Shewchuk orients them."""
    q = [[Fraction(float(v)) for v in r] for r in rows]
    rel = [[u - v for u, v in zip(r, q[-1], strict=True)] for r in q[:-1]]
    if kind in ("incircle", "insphere"):
        rel = [r + [sum(v * v for v in r)] for r in rel]
    m = np.array(rel, dtype=object)

    def det(a):
        if len(a) == 1:
            return a[0][0]
        return sum((-1) ** j * a[0][j] * det(np.delete(a[1:], j, axis=1)) for j in range(len(a)))

    d = det(m)
    return (d > 0) - (d < 0)


@pytest.mark.parametrize("lattice", [False, True], ids=["random", "lattice"])
def test_filtered_predicates_agree_with_rationals(lattice):
    """Where the float filter decides it agrees with exact rationals; where it cannot, the
    integer fallback (``exact_sign``) does."""
    orient2d = python_entry(P.orient2d)
    incircle = python_entry(P.incircle)
    orient3d_at = python_entry(P.orient3d_at)
    rng = np.random.default_rng(9)
    unsure = 0
    for _ in range(300):
        p = rng.random((5, 3))
        if lattice:  # degenerate: cocircular and coplanar sets are common
            p = np.round(p * 3) / 3
        s2 = orient2d(*p[:3, :2].ravel())
        c2 = incircle(*p[:4, :2].ravel())
        s3 = orient3d_at(*p[:4].ravel())
        for kind, got, rows in (("orient2d", s2, p[:3, :2]), ("incircle", c2, p[:4, :2]),
                                ("orient3d", s3, p[:4])):  # fmt: skip
            want = _exact(kind, rows)
            assert P.exact_sign(kind, rows) == want
            if got == P.UNSURE:
                unsure += 1
            else:
                assert got == want
    assert unsure > 0 or not lattice  # the lattice reaches the fallback: the test can fail


@pytest.mark.parametrize("threads", [1, 3])
def test_neighbour_lists_keep_each_neighbour_once_sorted(threads, monkeypatch):
    """``neighbour_lists`` (every corner of a cell a neighbour of every other, a site's
    rows placed a range of sites at a time, deduplicated by stamps, then sorted) against sets:
    every (index, shift) once, in sorted order, the shift the neighbour's offset less the
    site's, on random cells of 2 to 4 corners with repeated cells and vertices, offsets in
    0 to 3 dimensions and sites in no cell; in three ranges of sites, on one thread and
    three. In int64 and in the engine's int32 cells with int8 offsets (read as they
    are; their differences, up to 254, in int16)."""
    from knnrefine.certify import _tree
    from knnrefine.certify._tree import neighbour_lists

    monkeypatch.setattr(_tree, "SITE_BLOCKS", 3)
    rng = np.random.default_rng(54)
    for trial in range(200):
        m, t, d = int(rng.integers(1, 30)), int(rng.integers(0, 80)), int(rng.integers(0, 4))
        c = int(rng.integers(2, 5))
        cells = rng.integers(0, m, (t, c))
        cells[t // 2 :] = cells[: t - t // 2]  # cells repeated
        off = np.ascontiguousarray(rng.integers(-1, 2, (t, c, d)))
        if trial % 2:  # the engine's types, offsets at int8's ends
            off[rng.random(off.shape) < 0.2] = 127
            off[rng.random(off.shape) < 0.2] = -128
            cells, off = cells.astype(np.int32), off.astype(np.int8)
        first, nb, sh = neighbour_lists(cells, off, m, threads)
        for v in range(m):
            want = sorted({(int(cells[i, y]), *map(int, off[i, y].astype(int) - off[i, x]))
                           for i in range(t) for x in range(c) for y in range(c)
                           if x != y and cells[i, x] == v})  # fmt: skip
            got = [(int(nb[i]), *map(int, sh[i])) for i in range(first[v], first[v + 1])]
            assert got == want


def test_tile_classes_against_dictionaries_of_keys():
    """``common._tile_classes`` (check_cells_tile's classes, issue 52: each vertex's cells
    and facets compared among themselves, no key held for every facet) against Python
    dictionaries of every cell's and facet's key (its corners as (vertex, offsets less the
    least) sorted): the cells equal to an earlier one, the classes of more than two equal
    facets, the facets no other equals; in 2 and 3 dimensions, on few vertices (many
    repeats, vertices twice in a cell) and many, on one thread and in ranges of a few
    vertices."""
    from knnrefine.certify._tree import incidence
    from knnrefine.certify.common import CODE_BASE, _tile_classes

    def key(cell, o, corners):
        least = [min(o[j][a] for j in corners) for a in range(len(o[0]))]
        return tuple(sorted((int(cell[j]), *(int(o[j][a] - least[a]) for a in range(len(least))))
                            for j in corners))  # fmt: skip

    rng = np.random.default_rng(55)
    for d in (2, 3):
        for m, t in ((4, 300), (60, 400)):
            cells = rng.integers(0, m, (t, d + 1))
            cells[t // 3 : t // 2] = cells[: t // 2 - t // 3]  # some cells again
            off = rng.integers(-1, 2, (t, d + 1, d)).astype(np.int8)
            off[t // 3 : t // 2] = off[: t // 2 - t // 3]
            seen, facets = {}, {}
            repeats = 0
            for q in range(t):
                k = key(cells[q], off[q], range(d + 1))
                repeats += k in seen
                seen.setdefault(k, q)
                for i in range(d + 1):
                    facets.setdefault(key(cells[q], off[q], [j for j in range(d + 1) if j != i]),
                                      []).append(i * t + q)  # fmt: skip
            many = sum(len(f) > 2 for f in facets.values())
            alone_want = np.zeros((d + 1) * t, bool)
            alone_want[[f[0] for f in facets.values() if len(f) == 1]] = True
            first, incident = incidence(cells, m)
            widest = (d + 1) * int(np.diff(first).max())
            for ranges in (1, 7):
                alone = np.zeros((d + 1) * t, bool)
                edges = np.linspace(0, m, ranges + 1).astype(int)
                got = [_tile_classes(cells, off, first, incident, widest, CODE_BASE, alone,
                                     edges[j], edges[j + 1]) for j in range(ranges)]  # fmt: skip
                assert sum(r for r, _ in got) == repeats > 0
                assert sum(f for _, f in got) == many
                np.testing.assert_array_equal(alone, alone_want)


def test_size_sample_gives_the_integral_a_share_of_the_cells_and_the_rest_to_the_ratio():
    """Issue 52: the size integral asks d_{P,k} at one random point in each of
    min(t, ``samples`` // SIZE_SHARE) distinct cells; the other samples (up to ``samples``
    // t per cell in all, or one in each of ``samples`` distinct cells of a large mesh) only
    probe the ratio, bounded by their cell's corners."""
    from knnrefine.certify.common import SIZE_SHARE, size_sample

    rng = np.random.default_rng(0)
    chosen, dense = size_sample(100, 40, rng)  # a large mesh: 40 distinct cells
    assert len(chosen) == 40 // SIZE_SHARE and len(dense) == 40 - len(chosen)
    assert len(np.unique(np.concatenate([chosen, dense]))) == 40
    chosen, dense = size_sample(100, 150, rng)  # one point a cell
    assert len(chosen) == 150 // SIZE_SHARE == len(np.unique(chosen))
    assert np.array_equal(np.sort(np.concatenate([chosen, dense])), np.arange(100))
    chosen, dense = size_sample(100, 1000, rng)  # ten a cell, the integral one in each
    assert np.array_equal(chosen, np.arange(100))
    assert np.array_equal(np.bincount(dense, minlength=100), np.full(100, 9))


def test_size_integral_with_its_control_variate_is_unbiased_and_its_error_honest():
    """Issue 52: the size integral subtracts the integrand's mean over each cell's corners
    (integrated exactly) and samples the rest at one point in each of s of the t cells.
    Against a fine quadrature of a known integrand on a triangulated square: the mean of
    400 estimates is the integral, their spread is at most the standard error reported (it
    is conservative), and that error is well below plain sampling's. Cells with a corner
    not kept (-1) are estimated whole, still without bias."""
    from knnrefine.certify.common import SizeSample, size_integral
    from knnrefine.mesh import triangle_areas, uniform_in_triangles

    n = 24
    g = np.arange(n + 1) / n
    V = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    T = np.concatenate([np.column_stack([a, a + n + 1, a + n + 2]),
                        np.column_stack([a, a + n + 2, a + 1])])  # fmt: skip
    t = len(T)
    area = np.abs(triangle_areas(V[T]))

    def d(x):
        return 0.3 + x[:, 0] + 0.5 * x[:, 1] ** 2

    fine = (np.arange(2000) + 0.5) / 2000
    q = np.stack(np.meshgrid(fine, fine), -1).reshape(-1, 2)
    exact = float(np.mean(1.0 / d(q) ** 2))
    rng = np.random.default_rng(5)
    s = 300
    for dropped in (False, True):
        at = s + np.arange(len(V))  # the vertices' rows follow the s samples
        if dropped:  # vertices not kept: their cells estimated whole
            at[::7] = -1
        est, err, plain = [], [], []
        for _ in range(400):
            cells = np.sort(rng.choice(t, s, replace=False))
            x, _ = uniform_in_triangles(V[T[cells]], rng.random((s, 2)))
            d_pk = np.concatenate([d(x), d(V)])
            sample = SizeSample(np.ones(s, bool), area[cells], cells, T, area, t, at)
            total, stderr = size_integral(sample, d_pk, 0.0, 2)
            est.append(total)
            err.append(stderr)
            plain.append(t / s * float(np.sum(area[cells] / d(x) ** 2)))
        spread = float(np.std(est))
        assert abs(np.mean(est) - exact) < 4 * spread / np.sqrt(len(est))
        assert spread <= 1.15 * np.mean(err)
        if not dropped:
            assert np.mean(err) < 0.2 * np.std(plain)


@pytest.mark.parametrize(
    "domain", ["plane", "plane-lattice", "plane-line", "plane-few", "space", "space-few", "sphere"]
)
def test_d_m2_walked_on_the_triangulation_equals_brute_force(domain, monkeypatch):
    """Issue 52: d_{M,2} at the probes walked on the verified triangulation (to the nearest
    vertex by nearer neighbours, the second nearest among its neighbours) against every
    vertex by brute force: on the torus across its cut and at its vertices, on a lattice
    (every distance tied) and on points on a line with repeats, on the sphere at its
    poles; where the triangulation failed its check, the kd-tree answers. The nearest
    vertex the walk ends at (the bound of a uniform probe's d_{P,k}) is the nearest. The
    walk measures each vertex's nearest copy: on a torus of a few vertices (its initial
    ones: "few"), where a neighbour's nearest copy need not be the one its edge reaches,
    too."""
    import knnrefine
    from knnrefine._domains.plane import certify as plane
    from knnrefine._domains.space import certify as space
    from knnrefine._domains.sphere import certify as sphere
    from knnrefine.certify import common
    from knnrefine.certify.common import nearest_site

    monkeypatch.setattr(common, "WALK", 700)  # walked in chunks along the curve
    rng = np.random.default_rng(23)
    if domain == "sphere":
        lon, lat = rng.uniform(-180, 180, 4000), rng.normal(60, 20, 4000).clip(-90, 90)
        mesh = knnrefine.refine(np.column_stack([lon, lat]), 5, sphere=True)
        geometry = sphere.Geometry(mesh, 2)
        sites, period = geometry.xyz, None
        x = rng.normal(size=(3000, 3))
        x[:2] = [[0, 0, 1], [0, 0, -1]]
        x = np.concatenate([x / np.linalg.norm(x, axis=1, keepdims=True), sites[:100]])
    else:
        dim = 3 if domain.startswith("space") else 2
        box = (0,) * dim + (1,) * dim
        pts = rng.random((3000, dim)) ** 2
        k = 5
        if domain.endswith("few"):  # k over half the points: the initial vertices only
            pts, k = rng.random((60, dim)), 40
        if domain == "plane-lattice":
            pts = np.stack(np.meshgrid(*[np.arange(40) / 40] * 2), -1).reshape(-1, 2)
        if domain == "plane-line":
            pts = np.column_stack([rng.random(3000), np.full(3000, 0.5)])
            pts[1000:1500] = pts[:500]
        mesh = knnrefine.refine(pts, k, periodic=True, box=box)
        geometry = (plane if dim == 2 else space).Geometry(mesh, 2)
        sites, period = geometry.vertices, geometry.period
        x = rng.random((3000, dim)) * period
        x[:200, 0] = rng.choice([0.0, period[0] * (1 - 1e-16)], 200)  # on the cut
        x = np.concatenate([x, sites[:100]])
    tri = geometry.triangulation()
    assert not tri.problems
    want = np.sqrt(np.sort(_brute_d2(x, sites, period), axis=1)[:, 1])
    got = geometry.returned_d_m2(x, tri)[0]
    if domain == "sphere":
        want = 2 * np.arcsin(np.minimum(want / 2, 1.0))
    np.testing.assert_allclose(got, want, rtol=1e-12)
    failed = geometry.returned_d_m2(x, tri._replace(problems=["a test"]))[0]
    np.testing.assert_allclose(failed, want, rtol=1e-12)
    cells = geometry.cells(tri)
    walk_period = np.zeros(sites.shape[1]) if period is None else period
    near = nearest_site(cells, x, walk_period, 2, tri)[:, 0]
    d2 = _brute_d2(x, sites, period)
    np.testing.assert_allclose(d2[np.arange(len(x)), near], d2.min(axis=1), rtol=1e-12)
    if period is None:  # the kd-tree's fallback reads plain coordinates
        near = nearest_site(cells, x, walk_period, 2, tri._replace(problems=["a test"]))[:, 0]
        np.testing.assert_allclose(d2[np.arange(len(x)), near], d2.min(axis=1), rtol=1e-12)


def test_a_tree_built_in_the_background_answers_as_one_built_in_place(monkeypatch):
    """Issue 52: the points' tree is built in a thread beside the mesh's checks; its answers
    are those of one built in place (threads asking at once included), and an error in
    the build reaches the caller at the first question."""
    from concurrent.futures import ThreadPoolExecutor

    from knnrefine.certify import _tree

    rng = np.random.default_rng(31)
    pts = rng.random((20_000, 2))
    x = rng.random((2_000, 2))
    here = Tree(pts, None, np.ones(2), 2)
    there = Tree(pts, None, np.ones(2), 2, background=True)
    with ThreadPoolExecutor(4) as pool:
        answers = list(pool.map(lambda k: there.kth(x, k), [1, 5, 30, 30]))
    for k, got in zip([1, 5, 30, 30], answers, strict=True):
        np.testing.assert_array_equal(got, here.kth(x, k))

    def broken(*args):
        raise MemoryError("no room for the tree")

    monkeypatch.setattr(_tree, "_build", broken)
    failing = Tree(pts, None, None, 2, background=True)
    with pytest.raises(MemoryError, match="no room"):
        failing.kth(x, 3)


def test_sphere_edge_twins_against_a_dictionary():
    """Issue 52: each directed edge's reversed twin on the sphere found by a counting sort
    (``_twins``) against a dictionary of the edges: on a mesh's triangles, and None where a
    triangle is dropped (an edge without its twin), doubled or reversed (an edge twice)."""
    import knnrefine
    from knnrefine._domains.sphere.certify import _twins

    rng = np.random.default_rng(41)
    lonlat = np.column_stack([rng.uniform(-180, 180, 500), rng.uniform(-90, 90, 500)])
    tri = np.asarray(knnrefine.refine(lonlat, 5, sphere=True).triangles, np.int64)
    m, t = int(tri.max()) + 1, len(tri)
    got_tri, got_corner = _twins(tri, m)
    at = {(int(tri[f, (c + 1) % 3]), int(tri[f, (c + 2) % 3])): (f, c)
          for f in range(t) for c in range(3)}  # fmt: skip
    for f in range(t):
        for c in range(3):
            a, b = int(tri[f, (c + 1) % 3]), int(tri[f, (c + 2) % 3])
            assert (got_tri[f, c], got_corner[f, c]) == at[(b, a)]
    assert _twins(tri[1:], m) is None  # dropped
    assert _twins(np.concatenate([tri, tri[:1]]), m) is None  # doubled
    flipped = tri.copy()
    flipped[0] = flipped[0, ::-1]
    assert _twins(flipped, m) is None  # reversed: its edges repeat its neighbours'


@pytest.mark.parametrize("dim", [2, 3])
def test_tree_built_along_a_morton_curve_keeps_its_invariants(dim):
    """Issue 52: the tree is built from the points sorted along a Morton curve, split at
    their codes' highest differing bit, and by the sliding midpoint where the codes no
    longer tell them apart (points 1e-12 apart, below the codes' resolution), never
    between coinciding points. Every node's range is its children's, its box the tight
    box of its points, its total their weight; a leaf holds at most LEAF points unless
    they coincide; the points are the input's, permuted."""
    from knnrefine.certify import _tree

    rng = np.random.default_rng(5 + dim)
    pts = np.concatenate([
        rng.random((3000, dim)),
        0.3 + 1e-12 * rng.random((200, dim)),  # closer than the codes resolve
        np.repeat(rng.random((1, dim)), 100, axis=0),  # coinciding
        np.mod(rng.random((1, dim)) + rng.normal(0, 1e-4, (500, dim)), 1),  # a cluster
    ])  # fmt: skip
    w = rng.random(len(pts)) + 0.5
    for weights in (None, w):
        tree = Tree(pts, weights, None, 2)
        P, W, T = tree.pts, tree.weights_of(np.arange(len(pts))), tree.T
        # sorted in place (a copy given away), the same tree; the caller's points untouched
        given = pts.copy()
        sorted_in_place = Tree(given, weights, None, 2, scratch=True)
        assert sorted_in_place.pts is given
        np.testing.assert_array_equal(sorted_in_place.pts, P)
        np.testing.assert_array_equal(sorted_in_place.T, T)
        assert not np.shares_memory(P, pts)
        if weights is None:  # no n-long array of ones: one placeholder 1
            assert tree.w.shape == (1,)
        order = np.lexsort(P.T)
        want = np.lexsort(pts.T)
        np.testing.assert_array_equal(P[order], pts[want])
        lo, hi, child = T[:, 0].astype(int), T[:, 1].astype(int), T[:, 2].astype(int)
        assert lo[0] == 0 and hi[0] == len(pts)
        for i in range(len(T)):
            mine = P[lo[i] : hi[i]]
            np.testing.assert_array_equal(T[i, 4 : 4 + dim], mine.min(0))
            np.testing.assert_array_equal(T[i, 4 + dim :], mine.max(0))
            np.testing.assert_allclose(T[i, 3], W[lo[i] : hi[i]].sum(), rtol=1e-13)
            if child[i] >= 0:
                c = child[i]
                assert lo[c] == lo[i] and hi[c] == lo[c + 1] and hi[c + 1] == hi[i]
                assert lo[c] < hi[c] and lo[c + 1] < hi[c + 1]  # no empty child
            else:
                assert hi[i] - lo[i] <= _tree.LEAF or (mine == mine[0]).all()
        assert tree.depth >= int(np.log2(len(pts) / _tree.LEAF))


@pytest.mark.parametrize("dim", [2, 3])
def test_kth_blocks_across_a_cluster_beside_a_void_equal_brute_force(dim):
    """Issue 52: k-th queries in blocks, each block's window sized by its first answer.
    Queries sweeping from a void into a dense cluster (a window sized in the void floods
    its buffer there: the block is halved) and along a line through both, k = 1, 30, 120,
    unweighted and weighted: brute force's distances."""
    rng = np.random.default_rng(23 + dim)
    pts = np.concatenate([
        rng.random((2000, dim)),
        0.5 + 0.01 * rng.standard_normal((20_000, dim)),
    ])  # fmt: skip
    t = np.linspace(0, 1, 1500)[:, None]
    x = np.concatenate([rng.random((1500, dim)), 0.1 + t * (np.full(dim, 0.8))])
    brute = _brute_kths(x, pts, None, (1, 30, 120))
    for k, expected in zip((1, 30, 120), brute, strict=True):
        np.testing.assert_allclose(Tree(pts, None, None, 2).kth(x, k), expected, rtol=1e-12)
    w = rng.random(len(pts)) + 0.25
    np.testing.assert_allclose(Tree(pts, w, np.ones(dim), 2).kth(x, 50.0),
                               _brute_kth(x, pts, np.ones(dim), 50.0, w), rtol=1e-12)  # fmt: skip


def test_kth_window_sized_by_the_points_not_by_k():
    """Regression (issue 52): a block's window buffer was 64 k points, so k = 1e16 + 8 with
    weights (test_weights' heavy point) asked numpy for an array beyond any memory. The
    buffers follow min(k, n): k beyond the points' count or weight gives inf, and a heavy
    point's k its brute-force distance."""
    rng = np.random.default_rng(9)
    pts = rng.random((3000, 2))
    x = rng.random((700, 2))
    assert np.isinf(Tree(pts, None, None, 2).kth(x, 10**9)).all()
    w = np.ones(len(pts))
    w[0] = 1e16
    got = Tree(pts, w, None, 2).kth(x, 1e16 + 8)
    np.testing.assert_allclose(got, _brute_kth(x, pts, None, 1e16 + 8, w), rtol=1e-12)
    assert np.isinf(Tree(pts, w, None, 2).kth(x, 1e17)).all()


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("periodic", [False, True], ids=["box", "torus"])
def test_tree_on_points_on_a_line_equals_brute_force(dim, periodic):
    """Issue 52, degenerate input for the Morton-built tree and the k-th blocks: every point
    on one line (a box of zero width on the other axes: Morton codes vary along one axis),
    a tenth of them coinciding, some at 0 on a torus (the cut); queries on the line and
    off it. k-th distances and ball counts equal brute force's."""
    rng = np.random.default_rng(61 + dim + 2 * periodic)
    t = rng.random(6000)
    t[:600] = t[0]
    t[600:700] = 0.0
    pts = np.zeros((len(t), dim)) + 0.3
    pts[:, 0] = t
    period = np.ones(dim) if periodic else None
    x = np.concatenate([pts[rng.integers(0, len(t), 300)], rng.random((300, dim))])
    tree = Tree(pts, None, period, 2)
    for k, expected in zip((1, 30, 700), _brute_kths(x, pts, period, (1, 30, 700)), strict=True):
        np.testing.assert_allclose(tree.kth(x, k), expected, rtol=1e-12)
    r = rng.random(len(x)) * 0.05
    want = (_brute_d2(x, pts, period) <= r[:, None] ** 2).sum(1)
    np.testing.assert_array_equal(tree.held(x, r), want)


@pytest.mark.parametrize(
    "layout",
    ["uniform", "torus", "half-torus", "clustered", "line", "coinciding", "offset", "space",
     "space-torus", "sphere"],
)  # fmt: skip
def test_grid_counts_equal_brute_force(layout):
    """Balls counted from the grid of the tree's Morton runs (``_grid_held``: cells
    inside added whole, cells cut read or split into children, crowded finest cells and
    radii not finite left to the tree) equal brute force, exact below ``stop`` and at least
    ``stop`` above it: radii from 0 to past the whole torus, points and centres on its
    cut, points on a line (an axis of one coordinate), clusters finer than the table's
    cells, thousands of coinciding points, coordinates far from the origin against their
    spread."""
    from knnrefine.certify._tree import Tree

    rng = np.random.default_rng(17)
    dim = 3 if layout.startswith(("space", "sphere")) else 2
    n = 6000
    pts = rng.random((n, dim))
    period = None
    x = rng.random((600, dim))
    r = rng.random(600) * 0.08
    if layout in ("torus", "space-torus"):
        period = np.ones(dim)
        r[:100] = rng.random(100) * 0.8  # past half the period: the ball wraps onto itself
        pts[:300, 0] = 0.0  # on the cut, and balls about it from both sides
        x[100:140, 0] = 0.0
        x[140:180, 0] = np.nextafter(1.0, 0.0)
    if layout == "half-torus":
        period = np.array([1.0, 0.0])
    if layout == "clustered":
        centres = rng.random((12, dim))
        pts = centres[rng.integers(0, 12, n)] + rng.normal(0, 1e-4, (n, dim))
        x = pts[:600] + rng.normal(0, 1e-4, (600, dim))
        r = rng.random(600) * 3e-4
    if layout == "line":
        pts[:, 1] = 0.3
    if layout == "coinciding":
        pts = np.repeat(rng.random((3, dim)), n // 3, axis=0)
        x = np.concatenate([pts[::20] + 1e-9, x[:300]])
        r = np.concatenate([np.full(300, 1e-9), np.zeros(100), r[:200]])
    if layout == "offset":
        pts, x, r = pts * 1e-6 + 1e6, x * 1e-6 + 1e6, r * 1e-6
    if layout == "sphere":
        pts = rng.standard_normal((n, dim))
        pts /= np.linalg.norm(pts, axis=1, keepdims=True)
        x = pts[:600] + rng.normal(0, 1e-3, (600, dim))
    r[:5] = 0.0
    r[5:8] = [np.inf, 10.0, 1e-300]
    tree = Tree(pts, None, period)
    assert tree.grid is not None
    want = (_brute_d2(x, pts, period) <= np.square(r)[:, None]).sum(axis=1)
    assert np.array_equal(tree.held(x, r), want)
    stop = 7.0
    got = tree.held(x, r, stop)
    assert np.array_equal(np.minimum(got, stop), np.minimum(want, stop))
    assert np.all(got[want >= stop] >= stop)
    # fewer than k: settled by the cells' runs where they hold less in all (loose), or
    # counted until k; the same answers either way
    for k in (1.0, 7.0, 40.0):
        assert np.array_equal(tree.fewer(x, r, k), want < k)
        assert np.array_equal(tree.fewer(x, r, k, mostly=False), want < k)
    loose = tree.held(x, r, stop, loose=True)
    assert np.all(loose[want < stop] >= want[want < stop]) and np.all(loose[want >= stop] >= stop)


@pytest.mark.parametrize(
    "layout",
    ["uniform", "torus", "clustered", "line", "coinciding", "offset", "space", "space-torus",
     "sphere"],
)  # fmt: skip
def test_grid_kth_equals_brute_force(layout, monkeypatch):
    """k-th distances read from the grid's shells (``_grid_kth``: cells within the inner
    radius added whole, the points between the radii kept and the k-th found among them,
    the shell moved in or out until it holds the answer) equal brute force: along a Morton
    curve and in a random order (each query far from the one before), k from 1 to past
    the points (inf), on the same layouts as the counts; weighted too. Only crowded
    finest cells (thousands of coinciding points) are left to the tree."""
    from knnrefine.certify import _tree

    asked = []
    tree_kth = _tree._kth

    def counted(pts, w, T, depth, period, x, k, unit, out, start, end):
        asked.append(end - start)
        return tree_kth(pts, w, T, depth, period, x, k, unit, out, start, end)

    monkeypatch.setattr(_tree, "_kth", counted)
    rng = np.random.default_rng(29)
    dim = 3 if layout.startswith(("space", "sphere")) else 2
    n = 4000
    pts = rng.random((n, dim))
    period = None
    x = rng.random((500, dim))
    if layout in ("torus", "space-torus"):
        period = np.ones(dim)
        pts[:300, 0] = 0.0
        x[100:140, 0] = 0.0
        x[140:180, 0] = np.nextafter(1.0, 0.0)
    if layout == "clustered":
        centres = rng.random((12, dim))
        pts = centres[rng.integers(0, 12, n)] + rng.normal(0, 1e-4, (n, dim))
        x = np.concatenate([pts[:400] + rng.normal(0, 1e-4, (400, dim)), x[:100]])
    if layout == "line":
        pts[:, 1] = 0.3
    if layout == "coinciding":
        pts = np.repeat(rng.random((3, dim)), n // 3, axis=0)
        x = np.concatenate([pts[::20], x[:300]])
    if layout == "offset":
        pts, x = pts * 1e-6 + 1e6, x * 1e-6 + 1e6
    if layout == "sphere":
        pts = rng.standard_normal((n, dim))
        pts /= np.linalg.norm(pts, axis=1, keepdims=True)
        x = pts[:500] + rng.normal(0, 1e-3, (500, dim))
    tree = _tree.Tree(pts, None, period, 2)
    assert tree.grid is not None
    d2 = np.sort(_brute_d2(x, pts, period), axis=1)
    shuffled = rng.permutation(len(x))
    left = 0  # queries the grid should have answered, left to the tree
    for k in (1, 7, 60, len(pts) + 1):
        before = sum(asked)
        want = np.sqrt(d2[:, k - 1]) if k <= len(pts) else np.full(len(x), np.inf)
        np.testing.assert_allclose(tree.kth(x, k), want, rtol=1e-12)
        np.testing.assert_allclose(tree.kth(x[shuffled], k, sort=False), want[shuffled],
                                   rtol=1e-12)  # fmt: skip
        if dim == 2 or k >= _tree.GRID_KTH3:  # (in space a small k is the tree's)
            left += sum(asked) - before
    assert left <= (len(x) * 4 if layout == "coinciding" else 0)
    w = rng.random(len(pts)) * 2 + 1e-3
    np.testing.assert_allclose(_tree.Tree(pts, w, period, 2).kth(x, 20.5),
                               _brute_kth(x, pts, period, 20.5, w), rtol=1e-12)  # fmt: skip


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("periodic", [False, True], ids=["box", "torus"])
def test_grid_weights_equal_exact_sums(dim, periodic):
    """Weighted balls counted from the grid (runs inside added as differences of
    compensated prefix sums, cut cells point by point) equal the exactly rounded sums
    (``math.fsum``) of the weights inside, weights from 1e-12 to 1e6 side by side."""
    import math

    from knnrefine.certify._tree import Tree

    rng = np.random.default_rng(dim + 2 * periodic)
    pts = rng.random((5000, dim))
    w = rng.random(5000) * 3
    w[::7], w[::11] = 1e-12, 1e6
    period = np.ones(dim) if periodic else None
    x = rng.random((500, dim))
    r = rng.random(500) * 0.15
    tree = Tree(pts, w, period)
    assert tree.grid is not None and not tree.unit
    inside = _brute_d2(x, pts, period) <= np.square(r)[:, None]
    want = np.array([math.fsum(w[row]) for row in inside])
    assert np.array_equal(tree.held(x, r), want)
    for k in (1e-6, 1.0, 30.0, 2e6):
        assert np.array_equal(tree.fewer(x, r, k), want < k)


def test_separations_equal_numpys_in_every_metric():
    """The Lipschitz bounds' separations (``common.separations`` on a torus, a half torus
    and a box; the sphere's ``_angles``) equal numpy's formulas, NaN where a probe has no
    reference."""
    from knnrefine._domains.sphere.certify import Geometry as SphereGeometry
    from knnrefine.certify.common import separations

    rng = np.random.default_rng(5)
    x = rng.random((300, 2)) * 3.0
    rows = rng.integers(0, 300, 200)
    refs = rng.integers(-1, 300, (200, 3))
    for period in ([3.0, 3.0], [3.0, 0.0], [0.0, 0.0]):
        got = separations(x, rows, refs, None, np.array(period))
        g = x[rows][:, None, :] - x[np.maximum(refs, 0)]
        p = np.array(period)
        g = np.where(p > 0, g - p * np.rint(g / np.where(p > 0, p, 1.0)), g)
        want = np.where(refs >= 0, np.sqrt((g**2).sum(-1)), np.nan)
        assert np.allclose(got, want, rtol=1e-14, atol=0, equal_nan=True)
    u = rng.standard_normal((300, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u[1] = -u[0]  # antipodal: pi
    geometry = SphereGeometry.__new__(SphereGeometry)
    geometry.workers = None
    got = geometry.separation(u, np.array([0, 2, 5]), np.array([[1, -1], [2, 7], [9, 4]]))
    a, b = u[[0, 2, 2, 5, 5]], u[[1, 2, 7, 9, 4]]
    want = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))
    assert np.allclose(got[~np.isnan(got)], want, rtol=1e-13, atol=1e-15)
    assert np.isnan(got[0, 1]) and abs(got[0, 0] - np.pi) < 1e-12 and got[1, 0] == 0.0


def test_plane_circles_and_areas_equal_numpys_on_the_engines_types():
    """``verify_triangulation`` reads the engine's int32 triangles and neighbours and int8
    offsets as they are (no int64 copies) and computes areas, circumcentres and radii in
    one kernel without a corners copy: the same values bit for bit as ``mesh``'s numpy
    formulas on the gathered corners, and the same answers from int64 copies."""
    import knnrefine
    from knnrefine._domains.plane.certify import verify_triangulation
    from knnrefine._metric import BoxMetric
    from knnrefine.mesh import circumcircles, triangle_areas

    rng = np.random.default_rng(31)
    pts = np.mod(rng.normal(0.5, 0.2, (5000, 2)), 1.0)
    t = knnrefine.refine(pts, 5, periodic=True, box=(0, 0, 1, 1)).torus
    assert t.triangles.dtype == np.int32 and t.offsets.dtype == np.int8
    period = np.asarray(t.period, float)
    got = verify_triangulation(t.vertices, t.triangles, t.offsets, t.neighbours, period)
    wide = verify_triangulation(t.vertices, t.triangles.astype(np.int64),
                                t.offsets.astype(np.int64), t.neighbours.astype(np.int64),
                                period)  # fmt: skip
    assert got[0] == wide[0] == []
    corners = t.vertices[t.triangles] + t.offsets * period
    centres, radii = circumcircles(corners)
    np.testing.assert_array_equal(got[1], triangle_areas(corners))
    np.testing.assert_array_equal(got[2], BoxMetric((0, 0, *period), (True, True)).frame(centres))
    np.testing.assert_array_equal(got[3], radii)
    for a, b in zip(got[1:], wide[1:], strict=True):
        np.testing.assert_array_equal(a, b)


def test_edge_keys_one_of_each_twin_pair():
    """Where the neighbour links are symmetric, ``_edge_keys`` keeps one side of each twin
    pair: half the rows, and the same edges (keys) as every side's. A triangle whose
    sides are all repeated in another (a doubled triangle) leaves the links asymmetric,
    so every side is keyed and its keys are met twice."""
    import knnrefine
    from knnrefine._domains.plane.certify import _edge_keys, verify_triangulation
    from knnrefine.certify._rows import row_classes

    rng = np.random.default_rng(32)
    t = knnrefine.refine(rng.random((3000, 2)), 5, periodic=True, box=(0, 0, 1, 1)).torus
    tri, off, nb = t.triangles, t.offsets, t.neighbours

    def edges(key):
        return {tuple(r) for r in key}, int((row_classes(key, key[:, 0].copy(), len(t.vertices))
                                            == np.arange(len(key))).sum())  # fmt: skip

    every, half = _edge_keys(tri, off, nb, False), _edge_keys(tri, off, nb, True)
    assert len(half) * 2 == len(every) == 3 * len(tri)
    assert edges(half) == (edges(every)[0], len(half))
    # a doubled triangle: its copy's links are not returned (so every side is keyed), its
    # sides' keys are met twice, and the triangulation fails
    doubled = np.concatenate([tri, tri[:1]]), np.concatenate([off, off[:1]])
    links = np.concatenate([nb, nb[:1]])
    keys = _edge_keys(*doubled, links, False)
    assert edges(keys)[1] == len(half)
    problems = verify_triangulation(t.vertices, *doubled, links, np.asarray(t.period, float))[0]
    assert any("not symmetric" in p for p in problems), problems


def test_uniform_in_triangles_by_cells_equals_a_gathered_copy():
    """``mesh.uniform_in_triangles`` with the cells each point lies in gives, bit for bit,
    what it gives on the gathered corners (and the folded numbers), and so does it given
    (vertices, triangles): the certificate's and the density's samples need no (s, 3, d)
    copy. Every point lies in its triangle."""
    from knnrefine.mesh import uniform_in_triangles

    rng = np.random.default_rng(34)
    for d in (2, 3):
        corners = rng.normal(size=(50, 3, d))
        cells = rng.integers(0, 50, 400)
        u = rng.random((400, 2))
        x, folded = uniform_in_triangles(corners, u, cells)
        y, folded2 = uniform_in_triangles(corners[cells], u)
        np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(folded, folded2)
        vertices = corners.reshape(-1, d)  # as (vertices, triangles), read where they are
        for triangles in (
            np.arange(150).reshape(50, 3),
            np.arange(150, dtype=np.int32).reshape(50, 3),
        ):
            z, _ = uniform_in_triangles((vertices, triangles), u, cells)
            np.testing.assert_array_equal(x, z)
        assert np.all(folded.sum(axis=1) <= 1.0) and np.all(folded >= 0)
        a = corners[cells, 0]
        back = a + folded[:, :1] * (corners[cells, 1] - a) + folded[:, 1:] * (corners[cells, 2] - a)
        np.testing.assert_allclose(x, back, rtol=0, atol=1e-12)


@pytest.mark.parametrize("domain", ["plane", "plane-line", "sphere"])
def test_edge_vectors_and_midpoints_equal_numpy_gathers(domain):
    """The Voronoi cells' edge vectors, worked out where they are read (``_tree.edge_at``,
    issue 52: not held), as the edge midpoints (``common.edge_midpoints``) and each site's
    nearest neighbour (``common.nearest_neighbour``) read them, equal numpy's gathers bit
    for bit: sites[nb] - sites[site] + shift period, site + half the edge for the
    lexicographically positive direction of each edge, the least edge length not 0; on
    the torus across its cut, with points on a line, and on the sphere."""
    import knnrefine
    from knnrefine._domains.plane import certify as plane
    from knnrefine._domains.sphere import certify as sphere
    from knnrefine.certify._tree import neighbour_lists
    from knnrefine.certify.common import edge_midpoints, nearest_neighbour

    rng = np.random.default_rng(36)
    if domain == "sphere":
        pts = np.column_stack([rng.uniform(-180, 180, 3000), rng.uniform(-90, 90, 3000)])
        geometry = sphere.Geometry(knnrefine.refine(pts, 5, sphere=True), 2)
        sites, period = geometry.xyz, np.zeros(3)
        cells, off = geometry.tri, np.zeros((len(geometry.tri), 3, 0), np.int8)
    else:
        pts = rng.random((3000, 2))
        pts[:200, 0] = 0.0  # on the cut
        if domain == "plane-line":
            pts[:, 1] = 0.5
        geometry = plane.Geometry(knnrefine.refine(pts, 5, periodic=True, box=(0, 0, 1, 1)), 2)
        sites, period = geometry.vertices, geometry.period
        cells, off = geometry.mesh.torus.cells, geometry.mesh.torus.offsets
    first, nb, shift = neighbour_lists(cells, off, len(sites), 2)
    site = np.repeat(np.arange(len(sites)), np.diff(first))
    e = sites[nb] - sites[site]
    if shift.shape[1]:
        e = e + shift * period
    cells_ = geometry.cells(geometry.triangulation())
    np.testing.assert_array_equal(cells_.first, first)
    np.testing.assert_array_equal(cells_.neighbours, nb)
    np.testing.assert_array_equal(cells_.shift, shift)
    length = np.sqrt(sum(e[:, a] * e[:, a] for a in range(e.shape[1])))  # (axis by axis)
    length[length == 0] = np.inf
    nearest = np.minimum.reduceat(length, first[:-1])  # (every site has neighbours here)
    np.testing.assert_array_equal(nearest_neighbour(cells_), nearest)
    mids, ends = edge_midpoints(cells_)
    positive = np.zeros(len(e), bool)
    decided = np.zeros(len(e), bool)
    for a in range(e.shape[1]):
        positive |= ~decided & (e[:, a] > 0)
        decided |= e[:, a] != 0
    owner = np.repeat(np.arange(len(cells_.sites)), np.diff(cells_.first))
    np.testing.assert_array_equal(mids, cells_.sites[owner[positive]] + 0.5 * e[positive])
    np.testing.assert_array_equal(
        ends, np.column_stack([owner[positive], cells_.neighbours[positive]])
    )
    assert 2 * len(mids) == len(e)  # each edge once
    # a range of sites at a time (``probe_parts``' pieces), together, the same rows
    pieces = [edge_midpoints(cells_, a, a + 37) for a in range(0, len(cells_.sites), 37)]
    np.testing.assert_array_equal(np.concatenate([p[0] for p in pieces]), mids)
    np.testing.assert_array_equal(np.concatenate([p[1] for p in pieces]), ends)


def test_gathered_probes_the_same_whatever_room_they_start_with():
    """Issue 52: the probes are made a part at a time, a piece at a time, into arrays of
    the caller's bound (``common.gathered_probes``), grown where it is short: with room
    for one row or for all, the same probes, marks, d_{M,2}, near rows (a dropped vertex
    and a missing one read -1) and the size sample's vertex rows; each as the parts kept,
    in order."""
    from knnrefine.certify.common import SizeSample, gathered_probes

    rng = np.random.default_rng(8)
    verts = rng.random((50, 2))
    samples, mids, others = rng.random((30, 2)), rng.random((70, 2)), rng.random((20, 2))
    ends = rng.integers(0, 50, (70, 2))
    near_one = rng.integers(-1, 50, (20, 1))  # -1: none
    d_m2 = rng.random(50)

    def inside(x):
        return x[:, 0] < 0.8  # some of every part dropped, vertices among them

    def parts():  # (the midpoints in pieces, as ``probe_parts`` makes them)
        return [
            lambda: [(samples, False, None, None)],
            lambda: [(rng.random((0, 2)), True, None, None)],
            lambda: [(verts, False, d_m2, None)],
            lambda: ((mids[a : a + 9], False, None, ends[a : a + 9]) for a in range(0, 70, 9)),
            lambda: [(others, False, None, near_one)],
        ]

    size = SizeSample(None, np.ones(30), np.arange(30), np.zeros((30, 3), int), np.ones(30), 30)
    small = gathered_probes(parts(), inside, size, 2, 1)
    ample = gathered_probes(parts(), inside, size, 2, 1000)
    kept = [inside(p) for p in (samples, verts, mids, others)]
    parts_x = (samples, verts, mids, others)
    want_x = np.concatenate([p[k] for p, k in zip(parts_x, kept, strict=True)])
    at = np.full(50, -1)
    at[kept[1]] = kept[0].sum() + np.arange(kept[1].sum())
    for probes in (small, ample):
        np.testing.assert_array_equal(probes.x, want_x)
        np.testing.assert_array_equal(probes.extra.at, at)
        np.testing.assert_array_equal(probes.extra.kept, kept[0])
        a = int(kept[0].sum())
        b = a + int(kept[1].sum())
        np.testing.assert_array_equal(probes.d_m2[a:b], d_m2[kept[1]])
        assert np.isnan(probes.d_m2[:a]).all() and np.isnan(probes.d_m2[b:]).all()
        c = b + int(kept[2].sum())
        np.testing.assert_array_equal(probes.near[b:c], at[ends[kept[2]]])
        want = np.where(near_one[kept[3]] >= 0, at[near_one[kept[3]]], -1)
        np.testing.assert_array_equal(probes.near[c:, :1], want)
        assert (probes.near[c:, 1] == -1).all() and (probes.near[:b] == -1).all()
        np.testing.assert_array_equal(np.flatnonzero(probes.exact),
                                      np.concatenate([np.arange(a), np.arange(a, b)]))  # fmt: skip
        assert not probes.points.any()


def test_sphere_point_probes_are_the_keyed_sample_of_the_points_given():
    """Issue 52: on the sphere the unweighted tree sorts the unit vectors in place and the
    input-point probes are drawn from its points: the same sample, in the same order, as
    ``_sampling.key_sample`` of the unit vectors in the caller's order, with repeated
    points, points on one meridian and at the poles; the caller's points are untouched."""
    import warnings

    import knnrefine
    from knnrefine._domains.sphere import certify as sphere
    from knnrefine._sampling import key_sample

    rng = np.random.default_rng(61)
    pts = np.column_stack([rng.uniform(-180, 180, 3000), rng.uniform(-90, 90, 3000)])
    pts[:300] = pts[300:600]  # repeated
    pts[600:900, 0] = 12.5  # one meridian
    pts[900:910, 1] = 90.0  # a pole
    given = pts.copy()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = knnrefine.refine(pts, 5, sphere=True)
    unit, weights = sphere.checked_points(mesh, pts, None)
    want = key_sample(unit.copy(), 0.3)[0]
    points = sphere.Points(mesh, unit, weights, 2)
    got = points.sample_points(900, np.random.default_rng(0))
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(pts, given)
