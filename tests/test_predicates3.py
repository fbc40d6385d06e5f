"""orient3d and insphere (_engine/predicates3.py) against exact rational arithmetic
(fractions.Fraction determinants), on random, exactly coplanar / cospherical and
one-ulp-perturbed inputs: the floating-point filter never decides a sign wrongly and the
exact fallback decides the rest."""

import itertools
from fractions import Fraction

import numpy as np
import pytest

from knnrefine._engine import predicates3
from knnrefine._engine.jit import python_entry

_insphere = python_entry(predicates3.insphere)
_orient3d = python_entry(predicates3.orient3d)


def orient3d(a, b, c, d):
    return _orient3d(np.array([a, b, c, d], float))


def insphere(a, b, c, d, e):
    return _insphere(np.array([a, b, c, d, e], float))


def det(rows):
    """Exact determinant by fraction-free elimination (rows of Fractions)."""
    m = [list(r) for r in rows]
    n, sign = len(m), 1
    for i in range(n):
        pivot = next((r for r in range(i, n) if m[r][i] != 0), None)
        if pivot is None:
            return Fraction(0)
        if pivot != i:
            m[i], m[pivot] = m[pivot], m[i]
            sign = -sign
        for r in range(i + 1, n):
            f = m[r][i] / m[i][i]
            m[r] = [x - f * y for x, y in zip(m[r], m[i], strict=True)]
    out = Fraction(sign)
    for i in range(n):
        out *= m[i][i]
    return out


def sign(x):
    return (x > 0) - (x < 0)


def exact_orient3d(a, b, c, d):
    F = [[Fraction(float(p[i])) - Fraction(float(d[i])) for i in range(3)] for p in (a, b, c)]
    return sign(det(F))


def exact_insphere(a, b, c, d, e):
    rows = []
    for p in (a, b, c, d):
        r = [Fraction(float(p[i])) - Fraction(float(e[i])) for i in range(3)]
        rows.append(r + [sum(x * x for x in r)])
    return sign(det(rows))


def test_the_signs_are_pinned_on_the_unit_tetrahedron():
    o, x, y, z = (np.array(p, float) for p in ((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)))
    assert orient3d(x, y, z, o) == exact_orient3d(x, y, z, o) == 1
    assert orient3d(y, x, z, o) == -1
    centre = np.array([0.25, 0.25, 0.25])
    far = np.array([3.0, 3.0, 3.0])
    assert insphere(x, y, z, o, centre) == 1 and insphere(x, y, z, o, far) == -1
    assert insphere(y, x, z, o, centre) == -1  # reversed for the other orientation
    assert insphere(x, y, z, o, np.array([1.0, 1.0, 1.0])) == 0  # the cube's corner


def _ulp_variants(p, rng, count):
    """p moved by a few ulps along random axes."""
    out = []
    for _ in range(count):
        q = p.copy()
        a = rng.integers(0, 3)
        steps = int(rng.integers(-3, 4))
        for _ in range(abs(steps)):
            q[a] = np.nextafter(q[a], np.inf if steps > 0 else -np.inf)
        out.append(q)
    return out


def test_orient3d_on_exactly_coplanar_and_perturbed_points():
    """Points of the plane z = x / 2 + y / 4 (exact in binary), translated off the origin,
    and the fourth moved by up to 3 ulps: every sign as the rationals say, the zeros too."""
    rng = np.random.default_rng(0)
    checked = zeros = 0
    for _ in range(150):
        xy = rng.integers(-(2**20), 2**20, (4, 2)) * 2.0**-20
        pts = np.column_stack([xy, xy[:, 0] / 2 + xy[:, 1] / 4]) + np.array([0.375, 1.5, 0.75])
        for d in [pts[3], *_ulp_variants(pts[3], rng, 4)]:
            want = exact_orient3d(pts[0], pts[1], pts[2], d)
            assert orient3d(pts[0], pts[1], pts[2], d) == want
            checked += 1
            zeros += want == 0
    assert zeros >= 100 and checked - zeros >= 300  # both kinds were met


def _sphere_points():
    """Integer points on the sphere of radius 5 (exact), all sign changes and orders."""
    base = [(3, 4, 0), (5, 0, 0), (0, 3, 4), (4, 0, 3), (0, 0, 5)]
    out = set()
    for p in base:
        for perm in itertools.permutations(p):
            for s in itertools.product((1, -1), repeat=3):
                out.add(tuple(a * b for a, b in zip(perm, s, strict=True)))
    return np.array(sorted(out), float)


def test_insphere_on_cospherical_and_perturbed_points():
    """Five points of one sphere (scaled by 2^-7, translated) are cospherical: 0 exactly;
    moved by up to 3 ulps the sign is the rationals'; both filter and fallback are hit."""
    rng = np.random.default_rng(1)
    sphere = _sphere_points() * 2.0**-7 + np.array([0.8125, 0.3125, 1.0625])
    checked = zeros = 0
    for _ in range(120):
        i = rng.choice(len(sphere), 5, replace=False)
        a, b, c, d, e = sphere[i]
        if exact_orient3d(a, b, c, d) == 0:
            continue
        for q in [e, *_ulp_variants(e, rng, 3)]:
            want = exact_insphere(a, b, c, d, q)
            assert insphere(a, b, c, d, q) == want
            checked += 1
            zeros += want == 0
    assert zeros >= 50 and checked - zeros >= 150


def test_random_and_lattice_inputs_agree_with_the_rationals():
    """Random points (most decided by the filter) and points of a cubic lattice (many exact
    zeros: the corners of a cube are cospherical, a face's are coplanar)."""
    rng = np.random.default_rng(2)
    lattice = np.array(list(itertools.product(range(3), repeat=3)), float) * 0.125 + 0.5
    for pts in (rng.random((300, 5, 3)), lattice[rng.integers(0, len(lattice), (300, 5))]):
        for a, b, c, d, e in pts:
            assert orient3d(a, b, c, d) == exact_orient3d(a, b, c, d)
            assert insphere(a, b, c, d, e) == exact_insphere(a, b, c, d, e)


@pytest.mark.parametrize("scale", [1e-20, 1.0, 1e20])
def test_signs_hold_at_any_scale(scale):
    """Tiny and huge coordinates (within the documented range): the same signs."""
    rng = np.random.default_rng(3)
    sphere = _sphere_points() * scale
    for _ in range(40):
        a, b, c, d, e = sphere[rng.choice(len(sphere), 5, replace=False)]
        e = e * (1 + 2.0**-52)
        assert insphere(a, b, c, d, e) == exact_insphere(a, b, c, d, e)
        assert orient3d(a, b, c, e) == exact_orient3d(a, b, c, e)
