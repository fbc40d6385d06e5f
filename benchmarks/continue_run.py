"""Points that keep arriving (issue 55): a mesh continued with a batch of new points
(``refine(points, start=mesh)``) against a fresh refine of all of them, in one warm process,
for batches of 0.1 % to 50 % of the points, clustered in a new place. Each pair alternates
which runs first; medians of ``--repeat``. ``--stream N`` then adds N batches of 1 % one
after another and compares the last mesh with a fresh run (size; ``--certify`` certifies it).

    python benchmarks/continue_run.py [--n 1e6] [--k 10] [--repeat 3] [--stream 100]

Only the plane so far (space and the sphere: not yet).
"""

import argparse
import statistics
import time

import numpy as np

import knnrefine

BOX = (0.0, 0.0, 1.0, 1.0)


def points(n, rng):
    """Half uniform, half a wide normal blob: the start's points."""
    half = n // 2
    blob = np.clip(rng.normal(0.6, 0.1, (n - half, 2)), 0.0, 1.0)
    return np.concatenate([rng.random((half, 2)), blob])


def batch(b, rng, spread=0.02):
    """b new points clustered in one new place."""
    return np.clip(rng.normal(rng.uniform(0.1, 0.9, 2), spread, (b, 2)), 0.0, 1.0)


def timed(f):
    t = time.perf_counter()
    out = f()
    return time.perf_counter() - t, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=float, default=1e6)
    ap.add_argument("--k", type=float, default=None, help="default: refine's (sqrt(n) / 2)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--fractions", type=float, nargs="+", default=[0.001, 0.01, 0.1, 0.5])
    ap.add_argument("--stream", type=int, default=0, help="batches of 1 %% one after another")
    ap.add_argument("--certify", action="store_true")
    args = ap.parse_args(argv)
    n = int(args.n)
    rng = np.random.default_rng(0)
    first = points(n, rng)
    k = args.k if args.k is not None else knnrefine.density.default_k(n)
    start = knnrefine.refine(first, k, box=BOX)
    knnrefine.refine(np.concatenate([first, batch(10, rng)]), start=start)  # warm
    print(f"n = {n:,}, k = {k:g}, start: {start.stats.m:,} vertices")
    print("| batch | fresh refine (s) | continued (s) | continued / fresh | reopened triangles |")
    print("|---|---:|---:|---:|---:|")
    for fraction in args.fractions:
        every = np.concatenate([first, batch(max(1, int(fraction * n)), rng)])
        fresh, cont, reopened = [], [], 0
        for r in range(args.repeat):
            runs = [("fresh", lambda every=every: knnrefine.refine(every, k, box=BOX)),
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
            pts = np.concatenate([pts, batch(max(1, n // 100), rng, 0.05)])
            t, mesh = timed(lambda pts=pts, mesh=mesh: knnrefine.refine(pts, start=mesh))
            seconds.append(t)
        t_fresh, fresh = timed(lambda: knnrefine.refine(pts, k, box=BOX))
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
