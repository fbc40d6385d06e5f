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
    python benchmarks/density_grid.py --dim 3 --n 100000 --repeat 5   # 128^3 grid
    python benchmarks/density_grid.py --n 1e6 --repeat 1 --profile    # where the time goes

``--profile`` ends with one more adaptive fit (smoothing chosen) + grid under cProfile and
prints the cumulative seconds of its main phases.

In space (``--dim 3``) the points are a mixture of three Gaussians in R^3 (widths 0.12, 0.02,
0.006; ``Multiscale3``), the grid 128 x 128 x 128 over each estimate's own box, FFTKDE's
bandwidth the mean of the three axes' 1-D rules; the script also prints each estimate's L1
error against the truth (the mean of |f_hat / f - 1| at 20,000 draws from f; FFTKDE's grid
read there by trilinear interpolation).
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


class Multiscale3:
    """Three Gaussians in R^3, widths 0.12, 0.02, 0.006 (weights 0.5, 0.3, 0.2)."""

    W = np.array([0.5, 0.3, 0.2])
    MU = np.array([[0.35, 0.4, 0.5], [0.7, 0.7, 0.3], [0.75, 0.25, 0.6]])
    S = np.array([0.12, 0.02, 0.006])

    def pdf(self, x):
        out = np.zeros(len(x))
        for w, m, s in zip(self.W, self.MU, self.S, strict=True):
            out += w * np.exp(-((x - m) ** 2).sum(1) / (2 * s * s)) / (2 * np.pi * s * s) ** 1.5
        return out

    def sample(self, n, rng):
        c = rng.choice(3, n, p=self.W)
        return self.MU[c] + rng.normal(size=(n, 3)) * self.S[c][:, None]


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


def adaptive_job(pts, shape, given=None, probe=None):
    """KnnDensityEstimator (adaptive) fit + grid; given: (bandwidth, sensitivity) or None
    (chosen by leave-one-out). Returns (seconds, (bandwidth, sensitivity), the density at
    the points ``probe`` (not timed) or None)."""
    t0 = time.perf_counter()
    options = {} if given is None else {"bandwidth": given[0], "sensitivity": given[1]}
    est = knnrefine.KnnDensityEstimator(**options).fit(pts)
    est.grid(shape)
    seconds = time.perf_counter() - t0
    at = None if probe is None else np.exp(est.score_samples(probe))
    return seconds, (est.bandwidth_, est.sensitivity_), at


def fftkde_job(pts, shape, rule, probe=None):
    """FFTKDE with its rule's bandwidth (the mean over the axes) on the grid; returns
    (seconds, the density at ``probe`` by linear interpolation of the grid, not timed)."""
    from KDEpy import FFTKDE
    from KDEpy.bw_selection import improved_sheather_jones, silvermans_rule

    dim = pts.shape[1]
    select = improved_sheather_jones if rule == "ISJ" else silvermans_rule
    t0 = time.perf_counter()
    bw = float(np.mean([select(pts[:, [a]]) for a in range(dim)]))
    grid, values = FFTKDE(bw=bw).fit(pts).evaluate(shape)
    seconds = time.perf_counter() - t0
    if probe is None:
        return seconds, None
    from scipy.interpolate import RegularGridInterpolator

    axes = [np.unique(grid[:, a]) for a in range(dim)]
    table = values.reshape([len(a) for a in axes])
    read = RegularGridInterpolator(axes, table, bounds_error=False, fill_value=0.0)
    return seconds, read(probe)


PHASES = (  # (file, function) -> what it is, for --profile
    ("run.py", "refine", "the mesh (refine)"),
    ("estimate.py", "__init__", "exact d_Pk at the mesh's nodes + the integral"),
    ("adaptive.py", "__init__", "the adaptive set-up"),
    ("kernelsum.py", "build_centres", "  of which the kernels' kd-tree"),
    ("distance.py", "interpolate", "  of which the pilot at the points"),
    ("adaptive.py", "choose_smoothing", "the smoothing search"),
    ("estimator.py", "grid", "the grid"),
)


def profile(pts, shape):
    """One adaptive fit (smoothing chosen) + grid under cProfile: cumulative seconds of the
    phases in PHASES."""
    import cProfile
    import pstats

    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.runcall(lambda: knnrefine.KnnDensityEstimator().fit(pts).grid(shape))
    total = time.perf_counter() - t0
    stats = pstats.Stats(prof).stats
    print(f"profile of one adaptive fit + grid ({total:.2f} s, cProfile's overhead included):")
    for file, func, what in PHASES:
        seconds = sum(
            v[3] for (path, _, fn), v in stats.items()
            if fn == func and path.endswith(os.sep + file) and "knnrefine" in path
        )  # fmt: skip
        print(f"  {what:48s} {seconds:7.3f} s")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=float, default=1e6)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--dim", type=int, choices=(2, 3), default=2)
    ap.add_argument("--shape", type=int, nargs="+", default=None,
                    help="cells per axis (default 512 x 512, or 128^3 with --dim 3)")  # fmt: skip
    ap.add_argument("--profile", action="store_true", help="profile one more adaptive fit")
    args = ap.parse_args(argv)
    n, dim = int(args.n), args.dim
    shape = tuple(args.shape) if args.shape else ((512, 512) if dim == 2 else (128,) * 3)
    if len(shape) != dim:
        ap.error(f"--shape needs {dim} numbers")
    truth = Multiscale() if dim == 2 else Multiscale3()
    rng = np.random.default_rng(0)
    pts = truth.sample(n, rng)
    probe = truth.sample(20000, rng) if dim == 3 else None  # the L1 error's draws
    # warm up: compile (cached) kernels, import KDEpy
    small = (64,) * dim if dim == 2 else (32,) * dim
    knnrefine_job(pts[:20000], small)
    adaptive_job(pts[:20000], small)
    fftkde_job(pts[:20000], small, "ISJ")
    print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores; n = {n:,}, "
        f"dim {dim}, k = {default_k(n)}, grid {' x '.join(map(str, shape))}"
    )
    times = {
        "knnrefine": [], "FFTKDE (ISJ)": [], "FFTKDE (Silverman)": [],
        "adaptive (cv)": [], "adaptive (given)": [],
    }  # fmt: skip
    at = {}
    phases = []
    for r in range(args.repeat):
        s, ph = knnrefine_job(pts, shape)
        times["knnrefine"].append(s)
        phases.append(ph)
        for rule in ("ISJ", "Silverman"):
            seconds, at[f"FFTKDE ({rule})"] = fftkde_job(pts, shape, rule, probe)
            times[f"FFTKDE ({rule})"].append(seconds)
        seconds, chosen, at["adaptive (cv)"] = adaptive_job(pts, shape, probe=probe)
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
    if args.profile:
        profile(pts, shape)
    if probe is not None:
        f = truth.pdf(probe)
        print("L1 error against the truth (mean |f_hat / f - 1| at 20,000 draws from f):")
        for name, values in at.items():
            print(f"  {name:20s} {np.mean(np.abs(values / f - 1.0)):.3f}")


if __name__ == "__main__":
    main()
