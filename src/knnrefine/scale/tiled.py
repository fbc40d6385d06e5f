"""A tiled run: its plan from a sample, its rounds of strips, and the last step (the rule
that makes the union of the tiles' moves a kNNRefine run is ``_engine/region.py``'s).

* The sample: the points whose key (``sample_keys``, a hash of their coordinates' bits) is
  below a fraction. It is the same set whatever the partitioning of the input (a NumPy
  array, Dask chunks, Parquet files), so a run's mesh does not depend on it.
* ``strips``: two sets of strips balanced by the sample's quantiles, borders interleaved.
* ``coarse_pass``: a refinement of the sample's coarsest part (a ball holding k of a subset
  holds k of all, so its moves are moves of the whole run).
* ``run_rounds``: rounds alternating between the two sets; every strip of a round is a
  tile (``run_tile``) that refines what lies inside it, given its points (or their index
  kept from an earlier round) and the vertices in it.
* ``settle``: all vertices triangulated, what the rounds settled marked so; what is left
  (elements crossing a border of both sets, or below the floor) needs the counts of all the
  points: the caller's final pass.

Where the points live is a store's business: ``LocalStore`` (this process; tiles on an
executor's processes, each with a copy of its strip) and
``knnrefine.scale.distributed.DaskStore`` (partitions and strip indexes on Dask workers).
A store has ``n``, ``weight`` (the total, or None), ``bounds`` (the points' extent: lows,
highs), ``sample``, ``prepare``, ``run_round``, ``points`` and ``close``. Tiles in threads
of this process keep their meshes and stitch them instead of rounds (``scale/shared.py``,
whose ``ThreadStore`` has the plan's methods and one index of all points).
"""

import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from .._domains import box as box_domain
from .._domains import part
from .._engine import ahead, size
from .._engine import state as S
from .._engine.driver import Refinement
from .._engine.driver3 import Refinement3
from .._engine.embedding import Embedding
from .._engine.geometry import FLOOR_BITS
from .._engine.index import build_index
from .._engine.index3 import build_index3
from .._engine.initial import reach_factor
from .._engine.interrupt import Interrupts
from .._engine.jit import kernel
from .._engine.region import in_rectangle
from .._engine.region3 import in_box3
from .._options import Progress, vertex_budget
from .._sampling import key_sample
from ..errors import EngineError, InputError
from ..mesh import Mesh

MAX_ROUNDS = 6  # rounds of strips before the final pass takes whatever is left
COARSE_SHARE = 8  # the coarse pass refines 1 / (COARSE_SHARE * tiles) of the points ...
COARSE_MAX = 2_000_000  # ... but no more than this many (it runs in the calling process)
SAMPLE_MIN = 100_000  # the plan's sample (strips, initial mesh, size) has at least this many
STRIP_SAMPLE = 200_000  # points of the sample the strips are cut by, about


MIN_GAP = 0.25  # the two sets' cuts, interleaved, are at least this share of an even spacing
# apart: a strip is never empty (an empty region would hold no element; a strip of width 0
# once meant "no region" and let two tiles move everywhere) and never too thin to work in
AXIS_PREFERENCE = 1.25  # strips run across the shorter period only if their heaviest strip
# is this many times lighter than the longer period's


def strip_axis(period):
    """The axis strips are cut along by default: across the longest period (the first of
    equal ones)."""
    return int(np.argmax(period))


def regions_axis(regions, period):
    """The axis a set of strips (regions (T, 2 d): corners, then widths) is cut along: the
    one they do not span."""
    d = len(period)
    cut = [a for a in range(d) if not np.all(regions[:, d + a] >= period[a])]
    return cut[0] if len(cut) == 1 else strip_axis(period)


def strips(xy, period, tiles):
    """Two sets of ``tiles`` strips (slabs in space) as regions (tiles, 2 d) of the torus
    (lower corner, then widths), each holding about 1 / tiles of the points xy (a sample
    will do): cut at the quantiles j / tiles and (j + 1/2) / tiles (``_cuts``), so that each
    border of one set lies inside a strip of the other, at least MIN_GAP of an even spacing
    from its borders. Across the longest period, unless many points share a coordinate there
    (points on a line or a plane) and another axis balances them better
    (``AXIS_PREFERENCE``)."""
    d = len(period)
    first = strip_axis(period)
    plans = []
    for axis in [first] + [a for a in range(d) if a != first]:
        cuts = _cuts(xy[:, axis], period[axis], tiles)
        plans.append((_heaviest(xy[:, axis], cuts, period[axis]), axis, cuts))
    load, axis, cuts = plans[0]
    best = min(plans[1:], key=lambda plan: plan[0])
    if tiles > 1 and best[0] * AXIS_PREFERENCE < load:
        load, axis, cuts = best
    sets = []
    for s in (0, 1):
        x0 = np.sort(_wrap(cuts[s::2], period[axis]))
        regions = np.zeros((tiles, 2 * d))
        regions[:, axis] = x0
        regions[:, d:] = period  # the whole of every other period
        regions[:, d + axis] = np.diff(np.append(x0, x0[0] + period[axis]))
        sets.append(regions)
    return sets


def _wrap(c, period):
    c = c - np.floor(c / period) * period
    return np.where(c >= period, c - period, c)


def _cuts(coord, period, tiles):
    """The 2 tiles cuts of both sets, interleaved (set 0 at even positions): the quantiles
    of ``coord`` (in [0, period)) at i / (2 tiles), moved as little as possible (least
    squares: an isotonic fit) so that consecutive ones, and the last and the first across
    the period, are at least MIN_GAP * period / (2 tiles) apart. Where the quantiles are
    that far apart already (no point mass), they are kept."""
    n_cuts = 2 * tiles
    levels = np.arange(n_cuts) / n_cuts
    if len(coord) == 0:
        return levels * period
    c = np.quantile(coord, levels)
    gap = MIN_GAP * period / n_cuts
    steps = np.arange(n_cuts) * gap
    c = _nondecreasing(c - steps) + steps
    room = c[0] + period - c[-1]  # across the period's end
    if room < gap:  # blend with even spacing from c[0] (its gaps are all period / n_cuts)
        even = c[0] + np.arange(n_cuts) * (period / n_cuts)
        share = (gap - room) / (period / n_cuts - room)
        c = (1.0 - share) * c + share * even
    return c


def _nondecreasing(z):
    """The least-squares nondecreasing fit of z (pool adjacent violators)."""
    values, sizes = [], []
    for v in z:
        values.append(float(v))
        sizes.append(1)
        while len(values) > 1 and values[-2] > values[-1]:
            w = sizes[-2] + sizes[-1]
            values[-2] = (values[-2] * sizes[-2] + values[-1] * sizes[-1]) / w
            sizes[-2] = w
            values.pop()
            sizes.pop()
    return np.repeat(values, sizes)


def _heaviest(coord, cuts, period):
    """The largest share of the points in one strip of either set of these cuts."""
    if len(coord) == 0:
        return 0.0
    c = np.sort(coord)
    worst = 0
    for s in (0, 1):
        x0 = np.sort(_wrap(cuts[s::2], period))
        at = np.searchsorted(c, x0, side="left")
        counts = np.diff(np.append(at, at[0] + len(c)))  # the last strip wraps round
        worst = max(worst, int(counts.max()))
    return worst / len(c)


def split_strips(xy, regions, pad, period):
    """The rows of xy (torus coordinates) in each strip of one set widened by ``pad`` on
    both sides (a number, or one per row): (rows, bounds), strip j's rows being
    rows[bounds[j]:bounds[j + 1]] in increasing order. A point within its pad of a border
    is in both strips (and in every strip between them; in all of them when its widened
    interval goes round the period). A counting sort: O(n), whatever the number of strips."""
    axis = regions_axis(regions, period)
    cuts = np.ascontiguousarray(regions[:, axis])
    pads = np.ascontiguousarray(np.atleast_1d(np.asarray(pad, np.float64)))
    return _strip_rows(np.ascontiguousarray(xy[:, axis]), cuts, pads, float(period[axis]))


def strip_owner(xy, regions, period):
    """The one strip of the set ``regions`` that owns each point (torus coordinates): the
    strip whose [cut, next cut) holds it, the rule ``split_strips`` cuts by."""
    axis = regions_axis(regions, period)
    out = np.empty(len(xy), np.int64)
    _owners(np.ascontiguousarray(xy[:, axis]), np.ascontiguousarray(regions[:, axis]),
            float(period[axis]), out)  # fmt: skip
    return out


@kernel(inline="always")
def _strip_at(x, cuts, period):
    """The strip whose [cut, next cut) holds x (wrapped into the period)."""
    x = x - np.floor(x / period) * period
    j = np.searchsorted(cuts, x, side="right") - 1
    return j % cuts.shape[0]


@kernel(entry=True)
def _owners(c, cuts, period, out):
    for i in range(c.shape[0]):
        out[i] = _strip_at(c[i], cuts, period)


@kernel(inline="always")
def _strip_span(c, pad, cuts, period):
    """(first strip, number of strips) met by [c - pad, c + pad], going up from the first."""
    tiles = cuts.shape[0]
    if 2.0 * pad >= period:
        return 0, tiles
    a = _strip_at(c - pad, cuts, period)
    span = (_strip_at(c + pad, cuts, period) - a) % tiles + 1
    if span == 1 and tiles > 1:  # inside strip a, or round the whole period back into it
        x = c - pad
        x = x - np.floor(x / period) * period
        into = x - cuts[a]
        reach = into - np.floor(into / period) * period + 2.0 * pad
        width = cuts[a + 1] - cuts[a] if a + 1 < tiles else cuts[0] + period - cuts[a]
        if reach >= period:
            return 0, tiles
        if reach >= width:  # at the next cut, up to rounding: that strip too
            return a, 2
    return a, span


@kernel(entry=True)
def _strip_rows(c, cuts, pads, period):
    tiles = cuts.shape[0]
    n = c.shape[0]
    lo = np.empty(n, np.int64)
    span = np.empty(n, np.int64)
    bounds = np.zeros(tiles + 1, np.int64)
    for i in range(n):
        a, sp = _strip_span(c[i], pads[i if pads.shape[0] > 1 else 0], cuts, period)
        lo[i] = a
        span[i] = sp
        for q in range(sp):
            bounds[(a + q) % tiles + 1] += 1
    for j in range(tiles):
        bounds[j + 1] += bounds[j]
    fill = bounds[:tiles].copy()
    rows = np.empty(bounds[tiles], np.int64)
    for i in range(n):
        for q in range(span[i]):
            j = (lo[i] + q) % tiles
            rows[fill[j]] = i
            fill[j] += 1
    return rows, bounds


def new_index(points, weights, workers=1):
    """The counting index of the engine of the points' dimension over (n, d) points in
    internal coordinates (kept by the index; ``workers`` threads building it in the
    plane)."""
    if points.shape[1] == 3:
        return build_index3(points, copy=False, weights=weights)
    return build_index(points, workers=workers, weights=weights)


def tile_index(points, weights):
    """A strip's counting index, built on one thread (one of many tiles at once)."""
    return new_index(points, weights, workers=1)


def new_run(index, common, expected=0):
    """A run of the engine of the plan's dimension (``Refinement`` in the plane,
    ``Refinement3`` in space) from the initial mesh, with the plan's parameters ``common``
    (``refine_store``); ``expected`` vertices size its arrays (the plane's)."""
    k, tau, floor, budget = common["k"], common["tau"], common["min_size"], common["max_vertices"]
    period = common["period"]
    if len(period) == 3:
        return Refinement3(index, period, k, tau, floor, budget, common["m0"], common["grid"])
    return Refinement(index, k, *period, tau, floor, budget, m0=common["m0"],
                      grid=common["grid"], expected_vertices=expected)  # fmt: skip


def in_region(x, region, pad, period):
    """Mask of the points x (torus coordinates) in ``region`` widened by ``pad``."""
    if len(period) == 3:
        return in_box3(np.ascontiguousarray(x), np.asarray(region, float), pad,
                       np.asarray(period, float))  # fmt: skip
    return in_rectangle(x, *region, pad, *period)


def run_tile(task, index=None):
    """One tile of one round, the one tile of its process at a time: its points' index
    (``index``, else built from task["points"]), the vertices in its region, the earlier
    rounds' regions; returns the vertices it inserted (xy, kinds) and its counters."""
    t0 = time.perf_counter()
    # one of many tiles at once: one engine thread (its index, its sweeps), said to the run
    # rather than through KNNREFINE_THREADS, which stayed set in the caller's process when
    # the executor ran tiles there (threads, Dask in-process): every later run on one core
    left = task["time_left"]  # seconds, not a clock reading: tiles may run on other machines
    deadline = None if left is None else t0 + left
    if index is None:
        index = tile_index(task["points"], task["weights"])
    run = new_run(index, task, task["expected"])
    run.threads = 1  # its sweeps: the other tiles hold the other cores
    start, _ = run.seed(task["xy"], task["kinds"], task["stamps"], task["history"])
    region = np.asarray(task["region"], float)
    if not np.all(region[len(region) // 2 :] > 0.0):
        raise EngineError(f"a tile's region {tuple(region)} is empty (a broken plan)")
    run.set_region(region)
    status = run.run(deadline=deadline)
    xy, kinds = run.new_vertices(start)
    return {
        "xy": xy,
        "kinds": kinds,
        "status": int(status),
        "seconds": time.perf_counter() - t0,
        "counters": run.counters(),
    }


def coarse_pass(points, weights, common):
    """The vertices (xy, kinds) of a refinement of ``points``, a subset of the input (the
    sample's coarsest part), in this process: the strips then start from a mesh whose
    elements are a few times the final ones (from the initial mesh's, a first round could
    split almost nothing inside a strip). Nothing when the subset holds fewer than 4 k."""
    d = len(common["period"])
    if len(points) < 4 * common["k"]:
        return np.zeros((0, d)), np.zeros(0, np.int8)
    run = new_run(new_index(np.array(points), weights, workers=None), common)
    start = run.vertices
    run.run()
    return run.new_vertices(start)


def run_rounds(store, sets, xy, kinds, common, expected, m0_count, progress, interrupts, deadline):
    """Rounds alternating between the two sets of strips, each strip a tile run by
    ``store.run_round``, until a round after the first inserts nothing (or MAX_ROUNDS).
    Returns (xy, kinds, stamps, history, report, stopped): all vertices beyond the initial
    mesh, the round that inserted each, every round's regions, a report per round, and the
    status of a tile stopped by the budget or the deadline (None if none was). Such a tile's
    strip is not settled, so nothing after it may treat it as settled: the run ends."""
    tiles = len(sets[0])
    stamps = np.zeros(len(xy), np.int32)
    history = np.zeros((0, tiles, sets[0].shape[1]))
    report = []
    period, grid = common["period"], common["grid"]
    stopped = None
    for r in range(1, MAX_ROUNDS + 1):
        s = (r - 1) % 2
        tasks = []
        for region in sets[s]:
            inside = in_region(xy, region, 4 * grid, period)
            tasks.append({
                **common, "xy": xy[inside], "kinds": kinds[inside], "stamps": stamps[inside],
                "history": history, "region": region,
                "expected": int(expected / tiles + inside.sum()),
            })  # fmt: skip
        t0 = time.perf_counter()
        for task in tasks:
            task["time_left"] = None if deadline is None else deadline - t0
        results = store.run_round(s, tasks)
        check_seams(sets[s], [res["xy"] for res in results], period)
        new = np.concatenate([res["xy"] for res in results])
        report.append({
            "round": r, "new_vertices": len(new), "seconds": time.perf_counter() - t0,
            "tiles": [res["seconds"] for res in results],
            "tile_vertices": [len(res["xy"]) for res in results],
        })  # fmt: skip
        xy = np.concatenate([xy, new])
        kinds = np.concatenate([kinds] + [res["kinds"] for res in results])
        stamps = np.concatenate([stamps, np.full(len(new), r, np.int32)])
        history = np.concatenate([history, sets[s][None]])
        if progress is not None:
            progress(m0_count + len(xy), 0)
        if interrupts is not None:
            interrupts.check()
        stopped = next((res["status"] for res in results if res["status"] != S.STATUS_DONE), None)
        if stopped is None and deadline is not None and time.perf_counter() >= deadline:
            stopped = S.STATUS_STEPS
        if stopped is not None or (r >= 2 and len(new) == 0):
            break
    return xy, kinds, stamps, history, report, stopped


def check_seams(regions, inserted, period):
    """The premise of a round (``_engine/region.py``), checked on what it returned: the strips
    of the set tile the period (positive widths, in order, adding up to it), and every
    vertex a tile inserted lies in its own strip (at the centre of a ball inside it, so at
    most within rounding of its border). EngineError otherwise: no mesh is made from the
    round."""
    d = len(period)
    axis = regions_axis(regions, period)
    length = period[axis]
    x0, w = regions[:, axis], regions[:, d + axis]
    if not (np.all(w > 0) and np.all(np.diff(x0) > 0)) or abs(w.sum() - length) > 1e-9 * length:
        raise EngineError(f"the strips {regions.tolist()} do not tile the period {length}")
    slack = 1e-9 * length
    for j, xy in enumerate(inserted):
        into = np.mod(xy[:, axis] - x0[j], length)
        into = np.where(into > length - slack, into - length, into)  # just below x0
        out = (into < -slack) | (into > w[j] + slack)
        if out.any():
            raise EngineError(
                f"tile {j} inserted {int(out.sum())} vertices outside its strip "
                f"[{x0[j]:.17g}, {x0[j] + w[j]:.17g}] (a broken tile rule)"
            )


def margin_bands(emb, lo, hi):
    """Regions (B, 2 d) of the torus that hold no input point: along each non-periodic
    axis, the band between the far side of the points' extent [lo, hi] (input units) and its
    near side one period on, a grid step off each. Counts inside them are 0 whatever the
    index, so the plan's sample index decides their elements exactly."""
    a = emb.to_internal(np.array([lo, hi], float))
    period = emb.period_internal
    d = len(period)
    bands = []
    for axis in range(d):
        if emb.periodic[axis]:
            continue
        width = period[axis] - (a[1, axis] - a[0, axis]) - 2 * emb.grid
        if width <= 0:
            continue
        region = [0.0] * d + list(period)
        region[axis] = a[1, axis] + emb.grid
        region[d + axis] = width
        bands.append(region)
    return np.array(bands).reshape(-1, 2 * d)


def settle_bands(run, bands, deadline=None):
    """Run the mesh in each point-free band as a tile (its region), the bands in turn until
    a pass inserts nothing. Returns (status, elements still not settled)."""
    for _ in range(MAX_ROUNDS):
        before = run.vertices
        for band in bands:
            run.set_region(band)
            run.requeue()  # those deferred by the last band too
            status = run.run(deadline=deadline)
            if status != S.STATUS_DONE:
                return status, None
        if run.vertices == before:
            break
    run.set_region(None)  # the whole torus again
    return S.STATUS_DONE, run.unsettled()


def settle(index, xy, kinds, stamps, history, common, bands=None, deadline=None):
    """The run of the whole torus holding the initial mesh and every vertex of the rounds,
    what the rounds settled marked so and the rest queued; then the point-free ``bands``
    (``margin_bands``) settled as tiles. Returns (run, status, elements not settled). With
    none, the mesh is final and ``index`` was asked only counts in the bands (the plan's
    sample index will do); otherwise the caller runs it on the index of all points."""
    final = new_run(index, common, expected=len(common["m0"][0]) + len(xy))
    _, unsettled = final.seed(xy, kinds, stamps, history)
    status = S.STATUS_DONE
    if unsettled and bands is not None and len(bands):
        status, unsettled = settle_bands(final, bands, deadline)
    return final, status, unsettled


def _context():
    """fork where the platform has it (no re-import of the caller's script, workers start in
    milliseconds; the engine's threads are all joined between kernel calls), else spawn
    (macOS, Windows: the caller's script then needs the ``if __name__ == "__main__":``
    guard, as for any multiprocessing)."""
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("fork" if "fork" in methods else "spawn")


class LocalStore:
    """The points in this process. Each round's tiles receive copies of their strip's points
    and run on ``executor`` (its ``map``; None: a pool of ``workers`` local processes, shut
    down by ``close``)."""

    def __init__(self, points, weights, workers, executor=None):
        self.pts, self.weights, self.workers = points, weights, workers
        self.n = len(points)
        self.weight = None if weights is None else float(weights.sum())
        d = points.shape[1]
        lo = [float(points[:, a].min()) for a in range(d)]
        self.bounds = (lo, [float(points[:, a].max()) for a in range(d)])  # the points' extent
        self.executor = executor
        self.own = None
        self.framed = None

    def sample(self, fraction):
        return key_sample(self.pts, fraction, self.weights)

    def prepare(self, emb, sets, pad):
        """The points in torus coordinates and each set's rows per strip."""
        self.internal = emb.to_internal(self.pts)
        period = emb.period_internal
        self.rows = [split_strips(self.internal, regions, pad, period) for regions in sets]

    def _map(self, fn, *args):
        if self.executor is None and self.own is None:
            self.own = ProcessPoolExecutor(self.workers, mp_context=_context())
        return list((self.executor or self.own).map(fn, *args))

    def run_round(self, s, tasks):
        rows, bounds = self.rows[s]
        for j, task in enumerate(tasks):
            mine = rows[bounds[j] : bounds[j + 1]]
            task["points"] = self.internal[mine]
            task["weights"] = None if self.weights is None else self.weights[mine]
        return self._map(run_tile, tasks)

    def map_strips(self, fn, frame, regions, pad, payloads):
        """fn(points, weights, payload) for each strip of ``regions`` widened by ``pad``,
        the points in coordinates ``frame(points)`` (a picklable function, its period
        ``frame.period``): a store's way to run checks strip by strip where the points are."""
        if self.framed is None or self.framed[0] is not frame:
            self.framed = (frame, frame(self.pts))
        xy = self.framed[1]
        rows, bounds = split_strips(xy, regions, pad, frame.period)
        mine = [rows[bounds[j] : bounds[j + 1]] for j in range(len(regions))]
        w = [None if self.weights is None else self.weights[r] for r in mine]
        return self._map(fn, [xy[r] for r in mine], w, payloads)

    def points(self):
        return self.pts, self.weights

    def close(self):
        self.framed = None
        if self.own is not None:
            self.own.shutdown(cancel_futures=True)
            self.own = None


class ThreadStore(LocalStore):
    """The points in this process, refined by ``workers`` threads over the same arrays
    (``scale/shared.py``): the plan comes from the sample, as with any store (so the mesh
    is the same), and every tile counts in one index of all points (no copies, no
    pickling), a thread of this process whose kernels release the GIL; the last step
    counts in that index too."""

    def prepare(self, emb, sets, pad):
        """The index of all points, in torus coordinates (built by all threads)."""
        self.index = new_index(emb.to_internal(self.pts), self.weights, workers=None)


# -- a tiled run ------------------------------------------------------------------------------

# Points from which tiles in threads beat one process (whose index, sweeps and assembly use
# every core already), per dimension; below, ``workers`` > 1 runs one process. Measured on 2
# cores (docs/benchmarks.md, "Workers in threads"): in the plane the stitched strips are
# 0.75-1.0x of one process at 10^6 points and 1.04-1.14x faster at 4 x 10^6; in space the stitched
# slabs take 1.06-1.62x one process's time at 10^5 points, 0.88-1.02x at 3 x 10^5 (two runs)
# and 0.71-0.87x at 10^6.
# ``KNNREFINE_TILES=always`` tiles at every size (to measure them, or with more cores).
TILES_FROM = {"plane": 2_000_000, "space": 300_000, "sphere": None}  # None: no tiles yet


def tiles_pay(domain, n):
    """Whether ``workers`` > 1 without an executor runs tiles for n points in ``domain``
    (else one process): ``TILES_FROM``, or always when KNNREFINE_TILES=always in a domain
    that has tiles (the sphere has none: its workers are its kernels' threads)."""
    env = os.environ.get("KNNREFINE_TILES", "").strip().lower()
    if env not in ("", "auto", "always"):
        raise InputError(f"KNNREFINE_TILES must be 'auto' or 'always', got {env!r}")
    least = TILES_FROM[domain]
    return least is not None and (env == "always" or n >= least)


def _plan_start(sx, sw, store, opt, budget, interrupts):
    """(embedding, the sample's index, the initial mesh, its order, its grid) from the
    sample, else from all points (the sample may be too sparse): d_{S,k} >= d_{P,k} for a
    subset S, so an initial mesh the sample accepts is accepted. InputError when none is."""
    k, factor = opt.k, reach_factor(opt.tau)
    begin = part(opt.domain, "run").Start
    start = begin(sx, opt, budget, interrupts, sw)
    found = start.find(k, factor)
    if found is None and len(sx) < store.n:
        every, w_every = store.points()
        start = begin(every, opt, budget, interrupts, w_every)
        found = start.find(k, factor)
    if found is None:
        raise InputError(start.refusal(k, opt.tau))
    if opt.dim == 2:
        emb, index, (m0, order, grid) = found
        return emb, index, m0, order, grid
    emb, index, m0 = found
    return emb, index, m0, np.arange(len(m0[0])), None


@dataclass
class Plan:
    """What a tiled run starts from (``plan``): the embedding, the sample's index, the initial
    mesh (with its order and grid), the estimated size and the vertex budget, the two sets of
    strips, the engine's parameters ``common`` (``new_run``), the coarse pass' vertices
    (internal coordinates) and kinds, whether the sample is every point, and the seconds the
    plan took."""

    emb: Embedding
    s_index: object
    m0: tuple
    m0_order: np.ndarray
    m0_grid: tuple
    estimated: float
    budget: int
    sets: list
    common: dict
    xy: np.ndarray
    kinds: np.ndarray
    everything: bool
    seconds: float

    @property
    def reported_estimate(self) -> float:
        """The size estimate the mesh's stats report: none (0) in space, where the plan
        has only the start's budget."""
        return self.estimated if self.emb.dim == 2 else 0


def plan(store, opt, workers, interrupts, coarse_share=COARSE_SHARE) -> Plan:
    """A tiled run's plan from a sample of the points of ``store`` (the same set however they
    are split or ordered): the initial mesh, the size, the strips, and a coarse pass on
    1 / (coarse_share * workers) of the points, in this process."""
    t0 = time.perf_counter()
    n = store.n
    k, tau, min_size, dim = opt.k, opt.tau, opt.min_size, opt.dim
    start_budget = opt.start_budget(n)
    coarse_f = min(1.0 / (coarse_share * workers), COARSE_MAX / n)
    sx, sw, keys = store.sample(max(coarse_f, min(1.0, SAMPLE_MIN / n)))
    share = len(sx) / n if sw is None else float(sw.sum()) / store.weight
    emb, s_index, m0, m0_order, m0_grid = _plan_start(sx, sw, store, opt, start_budget,
                                                      interrupts)  # fmt: skip
    opt.past("setting up")
    period = tuple(emb.period_internal)
    if dim == 2:
        floor = max(min_size * emb.scale, emb.grid * 2.0**FLOOR_BITS)
        lo, hi = emb.box_internal()
        area = float(np.prod(hi - lo))
        estimated = size.estimate(s_index, k, floor, period[0], period[1], area)[0]
        estimated /= share
        budget = vertex_budget(estimated, opt, len(m0_order), n)
    else:  # no size estimate in space: the start's budget, as a run in one process
        estimated = budget = start_budget
    # the strips from at most STRIP_SAMPLE of the sample (by key: any order gives them)
    planned = keys < max(coarse_f, STRIP_SAMPLE / len(sx))
    internal = emb.to_internal(sx[planned])
    sets = strips(internal, period, workers)
    common = {
        "k": k, "period": period, "tau": tau, "min_size": min_size * emb.scale,
        "max_vertices": budget, "m0": m0, "grid": emb.grid,
    }  # fmt: skip
    coarse = keys[planned] < coarse_f
    cw = None if sw is None else sw[planned][coarse]
    xy, kinds = coarse_pass(internal[coarse], cw, common)
    return Plan(emb, s_index, m0, m0_order, m0_grid, estimated, budget, sets, common, xy, kinds,
                len(sx) == n, time.perf_counter() - t0)  # fmt: skip


def refine_store(store, opt, workers) -> Mesh:
    """A tiled run (``scale/tiled.py``) on the points of ``store`` (``LocalStore``, or
    ``distributed.DaskStore``) with the checked options ``opt`` (``RunOptions``) in
    ``workers`` strips (slabs in space): the plan from a sample of the points (initial
    mesh, size, strips), a coarse pass on part of it, rounds of tiles, then whatever no
    round settled on the index of all points, fetched only then."""
    n = store.n
    deadline = opt.deadline
    report = Progress(opt.progress)
    with ahead.compiling(opt.domain, report.compiling), Interrupts() as interrupts:
        t0 = time.perf_counter()
        p = plan(store, opt, workers, interrupts)
        emb, s_index, m0, m0_order = p.emb, p.s_index, p.m0, p.m0_order
        estimated, budget, sets, common, xy, kinds = (p.estimated, p.budget, p.sets, p.common,
                                                      p.xy, p.kinds)  # fmt: skip
        everything = p.everything
        store.prepare(emb, sets, 4 * emb.grid)
        setup = time.perf_counter() - t0
        xy, kinds, stamps, history, rounds, stopped = run_rounds(
            store, sets, xy, kinds, common, min(estimated, budget), len(m0[0]), report.refining,
            interrupts, deadline,
        )  # fmt: skip
        t1 = time.perf_counter()
        args = (xy, kinds, stamps, history, common)
        bands = margin_bands(emb, *store.bounds)
        run, status, unsettled = settle(s_index, *args, bands=bands, deadline=deadline)
        before, fetched = len(m0[0]) + len(xy), False
        if stopped is not None:
            status = stopped
        elif status == S.STATUS_DONE and unsettled:
            if everything:  # the same run, on the whole torus: what the bands deferred too
                run.requeue()
            else:  # what is left needs the counts of all points
                pts, w = store.points()
                fetched = True
                index = new_index(emb.to_internal(pts), w, workers=None)
                run, _, unsettled = settle(index, *args)
            status = run.run(deadline=deadline, progress=report.refining, interrupts=interrupts)
        rounds.append({
            "round": "final", "new_vertices": run.vertices - before,
            "seconds": time.perf_counter() - t1, "unsettled": unsettled, "fetched_points": fetched,
        })  # fmt: skip
        run.time_index = setup  # the tiles and rounds count as the refinement
        run.time_refine = time.perf_counter() - t0 - setup
        finish = part(opt.domain, "run").finish
        return finish(run, status, emb, opt, n=n, weight=store.weight,
                      points=lambda: store.points()[0], report=report,
                      estimated=p.reported_estimate, budget=budget, initial=len(m0_order),
                      rounds=rounds, interrupts=interrupts)  # fmt: skip


# -- a run continued from a mesh, the points in a store (``distributed.refine(start=)``) --


CONTINUE_TRIES = 3  # regions tried, each PAD_GROWTH times wider, before all the points
PAD_GROWTH = 4.0


def continue_store(store, start, opt, new_pts, new_w) -> Mesh:
    """A run continued from the mesh ``start`` (``opt.start``; its points the store's first
    rows, checked by the caller) with the store's new points ``new_pts`` and weights
    ``new_w`` (fetched), the old points fetched only where the run may move.

    The start's elements are settled but those the new points reach (the domain's
    ``continue_run``). The run may move only inside a region (``set_region``): the new
    points' (and the start's floor points') bounding box on the torus, widened by 4 times
    the mesh's spacing there; it counts with the points in that region alone, which hold
    every point its moves count (an element inside the region has its counting region
    inside it). What the region deferred is tried again in one 4 times wider, then with
    every point (``stats["rounds"]`` says which)."""
    run_mod = part(opt.domain, "run")
    n, n0 = store.n, int(start.stats.n)
    report = Progress(opt.progress)
    with ahead.compiling(opt.domain, report.compiling), Interrupts() as interrupts:
        t0 = time.perf_counter()
        emb = box_domain.start_embedding(start)
        period = np.array(emb.period_internal)
        new = emb.to_internal(new_pts)
        index = new_index(new.copy(), new_w)  # the new points: the reopening counts none
        run, expected, budget, reopened = run_mod.continue_run(start, emb, index, new, opt, n)
        spots = new if not len(start.floor_points) else np.concatenate(
            [new, emb.to_internal(start.floor_points)])  # fmt: skip
        pad = PAD_GROWTH * emb.scale * float(np.max(start.d_m2(emb.to_input(spots)),
                                                     initial=0.0))  # fmt: skip
        run.time_index = time.perf_counter() - t0
        opt.past("setting up")
        rounds, status, region = [], S.STATUS_DONE, None
        for _ in range(CONTINUE_TRIES if len(spots) else 0):  # (none: nothing reopened)
            region = _region_around(spots, pad, period)
            if region is None:  # as wide as the torus: every point
                break
            t1 = time.perf_counter()
            pts, w = store.points_in(emb, region)
            run.index = new_index(pts, w)
            run.set_region(region)
            run.queue_unsettled()
            status = run.run(deadline=opt.deadline, progress=report.refining,
                             interrupts=interrupts)  # fmt: skip
            run.set_region(None)
            unsettled = run.unsettled()
            rounds.append({"round": "near", "points": len(pts), "region": [float(r) / emb.scale
                           for r in region], "unsettled": unsettled,
                           "seconds": time.perf_counter() - t1})  # fmt: skip
            if status != S.STATUS_DONE or unsettled == 0:
                break
            pad *= PAD_GROWTH
            region = None
        if status == S.STATUS_DONE and region is None and len(spots):  # every point counts
            t1 = time.perf_counter()
            pts, w = store.points()
            run.index = new_index(emb.to_internal(pts), w)
            run.queue_unsettled()
            status = run.run(deadline=opt.deadline, progress=report.refining,
                             interrupts=interrupts)  # fmt: skip
            rounds.append({"round": "all", "points": n, "seconds": time.perf_counter() - t1})
        run.time_refine = time.perf_counter() - t0 - run.time_index
        mesh = run_mod.finish(run, status, emb, opt, n=n, weight=store.weight,
                              points=lambda: store.points()[0], report=report,
                              estimated=expected, budget=budget,
                              initial=start.stats.initial_vertices, rounds=rounds,
                              interrupts=interrupts)  # fmt: skip
    mesh.stats.continued = {"points": n - n0, "from_vertices": len(start.torus.vertices),
                            "reopened": reopened}  # fmt: skip
    return mesh


def _region_around(x, pad, period):
    """The box (corner, widths) on the torus holding the points x (internal coordinates)
    widened by ``pad``, as ``set_region`` takes it; None when it is the whole torus. Along
    each axis the shortest arc holding them (the largest gap between them left out)."""
    d = len(period)
    corner, widths = np.empty(d), np.empty(d)
    for a in range(d):
        c = np.sort(np.mod(x[:, a], period[a]))
        gaps = np.diff(np.concatenate([c, [c[0] + period[a]]]))
        j = int(np.argmax(gaps))  # the arc starts after the largest gap
        start = c[(j + 1) % len(c)]
        corner[a] = start - pad
        widths[a] = period[a] - gaps[j] + 2 * pad
    if (widths >= period).all():
        return None
    return np.concatenate([np.mod(corner, period), np.minimum(widths, period)])
