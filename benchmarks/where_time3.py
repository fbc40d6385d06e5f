"""Where a refinement in space spends its time, part by part, on its own final mesh: the
circumball counts (every tetrahedron's closed circumball counted again, in slot order, in
Z-order of the centres and in random order), the star walks (every vertex's star, with and
without the edges), and the cell counts (every vertex's closed Voronoi cell), each timed
alone on one thread after the run, beside the run's own time.

    python benchmarks/where_time3.py [--n 1e6] [--k 10] [--kind uniform]

The figures are the parts' costs out of the run's order and cache state: a walk inside a run
mostly meets the stars it just changed (docs/benchmarks.md, "Small k in space").
"""

import argparse
import os
import sys
import time

import numpy as np
from numba import njit

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_refine3 import make_points3  # noqa: E402

from knnrefine._domains.space.run import holds_k  # noqa: E402
from knnrefine._engine.driver3 import Refinement3, choose_grid3  # noqa: E402
from knnrefine._engine.index3 import build_index3, holds_k_within3  # noqa: E402
from knnrefine._engine.initial import reach_factor  # noqa: E402
from knnrefine._engine.refine3 import count_cell3  # noqa: E402
from knnrefine._engine.triangulation3 import star3, vertex_star3  # noqa: E402


@njit
def _walks(mesh, scratch, cnt, nv, light, period):
    total = 0
    for v in range(nv):
        if light:
            total += star3(v, mesh, scratch, cnt)[2]
        else:
            total += vertex_star3(v, mesh, scratch, cnt, period)[3]
    return total


@njit
def _cells(mesh, scratch, probe, cnt, prm, index, nv):
    held = 0
    for v in range(nv):
        held += count_cell3(v, mesh, scratch, probe, cnt, prm, index)
    return held


def _z_key(x):
    """Morton keys of points in [0, 1)^3, 21 bits an axis."""
    q = np.minimum((x * (1 << 21)).astype(np.int64), (1 << 21) - 1)
    key = np.zeros(len(x), np.int64)
    for bit in range(21):
        for a in range(3):
            key |= ((q[:, a] >> bit) & 1) << (3 * bit + a)
    return key


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=float, default=1e6)
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--kind", choices=["uniform", "clustered"], default="uniform")
    args = ap.parse_args(argv)
    n, k = int(args.n), args.k
    pts = make_points3(args.kind, n)
    period = np.ones(3)
    index = build_index3(pts)
    grid = choose_grid3(period, lambda x, r: holds_k(index, x, r, k, period), reach_factor(3))
    run = Refinement3(index, period, k, 3.0, 1e-6, 10 * n, grid)
    t0 = time.perf_counter()
    run.run()
    nv, nt = run.vertices, int(run.cnt[1])
    print(f"{args.kind} n={n:,} k={k}: run {time.perf_counter() - t0:.2f} s, {nv:,} vertices, "
          f"{nt:,} tetrahedra")  # fmt: skip

    xyz = np.asarray(run.mesh.xyz[:nv])
    corners = np.asarray(run.mesh.corners[:nt])
    p = xyz[corners]  # circumcentres on the torus, from corner 0's frame
    d = p - p[:, :1]
    d -= np.rint(d)
    rel = np.linalg.solve(2 * d[:, 1:], (d[:, 1:] ** 2).sum(-1)[..., None])[..., 0]
    centre = np.mod(p[:, 0] + rel, 1.0)
    r2 = (rel**2).sum(-1) * (1 + 1e-9)
    orders = {"slot order": np.arange(nt), "Z-order": np.argsort(_z_key(centre)),
              "random order": np.random.default_rng(0).permutation(nt)}  # fmt: skip
    for name, order in orders.items():
        x, r = np.ascontiguousarray(centre[order]), np.ascontiguousarray(r2[order])
        holds_k_within3(index, x[:8], r[:8], k, period)
        t = time.perf_counter()
        holds_k_within3(index, x, r, k, period)
        dt = time.perf_counter() - t
        print(f"  circumball counts, {name}: {dt / nt * 1e6:.2f} us each ({dt:.2f} s)")
    for light in (True, False):
        _walks(run.mesh, run.scratch, run.cnt, 8, light, period)
        t = time.perf_counter()
        met = _walks(run.mesh, run.scratch, run.cnt, nv, light, period)
        dt = time.perf_counter() - t
        what = "without edges (star3)" if light else "with edges (vertex_star3)"
        print(f"  star walks {what}: {dt / nv * 1e6:.2f} us each, {met / nv:.1f} tetrahedra, "
              f"{dt / met * 1e9:.0f} ns a tetrahedron")  # fmt: skip
    _cells(run.mesh, run.scratch, run.probe, run.cnt, run.prm, run.index, 8)
    t = time.perf_counter()
    _cells(run.mesh, run.scratch, run.probe, run.cnt, run.prm, run.index, nv)
    dt = time.perf_counter() - t
    print(f"  cell counts: {dt / nv * 1e6:.2f} us each ({dt:.2f} s)")


if __name__ == "__main__":
    main()
