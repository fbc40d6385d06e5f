"""The pictures in docs/, and the figures quoted beside them.

    python benchmarks/doc_images.py

docs/images/rama_density.png: the kNN density of the 202,215 backbone torsion angles (phi,
psi) of the Top8000 set (../shared/data/rama_top8000_phi_psi.csv) on the 360 x 360 degree
torus, k = sqrt(n) / 2, on a 512 x 512 grid, drawn as its highest-density regions (50, 80
and 95% of the mass: ``plot_density``'s default). Printed: the time to refine, to build the density
and to evaluate the grid, and d_{P,k}'s relative error against exact values on probes.
"""

import os
import time

import numpy as np

import knnrefine
from knnrefine.density import default_k
from knnrefine.plot import figure_size, plot_density, save_figure

HERE = os.path.dirname(os.path.abspath(__file__))
DATA = os.path.join(HERE, "..", "..", "shared", "data", "rama_top8000_phi_psi.csv")
OUT = os.path.join(HERE, "..", "docs", "images", "rama_density.png")


def main():
    if not os.path.exists(DATA):
        raise SystemExit(f"{DATA} is not available (it ships with the development checkout)")
    angles = np.loadtxt(DATA, delimiter=",", skiprows=1)
    box = (-180.0, -180.0, 180.0, 180.0)
    k = default_k(len(angles))
    knnrefine.refine(angles[:1000], 10, periodic=True, box=box)  # warm the kernels
    t0 = time.perf_counter()
    mesh = knnrefine.refine(angles, k, periodic=True, box=box)
    t1 = time.perf_counter()
    density = knnrefine.KnnDensity(mesh, angles)
    t2 = time.perf_counter()
    density.grid((512, 512))
    t3 = time.perf_counter()
    err = density.distance.error()
    save_figure(
        OUT,
        figure_size(mesh),
        lambda ax: plot_density(
            density, ax, shape=(512, 512), labels=("phi (degrees)", "psi (degrees)")
        ),
        force=True,
    )
    print(
        f"{os.path.relpath(OUT)}: n = {len(angles):,}, k = {k}, m = {len(mesh.vertices):,}; "
        f"refine {t1 - t0:.2f} s, KnnDensity {t2 - t1:.2f} s, 512 x 512 grid {t3 - t2:.2f} s; "
        f"d_Pk relative error median {100 * err['median']:.1f}%, worst {100 * err['worst']:.1f}% "
        f"({err['probes']:,} probes)"
    )


if __name__ == "__main__":
    main()
