"""The constants a run in space achieves: certify3's alpha_hat and beta_hat (the extremes of
d_M2 / d_Pk at dense probes) for the test matrix's inputs in the unit cube (periodic,
ordinary, and periodic in x and z only) and for the methionine torsions (period 360,
../shared/data, periodic only), against Theorem 6's alpha and beta.

    python benchmarks/certify3.py --n 20000 --out benchmarks/results/certify3.json
"""

import argparse
import json
import os
import sys

import numpy as np

import knnrefine

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))
from test_refine3 import INPUTS  # noqa: E402  (the test matrix's generators)

BOXES = {"torus": True, "ordinary": False, "mixed": (True, False, True)}
DATA = os.path.join(HERE, "..", "..", "shared", "data", "rota_top8000_met_chi1_chi2_chi3.csv")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--ks", type=int, nargs="+", default=[10, 100])
    ap.add_argument("--taus", type=float, nargs="+", default=[2.5, 3.0, 4.0])
    ap.add_argument("--boxes", nargs="+", choices=sorted(BOXES), default=sorted(BOXES))
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    cube = (0, 0, 0, 1, 1, 1)
    cases = [
        (name, gen(args.n, 1), cube, kind)
        for kind in args.boxes
        for name, gen in sorted(INPUTS.items())
    ]
    if os.path.exists(DATA) and "torus" in args.boxes:
        pts = np.loadtxt(DATA, delimiter=",", skiprows=1)
        cases.append(("methionine", pts, (0, 0, 0, 360, 360, 360), "torus"))
    rows = []
    for name, pts, box, kind in cases:
        for k in args.ks:
            for tau in args.taus:
                mesh = knnrefine.refine(pts, k, tau, periodic=BOXES[kind], box=box)
                c = knnrefine.certify(mesh, pts)
                rows.append({"input": name, "box": kind, "n": len(pts), "k": k, "tau": tau,
                             "m": len(mesh.vertices), "passed": c.passed,
                             "alpha_hat": c.alpha_hat, "beta_hat": c.beta_hat,
                             "alpha": c.alpha, "beta": c.beta, "probes": c.n_probes})  # fmt: skip
                m = len(mesh.vertices)
                print(f"{name:>10} {kind:>8} n={len(pts):>6} k={k:>3} tau={tau:g}: m = {m:>6,}"
                      f" passed={c.passed} alpha_hat {c.alpha_hat:.3f} (alpha {c.alpha:.3f}), "
                      f"beta_hat {c.beta_hat:.3f} (beta {c.beta:.1f})", flush=True)  # fmt: skip
    for kind in args.boxes:
        mine = [r for r in rows if r["box"] == kind]
        ratios = np.array([[r["alpha_hat"], r["beta_hat"]] for r in mine])
        print(f"{kind}: all {len(mine)} passed: {all(r['passed'] for r in mine)}; alpha_hat >= "
              f"{ratios[:, 0].min():.3f}, beta_hat <= {ratios[:, 1].max():.3f}")  # fmt: skip
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
