"""Spatial index over the input points P: a static kd-tree that counts, with early exit.

The input points never enter the triangulation; refinement only asks two questions about
them, both of the form "does this region hold at least k points of P":

* the closed circumball of a triangle (``count_in_disk``), and
* the closed Voronoi cell of a mesh vertex, an intersection of half-planes inside the disk of
  radius R(v) about v (``count_in_cell``).

The tree is built once by median splits along the wider side of each node's tight bounding
box; the points are permuted in place so that every node owns a contiguous range of them and
its count is ``hi - lo``. A query adds whole nodes that lie inside the region, skips nodes
that miss it, tests the points of boundary leaves one by one, and stops as soon as the count
reaches k. On the torus a query is repeated for each periodic copy of the region that meets
the fundamental domain (regions are smaller than half a period).

Weighted points (``build_index(..., weights=w)``) count with their weights: a region "holds
k points" when their weights sum to k or more; whole nodes add their weight total, points of
boundary leaves their own weight. Without weights every point weighs 1 and the counts are
the integer counts (the same code, a branch on whether ``weight`` is empty).

The refinement counts with a ``state.PointForest``: the tree it started with and a second
one over points added since (a continued run, ``grow_forest``; empty otherwise), counted as
one (``count_in_disk``, ``count_in_cell`` ask the second tree for what the first left short
of k), so that a batch of new points never copies the large tree.

Layout, chosen for the cache (a query visits both children of a node, whose boxes share one
64-byte line): ``pts`` (n, 2) float64, permuted, or (n, 3) with each point's weight in the
third column; ``box`` (nodes, 4) float64 tight bounding
boxes (x0, y0, x1, y1); ``node`` (nodes, 4) int64: lo, hi, the first child (the second is
next to it; -1 at a leaf) and the split axis; ``split`` (nodes,) float64: the split value
(points of the first child are <= it, of the second >= it, along the axis); ``weight``
(nodes,) float64: each node's weight total (empty without weights). A query first descends
while its region lies strictly on one side of the split, then counts from there.
"""

import numpy as np

from .geometry import plus_compensated
from .jit import kernel
from .state import NODE_AXIS, NODE_CHILD, NODE_HI, NODE_LO, PointForest, PointTree
from .threads import in_chunks, kth_range, run_all
from .threads import workers as thread_count

LEAF_SIZE = 32
STACK_SIZE = 128  # > 2 * tree depth for any n that fits in memory


@kernel(inline="always")
def _swap_rows(pts, i, j):
    for a in range(pts.shape[1]):
        pts[i, a], pts[j, a] = pts[j, a], pts[i, a]


@kernel()
def select_kth(pts, axis, lo, hi, kth):
    """Partially sort the rows pts[lo:hi] by coordinate ``axis`` so that row kth is in place.

    Floyd and Rivest's selection (1975): on a long range, first put in place the kth row of
    a sample range around it (about n^(2/3) rows), then partition the whole range once about
    that row's value, which lies close to the answer, so that what is left is short: about
    1.5 n comparisons instead of quickselect's 3 n."""
    left = lo
    right = hi - 1
    while right - left > 600:
        n = right - left + 1
        i = kth - left + 1
        z = np.log(n)
        s = 0.5 * np.exp(2.0 * z / 3.0)
        sd = 0.5 * np.sqrt(z * s * (n - s) / n) * (-1.0 if i < n / 2 else 1.0)
        sample_lo = max(left, int(kth - i * s / n + sd))
        sample_hi = min(right, int(kth + (n - i) * s / n + sd))
        _quickselect(pts, axis, sample_lo, sample_hi + 1, kth)
        t = pts[kth, axis]
        a = left
        b = right
        _swap_rows(pts, left, kth)
        if pts[right, axis] > t:
            _swap_rows(pts, right, left)
        while a < b:
            _swap_rows(pts, a, b)
            a += 1
            b -= 1
            while pts[a, axis] < t:
                a += 1
            while pts[b, axis] > t:
                b -= 1
        if pts[left, axis] == t:
            _swap_rows(pts, left, b)
        else:
            b += 1
            _swap_rows(pts, b, right)
        if b <= kth:
            left = b + 1
        if kth <= b:
            right = b - 1
    _quickselect(pts, axis, left, right + 1, kth)


@kernel()
def _quickselect(pts, axis, lo, hi, kth):
    """``select_kth`` by quickselect with a median-of-three pivot (for short ranges)."""
    left = lo
    right = hi - 1
    while right > left:
        mid = (left + right) >> 1
        x0 = pts[left, axis]  # median of three as pivot
        x1 = pts[mid, axis]
        x2 = pts[right, axis]
        if x0 > x1:
            x0, x1 = x1, x0
        if x1 > x2:
            x1 = x2
            if x0 > x1:
                x1 = x0
        pivot = x1
        i = left
        j = right
        while i <= j:
            while pts[i, axis] < pivot:
                i += 1
            while pts[j, axis] > pivot:
                j -= 1
            if i <= j:
                _swap_rows(pts, i, j)
                i += 1
                j -= 1
        if kth <= j:
            right = j
        elif kth >= i:
            left = i
        else:
            break


@kernel(entry=True)
def node_bound(n):
    """Nodes of the tree over n points (an upper bound when many points coincide)."""
    count = 0
    sizes = np.empty(STACK_SIZE, np.int64)
    sizes[0] = n
    sp = 1
    while sp > 0:
        sp -= 1
        m = sizes[sp]
        count += 1
        if m > LEAF_SIZE:
            sizes[sp] = m >> 1
            sizes[sp + 1] = m - (m >> 1)
            sp += 2
    return count


@kernel(entry=True, nogil=True)
def _build(pts, box, node, split, root, free, levels, frontier):
    """Split node ``root`` (its row range set) and its descendants, numbering new nodes from
    ``free``. Nodes ``levels`` below the root are not split but listed in ``frontier`` (their
    subtrees are built separately, possibly in parallel). Returns (next free node, frontier
    length)."""
    stack = np.empty(STACK_SIZE, np.int64)
    depth = np.empty(STACK_SIZE, np.int64)
    stack[0] = root
    depth[0] = 0
    sp = 1
    nf = 0
    while sp > 0:
        sp -= 1
        t = stack[sp]
        a = node[t, NODE_LO]
        b = node[t, NODE_HI]
        if depth[sp] == levels and b - a > LEAF_SIZE:
            frontier[nf] = t
            nf += 1
            continue
        x0 = np.inf
        y0 = np.inf
        x1 = -np.inf
        y1 = -np.inf
        for i in range(a, b):
            x = pts[i, 0]
            y = pts[i, 1]
            x0 = min(x0, x)
            x1 = max(x1, x)
            y0 = min(y0, y)
            y1 = max(y1, y)
        box[t, 0] = x0
        box[t, 1] = y0
        box[t, 2] = x1
        box[t, 3] = y1
        if b - a <= LEAF_SIZE or (x1 == x0 and y1 == y0):
            node[t, NODE_CHILD] = -1
            continue
        mid = (a + b) >> 1
        axis = 0 if x1 - x0 >= y1 - y0 else 1
        select_kth(pts, axis, a, b, mid)
        c = free
        free += 2
        node[t, NODE_CHILD] = c
        node[t, NODE_AXIS] = axis
        split[t] = pts[mid, axis]
        node[c, NODE_LO] = a
        node[c, NODE_HI] = mid
        node[c + 1, NODE_LO] = mid
        node[c + 1, NODE_HI] = b
        below = depth[sp] + 1
        stack[sp] = c
        stack[sp + 1] = c + 1
        depth[sp] = below
        depth[sp + 1] = below
        sp += 2
    return free, nf


@kernel(entry=True)
def _close_gaps(box, node, split, starts, ends):
    """Move the node blocks [starts[j], ends[j]) (ascending, disjoint) down so that each
    follows the previous one, and renumber the child links into them. Returns the node
    count."""
    nb = starts.shape[0]
    shift = np.zeros(nb, np.int64)
    to = starts[0]
    for j in range(nb):
        shift[j] = starts[j] - to
        for t in range(starts[j], ends[j]):
            u = t - shift[j]
            for c in range(4):
                box[u, c] = box[t, c]
                node[u, c] = node[t, c]
            split[u] = split[t]
        to += ends[j] - starts[j]
    for u in range(to):
        c = node[u, NODE_CHILD]
        if c < 0:
            continue
        for j in range(nb):
            if starts[j] <= c < ends[j]:
                node[u, NODE_CHILD] = c - shift[j]
    return to


PARALLEL_MIN = 100_000  # points; below this one thread builds faster than two start


def build_index(pts, workers=None, weights=None):
    """Build the kd-tree over the (n, 2) array pts, which it permutes in place and keeps
    (with ``weights``, (n,) finite and >= 0, it keeps a new (n, 3) array of both instead).
    Returns the index, a ``state.PointTree``.

    The top levels are split here; the subtrees below them are built by ``workers`` threads
    (default: ``threads.workers()``) when there are at least PARALLEL_MIN points.
    The permutation and every node's rows, box and split are those of a one-thread build;
    only the nodes' numbering differs."""
    if weights is not None:
        pts = np.column_stack([pts[:, 0], pts[:, 1], np.asarray(weights, np.float64)])
    pts, box, node, split = build_tree(pts, workers)
    weight = np.zeros(0)
    if weights is not None:
        weight = np.empty(node.shape[0])
        node_weights(pts, node, weight)
    return PointTree(pts, box, node, split, weight)


@kernel(entry=True)
def node_weights(pts, node, weight):
    """weight[t] = the sum of node t's points' weights, their last column (compensated:
    ``geometry.plus_compensated``)."""
    last = pts.shape[1] - 1
    for t in range(node.shape[0]):
        total = 0.0
        comp = 0.0
        for i in range(node[t, NODE_LO], node[t, NODE_HI]):
            total, comp = plus_compensated(total, comp, pts[i, last])
        weight[t] = total + comp


def build_tree(pts, workers):
    n = pts.shape[0]
    workers = max(1, thread_count() if workers is None else int(workers))
    levels = workers.bit_length() - 1 if n >= PARALLEL_MIN else 0
    cap = node_bound(n)
    box = np.empty((cap, 4))
    node = np.empty((cap, 4), np.int64)
    split = np.zeros(cap)
    node[0, NODE_LO] = 0
    node[0, NODE_HI] = n
    frontier = np.empty(max(1, 1 << levels), np.int64)
    if levels == 0:
        nnodes, _ = _build(pts, box, node, split, 0, 1, -1, frontier)
        return pts, box[:nnodes], node[:nnodes], split[:nnodes]
    top, nf = _build(pts, box, node, split, 0, 1, levels, frontier)
    roots = frontier[:nf]
    starts = np.empty(nf + 1, np.int64)
    starts[0] = 0
    base = top
    for j, r in enumerate(roots):
        starts[j + 1] = base
        base += node_bound(int(node[r, NODE_HI] - node[r, NODE_LO])) - 1
    ends = np.empty(nf + 1, np.int64)
    ends[0] = top

    def subtree(j):
        return _build(pts, box, node, split, roots[j], starts[j + 1], -1, frontier[:0])[0]

    ends[1:] = run_all(subtree, nf)
    nnodes = _close_gaps(box, node, split, starts, ends)
    return pts, box[:nnodes], node[:nnodes], split[:nnodes]


# -- more points into a built tree (a continued run, ``refine(..., start=)``) -----------------


@kernel(entry=True, nogil=True)
def leaves_of(node, split, q):
    """The leaf each point q[i] descends to: the side of each split it lies on (the first
    child on the split value, whose points are <= it)."""
    out = np.empty(q.shape[0], np.int64)
    for i in range(q.shape[0]):
        t = 0
        while node[t, NODE_CHILD] >= 0:
            if q[i, node[t, NODE_AXIS]] <= split[t]:
                t = node[t, NODE_CHILD]
            else:
                t = node[t, NODE_CHILD] + 1
        out[i] = t
    return out


@kernel(entry=True, nogil=True)
def _insert_rows(flat, extra, at, cols, out):
    """``out`` (flat, ``cols`` numbers a row): the old rows (``flat``) with new row j
    (``extra``) inserted before old row at[j] (ascending), copied in runs. (One thread:
    the copy is bound by memory, two took longer here.)"""
    src = 0
    for j in range(at.shape[0]):
        a = src * cols
        b = at[j] * cols
        out[a + j * cols : b + j * cols] = flat[a:b]
        for c in range(cols):
            out[b + j * cols + c] = extra[j, c]
        src = at[j]
    a = src * cols
    out[a + at.shape[0] * cols :] = flat[a:]


@kernel(entry=True, nogil=True)
def _merge_nodes(box, node, added, extra):
    """Every node's row range moved by the new rows before it and its box grown by its new
    rows, in one depth-first pass (leaves in row order: leaf t takes the next added[t] rows
    of ``extra``, which are in that order); an inner node's box becomes the union of its
    children's once both are done (tight boxes stay tight)."""
    d = box.shape[1] // 2
    stack = np.empty(STACK_SIZE, np.int64)
    after = np.zeros(STACK_SIZE, np.bool_)
    stack[0] = 0
    sp = 1
    shift = 0
    row = 0
    while sp > 0:
        t = stack[sp - 1]
        c = node[t, NODE_CHILD]
        if after[sp - 1]:  # both children done
            node[t, NODE_HI] += shift
            for a in range(d):
                box[t, a] = min(box[c, a], box[c + 1, a])
                box[t, a + d] = max(box[c, a + d], box[c + 1, a + d])
            sp -= 1
            continue
        node[t, NODE_LO] += shift
        if c >= 0:
            after[sp - 1] = True
            stack[sp] = c + 1
            after[sp] = False
            stack[sp + 1] = c
            after[sp + 1] = False
            sp += 2
            continue
        for j in range(row, row + added[t]):
            for a in range(d):
                box[t, a] = min(box[t, a], extra[j, a])
                box[t, a + d] = max(box[t, a + d], extra[j, a])
        row += added[t]
        shift += added[t]
        node[t, NODE_HI] += shift
        sp -= 1


@kernel(entry=True, nogil=True)
def _split_leaves(pts, box, node, split, grown, free):
    """``_build`` from each leaf in ``grown`` (its rows set), numbering new nodes from
    ``free``; returns the next free node."""
    none = np.empty(0, np.int64)
    for i in range(grown.shape[0]):
        free = _build(pts, box, node, split, grown[i], free, -1, none)[0]
    return free


def merge_index(index, q, weights=None, split_leaves=None):
    """The index of ``index``'s points and the points q (b, d) together (internal
    coordinates; ``weights`` (b,) for a weighted index), made from ``index`` without
    building it again: each new point goes into the leaf it descends to, after that leaf's
    rows (the rows copied once, in runs between the leaves that grow), every
    node's range moved by the rows inserted before it and its box grown (one depth-first
    pass), and a leaf grown past LEAF_SIZE split
    as a fresh build splits (the splits above stay valid: a point descends by them). Counts
    are those of a tree built afresh; ``index`` is left as it was; None when it is empty
    (the caller builds afresh). About b log n work plus one copy of the rows, against the
    n log n of a build. ``split_leaves(pts, box, node, split, leaves, free)`` splits those
    leaves numbering new nodes from ``free`` and returns the next free node: the plane's
    ``_split_leaves`` by default; ``index3.merge_index3`` gives space's.
    """
    pts, box, node, split, weight = index
    d = box.shape[1] // 2
    q = np.ascontiguousarray(q, dtype=np.float64).reshape(-1, d)
    if weight.shape[0] > 0:
        q = np.ascontiguousarray(np.column_stack([q, np.asarray(weights, np.float64)]))
    if pts.shape[0] == 0:
        return None
    n, b, cols = pts.shape[0], q.shape[0], pts.shape[1]
    leaf = leaves_of(node, split, q)
    # leaves own disjoint, non-empty row ranges: each new row goes before the old row that
    # follows its leaf, and rows of one leaf keep their order
    at = node[leaf, NODE_HI]
    order = np.argsort(at, kind="stable")
    at, leaf, extra = at[order], leaf[order], np.ascontiguousarray(q[order])
    count = node.shape[0]
    added = np.bincount(leaf, minlength=count)
    sizes = node[:, NODE_HI] - node[:, NODE_LO] + added
    grown = np.flatnonzero((added > 0) & (sizes > LEAF_SIZE))  # (only leaves have added)
    # a split leaf's leaves hold >= LEAF_SIZE / 2 rows: fewer than 4 s / LEAF_SIZE nodes
    room = count + int(np.sum(4 * sizes[grown] // LEAF_SIZE + 1))
    out_node, out_box, out_split = (
        np.empty((room, *x.shape[1:]), x.dtype) for x in (node, box, split)
    )
    out_pts = np.empty((n + b, cols))

    def rows():
        _insert_rows(pts.reshape(-1), extra, at, cols, out_pts.reshape(-1))

    def nodes():
        out_node[:count], out_box[:count], out_split[:count] = node, box, split
        _merge_nodes(out_box, out_node, added, extra)

    # the rows (bound by memory) copied on one thread while the nodes move on another
    if thread_count() > 1:
        run_all(lambda j: rows() if j == 0 else nodes(), 2)
    else:
        rows()
        nodes()
    if len(grown):
        count = (split_leaves or _split_leaves)(out_pts, out_box, out_node, out_split, grown,
                                                 count)  # fmt: skip
    out_node, out_box, out_split = out_node[:count], out_box[:count], out_split[:count]
    out_weight = np.zeros(0)
    if weight.shape[0] > 0:
        out_weight = np.empty(out_node.shape[0])
        node_weights(out_pts, out_node, out_weight)
    return PointTree(out_pts, out_box, out_node, out_split, out_weight)


EXTRA_UP_TO = 0.125  # the extra tree's points, as a fraction of the main tree's, at most


def forest_of(index):
    """``index`` as a ``state.PointForest``: a PointTree with an empty extra tree, or the
    forest itself."""
    if isinstance(index, PointForest):
        return index
    empty = PointTree(
        np.zeros((0, index.pts.shape[1])), np.zeros((1, index.box.shape[1])),
        np.array([[0, 0, -1, 0]], np.int64), np.zeros(1), np.zeros(min(index.weight.shape[0], 1)),
    )  # fmt: skip
    return PointForest(index, empty)


def points_in(forest):
    """The number of points of both trees of ``forest`` (or of one tree)."""
    return sum(int(t.pts.shape[0]) for t in forest_of(forest))


def tree_of(forest, merge=None):
    """The one tree holding both trees' points (``merge``: ``merge_index``, or space's
    ``index3.merge_index3``), or the main tree when the extra one is empty."""
    main, extra = forest_of(forest)
    if extra.pts.shape[0] == 0:
        return main
    d = main.box.shape[1] // 2
    weights = extra.pts[:, d] if extra.weight.shape[0] > 0 else None
    return (merge or merge_index)(main, extra.pts[:, :d], weights)


def grow_forest(forest, q, weights=None, merge=None, build=None):
    """The forest of ``forest``'s points and the points q (b, d) (internal coordinates;
    ``weights`` (b,) for a weighted index) without copying its main tree: the new points
    merged into its extra tree (``merge_index``) or one built over them, and the extra tree
    merged into the main one once it holds more than EXTRA_UP_TO of its points (the copy
    of every row then, for many batches: Bentley and Saxe's logarithmic method with two
    levels). ``forest`` is left as it was; None when its main tree is empty (the caller
    builds afresh). ``merge``, ``build``: ``merge_index`` and ``build_index`` by default."""
    merge, build = merge or merge_index, build or build_index
    main, extra = forest_of(forest)
    if main.pts.shape[0] == 0:
        return None
    d = main.box.shape[1] // 2
    q = np.ascontiguousarray(q, dtype=np.float64).reshape(-1, d)
    weights = None if weights is None else np.asarray(weights, np.float64)
    m = extra.pts.shape[0]
    if m + q.shape[0] > EXTRA_UP_TO * main.pts.shape[0]:
        if m:
            q = np.concatenate([extra.pts[:, :d], q])
            if weights is not None:
                weights = np.concatenate([extra.pts[:, d], weights])
        return forest_of(merge(main, q, weights))
    if m == 0:
        return PointForest(main, build(q.copy(), weights=weights))
    return PointForest(main, merge(extra, q, weights))


def marked_in_disks(forest, cx, cy, r2, lx, ly):
    """How many points of ``forest`` (both trees) lie in one of the closed disks
    (``mark_in_disks``)."""
    total = 0
    for tree in forest_of(forest):
        if tree.pts.shape[0]:
            total += mark_in_disks(tree, cx, cy, r2, lx, ly, np.zeros(tree.pts.shape[0], np.bool_))
    return total


@kernel(inline="always")
def held_by_node(node, weight, t):
    """What node t holds: its number of points, or its weight total for weighted points."""
    if weight.shape[0] == 0:
        return float(node[t, NODE_HI] - node[t, NODE_LO])
    return weight[t]


@kernel(inline="always")
def _weight_of(pts, weight, i):
    """Point i's weight: 1 unless the points are weighted (a third column)."""
    return 1.0 if weight.shape[0] == 0 else pts[i, 2]


@kernel(nrt=False)
def _start(node, split, cx, cy, r):
    """The deepest node whose split region strictly contains the disk (c, r): points outside
    it cannot lie in the disk."""
    t = 0
    while node[t, NODE_CHILD] >= 0:
        c = cx if node[t, NODE_AXIS] == 0 else cy
        if c + r < split[t]:
            t = node[t, NODE_CHILD]
        elif c - r > split[t]:
            t = node[t, NODE_CHILD] + 1
        else:
            break
    return t


@kernel(nrt=False)
def _count_disk(index, cx, cy, r2, k, stack):
    """Points of P in the closed disk (c, sqrt(r2)), counting (their weight) up to at least
    k (weights summed with ``geometry.plus_compensated``)."""
    count = 0.0
    comp = 0.0
    pts, box, node, split, weight = index
    if node[0, NODE_HI] == 0:
        return count
    stack[0] = _start(node, split, cx, cy, np.sqrt(r2))
    sp = 1
    while sp > 0:
        sp -= 1
        t = stack[sp]
        # nearest point of the box to the centre
        dx = max(box[t, 0] - cx, 0.0, cx - box[t, 2])
        dy = max(box[t, 1] - cy, 0.0, cy - box[t, 3])
        if dx * dx + dy * dy > r2:
            continue
        # farthest corner
        fx = max(cx - box[t, 0], box[t, 2] - cx)
        fy = max(cy - box[t, 1], box[t, 3] - cy)
        if fx * fx + fy * fy <= r2:
            count, comp = plus_compensated(count, comp, held_by_node(node, weight, t))
            if count + comp >= k:
                return count + comp
            continue
        c = node[t, NODE_CHILD]
        if c < 0:
            if weight.shape[0] == 0:
                inside = 0
                for i in range(node[t, NODE_LO], node[t, NODE_HI]):
                    ex = pts[i, 0] - cx
                    ey = pts[i, 1] - cy
                    inside += ex * ex + ey * ey <= r2
                count += inside
            else:
                for i in range(node[t, NODE_LO], node[t, NODE_HI]):
                    ex = pts[i, 0] - cx
                    ey = pts[i, 1] - cy
                    if ex * ex + ey * ey <= r2:
                        count, comp = plus_compensated(count, comp, pts[i, 2])
            if count + comp >= k:
                return count + comp
            continue
        # the child on the centre's side is visited first: where the points are
        near = 0 if (cx if node[t, NODE_AXIS] == 0 else cy) <= split[t] else 1
        stack[sp] = c + 1 - near
        stack[sp + 1] = c + near
        sp += 2
    return count + comp


@kernel(inline="always")
def _copies(c, r, period):
    """The periodic shifts s (an inclusive range) for which the disk (c + s period, r) meets
    [0, period], given r < period / 2. The centre itself is never wrapped: shifting the copy
    whose disk holds the domain by 0 keeps it exact (wrapping -1e-125 into [0, 1) gives 1.0)."""
    s0 = -np.floor(c / period)
    lo = s0 - 1.0
    hi = s0 + 1.0
    if c + lo * period + r < 0.0:
        lo += 1.0
    if c + hi * period - r > period:
        hi -= 1.0
    return int(lo), int(hi)


@kernel(nrt=False)
def count_in_disk(forest, cx, cy, r2, k, lx, ly, stack):
    """Number of points of the periodic set P + (lx, ly)Z^2 in the closed disk (c, sqrt(r2)),
    P the points of both trees of ``forest`` (a ``state.PointForest``): exact when below k;
    otherwise the search stops early and returns some value >= k.
    Needs sqrt(r2) < min(lx, ly) / 2. Shifted copies of c round at the scale of the period;
    the copy nearest the domain is c itself when c is inside it. Coordinates are zero or of
    magnitude >= 1e-150 (squared distances must not underflow; the engine's are far larger)."""
    count = _disk_copies(forest.main, cx, cy, r2, k, lx, ly, stack)
    if count >= k or forest.extra.node[0, NODE_HI] == 0:
        return count
    return count + _disk_copies(forest.extra, cx, cy, r2, k - count, lx, ly, stack)


@kernel(nrt=False)
def _disk_copies(index, cx, cy, r2, k, lx, ly, stack):
    """``count_in_disk`` in one tree."""
    r = np.sqrt(r2)
    count = 0.0
    comp = 0.0
    x_lo, x_hi = _copies(cx, r, lx)
    y_lo, y_hi = _copies(cy, r, ly)
    for sx in range(x_lo, x_hi + 1):
        ox = cx + sx * lx
        if ox + r < 0.0 or ox - r > lx:
            continue
        for sy in range(y_lo, y_hi + 1):
            oy = cy + sy * ly
            if oy + r < 0.0 or oy - r > ly:
                continue
            held = _count_disk(index, ox, oy, r2, k - (count + comp), stack)
            count, comp = plus_compensated(count, comp, held)
            if count + comp >= k:
                return count + comp
    return count + comp


@kernel(nrt=False)
def _count_cell(index, vx, vy, hx, hy, hc, nh, r2, k, stack, mask):
    """Points of P in the closed cell (see count_in_cell), counting (their weight, summed
    with ``geometry.plus_compensated``) up to at least k."""
    count = 0.0
    comp = 0.0
    pts, box, node, split, weight = index
    if node[0, NODE_HI] == 0:
        return count
    stack[0] = _start(node, split, vx, vy, np.sqrt(r2))
    sp = 1
    while sp > 0:
        sp -= 1
        t = stack[sp]
        x0 = box[t, 0] - vx
        x1 = box[t, 2] - vx
        y0 = box[t, 1] - vy
        y1 = box[t, 3] - vy
        dx = max(x0, 0.0, -x1)
        dy = max(y0, 0.0, -y1)
        if dx * dx + dy * dy > r2:
            continue
        fx = max(-x0, x1)
        fy = max(-y0, y1)
        inside = fx * fx + fy * fy <= r2
        outside = False
        for j in range(nh):
            a = hx[j]
            b = hy[j]
            hmax = a * (x1 if a > 0.0 else x0) + b * (y1 if b > 0.0 else y0)
            if hmax <= hc[j]:
                continue
            inside = False
            hmin = a * (x0 if a > 0.0 else x1) + b * (y0 if b > 0.0 else y1)
            if hmin > hc[j]:
                outside = True
                break
        if outside:
            continue
        if inside:
            count, comp = plus_compensated(count, comp, held_by_node(node, weight, t))
            if count + comp >= k:
                return count + comp
            continue
        c = node[t, NODE_CHILD]
        if c < 0:
            # one vectorisable pass per constraint over blocks of the leaf's points (a leaf
            # of coincident points can exceed LEAF_SIZE)
            found = 0
            for lo in range(node[t, NODE_LO], node[t, NODE_HI], LEAF_SIZE):
                m = min(LEAF_SIZE, node[t, NODE_HI] - lo)
                for i in range(m):
                    ex = pts[lo + i, 0] - vx
                    ey = pts[lo + i, 1] - vy
                    mask[i] = ex * ex + ey * ey <= r2
                for j in range(nh):
                    a = hx[j]
                    b = hy[j]
                    h = hc[j]
                    for i in range(m):
                        mask[i] &= a * (pts[lo + i, 0] - vx) + b * (pts[lo + i, 1] - vy) <= h
                if weight.shape[0] == 0:
                    for i in range(m):
                        found += mask[i]
                else:
                    for i in range(m):
                        if mask[i]:
                            count, comp = plus_compensated(count, comp, pts[lo + i, 2])
            count += found
            if count + comp >= k:
                return count + comp
            continue
        near = 0 if (vx if node[t, NODE_AXIS] == 0 else vy) <= split[t] else 1
        stack[sp] = c + 1 - near
        stack[sp + 1] = c + near
        sp += 2
    return count + comp


@kernel(nrt=False)
def count_in_cell(forest, vx, vy, hx, hy, hc, nh, r2, k, lx, ly, stack, mask):
    """Number of points of the periodic P in the closed cell {v + p : hx[j] px + hy[j] py <= hc[j]}
    contained in the disk (v, sqrt(r2)), P the points of both trees of ``forest``: exact when
    below k, otherwise some value >= k. For a Voronoi cell, (hx[j], hy[j]) is the j-th
    neighbour minus v and hc[j] half its squared length. ``mask`` is scratch of LEAF_SIZE
    booleans. Weighted points count their weight."""
    count = _cell_copies(forest.main, vx, vy, hx, hy, hc, nh, r2, k, lx, ly, stack, mask)
    if count >= k or forest.extra.node[0, NODE_HI] == 0:
        return count
    left = k - count
    return count + _cell_copies(forest.extra, vx, vy, hx, hy, hc, nh, r2, left, lx, ly, stack,
                                mask)  # fmt: skip


@kernel(nrt=False)
def _cell_copies(index, vx, vy, hx, hy, hc, nh, r2, k, lx, ly, stack, mask):
    """``count_in_cell`` in one tree."""
    r = np.sqrt(r2)
    count = 0.0
    comp = 0.0
    x_lo, x_hi = _copies(vx, r, lx)
    y_lo, y_hi = _copies(vy, r, ly)
    for sx in range(x_lo, x_hi + 1):
        ox = vx + sx * lx
        if ox + r < 0.0 or ox - r > lx:
            continue
        for sy in range(y_lo, y_hi + 1):
            oy = vy + sy * ly
            if oy + r < 0.0 or oy - r > ly:
                continue
            held = _count_cell(index, ox, oy, hx, hy, hc, nh, r2, k - (count + comp), stack, mask)
            count, comp = plus_compensated(count, comp, held)
            if count + comp >= k:
                return count + comp
    return count + comp


@kernel(entry=True)
def mark_in_disks(index, cx, cy, r2, lx, ly, mark):
    """Set mark[i] for every point i (in the index's order) of the periodic P lying in one of
    the closed disks (cx[d], cy[d], sqrt(r2[d])), each of radius below half a period. Returns
    the number of points marked (weights play no part)."""
    pts, box, node, split, weight = index
    stack = np.empty(STACK_SIZE, np.int64)
    leaves = np.empty(node.shape[0], np.int64)
    none = np.empty(0)
    for d in range(cx.shape[0]):
        r = np.sqrt(r2[d])
        x_lo, x_hi = _copies(cx[d], r, lx)
        y_lo, y_hi = _copies(cy[d], r, ly)
        for sx in range(x_lo, x_hi + 1):
            ox = cx[d] + sx * lx
            for sy in range(y_lo, y_hi + 1):
                oy = cy[d] + sy * ly
                if node[0, NODE_HI] == 0:
                    continue
                for f in range(leaves_near(box, node, none, r, ox, oy, stack, leaves)):
                    t = leaves[f]
                    for i in range(node[t, NODE_LO], node[t, NODE_HI]):
                        ex = pts[i, 0] - ox
                        ey = pts[i, 1] - oy
                        if ex * ex + ey * ey <= r2[d]:
                            mark[i] = True
    return int(mark.sum())


@kernel(inline="always")
def leaves_near(box, node, extent, r, x, y, stack, leaves):
    """The leaves whose bounding box lies within r + extent[t] of (x, y) (extent empty: r
    alone), into ``leaves``; returns how many. The planar walk of the tree: points within r
    (mark_in_disks, kernelsum.ball_moments), or, with extent[t] the widest kernel below node
    t, the leaves that may hold a kernel reaching (x, y) (kernelsum.kernel_sums)."""
    found = 0
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        t = stack[sp]
        dx = max(box[t, 0] - x, 0.0, x - box[t, 2])
        dy = max(box[t, 1] - y, 0.0, y - box[t, 3])
        reach = r + extent[t] if extent.shape[0] > 0 else r
        if dx * dx + dy * dy > reach * reach:
            continue
        c = node[t, NODE_CHILD]
        if c >= 0:
            stack[sp] = c
            stack[sp + 1] = c + 1
            sp += 2
        else:
            leaves[found] = t
            found += 1
    return found


@kernel(inline="always")
def _torus_gap(c, lo, hi, period):
    """Least and greatest torus distance from c to the interval [lo, hi] of [0, period)."""
    a = abs(lo - c)
    b = abs(hi - c)
    a = min(a, period - a)
    b = min(b, period - b)
    near = 0.0 if lo <= c <= hi else min(a, b)
    anti = c + 0.5 * period if c < 0.5 * period else c - 0.5 * period
    far = 0.5 * period if lo <= anti <= hi else max(a, b)
    return near, far


@kernel(nrt=False)
def count_in_torus_disk(index, cx, cy, r2, k, lx, ly, stack):
    """Number of points of P within torus distance sqrt(r2) of c, each point counted once, for
    any radius (``count_in_disk`` counts periodic copies and needs a radius below half the
    shorter period). Exact when below k; otherwise some value >= k. Used where a reach can
    exceed half a period: the initial mesh's precondition. Weighted points count their
    weight."""
    pts, box, node, split, weight = index
    if node[0, NODE_HI] == 0:
        return 0.0
    cx -= np.floor(cx / lx) * lx
    cy -= np.floor(cy / ly) * ly
    count = 0.0
    comp = 0.0
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        t = stack[sp]
        nx, fx = _torus_gap(cx, box[t, 0], box[t, 2], lx)
        ny, fy = _torus_gap(cy, box[t, 1], box[t, 3], ly)
        if nx * nx + ny * ny > r2:
            continue
        if fx * fx + fy * fy <= r2:
            count, comp = plus_compensated(count, comp, held_by_node(node, weight, t))
            if count + comp >= k:
                return count + comp
            continue
        c = node[t, NODE_CHILD]
        if c < 0:
            for i in range(node[t, NODE_LO], node[t, NODE_HI]):
                ex = abs(pts[i, 0] - cx)
                ey = abs(pts[i, 1] - cy)
                ex = min(ex, lx - ex)
                ey = min(ey, ly - ey)
                if ex * ex + ey * ey <= r2:
                    count, comp = plus_compensated(count, comp, _weight_of(pts, weight, i))
                    if count + comp >= k:
                        return count + comp
            continue
        stack[sp] = c
        stack[sp + 1] = c + 1
        sp += 2
    return count + comp


@kernel(entry=True)
def holds_k_within(index, xy, r2, k, lx, ly):
    """For each row of xy: does the closed torus disk of squared radius r2[i] about it hold at
    least k points of P (that is, d_{P,k}(xy[i])^2 <= r2[i])?"""
    out = np.zeros(xy.shape[0], np.bool_)
    stack = np.empty(STACK_SIZE, np.int64)
    for i in range(xy.shape[0]):
        out[i] = count_in_torus_disk(index, xy[i, 0], xy[i, 1], r2[i], k, lx, ly, stack) >= k
    return out


@kernel(entry=True, nogil=True)
def weights_at(index, qx, qy, out, start, stop):
    """out[j]: the number of points of P (weighted P: their weight) at exactly the place
    (qx[j], qy[j]), a point of the torus's fundamental domain: the closed disk of radius 0."""
    stack = np.empty(STACK_SIZE, np.int64)
    for j in range(start, stop):
        out[j] = _count_disk(index, qx[j], qy[j], 0.0, np.inf, stack)
    return 0


# -- the k-th nearest distance itself (for evaluating d_{P,k}, not for refining) ---------------


@kernel(inline="always")
def axis_gap(c, lo, hi, period, periodic):
    """Least and greatest distance along one axis from c to the interval [lo, hi]: on the
    circle of length ``period`` (c in [0, period)) when periodic, on the line otherwise."""
    if periodic:
        return _torus_gap(c, lo, hi, period)
    return max(lo - c, 0.0, c - hi), max(abs(c - lo), abs(c - hi))


WINDOW_LOW = -1  # the inner radius already holds k points
WINDOW_HIGH = -2  # the outer radius holds fewer than k
WINDOW_FULL = -3  # more points between the radii than the buffer holds


@kernel(nrt=False)
def select_held(buf, wbuf, n, target, unit):
    """The smallest value d of buf[:n] such that the values <= d hold at least ``target``
    (> 0, at most what all of them hold): their weights wbuf, or their number when ``unit``
    (wbuf is then neither read nor moved). A quickselect with a three-way partition, so that
    ties move together; reorders buf (and wbuf) in place."""
    lo = 0
    hi = n - 1
    while hi > lo:
        mid = (lo + hi) // 2
        a, b, c = buf[lo], buf[mid], buf[hi]
        pivot = max(min(a, b), min(max(a, b), c))
        # [lo, lt) < pivot, [lt, i) == pivot, (gt, hi] > pivot
        lt = lo
        i = lo
        gt = hi
        while i <= gt:
            v = buf[i]
            if v < pivot:
                buf[i], buf[lt] = buf[lt], buf[i]
                if not unit:
                    wbuf[i], wbuf[lt] = wbuf[lt], wbuf[i]
                lt += 1
                i += 1
            elif v > pivot:
                buf[i], buf[gt] = buf[gt], buf[i]
                if not unit:
                    wbuf[i], wbuf[gt] = wbuf[gt], wbuf[i]
                gt -= 1
            else:
                i += 1
        below = float(lt - lo)
        at = float(gt + 1 - lt)
        if not unit:
            below = 0.0
            comp = 0.0
            for e in range(lo, lt):
                below, comp = plus_compensated(below, comp, wbuf[e])
            below += comp
            at = 0.0
            comp = 0.0
            for e in range(lt, gt + 1):
                at, comp = plus_compensated(at, comp, wbuf[e])
            at += comp
        if below >= target:
            hi = lt - 1
        elif below + at >= target:
            return pivot
        else:
            target -= below + at
            lo = gt + 1
    return buf[lo]


@kernel(nrt=False)
def _kth_in_window(index, cx, cy, k, r_in, r_out, lx, ly, px, py, stack, buf, wbuf):
    """The squared distance from c to its k-th nearest point of P (for weighted P: the least
    radius whose closed disk holds weight >= k) if it lies in (r_in, r_out] (one traversal:
    nodes inside the inner disk are counted whole, points between the radii are kept in buf,
    with their weights in wbuf, then the one needed is selected), else WINDOW_LOW,
    WINDOW_HIGH or WINDOW_FULL. Periodic axes (px, py) use the distance of the circle, each
    point counted once whatever the radius; the others are planar."""
    pts, box, node, split, weight = index
    rin2 = r_in * r_in
    rout2 = r_out * r_out
    inner = 0.0
    inner_c = 0.0
    between = 0.0
    between_c = 0.0
    kept = 0
    cap = buf.shape[0]
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        t = stack[sp]
        nx, fx = axis_gap(cx, box[t, 0], box[t, 2], lx, px)
        ny, fy = axis_gap(cy, box[t, 1], box[t, 3], ly, py)
        if nx * nx + ny * ny > rout2:
            continue
        if fx * fx + fy * fy <= rin2:
            inner, inner_c = plus_compensated(inner, inner_c, held_by_node(node, weight, t))
            if inner + inner_c >= k:
                return WINDOW_LOW
            continue
        c = node[t, NODE_CHILD]
        if c >= 0:
            stack[sp] = c
            stack[sp + 1] = c + 1
            sp += 2
            continue
        for i in range(node[t, NODE_LO], node[t, NODE_HI]):
            ex = abs(pts[i, 0] - cx)
            ey = abs(pts[i, 1] - cy)
            if px:
                ex = min(ex, lx - ex)
            if py:
                ey = min(ey, ly - ey)
            d2 = ex * ex + ey * ey
            w = _weight_of(pts, weight, i)
            if d2 <= rin2:
                inner, inner_c = plus_compensated(inner, inner_c, w)
                if inner + inner_c >= k:
                    return WINDOW_LOW
            elif d2 <= rout2:
                if kept == cap:
                    return WINDOW_FULL
                buf[kept] = d2
                wbuf[kept] = w
                between, between_c = plus_compensated(between, between_c, w)
                kept += 1
    inner += inner_c
    if inner + (between + between_c) < k:
        return WINDOW_HIGH
    return select_held(buf, wbuf, kept, k - inner, weight.shape[0] == 0)


@kernel(entry=True, nogil=True)
def kth_distances(index, qx, qy, k, r_in, r_out, low, high, lx, ly, px, py, cap, out, start, stop):
    """out[i] = d_{P,k}(q_i) for i in [start, stop), internal units. (r_in[i], r_out[i]] is a
    guess that should hold it: a wrong one is moved outwards or inwards (by twice its width,
    then four times, ...) until it brackets the answer, never past the bounds low[i] <= d <=
    high[i], which must hold. ``cap``: the most points a window may hold. NaN where no window
    settles it within 200 tries (more points at one distance than ``cap``); the caller
    answers those another way. Query coordinates along periodic axes must lie in
    [0, period)."""
    stack = np.empty(STACK_SIZE, np.int64)
    buf = np.empty(cap)
    wbuf = np.empty(cap)
    for i in range(start, stop):
        known_low = max(low[i], 0.0)  # the ball of this radius holds less than k
        known_high = high[i]  # the ball of this radius holds k or more
        a = min(max(r_in[i], known_low), known_high)
        b = max(min(r_out[i], known_high), a)
        if not b > a:
            b = a + max(a, 1e-300)
        width = b - a
        out[i] = np.nan
        for _ in range(200):
            d2 = _kth_in_window(index, qx[i], qy[i], k, a, b, lx, ly, px, py, stack, buf, wbuf)
            done, out[i], a, b, width, known_low, known_high = move_window(
                d2, a, b, width, known_low, known_high
            )
            if done:
                break
    return 0


@kernel(inline="always")
def move_window(d2, a, b, width, known_low, known_high):
    """One step of the search for d_{P,k} in a window (a, b] (``kth_distances``, and
    ``index3.kth_distances3`` in space), after a window's answer d2 (a squared distance, or
    WINDOW_LOW, WINDOW_HIGH, WINDOW_FULL): (done, the distance (NaN unless known), the next
    window a, b, its width, and what is known: d_{P,k} in [known_low, known_high]). A
    window too low moves down by twice its width, one too high up, one too full halves."""
    if d2 >= 0.0:
        return True, np.sqrt(d2), a, b, width, known_low, known_high
    if d2 == WINDOW_LOW:
        if a == 0.0:  # weight k at distance 0
            return True, 0.0, a, b, width, known_low, known_high
        known_high = a
        width *= 2.0
        b = a
        a = max(known_low, a - width, 0.0)
    elif d2 == WINDOW_HIGH:
        known_low = b
        width *= 2.0
        a = b
        b = min(b + width, known_high)
    else:
        width *= 0.5
        b = a + width
    return not b > a, np.nan, a, b, width, known_low, known_high


class PointIndex:
    """The counting kd-tree over P with the embedding that maps input coordinates into its
    frame: exact d_{P,k} at any points, periodic axes by the distance of the circle, the others
    in the plane; weighted P counts weights. ``refine`` keeps the one it refined with on the
    Mesh (``Mesh.index``), so that evaluating d_{P,k} needs no second tree; ``build`` makes
    one for points alone. It holds the run's ``state.PointForest`` (``forest``: a continued
    run's two trees, which a later continuation grows) and merges it into one tree when
    that is first asked for (``index``). Space's meshes keep theirs here too (``merge``:
    ``index3.merge_index3``; its d_Pk is ``space.density.Index``'s)."""

    def __init__(self, embedding, index, fingerprint, merge=None):
        self.embedding = embedding
        self.forest = forest_of(index)  # a continued run's two trees (``grow_forest``)
        self._merge = merge  # what merges them (``tree_of``): space's merge_index3
        self._fingerprint = fingerprint  # or a function giving it, called when first asked
        self.n = points_in(self.forest)
        self.weighted = self.forest.main.weight.shape[0] > 0
        self.total = float(sum(t.weight[0] for t in self.forest if t.pts.shape[0])
                           if self.weighted else self.n)  # fmt: skip

    @property
    def index(self):
        """The one tree over every indexed point: a continued run's two trees are merged
        when first asked (``tree_of``), not by the run."""
        if self.forest.extra.pts.shape[0]:
            self.forest = forest_of(tree_of(self.forest, self._merge))
        return self.forest.main

    @classmethod
    def build(cls, points, box, periodic, weights=None):
        """The index of the (n, 2) float64 points (already checked to lie in the box along
        non-periodic axes) for the box and its periodic axes; ``weights`` (n,) or None."""
        from .embedding import Embedding

        emb = Embedding.make(box, periodic)
        index = build_index(emb.to_internal(points), weights=weights)
        return cls(emb, index, cls.fingerprint_of(points, weights))

    @property
    def fingerprint(self):
        """``fingerprint_of`` the indexed points (a continued run's, found when first
        asked: its caller does not wait for the sums of every point)."""
        if callable(self._fingerprint):
            self._fingerprint = self._fingerprint()
        return self._fingerprint

    @staticmethod
    def fingerprint_of(points, weights=None):
        """What tells the indexed points (and weights) from others: their number and column
        sums (per column: numpy's axis-0 sum of an (n, 2) array is 30 times slower)."""
        w = None if weights is None else float(np.sum(weights))
        return (len(points), float(points[:, 0].sum()), float(points[:, 1].sum()), w)

    def indexes(self, points, weights=None):
        """Whether ``points`` (n, 2) float64 with ``weights`` are the ones indexed (by
        fingerprint)."""
        return self.fingerprint == self.fingerprint_of(points, weights)

    def weight_at(self, x):
        """The number of indexed points (weighted: their weight) at exactly each of the
        indexed points x (q, 2), input units: one descent of the tree per point."""
        q = self.embedding.to_internal(x)
        qx, qy = q[:, 0].copy(), q[:, 1].copy()
        out = np.empty(len(q))
        in_chunks(lambda a, b: weights_at(self.index, qx, qy, out, a, b), len(q))
        return out

    def kth(self, x, k, r_in=None, r_out=None, low=None, high=None, workers=None):
        """Exact d_{P,k} at the points x (q, 2) in input units (weighted P: the least radius
        whose closed disk holds weight >= k). r_in, r_out: a window per point that should
        hold the answer (input units): a good one makes the search cheap (it collects the
        points between the radii), a bad one only costs retries; default: the distance at
        which a uniform density would hold k points, halved and doubled. low, high: bounds
        known to hold (default 0 and infinity)."""
        emb = self.embedding
        q = emb.to_query(x)
        m = len(q)
        k = float(k)

        def internal(r, default):
            if r is None:
                return np.full(m, default)
            return np.broadcast_to(np.asarray(r, np.float64) * emb.scale, (m,)).copy()

        lx, ly = emb.period_internal
        guess = np.sqrt(k * lx * ly / (np.pi * max(self.total, 1e-300)))
        r_in = internal(r_in, 0.5 * guess)
        r_out = internal(r_out, 2.0 * guess)
        low = internal(low, 0.0)
        high = internal(high, np.inf)
        # room for the points of a window: about k of them (k / the mean weight if weighted)
        per_point = self.total / max(self.n, 1) if self.weighted else 1.0
        cap = int(min(self.n, 4.0 * k / max(per_point, 1e-300) + 1024)) + 1
        out = np.empty(m)
        qx, qy = q[:, 0].copy(), q[:, 1].copy()
        px, py = (bool(p) for p in emb.periodic)

        def chunk(a, b):
            args = (qx, qy, k, r_in, r_out, low, high, lx, ly, px, py, cap, out, a, b)
            return kth_distances(self.index, *args)

        in_chunks(chunk, m, workers, most=kth_range(k))
        lost = np.flatnonzero(np.isnan(out))
        if len(lost):  # more ties than a window holds: by brute force (rare)
            out[lost] = self._brute_kth(q[lost], k)
        return out / emb.scale

    def _brute_kth(self, q, k):
        pts = self.index.pts
        lx, ly = self.embedding.period_internal
        res = np.empty(len(q))
        for i, (x, y) in enumerate(q):
            ex = np.abs(pts[:, 0] - x)
            ey = np.abs(pts[:, 1] - y)
            if self.embedding.periodic[0]:
                ex = np.minimum(ex, lx - ex)
            if self.embedding.periodic[1]:
                ey = np.minimum(ey, ly - ey)
            d2 = ex * ex + ey * ey
            order = np.argsort(d2, kind="stable")
            w = pts[order, 2] if self.weighted else np.ones(len(order))
            res[i] = np.sqrt(d2[order[np.searchsorted(np.cumsum(w), k)]])
        return res
