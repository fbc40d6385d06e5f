"""The smoothing search's scores through binned lattices (``engine/binned.py``) against the
exact kernel sums, on n points of the multi-scale mixture of ``density_accuracy.py``.

For each n: the default estimate's pilot (k = 2 sqrt(n)), 20,000 sample points (all when
fewer); at three smoothings (alpha 1/2; c 0.84, 1.19, 1.68) one leave-one-out pass each way,
timed (medians of ``--repeat``), and the binned values against the exact ones (relative error
of each point's density: median and 99th percentile; the difference of the mean
log-likelihoods); then ``choose_smoothing`` both ways (binned=True / False), the pair each
chooses and its time.

    python benchmarks/binned_scores.py                     # n = 10^4, 10^5, 10^6
    python benchmarks/binned_scores.py --n 1e5 --repeat 5
"""

import argparse
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from density_accuracy import Multiscale  # noqa: E402

import knnrefine  # noqa: E402
from knnrefine.density import choose_smoothing  # noqa: E402


def timed(repeat, call, *args, **options):
    """(the last result of call(*args, **options), the median seconds of ``repeat`` calls)."""
    seconds = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = call(*args, **options)
        seconds.append(time.perf_counter() - t0)
    return out, float(np.median(seconds))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=float, nargs="+", default=[1e4, 1e5, 1e6])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    for n in (int(v) for v in args.n):
        pts = Multiscale().sample(n, np.random.default_rng(0))
        density = knnrefine.KnnDensityEstimator(bandwidth=1.0, sensitivity=0.5).fit(pts).density_
        m = min(n, 20000)
        sample = np.sort(np.random.default_rng(1).choice(n, m, replace=False))
        density.loo(sample[:10], binned=True)  # compile
        print(f"\nn = {n:,}, k = {density.k}, {m:,} sample points")
        print("   c   exact s  binned s  rel. error median / p99  mean log-lik diff")
        for c in (0.84, 1.19, 1.68):
            density.set_bandwidth(c, 0.5)
            exact, te = timed(args.repeat, density.loo, sample)
            got, tb = timed(args.repeat, density.loo, sample, binned=True)
            rel = np.abs(np.expm1(got - exact))
            print(
                f"{c:5.2f} {te:9.3f} {tb:9.3f}   {np.median(rel):.1e} / "
                f"{np.quantile(rel, 0.99):.1e}        {got.mean() - exact.mean():+.1e}"
            )
        for binned in (True, False):
            (alpha, c, _), seconds = timed(1, choose_smoothing, density, binned=binned)
            print(f"choose_smoothing(binned={binned}): alpha {alpha}, c {c:.3g}, {seconds:.2f} s")


if __name__ == "__main__":
    main()
