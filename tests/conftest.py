import os
from pathlib import Path

import numpy as np
import oracle
import pytest

SHARED_DATA = Path(
    os.environ.get(
        "KNNREFINE_SHARED_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
    )
)

# achieved ratio ranges, printed at the end of the run
ACHIEVED = []


def load_shared(name):
    path = SHARED_DATA / name
    if not path.exists():
        pytest.skip(f"{path} is not available (it ships with the development checkout only)")
    return np.loadtxt(path, delimiter=",", skiprows=1)


def assert_certified(mesh, points, label="", torus_ratio=None):
    """Check a mesh with the independent oracle and record the achieved ratio range.

    Always: the torus triangulation is a valid Delaunay triangulation; every vertex has aspect
    <= tau; every Voronoi cell and closed circumball above the floor holds < k points;
    d_{M,2} / d_{P,k} lies in [alpha, beta] on probes in the box (input points, vertices,
    circumcenters, random points) where d_{P,k} >= min_size; and the returned vertices give
    the same d_{M,2} in the box as the whole torus mesh. ``torus_ratio`` (default: when every
    axis is periodic or the initial mesh meets Theorem 6's precondition) also requires the
    bounds on the whole torus.
    """
    points = np.asarray(points, float)
    k, tau = mesh.k, mesh.tau
    rep = oracle.check_torus(mesh.torus, points, k, tau, min_size=mesh.min_size)
    assert rep.max_aspect <= tau, f"aspect {rep.max_aspect} > tau {tau}"
    assert rep.max_cell_count < k, f"a Voronoi cell holds {rep.max_cell_count} >= k points"
    assert rep.max_ball_count < k, f"a circumball holds {rep.max_ball_count} >= k points"
    vt, pt, frame = oracle.box_trees(mesh.vertices, points, mesh.box, mesh.periodic)
    probes = oracle.box_probes(mesh.vertices, points, mesh.box)
    # and the circumcenters of the returned triangles that lie in the box
    period = np.array(mesh.period)
    corners = mesh.vertices[mesh.triangles]
    if mesh.offsets is not None:
        corners = corners + mesh.offsets * period
    cc, _ = oracle.circumcenters(corners[:, 0], corners[:, 1], corners[:, 2])
    lo, hi = np.array(mesh.box[:2]), np.array(mesh.box[2:])
    for a in range(2):
        if mesh.periodic[a]:
            cc[:, a] = lo[a] + oracle.wrap(cc[:, a] - lo[a], period[a])
    probes = np.concatenate([probes, cc[np.all((cc >= lo) & (cc <= hi), axis=1)]])
    lo, hi = oracle.ratio_range(frame(probes), vt, pt, k, mesh.min_size, len(points))
    if len(points) >= k:
        assert rep.alpha <= lo and hi <= rep.beta, (lo, hi, rep.alpha, rep.beta)
        if torus_ratio is None:
            torus_ratio = all(mesh.periodic) or mesh.stats["m0_violations"] == 0
        if torus_ratio:
            assert rep.alpha <= rep.ratio_min and rep.ratio_max <= rep.beta, rep
    # completeness of the returned vertices: same d_{M,2} in the box as the whole torus
    torus_tree = oracle.cKDTree(mesh.torus.vertices, boxsize=mesh.torus.period)
    rel = oracle.wrap(probes - np.array(mesh.torus.origin), np.array(mesh.torus.period))
    full = torus_tree.query(rel, k=2)[0][:, 1]
    np.testing.assert_allclose(
        mesh.d_m2(probes),
        full,
        rtol=1e-9,
        atol=1e-12 * max(b - a for a, b in zip(mesh.box[:2], mesh.box[2:], strict=True)),
    )
    ACHIEVED.append(
        (label, len(points), k, tau, mesh.periodic, len(mesh.vertices), rep.max_aspect, lo, hi)
    )
    return rep, (lo, hi)


def pytest_terminal_summary(terminalreporter):
    if not ACHIEVED:
        return
    tr = terminalreporter
    tr.section("achieved d_M2 / d_Pk in the box (alpha, beta: Theorem 6)")
    tr.write_line(
        f"{'case':34s} {'n':>7s} {'k':>4s} {'tau':>4s} {'periodic':>14s} {'m':>7s} "
        f"{'aspect':>7s} {'min':>7s} {'max':>7s}"
    )
    for label, n, k, tau, per, m, asp, lo, hi in ACHIEVED:
        tr.write_line(
            f"{label[:34]:34s} {n:7d} {k:4d} {tau:4g} {str(per):>14s} {m:7d} "
            f"{asp:7.3f} {lo:7.3f} {hi:7.3f}"
        )
