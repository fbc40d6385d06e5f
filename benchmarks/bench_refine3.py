"""Benchmark in space: knnrefine.refine on (n, 3) points in the periodic unit cube against
scipy's cKDTree(boxsize=1) exact k-th-neighbour distances at the n points (``--box
ordinary``: the cube not periodic, refined in its embedding torus, against a plain cKDTree;
``mixed``: periodic in x and z).

Each configuration runs in a fresh subprocess, after one untimed warm-up call on the same
input; refine and the cKDTree (build + ``query(points, k=[k], workers=-1)``, both cores)
alternate --repeat times and the medians are reported, with refine's peak resident memory
above what the process held before the call (``bench_refine.py``'s method) per mesh vertex,
and that peak less the counting index over the points (the input's copy: about 28 bytes a
point, whatever the mesh) per mesh vertex: the mesh's own memory.
Where n * k > --ckdtree-budget the query runs on 10^5 sampled points and its time is scaled
to n (marked "~"). ``--workers N`` also times ``refine(..., workers=N)`` (slabs in N
threads, stitched, from 10^6 points: ``scale.tiled.TILES_FROM``; below, one process unless
``KNNREFINE_TILES=always``), interleaved with the others, and reports it as a ratio to one
process.

    python benchmarks/bench_refine3.py --sizes 1e5 1e6 --ks 10 100 1000 --repeat 3 \\
        --out benchmarks/results/bench_refine3.json
    python benchmarks/bench_refine3.py --box ordinary --sizes 1e6 --ks 10 100 --repeat 3 \\
        --out benchmarks/results/bench_refine3_ordinary.json
    KNNREFINE_TILES=always python benchmarks/bench_refine3.py --sizes 1e5 1e6 --ks 10 100 \\
        --workers 2 --repeat 3 --out benchmarks/results/bench_refine3_threads.json
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


def make_points3(kind, n, seed=0):
    """uniform: the unit cube. clustered: 30 Gaussian clusters whose widths span three orders
    of magnitude (1e-4 to 1e-1) over a 10% uniform background, wrapped into the cube.
    plane: uniform on the plane z = 0.5 (a hostile input: empty space beside the points)."""
    rng = np.random.default_rng(seed)
    if kind == "uniform":
        return rng.random((n, 3))
    if kind == "plane":
        pts = rng.random((n, 3))
        pts[:, 2] = 0.5
        return pts
    centres = rng.random((30, 3))
    widths = 10 ** rng.uniform(-4, -1, 30)
    counts = rng.multinomial(n - n // 10, rng.dirichlet(np.ones(30)))
    parts = [rng.normal(c, w, (m, 3)) for c, w, m in zip(centres, widths, counts, strict=True)]
    return np.mod(np.concatenate(parts + [rng.random((n // 10, 3))]), 1.0)


BOXES = {
    "torus": (True, True, True),
    "ordinary": (False, False, False),
    "mixed": (True, False, True),
}


def worker(kind, n, k, repeat, budget, box_kind="torus", workers=1):
    from scipy.spatial import cKDTree

    import knnrefine

    box = (0.0, 0.0, 0.0, 1.0, 1.0, 1.0)
    periodic = BOXES[box_kind]
    boxsize = np.where(periodic, 1.0, 0.0) if any(periodic) else None
    pts = make_points3(kind, n)
    knnrefine.refine(pts, k, periodic=periodic, box=box)  # warm-up
    if workers > 1:
        knnrefine.refine(pts, k, periodic=periodic, box=box, workers=workers)
    times, peaks, kd, tiled, m_tiled = [], [], [], [], 0
    sampled = n * k > budget
    q = pts[np.random.default_rng(2).choice(n, 100_000, replace=False)] if sampled else pts
    for _ in range(repeat):
        _trim()
        base = _status_mb("VmRSS")
        ok = reset_peak()
        t0 = time.perf_counter()
        mesh = knnrefine.refine(pts, k, periodic=periodic, box=box)
        times.append(time.perf_counter() - t0)
        peaks.append((_status_mb("VmHWM") - base) if ok else float("nan"))
        m, t = len(mesh.vertices), len(mesh.tetrahedra)
        m_torus = mesh.stats["m_torus"]
        del mesh
        t0 = time.perf_counter()
        tree = cKDTree(pts, boxsize=boxsize)
        t_build = time.perf_counter() - t0
        t0 = time.perf_counter()
        tree.query(q, k=[k], workers=-1)
        kd.append(t_build + (time.perf_counter() - t0) * (n / len(q)))
        del tree
        if workers > 1:
            t0 = time.perf_counter()
            mesh = knnrefine.refine(pts, k, periodic=periodic, box=box, workers=workers)
            tiled.append(time.perf_counter() - t0)
            m_tiled = len(mesh.vertices)
            del mesh
    peak = float(np.median(peaks))
    from knnrefine._engine.index3 import build_index3

    index_mb = sum(a.nbytes for a in build_index3(pts)) / 2**20
    return {
        "kind": kind, "box": box_kind, "n": n, "k": k, "m": m, "m_torus": m_torus,
        "tetrahedra": t,
        "refine_s": float(np.median(times)), "refine_all_s": times,
        "ckdtree_s": float(np.median(kd)), "ckdtree_all_s": kd, "ckdtree_sampled": sampled,
        "ratio": float(np.median(times)) / float(np.median(kd)),
        "peak_mb": peak, "bytes_per_vertex": peak * 2**20 / m, "index_mb": index_mb,
        "mesh_bytes_per_vertex": (peak - index_mb) * 2**20 / m,
        "workers": workers, "tiled_s": float(np.median(tiled)) if tiled else None,
        "tiled_all_s": tiled, "m_tiled": m_tiled,
        "tiled_ratio": float(np.median(tiled)) / float(np.median(times)) if tiled else None,
    }  # fmt: skip


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[1e5, 1e6])
    ap.add_argument("--ks", type=int, nargs="+", default=[10, 100, 1000])
    ap.add_argument("--kinds", nargs="+", default=["uniform", "clustered"])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--ckdtree-budget", type=float, default=2e8)
    ap.add_argument("--box", choices=sorted(BOXES), default="torus")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--out")
    ap.add_argument("--worker", nargs=7, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        kind, n, k, repeat, budget, box_kind, workers = args.worker
        print(json.dumps(worker(kind, int(n), int(k), int(repeat), float(budget), box_kind,
                                int(workers))))  # fmt: skip
        return
    rows = []
    for kind in args.kinds:
        for n in (int(s) for s in args.sizes):
            for k in args.ks:
                if k >= n:
                    continue
                out = subprocess.run(
                    [sys.executable, __file__, "--worker", kind, str(n), str(k),
                     str(args.repeat), str(args.ckdtree_budget), args.box, str(args.workers)],
                    capture_output=True, text=True, check=True,
                )  # fmt: skip
                row = json.loads(out.stdout.strip().splitlines()[-1])
                rows.append(row)
                mark = "~" if row["ckdtree_sampled"] else ""
                print(
                    f"{kind:>9} n={n:.0e} k={k:>4}: refine {row['refine_s']:.3f} s, "
                    f"cKDTree {mark}{row['ckdtree_s']:.3f} s (ratio {row['ratio']:.2f}), "
                    f"m = {row['m']:,} (torus {row['m_torus']:,}), peak {row['peak_mb']:.0f} MB = "
                    f"{row['bytes_per_vertex']:.0f} B/vertex ({row['mesh_bytes_per_vertex']:.0f} "
                    f"without the index's {row['index_mb']:.0f} MB)"
                    + (
                        f"; workers={args.workers}: {row['tiled_s']:.3f} s "
                        f"({row['tiled_ratio']:.2f} x one process, m = {row['m_tiled']:,})"
                        if row["tiled_s"] is not None
                        else ""
                    ),
                    flush=True,
                )
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"machine": machine(), "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
