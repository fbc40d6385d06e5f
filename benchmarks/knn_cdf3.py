"""The kNN-CDF in space for several k in one call (``knnrefine.density.knn_cdf``) against
Monte Carlo at 10^6 uniform points with scipy's cKDTree(boxsize), the way cosmologists
compute it today, in the same run, on a Thomas process (the issue's case: a periodic box of
side 500, parents uniform, 20 children each, Gaussian with sigma = 5) and on clustered data.

For each input and k: ``knn_cdf`` for that k alone (its choice: the mesh with a control
sample above the break-even k, Monte Carlo below) and Monte Carlo at ``--queries`` points,
interleaved and timed, against a truth from 4 x 10^6 other uniform points; then every k in
one call both ways (Monte Carlo: one kd-tree query to the largest k). Printed per k:
the method, both times, the largest and median |error| against the truth at 49 radii (the
2nd to 98th percentiles of d_k), Monte Carlo's own errors there (its noise), the median width
of knn_cdf's 95% band and of the mesh's rigorous bounds.

    python benchmarks/knn_cdf3.py --n 1e5 --ks 1 8 64 --out benchmarks/results/knn_cdf3.json
"""

import argparse
import json
import os
import platform
import time

import numpy as np
from scipy.spatial import cKDTree

from knnrefine.density import knn_cdf


def thomas(n, side=500.0, children=20, sigma=5.0, seed=11):
    rng = np.random.default_rng(seed)
    parents = rng.random((n // children, 3)) * side
    pts = np.repeat(parents, children, axis=0)
    return np.mod(pts + rng.normal(0.0, sigma, pts.shape), side)


def clustered(n, seed=0):
    rng = np.random.default_rng(seed)
    centres = rng.random((30, 3))
    widths = 10 ** rng.uniform(-3, -1, 30)
    j = rng.integers(0, 30, n)
    pts = centres[j] + rng.standard_normal((n, 3)) * widths[j, None]
    pts[: n // 10] = rng.random((n // 10, 3))
    return np.mod(pts, 1.0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=float, default=1e5)
    ap.add_argument("--ks", type=int, nargs="+", default=[1, 8, 64])
    ap.add_argument("--queries", type=float, default=1e6)
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    n, nq = int(args.n), int(args.queries)
    print(f"# {platform.machine()}, {os.cpu_count()} cores; n = {n:,}, {nq:,} queries")
    inputs = [("thomas", thomas(n), 500.0), ("clustered", clustered(n), 1.0)]
    rows = []
    for name, pts, side in inputs:
        tree = cKDTree(pts, boxsize=side)
        far = np.random.default_rng(99).random((4 * nq, 3)) * side
        truth_d = np.sort(tree.query(far, k=args.ks, workers=-1)[0], axis=0)
        levels = np.linspace(0.02, 0.98, 49)
        radii = [np.quantile(truth_d[:, j], levels) for j in range(len(args.ks))]
        every = np.unique(np.concatenate(radii))
        box = (0, 0, 0, side, side, side)
        for j, k in enumerate(args.ks):  # each k alone, both ways, interleaved
            t0 = time.perf_counter()
            res = knn_cdf(pts, [k], every, box, queries=nq)
            t_ours = time.perf_counter() - t0
            t0 = time.perf_counter()
            q = np.random.default_rng(7).random((nq, 3)) * side
            mc = np.sort(tree.query(q, k=[k], workers=-1)[0][:, 0])
            t_mc = time.perf_counter() - t0
            at = np.searchsorted(every, radii[j])
            truth = np.searchsorted(truth_d[:, j], radii[j], side="right") / len(far)
            err = np.abs(res.cdf[0][at] - truth)
            mc_err = np.abs(np.searchsorted(mc, radii[j], side="right") / nq - truth)
            bounds = res.bounds.get(k)
            rigorous = float(np.median((bounds[1] - bounds[0])[at])) if bounds else None
            row = {"input": name, "n": n, "k": k, "method": res.method[0],
                   "knn_cdf_s": t_ours, "monte_carlo_s": t_mc,
                   "max_abs_error": float(err.max()), "median_abs_error": float(np.median(err)),
                   "mc_max_abs_error": float(mc_err.max()),
                   "mc_median_abs_error": float(np.median(mc_err)),
                   "band_width_median": float(np.median((res.upper[0] - res.lower[0])[at])),
                   "rigorous_width_median": rigorous, "vertices": res.vertices.get(k)}  # fmt: skip
            rows.append(row)
            print(f"{name:>9} k={k:>3} {res.method[0]:>11}: knn_cdf {t_ours:6.2f} s, "
                  f"Monte Carlo {t_mc:6.2f} s; |error| max {err.max():.4f} median "
                  f"{np.median(err):.5f} (Monte Carlo's {mc_err.max():.4f} / "
                  f"{np.median(mc_err):.5f}); 95% band median width "
                  f"{row['band_width_median']:.4f}"
                  + (f", rigorous bounds {rigorous:.3f}" if rigorous is not None else ""),
                  flush=True)  # fmt: skip
        t0 = time.perf_counter()
        knn_cdf(pts, args.ks, every, box, queries=nq)
        t_ours = time.perf_counter() - t0
        t0 = time.perf_counter()
        tree.query(np.random.default_rng(7).random((nq, 3)) * side, k=args.ks, workers=-1)
        t_mc = time.perf_counter() - t0
        rows.append({"input": name, "n": n, "k": list(args.ks), "knn_cdf_s": t_ours,
                     "monte_carlo_s": t_mc})  # fmt: skip
        print(
            f"{name:>9} every k at once: knn_cdf {t_ours:.2f} s, Monte Carlo (one query to "
            f"k = {max(args.ks)}) {t_mc:.2f} s",
            flush=True,
        )
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
