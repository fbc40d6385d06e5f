"""The kernels built with the package (portable code, numba's generic CPU) against kernels
compiled for this machine's CPU (issue 54), paired per kernel family: refine in each domain,
certify, the estimator in the plane and in space. Each run is a process of its own that loads
its kernels (none may compile: the count is printed), warms up once, then times the best
and the median of 3; the two sides alternate.

The portable side is a Python whose knnrefine was installed from a wheel built with its
kernels (``benchmarks/shipped_install.py`` makes one; or ``pip wheel .`` and a fresh
virtual environment); the host side is this interpreter with its own numba cache (compiled
here: run each family once first). ``--upgraded`` adds a third side: a Python with the same
build whose kernel sums were compiled for this CPU (``shipped.upgrade``, which the estimator
starts in the background after its first fit; here run to its end before timing): another
virtual environment with the same wheel installed. The portable side runs with
``KNNREFINE_HOST_KERNELS=0``, so that it keeps the portable code.

    python benchmarks/portable_code.py --portable /path/to/venv/bin/python \
        [--upgraded /path/to/venv2/bin/python] [--pairs 2]
"""

import argparse
import os
import subprocess
import sys

RUN = r"""
import sys, time
import numpy as np
from knnrefine._engine import shipped

compiled = shipped.compiles()
import knnrefine

rng = np.random.default_rng(0)
what = sys.argv[1]
if what == "refine, plane":
    pts = rng.random((300_000, 2))
    def f(): knnrefine.refine(pts, 20)
elif what == "refine, space":
    pts = rng.random((100_000, 3))
    def f(): knnrefine.refine(pts, 20)
elif what == "refine, sphere":
    pts = rng.random((200_000, 2)) * [360, 180] - [180, 90]
    def f(): knnrefine.refine(pts, 20, sphere=True)
elif what == "certify, plane":
    pts = rng.random((300_000, 2))
    mesh = knnrefine.refine(pts, 20)
    def f(): knnrefine.certify(mesh, pts)
elif what == "estimator, plane":
    pts = np.concatenate([rng.normal(0.5, 0.1, (150_000, 2)), rng.random((50_000, 2))])
    def f(): knnrefine.KnnDensityEstimator().fit(pts).grid()
elif what == "estimator, space":
    pts = rng.normal(0.5, 0.1, (100_000, 3))
    def f(): knnrefine.KnnDensityEstimator().fit(pts).grid((64, 64, 64))
f()
times = []
for _ in range(3):
    t = time.perf_counter()
    f()
    times.append(time.perf_counter() - t)
print("RESULT", min(times), sorted(times)[1], len(compiled))
"""

FAMILIES = ("refine, plane", "refine, space", "refine, sphere", "certify, plane",
            "estimator, plane", "estimator, space")  # fmt: skip


UPGRADE = """
from knnrefine._engine import shipped
import numpy as np, knnrefine
for dim in (3,):
    knnrefine.KnnDensityEstimator().fit(np.random.default_rng(0).random((3000, dim)))
print("UPGRADE", shipped.upgrade("kernel sums in space", wait=True))
"""


def one(python, family, env):
    out = subprocess.run([python, "-c", RUN, family], capture_output=True, text=True, env=env)
    if out.returncode:
        raise SystemExit(f"{python} {family}:\n{out.stderr[-3000:]}")
    best, median, compiled = out.stdout.split("RESULT")[1].split()
    return float(best), float(median), int(compiled)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--portable", required=True, help="a Python with a built knnrefine")
    ap.add_argument("--upgraded", help="a Python with the same build, its kernel sums upgraded")
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--families", nargs="+", default=list(FAMILIES), choices=FAMILIES)
    args = ap.parse_args(argv)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NUMBA_", "PYTHONPATH"))}
    env["KNNREFINE_HOST_KERNELS"] = "0"
    pythons = {"this CPU's code": sys.executable, "portable code": args.portable}
    if args.upgraded:
        pythons["portable, kernel sums upgraded"] = args.upgraded
        done = subprocess.run([args.upgraded, "-c", UPGRADE], capture_output=True, text=True,
                              env={**env, "KNNREFINE_HOST_KERNELS": "1"})  # fmt: skip
        print("upgrade:", done.stdout.split("UPGRADE")[-1].strip() or done.stderr[-2000:])
    names = list(pythons)
    print("| run | " + " | ".join(f"{n}: best (median)" for n in names) + " | "
          + " | ".join(f"{n} / this CPU's" for n in names[1:]) + " |")  # fmt: skip
    print("|---|" + "---|" * len(names) + "---:|" * (len(names) - 1))
    for family in args.families:
        times = {n: [] for n in names}
        for pair in range(args.pairs):
            order = names if pair % 2 == 0 else names[::-1]
            for n in order:
                times[n].append(one(pythons[n], family, env))
        cells = [", ".join(f"{b:.3f} ({m:.3f})" + (f" [{c} compiled]" if c else "")
                           for b, m, c in times[n]) for n in names]  # fmt: skip
        base = sum(b for b, _, _ in times[names[0]])
        ratios = [f"{sum(b for b, _, _ in times[n]) / base:.2f}" for n in names[1:]]
        print(f"| {family} | " + " | ".join(cells) + " | " + " | ".join(ratios) + " |", flush=True)


if __name__ == "__main__":
    main()
