"""Fingerprints of the meshes of a fixed matrix of inputs, to compare two versions bit for bit.

    python benchmarks/mesh_fingerprints.py > after.txt
    git stash; python benchmarks/mesh_fingerprints.py > before.txt; git stash pop
    diff before.txt after.txt            # no output: the same meshes, bit for bit

Each line: the case, the number of torus vertices and triangles, and a SHA-256 of every array
of the torus mesh (vertices, triangles, offsets, neighbours, kinds) and of the returned mesh
(vertices, triangles, offsets, kinds, order). The plane's matrix spans uniform, clustered,
lattice, duplicated and real-like inputs, k from 1 to 200, tau from 2.5 to 10, and every
periodic mode; space's (``--domains space``) uniform and clustered points in every periodic
mode; the sphere's uniform points, a cluster at a pole and one across the antimeridian
(the sphere's mesh is its own torus: its unit vectors and triangles). ``--domains plane space
sphere`` runs all three (the default: the plane only, as before).
"""

import argparse
import hashlib
import warnings

import numpy as np

import knnrefine


def inputs():
    rng = np.random.default_rng(0)
    uniform = rng.random((3000, 2))
    blobs = np.concatenate(
        [rng.normal(c, s, (800, 2)) for c, s in (((0.3, 0.3), 0.05), ((0.7, 0.6), 0.01))]
    )
    blobs = np.concatenate([np.mod(blobs, 1.0), rng.random((400, 2))])
    g = (np.arange(30) + 0.5) / 30
    lattice = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    dup = np.repeat(rng.random((300, 2)), 7, axis=0)
    angles = knnrefine.datasets.trp_chi1_chi2()[:5000]
    yield "uniform", uniform, (0, 0, 1, 1)
    yield "blobs", blobs, (0, 0, 1, 1)
    yield "lattice", lattice, (0, 0, 1, 1)
    yield "duplicates", dup, (0, 0, 1, 1)
    yield "angles", angles, (0, 0, 360, 360)


def digest(*arrays):
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def space_inputs():
    rng = np.random.default_rng(1)
    uniform = rng.random((3000, 3))
    blobs = np.mod(np.concatenate([rng.normal(0.3, 0.03, (1500, 3)), rng.random((800, 3))]), 1.0)
    yield "space uniform", uniform
    yield "space blobs", blobs


def sphere_inputs():
    rng = np.random.default_rng(2)
    uniform = rng.random((4000, 2)) * [360.0, 180.0] - [180.0, 90.0]
    pole = np.column_stack([rng.random(1500) * 360.0 - 180.0, 90.0 - rng.random(1500) * 2.0])
    seam = np.column_stack([179.0 + rng.random(1500) * 2.0, rng.random(1500) * 4.0])
    seam[:, 0] = np.where(seam[:, 0] >= 180.0, seam[:, 0] - 360.0, seam[:, 0])
    yield "sphere uniform", uniform
    yield "sphere pole", np.concatenate([pole, uniform[:500]])
    yield "sphere seam", np.concatenate([seam, uniform[:500]])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--domains", nargs="+", default=["plane"],
                        choices=["plane", "space", "sphere"])  # fmt: skip
    domains = parser.parse_args().domains
    warnings.simplefilter("ignore")
    if "plane" in domains:
        plane()
    if "space" in domains:
        for name, pts in space_inputs():
            for periodic in (False, True, (True, False, True)):
                for k, tau in ((2, 3.0), (10, 3.0), (30, 6.0)):
                    mesh = knnrefine.refine(pts, k, tau, periodic=periodic,
                                            box=(0, 0, 0, 1, 1, 1),
                                            min_size=1e-3 if k <= 2 else None)  # fmt: skip
                    _line(f"{name} periodic={periodic} k={k} tau={tau}", mesh)
    if "sphere" in domains:
        for name, pts in sphere_inputs():
            for k, tau in ((2, 3.0), (10, 3.0), (30, 6.0)):
                mesh = knnrefine.refine(pts, k, tau, sphere=True)
                print(f"{name} k={k} tau={tau}: m={len(mesh.xyz)} t={len(mesh.cells)} "
                      f"{digest(mesh.xyz, mesh.cells, mesh.kinds)} "
                      f"{digest(mesh.vertices, mesh.cells, mesh.kinds, mesh.order)}")  # fmt: skip


def _line(label, mesh):
    t = mesh.torus
    torus = digest(t.vertices, t.cells, t.offsets, t.kinds)
    user = digest(mesh.vertices, mesh.cells,
                  mesh.offsets if mesh.offsets is not None else np.zeros(0), mesh.kinds,
                  mesh.order)  # fmt: skip
    print(f"{label}: m={len(t.vertices)} t={len(t.cells)} {torus} {user}")


def plane():
    for name, pts, box in inputs():
        for periodic in (False, True, (True, False), (False, True)):
            for k, tau in ((1, 3.0), (2, 3.0), (5, 2.5), (10, 3.0), (30, 6.0), (200, 10.0)):
                label = f"{name} periodic={periodic} k={k} tau={tau}"
                floor = 1e-3 * (box[2] - box[0]) if k <= 2 else None
                try:
                    mesh = knnrefine.refine(pts, k, tau, periodic=periodic, box=box, min_size=floor)
                except knnrefine.InputError as exc:
                    print(f"{label}: refused ({str(exc)[:40]})")
                    continue
                t = mesh.torus
                links = getattr(t, "neighbours", None)
                if links is None:
                    links = getattr(t, "neighbors", None)  # a tree before the spelling changed
                torus = digest(t.vertices, t.triangles, t.offsets, links, t.kinds)
                user = digest(
                    mesh.vertices,
                    mesh.triangles,
                    mesh.offsets if mesh.offsets is not None else np.zeros(0),
                    mesh.kinds,
                    mesh.order,
                )
                print(f"{label}: m={len(t.vertices)} t={len(t.triangles)} {torus} {user}")


if __name__ == "__main__":
    main()
