"""Benchmark: knnrefine.refine against scipy's cKDTree k-th neighbour distances.

Each configuration runs in a fresh subprocess (so that its peak memory is its own), after one
untimed warm-up call on the same input (so loading compiled kernels and starting threads are
excluded); the time reported is the median wall time over --repeat runs, the memory the median
peak resident set above what the process held when the call started. In the same subprocess
scipy's cKDTree computes what a user would compute instead: the exact k-th-neighbour
distance at the n input points (tree build + ``query(points, k=[k], workers=-1)``, both
cores). Where n * k > --ckdtree-budget the
query runs on a random sample of 10^5 points and its time is scaled to n (marked "~").

Compile time is measured separately: once with an empty numba cache (first-ever compile) and
once more with that cache (what every later process pays).

    python benchmarks/bench_refine.py                       # the full grid (about 15 minutes)
    python benchmarks/bench_refine.py --sizes 1e4 1e5 --ks 10 100 --repeat 3
    python benchmarks/bench_refine.py --markdown results.json   # print the table again
"""

import argparse
import ctypes
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def make_points(kind, n, seed=0):
    """uniform: the unit square. clustered: 30 Gaussian clusters whose widths span three orders
    of magnitude (1e-4 to 1e-1) over a 10% uniform background."""
    rng = np.random.default_rng(seed)
    if kind == "uniform":
        return rng.random((n, 2))
    centres = rng.random((30, 2))
    widths = 10 ** rng.uniform(-4, -1, 30)
    weights = rng.dirichlet(np.ones(30))
    nb = n // 10
    counts = rng.multinomial(n - nb, weights)
    parts = [rng.normal(c, w, (m, 2)) for c, w, m in zip(centres, widths, counts, strict=True)]
    pts = np.concatenate(parts + [rng.random((nb, 2))])
    return np.clip(pts, 0.0, 1.0)


def _status_mb(field):
    """A memory figure of this process from /proc/self/status (VmHWM: peak, VmRSS: now)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _trim():
    """Return freed heap memory to the system (glibc), so that RSS counts live memory only."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def reset_peak():
    """Reset VmHWM to the current RSS (Linux >= 4.0: write 5 to clear_refs)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _refine(pts, k, tau, w):
    """refine with ``workers=w``; w = ONE_CORE: workers=1 with KNNREFINE_THREADS=1 (one
    thread for the index, the sweeps and the assembly too)."""
    import knnrefine

    if w != ONE_CORE:
        return knnrefine.refine(pts, k, tau, workers=w)
    saved = os.environ.get("KNNREFINE_THREADS")
    os.environ["KNNREFINE_THREADS"] = "1"
    try:
        return knnrefine.refine(pts, k, tau, workers=1)
    finally:
        if saved is None:
            del os.environ["KNNREFINE_THREADS"]
        else:
            os.environ["KNNREFINE_THREADS"] = saved


ONE_CORE = 0  # the workers value that stands for one core (``--one-core``)


def worker(kind, n, k, tau, repeat, ckdtree_budget, workers=(1,)):
    from scipy.spatial import cKDTree

    pts = make_points(kind, n)
    for w in workers:  # warm-up: loads every kernel this input needs, the threads
        _refine(pts, k, tau, w)
    first = _status_mb("VmRSS")
    times = {w: [] for w in workers}
    peaks = []
    totals = []
    sizes = {}
    for _ in range(repeat):
        for w in workers:  # interleaved: each repeat runs every workers value in turn
            # working memory: the peak above what the process holds when the call starts,
            # after the allocator has handed back what the previous call freed
            _trim()
            base = _status_mb("VmRSS")
            ok = reset_peak()
            t0 = time.perf_counter()
            mesh = _refine(pts, k, tau, w)
            times[w].append(time.perf_counter() - t0)
            sizes[w] = len(mesh.vertices)
            if w == workers[0]:
                totals.append(_status_mb("VmHWM") if ok else float("nan"))
                peaks.append(totals[-1] - base)
                stats = mesh.stats
                m = len(mesh.vertices)
            del mesh
    t0 = time.perf_counter()
    tree = cKDTree(pts)
    t_build = time.perf_counter() - t0
    sampled = n * k > ckdtree_budget
    q = pts[np.random.default_rng(2).choice(n, 100_000, replace=False)] if sampled else pts
    t0 = time.perf_counter()
    tree.query(q, k=[k], workers=-1)
    t_query = (time.perf_counter() - t0) * (n / len(q))
    return {
        "kind": kind,
        "n": n,
        "k": k,
        "tau": tau,
        "workers": list(workers),
        "refine_s": float(np.median(times[workers[0]])),
        "refine_all_s": times[workers[0]],
        # each workers value's median time and mesh size (memory: the first value's)
        "by_workers": {
            str(w): {"refine_s": float(np.median(times[w])), "all_s": times[w], "m": sizes[w]}
            for w in workers
        },
        "peak_mb": float(np.median(peaks)),
        # issue 10's budget for working memory: 24 bytes per input point, 300 per mesh vertex
        "budget_mb": (24 * n + 300 * m) / 2**20,
        "peak_total_mb": float(np.median(totals)),
        "base_rss_mb": first,
        "m": m,
        "m_torus": stats["m_torus"],
        "moves": stats["moves"],
        "time": stats["time"],
        "floor": stats["floor_circumballs"] + stats["floor_cells"],
        "ckdtree_s": t_build + t_query,
        "ckdtree_sampled": sampled,
    }


def compile_times():
    code = (
        "import time; t = time.perf_counter(); import numpy as np, knnrefine; "
        "p = np.random.default_rng(0).random((2000, 2)); knnrefine.refine(p, 10); "
        "knnrefine.refine(p, 10, periodic=True, box=(0, 0, 1, 1)); "
        "print(time.perf_counter() - t)"
    )
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        first = float(
            subprocess.run(
                [sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True
            ).stdout.split()[-1]
        )
        cached = float(
            subprocess.run(
                [sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True
            ).stdout.split()[-1]
        )
    return {"first_compile_s": first, "cached_start_s": cached}


def machine():
    import numba
    import scipy

    cpu = "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "numba": numba.__version__,
    }


def markdown(results):
    lines = []
    info = results["machine"]
    comp = results["compile"]
    lines.append(
        f"Machine: {info['cpu']}, {info['cores']} cores; Python {info['python']}, "
        f"numpy {info['numpy']}, scipy {info['scipy']}, numba {info['numba']}."
    )
    lines.append("")
    lines.append(
        f"JIT: first-ever compile {comp['first_compile_s']:.1f} s (empty numba cache); "
        f"a later process starts in {comp['cached_start_s']:.2f} s (cache reused)."
    )
    lines.append("")
    runs = results["runs"]
    extra = [w for w in (runs[0].get("workers", [1])[1:] if runs else [])]
    first = runs[0].get("workers", [1])[0] if runs else 1
    head = "".join(
        " one core (m) | workers=1 / one core |"
        if w == ONE_CORE
        else f" workers={w} (m) | speed-up |"
        for w in extra
    )
    if ONE_CORE in extra and len(extra) > 1:
        head += f" workers={extra[0]} over one core |"
    lines.append(
        f"| input | n | k | refine, workers={first} (median) | memory: refine / budget / "
        f"process peak | m | cKDTree k-th NN | refine / cKDTree |{head}"
    )
    over = ONE_CORE in extra and len(extra) > 1
    lines.append(
        "|---|---:|---:|---:|---:|---:|---:|---:|" + "---:|---:|" * len(extra) + "---:|" * over
    )
    for r in runs:
        ck = ("~" if r["ckdtree_sampled"] else "") + f"{r['ckdtree_s']:.2f} s"
        cols = ""
        for w in extra:
            b = r["by_workers"][str(w)]
            cols += f" {b['refine_s']:.3f} s ({b['m']}) | {r['refine_s'] / b['refine_s']:.2f}x |"
        if over:
            one, tiles = (r["by_workers"][str(w)]["refine_s"] for w in (ONE_CORE, extra[0]))
            cols += f" **{one / tiles:.2f}x** |"
        lines.append(
            f"| {r['kind']} | {r['n']:.0e} | {r['k']} | {r['refine_s']:.3f} s | "
            f"{r['peak_mb']:.1f} / {r['budget_mb']:.1f} / {r['peak_total_mb']:.0f} MiB | "
            f"{r['m']} | {ck} | {r['refine_s'] / r['ckdtree_s']:.2g} |{cols}"
        )
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", nargs="+", type=float, default=[1e4, 1e5, 1e6, 1e7])
    ap.add_argument("--ks", nargs="+", type=int, default=[10, 30, 100, 1000])
    ap.add_argument("--kinds", nargs="+", default=["uniform", "clustered"])
    ap.add_argument("--tau", type=float, default=3.0)
    ap.add_argument("--repeat", type=int, default=5, help="runs per configuration (n < 1e7)")
    ap.add_argument("--ckdtree-budget", type=float, default=2e8)
    ap.add_argument("--out", default=os.path.join(HERE, "results", "bench_refine.json"))
    ap.add_argument("--markdown", metavar="JSON", help="print the table of a saved run")
    ap.add_argument(
        "--workers",
        nargs="+",
        type=int,
        default=[1, 2],
        help="workers values, run interleaved in each configuration's process",
    )
    ap.add_argument(
        "--one-core",
        action="store_true",
        help="also run workers=1 on one core (KNNREFINE_THREADS=1), interleaved",
    )
    ap.add_argument(
        "--worker", nargs=4, metavar=("KIND", "N", "K", "REPEAT"), help=argparse.SUPPRESS
    )
    args = ap.parse_args(argv)
    if args.markdown:
        with open(args.markdown) as f:
            print(markdown(json.load(f)))
        return
    if args.one_core:
        args.workers = [*args.workers, ONE_CORE]
    if args.worker:
        kind, n, k, repeat = args.worker
        res = worker(
            kind,
            int(float(n)),
            int(k),
            args.tau,
            int(repeat),
            args.ckdtree_budget,
            tuple(args.workers),
        )
        print("RESULT " + json.dumps(res))
        return
    results = {
        "machine": machine(),
        "command": " ".join([os.path.basename(sys.argv[0])] + sys.argv[1:]),
        "compile": compile_times(),
        "runs": [],
    }
    print(f"compile: {results['compile']}", flush=True)
    for kind in args.kinds:
        for n in args.sizes:
            for k in args.ks:
                if k >= n:
                    continue
                repeat = args.repeat if n < 1e7 else min(args.repeat, 3)
                out = subprocess.run(
                    [
                        sys.executable,
                        __file__,
                        "--tau",
                        str(args.tau),
                        "--ckdtree-budget",
                        str(args.ckdtree_budget),
                        "--workers",
                        *map(str, args.workers),
                        "--worker",
                        kind,
                        str(n),
                        str(k),
                        str(repeat),
                    ],
                    check=True,
                    capture_output=True,
                    text=True,
                ).stdout
                res = json.loads(out.split("RESULT ", 1)[1])
                results["runs"].append(res)
                print(
                    f"{kind:9s} n={n:.0e} k={k:5d} refine {res['refine_s']:.3f} s "
                    f"peak {res['peak_mb']:.1f} MiB (budget {res['budget_mb']:.1f}) m={res['m']} "
                    "cKDTree "
                    f"{'~' if res['ckdtree_sampled'] else ''}{res['ckdtree_s']:.2f} s",
                    flush=True,
                )
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print()
    print(markdown(results))


if __name__ == "__main__":
    main()
