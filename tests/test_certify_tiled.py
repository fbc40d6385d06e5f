"""certify strip by strip (certify(..., workers=N, executor=...), certify_store,
distributed.certify):
every answer about the points (disk counts, cell counts, d_{P,k}) equals the one-process
certify's, which reads one cKDTree of all points; and a bad mesh fails the same way."""

from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest
from conftest import gaussian_clusters, unit_box

import knnrefine
from knnrefine._domains.plane.certify import Geometry
from knnrefine._domains.plane.certify import Points as TorusPoints
from knnrefine.errors import InputError
from knnrefine.scale.checks import TiledTorusPoints
from knnrefine.scale.tiled import LocalStore, split_strips, strip_owner, strips


def test_split_strips_with_a_pad_per_row_against_brute_force():
    """Per-row pads up to past half the period: strip j holds exactly the rows within their
    pad of it (periodic distance along the strip axis, brute force), and each row has one
    owner, the strip whose [cut, next cut) holds it."""
    rng = np.random.default_rng(1)
    lx, ly = 0.8, 0.5
    xy = rng.random((20000, 2)) * [lx, ly]
    xy[:500] = [0.31, 0.2]  # a duplicate that several cuts fall on
    pads = rng.random(len(xy)) ** 4 * 0.5
    for tiles in (1, 2, 3, 7):
        regions = strips(xy, (lx, ly), tiles)[0]
        rows, bounds = split_strips(xy, regions, pads, (lx, ly))
        owner = strip_owner(xy, regions, (lx, ly))
        for j, (x0, _, w, _) in enumerate(regions):
            d = (xy[:, 0] - x0) % lx
            dist = np.where(d < w, 0.0, np.minimum(d - w, lx - d))
            got = rows[bounds[j] : bounds[j + 1]]
            assert np.all(np.diff(got) > 0)
            want = np.flatnonzero(dist <= pads * (1 - 1e-12))
            maybe = np.flatnonzero(dist <= pads * (1 + 1e-12) + 1e-15)
            assert np.isin(want, got).all() and np.isin(got, maybe).all()
            assert np.array_equal(np.flatnonzero(owner == j), np.flatnonzero(d < w))


@pytest.fixture(scope="module")
def pool():
    """Local processes for certify's strips (``executor=``)."""
    with ProcessPoolExecutor(2) as executor:
        yield executor


def _tori(mesh, pts, tiles, weights=None):
    store = LocalStore(pts, weights, tiles)
    return TorusPoints(mesh, pts, weights, -1), TiledTorusPoints(mesh, store, tiles, -1), store


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("tiles", [2, pytest.param(5, marks=pytest.mark.slow)])
def test_strip_answers_equal_one_tree(tiles, weighted):
    """Disks of every size (up to past the whole torus), every cell, d_{P,k} anywhere: the
    strips' sums and decisions equal one cKDTree's answers, exactly."""
    pts = gaussian_clusters(30000, 2)
    w = np.random.default_rng(3).integers(0, 3, len(pts)).astype(float) if weighted else None
    k = 20.0 if weighted else 20
    mesh = knnrefine.refine(pts, k, periodic=(True, False), box=(0, 0, 1, 1), weights=w)
    one, tiled, store = _tori(mesh, pts, tiles, w)
    try:
        rng = np.random.default_rng(4)
        centres = rng.random((3000, 2)) * one.period
        radii = 10 ** rng.uniform(-3, 0.2, len(centres))
        np.testing.assert_array_equal(tiled.held(centres, radii), one.held(centres, radii))
        geometry = Geometry(mesh, -1)
        cells = geometry.cells(geometry.triangulation())
        np.testing.assert_array_equal(tiled.cell_counts(cells), one.cell_counts(cells))
        x = rng.random((5000, 2)) * one.period
        np.testing.assert_array_equal(tiled.d_pk(x), one.d_pk(x))
    finally:
        store.close()


def test_a_wrong_mesh_fails_the_same_strip_by_strip(pool):
    """A mesh of other points (dense where these are sparse): the guesses of d_{P,k} from
    the mesh are far too small, the strips ask again with wider pads, and the certificate
    (failed) equals the one-process certificate in every count and ratio."""
    rng = np.random.default_rng(5)
    made_from = gaussian_clusters(20000, 6)
    mesh = knnrefine.refine(made_from, 10, periodic=True, box=(0, 0, 1, 1))
    other = np.mod(rng.random((20000, 2)) * 0.3, 1.0)  # all in one corner
    a = knnrefine.certify(mesh, other, samples=5000, n_random=1000)
    b = knnrefine.certify(mesh, other, samples=5000, n_random=1000, workers=3, executor=pool)
    assert not a.passed and not b.passed
    for field in ("max_ball_count", "max_cell_count", "alpha_hat", "beta_hat", "size_integral"):
        assert getattr(a, field) == getattr(b, field), field
    _, tiled, store = _tori(mesh, other, 3)
    try:
        x = np.random.default_rng(7).random((2000, 2))
        tiled.d_pk(x)
        assert tiled.passes > 1  # the first pad was too narrow somewhere: asked again
    finally:
        store.close()


@pytest.mark.parametrize("periodic", [True, False])
def test_certify_in_tiles_equals_certify(periodic, pool):
    pts = gaussian_clusters(40000, 8)
    mesh = knnrefine.refine(pts, 30, periodic=periodic, box=(0, 0, 1, 1))
    a = knnrefine.certify(mesh, pts, samples=10000, n_random=2000)
    b = knnrefine.certify(mesh, pts, samples=10000, n_random=2000, workers=2, executor=pool)
    assert a.passed and b.passed
    for field in ("max_ball_count", "max_cell_count", "alpha_hat", "beta_hat", "size_integral",
                  "precondition_ok", "n", "m"):  # fmt: skip
        assert getattr(a, field) == getattr(b, field), field


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_bad_workers_are_refused(bad):
    pts = gaussian_clusters(2000, 9)
    mesh = knnrefine.refine(pts, 10)
    with pytest.raises(InputError, match="workers must be a positive integer"):
        knnrefine.certify(mesh, pts, workers=bad)


def test_an_executor_is_checked_before_any_work(pool):
    """certify's executor as refine's: something with a map, for workers >= 2 strips, in a
    box (the sphere has no strips); each refused with what to do."""
    pts = gaussian_clusters(2000, 9)
    mesh = knnrefine.refine(pts, 10)
    with pytest.raises(InputError, match="concurrent.futures.Executor"):
        knnrefine.certify(mesh, pts, workers=2, executor="pool")
    with pytest.raises(InputError, match="workers >= 2"):
        knnrefine.certify(mesh, pts, executor=pool)
    lonlat = np.column_stack([pts[:, 0] * 360 - 180, pts[:, 1] * 180 - 90])
    on_sphere = knnrefine.refine(lonlat, 10, sphere=True)
    with pytest.raises(InputError, match="drop executor="):
        knnrefine.certify(on_sphere, lonlat, workers=2, executor=pool)


@pytest.mark.parametrize("domain", ["plane", "space", "sphere"])
def test_certify_with_workers_threads_equals_one_thread(domain):
    """workers is threads in every domain, refine's and certify's: workers=2 accepted and
    certified, the same certificate at 1 and 2 threads."""
    rng = np.random.default_rng(14)
    if domain == "sphere":
        pts = np.column_stack([rng.uniform(-180, 180, 3000), rng.uniform(-60, 60, 3000)])
        mesh = knnrefine.refine(pts, 10, sphere=True, workers=2)
    else:
        pts = gaussian_clusters(1500, 14, dim=2 if domain == "plane" else 3)
        mesh = knnrefine.refine(pts, 10, workers=2)
    a = knnrefine.certify(mesh, pts, workers=1, samples=2000)
    b = knnrefine.certify(mesh, pts, workers=2, samples=2000)
    assert a.passed and b.passed
    for field in ("max_ball_count", "max_cell_count", "alpha_hat", "beta_hat", "size_integral"):
        assert getattr(a, field) == getattr(b, field), field


@pytest.mark.parametrize("workers", [2, 8])
def test_strips_that_hold_no_point(workers, pool):
    """regression (issue 28): certify(mesh, points, workers=2) crashed ('cannot reshape array
    of size 0') when a strip held no point, as with more strips than points. Points in a
    third of the torus, and five points at ten workers: the same verdict as in one process."""
    rng = np.random.default_rng(0)
    pts = rng.random((300, 2)) * [0.3, 1.0]
    mesh = knnrefine.refine(pts, 10, periodic=True, box=(0, 0, 1, 1))
    one = knnrefine.certify(mesh, pts)
    tiled = knnrefine.certify(mesh, pts, workers=workers, executor=pool)
    assert one.passed and tiled.passed
    assert (tiled.max_ball_count, tiled.max_cell_count) == (one.max_ball_count, one.max_cell_count)
    few = rng.random((5, 2))
    small = knnrefine.refine(few, 2, periodic=True, box=(0, 0, 1, 1))
    assert knnrefine.certify(small, few, workers=10, executor=pool).passed


# -- in space: the same questions asked of slabs -----------------------------------------------

BOX3 = unit_box(3)
FIELDS3 = ("max_ball_count", "max_cell_count", "alpha_hat", "beta_hat", "size_integral",
           "precondition_ok", "n", "m", "n_probes", "under_floor", "weight")  # fmt: skip


def test_slab_answers_in_space_equal_one_tree():
    """Balls of every size, every cell, d_{P,k} in the box's own metric at probes in the box
    (a torus shorter than twice the box along x and z, where the torus' and the box's
    metrics differ): the slabs' sums and decisions equal one process's kd-trees, exactly."""
    from knnrefine._domains.space.certify import Geometry as SpaceGeometry
    from knnrefine._domains.space.certify import Points as SpacePoints
    from knnrefine.scale.checks import TiledSpacePoints

    pts = gaussian_clusters(4000, 4, clusters=25, dim=3)
    w = np.random.default_rng(1).integers(1, 4, len(pts)).astype(float)
    mesh = knnrefine.refine(pts, 30, periodic=(False, True, False), box=BOX3, weights=w)
    assert mesh.torus.period[2] < 2.0  # the embedding's margin from a bound on d_Pk
    one = SpacePoints(mesh, pts, w, -1)
    store = LocalStore(pts, w, 3)
    try:
        tiled = TiledSpacePoints(mesh, store, 3, -1)
        rng = np.random.default_rng(10)
        centres = rng.random((2000, 3)) * one.period
        radii = 10 ** rng.uniform(-3, 0.2, len(centres))
        np.testing.assert_array_equal(tiled.held(centres, radii), one.held(centres, radii))
        geometry = SpaceGeometry(mesh, -1)
        cells = geometry.cells(geometry.triangulation())
        np.testing.assert_array_equal(tiled.cell_counts(cells), one.cell_counts(cells))
        x = one.metric.frame(rng.random((3000, 3)))  # probes in the box
        np.testing.assert_array_equal(tiled.d_pk(x), one.d_pk(x))
    finally:
        store.close()


def test_input_point_probes_are_the_same_in_one_process_and_in_strips():
    """The input points certify probes (up to 2 m, drawn by ``_sampling``'s keys) are the
    same in one process and over strips or slabs, in the same order (repeated points, points
    on a line and on the cut among them), so that an extreme attained at an input point is
    found on both paths. (A wrong mesh's beta_hat lies at
    an input point; the paths drew their points apart, and agreed by chance until issue
    52 drew the one-process sample from the tree: test_a_wrong_mesh_fails_the_same_strip_
    by_strip failed.)"""
    from knnrefine._domains.plane.certify import Points as PlanePoints
    from knnrefine._domains.space.certify import Points as SpacePoints
    from knnrefine.scale.checks import TiledSpacePoints

    rng = np.random.default_rng(6)
    pts = gaussian_clusters(6000, 6)
    line = np.column_stack([rng.random(300), np.full(300, 0.5)])  # on a line
    line[:100, 0] = 0.0  # on the cut
    pts = np.concatenate([pts, pts[:400], line])  # repeated points: keys tie
    mesh = knnrefine.refine(pts, 10, periodic=True, box=(0, 0, 1, 1))
    one = PlanePoints(mesh, pts, None, -1)
    _, tiled, store = _tori(mesh, pts, 3)
    try:
        for count in (100, 2 * len(mesh.vertices), 10**6):
            a, b = one.sample_points(count, rng), tiled.sample_points(count, rng)
            np.testing.assert_array_equal(a, b)
            assert 0.5 * min(count, len(pts)) < len(a) <= len(pts)
    finally:
        store.close()
    pts3 = gaussian_clusters(3000, 7, dim=3)
    mesh3 = knnrefine.refine(pts3, 10, periodic=(False, True, False), box=BOX3)
    store = LocalStore(pts3, None, 3)
    try:
        tiled3 = TiledSpacePoints(mesh3, store, 3, -1)
        one3 = SpacePoints(mesh3, pts3, None, -1)
        np.testing.assert_array_equal(
            one3.sample_points(1000, rng), tiled3.sample_points(1000, rng)
        )
    finally:
        store.close()


def test_bound_counts_in_space_are_in_the_box_metric():
    """Issue 52's bug: the Lipschitz bounds' ball counts (``Points.fewer``) were asked in the
    torus' metric while d_{P,k} is in the box's own; on a torus shorter than twice the box
    (the embedding's margin from a bound on d_Pk) balls near a face reached points across
    it, so a count could settle a probe that might be an extreme. Balls about the faces
    along the non-periodic axes, in one process (both modes) and over slabs, against the
    box metric's brute force; the torus' metric decides some of them otherwise."""
    from knnrefine._domains.space.certify import Points as SpacePoints
    from knnrefine.scale.checks import TiledSpacePoints

    pts = gaussian_clusters(4000, 4, clusters=25, dim=3)
    w = np.random.default_rng(1).integers(1, 4, len(pts)).astype(float)
    mesh = knnrefine.refine(pts, 30, periodic=(False, True, False), box=BOX3, weights=w)
    one = SpacePoints(mesh, pts, w, -1)
    assert one.period[2] < 2.0
    rng = np.random.default_rng(11)
    x = rng.random((400, 3))
    x[:, 2] = rng.choice([0.01, 0.99], len(x))  # beside the faces z = 0 and z = 1
    x[:100, 0] = rng.choice([0.01, 0.99], 100)  # and x = 0, x = 1
    centres = one.metric.frame(x)
    framed = one.metric.frame(pts)

    def distances(period):
        g = centres[:, None, :] - framed[None, :, :]
        g -= np.where(period > 0, period, 1.0) * np.rint(g / np.where(period > 0, period, np.inf))
        return np.sqrt((g**2).sum(-1))

    radii = rng.uniform(0.3, 0.9, len(x))
    box = (w * (distances(one.box_period) <= radii[:, None])).sum(axis=1)
    torus = (w * (distances(one.period) <= radii[:, None])).sum(axis=1)
    assert (torus > box).sum() > 50  # balls reaching across a face on the torus
    # per ball: k just above its count in the box's metric (fewer; on the torus, not
    # always), or at it (not fewer in either)
    k = box + np.where(rng.random(len(x)) < 0.7, 1.0, 0.0)
    want = box < k
    assert want.sum() > 200 and (~want).sum() > 50
    assert ((torus < k) != want).sum() > 30  # the torus' metric would decide these wrongly

    def fewer(questions, **kw):
        return np.array([questions.fewer(centres[i : i + 1], radii[i : i + 1], k[i], **kw)[0]
                         for i in range(len(k))])  # fmt: skip

    for mostly in (True, False):
        np.testing.assert_array_equal(fewer(one, mostly=mostly), want)
    store = LocalStore(pts, w, 3)
    try:
        tiled = TiledSpacePoints(mesh, store, 3, -1)
        np.testing.assert_array_equal(fewer(tiled), want)
    finally:
        store.close()


@pytest.mark.slow
def test_certify_in_space_with_workers_equals_certify(pool):
    """workers > 1 in space: the same certificate as one process, field by field; a mesh of
    other points fails in both, with the same figures (a box periodic along y only: the
    slabs' kd-trees straight along x and z; the answers' equality on such a torus is
    test_slab_answers_in_space_equal_one_tree's)."""
    periodic = (False, True, False)
    pts = gaussian_clusters(4000, 11, dim=3)
    mesh = knnrefine.refine(pts, 15, periodic=periodic, box=BOX3)
    options = dict(samples=10_000, n_random=2_000)
    a = knnrefine.certify(mesh, pts, **options)
    b = knnrefine.certify(mesh, pts, workers=2, executor=pool, **options)
    assert a.passed and b.passed
    for field in FIELDS3:
        assert getattr(a, field) == getattr(b, field), field
    other = np.random.default_rng(12).random((4000, 3)) * 0.3  # all in one corner
    a = knnrefine.certify(mesh, other, **options)
    b = knnrefine.certify(mesh, other, workers=3, executor=pool, **options)
    assert not a.passed and not b.passed
    for field in FIELDS3:
        assert getattr(a, field) == getattr(b, field), field
