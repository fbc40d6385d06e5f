"""orient2d and incircle against exact rational arithmetic (fractions.Fraction)."""

from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from knnrefine._engine import predicates
from knnrefine._engine.jit import python_entry

# internal kernels, called from Python through jitted entries
expansion_product = python_entry(predicates.expansion_product)
expansion_sum = python_entry(predicates.expansion_sum)
incircle = python_entry(predicates.incircle)
orient2d = python_entry(predicates.orient2d)
two_product = python_entry(predicates.two_product)
two_sum = python_entry(predicates.two_sum)


def sign(x):
    return (x > 0) - (x < 0)


def orient_exact(a, b, c):
    ax, ay, bx, by, cx, cy = map(Fraction, (*a, *b, *c))
    return sign((ax - cx) * (by - cy) - (ay - cy) * (bx - cx))


def incircle_exact(a, b, c, d):
    ax, ay, bx, by, cx, cy, dx, dy = map(Fraction, (*a, *b, *c, *d))
    adx, ady, bdx, bdy, cdx, cdy = ax - dx, ay - dy, bx - dx, by - dy, cx - dx, cy - dy
    return sign(
        (adx * adx + ady * ady) * (bdx * cdy - cdx * bdy)
        + (bdx * bdx + bdy * bdy) * (cdx * ady - adx * cdy)
        + (cdx * cdx + cdy * cdy) * (adx * bdy - bdx * ady)
    )


def ulp_nudge(rng, p, size=3):
    return p + rng.integers(-size, size + 1, 2) * np.spacing(p)


@pytest.mark.parametrize("scale", [1e-12, 1e-3, 1.0, 1e3, 1e12])
def test_orient_near_collinear(scale):
    rng = np.random.default_rng(0)
    for _ in range(500):
        a = rng.random(2) * scale + scale * rng.integers(-3, 4)
        b = rng.random(2) * scale
        c = ulp_nudge(rng, a + rng.random() * (b - a))
        assert orient2d(*a, *b, *c) == orient_exact(a, b, c)


@pytest.mark.parametrize("scale", [1e-9, 1.0, 1e6])
def test_incircle_near_cocircular(scale):
    rng = np.random.default_rng(1)
    for _ in range(500):
        centre = rng.random(2) * scale * 100
        r = scale * (0.1 + rng.random())
        t = rng.random(4) * 2 * np.pi
        pts = [centre + r * np.array([np.cos(x), np.sin(x)]) for x in t]
        pts[3] = ulp_nudge(rng, pts[3], 2)
        assert incircle(*pts[0], *pts[1], *pts[2], *pts[3]) == incircle_exact(*pts)


def test_exactly_degenerate_cases():
    # lattice points: collinear triples and cocircular quadruples are exactly zero
    assert orient2d(0.0, 0.0, 1.0, 1.0, 3.0, 3.0) == 0
    assert incircle(0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.0, 1.0) == 0
    assert incircle(0.0, 0.0, 2.0, 0.0, 2.0, 1.0, 0.0, 1.0) == 0  # a rectangle is cyclic
    # a classic failure of naive floating point (points nearly on a line, 1e-17 apart)
    a, b = (0.5, 0.5), (12.0, 12.0)
    c = (24.0, 24.0 + 2**-48)
    assert orient2d(*a, *b, *c) == orient_exact(a, b, c) == 1
    # rotated lattice as in delaunator's robustness4 fixture: rounding everywhere
    rot = np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]])
    g = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [2, 2], [2, 0]], float) @ rot.T
    for i, j, k_, l in [(0, 1, 2, 3), (0, 5, 4, 3), (1, 5, 4, 2)]:
        assert incircle(*g[i], *g[j], *g[k_], *g[l]) == incircle_exact(g[i], g[j], g[k_], g[l])
    for i, j, k_ in [(0, 2, 4), (1, 2, 3), (0, 1, 5)]:
        assert orient2d(*g[i], *g[j], *g[k_]) == orient_exact(g[i], g[j], g[k_])


def test_incircle_sign_convention():
    a, b, c = (0.0, 0.0), (1.0, 0.0), (0.0, 1.0)  # counter-clockwise
    assert incircle(*a, *b, *c, 0.25, 0.25) == 1
    assert incircle(*a, *b, *c, 2.0, 2.0) == -1
    assert incircle(*a, *c, *b, 0.25, 0.25) == -1  # clockwise reverses the sign


# the documented domain: zero or magnitudes in [1e-50, 1e50] (no product under- or overflows)
magnitude = st.floats(min_value=1e-50, max_value=1e6)
finite = st.one_of(st.just(0.0), magnitude, magnitude.map(lambda x: -x))


@settings(max_examples=300, deadline=None)
@given(st.lists(finite, min_size=6, max_size=6), st.integers(0, 4))
def test_orient_property(xs, nudge):
    a, b = np.array(xs[:2]), np.array(xs[2:4])
    c = a + 0.5 * (b - a) + nudge * np.spacing(np.array(xs[4:6]) + 1.0)
    assert orient2d(*a, *b, *c) == orient_exact(a, b, c)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(-20, 20), min_size=8, max_size=8), st.sampled_from([1.0, 0.1, 2**-40]))
def test_incircle_on_integer_grids(ij, step):
    """Grid points make exact cocircularity common."""
    p = np.array(ij, float).reshape(4, 2) * step
    assert incircle(*p[0], *p[1], *p[2], *p[3]) == incircle_exact(*p)


def test_expansion_arithmetic_is_exact():
    rng = np.random.default_rng(3)
    for _ in range(200):
        x, y = rng.normal(size=2) * 10.0 ** rng.integers(-20, 20, 2)
        s, e = two_sum(x, y)
        assert Fraction(s) + Fraction(e) == Fraction(x) + Fraction(y)
        p, e = two_product(x, y)
        assert Fraction(p) + Fraction(e) == Fraction(x) * Fraction(y)
        ea = np.array(sorted(rng.normal(size=3) * [1e-20, 1e-5, 1.0], key=abs))
        fa = np.array(sorted(rng.normal(size=2) * [1e-10, 1e3], key=abs))
        h = np.empty(16)
        n = expansion_sum(ea, 3, fa, 2, h)
        assert sum(map(Fraction, h[:n])) == sum(map(Fraction, ea)) + sum(map(Fraction, fa))
        n = expansion_product(ea, 3, fa, 2, h)
        assert sum(map(Fraction, h[:n])) == sum(map(Fraction, ea)) * sum(map(Fraction, fa))
