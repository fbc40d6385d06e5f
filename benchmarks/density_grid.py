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

The time budget curve (issue 53): for each tool, its median time and its L1 error against the
truth, so that a reader sees at which budgets each tool wins. The tools: knnrefine's default
(the adaptive estimate, smoothing chosen), the same with the chosen smoothing given, the plain
kNN estimate (refine + ``KnnDensity`` + grid), FFTKDE at Silverman's and ISJ's bandwidths, and
FFTKDE at its best bandwidth in hindsight (the least L1 over 13 bandwidths from 1/8 to 2 times
Silverman's, searched once before the repeats with the truth in hand; timed at that
bandwidth). In the plane the truths are ``density_accuracy.py``'s (``--truths``; each one's box
given to knnrefine, periodic where the truth is) and L1 is its importance-sampled integral of
|f_hat - f| (20,000 points, half from the truth, half uniform in its box); knnrefine's L1 is
its estimate at those points (0 off its box), FFTKDE's its grid (the one timed) read there
by linear interpolation, 0 off the grid. In space the draws are from the truth and L1 is the
mean of |f_hat / f - 1| there.

    python benchmarks/density_grid.py --n 1e5 --truths multiscale ridge heavy

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

from density_accuracy import TRUTHS, evaluation_points  # noqa: E402

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


def knnrefine_job(pts, shape, domain=None, probe=None):
    """The plain kNN estimate: refine (default k) + ``KnnDensity`` + its grid; ``domain``
    refine's box and periodic options. Returns (seconds, phases, the density at ``probe``
    (not timed) or None)."""
    phases = {}
    t0 = time.perf_counter()
    mesh = knnrefine.refine(pts, default_k(len(pts)), **(domain or {}))
    t1 = time.perf_counter()
    density = KnnDensity(mesh, pts)
    t2 = time.perf_counter()
    density.grid(shape)
    t3 = time.perf_counter()
    phases["refine"] = t1 - t0
    phases["node values + integral"] = t2 - t1
    phases["grid"] = t3 - t2
    return t3 - t0, phases, None if probe is None else density(probe)


def adaptive_job(pts, shape, given=None, probe=None, domain=None):
    """KnnDensityEstimator (adaptive) fit + grid; given: (bandwidth, sensitivity) or None
    (chosen by leave-one-out); ``domain`` its box and periodic options. Returns (seconds,
    (bandwidth, sensitivity), the density at the points ``probe`` (not timed) or None)."""
    t0 = time.perf_counter()
    options = {} if given is None else {"bandwidth": given[0], "sensitivity": given[1]}
    est = knnrefine.KnnDensityEstimator(**options, **(domain or {})).fit(pts)
    est.grid(shape)
    seconds = time.perf_counter() - t0
    at = None if probe is None else np.exp(est.score_samples(probe))
    return seconds, (est.bandwidth_, est.sensitivity_), at


def rule_bandwidth(pts, rule):
    """KDEpy's 1-D rule (ISJ or Silverman) made isotropic: the mean over the axes."""
    from KDEpy.bw_selection import improved_sheather_jones, silvermans_rule

    select = improved_sheather_jones if rule == "ISJ" else silvermans_rule
    return float(np.mean([select(pts[:, [a]]) for a in range(pts.shape[1])]))


def fftkde_job(pts, shape, rule, probe=None):
    """FFTKDE with its rule's bandwidth (``rule``: "ISJ", "Silverman", or a number, the
    bandwidth itself) on the grid; returns (seconds, the density at ``probe`` by linear
    interpolation of the grid, not timed)."""
    from KDEpy import FFTKDE

    dim = pts.shape[1]
    t0 = time.perf_counter()
    bw = float(rule) if not isinstance(rule, str) else rule_bandwidth(pts, rule)
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


def profile(pts, shape, domain=None):
    """One adaptive fit (smoothing chosen) + grid under cProfile: cumulative seconds of the
    phases in PHASES."""
    import cProfile
    import pstats

    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.runcall(lambda: knnrefine.KnnDensityEstimator(**(domain or {})).fit(pts).grid(shape))
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
    ap.add_argument("--truths", nargs="+", default=["multiscale"], choices=list(TRUTHS),
                    help="density_accuracy's truths, in the plane")  # fmt: skip
    ap.add_argument("--profile", action="store_true", help="profile one more adaptive fit")
    args = ap.parse_args(argv)
    n, dim = int(args.n), args.dim
    shape = tuple(args.shape) if args.shape else ((512, 512) if dim == 2 else (128,) * 3)
    if len(shape) != dim:
        ap.error(f"--shape needs {dim} numbers")
    if dim == 3:
        cases = [("multiscale3", Multiscale3(), None)]
    else:
        cases = [(key, TRUTHS[key](), None) for key in args.truths]
        cases = [(key, t, {"box": t.box, "periodic": t.periodic}) for key, t, _ in cases]
    print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores; n = {n:,}, "
        f"dim {dim}, k = {default_k(n)}, grid {' x '.join(map(str, shape))}"
    )
    for key, truth, domain in cases:
        run_case(key, truth, domain, n, dim, shape, args)


TOOLS = ("adaptive (cv)", "adaptive (given)", "knnrefine kNN", "FFTKDE (Silverman)",
         "FFTKDE (ISJ)", "FFTKDE (best)")  # fmt: skip


def run_case(key, truth, domain, n, dim, shape, args):
    """One truth: warm-up, the hindsight bandwidth, ``args.repeat`` interleaved rounds of
    every tool, then the medians, the L1 errors and knnrefine's phases."""
    rng = np.random.default_rng(0)
    pts = truth.sample(n, rng)
    if dim == 2:  # importance-sampled: half from the truth, half uniform in its box
        ev, f, q = evaluation_points(truth, np.random.default_rng(1))
    else:  # draws from f: the mean of |f_hat / f - 1|
        ev = truth.sample(20000, rng)
        f = q = truth.pdf(ev)
    # warm up: compile (cached) kernels, import KDEpy
    small = (64,) * dim if dim == 2 else (32,) * dim
    knnrefine_job(pts[:20000], small, domain)
    adaptive_job(pts[:20000], small, domain=domain)
    fftkde_job(pts[:20000], small, "ISJ")
    silverman = rule_bandwidth(pts, "Silverman")
    tried = {}
    for bw in silverman * np.geomspace(1 / 8, 2, 13):  # the best bandwidth in hindsight
        tried[bw] = float(np.mean(np.abs(fftkde_job(pts, shape, bw, ev)[1] - f) / q))
    best = min(tried, key=tried.get)
    step = float(np.ptp(pts, axis=0).max()) / shape[0]  # (about FFTKDE's grid step)
    isj = rule_bandwidth(pts, "ISJ")
    print(f"\n## {key}: {getattr(truth, 'name', key)}")
    print(f"FFTKDE's bandwidths: Silverman {silverman:.3g}, ISJ {isj:.3g}, best in hindsight "
          f"{best:.3g} (the grid's step about {step:.3g}: a bandwidth below it leaves "
          "FFTKDE's grid spiky)", flush=True)  # fmt: skip
    times = {name: [] for name in TOOLS}
    at = {}
    phases = []
    chosen = None
    for r in range(args.repeat):
        first = r == 0  # (the values at the evaluation points, read once: not timed)
        s, ph, values = knnrefine_job(pts, shape, domain, ev if first else None)
        times["knnrefine kNN"].append(s)
        phases.append(ph)
        for rule, name in (("Silverman", "FFTKDE (Silverman)"), ("ISJ", "FFTKDE (ISJ)"),
                           (best, "FFTKDE (best)")):  # fmt: skip
            seconds, v = fftkde_job(pts, shape, rule, ev if first else None)
            times[name].append(seconds)
            at.setdefault(name, v)
        at.setdefault("knnrefine kNN", values)
        seconds, chosen, v = adaptive_job(pts, shape, probe=ev if first else None, domain=domain)
        times["adaptive (cv)"].append(seconds)
        at.setdefault("adaptive (cv)", v)
        seconds, _, v = adaptive_job(pts, shape, chosen, ev if first else None, domain)
        times["adaptive (given)"].append(seconds)
        at.setdefault("adaptive (given)", v)
        print(
            f"repeat {r + 1}: " + ", ".join(f"{k} {v[-1]:.3f} s" for k, v in times.items()),
            flush=True,
        )
    med = {k: float(np.median(v)) for k, v in times.items()}
    base = med["FFTKDE (Silverman)"]
    print("\n| tool | time (median) | / FFTKDE (Silverman) | L1 |")
    print("|---|---:|---:|---:|")
    for name in TOOLS:
        value = np.maximum(np.nan_to_num(at[name], nan=0.0), 0.0)  # (0 off an estimate's box)
        l1 = float(np.mean(np.abs(value - f) / q))
        print(f"| {name} | {med[name]:.3f} s | {med[name] / base:.1f} | {l1:.4f} |")
    fastest = min(med["FFTKDE (ISJ)"], med["FFTKDE (Silverman)"])
    print(f"knnrefine kNN / faster FFTKDE = {med['knnrefine kNN'] / fastest:.2f} (target <= 2)")
    print(f"adaptive smoothing chosen: bandwidth {chosen[0]:.3g}, sensitivity {chosen[1]:.2g}")
    print("knnrefine kNN's phases (median):")
    for name in phases[0]:
        print(f"  {name:24s} {np.median([p[name] for p in phases]):7.3f} s")
    if args.profile:
        profile(pts, shape, domain)


if __name__ == "__main__":
    main()
