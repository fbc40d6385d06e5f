"""Rounds of tiles in local processes, then the final pass (the rule is ``tiles.py``'s).

``refine_tiled`` plans two interleaved sets of strips balanced by point count, runs rounds
alternating between them (every strip of a round in its own process, with only its points
and the vertices in it), and ends with the whole torus in this process: the vertices of all
rounds triangulated (``tiles.insert_points``), what the rounds settled marked so
(``tiles.mark_settled``), and the engine's loop run on the rest. It returns that last
``Refinement``, so the caller assembles the mesh as for a run in one process.
"""

import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from ..errors import EngineError
from . import refine as R
from .driver import Refinement
from .index import build_index
from .state import C_NV, ERRORS, P_REGION_H, P_REGION_W, P_REGION_X0, P_REGION_Y0
from .tiles import WALK_LOST, in_rectangle, insert_points, mark_settled, spatial_order

MAX_ROUNDS = 6  # rounds of strips before the final pass takes whatever is left


def strips(xy, lx, ly, tiles):
    """Two sets of ``tiles`` strips (tiles, 4) as regions (x0, y0, w, h) of the torus, across
    the longer period, each holding about 1 / tiles of the points: the first cut at the
    quantiles j / tiles, the second at (j + 1/2) / tiles, so that each border of one lies
    inside a strip of the other."""
    axis = 0 if lx >= ly else 1
    period = (lx, ly)[axis]
    coord = np.sort(xy[:, axis])
    sets = []
    for shift in (0.0, 0.5):
        q = (np.arange(tiles) + shift) / tiles
        cuts = np.quantile(coord, q) if len(coord) else q * period
        width = np.diff(np.append(cuts, cuts[0] + period))
        regions = np.zeros((tiles, 4))
        regions[:, axis] = cuts
        regions[:, 2 + axis] = width
        regions[:, 3 - axis] = (ly, lx)[axis]  # the whole other period
        sets.append(regions)
    return sets


def seed(run, xy, kinds, stamps, regions):
    """Insert the vertices xy (with their kinds and rounds) into the run's initial mesh, mark
    what earlier rounds settled (regions (Q, T, 4)), and queue the rest."""
    order = spatial_order(np.ascontiguousarray(xy), run.lx, run.ly)
    pts = np.ascontiguousarray(xy[order])
    ids = np.full(len(pts), -1, np.int64)
    done = 0
    while done < len(pts):
        done = insert_points(pts, ids, done, run.mesh, run.book, run.scratch, run.cnt, run.prm)
        if done < 0:
            what = "a walk got lost" if done == WALK_LOST else ERRORS.get(done, str(done))
            raise EngineError(f"triangulating a tile's vertices failed: {what}")
        if done < len(pts):
            run._grow_if_needed()
    nv = int(run.cnt[C_NV])
    all_stamps = np.zeros(nv, np.int32)
    placed = ids >= 0
    all_stamps[ids[placed]] = stamps[order][placed]
    run.book.kinds[ids[placed]] = kinds[order][placed]
    run.reserve_queues(3 * nv + R.HEADROOM)  # queue_all pushes every triangle and vertex
    mark_settled(run.mesh, run.book, run.cnt, run.prm, all_stamps, regions)
    R.queue_all(run.mesh, run.book, run.queues, run.cnt, run.prm)
    return nv


def run_tile(task):
    """One tile of one round (in a worker process): its points, the vertices in its region,
    the earlier rounds' regions; returns the vertices it inserted (xy, kinds) and its
    counters."""
    t0 = time.perf_counter()
    os.environ["KNNREFINE_THREADS"] = "1"  # one of many tiles at once: one engine thread
    index = build_index(task["points"], weights=task["weights"])
    run = Refinement(
        index, task["k"], task["lx"], task["ly"], task["tau"], task["min_size"],
        task["max_vertices"], m0=task["m0"], grid=task["grid"],
        expected_vertices=task["expected"],
    )  # fmt: skip
    start = seed(run, task["xy"], task["kinds"], task["stamps"], task["history"])
    x0, y0, w, h = task["region"]
    run.prm[P_REGION_X0], run.prm[P_REGION_Y0] = x0, y0
    run.prm[P_REGION_W], run.prm[P_REGION_H] = w, h
    status = run.run(deadline=task["deadline"])
    nv = int(run.cnt[C_NV])
    return {
        "xy": run.mesh.xy[start:nv].copy(),
        "kinds": run.book.kinds[start:nv].copy(),
        "status": int(status),
        "seconds": time.perf_counter() - t0,
        "counters": run.counters(),
    }


COARSE_SHARE = 8  # the coarse pass refines 1 / (COARSE_SHARE * workers) of the points


def coarse_pass(points, weights, k, lx, ly, tau, min_size, max_vertices, m0, grid, workers):
    """The vertices (xy, kinds) of a refinement of a random subset of the points, in this
    process: a ball holding k of the subset holds k of all, so every move it makes is a move
    of the whole run, and the strips start from a mesh whose elements are a few times the
    final ones (from the initial mesh's, a first round could split almost nothing inside a
    strip). Nothing when the subset would hold fewer than 4 k points."""
    m = len(points) // (COARSE_SHARE * workers)
    if m < 4 * k:
        return np.zeros((0, 2)), np.zeros(0, np.int8)
    pick = np.sort(np.random.default_rng(0).choice(len(points), m, replace=False))
    index = build_index(points[pick], weights=None if weights is None else weights[pick])
    run = Refinement(index, k, lx, ly, tau, min_size, max_vertices, m0=m0, grid=grid)
    run.run()
    start, nv = len(m0[0]), int(run.cnt[C_NV])
    return run.mesh.xy[start:nv].copy(), run.book.kinds[start:nv].copy()


def _context():
    """fork where the platform has it (no re-import of the caller's script, workers start in
    milliseconds; the engine's threads are all joined between kernel calls), else spawn
    (macOS, Windows: the caller's script then needs the ``if __name__ == "__main__":``
    guard, as for any multiprocessing)."""
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("fork" if "fork" in methods else "spawn")


def refine_tiled(
    points, weights, k, lx, ly, tau, min_size, max_vertices, m0, grid, expected, index,
    workers, progress=None, interrupts=None, deadline=None, executor=None,
):  # fmt: skip
    """kNNRefine in rounds of ``workers`` strips in as many processes, then the final pass
    on ``index`` (the full counting index) in this one. points: internal coordinates.
    ``executor``: a ``concurrent.futures.Executor`` whose ``map`` runs the tiles (a Dask
    client's ``get_executor()``, for one); None: a pool of ``workers`` local processes.
    Returns (the final Refinement, its status, a per-round report). A tile stopped by the
    budget or the deadline (``deadline``, a time.perf_counter() value, holds in the tiles
    too) ends the run with that status: what it left inside its strip is not settled, so
    no later round or pass may treat it as settled."""
    sets = strips(points, lx, ly, workers)
    masks = [
        [in_rectangle(points, *region, 4 * grid, lx, ly) for region in regions] for regions in sets
    ]
    xy, kinds = coarse_pass(points, weights, k, lx, ly, tau, min_size, max_vertices, m0, grid,
                            workers)  # fmt: skip
    stamps = np.zeros(len(xy), np.int32)
    history = np.zeros((0, workers, 4))
    report = []
    common = {
        "k": k, "lx": lx, "ly": ly, "tau": tau, "min_size": min_size,
        "max_vertices": max_vertices, "m0": m0, "grid": grid, "deadline": deadline,
    }  # fmt: skip
    stopped = None
    own = executor is None
    pool = ProcessPoolExecutor(workers, mp_context=_context()) if own else executor
    try:
        for r in range(1, MAX_ROUNDS + 1):
            regions = sets[(r - 1) % 2]
            tasks = []
            for j, region in enumerate(regions):
                inside = in_rectangle(xy, *region, 4 * grid, lx, ly)
                mask = masks[(r - 1) % 2][j]
                tasks.append({
                    **common, "points": points[mask],
                    "weights": None if weights is None else weights[mask],
                    "xy": xy[inside], "kinds": kinds[inside], "stamps": stamps[inside],
                    "history": history, "region": region,
                    "expected": int(expected / workers + inside.sum()),
                })  # fmt: skip
            t0 = time.perf_counter()
            results = list(pool.map(run_tile, tasks))
            new = np.concatenate([res["xy"] for res in results])
            report.append({
                "round": r, "new_vertices": len(new), "seconds": time.perf_counter() - t0,
                "tiles": [res["seconds"] for res in results],
                "tile_vertices": [len(res["xy"]) for res in results],
            })  # fmt: skip
            xy = np.concatenate([xy, new])
            kinds = np.concatenate([kinds] + [res["kinds"] for res in results])
            stamps = np.concatenate([stamps, np.full(len(new), r, np.int32)])
            history = np.concatenate([history, regions[None]])
            if progress is not None:
                progress(len(m0[0]) + len(xy), 0)
            if interrupts is not None:
                interrupts.check()
            stopped = next(
                (res["status"] for res in results if res["status"] != R.STATUS_DONE), None
            )
            if stopped is None and deadline is not None and time.perf_counter() >= deadline:
                stopped = R.STATUS_STEPS
            if stopped is not None or (r >= 2 and len(new) == 0):
                break
    finally:
        if own:
            pool.shutdown(cancel_futures=True)
    final = Refinement(
        index, k, lx, ly, tau, min_size, max_vertices, m0=m0, grid=grid,
        expected_vertices=len(m0[0]) + len(xy),
    )  # fmt: skip
    seed(final, xy, kinds, stamps, history)
    if stopped is not None:
        return final, stopped, report
    t0 = time.perf_counter()
    before = int(final.cnt[C_NV])
    status = final.run(deadline=deadline, progress=progress, interrupts=interrupts)
    report.append({
        "round": "final", "new_vertices": int(final.cnt[C_NV]) - before,
        "seconds": time.perf_counter() - t0,
    })  # fmt: skip
    return final, status, report
