"""Property tests: any small input, periodic or not, any k and tau: refine either returns a
mesh that certify passes, or rejects the input with an InputError that the input deserves.
No kernel may crash. (Profiles: see conftest.py; CI's examples are fixed.)"""

import re

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

import knnrefine
from knnrefine import InputError, certify
from knnrefine._validation import MIN_SIDE

unit = st.floats(0.0, 1.0, allow_nan=False)


@st.composite
def point_sets(draw):
    """Points in the unit square: random, some duplicated, some on a lattice, some on the
    sides (the seam when periodic); then scaled (tiny to huge) and offset."""
    n = draw(st.integers(1, 40))
    pts = draw(st.lists(st.tuples(unit, unit), min_size=n, max_size=n))
    pts = np.array(pts, float).reshape(-1, 2)
    extra = []
    if draw(st.booleans()):  # duplicates
        reps = draw(st.integers(1, 6))
        extra.append(np.repeat(pts[: draw(st.integers(1, len(pts)))], reps, axis=0))
    if draw(st.booleans()):  # a lattice
        side = draw(st.integers(2, 6))
        g = np.arange(side) / side
        extra.append(np.stack(np.meshgrid(g, g), -1).reshape(-1, 2))
    if draw(st.booleans()):  # on the sides of the box
        s = np.array(draw(st.lists(unit, min_size=1, max_size=8)))
        extra.append(np.stack([s, np.zeros_like(s)], 1))
        extra.append(np.stack([np.ones_like(s), s], 1))
    pts = np.concatenate([pts] + extra)
    scale = draw(st.sampled_from([1e-9, 2.0**-20, 1.0, 360.0, 1e9]))
    offset = draw(st.sampled_from([0.0, -180.0, 1e6]))
    return pts * scale + offset, scale, offset


@given(
    point_sets(),
    st.integers(1, 12),
    st.floats(2.2, 6.0),
    st.sampled_from([False, True, (True, False), (False, True)]),
    st.booleans(),
)
def test_refine_is_certified_or_rejected(data, k, tau, periodic, floor_on_box):
    pts, scale, offset = data
    box = None
    if periodic is not False or floor_on_box:
        box = (offset, offset, offset + scale, offset + scale)
    # k = 1 and heavy duplicates refine down to the floor: keep it coarse enough to be quick
    min_size = 1e-3 * scale if k <= 2 else None
    kwargs = dict(periodic=periodic, box=box, min_size=min_size)
    try:
        mesh = knnrefine.refine(pts, k, tau, **kwargs)
    except InputError as exc:
        assert_deserved(exc, pts, k, tau, box, kwargs)
        return
    cert = certify(mesh, pts, samples=5000, n_random=2000)
    assert cert.passed, str(cert)
    assert mesh.vertices.shape[1] == 2 and np.isfinite(mesh.vertices).all()


@given(
    st.one_of(
        st.lists(
            st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=2, max_size=2),
            max_size=5,
        ),
        st.lists(st.integers(), max_size=6),
        st.text(max_size=5),
        st.lists(st.lists(st.floats(-1, 1), min_size=1, max_size=4), max_size=4),
    ),
    st.integers(-3, 5),
    st.floats(allow_nan=True, allow_infinity=True),
)
def test_garbage_is_rejected_cleanly(points, k, tau):
    """Whatever comes in, the answer is a mesh or an InputError: never a crash in a kernel."""
    try:
        knnrefine.refine(points, k, tau, max_vertices=20_000)
    except InputError:
        pass
    except knnrefine.BudgetError:
        pass


def assert_deserved(exc, pts, k, tau, box, kwargs):
    """Only the refusals the documentation promises: k > n, a default box narrower than
    1e-100, a box spanning too few doubles at its magnitude (fewer than 2^24, up to the
    margin's share), or Theorem 6's precondition out of reach (whose message names a k that
    works)."""
    message = str(exc)
    the_box = box if box is not None else (*pts.min(axis=0), *pts.max(axis=0))
    steps = max(the_box[2] - the_box[0], the_box[3] - the_box[1]) / np.spacing(
        np.abs(the_box).max()
    )
    if "larger than the number of points" in message:
        assert k > len(pts), message
    elif "span only" in message:
        assert box is None and np.ptp(pts, axis=0).max() < MIN_SIDE, message
    elif "too small for its coordinates' magnitude" in message:
        assert steps < 2.0**26, message
    elif "the position within the period is lost" in message:
        assert steps < 2.0**26, message
    elif "cannot be certified" in message:
        found = re.search(r"use k <= (\d+)", message)
        if found:  # the largest k it names is accepted, and certified
            k_ok = int(found.group(1))
            mesh = knnrefine.refine(pts, k_ok, tau, **kwargs)
            assert certify(mesh, pts, samples=5000, n_random=2000).passed
    else:
        raise AssertionError(f"a valid input was rejected: {message}")
