"""k="cv" against a default fit: KnnDensityEstimator(k="cv") and KnnDensityEstimator() on
the same points, timed in the same process, by turns (a default fit's median of --repeat,
k="cv" once a turn), with the held-out log-likelihood per point of both at fresh draws from
the truth (issue 53's target: k="cv" within 20 default fits).

    python benchmarks/density_k_cv.py [--sizes 1e4 1e5] [--truths multiscale heavy]

Truths are ``density_accuracy.py``'s, each in its own box.
"""

import argparse
import platform
import time

import numpy as np
from density_accuracy import TRUTHS

from knnrefine import KnnDensityEstimator


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[1e4, 1e5])
    ap.add_argument("--truths", nargs="+", default=["multiscale", "heavy"], choices=list(TRUTHS))
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    print(f"# {platform.machine()}, n = {args.sizes}, {args.repeat} default fits a turn")
    print(
        '| truth | n | default fit | k="cv" | ratio | k default / chosen | '
        "held-out ll default / cv | ks scored |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---|")
    for name in args.truths:
        truth = TRUTHS[name]()
        for n in (int(s) for s in args.sizes):
            rng = np.random.default_rng(0)
            X = truth.sample(n, rng)
            test = truth.sample(20000, np.random.default_rng(1))
            KnnDensityEstimator(box=truth.box).fit(X[: min(n, 3000)])  # kernels loaded first
            fits, cvs = [], []
            for _ in range(2):  # by turns
                for _ in range(args.repeat):
                    t0 = time.perf_counter()
                    default = KnnDensityEstimator(box=truth.box).fit(X)
                    fits.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                cv = KnnDensityEstimator(box=truth.box, k="cv").fit(X)
                cvs.append(time.perf_counter() - t0)
            fit, search = float(np.median(fits)), float(np.median(cvs))
            ll = [est.score(test) / len(test) for est in (default, cv)]
            print(
                f"| {name} | {n:,} | {fit:.3f} s | {search:.2f} s | {search / fit:.1f} | "
                f"{default.k_} / {cv.k_} | {ll[0]:.4f} / {ll[1]:.4f} | "
                f"{', '.join(str(int(k)) for k in cv.cv_ks_)} |"
            )


if __name__ == "__main__":
    main()
