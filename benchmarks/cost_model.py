"""A measured cost model of the tiled refinement on Dask, extrapolated to 10^9 and 10^10 points
on 8 to 256 workers. A MODEL, not a run: what it assumes is printed with it.

Measured here, each on one thread (a worker's share), medians of --repeat:
  cut      seconds per point to put a partition in torus coordinates and cut it into both
           sets' strips (``distributed._cut``);
  index    seconds per point and per log2(points) to build a strip's counting index
           (``partition.tile_index``; a sort-based build, n log n);
  tiles    seconds per point of a strip for all rounds' tiles together (a tiled run of
           --n points on --workers Dask workers: the slowest strip of each round, summed);
  client   seconds per mesh vertex in the calling process after the rounds (the last step
           and assembling the Mesh), and m / n (vertices per point at this k);
  task     seconds of scheduler time per Dask task (--tasks no-op tasks submitted and
           gathered);
  memory   peak resident bytes per point of a worker (from bench_distributed's 10^8 row
           when its results file is there).
Model, for n points on W workers (one thread each), P = n / 10^6 partitions:
  worker   (cut + 2 index log2(n / W) + tiles) n / W     every worker busy on its strips
  network  2 x 16 bytes x n (W - 1) / W / W / B     each point to its strip's worker, both
                                                     sets, B bytes/s per worker (assumed)
  tasks    (P (1 + 2 W) + 2 W + rounds W) x task    the scheduler handles tasks one by one
  client   setup + client x m                       the plan, the last step and the Mesh
  wall     worker + network + tasks + client        no overlap assumed (an upper bound)
Checked against bench_distributed's measured 10^8 run on 2 workers, when available.

    python benchmarks/cost_model.py --n 2e6 --repeat 3
"""

import argparse
import json
import os
import statistics
import time

import numpy as np

os.environ.setdefault("KNNREFINE_THREADS", "1")

RESULTS = os.path.join(os.path.dirname(__file__), "results")


def timed(fn, repeat):
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return statistics.median(out)


def measure(n, workers, repeat, tasks, k):
    import dask.array as da
    from distributed import Client

    from knnrefine._engine.embedding import Embedding
    from knnrefine.scale import distributed
    from knnrefine.scale.distributed import _cut
    from knnrefine.scale.tiled import strips, tile_index

    rng = np.random.default_rng(0)
    pts = rng.random((n, 2))
    emb = Embedding.make((0.0, 0.0, 1.0, 1.0), (True, True))
    lx, ly = emb.period_internal
    sets = strips(emb.to_internal(pts[:100_000]), (lx, ly), workers)
    internal = emb.to_internal(pts)
    out = {
        "cut": timed(lambda: _cut((pts, None), emb.to_internal, (lx, ly), sets, 4 * emb.grid),
                     repeat) / n,
        "index": timed(lambda: tile_index(internal, None), repeat) / n / np.log2(n),
    }  # fmt: skip
    with distributed.local_cluster(workers) as cluster, Client(cluster) as client:
        source = client.persist(da.from_array(pts, chunks=(1_000_000, 2)))
        distributed.refine(source, k, client=client, periodic=True, box=(0, 0, 1, 1))  # warm
        runs = []
        for _ in range(repeat):
            t = time.perf_counter()
            mesh = distributed.refine(source, k, client=client, periodic=True, box=(0, 0, 1, 1))
            wall = time.perf_counter() - t
            rounds = [r for r in mesh.stats["rounds"] if r["round"] != "final"]
            final = mesh.stats["rounds"][-1]["seconds"]
            after = wall - mesh.stats["time"]["setup"] - sum(r["seconds"] for r in rounds)
            runs.append((sum(max(r["tiles"]) for r in rounds), after, len(mesh.vertices),
                         mesh.stats["time"]["setup"], len(rounds), final))  # fmt: skip
        tile_s, after_s, m, setup, rounds, _ = (
            statistics.median(v) for v in zip(*runs, strict=True)
        )
        out["tiles"] = tile_s / (n / workers)
        out["client"] = after_s / m
        out["m_per_n"] = m / n
        out["setup"] = setup
        out["rounds"] = int(rounds)

        def noop(i):
            return i

        def batch():
            client.gather(client.map(noop, range(tasks), pure=False))

        batch()
        out["task"] = timed(batch, repeat) / tasks
    return out


def model(c, n, w, bandwidth, memory_per_point):
    parts = n / 1e6
    worker = (c["cut"] + 2 * c["index"] * np.log2(n / w) + c["tiles"]) * n / w
    network = 32.0 * n * (w - 1) / w / w / bandwidth
    tasks = (parts * (1 + 2 * w) + 2 * w + c["rounds"] * w) * c["task"]
    m = c["m_per_n"] * n
    client = c["setup"] + c["client"] * m
    return {
        "n": n, "workers": w, "worker_s": worker, "network_s": network, "tasks_s": tasks,
        "client_s": client, "wall_s": worker + network + tasks + client, "m": m,
        "worker_gb": memory_per_point * n / w / 1e9 if memory_per_point else None,
    }  # fmt: skip


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=float, default=2e6, help="points of the measured runs")
    ap.add_argument("--k", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--tasks", type=int, default=5000)
    ap.add_argument("--bandwidth", type=float, default=1.25e9,
                    help="assumed bytes/s into each worker (10 GbE)")  # fmt: skip
    ap.add_argument("--out", default=os.path.join(RESULTS, "cost_model.json"))
    args = ap.parse_args(argv)
    c = measure(int(args.n), args.workers, args.repeat, args.tasks, args.k)
    print(f"measured on {os.cpu_count()} cores, n = {args.n:.0e}, k = {args.k}, "
          f"{args.workers} workers:")  # fmt: skip
    print(f"  cut {c['cut'] * 1e9:.0f} ns/pt, index {c['index'] * 1e9:.1f} ns/pt/log2, tiles "
          f"{c['tiles'] * 1e9:.0f} ns/pt, client {c['client'] * 1e6:.2f} us/vertex, m/n "
          f"{c['m_per_n']:.4f}, setup {c['setup']:.2f} s, task {c['task'] * 1e6:.0f} us, "
          f"rounds {c['rounds']}")  # fmt: skip
    memory, check = None, None
    bench = os.path.join(RESULTS, "bench_distributed.json")
    if os.path.exists(bench):
        rows = {r["n"]: r for r in json.load(open(bench))["rows"]}
        big = rows.get(100_000_000)
        if big:
            memory = big["worker_peak_gb"] * 1e9 / (big["n"] / big["workers"])
            got = model(c, big["n"], big["workers"], args.bandwidth, memory)
            check = {"measured_s": big["tiled_s"], "model_s": got["wall_s"]}
            print(
                f"check: 10^8 on {big['workers']} workers measured {big['tiled_s']:.1f} s, "
                f"model {got['wall_s']:.1f} s; worker memory {memory:.0f} bytes/point"
            )
    table = [model(c, n, w, args.bandwidth, memory) for n in (1e9, 1e10)
             for w in (8, 32, 128, 256)]  # fmt: skip
    print(f"{'n':>7} {'W':>4} {'worker s':>9} {'network s':>9} {'tasks s':>8} {'client s':>9} "
          f"{'wall s':>8} {'m':>10} {'GB/worker':>9}")  # fmt: skip
    for r in table:
        gb = "-" if r["worker_gb"] is None else f"{r['worker_gb']:.1f}"
        print(f"{r['n']:7.0e} {r['workers']:4d} {r['worker_s']:9.1f} {r['network_s']:9.1f} "
              f"{r['tasks_s']:8.1f} {r['client_s']:9.1f} {r['wall_s']:8.1f} {r['m']:10.3g} "
              f"{gb:>9}")  # fmt: skip
    with open(args.out, "w") as fh:
        json.dump({"command": "python benchmarks/cost_model.py " + " ".join(argv or []),
                   "measured": c, "check_1e8": check, "bandwidth": args.bandwidth,
                   "model": table}, fh, indent=1)  # fmt: skip


if __name__ == "__main__":
    main()
