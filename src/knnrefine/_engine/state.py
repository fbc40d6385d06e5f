"""The engine's state, by name: what every kernel reads and writes (docs/data-structure.md).

Four structures of flat arrays, each a namedtuple that the kernels receive as one argument
and read by field (``mesh.neighbours[t, i]``):

* ``TorusMesh``: the triangulation of the flat torus, what ``triangulation.py`` owns;
* ``Bookkeeping``: the refinement's marks on it (``refine.py``): which circumballs and cells
  were tested, how each vertex arrived, the queue flags;
* ``Scratch``: the insertion's working space (cavity, boundary, per-triangle stamps);
* ``Queues``: three bucket queues (``queue.py``), each a ``Queue``.

Counters (int64) and parameters (float64) live in two small arrays whose slots are named
here, in one table. Arrays grow along the vertex axis or the triangle axis, by a quarter at a
time from a first size taken from the size estimate; ``VERTEX_FIELDS`` and
``TRIANGLE_FIELDS`` say which field grows along which.
"""

import mmap
from collections import namedtuple

import numpy as np

TorusMesh = namedtuple(
    "TorusMesh",
    [
        "corners",  # (T, 3) int32: the vertex at each corner, counter-clockwise
        "neighbours",  # (T, 3) int32: the triangle across the edge opposite each corner
        "offsets",  # (T, 3, 2) int8: each corner's periodic offset (minimum 0 per axis)
        "radius2",  # (T,) float64: squared circumradius
        "xy",  # (V, 2) float64: vertex positions on the grid, in [0, lx) x [0, ly)
        "star",  # (V,) int32: one triangle at each vertex (where a walk round it starts)
        "outradius2",  # (V,) float64: R(v)^2, the largest squared circumradius around v
        "nearest2",  # (V,) float64: d_{M,2}(v)^2, the squared distance to the nearest vertex
    ],
)

Bookkeeping = namedtuple(
    "Bookkeeping",
    [
        "ball_state",  # (T,) int8: UNTESTED, GOOD, FLOOR or FAILED (its closed circumball)
        "kinds",  # (V,) int8: how each vertex arrived (INITIAL ... CLEAN)
        "cell_state",  # (V,) int8: UNTESTED, GOOD, FLOOR or FAILED (its closed Voronoi cell)
        "flags",  # (V,) int8: IN_CELL_QUEUE, IN_CLEAN_QUEUE, CLEAN_BELOW_FLOOR, CLEAN_FAILED
    ],
)

Scratch = namedtuple(
    "Scratch",
    [
        "mark",  # (T,) int32: insertion stamp of the triangles already in the cavity
        "cavity",  # (C,) int32: the cavity's triangles, then the new triangles' slots
        "cavity_shift",  # (C, 2) int64: each cavity triangle's shift relative to the seed
        "boundary",  # (C, 4) int32: boundary edges: head, tail, outer triangle, its index
        "boundary_offsets",  # (C, 4) int64: the boundary edge's corner offsets
        "link",  # (L, 2) int64: the fan's boundary edges by first vertex (a hash table)
    ],
)

# -- three dimensions (``triangulation3.py``) ------------------------------------------------
TorusMesh3 = namedtuple(
    "TorusMesh3",
    [
        "corners",  # (T, 4) int32: the vertex at each corner, positively oriented (orient3d > 0)
        "neighbours",  # (T, 4) int32: the tetrahedron across the face opposite each corner
        "offsets",  # (T,) uint32: each corner's periodic offset per axis (minimum 0 per
        # axis), two bits each (``triangulation3.offset3``)
        "radius2",  # (T,) float64: squared circumradius
        "xyz",  # (V, 3) float64: vertex positions on the grid, in [0, lx) x [0, ly) x [0, lz)
        "star",  # (V,) int32: one tetrahedron at each vertex (where a walk round it starts)
        "outradius2",  # (V,) float64: R(v)^2, the largest squared circumradius around v
        "nearest2",  # (V,) float64: d_{M,2}(v)^2, the squared distance to the nearest vertex
    ],
)

Scratch3 = namedtuple(
    "Scratch3",
    [
        "mark",  # (T,) int32: stamp of the tetrahedra already met (cavity, star walks;
        # -1: a free slot); the driver restarts the stamps past driver3.STAMP_LIMIT
        "cavity",  # (C,) int32: the cavity's tetrahedra, then the new ones' slots
        "cavity_shift",  # (C, 3) int64: each cavity tetrahedron's shift relative to the seed
        "boundary",  # (B, 3) int64: boundary faces: outer tetrahedron, its index, face index
        "face_corners",  # (B, 4) int64: the cavity tetrahedron behind each boundary face
        "face_offsets",  # (B, 4, 3) int64: its corners' offsets in the seed's frame
        "link",  # (L, 3) int64: the new tetrahedra's inner faces by edge (a hash table)
        "walk",  # (W,) int32: the stack of a walk round a vertex
        "points",  # (5, 3) float64: the corners handed to a predicate
        "shift",  # (3,) int64: the new vertex's offset in the seed's frame
        "walk_point",  # (3,) float64: a point to insert (a circumcentre)
        "moved",  # (C + 1, 2) int64: row 0: the count; then (from, to) of each tetrahedron
        # moved by the last insertion, in order
        "no_h",  # (0, 3) float64, "no_ids" (0,) int64: a star walk that collects no
        "no_ids",  # neighbours (``triangulation3.walk_star3``)
    ],
)

# -- the sphere (``triangulation_sphere.py``) -------------------------------------------------
SphereMesh = namedtuple(
    "SphereMesh",
    [
        "corners",  # (T, 3) int32: the vertex at each corner, counter-clockwise seen from outside
        "neighbours",  # (T, 3) int32: the triangle across the edge opposite each corner
        "chord2",  # (T,) float64: the circumcap's squared chord radius |centre - corner|^2
        # (its centre is computed when asked: ``triangulation_sphere.circumcap_centre``)
        "gen",  # (T,) int32: how often the slot was filled (a queue entry's aux: stale if not)
        "xyz",  # (V, 3) float64: vertex unit vectors
        "star",  # (V,) int32: one triangle at each vertex (where a walk round it starts)
    ],
)

SphereScratch = namedtuple(
    "SphereScratch",
    [
        "mark",  # (T,) int32: insertion stamp of the triangles already met
        "vmark",  # (V,) int32: insertion stamp of the vertices on the cavity's boundary
        # (the driver restarts the stamps past STAMP_LIMIT_SPHERE)
        "vnext",  # (V,) int32: the boundary edge that starts at each such vertex
        "cavity",  # (C,) int32: the cavity's triangles, then the new triangles' slots
        "horizon",  # (C, 3) int32: boundary edges (first vertex, second, outer triangle)
        "points",  # (4, 3) float64: the corners handed to a predicate
        "point",  # (3,) float64: a point to insert (a circumcap's centre)
        "ids",  # (D,) int64: a vertex's neighbours (a star walk)
        "h",  # (D, 3) float64: their offsets from the vertex
        "hc",  # (D,) float64: the bisectors' offsets (a cell count)
        "stack",  # (S,) int64: a tree walk's stack
    ],
)

# the scratch of a 3-D cell count: a vertex's neighbours (relative positions, indices, the
# half-spaces' offsets) and the tree walk's stack
Probe3 = namedtuple("Probe3", ["h", "ids", "hc", "stack"])

Queue = namedtuple("Queue", ["head", "ident", "aux", "next", "scalars"])
Queues = namedtuple("Queues", ["balls", "cells", "cleans"])

# the scratch of a vertex-star walk and of a counting query (its stack, a leaf's mask)
Probe = namedtuple("Probe", ["hx", "hy", "hc", "stack", "mask"])

VERTEX_FIELDS = (
    ("mesh", "xy"),
    ("mesh", "star"),
    ("mesh", "outradius2"),
    ("mesh", "nearest2"),
    ("book", "kinds"),
    ("book", "cell_state"),
    ("book", "flags"),
)
TRIANGLE_FIELDS = (
    ("mesh", "corners"),
    ("mesh", "neighbours"),
    ("mesh", "offsets"),
    ("mesh", "radius2"),
    ("book", "ball_state"),
    ("scratch", "mark"),
)

# -- counters (int64 array ``cnt``) -----------------------------------------------------------
C_NV = 0  # vertices in use
C_NT = 1  # triangles in use (always 2 * C_NV on the torus)
C_STAMP = 2  # insertions so far: stamps the cavity marks
C_LAST_NB = 3  # boundary edges of the last cavity (= its new triangles)
C_SWEEP_MIN = 4  # cells newly queued that make a sweep worthwhile (refine.sweep_cells)
C_BALLS_SWEPT = 5  # in space: 1 + the circumball class swept last (refine3.sweep_balls3)
C_SWEEP_CELLS = 6  # in space: the sweep asked for is the cells' (refine3.sweep_cells3)
C_MAX_VERTICES = 9
C_DISK_TESTS = 26  # circumball counts made
C_CELL_TESTS = 27  # cell counts made
C_FAILED = 28  # insertions refused (the point rounds onto a vertex)
C_ERROR = 29  # the code of a broken invariant (see ERRORS)
C_CELLS_QUEUED = 30  # cells ever queued
C_CELLS_SWEPT = 31  # C_CELLS_QUEUED at the last sweep (refine.sweep_cells)
C_DEFERRED = 32  # elements popped outside the region (``_engine/region.py``): left for another tile
N_COUNTERS = 33

# -- parameters (float64 array ``prm``) -------------------------------------------------------
P_LX = 0  # the torus' periods, internal units
P_LY = 1
P_TAU2 = 2  # tau^2, lowered by a relative 1e-12 (conservative aspect test)
P_FLOOR2 = 3  # the Break floor squared: max(min_size, clean floor)^2
P_CLEAN_FLOOR2 = 4  # the Clean floor squared: 2^14 grid steps
P_INFLATE = 5  # 1 + 1e-9: the counting regions' inflation
P_GRID = 6  # the grid step q every vertex is snapped to
P_K = 7  # the k of d_{P,k}: a count, or a weight for weighted points
# a tile's region (``_engine/region.py``): moves only for elements inside the rectangle
# [x0, x0 + w] x [y0, y0 + h] of the torus (wrapping); w = NO_REGION: the whole torus. A
# region of width 0 holds no element (it never means the whole torus: two tiles would then
# both move everywhere)
P_REGION_X0 = 8
P_REGION_Y0 = 9
P_REGION_W = 10
P_REGION_H = 11
N_PARAMS = 12
NO_REGION = -1.0  # P_REGION_W of a run that is not a tile

# -- insertion results and broken invariants ---------------------------------------------------
INSERT_NOT_IN_SEED = -1  # the point is not strictly inside the seed's circumcircle
INSERT_CAVITY_OVERFLOW = -2
INSERT_TOPOLOGY = -3
STAR_OVERFLOW = -100

ERRORS = {
    INSERT_CAVITY_OVERFLOW: "a cavity grew beyond its capacity of triangles (MAX_CAVITY)",
    INSERT_TOPOLOGY: "a cavity was not a topological disk (the triangulation is broken)",
    STAR_OVERFLOW: "a vertex has more neighbours than MAX_DEGREE (a broken well-spacing)",
}


def grown(array, size):
    """``array`` copied into a zeroed array of ``size`` rows."""
    out = np.zeros((size,) + array.shape[1:], array.dtype)
    out[: array.shape[0]] = array
    return out


# private anonymous mappings: POSIX (Windows' mmap module has no flags: plain arrays there)
_ANONYMOUS = getattr(mmap, "MAP_ANONYMOUS", getattr(mmap, "MAP_ANON", None))
_PRIVATE = None if _ANONYMOUS is None else mmap.MAP_PRIVATE | _ANONYMOUS


def mapped(shape, dtype):
    """A zeroed array of ``shape`` in its own anonymous private memory mapping (``mmap``):
    its pages cost memory only once written, it can grow in place (``grow``), and freeing it
    returns its memory to the system at once, whatever the C library's heap holds. Where the
    system has no such mappings, a plain ``np.zeros``."""
    dtype = np.dtype(dtype)
    if _PRIVATE is None:
        return np.zeros(shape, dtype)
    count = int(np.prod(shape))
    mm = mmap.mmap(-1, max(count * dtype.itemsize, 1), flags=_PRIVATE)
    flat = np.frombuffer(mm, dtype, count)
    return flat.reshape(shape) if len(shape) > 1 else flat


def _mapping(array):
    """The mapping that ``array`` (made by ``mapped``) spans whole, or None."""
    base = array.base
    if isinstance(base, np.ndarray) and base.ndim == 1 and base.size == array.size:
        base = base.base
    if isinstance(base, memoryview):  # np.frombuffer's
        base = base.obj
    return base if isinstance(base, mmap.mmap) and array.flags.c_contiguous else None


def _remapped(owner, path, size):
    """The array at ``path`` of ``owner`` grown to ``size`` rows inside its own mapping:
    the system moves its pages (``mremap``) instead of copying them, and the new rows are
    zero pages, untouched until written. The owner's reference is dropped first (a mapping
    with live views cannot move); if a view is held elsewhere, or the system cannot move a
    mapping (no ``mremap``: macOS), the rows are copied into a new mapping instead. Arrays
    not made by ``mapped`` are copied into one."""
    array = _get(owner, path)
    mm = _mapping(array)
    rows, tail, dtype = array.shape[0], array.shape[1:], array.dtype
    if mm is None:
        out = mapped((size,) + tail, dtype)
        out[:rows] = array
        return out
    _set(owner, path, None)
    del array
    count = size * int(np.prod(tail, dtype=np.int64))
    try:
        _resize(mm, count * dtype.itemsize)
    except (BufferError, OSError, SystemError):  # a view held elsewhere; no mremap
        old = np.frombuffer(mm, dtype, rows * (count // size)).reshape((rows,) + tail)
        out = mapped((size,) + tail, dtype)
        out[:rows] = old
        return out
    flat = np.frombuffer(mm, dtype, count)
    return flat.reshape((size,) + tail) if tail else flat


def _resize(mm, nbytes):
    mm.resize(nbytes)


def _get(owner, path):
    for name in path:
        owner = getattr(owner, name)
    return owner


def _set(owner, path, value):
    """Set the field at ``path`` of ``owner`` (an object, then namedtuples) to ``value``."""
    if len(path) == 1:
        setattr(owner, path[0], value)
        return
    inner = _get(owner, path[:-1])
    _set(owner, path[:-1], inner._replace(**{path[-1]: value}))


def grow(owner, fields, size, in_place=False):
    """Grow the arrays at ``fields`` (paths: an attribute of ``owner``, then fields of the
    namedtuples inside, such as ("mesh", "corners") or ("queues", "balls", "ident")) to
    ``size`` rows, one at a time: each old array is freed before the next is copied, so
    growing costs one array's worth of extra memory, not the structures' (``in_place``:
    none, the arrays live in their own mappings and grow there: ``_remapped``)."""
    for path in fields:
        if in_place:
            new = _remapped(owner, path, size)
        else:
            new = grown(_get(owner, path), size)
        _set(owner, path, new)


# vertex kinds (insertion moves)
INITIAL = 0
BREAK_BALL = 1  # Break: circumcenter of a triangle whose circumball holds >= k points
BREAK_CELL = 2  # Break: far corner of a Voronoi cell holding >= k points
CLEAN = 3  # Clean: far corner of a cell with aspect > tau
KIND_NAMES = ("initial", "break_circumball", "break_cell", "clean")

# states of a triangle's circumball (book.ball_state) and of a vertex's cell (book.cell_state)
UNTESTED = 0
GOOD = 1  # holds < k points: settled
FLOOR = 2  # holds >= k points but is smaller than min_size: left alone
FAILED = 3  # its split point landed on an existing vertex (grid resolution)
DEFERRED = 4  # outside the tile's region (_engine/region.py): left to another tile or pass

# book.flags bits
IN_CELL_QUEUE = 1
IN_CLEAN_QUEUE = 2
CLEAN_BELOW_FLOOR = 4  # aspect > tau but its cell is below the Clean floor
CLEAN_FAILED = 8
TOUCHED = 16  # in space, during one insertion: looked at already (refine3.refine_steps3)

# refine_steps results
STATUS_DONE = 0
STATUS_STEPS = 1  # max_steps insertions made; call again
STATUS_GROW = 2  # an array is nearly full; grow it and call again
STATUS_MAX_VERTICES = 3
STATUS_ERROR = 4  # a broken invariant; cnt[C_ERROR] holds the code (state.ERRORS)
STATUS_SWEEP = 5  # many cells (in space: circumballs) wait to be counted: sweep, call again


# the counting index over P (``index.py``, ``index3.py``): a static kd-tree whose nodes own
# contiguous ranges of the permuted points
PointTree = namedtuple(
    "PointTree",
    [
        "pts",  # (n, d) float64 permuted (weighted, plane: (n, 3), the weight last)
        "box",  # (nodes, 2 d) float64: each node's tight box, lower corner then upper
        "node",  # (nodes, 4) int64: the NODE_* columns
        "split",  # (nodes,) float64: the split coordinate
        "weight",  # (nodes,) float64: each node's total weight; (0,) unweighted
    ],
)
# the plane's counting index in a run: two PointTrees counted as one, the tree the run began
# with and a small one over the points added since (a continued run; empty otherwise), so
# that adding points copies neither the large tree nor its points (``index.grow_forest``)
PointForest = namedtuple("PointForest", ["main", "extra"])
NODE_LO = 0  # the node's first point
NODE_HI = 1  # one past its last point
NODE_CHILD = 2  # its first child (the second follows it); -1 at a leaf
NODE_AXIS = 3  # the split axis
