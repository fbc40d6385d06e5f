"""The adaptive estimate's pilot k: L1 error and held-out log-likelihood against k.

    python benchmarks/pilot_k.py --sizes 1e4 1e5     # about 10 minutes

For each truth of ``density_accuracy.py`` and each n, KnnDensityEstimator (adaptive, its
bandwidth and sensitivity by leave-one-out likelihood, the truth's box) with
k = m sqrt(n) / 2 for m in 0.5, 1, 2, 4, 8: the L1 error (importance-sampled, as the study),
the mean log-density at 20,000 held-out points, the bandwidth and sensitivity chosen and
their leave-one-out score (which, unlike the held-out score, does not rise with k: the pilot
includes the left-out point). Chose the default pilot k = 2 sqrt(n) (m = 4).
"""

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from density_accuracy import TRUTHS, evaluation_points  # noqa: E402

import knnrefine  # noqa: E402

MULTIPLES = (0.5, 1, 2, 4, 8)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", nargs="+", type=float, default=[1e4, 1e5])
    args = ap.parse_args(argv)
    print("| truth | n | " + " | ".join(f"k = {m:g} sqrt(n)/2" for m in MULTIPLES) + " |")
    print("|---|---:|" + "---|" * len(MULTIPLES))
    for n in (int(s) for s in args.sizes):
        for key, truth_class in TRUTHS.items():
            truth = truth_class()
            ev, f, q = evaluation_points(truth, np.random.default_rng(0))
            test = truth.sample(20000, np.random.default_rng(3))
            pts = truth.sample(n, np.random.default_rng(1))
            cells = []
            for m in MULTIPLES:
                k = int(round(m * 0.5 * np.sqrt(n)))
                est = knnrefine.KnnDensityEstimator(k=k, box=truth.box, periodic=truth.periodic)
                est.fit(pts)
                l1 = np.mean(np.abs(np.exp(est.score_samples(ev)) - f) / q)
                ll = est.score(test) / len(test)
                loo = float(np.max(est.bandwidth_scores_))
                cells.append(
                    f"L1 {l1:.3f}, LL {ll:.3f} (c {est.bandwidth_:.2f}, alpha "
                    f"{est.sensitivity_:.1f}, LOO {loo:.3f})"
                )
            print(f"| {key} | {n:.0e} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
