"""Mesh size against k, and the size estimate refine makes before it starts.

    python benchmarks/mesh_size.py                 # uniform points, then the real data sets

For uniform points (n = 10^5, k from 2 to 100; k = 1 at n = 10^4) it prints m / n next to the
model of ``knnrefine._engine.size`` (m / n = 2.3 / (k - 1.47)) and refine's estimate; for the
real data sets of ../shared/data (when present) the estimate against the actual torus mesh
size at k = 2, 10 and 100. The estimate sets the default vertex budget (three times it) and
the large-run warning, so what matters is that it is never far below the truth.
"""

import os
import time
import warnings

import numpy as np
from certify_datasets import DATA, SETTINGS  # the data sets' periodic boxes, one place

import knnrefine


def row(name, points, k, **kw):
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = knnrefine.refine(points, k, max_vertices=10**8, **kw)
    m, est = mesh.stats["m_torus"], mesh.stats["estimated_vertices"]
    n = len(points)
    model = 2.3 / (k - 1.47) if k >= 2 else float("nan")
    print(
        f"| {name} | {n} | {k} | {m} | {m / n:.3f} | {model:.3f} | {est} | {est / m:.2f} | "
        f"{time.perf_counter() - t0:.1f} |",
        flush=True,
    )


def main():
    print(
        "| points | n | k | m (torus) | m / n | model 2.3/(k-1.47) | estimate | estimate / m "
        "| seconds |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    rng = np.random.default_rng(0)
    row("uniform", rng.random((10_000, 2)), 1)
    uniform = rng.random((100_000, 2))
    for k in (2, 3, 5, 10, 30, 100):
        row("uniform", uniform, k)
    if not os.path.isdir(DATA):
        return
    for name in sorted(os.listdir(DATA)):
        if not name.endswith(".csv"):
            continue
        points = np.loadtxt(os.path.join(DATA, name), delimiter=",", skiprows=1)
        if points.ndim != 2 or points.shape[1] != 2:
            continue  # not planar
        periodic, box = SETTINGS.get(name, (False, None))
        for k in (2, 10, 100):
            if k <= len(points):
                row(name.removesuffix(".csv"), points, k, periodic=periodic, box=box)


if __name__ == "__main__":
    main()
