"""L1 error of the adaptive estimate on the uniform disc (``density_accuracy.py``'s "disc":
radius 0.45, nothing outside) at a fixed bandwidth factor c, alpha = 0 (what the search picks
there), against the c the default's search chooses: is the disc lost by the estimator's form
or by the choice of c?

Scored as the study scores (the same points, importance-sampled L1 on its 20,000 evaluation
points).

    python benchmarks/disc_bandwidth.py               # n = 10^4 and 10^5
"""

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from density_accuracy import Disc, evaluation_points  # noqa: E402

import knnrefine  # noqa: E402

CS = (0.5, 0.6, 0.71, 0.84, 1.0, 1.19, 1.41)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[1e4, 1e5])
    args = ap.parse_args(argv)
    truth = Disc()
    ev, f, q = evaluation_points(truth, np.random.default_rng(0))  # as the study draws them
    for n in (int(v) for v in args.sizes):
        pts = truth.sample(n, np.random.default_rng(1))
        chosen = knnrefine.KnnDensityEstimator(box=truth.box).fit(pts)
        l1 = np.mean(np.abs(np.exp(chosen.score_samples(ev)) - f) / q)
        print(f"n = {n:,}: the search chose alpha {chosen.sensitivity_}, "
              f"c {chosen.bandwidth_:.3g}: L1 {l1:.4f}")  # fmt: skip
        for c in CS:
            est = knnrefine.KnnDensityEstimator(box=truth.box, bandwidth=c, sensitivity=0.0)
            e = np.exp(est.fit(pts).score_samples(ev))
            print(f"  alpha 0, c = {c:4.2f}: L1 {np.mean(np.abs(e - f) / q):.4f}")


if __name__ == "__main__":
    main()
