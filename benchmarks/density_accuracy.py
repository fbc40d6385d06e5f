"""Density estimation: knnrefine's kNN density against the truth and the usual tools.

    python benchmarks/density_accuracy.py              # n = 1e4, 1e5, 1e6 (about 15 minutes)
    python benchmarks/density_accuracy.py --sizes 1e4 1e5

Truths: a Gaussian mixture whose components have widths 0.12, 0.02 and 0.003 (restricted to
the unit square), a uniform density on the unit square with a hole of radius 0.25, and a
mixture of two von Mises products on the torus [-pi, pi)^2.

L1 error: the integral of |estimate - truth| over the box, by importance-sampled Monte Carlo
(20,000 points drawn from 1/2 truth + 1/2 uniform, the same for every method), which resolves
the narrow component whatever the method's own grid.

Methods, each with its automatic bandwidth, in the same run on the same points:
* knnrefine: refine(points, k) then KnnDensity (normalised over the box); k = sqrt(n) / 2
  (``knnrefine.density.default_k``); periodic on the torus truth.
* scipy gaussian_kde (Scott's rule). Where n * evaluations > 2e9 it is evaluated on a random
  subset of the L1 sample (marked ~).
* KDEpy FFTKDE on a grid of step bw / 2 (at most 4096 x 4096), interpolated: KDEpy's
  automatic bandwidths are 1-D, so the isotropic bandwidth is the mean of the two marginals'
  bandwidths, by ISJ (Improved Sheather-Jones) and by Silverman's rule.
* scikit-learn KernelDensity with Scott's rule in data units (its bandwidth="scott" is the
  bare factor n^(-1/6), meant for standardised data), rtol 1e-4; subsampled like
  gaussian_kde.
None of the peers knows about the torus.

Then the time each takes to produce a 512 x 512 grid from n = 1e5 points (gaussian_kde and
KernelDensity timed on 16 rows and scaled to 512, marked ~).
"""

import argparse
import json
import os
import time

import numpy as np
from scipy.special import erf, i0
from scipy.stats import gaussian_kde

import knnrefine
from knnrefine.density import default_k

HERE = os.path.dirname(os.path.abspath(__file__))


class Multiscale:
    name = "Gaussian mixture, widths 0.12 / 0.02 / 0.003"
    box = (0.0, 0.0, 1.0, 1.0)
    periodic = False
    W = np.array([0.5, 0.3, 0.2])
    MU = np.array([[0.35, 0.4], [0.7, 0.7], [0.75, 0.25]])
    S = np.array([0.12, 0.02, 0.003])

    def __init__(self):
        def inside(a, s):
            return 0.5 * (erf((1 - a) / (s * np.sqrt(2))) - erf(-a / (s * np.sqrt(2))))

        self.Z = sum(
            w * inside(m[0], s) * inside(m[1], s)
            for w, m, s in zip(self.W, self.MU, self.S, strict=True)
        )

    def pdf(self, x):
        out = np.zeros(len(x))
        for w, m, s in zip(self.W, self.MU, self.S, strict=True):
            out += w * np.exp(-((x - m) ** 2).sum(1) / (2 * s * s)) / (2 * np.pi * s * s)
        return out / self.Z

    def sample(self, n, rng):
        out, got = [], 0
        while got < n:
            c = rng.choice(3, n, p=self.W)
            x = self.MU[c] + rng.normal(size=(n, 2)) * self.S[c][:, None]
            x = x[(x >= 0).all(1) & (x <= 1).all(1)]
            out.append(x)
            got += len(x)
        return np.concatenate(out)[:n]


class Hole:
    name = "uniform with a hole (radius 0.25)"
    box = (0.0, 0.0, 1.0, 1.0)
    periodic = False

    def pdf(self, x):
        outside = ((x - 0.5) ** 2).sum(1) > 0.25**2
        return outside / (1 - np.pi * 0.25**2)

    def sample(self, n, rng):
        out, got = [], 0
        while got < n:
            x = rng.random((2 * n, 2))
            x = x[((x - 0.5) ** 2).sum(1) > 0.25**2]
            out.append(x)
            got += len(x)
        return np.concatenate(out)[:n]


class VonMises:
    name = "von Mises mixture on the torus"
    box = (-np.pi, -np.pi, np.pi, np.pi)
    periodic = True
    W = np.array([0.6, 0.4])
    MU = np.array([[-1.2, 2.5], [1.0, -0.5]])
    K = np.array([[4.0, 8.0], [30.0, 30.0]])

    def pdf(self, x):
        out = np.zeros(len(x))
        for w, m, k in zip(self.W, self.MU, self.K, strict=True):
            out += w * np.prod(np.exp(k * np.cos(x - m)) / (2 * np.pi * i0(k)), axis=1)
        return out

    def sample(self, n, rng):
        c = rng.choice(2, n, p=self.W)
        x = rng.vonmises(self.MU[c], self.K[c])
        return (x + np.pi) % (2 * np.pi) - np.pi


def l1_sample(truth, rng, size=20000):
    lo, hi = np.array(truth.box[:2]), np.array(truth.box[2:])
    half = rng.random(size) < 0.5
    x = np.where(half[:, None], truth.sample(size, rng), lo + rng.random((size, 2)) * (hi - lo))
    q = 0.5 * truth.pdf(x) + 0.5 / np.prod(hi - lo)
    return x, truth.pdf(x), q


def knnrefine_estimate(points, truth, ev):
    k = default_k(len(points))
    mesh = knnrefine.refine(points, k, periodic=truth.periodic, box=truth.box)
    return knnrefine.KnnDensity(mesh, points)(ev), f"k = {k}, m = {len(mesh.vertices)}"


def scipy_estimate(points, truth, ev):
    kde = gaussian_kde(points.T)
    return kde(ev.T), f"bw = {kde.factor:.3g} x sd"


def fftkde_estimate(points, truth, ev, rule="ISJ"):
    """KDEpy's FFTKDE; its bandwidth rules are 1-D, so the isotropic bandwidth is the mean of
    the two marginals'. The grid step is at most bw / 2 (capped at 4096 x 4096)."""
    from KDEpy import FFTKDE
    from KDEpy.bw_selection import improved_sheather_jones, silvermans_rule
    from scipy.interpolate import RegularGridInterpolator

    select = improved_sheather_jones if rule == "ISJ" else silvermans_rule
    bw = float(np.mean([select(points[:, [a]]) for a in range(2)]))
    span = float(np.ptp(points, axis=0).max()) + 8 * bw
    grid = int(min(4096, max(256, np.ceil(2 * span / bw))))
    g, v = FFTKDE(bw=bw).fit(points).evaluate((grid, grid))
    xs = np.unique(g[:, 0])
    ys = np.unique(g[:, 1])
    f = RegularGridInterpolator(
        (xs, ys), v.reshape(len(xs), len(ys)), bounds_error=False, fill_value=0.0
    )
    return f(ev), f"bw = {bw:.3g}, grid {grid}^2"


def scott_bandwidth(points):
    """Scott's rule in data units: n^(-1/6) times the mean standard deviation of the axes
    (scikit-learn's bandwidth="scott" is the bare factor, for standardised data)."""
    return len(points) ** (-1 / 6) * float(points.std(axis=0).mean())


def sklearn_estimate(points, truth, ev):
    from sklearn.neighbors import KernelDensity

    bw = scott_bandwidth(points)
    kd = KernelDensity(bandwidth=bw, rtol=1e-4).fit(points)
    return np.exp(kd.score_samples(ev)), f"bw = {bw:.3g}"


METHODS = {
    "knnrefine": knnrefine_estimate,
    "gaussian_kde": scipy_estimate,
    "FFTKDE (ISJ)": fftkde_estimate,
    "FFTKDE (Silverman)": lambda p, t, e: fftkde_estimate(p, t, e, rule="Silverman"),
    "KernelDensity": sklearn_estimate,
}


def accuracy(sizes, seed=0):
    rows = []
    for truth in (Multiscale(), Hole(), VonMises()):
        rng = np.random.default_rng(seed)
        ev, f, q = l1_sample(truth, rng)
        for n in sizes:
            pts = truth.sample(n, np.random.default_rng(seed + 1))
            for name, method in METHODS.items():
                sub = np.arange(len(ev))
                if name in ("gaussian_kde", "KernelDensity") and n * len(ev) > 2e9:
                    sub = np.random.default_rng(seed + 2).choice(len(ev), int(2e9 // n), False)
                t0 = time.perf_counter()
                est, info = method(pts, truth, ev[sub])
                seconds = time.perf_counter() - t0
                l1 = float(np.mean(np.abs(est - f[sub]) / q[sub]))
                rows.append(
                    {
                        "truth": truth.name,
                        "n": n,
                        "method": name,
                        "L1": l1,
                        "seconds": seconds,
                        "info": info,
                        "sampled": len(sub) < len(ev),
                    }
                )
                print(
                    f"{truth.name[:34]:34s} n={n:.0e} {name:14s} L1 = {l1:.4f} "
                    f"{'~' if len(sub) < len(ev) else ' '} {seconds:7.2f} s  ({info})",
                    flush=True,
                )
    return rows


def grid_timing(n=100_000, shape=(512, 512), seed=0):
    truth = Multiscale()
    pts = truth.sample(n, np.random.default_rng(seed))
    ny, nx = shape
    xs = (np.arange(nx) + 0.5) / nx
    ys = (np.arange(ny) + 0.5) / ny
    gx, gy = np.meshgrid(xs, ys)
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    rows_part = grid[: 16 * nx]
    out = {}
    t0 = time.perf_counter()
    mesh = knnrefine.refine(pts, default_k(n))
    knnrefine.KnnDensity(mesh, pts).grid(shape)
    out["knnrefine"] = (time.perf_counter() - t0, False)
    t0 = time.perf_counter()
    gaussian_kde(pts.T)(rows_part.T)
    out["gaussian_kde"] = ((time.perf_counter() - t0) * ny / 16, True)
    t0 = time.perf_counter()
    from KDEpy import FFTKDE
    from KDEpy.bw_selection import improved_sheather_jones

    bw = float(np.mean([improved_sheather_jones(pts[:, [a]]) for a in range(2)]))
    FFTKDE(bw=bw).fit(pts).evaluate(shape)  # the grid asked for, whatever the bandwidth
    out["FFTKDE (ISJ)"] = (time.perf_counter() - t0, False)
    from sklearn.neighbors import KernelDensity

    t0 = time.perf_counter()
    KernelDensity(bandwidth=scott_bandwidth(pts), rtol=1e-4).fit(pts).score_samples(rows_part)
    out["KernelDensity"] = ((time.perf_counter() - t0) * ny / 16, True)
    for name, (s, scaled) in out.items():
        print(f"512 x 512 grid from n = {n:.0e}: {name:14s} {'~' if scaled else ' '}{s:8.2f} s")
    return out


def markdown(rows, timing):
    lines = ["| truth | n | " + " | ".join(METHODS) + " |", "|---|---:|" + "---:|" * len(METHODS)]
    keys = sorted({(r["truth"], r["n"]) for r in rows}, key=lambda t: (t[0], t[1]))
    order = [Multiscale.name, Hole.name, VonMises.name]
    keys.sort(key=lambda t: (order.index(t[0]), t[1]))
    for truth, n in keys:
        cells = []
        best = min(r["L1"] for r in rows if r["truth"] == truth and r["n"] == n)
        for name in METHODS:
            r = next(r for r in rows if r["truth"] == truth and r["n"] == n and r["method"] == name)
            cell = f"{r['L1']:.3f}{'~' if r['sampled'] else ''} ({r['seconds']:.2f} s)"
            cells.append(f"**{cell}**" if r["L1"] == best else cell)
        lines.append(f"| {truth} | {n:.0e} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("| 512 x 512 grid, n = 1e5 | " + " | ".join(timing) + " |")
    lines.append("|---|" + "---:|" * len(timing))
    lines.append(
        "| seconds | "
        + " | ".join(f"{'~' if scaled else ''}{s:.2f}" for s, scaled in timing.values())
        + " |"
    )
    lines.append("")
    lines.append("~: timed on part of the work and scaled (an extrapolation, not a measurement).")
    for name, (seconds, scaled) in timing.items():
        if name == "knnrefine":
            continue
        ratio = seconds / timing["knnrefine"][0]
        faster = f"{ratio:.1f}x slower" if ratio > 1 else f"{1 / ratio:.1f}x faster"
        lines.append(
            f"{name} is {faster} than knnrefine on the 512 x 512 grid"
            + (" (extrapolated)" if scaled else "")
            + "."
        )
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", nargs="+", type=float, default=[1e4, 1e5, 1e6])
    ap.add_argument("--out", default=os.path.join(HERE, "results", "density_accuracy.json"))
    args = ap.parse_args(argv)
    knnrefine.refine(np.random.default_rng(0).random((500, 2)), 10)  # warm the kernels
    rows = accuracy([int(n) for n in args.sizes])
    timing = grid_timing()
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump({"rows": rows, "grid_timing": timing}, f, indent=1)
    print()
    print(markdown(rows, timing))


if __name__ == "__main__":
    main()
