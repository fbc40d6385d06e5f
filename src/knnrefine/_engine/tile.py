"""A run as one tile of a tiled run, the same in both dimensions: ``TileRun``, which
``driver.Refinement`` (the plane) and ``driver3.Refinement3`` (space) share. The rule a tile
moves by is ``region.py``'s (``region3.py`` in space); a run supplies the per-dimension
kernels through four hooks."""

import numpy as np

from ..errors import EngineError
from .index import forest_of
from .state import C_NT, ERRORS, GOOD


class TileRun:
    """Seeding a run with the vertices of earlier rounds, and reading what it added. Hooks:
    ``_order(x)`` (a space-filling order of points), ``_insert_given(pts, ids, done)`` (the
    kernel inserting pts[done:], returning where it stopped or a negative code),
    ``_lost`` (that kernel's code for a lost walk), ``_mark_settled(stamps, regions)``
    ((balls, cells) marked GOOD), ``requeue()``, ``_grow()``, and ``positions`` (the vertex
    array) and ``_tau2`` (tau^2 as the kernels compare it)."""

    @property
    def index(self):
        """The counting index over P the kernels take: a ``state.PointForest``."""
        return self._index

    @index.setter
    def index(self, index):
        """A PointTree (``build_index``, ``build_index3``), a PointForest
        (``index.grow_forest``), or None (the run let go of it)."""
        self._index = None if index is None else forest_of(index)

    def seed(self, x, kinds, stamps, regions):
        """Insert the vertices x (with their kinds and the rounds that made them) into the
        initial mesh, mark what earlier rounds settled (regions (Q, T, 2 d)) and queue the
        rest. Returns (the number of vertices, the elements not settled: circumballs and
        cells)."""
        ids = self.insert(x, kinds)
        nv = self.vertices
        all_stamps = np.zeros(nv, np.int32)
        all_stamps[ids] = stamps
        balls, cells = self._mark_settled(all_stamps, np.ascontiguousarray(regions, float))
        self.requeue()
        return nv, int(self.cnt[C_NT]) - balls + nv - cells

    def insert(self, x, kinds):
        """Insert the vertices x (other tiles' moves: none of them a vertex here already),
        in a space-filling order, with their kinds; returns each one's vertex id. What the
        insertions made is untested and not queued (``requeue``)."""
        order = self._order(np.ascontiguousarray(x))
        pts = np.ascontiguousarray(x[order])
        ids = np.full(len(pts), -1, np.int64)
        done = 0
        while done < len(pts):
            done = self._insert_given(pts, ids, done)
            if done < 0:
                what = "a walk got lost" if done == self._lost else ERRORS.get(done, str(done))
                raise EngineError(f"triangulating a tile's vertices failed: {what}")
            if done < len(pts):
                self._grow()
        placed = ids >= 0
        if not placed.all():  # each was inserted at the centre of a ball empty of the others
            raise EngineError(
                f"{int((~placed).sum())} of the tiles' vertices coincide with others: tiles "
                "moved outside their strips (a broken plan)"
            )
        self.book.kinds[ids] = kinds[order]
        out = np.empty(len(pts), np.int64)
        out[order] = ids
        return out

    def new_vertices(self, start):
        """(positions, kinds) of the vertices from ``start`` on: copies."""
        nv = self.vertices
        return self.positions[start:nv].copy(), self.book.kinds[start:nv].copy()

    def unsettled(self):
        """Elements not known to be settled: circumballs and cells not GOOD, and cells whose
        aspect exceeds tau."""
        nt, nv = int(self.cnt[C_NT]), self.vertices
        aspect = 4.0 * self.mesh.outradius2[:nv] > self._tau2 * self.mesh.nearest2[:nv]
        return int(
            (self.book.ball_state[:nt] != GOOD).sum()
            + (self.book.cell_state[:nv] != GOOD).sum()
            + aspect.sum()
        )
