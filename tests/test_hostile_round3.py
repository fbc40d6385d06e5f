"""The third hostile round (issue 50): each bug a tester found, as a test named after it that
fails on the code before its fix."""

import dataclasses

import numpy as np
import pytest

import knnrefine

TAMPER_CASES = [
    ("plane, ordinary box", 2, {}),
    ("plane, torus", 2, {"periodic": True, "box": (0, 0, 1, 1)}),
    ("plane, periodic in x", 2, {"periodic": (True, False), "box": (0, 0, 1, 1)}),
    ("space, ordinary box", 3, {}),
    ("space, torus", 3, {"periodic": True, "box": (0, 0, 0, 1, 1, 1)}),
    ("space, periodic in x and z", 3, {"periodic": (True, False, True), "box": (0, 0, 0, 1, 1, 1)}),
    ("sphere", 2, {"sphere": True}),
]


def _tampered(mesh, how, at):
    """The mesh with cell ``at`` dropped, replaced by a copy of the next one, or listed
    twice (its offsets with it)."""

    def edit(a):
        if a is None:
            return None
        if how == "dropped":
            return np.delete(a, at, 0)
        if how == "copied":
            return np.concatenate([a[:at], a[at + 1 : at + 2], a[at + 1 :]])
        return np.concatenate([a, a[at : at + 1]])

    return dataclasses.replace(mesh, cells=edit(mesh.cells), offsets=edit(mesh.offsets))


@pytest.mark.parametrize("name, dim, options", TAMPER_CASES, ids=[c[0] for c in TAMPER_CASES])
def test_certify_fails_a_mesh_with_a_dropped_copied_or_doubled_cell(name, dim, options, tmp_path):
    """Item 2: certify said "returned mesh ... PASSED" for a plane or space mesh with a cell
    dropped, replaced by a copy of another, or listed twice (the sphere's caught it): now the
    returned cells must each be listed once and tile the box, also after an .npz round trip.
    The untouched mesh passes; cells on the box's edge and in its middle are tampered."""
    rng = np.random.default_rng(dim)
    pts = rng.random((2000, dim))
    if options.get("sphere"):  # longitude and latitude in degrees
        pts = pts * [360.0, 180.0] - [180.0, 90.0]
    mesh = knnrefine.refine(pts, 10, **options)
    assert knnrefine.certify(mesh, pts, samples=5000).passed
    # a cell in the middle of the box and one at its edge (its first corner the lowest)
    corners = mesh.vertices[mesh.cells[:, 0]]
    middle = int(np.argmin(np.abs(corners - 0.5).sum(axis=1)))
    edge = int(np.argmin(corners.sum(axis=1)))
    for at in (middle, edge):
        for how in ("dropped", "copied", "doubled"):
            bad = _tampered(mesh, how, at)
            path = tmp_path / f"{how}.npz"
            knnrefine.io.write_mesh(bad, path, force=True)
            for m in (bad, knnrefine.io.read_mesh(path)):
                cert = knnrefine.certify(m, pts, samples=2000)
                assert not cert.passed, (name, how, at)
                # in a box the torus mesh is certified and the returned cells checked
                # against it; on the sphere the returned triangles are the triangulation
                flagged = cert.triangulation_problems if "sphere" in options else cert.mesh_problems
                assert flagged, (name, how, at)
                assert "FAILED" in str(cert)


def test_certify_names_what_is_wrong_with_a_tampered_cell_list():
    """Item 2: the problems say what is wrong: a hole, a cell listed twice, a facet of three
    cells; a cell naming a vertex that does not exist is a problem, not an IndexError."""
    pts = np.random.default_rng(5).random((2000, 2))
    mesh = knnrefine.refine(pts, 10, periodic=True, box=(0, 0, 1, 1))
    hole = knnrefine.certify(_tampered(mesh, "dropped", 7), pts, samples=2000).mesh_problems
    assert any("hole" in p for p in hole)
    twice = knnrefine.certify(_tampered(mesh, "doubled", 7), pts, samples=2000).mesh_problems
    assert any("listed more than once" in p for p in twice)
    assert any("more than two cells" in p for p in twice)
    cells = mesh.cells.copy()
    cells[3, 1] = len(mesh.vertices) + 5
    gone = knnrefine.certify(dataclasses.replace(mesh, cells=cells), pts, samples=2000)
    assert not gone.passed and any("does not exist" in p for p in gone.mesh_problems)
