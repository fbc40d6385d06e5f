"""How much of a partitioned mesh is halo: for uniform and clustered points, the vertices each
part holds beyond its own (``write_partitioned``), as a multiple of the vertices it owns, and
the time to write and read the folder back, and the kNN density part by part
(``PartitionedMesh.density``, strips in this process) against ``KnnDensity`` of the whole
mesh (a new index over the points), and part by part with d_{P,k} asked in two local
processes' strips (``workers=2``: what ``distributed.density`` does on a cluster); medians of
``--repeat`` interleaved runs.

    python benchmarks/partitioned_halo.py --n 1e6 --k 100 --parts 4 16
"""

import argparse
import dataclasses
import tempfile
import time

import numpy as np

import knnrefine
from knnrefine.scale.parts import write_partitioned


def clustered(n, seed=0):
    """Thirty Gaussian clusters, widths 1e-3 to 3e-2, wrapped into the unit square."""
    rng = np.random.default_rng(seed)
    centres = rng.random((30, 2))
    widths = 10 ** rng.uniform(-3, -1.5, 30)
    j = rng.integers(0, 30, n)
    return np.mod(centres[j] + rng.normal(size=(n, 2)) * widths[j, None], 1.0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=float, default=1e6)
    ap.add_argument("--k", type=int, default=100)
    ap.add_argument("--parts", type=int, nargs="+", default=[4, 16])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    n = int(args.n)
    inputs = {"uniform": np.random.default_rng(1).random((n, 2)), "clustered": clustered(n)}
    print(f"n = {n:.0e}, k = {args.k}, periodic unit box")
    for name, pts in inputs.items():
        mesh = knnrefine.refine(pts, args.k, periodic=True, box=(0, 0, 1, 1))
        # without the engine's index KnnDensity builds its own, as for a mesh read from a file
        fresh = dataclasses.replace(mesh, index=None)
        for parts in args.parts:
            with tempfile.TemporaryDirectory() as tmp:
                t = time.perf_counter()
                pm = write_partitioned(mesh, f"{tmp}/m", parts)
                write = time.perf_counter() - t
                t = time.perf_counter()
                pm.to_mesh()
                read = time.perf_counter() - t
                whole, parted, stripped = [], [], []
                for _ in range(args.repeat):  # interleaved
                    t = time.perf_counter()
                    want = knnrefine.KnnDensity(fresh, pts)
                    grid = want.grid((512, 512))[2]
                    whole.append(time.perf_counter() - t)
                    t = time.perf_counter()
                    got = pm.density(pts)
                    grid_parts = got.grid((512, 512))[2]
                    parted.append(time.perf_counter() - t)
                    t = time.perf_counter()
                    strips = pm.density(pts, workers=2)
                    strips.grid((512, 512))
                    stripped.append(time.perf_counter() - t)
                worst = float(np.max(np.abs(grid_parts - grid) / grid))
            ratio = [p["halo_vertices"] / p["vertices"] for p in pm.manifest["parts"]]
            print(f"{name:>9} m = {len(mesh.vertices):>7,} parts {parts:>3}: halo / own "
                  f"median {np.median(ratio):.2f}, max {max(ratio):.2f}; write {write:.2f} s, "
                  f"to_mesh {read:.2f} s; density + 512^2 grid part by part "
                  f"{np.median(parted):.2f} s (asked in 2 processes' strips "
                  f"{np.median(stripped):.2f} s), whole mesh {np.median(whole):.2f} s "
                  f"(grids differ by {worst:.1e})")  # fmt: skip


if __name__ == "__main__":
    main()
