"""k by held-out likelihood: scikit-learn's GridSearchCV over KnnDensityEstimator's k, and
the estimator's own k="cv".

Times the whole search (5-fold, shuffled) on n points of a Gaussian mixture (widths 0.1 and
0.02) and prints the cross-validation curve: mean held-out log-likelihood per point for each k,
for the plain kNN estimate (method="knn", ks 10 to 300) and the default adaptive one (the
pilot's k, 100 to 3000; each fit chooses its bandwidth by leave-one-out). Then times
KnnDensityEstimator(k="cv") (5 folds, its default grid of 10 values) on the same points and
prints its curve.

    python benchmarks/grid_search.py [--n 100000] [--method knn adaptive]
"""

import argparse
import time

import numpy as np
from sklearn.model_selection import GridSearchCV, KFold

from knnrefine import KnnDensityEstimator


def mixture(n, seed=0):
    rng = np.random.default_rng(seed)
    m = n // 4
    return np.concatenate(
        [rng.normal([0.35, 0.4], 0.1, (n - m, 2)), rng.normal([0.75, 0.7], 0.02, (m, 2))]
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--method", nargs="+", default=["knn", "adaptive"])
    ap.add_argument("--folds", type=int, default=5)
    args = ap.parse_args()
    X = mixture(args.n)
    KnnDensityEstimator(k=10).fit(X[:2000])  # kernels loaded (or compiled) outside the timing
    cv = KFold(args.folds, shuffle=True, random_state=0)
    n_test = args.n / args.folds
    for method in args.method:
        ks = KS[method]
        t0 = time.perf_counter()
        search = GridSearchCV(KnnDensityEstimator(method=method), {"k": ks}, cv=cv).fit(X)
        seconds = time.perf_counter() - t0
        print(
            f"\nGridSearchCV, method {method}, n = {args.n}, {args.folds} folds, {len(ks)} values "
            f"of k: {seconds:.1f} s (refit on all points included); best k = "
            f"{search.best_params_['k']}"
        )
        print("| k | mean held-out log-likelihood per point |")
        print("|---:|---:|")
        for k, score in zip(ks, search.cv_results_["mean_test_score"], strict=True):
            print(f"| {k} | {score / n_test:.4f} |")
    for method in args.method:
        t0 = time.perf_counter()
        est = KnnDensityEstimator(k="cv", method=method, cv=args.folds).fit(X)
        seconds = time.perf_counter() - t0
        print(
            f'\nKnnDensityEstimator(k="cv", method="{method}"), default grid: {seconds:.1f} s '
            f"(final fit included); k = {est.k_}"
        )
        print("| k | mean held-out log-likelihood per point |")
        print("|---:|---:|")
        for k, score in zip(est.cv_ks_, est.cv_scores_, strict=True):
            print(f"| {k} | {score:.4f} |")


KS = {"knn": [10, 30, 100, 300], "adaptive": [100, 300, 1000, 3000]}

if __name__ == "__main__":
    main()
