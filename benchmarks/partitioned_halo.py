"""How much of a partitioned mesh is halo: for uniform and clustered points, the vertices each
part holds beyond its own (``write_partitioned``), as a multiple of the vertices it owns, and
the time to write and read the folder back.

    python benchmarks/partitioned_halo.py --n 1e6 --k 100 --parts 4 16
"""

import argparse
import tempfile
import time

import numpy as np

import knnrefine
from knnrefine.partitioned import write_partitioned


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
    args = ap.parse_args(argv)
    n = int(args.n)
    inputs = {"uniform": np.random.default_rng(1).random((n, 2)), "clustered": clustered(n)}
    print(f"n = {n:.0e}, k = {args.k}, periodic unit box")
    for name, pts in inputs.items():
        mesh = knnrefine.refine(pts, args.k, periodic=True, box=(0, 0, 1, 1))
        for parts in args.parts:
            with tempfile.TemporaryDirectory() as tmp:
                t = time.perf_counter()
                pm = write_partitioned(mesh, f"{tmp}/m", parts)
                write = time.perf_counter() - t
                t = time.perf_counter()
                pm.to_mesh()
                read = time.perf_counter() - t
            ratio = [p["halo_vertices"] / p["vertices"] for p in pm.manifest["parts"]]
            print(f"{name:>9} m = {len(mesh.vertices):>7,} parts {parts:>3}: halo / own "
                  f"median {np.median(ratio):.2f}, max {max(ratio):.2f}; write {write:.2f} s, "
                  f"to_mesh {read:.2f} s")  # fmt: skip


if __name__ == "__main__":
    main()
