"""How well the mesh carries d_{P,k} everywhere, and how fast it evaluates a grid.

    python benchmarks/distance_error.py

n = 10^5 points of a Gaussian mixture (widths 0.1 and 0.01) over uniform noise in the unit
square; for k = 10, 100 and 1000: the mesh size m, the relative error of KnnDistance against
exact d_{P,k} (scipy's cKDTree, independent of knnrefine's index) on 25,000 probes (random
points of the box and input points: median, 99th percentile, worst), the time to build
KnnDistance from the mesh (exact d_{P,k} at its nodes), and the time to evaluate it on a
512 x 512 grid (median of 5).
"""

import time

import numpy as np

import knnrefine
from knnrefine._metric import BoxMetric


def points(n=100_000, seed=0):
    rng = np.random.default_rng(seed)
    parts = [
        rng.normal([0.3, 0.3], 0.1, (int(0.45 * n), 2)),
        rng.normal([0.7, 0.6], 0.01, (int(0.35 * n), 2)),
        rng.random((n - int(0.45 * n) - int(0.35 * n), 2)),
    ]
    return np.clip(np.concatenate(parts), 0.0, 1.0)


def main():
    pts = points()
    print("| k | m | median | 99th percentile | worst | build KnnDistance | 512 x 512 grid |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for k in (10, 100, 1000):
        mesh = knnrefine.refine(pts, k)
        t0 = time.perf_counter()
        d = knnrefine.KnnDistance(mesh, pts)
        build = time.perf_counter() - t0
        rng = np.random.default_rng(0)
        lo, hi = np.array(mesh.box[:2]), np.array(mesh.box[2:])
        probes = np.concatenate(
            [lo + rng.random((12_500, 2)) * (hi - lo), pts[rng.choice(len(pts), 12_500, False)]]
        )
        exact = BoxMetric(mesh.box, mesh.periodic).kth(pts, probes, k)
        rel = np.abs(d(probes) - exact) / exact
        err = {"median": np.median(rel), "p99": np.percentile(rel, 99), "worst": rel.max()}
        d.grid((512, 512))
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            d.grid((512, 512))
            times.append(time.perf_counter() - t0)
        print(
            f"| {k} | {len(mesh.vertices):,} | {100 * err['median']:.1f}% | "
            f"{100 * err['p99']:.1f}% | {100 * err['worst']:.1f}% | {build:.2f} s | "
            f"{np.median(times):.3f} s |",
            flush=True,
        )


if __name__ == "__main__":
    main()
