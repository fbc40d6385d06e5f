"""Certify knnrefine on the real data sets of ../shared/data, and time certify at n = 10^6.

    python benchmarks/certify_datasets.py                 # table in Markdown
    python benchmarks/certify_datasets.py --ks 10 100 --tau 3

For every file and k: refine (torsion angles periodic, earthquakes periodic in longitude only,
the rest in their bounding box), then knnrefine.certify with its default probes, and report
alpha_hat, beta_hat, the size ratio m / integral(1 / d_Pk^2), the largest aspect and where the
resolution floor acted. Then certify timing on 10^6 uniform points, k = 100 (median of 3).
"""

import argparse
import os
import time

import numpy as np

import knnrefine

HERE = os.path.dirname(os.path.abspath(__file__))
DATA = os.path.join(HERE, "..", "..", "shared", "data")
SETTINGS = {
    "earthquakes_global_1965_2016.csv": ((True, False), (-180, -90, 180, 90)),
    "rama_top8000_phi_psi.csv": (True, (-180, -180, 180, 180)),
    "rota_top8000_trp_chi1_chi2.csv": (True, (0, 0, 360, 360)),
    "rama_sars_cov2_spike_chainB.csv": (True, (0, 0, 360, 360)),
}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ks", nargs="+", type=int, default=[10, 100])
    ap.add_argument("--tau", type=float, default=3.0)
    ap.add_argument("--data", default=DATA)
    args = ap.parse_args(argv)
    print(
        "| data set | n | k | periodic | m | max aspect | alpha_hat | beta_hat | "
        "size ratio | floor elements (sites) | certify |"
    )
    print("|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for name in sorted(os.listdir(args.data)):
        if not name.endswith(".csv"):
            continue
        pts = np.loadtxt(os.path.join(args.data, name), delimiter=",", skiprows=1)
        if pts.ndim != 2 or pts.shape[1] != 2:
            continue  # not a planar data set (the torsion-angle triples are three-dimensional)
        periodic, box = SETTINGS.get(name, (False, None))
        for k in args.ks:
            if k >= len(pts):
                continue
            mesh = knnrefine.refine(pts, k, args.tau, periodic=periodic, box=box)
            c = knnrefine.certify(mesh, pts)
            floor = c.floor_circumballs + c.floor_cells
            per = {(True, True): "yes", (False, False): "no"}.get(tuple(c.periodic), "x only")
            print(
                f"| {name.removesuffix('.csv')} | {c.n} | {k} | {per} | {c.m} | "
                f"{c.max_aspect:.3f} | {c.alpha_hat:.3f} | {c.beta_hat:.3f} | "
                f"{c.size_ratio:.2f} | {floor} ({len(c.floor_sites)}) | "
                f"{'passed' if c.passed else 'FAILED'} |",
                flush=True,
            )
    alpha, beta = knnrefine.theorem6_constants(args.tau)
    print(f"\nTheorem 6 at tau = {args.tau:g}: alpha = {alpha:.4f}, beta = {beta:.2f}.")
    pts = np.random.default_rng(0).random((1_000_000, 2))
    mesh = knnrefine.refine(pts, 100, args.tau)
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        c = knnrefine.certify(mesh, pts)
        times.append(time.perf_counter() - t0)
    print(
        f"certify, 10^6 uniform points, k = 100: median {np.median(times):.2f} s "
        f"(runs {', '.join(f'{t:.2f}' for t in times)}), {c.n_probes} probes, "
        f"{'passed' if c.passed else 'FAILED'}"
    )


if __name__ == "__main__":
    main()
