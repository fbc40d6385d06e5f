"""The sphere: knnrefine against what users do instead, for speed and for accuracy.

Speed (``--part speed``): ``knnrefine.refine(lonlat, k, sphere=True)`` on n points, uniform
on the sphere or clustered (a mixture of 30 von Mises-Fisher caps whose widths span two orders
of magnitude, over a 10% uniform background), against scipy's cKDTree k-th-neighbour
distance at every point on their unit vectors (build + ``query(points, k=[k], workers=-1)``,
both cores: the issue's baseline), HEALPix binning (healpy: ``ang2pix`` + ``bincount`` at the
resolution whose pixels hold about k points on average, the quick picture astronomers draw)
and, at n <= 10^5, scipy's SphericalVoronoi of the points (the other mesh a user could
make; on clustered points it refuses "duplicate generators" within its tolerance, and is
reported as refused). Each configuration runs in a fresh subprocess after one untimed
warm-up call; the tools alternate --repeat times and the medians are reported, with
refine's peak resident memory above the process' before the call per mesh vertex, and that
peak less the counting
index over the points (their unit vectors and the tree: about 30 bytes a point, whatever
the mesh) per mesh vertex: the mesh's own memory, the plane's budget being 300 bytes.

Accuracy (``--part accuracy``): known densities on the unit sphere, at n points, scored at
4,000 draws from the truth by L1 = mean |f_hat / f - 1| (inside the support for the band and
the cap) and the held-out mean log-likelihood: knnrefine's default estimate
(``KnnDensityEstimator(sphere=True)``: adaptive kernels, the smoothing by leave-one-out
likelihood), its kNN density (``KnnDensity``, default k = sqrt(n) / 2), scikit-learn's
``KernelDensity(metric="haversine")`` (Gaussian, bandwidth by 5-fold likelihood cross-
validation over 8 values on a 2,000-point subsample: "KDE-CV"), and HEALPix histograms
(nside with about sqrt(n) points per pixel). The truths: a mixture of two von Mises-Fisher
components (one across the antimeridian, one near the north pole), the band |lat| <= 20 and
the polar cap of radius 30 degrees. Seconds are each method's whole fit + evaluation.

    python benchmarks/bench_sphere.py --part speed --sizes 1e5 1e6 --ks 10 100 --repeat 3
    python benchmarks/bench_sphere.py --part accuracy --sizes 1e4 1e5

Needs healpy for its columns (``pip install healpy``; they are left out without it) and
scikit-learn for KDE-CV (``pip install 'knnrefine[sklearn]'``).
"""

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_refine import _status_mb, _trim, machine, reset_peak  # noqa: E402


def unit_of(lonlat):
    lon, lat = np.radians(lonlat[:, 0]), np.radians(lonlat[:, 1])
    c = np.cos(lat)
    return np.column_stack([c * np.cos(lon), c * np.sin(lon), np.sin(lat)])


def lonlat_of(x):
    return np.column_stack(
        [np.degrees(np.arctan2(x[:, 1], x[:, 0])), np.degrees(np.arcsin(np.clip(x[:, 2], -1, 1)))]
    )


def vmf(n, mu, kappa, rng):
    """n unit vectors from the von Mises-Fisher distribution about the unit vector mu."""
    u = rng.random(n)
    w = 1.0 + np.log(u + (1.0 - u) * np.exp(-2.0 * kappa)) / kappa
    phi = rng.uniform(0, 2 * np.pi, n)
    a = np.cross(mu, [0.0, 0.0, 1.0] if abs(mu[2]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(mu, a)
    s = np.sqrt(np.maximum(1 - w * w, 0))[:, None]
    return w[:, None] * mu + s * (np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * b)


def uniform_unit(n, rng):
    x = rng.standard_normal((n, 3))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def make_points(kind, n, seed=0):
    """(n, 2) lon/lat degrees: uniform, or 30 vMF caps (kappa 10^2..10^6) + 10% uniform."""
    rng = np.random.default_rng(seed)
    if kind == "uniform":
        return lonlat_of(uniform_unit(n, rng))
    centres = uniform_unit(30, rng)
    kappas = 10 ** rng.uniform(2, 6, 30)
    counts = rng.multinomial(n - n // 10, rng.dirichlet(np.ones(30)))
    parts = [vmf(m, c, kp, rng) for c, kp, m in zip(centres, kappas, counts, strict=True)]
    return lonlat_of(np.concatenate(parts + [uniform_unit(n // 10, rng)]))


def healpix_counts(unit, k):
    """HEALPix binning at the nside whose pixels hold about k points on average."""
    import healpy as hp

    npix = max(12, len(unit) / k)
    nside = int(2 ** max(0, round(np.log2(np.sqrt(npix / 12)))))
    pix = hp.vec2pix(nside, unit[:, 0], unit[:, 1], unit[:, 2])
    return np.bincount(pix, minlength=hp.nside2npix(nside)), nside


def speed_worker(kind, n, k, repeat):
    from scipy.spatial import SphericalVoronoi, cKDTree

    import knnrefine

    pts = make_points(kind, n)
    try:
        import healpy  # noqa: F401

        have_healpy = True
    except ImportError:
        have_healpy = False
    knnrefine.refine(pts[:2000], 10, sphere=True)  # warm-up: kernels loaded or compiled
    times = {"refine": [], "cKDTree": [], "healpix": [], "SphericalVoronoi": []}
    peak = []
    mesh = None
    for _ in range(repeat):
        _trim()
        before = _status_mb("VmRSS")
        reset_peak()
        t0 = time.perf_counter()
        mesh = knnrefine.refine(pts, k, sphere=True)
        times["refine"].append(time.perf_counter() - t0)
        peak.append(_status_mb("VmHWM") - before)
        mesh_m = len(mesh.vertices)
        tree = mesh.index  # the counting index over the points' unit vectors (kept)
        index_mb = sum(a.nbytes for a in (tree.pts, tree.box, tree.node, tree.split)) / 2**20
        t0 = time.perf_counter()
        unit = unit_of(pts)
        cKDTree(unit).query(unit, k=[k], workers=-1)
        times["cKDTree"].append(time.perf_counter() - t0)
        if have_healpy:
            t0 = time.perf_counter()
            healpix_counts(unit_of(pts), k)
            times["healpix"].append(time.perf_counter() - t0)
        if n <= 100_000:
            t0 = time.perf_counter()
            try:
                SphericalVoronoi(np.unique(unit_of(pts), axis=0)).sort_vertices_of_regions()
                times["SphericalVoronoi"].append(time.perf_counter() - t0)
            except ValueError:  # "Duplicate generators present": points within its tolerance
                times["SphericalVoronoi"].append(float("nan"))
    med = {key: float(np.median(v)) for key, v in times.items() if v}
    return {
        "kind": kind,
        "n": n,
        "k": k,
        "m": mesh_m,
        "seconds": med,
        "refine_over_ckdtree": med["refine"] / med["cKDTree"],
        "peak_mb": float(np.median(peak)),
        "bytes_per_vertex": float(np.median(peak)) * 2**20 / mesh_m,
        "index_mb": index_mb,
        "mesh_bytes_per_vertex": (float(np.median(peak)) - index_mb) * 2**20 / mesh_m,
    }


def speed(args):
    rows = []
    print(f"# {machine()['cpu']}, {os.cpu_count()} cores; medians of {args.repeat}")
    head = ("points", "n", "k", "m", "refine", "cKDTree", "ratio", "HEALPix", "SphVor",
            "B/vertex", "less index")  # fmt: skip
    widths = (10, 9, 5, 8, 8, 8, 6, 8, 8, 9, 10)
    print(" ".join(f"{h:>{w}}" for h, w in zip(head, widths, strict=True)))
    for kind in args.kinds:
        for n in args.sizes:
            for k in args.ks:
                out = subprocess.run(
                    [sys.executable, __file__, "--worker", kind, str(int(n)), str(k),
                     str(args.repeat)],
                    capture_output=True, text=True, check=True,
                )  # fmt: skip
                row = json.loads(out.stdout.strip().splitlines()[-1])
                rows.append(row)
                s = row["seconds"]
                hp = f"{s['healpix']:.3f}" if "healpix" in s else "-"
                sv = s.get("SphericalVoronoi")
                sv = "-" if sv is None else "refused" if np.isnan(sv) else f"{sv:.2f}"
                print(f"{kind:>10} {row['n']:>9,} {k:>5} {row['m']:>8,} {s['refine']:>8.3f} "
                      f"{s['cKDTree']:>8.3f} {row['refine_over_ckdtree']:>6.3f} {hp:>8} "
                      f"{sv:>8} {row['bytes_per_vertex']:>9.0f} "
                      f"{row['mesh_bytes_per_vertex']:>10.0f}", flush=True)  # fmt: skip
    return rows


# -- accuracy ---------------------------------------------------------------------------------
def vmf_pdf(x, mu, kappa):
    return kappa / (2 * np.pi * (1 - np.exp(-2 * kappa))) * np.exp(kappa * (x @ mu - 1))


class Truth:
    def __init__(self, name):
        self.name = name
        self.mus = unit_of(np.array([[175.0, 10.0], [30.0, 75.0]]))

    def sample(self, n, rng):
        if self.name == "mixture":
            m = rng.binomial(n, 0.6)
            return np.concatenate([vmf(m, self.mus[0], 40.0, rng),
                                   vmf(n - m, self.mus[1], 150.0, rng)])  # fmt: skip
        if self.name == "band":
            z = rng.uniform(-np.sin(np.radians(20)), np.sin(np.radians(20)), n)
        else:
            z = rng.uniform(np.cos(np.radians(30)), 1.0, n)
        phi = rng.uniform(0, 2 * np.pi, n)
        r = np.sqrt(1 - z * z)
        return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])

    def pdf(self, x):
        if self.name == "mixture":
            return 0.6 * vmf_pdf(x, self.mus[0], 40.0) + 0.4 * vmf_pdf(x, self.mus[1], 150.0)
        if self.name == "band":
            edge = np.sin(np.radians(20))
            return (np.abs(x[:, 2]) <= edge) / (4 * np.pi * edge)
        return (x[:, 2] >= np.cos(np.radians(30))) / (2 * np.pi * (1 - np.cos(np.radians(30))))


def score(fhat, f):
    """(L1 = mean |fhat / f - 1|, mean log fhat) at draws from f."""
    return float(np.mean(np.abs(fhat / f - 1))), float(np.mean(np.log(np.maximum(fhat, 1e-300))))


def knnrefine_fit(unit, probes):
    """The default estimate: ``KnnDensityEstimator(sphere=True)``, adaptive kernels with the
    smoothing by leave-one-out likelihood."""
    import knnrefine

    est = knnrefine.KnnDensityEstimator(sphere=True).fit(lonlat_of(unit))
    return np.exp(est.score_samples(lonlat_of(probes)))


def knn_fit(unit, probes):
    """The plain kNN estimate, ``KnnDensity`` at its default k."""
    import knnrefine
    from knnrefine.density import KnnDensity

    lonlat = lonlat_of(unit)
    mesh = knnrefine.refine(lonlat, None, sphere=True)
    return KnnDensity(mesh, lonlat)(lonlat_of(probes))


def kde_cv_fit(unit, probes, rng):
    from sklearn.model_selection import GridSearchCV
    from sklearn.neighbors import KernelDensity

    latlon = np.radians(lonlat_of(unit)[:, ::-1])
    sub = latlon[rng.choice(len(latlon), min(2000, len(latlon)), replace=False)]
    grid = GridSearchCV(KernelDensity(metric="haversine", algorithm="ball_tree"),
                        {"bandwidth": np.geomspace(0.005, 0.3, 8)}, cv=5)  # fmt: skip
    grid.fit(sub)
    kde = KernelDensity(metric="haversine", algorithm="ball_tree",
                        bandwidth=grid.best_params_["bandwidth"]).fit(latlon)  # fmt: skip
    return np.exp(kde.score_samples(np.radians(lonlat_of(probes)[:, ::-1])))


def healpix_fit(unit, probes):
    import healpy as hp

    counts, nside = healpix_counts(unit, np.sqrt(len(unit)))
    area = 4 * np.pi / hp.nside2npix(nside)
    pix = hp.vec2pix(nside, probes[:, 0], probes[:, 1], probes[:, 2])
    return counts[pix] / (len(unit) * area)


def accuracy(args):
    rng = np.random.default_rng(0)
    methods = {"knnrefine": lambda u, p: knnrefine_fit(u, p),
               "kNN": lambda u, p: knn_fit(u, p),
               "KDE-CV": lambda u, p: kde_cv_fit(u, p, rng),
               "HEALPix": lambda u, p: healpix_fit(u, p)}  # fmt: skip
    rows = []
    print(f"# {machine()['cpu']}, {os.cpu_count()} cores")
    knnrefine_fit(Truth("cap").sample(2000, rng), Truth("cap").sample(10, rng))  # warm-up
    print(f"{'truth':>8} {'n':>8} {'method':>10} {'L1':>7} {'loglik':>8} {'seconds':>8}")
    for name in ("mixture", "band", "cap"):
        truth = Truth(name)
        for n in args.sizes:
            unit = truth.sample(int(n), np.random.default_rng(1))
            probes = truth.sample(4000, np.random.default_rng(2))
            f = truth.pdf(probes)
            for method, fit in methods.items():
                try:
                    t0 = time.perf_counter()
                    fhat = fit(unit, probes)
                    seconds = time.perf_counter() - t0
                except ImportError as exc:
                    print(f"{name:>8} {int(n):>8,} {method:>10}  skipped ({exc.name} missing)")
                    continue
                l1, ll = score(fhat, f)
                rows.append({"truth": name, "n": int(n), "method": method, "L1": l1,
                             "loglik": ll, "seconds": seconds})  # fmt: skip
                print(f"{name:>8} {int(n):>8,} {method:>10} {l1:>7.4f} {ll:>8.3f} "
                      f"{seconds:>8.2f}", flush=True)  # fmt: skip
    return rows


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        kind, n, k, repeat = sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
        print(json.dumps(speed_worker(kind, n, k, repeat)))
        return
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--part", choices=("speed", "accuracy"), default="speed")
    p.add_argument("--sizes", type=float, nargs="+", default=[1e5, 1e6])
    p.add_argument("--ks", type=int, nargs="+", default=[10, 100])
    p.add_argument("--kinds", nargs="+", default=["uniform", "clustered"])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--out", help="write the rows as JSON here")
    args = p.parse_args()
    rows = speed(args) if args.part == "speed" else accuracy(args)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"machine": machine(), "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
