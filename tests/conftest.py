import functools
import hashlib
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from scipy.spatial import cKDTree

import knnrefine

SHARED_DATA = Path(
    os.environ.get(
        "KNNREFINE_SHARED_DATA", Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
    )
)

# The suite runs the kernels it finds: a build's portable ones are not replaced by this CPU's
# compiled in the background (``_engine/shipped.upgrade``; tests/test_shipped.py turns it on
# where it tests it), which would compile while the tests run and write into the install.
os.environ.setdefault("KNNREFINE_HOST_KERNELS", "0")

# Property tests: CI runs a fixed, derandomized set of examples (the same every run, no
# example database); the wide search is a separate profile run by hand:
#     python -m pytest tests/test_properties.py tests/test_index.py --hypothesis-profile=wide
settings.register_profile(
    "ci",
    max_examples=60,
    derandomize=True,
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
settings.register_profile(
    "wide",
    max_examples=2000,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

# Every mesh a test makes with knnrefine.refine (directly, or through the API and the
# command line in this process) is certified, up to these sizes (certify takes seconds beyond
# them; the big runs in tests/ check their own results): at the end of the test, unless the
# test certified that mesh itself (then once is enough: the test's own call, with its own
# probes, is the certificate).
CERTIFY_UP_TO_POINTS = 200_000
CERTIFY_UP_TO_VERTICES = 400_000
CERTIFIED = {"meshes": 0, "by the test": 0, "skipped": 0, "again": 0}
# meshes already certified in this session: (points, weights, mesh) digests; a test that
# refines the same points to the same mesh again (cross-validation folds, refits) is not
# certified twice
CERTIFIED_DIGESTS = set()


def _digest(mesh, points, weights):
    parts = [points, mesh.vertices, np.asarray(mesh.box, float), np.asarray(mesh.periodic)]
    if weights is not None:
        parts.append(weights)
    h = hashlib.sha1()
    for a in parts:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest(), int(mesh.k), float(mesh.tau)


@pytest.fixture(autouse=True)
def certify_every_mesh(monkeypatch):
    import sys

    pipeline = knnrefine._pipeline  # every run in this process goes through its one entry
    refine_checked = pipeline.refine_checked
    steps = sys.modules["knnrefine.certify.steps"]  # its names are read at each call
    made, seen = [], set()

    def register(mesh, points, kwargs):
        if (
            mesh.stats["n"] <= CERTIFY_UP_TO_POINTS
            and mesh.stats["m_torus"] <= CERTIFY_UP_TO_VERTICES
        ):
            weights = kwargs.get("weights")
            copy = None if weights is None else np.array(weights, dtype=float)
            made.append((mesh, np.array(points, dtype=float), copy))
        else:
            CERTIFIED["skipped"] += 1
        return mesh

    @functools.wraps(refine_checked)
    def refine_and_register(pts, w, opt):
        mesh = refine_checked(pts, w, opt)
        if opt.start is not None:  # a continued run: pts are its new points, all are given
            pts, w = opt.given, opt.given_weights
        return register(mesh, pts, {"weights": w})

    def seen_by(check):
        @functools.wraps(check)
        def wrapped(mesh, *args, **kwargs):
            seen.add(id(mesh))
            return check(mesh, *args, **kwargs)

        return wrapped

    monkeypatch.setattr(pipeline, "refine_checked", refine_and_register)
    # tiled runs (workers, executors) come from scale's one entry
    import knnrefine.scale.shared as shared

    tiled = shared.refine_local

    @functools.wraps(tiled)
    def tiled_and_register(pts, w, opt, *args, **kwargs):
        return register(tiled(pts, w, opt, *args, **kwargs), pts, {"weights": w})

    monkeypatch.setattr(shared, "refine_local", tiled_and_register)
    # every certificate, in every domain, in this process or strip by strip: certify's steps
    monkeypatch.setattr(steps, "run_checks", seen_by(steps.run_checks))
    yield
    for mesh, points, weights in made:
        if id(mesh) in seen:
            CERTIFIED["by the test"] += 1
            continue
        key = _digest(mesh, points, weights)
        if key in CERTIFIED_DIGESTS:
            CERTIFIED["again"] += 1
            continue
        cert = knnrefine.certify(mesh, points, samples=5_000, n_random=1_000, weights=weights)
        assert cert.passed, str(cert)
        CERTIFIED["meshes"] += 1
        CERTIFIED_DIGESTS.add(key)


# achieved constants, printed at the end of the run
ACHIEVED = []


# -- generators of points, defined once (the plane's and space's tests share them) ---------


@pytest.fixture(scope="module")
def tiles_always():
    """refine(workers=N) runs its tiles at every size (``KNNREFINE_TILES=always``): below
    ``scale.tiled.TILES_FROM`` it would run one process, which is faster there; the tests of
    the tiles want the tiles."""
    saved = os.environ.get("KNNREFINE_TILES")
    os.environ["KNNREFINE_TILES"] = "always"
    yield
    if saved is None:
        del os.environ["KNNREFINE_TILES"]
    else:
        os.environ["KNNREFINE_TILES"] = saved


@pytest.fixture(scope="session")
def compiled():
    """The kernels of a refinement in the plane and in space, boxes and tori, compiled (or
    loaded from numba's cache) before a test that times a run: under pytest-xdist a worker
    can reach such a test before any test of its own compiled them, and a first compile
    takes 20-40 s (the tests time the run, not the compiler)."""
    pts = np.random.default_rng(0).random((300, 3))
    for d in (2, 3):
        knnrefine.refine(pts[:, :d], 3)
        knnrefine.refine(pts[:, :d], 3, periodic=True, box=(0,) * d + (1,) * d)


@pytest.fixture(params=[2, 3], ids=["plane", "space"])
def dim(request):
    """The dimension a test runs in: the plane's and space's suites are one."""
    return request.param


def unit_box(dim):
    """The unit box of ``dim`` dimensions, (0, ..., 0, 1, ..., 1)."""
    return (0.0,) * dim + (1.0,) * dim


def uniform(n, seed=0, dim=2):
    """n uniform points in the unit box."""
    return np.random.default_rng(seed).random((n, dim))


def clusters_on_background(n, seed, dim, clusters, exponents, background):
    """``clusters`` Gaussian clusters of widths 10^exponents[0] to 10^exponents[1], wrapped
    into the unit box, the first n // background points uniform."""
    rng = np.random.default_rng(seed)
    centres = rng.random((clusters, dim))
    widths = 10.0 ** rng.uniform(*exponents, clusters)
    j = rng.integers(0, clusters, n)
    pts = centres[j] + rng.standard_normal((n, dim)) * widths[j, None]
    pts[: n // background] = rng.random((n // background, dim))
    return np.mod(pts, 1.0)


def multiscale(n, seed, dim=3):
    """Eight clusters of widths 1e-3 to 1e-1, a tenth of the points uniform."""
    return clusters_on_background(n, seed, dim, 8, (-3, -1), 10)


def background_clusters(n, seed, dim=3):
    """Six clusters of widths 1e-2 to 1e-1, a fifth of the points uniform."""
    return clusters_on_background(n, seed, dim, 6, (-2, -1), 5)


def two_blobs(dim, n, seed):
    """Two Gaussian blobs and a uniform background in the unit box (clipped into it)."""
    rng = np.random.default_rng(seed)
    a = rng.normal(0.3, 0.06, (n // 3, dim))
    b = rng.normal(0.7, 0.1, (n // 3, dim))
    c = rng.random((n - 2 * (n // 3), dim))
    return np.clip(np.concatenate([a, b, c]), 0.0, 1.0 - 1e-12)


def sphere_shell(n, seed, radius=0.3, width=0.01):
    """A noisy sphere of ``radius`` about the unit cube's centre."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1)[:, None]
    return 0.5 + radius * v + width * rng.normal(size=(n, 3))


def gaussian_clusters(n, seed=0, clusters=30, dim=2):
    """Gaussian clusters with widths from 1e-3 to 3e-2 (log-uniform), wrapped into the unit
    box: scales that differ by thirty times in one input."""
    rng = np.random.default_rng(seed)
    centres = rng.random((clusters, dim))
    widths = 10 ** rng.uniform(-3, -1.5, clusters)
    j = rng.integers(0, clusters, n)
    return np.mod(centres[j] + rng.normal(size=(n, dim)) * widths[j, None], 1.0)


DOMAINS = ["plane", "space", "sphere"]


@pytest.fixture(params=DOMAINS)
def domain(request):
    """The domain a test runs in: one suite for the plane, space and the sphere."""
    return request.param


def points_in(domain, n=2000, seed=0):
    """Clustered points of a domain: ``gaussian_clusters`` in the unit box of the plane or
    of space; on the sphere, longitudes and latitudes (below 70 degrees) uniform."""
    rng = np.random.default_rng(seed)
    if domain == "sphere":
        return np.column_stack([rng.uniform(-180, 180, n), rng.uniform(-70, 70, n)])
    return gaussian_clusters(n, seed, dim=2 if domain == "plane" else 3)


def degenerate_in(domain, n=1500, seed=0):
    """Degenerate points of a domain: a third on a line (the equator and the antimeridian's
    great circle on the sphere, the seam x = 0 of the box), a third five copies each of
    points of the rest (fewer than the tests' k = 10: no floor), the rest as
    ``points_in``."""
    pts = points_in(domain, n, seed)
    third = n // 3
    line = np.linspace(0.0, 1.0, third, endpoint=False)
    if domain == "sphere":
        pts[:third] = np.column_stack([line * 360 - 180, np.zeros(third)])
        pts[third : third + 50] = np.column_stack([np.full(50, 180.0), np.linspace(-60, 60, 50)])
    else:
        pts[:third, 0] = 0.0
        pts[:third, 1] = line
    copied = max(1, third // 5)
    pts[third : 2 * third] = pts[2 * third : 2 * third + copied][np.arange(third) % copied]
    return pts


def refine_in(domain, pts, k=10, **options):
    """``knnrefine.refine`` of a domain's points."""
    return knnrefine.refine(pts, k, sphere=domain == "sphere", **options)


def on_lines(n, share, xs, seed=0, axis=0, dim=2):
    """Uniform points, ``share`` of them moved onto the lines {axis = x for x in xs} (planes
    in space)."""
    rng = np.random.default_rng(seed)
    X = rng.random((n, dim))
    moved = int(share * n)
    X[:moved, axis] = np.asarray(xs, float)[rng.integers(0, len(xs), moved)]
    return X


# degenerate inputs for the tiled paths (points sharing coordinates): name -> f(n, rng)
DEGENERATE = {
    "line": lambda n, rng: on_lines(n, rng.uniform(0.3, 1.0), [0.5], int(rng.integers(99))),
    "two lines": lambda n, rng: on_lines(n, 1.0, [0.3, 0.7], int(rng.integers(99))),
    "seam": lambda n, rng: on_lines(n, 0.5, [0.0], int(rng.integers(99))),
    "cross": lambda n, rng: np.concatenate(
        [on_lines(n // 2, 1.0, [0.5], 1), on_lines(n - n // 2, 1.0, [0.5], 2, axis=1)]
    ),
    "diagonal": lambda n, rng: np.column_stack([rng.random(n)] * 2) * [1.0, 0.5] + [0, 0.25],
    "lattice": lambda n, rng: rng.integers(0, 6, (n, 2)) / 6.0,
}
# the same in space: points on planes, on the seam, on a line, on a lattice
DEGENERATE3 = {
    "plane": lambda n, rng: on_lines(
        n, rng.uniform(0.3, 1.0), [0.5], int(rng.integers(99)), dim=3
    ),  # fmt: skip
    "two planes": lambda n, rng: on_lines(n, 1.0, [0.3, 0.7], int(rng.integers(99)), dim=3),
    "seam": lambda n, rng: on_lines(n, 0.5, [0.0], int(rng.integers(99)), dim=3),
    "cross": lambda n, rng: np.concatenate(
        [on_lines(n // 2, 1.0, [0.5], 1, dim=3), on_lines(n - n // 2, 1.0, [0.5], 2, 1, 3)]
    ),
    "line": lambda n, rng: np.column_stack([rng.random(n), np.full(n, 0.5), np.full(n, 0.25)]),
    # 512 sites: many points coincide, fewer than k = 12 at a site (at k or more, d_Pk is 0
    # there and every run refines down to the floor: hundreds of thousands of vertices)
    "lattice": lambda n, rng: rng.integers(0, 8, (n, 3)) / 8.0,
}


def torus_frame(mesh):
    """Points in input coordinates -> the frame of the mesh's torus: relative to its origin,
    periodic axes wrapped into [0, period) (where the torus' vertices and the mesh's offsets
    live)."""
    from knnrefine._metric import BoxMetric

    origin, period = np.asarray(mesh.torus.origin), np.asarray(mesh.torus.period)
    return BoxMetric((*origin, *(origin + period)), mesh.periodic).frame


def assert_unfolding_keeps_every_copy(mesh, box):
    """A brute numpy oracle for ``embedding.unfold`` (the mesh as returned, from its torus
    mesh), in the plane or in space: the cell copies (shifts -1..1 along non-periodic axes)
    whose bounding boxes meet the box are the cells returned, each once, and every vertex
    copy within r* (the longest kept edge) of the box is among the vertices returned, none
    twice."""
    import itertools

    t = mesh.torus
    d = t.vertices.shape[1]
    period = np.array(t.period)
    per = np.array(mesh.periodic)
    lo = np.array(box[:d]) - t.origin
    hi = np.array(box[d:]) - t.origin
    c = t.vertices[t.cells] + t.offsets * period
    pairs = [(i, j) for i in range(d + 1) for j in range(i)]
    want, edges = [], 0.0
    for s in itertools.product(*[[0] if p else [-1, 0, 1] for p in per]):
        cs = c + np.array(s) * period
        kept = cs[((cs.max(axis=1) >= lo) & (cs.min(axis=1) <= hi) | per).all(axis=1)]
        want.append(np.round(kept.mean(axis=1), 12))
        for i, j in pairs:
            e2 = ((kept[:, i] - kept[:, j]) ** 2).sum(axis=1)
            edges = max(edges, float(e2.max(initial=0.0)))
    want = {tuple(x) for x in np.concatenate(want)}
    got = mesh.corners() - np.array(t.origin)
    assert len(got) == len(want)
    assert {tuple(np.round(x, 12)) for x in got.mean(axis=1)} == want
    local = torus_frame(mesh)(mesh.vertices)
    assert len({tuple(x) for x in np.round(local, 12)}) == len(local)  # no repeats
    near = set()
    for s in itertools.product(*[[0] if p else [-1, 0, 1, 2] for p in per]):
        x = t.vertices + np.array(s) * period
        gap = np.where(per, 0.0, np.maximum(np.maximum(lo - x, 0.0), x - hi))
        near |= {tuple(v) for v in np.round(x[(gap**2).sum(axis=1) <= edges], 12)}
    assert near <= {tuple(v) for v in np.round(local, 12)}


def load_shared(name):
    path = SHARED_DATA / name
    if not path.exists():
        pytest.skip(f"{path} is not available (it ships with the development checkout only)")
    return np.loadtxt(path, delimiter=",", skiprows=1)


def assert_lattice_close(got, exact, worst, mean_rel=None):
    """A lattice grid's kernel sums (``adaptive._grid_sums``) against the exact sums at the
    same centres: never below 0; where the estimate is seen (above 1e-3 of its peak) a median
    relative error below 1e-3 and a 99th percentile below 1e-2; nowhere off by more than
    ``worst`` times the peak; with ``mean_rel``, the mean (the mass) within it."""
    assert (got >= 0).all()
    seen = exact > 1e-3 * exact.max()
    rel = np.abs(got - exact)[seen] / exact[seen]
    assert np.median(rel) < 1e-3 and np.quantile(rel, 0.99) < 1e-2
    assert np.abs(got - exact).max() < worst * exact.max()
    if mean_rel is not None:
        assert got.mean() == pytest.approx(exact.mean(), rel=mean_rel)


def assert_binned_close(got, exact, mean_rel=1e-3):
    """A grid's kernel sums read from binned lattices (``engine.binned``: each kernel's mass
    binned on a lattice of its scale, its shape drawn once per lattice point) against the
    exact sums at the same centres: never below 0; their L1 distance below 1 % of the exact
    sums' (measured 0.4-0.8 % on a mixture, on a line and on duplicates); nowhere off by more
    than 2.5 % of the peak; the mass within ``mean_rel``."""
    assert (got >= 0).all()
    assert np.abs(got - exact).sum() < 1e-2 * exact.sum()
    assert np.abs(got - exact).max() < 2.5e-2 * exact.max()
    assert got.mean() == pytest.approx(exact.mean(), rel=mean_rel)


def assert_certified(mesh, points, label=""):
    """knnrefine.certify (validated against brute force in test_certify.py) must pass: the
    torus triangulation is Delaunay; aspect <= tau; every Voronoi cell and closed circumball
    above the floor holds < k points; d_{M,2} / d_{P,k} lies in [alpha, beta] on probes in the
    box (input points, vertices, circumcenters, edge midpoints, random points) wherever
    d_{P,k} >= min_size. Also: the returned vertices give the same d_{M,2} in the box as the
    whole torus mesh."""
    cert = knnrefine.certify(mesh, points, n_random=20_000)
    assert cert.passed, str(cert)
    rng = np.random.default_rng(0)
    d = mesh.dim
    lo, hi = np.array(mesh.box[:d]), np.array(mesh.box[d:])
    probes = np.concatenate([lo + rng.random((2000, d)) * (hi - lo), np.asarray(points)[:2000]])
    torus = mesh.torus
    period = np.array(torus.period)
    full = cKDTree(torus.vertices, boxsize=period).query(
        np.mod(probes - np.array(torus.origin), period) % period, k=2
    )[0][:, 1]
    np.testing.assert_allclose(
        mesh.d_m2(probes), full, rtol=1e-9, atol=1e-12 * float((hi - lo).max())
    )
    ACHIEVED.append(
        f"{label[:34]:34s} {cert.n:7d} {cert.k:4d} {cert.tau:4g} {str(cert.periodic):>14s} "
        f"{cert.m:7d} {cert.max_aspect:7.3f} {cert.alpha_hat:7.3f} {cert.beta_hat:7.3f} "
        f"{cert.size_ratio:6.2f}"
    )
    return cert


def pytest_sessionfinish(session):
    """Under pytest-xdist a worker hands its tallies to the controller, which reports them
    (``pytest_testnodedown``)."""
    out = getattr(session.config, "workeroutput", None)
    if out is not None:
        out["certified"] = dict(CERTIFIED)
        out["achieved"] = list(ACHIEVED)


@pytest.hookimpl(optionalhook=True)  # a pytest-xdist hook: absent without it
def pytest_testnodedown(node, error):
    out = getattr(node, "workeroutput", {})
    for key, count in out.get("certified", {}).items():
        CERTIFIED[key] += count
    ACHIEVED.extend(out.get("achieved", []))


def pytest_terminal_summary(terminalreporter):
    tr = terminalreporter
    if CERTIFIED["meshes"] or CERTIFIED["skipped"] or CERTIFIED["by the test"]:
        tr.section("every mesh certified")
        tr.write_line(
            f"{CERTIFIED['meshes'] + CERTIFIED['by the test']} meshes made by the tests were "
            f"certified ({CERTIFIED['by the test']} by the tests themselves); "
            f"{CERTIFIED['skipped']} larger than {CERTIFY_UP_TO_POINTS:,} points or "
            f"{CERTIFY_UP_TO_VERTICES:,} vertices were not; {CERTIFIED['again']} made again "
            "from the same points (the same mesh) were not certified twice"
        )
    if not ACHIEVED:
        return
    tr.section("certified meshes: achieved d_M2 / d_Pk (alpha_hat, beta_hat) and size ratio")
    tr.write_line(
        f"{'case':34s} {'n':>7s} {'k':>4s} {'tau':>4s} {'periodic':>14s} {'m':>7s} "
        f"{'aspect':>7s} {'a_hat':>7s} {'b_hat':>7s} {'size':>6s}"
    )
    for line in ACHIEVED:
        tr.write_line(line)


def simplices_of(corners, offsets):
    """Each simplex (triangle or tetrahedron) as a hashable key: its corners sorted, with
    their periodic offsets relative to the lowest's (a simplex's frame is arbitrary), for
    comparing triangulations whatever their order (the stitch tests)."""
    keys = set()
    for c, o in zip(corners, offsets, strict=True):
        order = np.argsort(c)
        rel = o[order] - o[order[0]]
        keys.add((tuple(int(v) for v in c[order]), tuple(rel.ravel().tolist())))
    return keys


def as_tile(run, number, area):
    """A stand-in for ``scale.shared.Tile`` holding a finished run (ids: its own)."""
    from types import SimpleNamespace

    return SimpleNamespace(run=run, gid=np.arange(run.vertices), area=np.asarray(area, float),
                           number=number)  # fmt: skip


def of_trees(kernel):
    """A counting kernel that takes a ``state.PointForest`` (its ``python_entry``; the
    plane's or space's), called with one tree or a forest."""
    from knnrefine._engine.index import forest_of
    from knnrefine._engine.jit import python_entry

    entry = python_entry(kernel)
    return lambda index, *args: entry(forest_of(index), *args)
