"""Tiled refinement on a Dask LocalCluster against one process, interleaved in one run.

For each n: uniform points on the unit torus, a Dask array generated chunk by chunk on the
workers and kept there (persisted); ``knnrefine.scale.distributed.refine`` reads it partition by
partition where it lies. The single-process run gets the same points computed into this
process (its input; the tiled run never reads them here). k = 100; per repeat one
single-process ``knnrefine.refine`` and one ``knnrefine.scale.distributed.refine`` on the same
cluster, alternating. Prints medians, the speed-up, the share of setup (sample, plan,
strips and their indexes), rounds and the last step, and peak resident memory of this
process and of each worker (ru_maxrss, which only grows: the largest n dominates).
``--no-single`` skips the single-process runs (for n beyond this machine's memory).

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
from knnrefine.scale import distributed


def peak_gb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", nargs="+", type=float, default=[1e6, 1e7])
    ap.add_argument("--k", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=None, help="JSON file for the rows")
    ap.add_argument("--no-single", action="store_true", help="only the tiled runs")
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
                source = da.random.RandomState(1).random_sample((n, 2), chunks=(chunk, 2))
            source = client.persist(source)
            pts = None if args.no_single else source.compute()
            single, tiled, reports, sizes, times = [], [], [], [], []
            for _ in range(args.repeat):
                m_one = 0
                if pts is not None:
                    t = time.perf_counter()
                    m_one = len(knnrefine.refine(pts, args.k, **opts).vertices)
                    single.append(time.perf_counter() - t)
                t = time.perf_counter()
                mesh = distributed.refine(source, args.k, client=client, **opts)
                tiled.append(time.perf_counter() - t)
                reports.append(mesh.stats["rounds"])
                times.append(mesh.stats["time"])
                sizes.append((m_one, len(mesh.vertices)))
            del source
            setup = [t["setup"] for t in times]
            rounds = [sum(r["seconds"] for r in rep if r["round"] != "final") for rep in reports]
            final = [sum(r["seconds"] for r in rep if r["round"] == "final") for rep in reports]
            final_new = [
                sum(r["new_vertices"] for r in rep if r["round"] == "final") for rep in reports
            ]
            workers_gb = client.run(peak_gb)
            row = {
                "n": n, "k": args.k, "workers": args.workers,
                "single_s": statistics.median(single) if single else None,
                "tiled_s": statistics.median(tiled),
                "speedup": statistics.median(single) / statistics.median(tiled) if single else None,
                "setup_s": statistics.median(setup),
                "rounds_s": statistics.median(rounds), "final_s": statistics.median(final),
                "fetched_points": any(r[-1]["fetched_points"] for r in reports),
                "tiles_s": [r["tiles"] for r in reports[0] if r["round"] != "final"],
                "final_vertices": int(statistics.median(final_new)),
                "m_single": sizes[0][0], "m_tiled": sizes[0][1],
                "client_peak_gb": peak_gb(), "worker_peak_gb": max(workers_gb.values()),
                "single_all": single, "tiled_all": tiled,
            }  # fmt: skip
            rows.append(row)
            one = "-" if row["single_s"] is None else f"{row['single_s']:.2f} s"
            speedup = "-" if row["speedup"] is None else f"{row['speedup']:.2f}"
            print(
                f"n = {n:.0e}: one process {one}, {args.workers} workers "
                f"{row['tiled_s']:.2f} s (speed-up {speedup}); setup {row['setup_s']:.2f} s, "
                f"rounds {row['rounds_s']:.2f} s, last step {row['final_s']:.2f} s "
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
