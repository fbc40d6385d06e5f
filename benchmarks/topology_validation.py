"""Persistence on the mesh against cubical persistence of exact d_{P,k} on a fine grid.

    python benchmarks/topology_validation.py

For each input, diagrams of the sublevel sets of log d_{P,k}: on the mesh (exact values at the
vertices and edge midpoints, linear in between) and on a 1024 x 1024 grid of exact values
(gudhi's cubical complex, periodic where the data is). Reported: their bottleneck distance per
dimension; the stability bound it should respect, the largest |log| gap between the mesh's
interpolant and exact d_{P,k} measured on probes (plus the grid's own resolution); and for
comparison the filtration by the mesh's own d_{M,2} (centred by the median log ratio), which
Theorem 6 only bounds by log(beta / alpha) / 2. Then the outlier showcase (``showcase``).
"""

import os
import warnings

import numpy as np

import knnrefine
from knnrefine.topology import Persistence, bottleneck, grid_persistence

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data")


def inputs():
    rng = np.random.default_rng(0)
    t = rng.random(8000) * 2 * np.pi
    ring = np.concatenate(
        [
            np.stack([np.cos(t), np.sin(t)], 1) + rng.normal(0, 0.05, (8000, 2)),
            rng.random((2000, 2)) * 4 - 2,
        ]
    )
    yield "noisy circle, 20% outliers", ring, 30, False, (-2, -2, 2, 2)
    trp = knnrefine.datasets.trp_chi1_chi2()
    yield "Trp chi1/chi2 (torus)", trp, 30, True, (0, 0, 360, 360)
    path = os.path.join(DATA, "franti_s1.csv")
    if os.path.exists(path):
        s1 = np.loadtxt(path, delimiter=",", skiprows=1)
        lo, hi = s1.min(0), s1.max(0)
        yield "Franti S1", s1, 35, False, (*lo, *hi)


def main():
    alpha, beta = knnrefine.theorem6_constants(3.0)
    allow = np.log(beta / alpha) / 2
    print(
        "| input | dim | bottleneck: mesh d_Pk vs grid | stability bound (interpolation) "
        "| bottleneck: mesh d_M2 vs grid | Theorem 6 allows (d_M2) |"
    )
    print("|---|---:|---:|---:|---:|---:|")
    for name, pts, k, periodic, box in inputs():
        mesh = knnrefine.refine(pts, k, periodic=periodic, box=box)
        ph = Persistence(mesh, pts)
        m2 = Persistence(mesh, pts, function="d_m2")
        shift = float(np.median(m2.values - ph.values))  # centre log d_M2 on log d_Pk
        grid = grid_persistence(pts, k, box, periodic=(periodic, periodic), shape=(1024, 1024))
        err = knnrefine.KnnDistance(mesh, pts).error()
        bound = np.log1p(err["worst"])
        cell = max(box[2] - box[0], box[3] - box[1]) / 1024
        for dim in (0, 1):
            b = bottleneck(ph.diagram(dim), grid[dim])
            b2 = bottleneck(m2.diagram(dim) - shift, grid[dim])
            print(
                f"| {name} (k = {k}, m = {len(mesh.vertices)}) | H{dim} | {b:.4f} | "
                f"{bound:.4f} (+ grid cell {cell:.3g}) | {b2:.3f} | {allow:.2f} |",
                flush=True,
            )


def showcase(seeds=(0, 1, 2)):
    """The outlier showcase of tests/test_topology.py, printed: 1,600 points on a noisy circle
    and 400 uniform outliers in [-2, 2]^2; the three most persistent H1 classes of the sublevel
    sets of d_Pk (linear scale) at k = 1 and k = 30, and the top one over the runner-up."""
    print()
    print("| seed | k | H1 persistences (largest three) | top / runner-up |")
    print("|---:|---:|---|---:|")
    for seed in seeds:
        rng = np.random.default_rng(seed)
        t = rng.random(1600) * 2 * np.pi
        circle = np.stack([np.cos(t), np.sin(t)], 1) + rng.normal(0, 0.05, (1600, 2))
        pts = np.concatenate([circle, rng.random((400, 2)) * 4 - 2])
        for k, floor in ((1, 1e-2), (30, None)):
            with warnings.catch_warnings():  # k = 1: every point is under the floor, expected
                warnings.simplefilter("ignore", knnrefine.FloorWarning)
                mesh = knnrefine.refine(pts, k, box=(-2, -2, 2, 2), min_size=floor)
            top = Persistence(mesh, pts, log=False).most_persistent(1, 3)
            ratio = f"{top[0] / top[1]:.1f}" if len(top) > 1 else "only one loop"
            shown = ", ".join(f"{p:.3f}" for p in top)
            print(f"| {seed} | {k} | {shown} | {ratio} |", flush=True)


if __name__ == "__main__":
    main()
    showcase()
