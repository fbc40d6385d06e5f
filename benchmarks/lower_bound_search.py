"""Random search for meshes that break Theorem 6 (run by hand; issue 8's done criterion).

    python benchmarks/lower_bound_search.py                      # 990 periodic or mixed runs
    python benchmarks/lower_bound_search.py --modes all --runs 400 --seed 7
    python benchmarks/lower_bound_search.py --show 10            # print the first failures

Each run draws a box (square, strips 10:1 and 1:10, 3:1), a point set (uniform, Gaussian
blobs, a few points, a lattice, a line, duplicates), n in [2, 2000], k anywhere in [1, n] (half
the draws k >= n/2, where the initial mesh is hardest to satisfy), tau log-uniform in
[2.001, 50] and a periodic mode, then refines and certifies. A run ends one of three ways:
refused up front (InputError: the initial mesh cannot satisfy the theorem's precondition),
certified, or FAILED (which checks failed). The counts, by mode, are the figures quoted in the
issue notes; the exit status is 1 when any run failed.
"""

import argparse
import multiprocessing as mp
import time
import warnings
from collections import Counter

import numpy as np

import knnrefine

MODES = {"periodic": True, "x": (True, False), "y": (False, True), "plain": False}
SHAPES = [(1.0, 1.0), (0.1, 1.0), (1.0, 0.1), (3.0, 1.0), (360.0, 360.0)]


def draw(seed):
    """One configuration from its seed: (points, k, tau, periodic, box, label)."""
    rng = np.random.default_rng(seed)
    w, h = SHAPES[rng.integers(len(SHAPES))]
    x0, y0 = rng.choice([0.0, -0.5 * w, 1000.0]), rng.choice([0.0, -0.5 * h])
    n = int(np.exp(rng.uniform(np.log(2), np.log(2000))))
    kind = rng.choice(["uniform", "blobs", "few", "lattice", "line", "duplicates"])
    if kind == "uniform":
        u = rng.random((n, 2))
    elif kind == "blobs":
        c = rng.random((int(rng.integers(1, 5)), 2))
        u = c[rng.integers(len(c), size=n)] + rng.normal(0, rng.uniform(0.005, 0.1), (n, 2))
    elif kind == "few":
        n = int(rng.integers(2, 12))
        u = rng.random((n, 2))
    elif kind == "lattice":
        s = max(2, int(np.sqrt(n)))
        g = (np.arange(s) + 0.5) / s
        u = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    elif kind == "line":
        t = rng.random(n)
        u = np.stack([t, 0.3 + 0.4 * t], 1)
    else:
        base = rng.random((max(1, n // 5), 2))
        u = np.repeat(base, 5, axis=0)
    u = np.mod(u, 1.0)
    pts = np.array([x0, y0]) + u * [w, h]
    n = len(pts)
    if rng.random() < 0.5:
        k = int(rng.integers(max(1, n // 2), n + 1))
    else:
        k = int(np.exp(rng.uniform(0, np.log(n + 1))))
    k = max(2, min(k, n)) if n >= 2 else 1
    tau = float(np.exp(rng.uniform(np.log(2.001), np.log(50.0))))
    box = (x0, y0, x0 + w, y0 + h)
    return pts, k, tau, box, f"{kind} n={n} k={k} tau={tau:.3f} box={w:g}x{h:g}"


def one(job):
    warnings.simplefilter("ignore")  # FloorWarning: duplicates put whole data sets under it
    seed, mode = job
    pts, k, tau, box, label = draw(seed)
    periodic = MODES[mode]
    t0 = time.perf_counter()
    try:
        mesh = knnrefine.refine(
            pts, k, tau, periodic=periodic, box=box, max_vertices=400_000, time_limit=60
        )
    except knnrefine.InputError as exc:
        return seed, mode, label, "refused", str(exc).split(";")[0][:160], time.perf_counter() - t0
    except knnrefine.BudgetError as exc:
        return seed, mode, label, "budget", str(exc)[:120], time.perf_counter() - t0
    cert = knnrefine.certify(mesh, pts, samples=20_000, n_random=5_000)
    if cert.passed:
        return seed, mode, label, "certified", "", time.perf_counter() - t0
    what = []
    if not cert.triangulation_ok:
        what.append("triangulation")
    if cert.max_aspect > tau:
        what.append(f"aspect {cert.max_aspect:.4g}")
    if cert.max_cell_count >= k or cert.max_ball_count >= k:
        what.append(f"counts {cert.max_cell_count}/{cert.max_ball_count}")
    if cert.alpha_hat < cert.alpha:
        what.append(f"lower bound {cert.alpha_hat:.4g} < {cert.alpha:.4g}")
    if cert.beta_hat > cert.beta:
        what.append(f"upper bound {cert.beta_hat:.4g} > {cert.beta:.4g}")
    return seed, mode, label, "FAILED", ", ".join(what), time.perf_counter() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=990)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--modes", default="periodic,x,y", help="comma list of periodic, x, y, plain; or all"
    )
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--show", type=int, default=20, help="failures and refusals to print")
    args = ap.parse_args(argv)
    modes = list(MODES) if args.modes == "all" else args.modes.split(",")
    jobs = [(args.seed * 100_000 + i, modes[i % len(modes)]) for i in range(args.runs)]
    t0 = time.perf_counter()
    with mp.get_context("spawn").Pool(args.workers) as pool:
        results = pool.map(one, jobs, chunksize=4)
    tally = Counter((mode, outcome) for _, mode, _, outcome, _, _ in results)
    print(
        f"{args.runs} runs in {time.perf_counter() - t0:.0f} s (knnrefine {knnrefine.__version__})"
    )
    print(f"{'mode':10s} {'certified':>10s} {'refused':>8s} {'budget':>7s} {'FAILED':>7s}")
    for mode in modes:
        print(
            f"{mode:10s} {tally[mode, 'certified']:10d} {tally[mode, 'refused']:8d} "
            f"{tally[mode, 'budget']:7d} {tally[mode, 'FAILED']:7d}"
        )
    shown = Counter()
    for seed, mode, label, outcome, why, secs in results:
        if outcome in ("FAILED", "refused", "budget") and shown[outcome] < args.show:
            shown[outcome] += 1
            print(f"{outcome:9s} seed={seed} {mode:8s} {label}: {why} ({secs:.1f} s)")
    return 1 if tally_failed(tally) else 0


def tally_failed(tally):
    return sum(v for (mode, outcome), v in tally.items() if outcome == "FAILED")


if __name__ == "__main__":
    raise SystemExit(main())
