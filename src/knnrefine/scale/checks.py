"""certify strip by strip: every question about the points (counts in disks and cells,
d_{P,k}) asked where the points are, in worker processes (``LocalStore``) or on a Dask
cluster (``distributed.DaskStore``), never gathering them; the mesh's own checks run in this
process (``certify.steps.run_checks``). The same checks and the same verdict as one process.
"""

import time

import numpy as np
from scipy.spatial import cKDTree

from .._domains import part
from .._metric import TorusFrame, cell_tally, held_in_balls, weighted_kth
from ..certify import steps
from ..certify.certificate import Certificate
from ..certify.common import check_source, checked_points
from .tiled import SAMPLE_MIN, LocalStore, regions_axis, split_strips, strip_owner, strips


def certify_local(mesh, points, weights, strips, executor, *, samples, n_random,
                  max_point_probes, random_state) -> Certificate:  # fmt: skip
    """``knnrefine.certify`` with an executor: the points' questions asked strip by strip,
    ``strips`` strips, each a task of ``executor`` (processes or machines).

    Parameters
    ----------
    mesh, points, weights, samples, n_random, max_point_probes, random_state
        As for ``knnrefine.certify``.
    strips : int
        Strips of the points, >= 2 (certify's ``workers``).
    executor : concurrent.futures.Executor
        Runs the strips (its ``map``).

    Returns
    -------
    Certificate
    """
    t0 = time.perf_counter()
    pts, weights = checked_points(mesh, points, weights)
    store = LocalStore(pts, weights, strips, executor)
    try:
        return check_store(mesh, store, strips, -1, samples=samples, n_random=n_random,
                           max_point_probes=max_point_probes, random_state=random_state,
                           t0=t0)  # fmt: skip
    finally:
        store.close()


def check_store(mesh, store, tiles, workers, *, samples, n_random, max_point_probes,
                random_state, t0):  # fmt: skip
    """certify's steps (``certify.steps.run_checks``) in either dimension with the points'
    questions asked of ``store`` (``workers``: this process' threads)."""
    geometry = part(mesh.domain, "certify").Geometry(mesh, workers)
    tiled = TiledSpacePoints if mesh.domain == "space" else TiledTorusPoints
    points = tiled(mesh, store, tiles, workers)
    return steps.run_checks(mesh, geometry, points, samples=samples, n_random=n_random,
                            max_point_probes=max_point_probes, random_state=random_state,
                            t0=t0)  # fmt: skip


def certify_store(mesh, store, tiles, *, samples=100_000, n_random=20_000,
                  max_point_probes=100_000, random_state=0, workers=-1) -> Certificate:  # fmt: skip
    """``certify`` of a mesh against the points of ``store`` (``scale/tiled.py``:
    ``LocalStore`` or ``distributed.DaskStore``), which never come to this process: counts
    and d_{P,k} are asked strip by strip (``tiles`` strips of equal share), each strip where
    its points are. The caller has checked that the points lie in the mesh's box."""
    t0 = time.perf_counter()
    check_source(mesh.stats, store.n, store.weight)
    return check_store(mesh, store, int(tiles), workers, samples=samples, n_random=n_random,
                       max_point_probes=max_point_probes, random_state=random_state,
                       t0=t0)  # fmt: skip


class StripQuestions:
    """Questions about points held in a store (``LocalStore`` or ``distributed.DaskStore``),
    asked strip by strip where they are (``store.map_strips``, ``certify_strip``), in the
    frame of the torus of ``period`` with origin ``origin``: ``tiles`` strips of equal share
    of the points. Strip j owns the points of [cut j, cut j + 1) along the strip axis and
    sees the others within a pad: counts in disks add up the owners' (each point is owned
    once, a disk goes to every strip it meets); d_{P,k} at x is decided by x's strip when
    its k-th point lies within the pad, and asked again with four times the pad otherwise
    (the whole torus at last)."""

    def __init__(self, store, origin, period, k, tiles):
        self.store, self.k = store, k
        self.period = np.asarray(period, float)
        self.input_frame = TorusFrame(np.asarray(origin, float), self.period)
        sx = store.sample(min(1.0, SAMPLE_MIN / store.n))[0]
        self.regions = strips(self.input_frame(sx), self.period, int(tiles))[0]
        self.axis_period = float(self.period[regions_axis(self.regions, self.period)])
        self.passes = 0

    def ask(self, jobs, pad):
        """One job per strip (a dict: ``certify_strip``), the strips widened by ``pad``."""
        common = {"regions": self.regions, "period": tuple(self.period), "k": self.k,
                  "pad": pad, "complete": 2.0 * pad >= self.axis_period}  # fmt: skip
        jobs = [{**common, "j": j, **job} for j, job in enumerate(jobs)]
        self.passes += 1
        return self.store.map_strips(certify_strip, self.input_frame, self.regions, pad, jobs)

    def route(self, x, pad):
        """The rows of x (torus frame) within ``pad`` of each strip (one pad per row)."""
        rows, bounds = split_strips(x, self.regions, pad, self.period)
        return [rows[bounds[j] : bounds[j + 1]] for j in range(len(self.regions))]

    def d_pk(self, x, pad, boxsize=None):
        """Exact d_{P,k} at x (torus frame); ``pad`` a first guess of its reach (it only sets
        how often a question is asked again). ``boxsize``: a metric other than the torus',
        the kd-tree's periods with 0 on straight axes (the box's own, ``TiledSpacePoints``)."""
        out = np.full(len(x), np.nan)
        if len(x) == 0:
            return out
        owner = strip_owner(x, self.regions, self.period)
        todo = np.arange(len(x))
        pad = max(float(pad), 1e-12 * self.axis_period)
        while len(todo):
            mine = [todo[owner[todo] == j] for j in range(len(self.regions))]
            got = self.ask([{"dpk": x[r], "boxsize": boxsize} for r in mine], pad)
            for r, g in zip(mine, got, strict=True):
                out[r] = g["dpk"]
            todo = todo[np.isnan(out[todo])]
            pad *= 4.0
        return out

    def cell_counts(self, cells, stop=np.inf):
        """What the closed Voronoi cell of each of the vertices (torus frame, R(v) =
        ``outradii``) holds: each point counts for every vertex as near as its nearest, asked
        of the strip that owns it with the vertices within a pad, the pad widened until every
        point's nearest vertex lies within it (``stop`` is not needed: exact everywhere)."""
        vertices, outradii = cells.sites, cells.outradii
        m = len(vertices)
        out = np.zeros(m, float if self.store.weight is not None else np.int64)
        # Voronoi cell of v lies within R(v) of v: a first vertex pad from the outradii
        pad = max(float(np.quantile(outradii, 0.999)) * 1.01, 1e-12 * self.axis_period)
        before = -1.0
        while True:
            mine = self.route(vertices, pad)
            complete = 2.0 * pad >= self.axis_period
            jobs = [{"cells": (vertices[r], r, pad, before, complete)} for r in mine]
            got = self.ask(jobs, 0.0)
            for g in got:
                np.add.at(out, g["cell_ids"], g["cell_counts"])
            if sum(g["undecided"] for g in got) == 0:
                return out
            before, pad = pad, 4.0 * pad

    def held(self, centres, radii, stop=np.inf, boxsize=None):
        """What each closed ball (torus frame) holds: a count, or a weight (exact, whatever
        ``stop``). ``boxsize``: a metric other than the torus' (``d_pk``'s)."""
        radii = np.broadcast_to(np.asarray(radii, float), len(centres))
        out = np.zeros(len(centres), np.int64 if self.store.weight is None else float)
        if len(centres) == 0:
            return out
        mine = self.route(centres, radii * (1.0 + 1e-9) + 1e-12 * self.axis_period)
        got = self.ask([{"balls": (centres[r], radii[r]), "boxsize": boxsize} for r in mine],
                       0.0)  # fmt: skip
        for r, g in zip(mine, got, strict=True):
            out[r] += g["held"]
        return out


class TiledTorusPoints:
    """The plane's ``certify.Points`` for points held in a store: every question
    about them is a ``StripQuestions``."""

    def __init__(self, mesh, store, tiles, workers):
        torus = mesh.torus
        self.origin = np.asarray(torus.origin, float)
        self.period = np.asarray(torus.period, float)
        self.k, self.workers, self.store = mesh.k, workers, store
        self.input_frame = TorusFrame(self.origin, self.period)
        self.n = store.n
        self.weighted = store.weight is not None
        self.total = float(store.n) if store.weight is None else float(store.weight)
        self.questions = StripQuestions(store, self.origin, self.period, self.k, tiles)
        self._vertex_tree = cKDTree(np.asarray(torus.vertices, float), boxsize=self.period)

    @property
    def passes(self):
        return self.questions.passes

    def d_pk(self, x):
        # a first pad from the mesh (a guess only: what the strips decide is exact)
        if len(x) == 0:
            return np.zeros(0)
        d_m2 = self._vertex_tree.query(x, k=2, workers=self.workers)[0][:, 1]
        return self.questions.d_pk(x, float(np.quantile(4.0 * d_m2, 0.99)))

    def held(self, centres, radii, stop=np.inf):
        return self.questions.held(centres, radii)

    def fewer(self, centres, radii, k, mostly=True):
        return self.questions.held(centres, radii) < k

    def cell_counts(self, cells, stop=np.inf):
        return self.questions.cell_counts(cells)

    def sample_points(self, count, rng):
        sx = self.store.sample(min(1.0, count / self.n))[0]
        return self.input_frame(sx)


class TiledSpacePoints:
    """Space's ``certify.Points`` for points held in a store: every question about them a
    ``StripQuestions`` (slabs). d_{P,k} is asked in the box's own metric, as in one process:
    each slab's kd-tree is straight along the non-periodic axes (the box lies unwrapped in
    the torus frame there, and a point within a pad in the box's metric is within it on the
    torus, so a slab widened by the pad holds every point it needs)."""

    def __init__(self, mesh, store, tiles, workers):
        torus = mesh.torus
        self.origin = np.asarray(torus.origin, float)
        self.period = np.asarray(torus.period, float)
        self.boxsize = tuple(np.where(mesh.periodic, self.period, 0.0))
        self.store, self.k, self.n, self.workers = store, mesh.k, store.n, workers
        self.weighted = store.weight is not None
        self.total = float(store.n) if store.weight is None else float(store.weight)
        self.input_frame = TorusFrame(self.origin, self.period)
        self.questions = StripQuestions(store, self.origin, self.period, self.k, tiles)
        self._vertex_tree = cKDTree(np.asarray(torus.vertices, float), boxsize=self.period)

    def held(self, centres, radii, stop=np.inf):
        return self.questions.held(centres, radii)

    def fewer(self, centres, radii, k, mostly=True):
        """In d_{P,k}'s metric, the box's own (``boxsize``), as ``d_pk``."""
        return self.questions.held(centres, radii, boxsize=self.boxsize) < k

    def cell_counts(self, cells, stop=np.inf):
        return self.questions.cell_counts(cells)

    def d_pk(self, x):
        # a first pad from the mesh (a guess only: what the slabs decide is exact)
        if len(x) == 0:
            return np.zeros(0)
        d_m2 = self._vertex_tree.query(x, k=2, workers=self.workers)[0][:, 1]
        return self.questions.d_pk(x, float(np.quantile(4.0 * d_m2, 0.99)), self.boxsize)

    def sample_points(self, count, rng):
        sx = self.store.sample(min(1.0, count / self.n))[0]
        return self.input_frame(sx)


def certify_strip(points, weights, job):
    """One strip's answers (``TiledTorusPoints``) from its points (the torus frame) within
    ``job["pad"]`` of it: d_{P,k} at its queries (NaN where the k-th point may lie beyond
    the pad), what its own points add to each disk, to each vertex's cell."""
    period = np.asarray(job["period"], float)
    out = {}
    if "dpk" in job:
        x, k = job["dpk"], job["k"]
        boxsize = period if job.get("boxsize") is None else job["boxsize"]
        tree = cKDTree(points, boxsize=None if not any(boxsize) else boxsize)
        if weights is not None:
            d = weighted_kth(tree, weights, x, k, 1)
        elif len(points) >= k and len(x):
            d = tree.query(x, k=[k])[0][:, 0]
        else:
            d = np.full(len(x), np.inf)
        if not job["complete"]:
            d[~(d <= job["pad"])] = np.nan  # the k-th point may lie beyond the pad
        out["dpk"] = d
    own = strip_owner(points, job["regions"], period) == job["j"]
    pts, w = points[own], None if weights is None else weights[own]
    if "balls" in job:
        centres, radii = job["balls"]
        boxsize = period if job.get("boxsize") is None else job["boxsize"]
        tree = cKDTree(pts, boxsize=None if not any(boxsize) else boxsize)
        out["held"] = held_in_balls(tree, w, centres, radii, 1)
    if "cells" in job:
        vxy, ids, pad, before, complete = job["cells"]
        if len(vxy) == 0 or len(pts) == 0:  # nothing to tally (a strip may hold no point)
            undecided = 0 if complete or len(vxy) else len(pts)
            out.update(cell_ids=ids[:0], cell_counts=np.zeros(0), undecided=undecided)
            return out
        dd, ii = cKDTree(vxy, boxsize=period).query(pts, k=min(3, len(vxy)))
        dd, ii = dd.reshape(len(pts), -1), ii.reshape(len(pts), -1)
        reach = dd[:, 0] * (1.0 + 1e-12)
        now = np.ones(len(pts), bool) if complete else reach <= pad
        new = now & (reach > before)  # decided now, not by an earlier pass
        tally = cell_tally(dd[new], ii[new], None if w is None else w[new], len(vxy))
        nz = np.flatnonzero(tally)
        out.update(cell_ids=ids[nz], cell_counts=tally[nz], undecided=int((~now).sum()))
    return out
