"""Density estimation: knnrefine's estimates against the truth and the usual tools.

    python benchmarks/density_accuracy.py                    # n = 1e4, 1e5, 1e6 (over an hour)
    python benchmarks/density_accuracy.py --sizes 1e4 1e5    # about 15 minutes
    python benchmarks/density_accuracy.py --truths ridge edge --sizes 1e5
    python benchmarks/density_accuracy.py --methods "knnrefine LSCV" --merge   # one method

Truths (each restricted to its box, normalised there):
* multiscale: a Gaussian mixture with widths 0.12, 0.02 and 0.003;
* hole: uniform on the unit square with a hole of radius 0.25;
* torus: two von Mises products on the torus [-pi, pi)^2;
* heavy: a product of two Student t marginals (3 degrees of freedom) on [-20, 20]^2;
* ridge: 90% on a circular arc (radius 0.3) with a Gaussian cross-section 0.002 wide, 10%
  uniform background;
* edge: half uniform on a disk of radius 0.2 (a jump of 4x the background at its rim), half
  uniform on the unit square;
* disc: uniform on a disk of radius 0.45, nothing outside it (a sharp edge to 0).

Scores, the same evaluation points for every method:
* L1 error, the integral of |estimate - truth| over the box, and the Hellinger distance
  sqrt(1/2 integral (sqrt(estimate) - sqrt(truth))^2), both by importance-sampled Monte
  Carlo (20,000 points drawn from 1/2 truth + 1/2 uniform), which resolves narrow features
  whatever a method's own grid;
* held-out log-likelihood: the mean log-density at 20,000 fresh points from the truth (-inf
  when a method gives one of them density 0).

Methods, each with its automatic smoothing, in the same run on the same points:
* knnrefine: ``KnnDensityEstimator`` with its defaults (the adaptive estimate, pilot
  k = 2 sqrt(n), sensitivity and bandwidth by leave-one-out likelihood) and the truth's
  box; "knnrefine local" the same with shape="local"; "knnrefine LSCV" the default with
  its smoothing chosen by least-squares cross-validation (criterion="least-squares", which
  aims at the integrated squared error, so at L1 and Hellinger rather than likelihood);
  "knnrefine kNN" the plain kNN estimate (method="knn"). Periodic on the torus.
* scipy gaussian_kde (Scott's rule);
* KDEpy FFTKDE on a grid of step bw / 2 (at most 4096 x 4096), interpolated (0 off the grid):
  KDEpy's automatic bandwidths are 1-D, so the isotropic bandwidth is the mean of the two
  marginals' bandwidths, by ISJ (Improved Sheather-Jones) and by Silverman's rule;
* scikit-learn KernelDensity (Gaussian, rtol 1e-4) with its bandwidth cross-validated:
  GridSearchCV (3 folds) over 13 bandwidths from 1/8 to 2 times Scott's rule, on at most
  20,000 of the points, the winner scaled by (20,000 / n)^(1/6) (the rule's rate) for the
  full sample.
Where n times the 40,000 evaluations exceeds 1.2e10 (n = 1e6: gaussian_kde's sums would
take many minutes per truth), every method is scored on the same random subset, 6,000 of
each kind of point at 1e6 (marked ~), so that the comparison stays paired. None of the
peers knows about the box or the torus.
"""

import argparse
import json
import os
import time

import numpy as np
from scipy.special import erf, i0
from scipy.stats import gaussian_kde
from scipy.stats import t as student

import knnrefine

HERE = os.path.dirname(os.path.abspath(__file__))


def rejection(n, draw, keep):
    """n points from batches draw() (n, 2), keeping the rows where keep(batch) holds."""
    out, got = [], 0
    while got < n:
        x = draw()
        x = x[keep(x)]
        out.append(x)
        got += len(x)
    return np.concatenate(out)[:n]


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
        def draw():
            c = rng.choice(3, n, p=self.W)
            return self.MU[c] + rng.normal(size=(n, 2)) * self.S[c][:, None]

        return rejection(n, draw, lambda x: (x >= 0).all(1) & (x <= 1).all(1))


class Hole:
    name = "uniform with a hole (radius 0.25)"
    box = (0.0, 0.0, 1.0, 1.0)
    periodic = False

    def pdf(self, x):
        outside = ((x - 0.5) ** 2).sum(1) > 0.25**2
        return outside / (1 - np.pi * 0.25**2)

    def sample(self, n, rng):
        return rejection(
            n, lambda: rng.random((2 * n, 2)), lambda x: ((x - 0.5) ** 2).sum(1) > 0.25**2
        )


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


class Heavy:
    name = "Student t (3 dof) product, heavy tails"
    box = (-20.0, -20.0, 20.0, 20.0)
    periodic = False
    DOF = 3

    def __init__(self):
        self.Z = (student.cdf(20, self.DOF) - student.cdf(-20, self.DOF)) ** 2

    def pdf(self, x):
        return student.pdf(x[:, 0], self.DOF) * student.pdf(x[:, 1], self.DOF) / self.Z

    def sample(self, n, rng):
        draw = lambda: rng.standard_t(self.DOF, (n, 2))  # noqa: E731
        return rejection(n, draw, lambda x: (np.abs(x) <= 20).all(1))


class Ridge:
    name = "thin curved ridge (width 0.002) over a background"
    box = (0.0, 0.0, 1.0, 1.0)
    periodic = False
    C = np.array([0.5, 0.3])
    RADIUS, WIDTH, T0, T1, ON = 0.3, 0.002, 0.2, 2.8, 0.9

    def pdf(self, x):
        d = x - self.C
        r = np.hypot(d[:, 0], d[:, 1])
        t = np.arctan2(d[:, 1], d[:, 0])
        across = np.exp(-0.5 * ((r - self.RADIUS) / self.WIDTH) ** 2)
        across /= np.sqrt(2 * np.pi) * self.WIDTH
        # uniform angle, Gaussian radius: density in the plane is that over r (polar area)
        arc = ((t >= self.T0) & (t <= self.T1)) * across / ((self.T1 - self.T0) * r)
        return self.ON * arc + (1 - self.ON)

    def sample(self, n, rng):
        on = rng.random(n) < self.ON
        m = int(on.sum())
        t = rng.uniform(self.T0, self.T1, m)
        r = self.RADIUS + self.WIDTH * rng.normal(size=m)
        x = rng.random((n, 2))
        x[on] = self.C + r[:, None] * np.column_stack([np.cos(t), np.sin(t)])
        return x


class Edge:
    name = "uniform disk (sharp edge) over a background"
    box = (0.0, 0.0, 1.0, 1.0)
    periodic = False
    R = 0.2

    def pdf(self, x):
        inside = ((x - 0.5) ** 2).sum(1) <= self.R**2
        return 0.5 * inside / (np.pi * self.R**2) + 0.5

    def sample(self, n, rng):
        on = rng.random(n) < 0.5
        disk = uniform_disk(int(on.sum()), self.R, rng)  # drawn first: the study's stream
        x = rng.random((n, 2))
        x[on] = disk
        return x


def uniform_disk(n, radius, rng):
    """n points uniform on the disk of ``radius`` about (0.5, 0.5)."""
    r = radius * np.sqrt(rng.random(n))
    t = rng.random(n) * 2 * np.pi
    return 0.5 + r[:, None] * np.column_stack([np.cos(t), np.sin(t)])


class Disc:
    name = "uniform disk (radius 0.45), nothing outside it"
    box = (0.0, 0.0, 1.0, 1.0)
    periodic = False
    R = 0.45

    def pdf(self, x):
        return (((x - 0.5) ** 2).sum(1) <= self.R**2) / (np.pi * self.R**2)

    def sample(self, n, rng):
        return uniform_disk(n, self.R, rng)


TRUTHS = {
    "multiscale": Multiscale,
    "hole": Hole,
    "torus": VonMises,
    "heavy": Heavy,
    "ridge": Ridge,
    "edge": Edge,
    "disc": Disc,
}


def evaluation_points(truth, rng, size=20000):
    """(points, truth's pdf there, proposal density q) for the importance-sampled integrals:
    half from the truth, half uniform on the box."""
    lo, hi = np.array(truth.box[:2]), np.array(truth.box[2:])
    half = rng.random(size) < 0.5
    x = np.where(half[:, None], truth.sample(size, rng), lo + rng.random((size, 2)) * (hi - lo))
    q = 0.5 * truth.pdf(x) + 0.5 / np.prod(hi - lo)
    return x, truth.pdf(x), q


def knnrefine_estimate(points, truth, ev, **options):
    est = knnrefine.KnnDensityEstimator(box=truth.box, periodic=truth.periodic, **options)
    est.fit(points)
    info = f"k = {est.k_}, m = {len(est.mesh_.vertices)}"
    if getattr(est, "bandwidth_", None) is not None:
        info += f", c = {est.bandwidth_:.3g}, alpha = {est.sensitivity_:.2g}"
    return np.exp(est.score_samples(ev)), info


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
    return np.maximum(f(ev), 0.0), f"bw = {bw:.3g}, grid {grid}^2"


def scott_bandwidth(points):
    """Scott's rule in data units: n^(-1/6) times the mean standard deviation of the axes
    (scikit-learn's bandwidth="scott" is the bare factor, for standardised data)."""
    return len(points) ** (-1 / 6) * float(points.std(axis=0).mean())


def sklearn_estimate(points, truth, ev, cv_points=20000):
    """KernelDensity with its bandwidth chosen by 3-fold GridSearchCV on at most cv_points
    points, scaled to the full sample by the n^(-1/6) rate."""
    from sklearn.model_selection import GridSearchCV
    from sklearn.neighbors import KernelDensity

    rng = np.random.default_rng(0)
    sub = points if len(points) <= cv_points else points[rng.choice(len(points), cv_points)]
    grid = scott_bandwidth(sub) * np.geomspace(1 / 8, 2, 13)
    search = GridSearchCV(KernelDensity(rtol=1e-4), {"bandwidth": grid}, cv=3).fit(sub)
    bw = search.best_params_["bandwidth"] * (len(sub) / len(points)) ** (1 / 6)
    kd = KernelDensity(bandwidth=bw, rtol=1e-4).fit(points)
    return np.exp(kd.score_samples(ev)), f"bw = {bw:.3g}"


def knn_plain(points, truth, ev):
    return knnrefine_estimate(points, truth, ev, method="knn")


def knn_local(points, truth, ev):
    return knnrefine_estimate(points, truth, ev, shape="local")


def knn_least_squares(points, truth, ev):
    return knnrefine_estimate(points, truth, ev, criterion="least-squares")


METHODS = {
    "knnrefine": knnrefine_estimate,
    "knnrefine local": knn_local,
    "knnrefine LSCV": knn_least_squares,
    "knnrefine kNN": knn_plain,
    "gaussian_kde": scipy_estimate,
    "FFTKDE (ISJ)": fftkde_estimate,
    "FFTKDE (Silverman)": lambda p, t, e: fftkde_estimate(p, t, e, rule="Silverman"),
    "KernelDensity (CV)": sklearn_estimate,
}
BUDGET = 1.2e10  # n times evaluations above which every method is scored on a subset


def accuracy(truths, sizes, seed=0, out=None, methods=None, merge=False):
    """Score ``methods`` (default: all) on each truth and size; with ``merge``, the rows are
    added to those already in ``out`` (replacing rows of the same truth, n and method), so a
    method or a size can be re-run alone."""
    methods = list(METHODS) if methods is None else methods
    kept = []
    if merge and out and os.path.exists(out):
        with open(out) as fh:
            kept = json.load(fh)["rows"]
    rows = []

    def save():
        done = {(r["key"], r["n"], r["method"]) for r in rows}
        old = [r for r in kept if (r["key"], r["n"], r["method"]) not in done]
        with open(out, "w") as fh:
            json.dump({"rows": old + rows}, fh, indent=1)

    for key in truths:
        truth = TRUTHS[key]()
        rng = np.random.default_rng(seed)
        ev, f, q = evaluation_points(truth, rng)
        test = truth.sample(len(ev), np.random.default_rng(seed + 3))
        both = np.concatenate([ev, test])
        for n in sizes:
            pts = truth.sample(n, np.random.default_rng(seed + 1))
            sub = np.arange(len(both))
            if n * len(both) > BUDGET:  # the same subset for every method
                half = int(BUDGET / 2 // n)
                pick = np.random.default_rng(seed + 2)
                sub = np.concatenate(
                    [pick.choice(len(ev), half, False), len(ev) + pick.choice(len(ev), half, False)]
                )
            for name in methods:
                method = METHODS[name]
                t0 = time.perf_counter()
                est, info = method(pts, truth, both[sub])
                seconds = time.perf_counter() - t0
                on_ev = sub < len(ev)
                e, fe, qe = est[on_ev], f[sub[on_ev]], q[sub[on_ev]]
                l1 = float(np.mean(np.abs(e - fe) / qe))
                hellinger = float(np.sqrt(0.5 * np.mean((np.sqrt(e) - np.sqrt(fe)) ** 2 / qe)))
                with np.errstate(divide="ignore"):
                    ll = float(np.mean(np.log(est[~on_ev])))
                row = {
                    "truth": truth.name, "key": key, "n": n, "method": name, "L1": l1,
                    "hellinger": hellinger, "loglik": ll, "seconds": seconds, "info": info,
                    "sampled": len(sub) < len(both),
                }  # fmt: skip
                rows.append(row)
                print(
                    f"{key:10s} n={n:.0e} {name:18s} L1 {l1:.4f} H {hellinger:.4f} "
                    f"LL {ll:9.4f} {'~' if row['sampled'] else ' '} {seconds:7.2f} s  ({info})",
                    flush=True,
                )
                if out:  # keep what is done (a long run can be stopped)
                    save()
    if out and merge:
        with open(out) as fh:
            return json.load(fh)["rows"]
    return rows


def markdown(rows):
    """One table per score: rows (truth, n), a column per method, the best in bold."""
    out = []
    keys = sorted(
        {(r["key"], r["n"]) for r in rows}, key=lambda kn: (list(TRUTHS).index(kn[0]), kn[1])
    )
    for score, label, better in (
        ("L1", "L1 error (lower is better)", min),
        ("hellinger", "Hellinger distance (lower is better)", min),
        ("loglik", "held-out log-likelihood per point (higher is better)", max),
    ):
        out += [f"{label}:", ""]
        out.append("| truth | n | " + " | ".join(METHODS) + " |")
        out.append("|---|---:|" + "---:|" * len(METHODS))
        for key, n in keys:
            got = {r["method"]: r for r in rows if r["key"] == key and r["n"] == n}
            best = better(r[score] for r in got.values())
            cells = []
            for name in METHODS:
                if name not in got:
                    cells.append("")
                    continue
                r = got[name]
                cell = f"{r[score]:.3f}{'~' if r['sampled'] else ''}"
                cells.append(f"**{cell}**" if r[score] == best else cell)
            out.append(f"| {key} | {n:.0e} | " + " | ".join(cells) + " |")
        out.append("")
    out.append("| seconds (fit + evaluate) | n | " + " | ".join(METHODS) + " |")
    out.append("|---|---:|" + "---:|" * len(METHODS))
    for key, n in keys:
        got = {r["method"]: r for r in rows if r["key"] == key and r["n"] == n}
        cells = [f"{got[m]['seconds']:.2f}" if m in got else "" for m in METHODS]
        out.append(f"| {key} | {n:.0e} | " + " | ".join(cells) + " |")
    out.append("")
    sub = int(BUDGET / 2 // 1e6)
    out.append(
        f"~: every method scored on the same random subset ({sub:,} + {sub:,} points at n = 1e6)."
    )
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", nargs="+", type=float, default=[1e4, 1e5, 1e6])
    ap.add_argument("--truths", nargs="+", choices=list(TRUTHS), default=list(TRUTHS))
    ap.add_argument("--methods", nargs="+", choices=list(METHODS), default=list(METHODS))
    ap.add_argument("--out", default=os.path.join(HERE, "results", "density_accuracy.json"))
    ap.add_argument(
        "--merge", action="store_true", help="add to the rows already in --out (same truth, n "
        "and method replaced) instead of starting afresh",
    )  # fmt: skip
    args = ap.parse_args(argv)
    knnrefine.KnnDensityEstimator(k=10).fit(np.random.default_rng(0).random((500, 2)))  # warm
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    sizes = [int(n) for n in args.sizes]
    rows = accuracy(args.truths, sizes, out=args.out, methods=args.methods, merge=args.merge)
    print()
    print(markdown(rows))


if __name__ == "__main__":
    main()
