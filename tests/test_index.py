"""The counting kd-tree against brute force: closed disks and convex cells, periodic."""

import numpy as np
import oracle
import pytest
from conftest import of_trees
from hypothesis import given
from hypothesis import strategies as st

from knnrefine._engine import index as engine_index
from knnrefine._engine.index import LEAF_SIZE, STACK_SIZE, build_index
from knnrefine._engine.jit import python_entry

count_in_cell = of_trees(engine_index.count_in_cell)
count_in_disk = of_trees(engine_index.count_in_disk)


def periodic_copies(points, lx, ly):
    return np.concatenate([points + [sx * lx, sy * ly] for sx in (-1, 0, 1) for sy in (-1, 0, 1)])


def assert_count(got, lo, hi, k):
    """Exact below k (up to points on the boundary); otherwise any value in [k, true count]."""
    if got >= k:
        assert hi >= k and got <= hi, (got, lo, hi, k)
    else:
        assert lo <= got <= hi, (got, lo, hi, k)


def make(points):
    return build_index(np.array(points, dtype=np.float64).reshape(-1, 2))


def point_sets(rng):
    yield "empty", np.zeros((0, 2))
    yield "one", np.array([[0.3, 0.7]])
    yield "uniform", rng.random((3000, 2))
    yield "duplicates", np.repeat(rng.random((40, 2)), 30, axis=0)
    g = np.arange(20) / 20
    yield "lattice", np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    yield "clustered", np.clip(rng.normal(0.5, 1e-6, (2000, 2)), 0, 0.999)
    yield "heaps", np.repeat(rng.random((6, 2)), 4 * LEAF_SIZE, axis=0)  # leaves > LEAF_SIZE


@pytest.mark.parametrize("case", range(7))
def test_count_in_disk_matches_brute_force(case):
    rng = np.random.default_rng(case)
    name, pts = list(point_sets(rng))[case]
    index = make(pts)
    stack = np.empty(STACK_SIZE, np.int64)
    cover = periodic_copies(pts, 1.0, 1.0)
    for _ in range(300):
        c = rng.random(2) * 1.4 - 0.2
        r = rng.choice([1e-7, 0.01, 0.05, 0.2, 0.45]) * rng.random()
        if name == "lattice" and rng.random() < 0.5:  # discs through lattice points
            c = np.round(c * 20) / 20 + 0.025
            r = np.hypot(0.025, 0.025)
        d2 = ((cover - c) ** 2).sum(1)
        # points within rounding of the circle may count either way
        lo = int((d2 <= r * r * (1 - 1e-12)).sum())
        hi = int((d2 <= r * r * (1 + 1e-12)).sum())
        for k in (1, 7, 100, 10**9):
            got = count_in_disk(index, c[0], c[1], r * r, k, 1.0, 1.0, stack)
            assert_count(got, lo, hi, k)


@pytest.mark.parametrize("case", range(7))
def test_count_in_cell_matches_brute_force(case):
    rng = np.random.default_rng(10 + case)
    name, pts = list(point_sets(rng))[case]
    index = make(pts)
    stack = np.empty(STACK_SIZE, np.int64)
    cover = periodic_copies(pts, 1.0, 1.0)
    for _ in range(200):
        v = rng.random(2)
        nb, hc, R2 = oracle.random_cell(rng)
        deg = len(hc)
        rel = cover - v
        lo = int(oracle.in_cell(rel, nb, hc, R2, 1 - 1e-12).sum())
        hi = int(oracle.in_cell(rel, nb, hc, R2, 1 + 1e-12).sum())
        for k in (1, 5, 10**9):
            got = count_in_cell(
                index,
                v[0],
                v[1],
                nb[:, 0].copy(),
                nb[:, 1].copy(),
                hc,
                deg,
                R2,
                k,
                1.0,
                1.0,
                stack,
                np.zeros(LEAF_SIZE, np.bool_),
            )
            assert_count(got, lo, hi, k)


def coordinate(lo, hi):
    """Coordinates in the kernels' domain: zero or of magnitude >= 1e-150, so that squared
    differences do not underflow (the brute force below squares them too)."""
    return st.floats(lo, hi).filter(lambda v: v == 0.0 or abs(v) >= 1e-150)


@given(
    st.lists(st.tuples(coordinate(0, 0.999), coordinate(0, 0.999)), min_size=0, max_size=60),
    coordinate(-0.5, 1.5),
    coordinate(-0.5, 1.5),
    coordinate(0, 0.49),
)
def test_disk_property(pts, cx, cy, r):
    """count_in_disk is exact for the unshifted centre and point; a copy shifted by a period
    rounds at the scale of the period (its documented tolerance), so points within a few ulps
    of the circle through a shifted copy may count either way."""
    pts = np.array(pts, float).reshape(-1, 2)
    index = make(pts)
    stack = np.empty(STACK_SIZE, np.int64)
    eps = 2.0**-48
    lo = hi = 0
    for sx in (-1, 0, 1):
        for sy in (-1, 0, 1):
            d2 = ((pts + [sx, sy] - [cx, cy]) ** 2).sum(1)
            if sx == 0 and sy == 0:
                lo += int((d2 <= r * r).sum())
                hi += int((d2 <= r * r).sum())
            else:
                d = np.sqrt(d2)
                lo += int((d <= r - eps).sum())
                hi += int((d <= r + eps).sum())
    got = count_in_disk(index, cx, cy, r * r, 10**9, 1.0, 1.0, stack)
    assert lo <= got <= hi, (got, lo, hi)


def test_centre_a_hair_below_the_seam_is_not_wrapped_onto_a_point():
    """Regression (hypothesis, seed 2): wrapping the centre (0, -2.67e-125) into [0, 1) rounds
    it to (0, 1.0), i.e. onto the point (0, 0); the disk of radius 0 about the true centre
    holds no point."""
    index = make([[0.0, 0.0]])
    stack = np.empty(STACK_SIZE, np.int64)
    assert count_in_disk(index, 0.0, -2.67e-125, 0.0, 10**9, 1.0, 1.0, stack) == 0
    assert count_in_disk(index, 0.0, -2.67e-125, 2.67e-125**2, 10**9, 1.0, 1.0, stack) == 1


def test_tree_is_a_partition():
    rng = np.random.default_rng(2)
    pts = rng.random((5000, 2))
    sorted_pts, box, node, split, _ = make(pts)
    assert sorted(map(tuple, sorted_pts)) == sorted(map(tuple, pts))
    for t in range(len(node)):
        lo, hi, c, axis = node[t]
        inside = sorted_pts[lo:hi]
        assert np.all(inside >= box[t, :2]) and np.all(inside <= box[t, 2:])
        if c >= 0:
            assert node[c, 0] == lo and node[c, 1] == node[c + 1, 0] and node[c + 1, 1] == hi
            left = sorted_pts[node[c, 0] : node[c, 1], axis]
            right = sorted_pts[node[c + 1, 0] : node[c + 1, 1], axis]
            assert left.max() <= split[t] <= right.min()
        else:
            assert hi - lo <= LEAF_SIZE or np.all(inside == inside[0])


def _preorder(index):
    """The tree as a list of (rows, box, split, axis) in depth-first order: what a query sees,
    whatever the nodes' numbering."""
    _, box, node, split, _ = index
    out, stack = [], [0]
    while stack:
        t = stack.pop()
        lo, hi, c, axis = node[t]
        if c >= 0:
            out.append((lo, hi, tuple(box[t]), split[t], axis))
            stack += [c + 1, c]
        else:
            out.append((lo, hi, tuple(box[t]), None, None))
    return out


@pytest.mark.parametrize("workers", [2, 3, 4, 8])
def test_parallel_build_is_the_one_thread_tree(workers, monkeypatch):
    """Subtrees built by threads give the same permutation and nodes as one thread, also where
    coincident points stop splitting early (gaps in the node blocks, closed afterwards)."""
    import knnrefine._engine.index as I

    monkeypatch.setattr(I, "PARALLEL_MIN", 0)
    rng = np.random.default_rng(workers)
    sets = list(point_sets(rng))[2:] + [("big", rng.random((150_000, 2)))]
    for name, pts in sets:
        one = build_index(pts.copy(), workers=1)
        many = build_index(pts.copy(), workers=workers)
        assert np.array_equal(one[0], many[0]), name
        assert len(one[2]) == len(many[2]), name
        assert _preorder(one) == _preorder(many), name
        # every node reachable exactly once: no stale block left behind
        assert len(_preorder(many)) == len(many[2]), name


# -- the k-th nearest distance (PointIndex.kth): evaluating d_{P,k}, not refining ------------


def _kth_brute(q, pts, k, periodic, period):
    """d_{P,k} by brute force: per axis the circle's distance (periodic) or the line's."""
    e = np.abs(q[:, None, :] - pts[None, :, :])
    for a in range(2):
        if periodic[a]:
            e[..., a] = np.minimum(e[..., a], period[a] - e[..., a])
    return np.sqrt(np.partition((e**2).sum(-1), k - 1, axis=1)[:, k - 1])


@pytest.mark.parametrize("periodic", [(False, False), (True, True), (True, False)])
@pytest.mark.parametrize("case", range(1, 7))
def test_kth_distance_matches_brute_force(case, periodic):
    rng = np.random.default_rng(case)
    name, pts = list(point_sets(rng))[case]
    index = engine_index.PointIndex.build(pts, (0.0, 0.0, 1.0, 1.0), periodic)
    q = np.concatenate([rng.random((150, 2)), pts[rng.integers(0, len(pts), 50)]])
    if not all(periodic):  # planar axes answer outside the box too
        q = np.concatenate([q, rng.random((30, 2)) * 3 - 1])
        q[-30:, [a for a in range(2) if periodic[a]]] %= 1.0
    for k in sorted({1, 2, 7, 100, len(pts)}):
        if k > len(pts):
            continue
        ref = _kth_brute(q, pts, k, periodic, (1.0, 1.0))
        np.testing.assert_allclose(index.kth(q, k), ref, rtol=1e-12, atol=1e-15)
        # any window: too low, too high, too narrow, empty; the bounds hold
        for r_in, r_out in ((0.01 * ref, 0.02 * ref), (3 * ref, 9 * ref), (ref, ref), (0, 0)):
            got = index.kth(q, k, r_in, r_out, workers=2)
            np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-15)
        got = index.kth(q, k, 0.5 * ref, 2 * ref, low=0.9 * ref, high=1.1 * ref)
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-15)


def test_kth_distance_with_more_ties_than_the_window_holds():
    # 3,000 copies of one point at the same distance from every query: no window can split
    # them (the buffer holds 4 k + 1024), so the kernel gives up and brute force answers
    rng = np.random.default_rng(5)
    pts = np.concatenate([np.repeat([[0.5, 0.5]], 3000, axis=0), rng.random((500, 2))])
    index = engine_index.PointIndex.build(pts, (0.0, 0.0, 1.0, 1.0), (False, False))
    q = np.concatenate([rng.random((20, 2)), [[0.5, 0.5]]])
    for k in (5, 200, 3400):
        ref = _kth_brute(q, pts, k, (False, False), (1.0, 1.0))
        np.testing.assert_allclose(index.kth(q, k), ref, rtol=1e-12, atol=0)


def test_kth_distance_is_the_same_on_a_refined_mesh_index():
    # the index refine keeps (internal units, embedded box) answers as one built for the data
    import knnrefine

    rng = np.random.default_rng(2)
    pts = np.concatenate([rng.normal([2.0, -1.0], [0.5, 0.01], (3000, 2)), rng.random((300, 2))])
    mesh = knnrefine.refine(pts, 30)
    assert mesh.index.indexes(pts) and not mesh.index.indexes(pts[::-1] + 1e-9)
    q = rng.random((400, 2)) * 6 - [1.0, 3.0]  # inside and far outside the box
    ref = _kth_brute(q, pts, 30, (False, False), (0.0, 0.0))
    np.testing.assert_allclose(mesh.index.kth(q, 30), ref, rtol=1e-12)


@pytest.mark.parametrize("kind", ["uniform", "ties", "sorted", "reversed"])
def test_select_puts_the_kth_row_in_place(kind):
    # Floyd-Rivest on long ranges, quickselect on short ones: rows move whole, the kth is the
    # sorted order's, nothing outside [lo, hi) moves
    select = python_entry(engine_index.select_kth)

    rng = np.random.default_rng(len(kind))
    for n in (1, 2, 33, 601, 602, 5000, 70000):
        p = {
            "uniform": rng.random((n, 2)),
            "ties": rng.integers(0, 3, (n, 2)).astype(float),
            "sorted": np.sort(rng.random((n, 2)), axis=0),
            "reversed": np.sort(rng.random((n, 2)), axis=0)[::-1].copy(),
        }[kind]
        for _ in range(4):
            lo = int(rng.integers(0, n))
            hi = int(rng.integers(lo + 1, n + 1))
            kth = int(rng.integers(lo, hi))
            axis = int(rng.integers(0, 2))
            q = p.copy()
            select(q, axis, lo, hi, kth)
            assert np.array_equal(q[:lo], p[:lo]) and np.array_equal(q[hi:], p[hi:])
            assert q[kth, axis] == np.sort(p[lo:hi, axis])[kth - lo]
            assert (q[lo:kth, axis] <= q[kth, axis]).all()
            assert (q[kth + 1 : hi, axis] >= q[kth, axis]).all()
            rows = np.lexsort(q[lo:hi].T), np.lexsort(p[lo:hi].T)
            assert np.array_equal(q[lo:hi][rows[0]], p[lo:hi][rows[1]])


def test_mark_in_disks_matches_brute_force():
    """mark_in_disks (the floor's point count, through the planar leaf walk it shares with
    the kernel sums) marks exactly the points within a closed disk's periodic distance."""
    rng = np.random.default_rng(31)
    lx, ly = 2.0, 1.0
    for name, pts in point_sets(rng):
        pts = pts * [lx, ly]
        index = make(pts)
        ordered = index[0]  # the index's order
        cx, cy = rng.random(7) * lx, rng.random(7) * ly
        r2 = (rng.random(7) * 0.3) ** 2
        r2[0] = 0.0  # a disk of radius 0 marks only points at its centre
        if len(ordered):
            cx[0], cy[0] = ordered[0]
        mark = np.zeros(len(ordered), np.bool_)
        got = engine_index.mark_in_disks(index, cx, cy, r2, lx, ly, mark)
        ex = np.abs(ordered[:, None, 0] - cx)
        ey = np.abs(ordered[:, None, 1] - cy)
        ex, ey = np.minimum(ex, lx - ex), np.minimum(ey, ly - ey)
        want = (ex * ex + ey * ey <= r2).any(axis=1)
        assert got == want.sum() and (mark == want).all(), name


def _check_partition(index, pts):
    """The tree's invariants (``test_tree_is_a_partition``'s), for ``pts`` (n, d) as
    indexed, in the plane or in space."""
    sorted_pts, box, node, split, _ = index
    d = pts.shape[1]
    assert sorted(map(tuple, sorted_pts[:, :d])) == sorted(map(tuple, pts))
    for t in range(len(node)):
        lo, hi, c, axis = node[t]
        inside = sorted_pts[lo:hi, :d]
        if hi > lo:  # tight boxes
            assert np.array_equal(box[t, :d], inside.min(0))
            assert np.array_equal(box[t, d:], inside.max(0))
        if c >= 0:
            assert node[c, 0] == lo and node[c, 1] == node[c + 1, 0] and node[c + 1, 1] == hi
            left = sorted_pts[node[c, 0] : node[c, 1], axis]
            right = sorted_pts[node[c + 1, 0] : node[c + 1, 1], axis]
            assert left.max(initial=-np.inf) <= split[t] <= right.min(initial=np.inf)
        else:
            assert hi - lo <= LEAF_SIZE or np.all(inside == inside[0])


@pytest.mark.parametrize(
    "case",
    ["clustered", "clustered, one thread", "spread", "on splits", "empty start",
     "more than there were"],
)  # fmt: skip
def test_merged_tree_counts_as_one_built_afresh(case, monkeypatch):
    """``merge_index`` (a continued run's index: the start's tree with new points) is a
    valid tree over all the points (tight boxes, splits that separate, leaves of at most
    LEAF_SIZE), counts in disks and cells as brute force does, and leaves the tree it was
    given as it was; rows and nodes move on two threads, or one after the other on one."""
    if case.endswith("one thread"):
        monkeypatch.setenv("KNNREFINE_THREADS", "1")
    rng = np.random.default_rng(31)
    old = rng.random((0 if case == "empty start" else 4000, 2))
    if case.startswith("clustered"):
        new = np.clip(rng.normal(0.3, 0.01, (500, 2)), 0, 0.999)
    elif case == "on splits":  # exactly on split values: the first child's side
        base = build_index(old.copy())
        new = np.column_stack([base.split[:300], base.split[:300]])
    elif case == "more than there were":  # every leaf grows and splits
        new = rng.random((9000, 2))
    else:
        new = rng.random((700, 2))
    index = build_index(old.copy())
    before = [a.copy() for a in index]
    merged = engine_index.merge_index(index, new)
    for a, b in zip(index, before, strict=True):
        assert np.array_equal(a, b)
    if case == "empty start":  # nothing to merge into: the caller builds afresh
        assert merged is None
        return
    every = np.concatenate([old, new])
    _check_partition(merged, every)
    stack = np.zeros(STACK_SIZE, np.int64)
    for cx, cy, r in rng.random((300, 3)) * [1, 1, 0.1]:
        brute = int((((every - [cx, cy]) ** 2).sum(1) <= r * r).sum())
        assert count_in_disk(merged, cx, cy, r * r, 10**9, 10.0, 10.0, stack) == brute


def test_merged_weighted_tree_sums_the_new_weights():
    rng = np.random.default_rng(32)
    old, new = rng.random((3000, 2)), np.clip(rng.normal(0.6, 0.02, (400, 2)), 0, 0.999)
    w_old, w_new = rng.random(3000) + 0.5, rng.random(400) + 0.5
    merged = engine_index.merge_index(build_index(old.copy(), weights=w_old), new, w_new)
    fresh = build_index(np.concatenate([old, new]), weights=np.concatenate([w_old, w_new]))
    assert np.isclose(merged.weight[0], fresh.weight[0], rtol=1e-14)
    every, w = np.concatenate([old, new]), np.concatenate([w_old, w_new])
    stack = np.zeros(STACK_SIZE, np.int64)
    for cx, cy, r in rng.random((200, 3)) * [1, 1, 0.1]:
        brute = w[((every - [cx, cy]) ** 2).sum(1) <= r * r].sum()
        got = count_in_disk(merged, cx, cy, r * r, 1e18, 10.0, 10.0, stack)
        assert np.isclose(got, brute, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("weighted", [False, True], ids=["counts", "weights"])
def test_a_grown_forest_counts_as_one_tree_of_all_its_points(weighted):
    """``grow_forest`` (a continued run's index: the start's tree untouched, the new points
    in a second tree) counts disks and cells, across the period, as brute force over every
    point does, batch after batch; the forest it grew from is left as it was; the extra
    tree is merged into the main one once it holds more than EXTRA_UP_TO of its points;
    ``tree_of`` is a valid tree of them all."""
    rng = np.random.default_rng(33)
    pts = rng.random((4000, 2))
    w = rng.random(4000) + 0.5 if weighted else None
    forest = engine_index.forest_of(build_index(pts.copy(), weights=w))
    main = forest.main
    stack = np.zeros(STACK_SIZE, np.int64)
    mask = np.zeros(LEAF_SIZE, np.bool_)
    extras = []
    for _ in range(6):  # 150 points a batch: the fourth passes 4000 / 8 and folds
        new = np.clip(rng.normal(rng.random(2), 0.03, (150, 2)), 0, 0.999)
        w_new = rng.random(150) + 0.5 if weighted else None
        before = [a.copy() for a in forest.extra]
        grown = engine_index.grow_forest(forest, new, w_new)
        for a, b in zip(forest.extra, before, strict=True):
            assert np.array_equal(a, b)
        pts = np.concatenate([pts, new])
        w = np.concatenate([w, w_new]) if weighted else None
        forest = grown
        extras.append(len(forest.extra.pts))
        cover = periodic_copies(pts, 1.0, 1.0)
        cw = np.tile(w, 9) if weighted else np.ones(len(cover))
        for _ in range(60):
            c, r = rng.random(2) * 1.2 - 0.1, 0.2 * rng.random()
            d2 = ((cover - c) ** 2).sum(1)
            brute = cw[d2 <= r * r].sum()
            got = count_in_disk(forest, c[0], c[1], r * r, 1e18, 1.0, 1.0, stack)
            assert np.isclose(got, brute, rtol=1e-12, atol=1e-12)
            nb, hc, R2 = oracle.random_cell(rng)
            inside = oracle.in_cell(cover - c, nb, hc, R2, 1.0)
            got = count_in_cell(forest, c[0], c[1], nb[:, 0].copy(), nb[:, 1].copy(), hc,
                                len(hc), R2, 1e18, 1.0, 1.0, stack, mask)  # fmt: skip
            assert np.isclose(got, cw[inside].sum(), rtol=1e-12, atol=1e-12)
    assert extras == [150, 300, 450, 0, 150, 300]  # 600 > 4000 / 8: merged at the 4th
    assert forest.main is not main and len(forest.main.pts) == 4600 and len(pts) == 4900
    one = engine_index.tree_of(forest)
    _check_partition(one, pts)
    assert engine_index.marked_in_disks(forest, np.array([0.5]), np.array([0.5]),
                                        np.array([0.04]), 1.0, 1.0) == int(
        (((pts - 0.5) ** 2).sum(1) <= 0.04).sum())  # fmt: skip


def test_a_point_index_over_a_forest_merges_it_when_first_asked():
    """A continued mesh keeps its index's two trees; d_Pk at points (which needs one tree)
    merges them once, and answers as an index built over every point does."""
    rng = np.random.default_rng(34)
    from knnrefine._engine.embedding import Embedding

    emb = Embedding.make((0.0, 0.0, 1.0, 1.0), (False, False))
    old, new = rng.random((3000, 2)), np.clip(rng.normal(0.4, 0.02, (200, 2)), 0, 1)
    tree = build_index(emb.to_internal(old))
    forest = engine_index.grow_forest(tree, emb.to_internal(new))
    kept = engine_index.PointIndex(emb, forest, None)
    assert kept.n == 3200 and len(kept.forest.extra.pts) == 200
    every = np.concatenate([old, new])
    fresh = engine_index.PointIndex.build(every, (0.0, 0.0, 1.0, 1.0), (False, False))
    x = rng.random((300, 2))
    assert np.array_equal(kept.kth(x, 25), fresh.kth(x, 25))
    assert len(kept.forest.extra.pts) == 0 and len(kept.index.pts) == 3200


@pytest.mark.parametrize("case", ["clustered", "spread", "weighted"])
def test_merged_tree_in_space_counts_as_one_built_afresh(case):
    """``index3.merge_index3`` (a continued run's index in space and on the sphere): a valid
    tree over all the points whose counts in balls are brute force's, the given tree left
    as it was; its grown leaves split by ``_build3`` and grafted in."""
    from knnrefine._engine.index3 import build_index3, holds_k_within3, merge_index3

    rng = np.random.default_rng(33)
    old = rng.random((5000, 3))
    new = (np.clip(rng.normal(0.4, 0.01, (900, 3)), 0, 0.999) if case == "clustered"
           else rng.random((3000, 3)))  # fmt: skip
    w_old = w_new = None
    if case == "weighted":
        w_old, w_new = rng.random(len(old)) + 0.5, rng.random(len(new)) + 0.5
    index = build_index3(old.copy(), weights=w_old)
    before = [a.copy() for a in index]
    merged = merge_index3(index, new, w_new)
    for a, b in zip(index, before, strict=True):
        assert np.array_equal(a, b)
    every = np.concatenate([old, new])
    _check_partition(merged, every)
    w = np.ones(len(every)) if w_old is None else np.concatenate([w_old, w_new])
    x, r = rng.random((300, 3)), rng.uniform(0.02, 0.2, 300)
    dist = np.linalg.norm(every[None] - x[:, None], axis=2)
    held = (w * (dist <= r[:, None])).sum(axis=1)
    k = np.median(held) + 0.25  # (no ball's sum within rounding of k)
    got = holds_k_within3(merged, x, r**2, float(k), np.full(3, 10.0))
    assert np.array_equal(got, held >= k)
