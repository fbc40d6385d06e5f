"""Points that keep arriving (issue 55): a mesh continued with a batch of new points
(``refine(points, start=mesh)``) against a fresh refine of all of them, in one warm process,
for batches of 0.1 % to 50 % of the points, clustered in a new place. Each pair alternates
which runs first; medians of ``--repeat``. ``--stream N`` then adds N batches of 1 % one
after another and compares the last mesh with a fresh run (size; ``--certify`` certifies it).

    python benchmarks/continue_run.py [--domain plane|space|sphere] [--n 1e6] [--k 10]
        [--repeat 3] [--stream 100] [--certify]

The plane in the unit square, space in the unit cube, the sphere with points in
(longitude, latitude); the default k is refine's (sqrt(n) / 2).
"""

import argparse
import statistics
import time

import numpy as np

import knnrefine

BOXES = {"plane": (0.0, 0.0, 1.0, 1.0), "space": (0.0, 0.0, 0.0, 1.0, 1.0, 1.0)}


def points(domain, n, rng):
    """Half uniform, half a wide normal blob: the start's points."""
    half = n // 2
    if domain == "sphere":
        uniform = np.column_stack([rng.uniform(-180, 180, half),
                                   np.degrees(np.arcsin(rng.uniform(-1, 1, half)))])  # fmt: skip
        blob = np.column_stack([rng.normal(20, 10, n - half),
                                np.clip(rng.normal(40, 10, n - half), -90, 90)])  # fmt: skip
        return np.concatenate([uniform, blob])
    d = 2 if domain == "plane" else 3
    blob = np.clip(rng.normal(0.6, 0.1, (n - half, d)), 0.0, 1.0)
    return np.concatenate([rng.random((half, d)), blob])


def batch(domain, b, rng, spread=0.02):
    """b new points clustered in one new place."""
    if domain == "sphere":
        centre = (rng.uniform(-170, 170), rng.uniform(-60, 60))
        lat = np.clip(rng.normal(centre[1], 100 * spread, b), -90, 90)
        return np.column_stack([rng.normal(centre[0], 100 * spread, b), lat])
    d = 2 if domain == "plane" else 3
    return np.clip(rng.normal(rng.uniform(0.1, 0.9, d), spread, (b, d)), 0.0, 1.0)


def fresh_run(domain, pts, k):
    if domain == "sphere":
        return knnrefine.refine(pts, k, sphere=True)
    return knnrefine.refine(pts, k, box=BOXES[domain])


def timed(f):
    t = time.perf_counter()
    out = f()
    return time.perf_counter() - t, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--domain", choices=["plane", "space", "sphere"], default="plane")
    ap.add_argument("--n", type=float, default=1e6)
    ap.add_argument("--k", type=float, default=None, help="default: refine's (sqrt(n) / 2)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.001, 0.01, 0.1, 0.5])
    ap.add_argument("--stream", type=int, default=0, help="batches of 1 %% one after another")
    ap.add_argument("--certify", action="store_true")
    args = ap.parse_args(argv)
    n = int(args.n)
    rng = np.random.default_rng(0)
    domain = args.domain
    first = points(domain, n, rng)
    k = args.k if args.k is not None else knnrefine.density.default_k(n)
    start = fresh_run(domain, first, k)
    knnrefine.refine(np.concatenate([first, batch(domain, 10, rng)]), start=start)  # warm
    print(f"{domain}, n = {n:,}, k = {k:g}, start: {start.stats.m:,} vertices")
    print("| batch | fresh refine (s) | continued (s) | continued / fresh | reopened cells |")
    print("|---|---:|---:|---:|---:|")
    for fraction in args.fractions:
        every = np.concatenate([first, batch(domain, max(1, int(fraction * n)), rng)])
        fresh, cont, reopened = [], [], 0
        for r in range(args.repeat):
            runs = [("fresh", lambda every=every: fresh_run(domain, every, k)),
                    ("cont", lambda every=every: knnrefine.refine(every, start=start))]  # fmt: skip
            for name, f in runs if r % 2 == 0 else runs[::-1]:
                seconds, mesh = timed(f)
                (fresh if name == "fresh" else cont).append(seconds)
                if name == "cont":
                    reopened = mesh.stats.continued["reopened"]
        f, c = statistics.median(fresh), statistics.median(cont)
        print(f"| {fraction:.1%} | {f:.3f} | {c:.3f} | {c / f:.3f} | {reopened:,} |", flush=True)
    if args.stream:
        pts, mesh, seconds = first, start, []
        for _ in range(args.stream):
            pts = np.concatenate([pts, batch(domain, max(1, n // 100), rng, 0.05)])
            t, mesh = timed(lambda pts=pts, mesh=mesh: knnrefine.refine(pts, start=mesh))
            seconds.append(t)
        t_fresh, fresh = timed(lambda: fresh_run(domain, pts, k))
        print(f"stream of {args.stream} batches of 1 %: {len(pts):,} points, continued "
              f"{mesh.stats.m:,} vertices against {fresh.stats.m:,} fresh "
              f"({mesh.stats.m / fresh.stats.m - 1:+.1%}); a batch took "
              f"{statistics.median(seconds):.3f} s (median), a fresh run of all "
              f"{t_fresh:.3f} s")  # fmt: skip
        if args.certify:
            cert = knnrefine.certify(mesh, pts)
            print(f"the stream's last mesh: certificate {'PASSED' if cert.passed else 'FAILED'}")


if __name__ == "__main__":
    main()
