"""How many leave-one-out points the adaptive estimate's smoothing search needs: the default
(``loo_points=20000``) against 5,000 and 2,000 on the six truths of ``density_accuracy.py``
(each truth's box given), L1 error and held-out log-likelihood as scored there, the fit's
time, and the smoothing chosen.

    python benchmarks/loo_points.py                # n = 10^4 and 10^5 (a few minutes)
    python benchmarks/loo_points.py 1e6
"""

import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import density_accuracy as da  # noqa: E402

import knnrefine  # noqa: E402

VARIANTS = {"20000": {}, "5000": {"loo_points": 5000}, "2000": {"loo_points": 2000}}


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    sizes = [int(float(s)) for s in argv] or [10_000, 100_000]
    print("truth n loo_points L1 loglik seconds alpha c")
    for key, truth_class in da.TRUTHS.items():
        truth = truth_class()
        ev, f, q = da.evaluation_points(truth, np.random.default_rng(0))
        test = truth.sample(len(ev), np.random.default_rng(3))
        for n in sizes:
            pts = truth.sample(n, np.random.default_rng(1))
            for name, options in VARIANTS.items():
                t0 = time.perf_counter()
                est = knnrefine.KnnDensityEstimator(
                    box=truth.box, periodic=truth.periodic, **options
                ).fit(pts)
                seconds = time.perf_counter() - t0
                l1 = float(np.mean(np.abs(np.exp(est.score_samples(ev)) - f) / q))
                ll = float(np.mean(est.score_samples(test)))
                print(f"{key} {n} {name} {l1:.4f} {ll:.4f} {seconds:.2f} "
                      f"{est.sensitivity_:.2g} {est.bandwidth_:.3g}", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
