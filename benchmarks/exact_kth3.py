"""Exact d_{P,k} in space at a mesh's nodes: knnrefine's counting tree with windows about
sampled guesses (space's ``density.Index``'s path from k = WINDOWS_FROM_K on) against scipy's
periodic cKDTree k-nearest query, in the same process, interleaved, medians of three.

    python benchmarks/exact_kth3.py                       # 10^5 points, k = 64, 128, 632
    python benchmarks/exact_kth3.py --n 1e6 --ks 2000

Points: the clustered set of ``knn_cdf3.py`` (30 Gaussian blobs over a uniform tenth) and
its Thomas process, on the periodic box; queries: the mesh's vertices (at k) and five
jittered copies of each, as ``KnnDistance`` asks at vertices and edge midpoints. Both ways
must agree exactly (the script stops otherwise).
"""

import argparse
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from knn_cdf3 import clustered, thomas  # noqa: E402

import knnrefine  # noqa: E402
from knnrefine._domains.space.density import Index as TreeIndex  # noqa: E402
from knnrefine._metric import BoxMetric  # noqa: E402


def timed(f, repeat=3):
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = f()
        times.append(time.perf_counter() - t)
    return float(np.median(times)), out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=float, default=1e5)
    ap.add_argument("--ks", type=int, nargs="+", default=[64, 128, 632])
    args = ap.parse_args(argv)
    n = int(args.n)
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores; n = {n:,}")
    sets = (("clustered", clustered(n), 1.0), ("thomas", thomas(n), 500.0))
    for name, pts, side in sets:
        for k in args.ks:
            mesh = knnrefine.refine(pts, k, periodic=True, box=(0, 0, 0, side, side, side))
            index = TreeIndex(mesh, pts)
            rng = np.random.default_rng(0)
            v = np.asarray(mesh.vertices, float)
            jitter = rng.normal(0, 1e-3 * side, (5 * len(v), 3))
            q = np.concatenate([v, np.repeat(v, 5, axis=0) + jitter])
            q = np.mod(q, side)
            origin = np.asarray(mesh.torus.origin, float)
            metric = BoxMetric((*origin, *(origin + side)), (True,) * 3)  # the torus
            frame = np.ascontiguousarray(metric.frame(q))
            scipy_tree = metric.tree(pts)
            windows_s, got = timed(lambda: index.windows(frame, k))  # noqa: B023
            scipy_s, want = timed(lambda: scipy_tree.query(frame, k=[k], workers=-1)[0][:, 0])  # noqa: B023
            if not np.array_equal(got, want):
                raise SystemExit(f"{name} k = {k}: the two ways differ")
            print(f"{name:9s} k = {k:5d}: {len(q):7,} queries, windows {windows_s:.3f} s, "
                  f"scipy {scipy_s:.3f} s, scipy / windows {scipy_s / windows_s:.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
