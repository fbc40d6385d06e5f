"""The kNN-CDF in space: CDF_k(r), the share of the periodic box where d_{P,k} <= r,
integrated over a mesh (``KnnDistance.cdf``, with rigorous bounds) against Monte
Carlo at 10^6 uniform random points with scipy's cKDTree(boxsize), the way cosmologists
compute it today, in the same run.

    python benchmarks/knn_cdf3.py --n 1e5 --ks 10 100 --out benchmarks/results/knn_cdf3.json
"""

import argparse
import json
import os
import time

import numpy as np
from scipy.spatial import cKDTree

import knnrefine
from knnrefine import KnnDistance

HERE = os.path.dirname(os.path.abspath(__file__))
DATA = os.path.join(HERE, "..", "..", "shared", "data", "rota_top8000_met_chi1_chi2_chi3.csv")


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
    ap.add_argument("--ks", type=int, nargs="+", default=[10, 100])
    ap.add_argument("--queries", type=float, default=1e6)
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    n, nq = int(args.n), int(args.queries)
    inputs = [("uniform", np.random.default_rng(1).random((n, 3)), 1.0),
              ("clustered", clustered(n), 1.0)]  # fmt: skip
    if os.path.exists(DATA):
        inputs.append(("methionine", np.loadtxt(DATA, delimiter=",", skiprows=1), 360.0))
    rows = []
    for name, pts, side in inputs:
        for k in args.ks:
            t0 = time.perf_counter()
            mesh = knnrefine.refine(pts, k, periodic=True, box=(0, 0, 0, side, side, side))
            dist = KnnDistance(mesh, pts)
            t_mesh = time.perf_counter() - t0
            t0 = time.perf_counter()
            tree = cKDTree(pts, boxsize=side)
            q = np.random.default_rng(2).random((nq, 3)) * side
            exact = np.sort(tree.query(q, k=[k], workers=-1)[0][:, 0])
            t_mc = time.perf_counter() - t0
            radii = np.quantile(exact, np.linspace(0.02, 0.98, 49))
            t0 = time.perf_counter()
            cdf = dist.cdf(radii)
            lo, hi = dist.cdf_bounds(radii)
            t_cdf = time.perf_counter() - t0
            truth = np.searchsorted(exact, radii, side="right") / nq
            row = {"input": name, "n": len(pts), "k": k, "m": len(mesh.vertices),
                   "mesh_s": t_mesh, "cdf_s": t_cdf, "monte_carlo_s": t_mc,
                   "max_abs_error": float(np.abs(cdf - truth).max()),
                   "median_abs_error": float(np.median(np.abs(cdf - truth))),
                   "inside_bounds": bool(((lo <= truth + 1e-3) & (truth <= hi + 1e-3)).all()),
                   "bounds_width_median": float(np.median(hi - lo))}  # fmt: skip
            rows.append(row)
            print(f"{name:>10} n={len(pts):,} k={k:>3}: m = {row['m']:,}; mesh + d_Pk "
                  f"{t_mesh:.2f} s, 49 CDF values {t_cdf:.2f} s; Monte Carlo at {nq:.0e} "
                  f"points {t_mc:.2f} s; |mesh - MC| max {row['max_abs_error']:.4f}, median "
                  f"{row['median_abs_error']:.4f}; MC inside the bounds: {row['inside_bounds']}"
                  f" (median width {row['bounds_width_median']:.3f})", flush=True)  # fmt: skip
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
