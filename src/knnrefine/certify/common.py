"""What the plane's and space's certificates share: that the points are the run's own
(``check_source``), Lemma 2's precondition on the initial vertices (``check_precondition``) and
finding rows of integers in a table (``find_rows``), and that the points given to certify are
the mesh's (``check_points_are_the_meshs``). Weighted counts from kd-trees are
``metric``'s (``held_in_balls``, ``cell_tally``, ``weighted_kth``)."""

import numpy as np
from scipy.spatial import cKDTree

from ..errors import InputError
from ..validation import check_inside, check_made_from, weights_of_run


def check_source(stats, n, weight):
    """``n`` points of total ``weight`` (None: unweighted) are as many as the run with these
    stats was refined from, else InputError."""
    made_from, total = stats.get("n"), stats.get("weight")
    if made_from is not None and int(made_from) != n:
        raise InputError(
            f"the mesh was made from {int(made_from):,} points but the source holds "
            f"{n:,}: use the points it was refined from"
        )
    if (total is None) != (weight is None) or (
        total is not None and not np.isclose(weight, total, rtol=1e-9, atol=0)
    ):
        raise InputError(
            f"the mesh was refined with total weight {total} but the source's is "
            f"{weight}: give the weights it was refined with (or none)"
        )


def check_points_are_the_meshs(mesh, pts, weights=None):
    """A mesh is certified against the points it was made from: as many as it records, inside
    its box along non-periodic axes, with weights exactly when it was refined with weights
    (of the total it records). Anything else is an input error, not a failed certificate.
    Returns the weights as float64, or None."""
    check_made_from(mesh.stats, len(pts), "certify a mesh against")
    weights = weights_of_run(mesh.stats, len(pts), weights)
    dim = mesh.dim
    for a in range(dim):
        if mesh.periodic[a]:
            continue
        lo, hi = mesh.box[a], mesh.box[a + dim]
        out = (pts[:, a] < lo) | (pts[:, a] > hi)
        if out.any():
            raise InputError(
                f"{int(out.sum()):,} of the points lie outside the mesh's box along "
                f"{'xyz'[a]} ([{lo:g}, {hi:g}]), the first at index {int(np.argmax(out))}: these "
                "are not the points the mesh was refined from"
            )
    check_inside(pts, mesh.box, mesh.periodic, warn=False)  # periodic positions not lost
    return weights


def check_precondition(initial, torus, k, tau, period=None, spacing=None):
    """Lemma 2's base case, checked here independently of the engine: can the initial vertices
    be ordered so that each u has d_Pk(u) <= (K - 1) lambda_u, lambda_u its distance to the
    nearest earlier one (K = max(2 tau / (tau - 2), 3))? Peel: a vertex whose disk of radius
    (K - 1) x (distance to the nearest other remaining vertex) holds k points can go last.
    ``torus.held(centres, radii)`` counts the points; ``spacing(vertices)`` gives each
    vertex's distance to its nearest other one (default: on the torus of ``period``).
    Returns (ok, note)."""
    if spacing is None:

        def spacing(vertices):
            return cKDTree(vertices, boxsize=period).query(vertices, k=2)[0][:, 1]

    factor = max(2.0 * tau / (tau - 2.0), 3.0) - 1.0
    remaining = np.asarray(initial, float)
    if torus.total < k:
        return False, "n < k"
    rounds = 0
    while len(remaining) > 1:
        lam = spacing(remaining)
        ok = torus.held(remaining, factor * lam) >= k
        if not ok.any():
            return False, f"{len(remaining)} initial vertices have d_Pk > {factor:.3g} lambda"
        remaining = remaining[~ok]
        rounds += 1
    return True, f"{len(initial)} vertices ordered in {rounds} round{'s' if rounds != 1 else ''}"


def find_rows(table, rows):
    """Index of each of ``rows`` (rows of integers, as wide as ``table``'s) in ``table``, -1
    if absent: rows compared as bytes, one sort of the table."""
    if len(rows) == 0 or len(table) == 0:
        return np.full(len(rows), -1, np.int64)
    view = np.dtype((np.void, 8 * np.shape(table)[1]))
    a = np.ascontiguousarray(table, np.int64).view(view).ravel()
    b = np.ascontiguousarray(rows, np.int64).view(view).ravel()
    order = np.argsort(a, kind="stable")  # byte order, consistent for both searches
    i = np.minimum(np.searchsorted(a[order], b), len(a) - 1)
    return np.where(a[order][i] == b, order[i], -1)
