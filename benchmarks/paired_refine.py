"""Before/after timing of refine: the same command alternating between two source trees
(this checkout's ``src`` and another's, e.g. a ``git worktree`` of an earlier commit), each
run in a fresh process after a warm-up call on 20,000 of the points, refine only, medians
over --repeat pairs. Mesh sizes are printed too (the same when a change leaves the moves
alone). ``--dim 3``: the periodic unit cube, ``bench_refine3.py``'s points (``--ordinary``:
the cube not periodic); ``--dim 2``: the unit square (not periodic), ``bench_refine.py``'s
points; ``--sphere``: the sphere, ``bench_sphere.py``'s points; ``--workers``: refine's.

    git worktree add /tmp/before <commit>
    python benchmarks/paired_refine.py --before /tmp/before/src --dim 3 --n 1e6 --k 10 \\
        --kind uniform --repeat 3
"""

import argparse
import os
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def one(dim, kind, n, k, workers, ordinary=False, sphere=False):
    sys.path.insert(0, HERE)
    import knnrefine

    if sphere:
        from bench_sphere import make_points as sphere_points

        pts, where = sphere_points(kind, n), {"sphere": True}
    elif dim == 3:
        from bench_refine3 import make_points3

        pts = make_points3(kind, n)
        where = {"box": (0, 0, 0, 1, 1, 1), "periodic": not ordinary}
    else:
        from bench_refine import make_points

        pts, where = make_points(kind, n), {}
    knnrefine.refine(pts[:20000], k, workers=workers, **where)
    t0 = time.perf_counter()
    mesh = knnrefine.refine(pts, k, workers=workers, **where)
    print(time.perf_counter() - t0, len(mesh.vertices))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--before", required=True, help="the other tree's src directory")
    ap.add_argument("--dim", type=int, choices=[2, 3], default=3)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--ordinary", action="store_true", help="in space: the cube not periodic")
    ap.add_argument("--sphere", action="store_true", help="on the sphere (--dim is ignored)")
    ap.add_argument("--n", type=float, default=1e6)
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--kind", choices=["uniform", "clustered"], default="uniform")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        one(args.dim, args.kind, int(args.n), args.k, args.workers, args.ordinary, args.sphere)
        return
    trees = {"before": os.path.abspath(args.before),
             "after": os.path.join(os.path.dirname(HERE), "src")}  # fmt: skip
    times = {name: [] for name in trees}
    cmd = [sys.executable, __file__, "--one", "--before", args.before, "--n", str(args.n),
           "--k", str(args.k), "--kind", args.kind, "--dim", str(args.dim)]  # fmt: skip
    if args.workers is not None:
        cmd += ["--workers", str(args.workers)]
    if args.ordinary:
        cmd += ["--ordinary"]
    if args.sphere:
        cmd += ["--sphere"]
    for _ in range(args.repeat):
        for name, src in trees.items():
            env = dict(os.environ, PYTHONPATH=src)
            out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
            seconds, m = out.stdout.split()[-2:]
            times[name].append(float(seconds))
            print(f"{name}: {float(seconds):.3f} s, m = {int(m):,}", flush=True)
    a, b = (statistics.median(times[x]) for x in ("before", "after"))
    where = "sphere" if args.sphere else f"d={args.dim}"
    print(
        f"{args.kind} {where} n={args.n:.0e} k={args.k} workers={args.workers}: "
        f"before {a:.2f} s, after {b:.2f} s, "
        f"after / before {b / a:.3f} (medians of {args.repeat})"
    )


if __name__ == "__main__":
    main()
