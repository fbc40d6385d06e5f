"""Evaluating d_{P,k} in space: KnnDistance built on a mesh in space, then 100,000 queries
(point location in the linear pieces), first call (the locator built) and later calls,
against scipy's cKDTree(boxsize) answering the same queries exactly, in the same run.

    python benchmarks/evaluate3.py --n 30000 --k 10 --queries 100000
"""

import argparse
import time

import numpy as np
from scipy.spatial import cKDTree

import knnrefine


def clustered(n, seed=0):
    rng = np.random.default_rng(seed)
    centres = rng.random((25, 3))
    widths = 10 ** rng.uniform(-3, -1.5, 25)
    j = rng.integers(0, 25, n)
    return np.mod(centres[j] + rng.standard_normal((n, 3)) * widths[j, None], 1.0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=30000)
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--queries", type=int, default=100000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    pts = clustered(args.n, 1)
    mesh = knnrefine.refine(pts, args.k, periodic=True, box=(0, 0, 0, 1, 1, 1))
    q = np.random.default_rng(2).random((args.queries, 3))
    dist = knnrefine.KnnDistance(mesh, pts)
    t = time.perf_counter()
    dist(q)
    first = time.perf_counter() - t
    later, exact = [], []
    tree = cKDTree(pts, boxsize=1.0)
    for _ in range(args.repeats):  # interleaved: the mesh's answer, then the exact one
        t = time.perf_counter()
        dist(q)
        later.append(time.perf_counter() - t)
        t = time.perf_counter()
        tree.query(q, k=[args.k], workers=-1)
        exact.append(time.perf_counter() - t)
    print(
        f"n = {args.n:,}, k = {args.k}, m = {len(mesh.vertices):,}, {args.queries:,} queries: "
        f"first call {first:.2f} s, later calls median {np.median(later):.2f} s; "
        f"cKDTree(boxsize) median {np.median(exact):.2f} s"
    )


if __name__ == "__main__":
    main()
