"""Tiled refinement on a Dask LocalCluster against one process, interleaved in one run.

For each n: uniform points on the unit torus (a Dask array generated chunk by chunk on the
workers, then read into this process: the final pass needs them all), k = 100; per repeat
one single-process ``knnrefine.refine`` and one ``knnrefine.distributed.refine`` on the same
cluster, alternating. Prints medians, the speed-up, the share of the rounds and of the final
pass (the seam work left to one process), and peak resident memory of this process and of
each worker (ru_maxrss, which only grows: the largest n dominates).

    python benchmarks/bench_distributed.py --sizes 1e6 1e7 --repeat 3
"""

import argparse
import json
import os
import platform
import resource
import statistics
import time

import numpy as np

import knnrefine
from knnrefine import distributed


def peak_gb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", nargs="+", type=float, default=[1e6, 1e7])
    ap.add_argument("--k", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=None, help="JSON file for the rows")
    args = ap.parse_args(argv)
    import dask
    import dask.array as da
    from distributed import Client

    print(f"{platform.node()}: {os.cpu_count()} cores, {args.workers} Dask workers, k = {args.k}")
    rows = []
    with distributed.local_cluster(args.workers) as cluster, Client(cluster) as client:
        warm = np.random.default_rng(0).random((20000, 2))
        opts = {"periodic": True, "box": (0, 0, 1, 1)}
        knnrefine.refine(warm, 10, **opts)
        distributed.refine(warm, 10, client=client, **opts)
        for n in (int(s) for s in args.sizes):
            chunk = min(n, 2_000_000)
            with dask.config.set(scheduler=client):
                pts = da.random.RandomState(1).random_sample((n, 2), chunks=(chunk, 2))
                pts = pts.compute()
            single, tiled, reports, sizes = [], [], [], []
            for _ in range(args.repeat):
                t = time.perf_counter()
                one = knnrefine.refine(pts, args.k, **opts)
                single.append(time.perf_counter() - t)
                t = time.perf_counter()
                mesh = distributed.refine(pts, args.k, client=client, **opts)
                tiled.append(time.perf_counter() - t)
                reports.append(mesh.stats["rounds"])
                sizes.append((len(one.vertices), len(mesh.vertices)))
            rounds = [sum(r["seconds"] for r in rep if r["round"] != "final") for rep in reports]
            final = [sum(r["seconds"] for r in rep if r["round"] == "final") for rep in reports]
            final_new = [
                sum(r["new_vertices"] for r in rep if r["round"] == "final") for rep in reports
            ]
            workers_gb = client.run(peak_gb)
            row = {
                "n": n, "k": args.k, "workers": args.workers,
                "single_s": statistics.median(single), "tiled_s": statistics.median(tiled),
                "speedup": statistics.median(single) / statistics.median(tiled),
                "rounds_s": statistics.median(rounds), "final_s": statistics.median(final),
                "final_vertices": int(statistics.median(final_new)),
                "m_single": sizes[0][0], "m_tiled": sizes[0][1],
                "client_peak_gb": peak_gb(), "worker_peak_gb": max(workers_gb.values()),
                "single_all": single, "tiled_all": tiled,
            }  # fmt: skip
            rows.append(row)
            print(
                f"n = {n:.0e}: one process {row['single_s']:.2f} s, {args.workers} workers "
                f"{row['tiled_s']:.2f} s (speed-up {row['speedup']:.2f}); rounds "
                f"{row['rounds_s']:.2f} s, final pass {row['final_s']:.2f} s "
                f"({row['final_vertices']} vertices); m {row['m_single']} / {row['m_tiled']}; "
                f"peak RSS client {row['client_peak_gb']:.2f} GB, worker "
                f"{row['worker_peak_gb']:.2f} GB",
                flush=True,
            )
    if args.out:
        with open(args.out, "w") as fh:
            json.dump({"rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
