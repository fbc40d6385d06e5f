"""The everyday job: n points -> a density on a 512 x 512 grid, knnrefine against KDEpy's
FFTKDE in the same run (issue 11's target: knnrefine's whole job, refinement included, within
2x FFTKDE's).

Both sides are timed whole, interleaved, on the same points (the multi-scale Gaussian mixture
of ``density_accuracy.py``): knnrefine = ``refine`` (default k) + ``KnnDensity`` (exact
d_{P,k} at the mesh's nodes from the engine's own index, the normalising integral) +
``grid``; FFTKDE = its bandwidth rule (ISJ or Silverman, the mean of the two axes' 1-D
rules, as ``density_accuracy.py``) + fit + evaluate on the grid asked for. Prints each
repeat, the medians, the ratio, and knnrefine's phases (median).

The adaptive estimate (``KnnDensityEstimator``'s default) is timed in the same repeats,
twice: with its smoothing chosen by leave-one-out likelihood (the default), and with the
chosen pair given (``bandwidth``, ``sensitivity``: a refit of known smoothing), each fit +
the same grid.

    python benchmarks/density_grid.py                 # n = 10^6, 3 repeats
    python benchmarks/density_grid.py --n 100000 --repeat 5
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
from knnrefine.density import KnnDensity, default_k  # noqa: E402


def knnrefine_job(pts, shape):
    phases = {}
    t0 = time.perf_counter()
    mesh = knnrefine.refine(pts, default_k(len(pts)))
    t1 = time.perf_counter()
    density = KnnDensity(mesh, pts)
    t2 = time.perf_counter()
    density.grid(shape)
    t3 = time.perf_counter()
    phases["refine"] = t1 - t0
    phases["node values + integral"] = t2 - t1
    phases["grid"] = t3 - t2
    return t3 - t0, phases


def adaptive_job(pts, shape, given=None):
    """KnnDensityEstimator (adaptive) fit + grid; given: (bandwidth, sensitivity) or None
    (chosen by leave-one-out). Returns (seconds, (bandwidth, sensitivity))."""
    t0 = time.perf_counter()
    options = {} if given is None else {"bandwidth": given[0], "sensitivity": given[1]}
    est = knnrefine.KnnDensityEstimator(**options).fit(pts)
    est.density_.grid(shape)
    return time.perf_counter() - t0, (est.bandwidth_, est.sensitivity_)


def fftkde_job(pts, shape, rule):
    from KDEpy import FFTKDE
    from KDEpy.bw_selection import improved_sheather_jones, silvermans_rule

    select = improved_sheather_jones if rule == "ISJ" else silvermans_rule
    t0 = time.perf_counter()
    bw = float(np.mean([select(pts[:, [a]]) for a in range(2)]))
    FFTKDE(bw=bw).fit(pts).evaluate(shape)
    return time.perf_counter() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=float, default=1e6)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--shape", type=int, nargs=2, default=(512, 512))
    args = ap.parse_args(argv)
    n = int(args.n)
    shape = tuple(args.shape)
    pts = Multiscale().sample(n, np.random.default_rng(0))
    # warm up: compile (cached) kernels, import KDEpy
    knnrefine_job(pts[:20000], (64, 64))
    adaptive_job(pts[:20000], (64, 64))
    fftkde_job(pts[:20000], (64, 64), "ISJ")
    print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores; n = {n:,}, "
        f"k = {default_k(n)}, grid {shape[0]} x {shape[1]}"
    )
    times = {
        "knnrefine": [], "FFTKDE (ISJ)": [], "FFTKDE (Silverman)": [],
        "adaptive (cv)": [], "adaptive (given)": [],
    }  # fmt: skip
    phases = []
    for r in range(args.repeat):
        s, ph = knnrefine_job(pts, shape)
        times["knnrefine"].append(s)
        phases.append(ph)
        times["FFTKDE (ISJ)"].append(fftkde_job(pts, shape, "ISJ"))
        times["FFTKDE (Silverman)"].append(fftkde_job(pts, shape, "Silverman"))
        seconds, chosen = adaptive_job(pts, shape)
        times["adaptive (cv)"].append(seconds)
        times["adaptive (given)"].append(adaptive_job(pts, shape, chosen)[0])
        print(
            f"repeat {r + 1}: " + ", ".join(f"{k} {v[-1]:.3f} s" for k, v in times.items()),
            flush=True,
        )
    med = {k: float(np.median(v)) for k, v in times.items()}
    print("\nmedians:")
    for name, s in med.items():
        print(f"  {name:20s} {s:7.3f} s")
    fastest = min(med["FFTKDE (ISJ)"], med["FFTKDE (Silverman)"])
    print(f"  knnrefine / faster FFTKDE = {med['knnrefine'] / fastest:.2f} (target <= 2)")
    for name in ("adaptive (cv)", "adaptive (given)"):
        print(f"  {name} / faster FFTKDE = {med[name] / fastest:.1f}")
    print(f"  adaptive smoothing chosen: bandwidth {chosen[0]:.3g}, sensitivity {chosen[1]:.2g}")
    print("knnrefine's phases (median):")
    for name in phases[0]:
        print(f"  {name:24s} {np.median([p[name] for p in phases]):7.3f} s")


if __name__ == "__main__":
    main()
