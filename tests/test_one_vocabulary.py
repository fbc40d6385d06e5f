"""Issue 51's vocabulary: one seed name (random_state), workers as threads in every domain,
options after the data keyword-only, one spelling (neighbours), progress=True a bar, the
CLI's flags as the API's (--weights, --workers, --random-state, combinable periodic axes, -k
as a number), knn_cdf and plot reachable from the package."""

import inspect
import io as std_io

import numpy as np
import pytest
from conftest import DOMAINS, degenerate_in, points_in, refine_in

import knnrefine
import knnrefine.scale.distributed
from knnrefine import io
from knnrefine.cli.main import main
from knnrefine.errors import InputError


def test_knn_cdf_and_plot_are_reachable_after_import_knnrefine():
    assert callable(knnrefine.knn_cdf)
    assert callable(knnrefine.plot.plot_mesh)
    assert "knn_cdf" in knnrefine.__all__
    assert {"knn_cdf", "plot"} <= set(dir(knnrefine))
    with pytest.raises(AttributeError):
        knnrefine.no_such_name  # noqa: B018


def test_one_seed_name_everywhere():
    """Every public call that draws takes random_state (and no other seed name)."""
    calls = [
        knnrefine.certify,
        knnrefine.knn_cdf,
        knnrefine.KnnDensity.sample,
        knnrefine.KnnDistance.error,
        knnrefine.KnnDistance.sample_pieces,
        knnrefine.KnnDensityEstimator,
        knnrefine.KnnDensityEstimator.sample,
        knnrefine.KnnDensityEstimator.bootstrap,
        knnrefine.datasets.ring,
        knnrefine.datasets.blobs,
        knnrefine.scale.distributed.certify,
    ]
    for call in calls:
        names = set(inspect.signature(call).parameters)
        assert "random_state" in names, call
        assert not names & {"seed", "rng"}, call


def test_options_after_the_data_are_keyword_only():
    """KnnDensity(mesh, p, False) set normalized and KnnDistance(mesh, p, False) subdivide:
    now a TypeError."""
    pts = points_in("plane", 1000)
    mesh = knnrefine.refine(pts, 10)
    with pytest.raises(TypeError):
        knnrefine.KnnDensity(mesh, pts, False)
    with pytest.raises(TypeError):
        knnrefine.KnnDistance(mesh, pts, False)
    with pytest.raises(TypeError):
        knnrefine.cluster(mesh, pts, 2)
    with pytest.raises(TypeError):
        io.write_mesh(mesh, "never.npz", True)
    for call in (knnrefine.KnnDensity, knnrefine.KnnDistance, knnrefine.cluster):
        params = list(inspect.signature(call).parameters.values())
        after = [p for p in params if p.name not in ("self", "mesh", "points")]
        assert all(p.kind is p.KEYWORD_ONLY for p in after), call


def test_random_state_takes_what_scikit_learn_takes():
    pts = points_in("plane", 1500)
    mesh = knnrefine.refine(pts, 10)
    density = knnrefine.KnnDensity(mesh, pts)
    a = density.sample(100, random_state=3)
    np.testing.assert_array_equal(a, density.sample(100, random_state=np.random.default_rng(3)))
    assert density.sample(5, random_state=np.random.RandomState(1)).shape == (5, 2)
    assert density.sample(5).shape == (5, 2)
    c = knnrefine.certify(mesh, pts, samples=2000, random_state=np.random.default_rng(1))
    assert c.passed
    for bad in ("seed", 1.5, True):
        with pytest.raises(InputError, match="random_state must be"):
            knnrefine.certify(mesh, pts, random_state=bad)


@pytest.mark.parametrize("degenerate", [False, True])
@pytest.mark.parametrize("domain", DOMAINS)
def test_workers_2_is_accepted_and_certified_in_every_domain(domain, degenerate, tiles_always):
    """workers=2 in every domain, in tiles where a domain has them (KNNREFINE_TILES=always),
    on clustered points and on degenerate ones (a third on a line or a seam, a third
    duplicates): accepted, and certified with workers=2 threads."""
    pts = (degenerate_in if degenerate else points_in)(domain, 900)
    mesh = refine_in(domain, pts, workers=2)
    cert = knnrefine.certify(mesh, pts, workers=2, samples=1000)
    assert cert.passed, str(cert)
    if domain != "sphere":
        assert mesh.stats.rounds  # the tiled path ran
    with pytest.raises(InputError, match="positive integer"):
        refine_in(domain, pts, workers=0)


def test_one_spelling_and_files_of_the_old_one_still_read(tmp_path):
    """Torus.neighbours (was neighbors); an .npz written with the old key reads."""
    pts = points_in("plane", 1000)
    mesh = knnrefine.refine(pts, 10, periodic=True, box=(0, 0, 1, 1))
    assert mesh.torus.neighbours is not None
    assert not hasattr(mesh.torus, "neighbors")
    path = tmp_path / "m.npz"
    io.write_mesh(mesh, path)
    with np.load(path) as d:
        arrays = {key: d[key] for key in d.files}
    arrays["torus_neighbors"] = arrays.pop("torus_neighbours")
    old = tmp_path / "old.npz"
    np.savez(old, **arrays)
    np.testing.assert_array_equal(io.read_mesh(old).torus.neighbours, mesh.torus.neighbours)
    assert knnrefine.certify(io.read_mesh(old), pts, samples=2000).passed


@pytest.mark.parametrize("domain", DOMAINS)
def test_progress_true_draws_a_bar_and_a_bad_progress_is_refused(domain, monkeypatch):
    import tqdm.auto

    made = []
    real = tqdm.auto.tqdm

    def recording(*args, **kwargs):
        kwargs["file"] = std_io.StringIO()
        kwargs["delay"] = 0.0
        bar = real(*args, **kwargs)
        made.append(bar)
        return bar

    monkeypatch.setattr(tqdm.auto, "tqdm", recording)
    pts = points_in(domain, 1500)
    mesh = refine_in(domain, pts, progress=True)
    assert len(made) == 1  # one bar for the run
    bar = made[0]
    assert bar.n >= len(mesh.vertices) > 0  # the vertices so far (the torus' may be more)
    assert bar.disable  # closed when the mesh was done
    with pytest.raises(InputError, match="progress must be True"):
        refine_in(domain, pts, progress="yes")


def _csv(path, pts, weights=None):
    cols = ["x", "y", "z"][: pts.shape[1]]
    with open(path, "w") as f:
        f.write(",".join(cols + (["w"] if weights is not None else [])) + "\n")
        for i, row in enumerate(pts.tolist()):
            extra = [repr(float(weights[i]))] if weights is not None else []
            f.write(",".join([repr(v) for v in row] + extra) + "\n")
    return path


def test_the_cli_takes_weights_workers_random_state_and_k_as_the_api(tmp_path, capsys):
    pts = points_in("plane", 1500)
    w = np.random.default_rng(2).integers(1, 4, len(pts)).astype(float)
    csv = _csv(tmp_path / "p.csv", pts, w)
    out = tmp_path / "m.npz"
    args = ["refine", csv, "--weights", "w", "-k", "12.5", "--workers", "2", "-o", out]
    assert main([str(a) for a in args + ["--certify", "--random-state", "4"]]) == 0
    mesh = io.read_mesh(out)
    assert mesh.k == 12.5
    assert mesh.stats["weight"] == pytest.approx(w.sum())
    want = knnrefine.refine(pts, 12.5, weights=w, workers=2)  # the path the CLI takes
    np.testing.assert_array_equal(mesh.vertices, want.vertices)
    assert main(["certify", str(out), str(csv), "--weights", "w", "--workers", "2",
                 "--random-state", "1"]) == 0  # fmt: skip
    # certify without the weights of a weighted mesh: refused (exit 1)
    assert main(["certify", str(out), str(csv)]) == 1
    # no -k: the API's default
    default = tmp_path / "d.npz"
    assert main(["refine", str(csv), "-o", str(default), "--quiet"]) == 0
    assert io.read_mesh(default).k == knnrefine.density.default_k(len(pts))
    capsys.readouterr()


@pytest.mark.parametrize("flags, want", [
    (["--periodic-x", "--periodic-z"], (True, False, True)),
    (["--periodic-y", "--periodic-z"], (False, True, True)),
    (["--periodic-x", "--periodic-y", "--periodic-z"], (True, True, True)),
])  # fmt: skip
def test_the_cli_combines_periodic_axes(tmp_path, flags, want, capsys):
    pts = points_in("space", 600)
    csv = _csv(tmp_path / "p.csv", pts)
    out = tmp_path / "m.npz"
    argv = ["refine", str(csv), "-k", "10", "--box", "0", "0", "0", "1", "1", "1", "-o", str(out)]
    assert main(argv + flags + ["--quiet"]) == 0
    assert tuple(io.read_mesh(out).periodic) == want
    capsys.readouterr()


def test_cluster_and_persistence_take_weights_on_the_command_line(tmp_path, capsys):
    pytest.importorskip("gudhi")
    pts = points_in("plane", 1500)
    w = np.random.default_rng(2).integers(1, 4, len(pts)).astype(float)
    csv = _csv(tmp_path / "p.csv", pts, w)
    labels = tmp_path / "labels.npy"
    assert main(["cluster", str(csv), "--weights", "w", "-o", str(labels), "--quiet"]) == 0
    mesh = knnrefine.refine(pts, knnrefine.density.default_k(w.sum()), weights=w)
    want = knnrefine.cluster(mesh, pts, weights=w).labels
    np.testing.assert_array_equal(np.load(labels), want)
    diagram = tmp_path / "ph.csv"
    assert main(["persistence", str(csv), "--weights", "w", "-o", str(diagram), "--quiet"]) == 0
    capsys.readouterr()
