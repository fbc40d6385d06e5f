"""The knnrefine command line: every subcommand in-process and through a subprocess, file
formats both ways, pictures, and bad files."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

import knnrefine
from knnrefine import io
from knnrefine.cli.main import main


@pytest.fixture(scope="module")
def points():
    rng = np.random.default_rng(0)
    return np.concatenate(
        [rng.random((1500, 2)) * [360, 180] - [180, 90], rng.normal([20, 10], 3, (500, 2))]
    )


@pytest.fixture()
def csv(tmp_path, points):
    path = tmp_path / "quakes.csv"
    with open(path, "w") as f:
        f.write("id,lon,lat\n")
        for i, (x, y) in enumerate(points.tolist()):
            f.write(f"{i},{x!r},{y!r}\n")
    return path


def run(*argv):
    return main([str(a) for a in argv])


def test_refine_writes_every_format(tmp_path, csv, points, capsys):
    outs = [tmp_path / f"m{ext}" for ext in (".npz", ".vtu", ".vtk", ".xdmf", ".geojson", ".csv")]
    args = [
        "refine",
        csv,
        "--columns",
        "lon,lat",
        "-k",
        8,
        "--periodic-x",
        "--box",
        -180,
        -90,
        180,
        90,
        "--plot",
        tmp_path / "m.png",
    ]
    for o in outs:
        args += ["-o", o]
    assert run(*args) == 0
    out = capsys.readouterr().out
    assert "refined n = 2,000 points" in out and "wrote" in out
    mesh = io.read_mesh(tmp_path / "m.npz")
    direct = knnrefine.refine(points, 8, periodic=(True, False), box=(-180, -90, 180, 90))
    # .npz is lossless: the same mesh, field by field
    for name in ("vertices", "triangles", "offsets", "kinds", "order", "floor_points"):
        np.testing.assert_array_equal(getattr(mesh, name), getattr(direct, name))
    assert (mesh.k, mesh.tau, mesh.periodic, mesh.box, mesh.min_size) == (
        direct.k,
        direct.tau,
        direct.periodic,
        direct.box,
        direct.min_size,
    )
    for name in ("vertices", "triangles", "offsets", "neighbours", "kinds"):
        np.testing.assert_array_equal(getattr(mesh.torus, name), getattr(direct.torus, name))
    assert mesh.stats["moves"] == direct.stats["moves"]
    assert knnrefine.certify(mesh, points).passed
    # meshio formats: the flat mesh (seam-crossing corners copied), with point data
    meshio = pytest.importorskip("meshio")
    flat_points, flat_tri, source = mesh.flat()
    for ext in (".vtu", ".vtk", ".xdmf"):
        m = meshio.read(tmp_path / f"m{ext}")
        np.testing.assert_allclose(m.points[:, :2], flat_points)
        np.testing.assert_array_equal(m.cells_dict["triangle"], flat_tri)
        np.testing.assert_array_equal(m.point_data["vertex"], source)
        np.testing.assert_allclose(m.point_data["d_m2"], mesh.d_m2(flat_points))
    assert_gis_exports_stay_in_the_box(tmp_path / "m.geojson", tmp_path / "m.csv", mesh)


def assert_gis_exports_stay_in_the_box(geojson, csv, mesh):
    """GeoJSON of a lon/lat mesh periodic in x: every coordinate in [-180, 180] x [-90, 90]
    (latitudes used to reach -182 and longitudes 219), triangles across the antimeridian
    split into two pieces, the pieces tiling the box exactly. The vertex CSV: only vertices
    in the box, with their index in the mesh."""
    gj = json.loads(geojson.read_text())
    assert gj["type"] == "FeatureCollection" and gj["properties"]["k"] == mesh.k
    lo, hi = np.array(mesh.box[:2]), np.array(mesh.box[2:])
    area = 0.0
    pieces_of = {}
    for feature in gj["features"]:
        ring = np.array(feature["geometry"]["coordinates"][0])
        assert np.array_equal(ring[0], ring[-1])
        assert np.all(ring >= lo) and np.all(ring <= hi), ring
        x, y = ring[:-1, 0], ring[:-1, 1]
        area += 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
        t = feature["properties"]["triangle"]
        pieces_of[t] = pieces_of.get(t, 0) + 1
    assert area == pytest.approx(float(np.prod(hi - lo)), rel=1e-9)
    corners = mesh.corners()
    in_lat = np.all((corners[:, :, 1] > lo[1]) & (corners[:, :, 1] < hi[1]), axis=1)
    across = np.flatnonzero(np.any(corners[:, :, 0] > hi[0], axis=1) & in_lat)
    assert len(across) > 0 and all(pieces_of[int(t)] == 2 for t in across)
    table = np.loadtxt(csv, delimiter=",", skiprows=1)
    assert open(csv).readline().strip() == "vertex,x,y,kind,order"
    assert np.all((table[:, 1:3] >= lo) & (table[:, 1:3] <= hi))
    inside = np.all((mesh.vertices >= lo) & (mesh.vertices <= hi), axis=1)
    np.testing.assert_array_equal(table[:, 0], np.flatnonzero(inside))
    np.testing.assert_array_equal(table[:, 1:3], mesh.vertices[inside])
    assert inside.sum() < len(mesh.vertices)  # the margin's copies were left out


def picture_is_real(path):
    ext = os.path.splitext(path)[1]
    data = open(path, "rb").read()
    if ext == ".png":
        import matplotlib.image

        img = matplotlib.image.imread(path)
        assert img.shape[0] > 300 and img.shape[1] > 300
        assert img[..., :3].std() > 0.05  # not a blank canvas
        colours = np.unique((img[..., :3] * 255).astype(np.uint8).reshape(-1, 3), axis=0)
        assert len(colours) > 100  # a colour map, not just lines
    elif ext == ".svg":
        import xml.etree.ElementTree as ET

        assert len(list(ET.fromstring(data).iter())) > 200
    else:
        assert data.startswith(b"%PDF") and len(data) > 20_000


@pytest.mark.parametrize("ext", [".png", ".svg", ".pdf"])
@pytest.mark.parametrize("cells", ["triangles", "voronoi"])
def test_plot(tmp_path, csv, ext, cells):
    assert run("refine", csv, "--columns", "1,2", "-k", 10, "-o", tmp_path / "m.npz", "-q") == 0
    pic = tmp_path / f"pic{ext}"
    assert (
        run(
            "plot",
            tmp_path / "m.npz",
            "-o",
            pic,
            "--points",
            csv,
            "--columns",
            "lon,lat",
            "--cells",
            cells,
            "-q",
        )
        == 0
    )
    picture_is_real(pic)


def test_certify_command(tmp_path, csv, capsys):
    assert run("refine", csv, "--columns", "lon,lat", "-k", 10, "-o", tmp_path / "m.npz") == 0
    assert (
        run(
            "certify",
            tmp_path / "m.npz",
            csv,
            "--columns",
            "lon,lat",
            "--json",
            tmp_path / "c.json",
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "PASSED" in out
    assert json.loads((tmp_path / "c.json").read_text())["passed"] is True
    # other data than the mesh was made for: an input error (status 1)
    other = tmp_path / "other.npy"
    np.save(other, np.random.default_rng(1).normal(0, 1, (5000, 2)))
    assert run("certify", tmp_path / "m.npz", other, "-q") == 1
    # a mesh that fails its certificate (it claims a stricter tau): status 3
    import dataclasses

    strict = dataclasses.replace(io.read_mesh(tmp_path / "m.npz"), tau=2.2)
    io.write_mesh(strict, str(tmp_path / "strict.npz"))
    assert run("certify", tmp_path / "strict.npz", csv, "--columns", "lon,lat", "-q") == 3


def test_inputs_npy_npz_parquet_tsv_whitespace_stdin(tmp_path, points):
    np.save(tmp_path / "p.npy", points)
    np.savez(tmp_path / "p.npz", points=points)
    ref = io.read_points(tmp_path / "p.npy")
    np.testing.assert_array_equal(ref, points)
    np.testing.assert_array_equal(io.read_points(tmp_path / "p.npz"), points)
    (tmp_path / "p.tsv").write_text(
        "lat\tlon\n" + "".join(f"{y!r}\t{x!r}\n" for x, y in points.tolist())
    )
    np.testing.assert_array_equal(io.read_points(tmp_path / "p.tsv", "lon,lat"), points)
    (tmp_path / "p.txt").write_text(
        "# no header\n" + "".join(f"{x!r}   {y!r}\n" for x, y in points.tolist())
    )
    np.testing.assert_array_equal(io.read_points(tmp_path / "p.txt"), points)
    pa = pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq

    pq.write_table(pa.table({"x": points[:, 0], "y": points[:, 1]}), tmp_path / "p.parquet")
    np.testing.assert_array_equal(io.read_points(tmp_path / "p.parquet", "x,y"), points)
    # standard input, through the real console script
    text = "x,y\n" + "".join(f"{x!r},{y!r}\n" for x, y in points.tolist())
    out = subprocess.run(
        cli() + ["refine", "-", "-k", "10", "-o", str(tmp_path / "s.npz")],
        input=text,
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr
    np.testing.assert_array_equal(
        io.read_mesh(tmp_path / "s.npz").vertices, knnrefine.refine(points, 10).vertices
    )


@pytest.mark.parametrize(
    "content, message",
    [
        (None, "no such file"),
        ("", "empty"),
        ("x,y\n", "header but no points"),
        ("x,y\n1,2\n3,4,5\n6,7\n", "malformed rows"),
        ("x,y\n1,2\n3,abc\n", "non-numeric value 'abc' in column 'y', line 3"),
        ("x\n1\n2\n", "at least two columns"),
        ("x,y\n1,2\n3,nan\n4,5\n", "NaN or infinite"),
    ],
)
def test_bad_files_exit_1_with_a_message(tmp_path, capsys, content, message):
    path = tmp_path / "bad.csv"
    if content is not None:
        path.write_text(content)
    assert run("refine", path, "-k", 1, "-o", tmp_path / "m.npz") == 1
    err = capsys.readouterr().err
    assert err.startswith("knnrefine: error:") and message in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "m.npz").exists()


def test_bad_columns_and_formats(tmp_path, csv, capsys):
    assert run("refine", csv, "--columns", "lon,depth", "-k", 5, "-o", tmp_path / "m.npz") == 1
    assert "no column named 'depth'" in capsys.readouterr().err
    assert run("refine", csv, "-k", 5, "-o", tmp_path / "m.stl") == 1
    assert "meshes are written as .npz, .vtu" in capsys.readouterr().err
    assert run("plot", tmp_path / "missing.npz", "-o", tmp_path / "p.png") == 1
    (tmp_path / "fake.npz").write_bytes(b"not a zip file")
    assert run("plot", tmp_path / "fake.npz", "-o", tmp_path / "p.png") == 1
    assert "fake.npz is not an .npz file but text" in capsys.readouterr().err
    (tmp_path / "cut.npz").write_bytes(b"PK\x03\x04" + bytes(40))  # a zip's start, cut short
    assert run("plot", tmp_path / "cut.npz", "-o", tmp_path / "p.png") == 1
    assert "not a readable .npz" in capsys.readouterr().err


def test_refuses_to_overwrite_without_force(tmp_path, csv, capsys):
    out = tmp_path / "m.npz"
    assert run("refine", csv, "-k", 5, "-o", out, "-q") == 0
    before = out.read_bytes()
    assert run("refine", csv, "-k", 7, "-o", out) == 1
    assert "exists; use --force" in capsys.readouterr().err
    assert out.read_bytes() == before
    assert run("refine", csv, "-k", 7, "-o", out, "--force", "-q") == 0
    assert io.read_mesh(out).k == 7
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".knnrefine-")]  # no leftovers


def test_a_failed_write_leaves_nothing(tmp_path, monkeypatch):
    mesh = knnrefine.refine(np.random.default_rng(2).random((200, 2)), 5)

    def broken(mesh, path):
        open(path, "w").write("half")
        raise OSError("disk full")

    monkeypatch.setitem(io.WRITERS, ".npz", broken)
    with pytest.raises(knnrefine.InputError, match=r"m\.npz: could not be written \(disk full\)"):
        io.write_mesh(mesh, str(tmp_path / "m.npz"))
    assert os.listdir(tmp_path) == []


def test_usage_errors_exit_2(capsys):
    for argv in (["no-such-command"], ["refine"], ["refine", "x.csv", "-k", "ten"], []):
        with pytest.raises(SystemExit) as info:
            main(argv)
        assert info.value.code == 2


def test_help_shows_examples(capsys):
    for argv in (
        ["--help"],
        ["refine", "--help"],
        ["certify", "--help"],
        ["plot", "--help"],
        ["demo", "--help"],
    ):
        with pytest.raises(SystemExit) as info:
            main(argv)
        assert info.value.code == 0
        assert "example" in capsys.readouterr().out


def test_debug_shows_the_traceback(tmp_path):
    with pytest.raises(knnrefine.InputError):
        main(["refine", str(tmp_path / "missing.csv"), "-k", "3", "--debug"])


def test_demo_in_process(tmp_path, capsys):
    assert run("demo", "--out", tmp_path / "demo") == 0
    out = capsys.readouterr().out
    assert "18,748 points" in out and "PASSED" in out
    for name in ("mesh.npz", "mesh.vtu", "mesh.png", "certificate.txt", "certificate.json"):
        assert (tmp_path / "demo" / name).stat().st_size > 0
    picture_is_real(str(tmp_path / "demo" / "mesh.png"))
    assert run("demo", "--out", tmp_path / "demo", "-q") == 0  # re-runnable
    assert capsys.readouterr().out == ""


def cli():
    exe = shutil.which("knnrefine")
    return [exe] if exe else [sys.executable, "-m", "knnrefine.cli.main"]


@pytest.mark.slow
def test_every_subcommand_through_a_subprocess(tmp_path, csv):
    def call(*argv):
        return subprocess.run(
            cli() + [str(a) for a in argv], capture_output=True, text=True, cwd=tmp_path
        )

    r = call("refine", csv, "--columns", "lon,lat", "-k", 10, "-o", "m.npz")
    assert r.returncode == 0 and "refined" in r.stdout, r.stderr
    r = call("certify", "m.npz", csv, "--columns", "lon,lat")
    assert r.returncode == 0 and "PASSED" in r.stdout
    r = call("plot", "m.npz", "-o", "m.png")
    assert r.returncode == 0 and (tmp_path / "m.png").exists()
    r = call("demo", "-k", 40)
    assert r.returncode == 0 and (tmp_path / "knnrefine-demo" / "mesh.png").exists()
    r = call("refine", "missing.csv", "-k", 3)
    assert r.returncode == 1 and "Traceback" not in r.stderr


def test_reading_from_a_pipe_reads_it_once(tmp_path, points):
    """A named pipe (or `<(...)` in a shell) can be read only once: the sniffing of the first
    line must not lose it (regression)."""
    import threading

    fifo = tmp_path / "points.fifo"
    os.mkfifo(fifo)
    text = "x,y\n" + "".join(f"{x!r},{y!r}\n" for x, y in points.tolist())
    writer = threading.Thread(target=lambda: fifo.write_text(text))
    writer.start()
    got = io.read_points(str(fifo))
    writer.join()
    np.testing.assert_array_equal(got, points)


def test_density_persistence_cluster_commands(tmp_path, capsys):
    pytest.importorskip("gudhi")
    rng = np.random.default_rng(7)
    t = rng.random(1200) * 2 * np.pi
    ring = np.concatenate(
        [
            np.stack([np.cos(t), np.sin(t)], 1) + rng.normal(0, 0.05, (1200, 2)),
            rng.normal([3, 0], 0.1, (600, 2)),
            rng.random((300, 2)) * 6 - 2,
        ]
    )
    src = tmp_path / "ring.npy"
    np.save(src, ring)
    # density: a grid that integrates to about 1, and a picture
    assert (
        run(
            "density",
            src,
            "-o",
            tmp_path / "d.npz",
            "-o",
            tmp_path / "d.csv",
            "--grid",
            64,
            48,
            "--plot",
            tmp_path / "d.png",
        )
        == 0
    )
    g = np.load(tmp_path / "d.npz")
    assert g["density"].shape == (48, 64) and int(g["k"]) == round(2 * np.sqrt(len(ring)))
    assert str(g["method"]) == "adaptive" and 0 <= float(g["sensitivity"]) <= 1
    cell = np.diff(g["xs"])[0] * np.diff(g["ys"])[0]
    assert g["density"].sum() * cell == pytest.approx(1.0, rel=0.05)
    assert np.loadtxt(tmp_path / "d.csv", delimiter=",", skiprows=1).shape == (48 * 64, 4)
    picture_is_real(str(tmp_path / "d.png"))
    # persistence: the ring's loop is the one long H1 class
    assert (
        run(
            "persistence",
            src,
            "-k",
            30,
            "--linear",
            "-o",
            tmp_path / "p.csv",
            "--plot",
            tmp_path / "p.svg",
        )
        == 0
    )
    rows = np.loadtxt(tmp_path / "p.csv", delimiter=",", skiprows=1)
    h1 = rows[rows[:, 0] == 1]
    life = np.sort(h1[:, 2] - h1[:, 1])[::-1]
    assert life[0] > 0.4 and (len(life) == 1 or life[0] > 3 * life[1])  # the ring dominates
    picture_is_real(str(tmp_path / "p.svg"))
    # cluster, reusing a mesh file: the ring and the blob
    assert run("refine", src, "-k", 30, "-o", tmp_path / "m.npz", "-q") == 0
    assert (
        run(
            "cluster",
            src,
            "--mesh",
            tmp_path / "m.npz",
            "--n-clusters",
            2,  # a thin ring is a curve: its arcs pass the 2-D significance test (docs/uses.md)
            "-o",
            tmp_path / "c.npy",
            "--plot",
            tmp_path / "c.png",
        )
        == 0
    )
    labels = np.load(tmp_path / "c.npy")
    assert len(np.unique(labels[:1800])) == 2
    assert np.bincount(labels[1200:1800]).argmax() != np.bincount(labels[:1200]).argmax()
    picture_is_real(str(tmp_path / "c.png"))
    assert run("cluster", src, "--mesh", tmp_path / "m.npz", "-k", 10) == 1  # disagrees
    out = capsys.readouterr()
    assert "disagrees with the mesh's k = 30" in out.err


def test_warnings_and_refusals_are_one_line_each(tmp_path, capsys):
    """A run whose data lies under the floor warns in one line after the bar is gone; a run
    Theorem 6 cannot certify exits 1 naming what would work."""
    points = np.random.default_rng(0).random((3000, 2))
    path = tmp_path / "p.csv"
    np.savetxt(path, points, delimiter=",")
    out = tmp_path / "m.npz"
    assert (
        run(
            "refine",
            str(path),
            "-k",
            "10",
            "--box",
            "-1000000",
            "-1000000",
            "1000000",
            "1000000",
            "-o",
            str(out),
        )
        == 0
    )
    err = capsys.readouterr().err
    assert err.startswith("knnrefine: warning: 3000 of the 3000 points (100%)"), err
    assert err.count("\n") == 1
    strip = tmp_path / "strip.csv"
    np.savetxt(strip, np.random.default_rng(0).random((1000, 2)) * [0.1, 1], delimiter=",")
    status = run(
        "refine",
        str(strip),
        "-k",
        "900",
        "--tau",
        "2.5",
        "--periodic",
        "--box",
        "0",
        "0",
        "0.1",
        "1",
        "-o",
        str(tmp_path / "s.npz"),
    )
    err = capsys.readouterr().err
    assert status == 1 and "cannot be certified" in err and "use k <= 570" in err, err
    assert not (tmp_path / "s.npz").exists()


# -- issue 9: reading, outputs checked first, usage errors, wording ----------------------------


def test_a_hash_inside_a_text_field_is_data(tmp_path):
    """'name,x,y' / 'a #1,1,2' was read as a NaN row: '#' truncated the line."""
    path = tmp_path / "named.csv"
    path.write_text("# stations, surveyed 2024\nname,x,y\na #1,1,2\nb,3,4\nc # 3,5,6\n")
    points, names = io.read_points_named(str(path), "x,y")
    np.testing.assert_array_equal(points, [[1, 2], [3, 4], [5, 6]])
    assert names == ("x", "y")
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y\n1,2\n# not a comment here\n3,4\n")
    with pytest.raises(knnrefine.InputError, match="line 3"):
        io.read_points(str(bad))


@pytest.mark.parametrize(
    "plot, message",
    [("missing/m.png", "the folder missing does not exist"), ("m.jpg", "pictures are written as")],
)
def test_outputs_are_checked_before_any_work(tmp_path, csv, capsys, plot, message, monkeypatch):
    """--plot into a missing folder, or as .jpg, was found out after the mesh was written:
    exit 1 with an output left behind."""
    monkeypatch.chdir(tmp_path)
    status = run("refine", csv, "--columns", "lon,lat", "-k", 5, "-o", "m.npz", "--plot", plot)
    assert status == 1 and message in capsys.readouterr().err
    assert not (tmp_path / "m.npz").exists()
    status = run("density", csv, "--columns", "lon,lat", "-o", "d.npz", "--plot", plot)
    assert status == 1 and not (tmp_path / "d.npz").exists()


def test_density_weights_column_counts_like_copies(tmp_path, points):
    """--weights COLUMN: a point of weight w is w points (both methods, the smoothing chosen
    by leave-one-out in the adaptive one), and the grids are the library's."""
    from knnrefine.density import AdaptiveDensity, KnnDensity

    w = np.random.default_rng(8).integers(0, 4, len(points))
    weighted, copies = tmp_path / "w.csv", tmp_path / "c.csv"
    np.savetxt(weighted, np.column_stack([points, w]), delimiter=",", header="x,y,n", comments="")
    np.savetxt(copies, np.repeat(points, w, axis=0), delimiter=",", header="x,y", comments="")
    box = ["--box", -181, -91, 181, 91]
    for method in ("adaptive", "knn"):
        a, b = tmp_path / f"a_{method}.npz", tmp_path / f"b_{method}.npz"
        assert run("density", weighted, "--weights", "n", "--method", method, *box, "-o", a) == 0
        assert run("density", copies, "--method", method, *box, "-o", b) == 0
        ga, gb = np.load(a), np.load(b)
        assert int(ga["k"]) == int(gb["k"]) and float(ga["n"]) == w.sum()
        np.testing.assert_allclose(ga["density"], gb["density"], rtol=1e-9)
    # the adaptive grid with given smoothing is the library's estimate
    out = tmp_path / "given.npz"
    given = ["--bandwidth", 1.2, "--sensitivity", 0.3, "-k", 30, *box, "-o", out]
    assert run("density", weighted, "--weights", 2, *given) == 0
    keep = w > 0
    mesh = knnrefine.refine(points[keep], 30, box=(-181, -91, 181, 91), weights=w[keep])
    ref = AdaptiveDensity(mesh, points[keep], 1.2, weights=w[keep], sensitivity=0.3)
    g = np.load(out)
    np.testing.assert_allclose(g["density"], ref.grid((512, 512))[2], rtol=1e-12)
    knn = KnnDensity(mesh, points[keep], weights=w[keep])
    np.testing.assert_allclose(g["d_pk"] ** -2 * knn.constant, knn.grid((512, 512))[2])
    # a negative weight: refused before any work, nothing written
    w[3] = -1
    np.savetxt(weighted, np.column_stack([points, w]), delimiter=",", header="x,y,n", comments="")
    assert run("density", weighted, "--weights", "n", "-o", tmp_path / "bad.npz") == 1
    assert not (tmp_path / "bad.npz").exists()


def test_density_criterion_least_squares_is_the_librarys_choice(tmp_path, points, capsys):
    """--criterion least-squares chooses c and alpha as choose_smoothing does with it (the
    grid is then the library's estimate at that pair), and says so."""
    from knnrefine.density import AdaptiveDensity, choose_smoothing

    src = tmp_path / "p.csv"
    np.savetxt(src, points, delimiter=",", header="x,y", comments="")
    out = tmp_path / "ls.npz"
    box = (-181, -91, 181, 91)
    assert run("density", src, "--criterion", "least-squares", "-k", 30, "--box", *box,
               "-o", out) == 0  # fmt: skip
    assert "(by least squares," in capsys.readouterr().out
    mesh = knnrefine.refine(points, 30, box=box)
    ref = AdaptiveDensity(mesh, points)
    alpha, c, _ = choose_smoothing(ref, criterion="least-squares")
    g = np.load(out)
    assert (float(g["sensitivity"]), float(g["bandwidth"])) == (alpha, c)
    assert str(g["criterion"]) == "least-squares"
    np.testing.assert_allclose(g["density"], ref.grid((512, 512))[2], rtol=1e-12)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["density", "{csv}", "--method", "knn", "--bandwidth", "2", "-o", "d.npz"], "belongs to"),
        (
            ["density", "{csv}", "--method", "knn", "--criterion", "least-squares", "-o", "d.npz"],
            "--criterion belongs to",
        ),  # fmt: skip
        (["density", "{csv}", "--sensitivity", "1.5", "-o", "d.npz"], "sensitivity must be"),
        (["density", "{csv}", "--bandwidth", "0", "-o", "d.npz"], "bandwidth must be"),
        (["density", "{csv}", "--grid", "0", "-o", "d.npz"], "--grid takes one or two positive"),
        (["density", "{csv}", "--grid", "10", "20", "30", "-o", "d.npz"], "--grid takes one"),
        (["refine", "{csv}", "-k", "5", "--periodic"], "--periodic needs --box XMIN YMIN"),
    ],
)
def test_usage_errors_exit_2_in_command_line_words(tmp_path, csv, capsys, argv, message):
    """A missing -k exited 1 though the README says 2 for usage; messages used API words."""
    status = run(*[str(a).replace("{csv}", str(csv)) for a in argv])
    err = capsys.readouterr().err
    assert status == 2 and message in err, err
    assert "box=(" not in err and "force=True" not in err


def test_a_read_only_folder_is_named_not_the_temporary_file(tmp_path, monkeypatch):
    def refused(*args, **kwargs):
        raise PermissionError(13, "Permission denied", str(tmp_path / ".knnrefine-abc.npz"))

    monkeypatch.setattr(io.tempfile, "mkstemp", refused)
    with pytest.raises(knnrefine.InputError) as info:
        io.write_text(str(tmp_path / "c.txt"), "hello")
    assert "c.txt: cannot write in" in str(info.value) and ".knnrefine-" not in str(info.value)


def test_plurals_and_labels_keep_their_names(tmp_path, capsys):
    one = tmp_path / "one.csv"
    one.write_text("lon,lat\n3.5,4.5\n")
    assert run("refine", one, "-k", 1, "--min-size", 0.01, "-o", tmp_path / "one.npz") == 0
    assert "read 1 point from" in capsys.readouterr().out
    pts = knnrefine.datasets.blobs()[:3000]
    src = tmp_path / "b.csv"
    io.write_table(str(src), {"east": pts[:, 0], "north": pts[:, 1]})
    assert run("cluster", src, "-k", 30, "-o", tmp_path / "l.csv") == 0
    lines = (tmp_path / "l.csv").read_text().splitlines()
    assert lines[0] == "row,east,north,label"
    row, east, north, label = lines[1].split(",")
    assert int(row) == 0 and float(east) == pts[0, 0] and len(east) <= 20  # round-trip, short


@pytest.mark.slow
def test_no_carriage_returns_in_a_redirected_stderr(tmp_path):
    """A run long enough that a terminal would show the bar (over its 1 s delay: 150,000
    points at k = 2 refine for a few seconds) writes no carriage return to a file."""
    points = np.random.default_rng(0).random((150_000, 2))
    src = tmp_path / "p.npy"
    np.save(src, points)
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "knnrefine.cli.main",
            "refine",
            str(src),
            "-k",
            "2",
            "-o",
            str(tmp_path / "m.npz"),
        ],
        capture_output=True,
    )
    assert out.returncode == 0, out.stderr
    assert b"\r" not in out.stderr


def test_first_run_in_space_asks_about_the_kernels_of_space(capsys, monkeypatch):
    """Issue 32: the CLI's notice asked whether the plane's kernels were compiled, also for
    points in space; each domain now asks about its own."""
    from knnrefine._engine.refine import refine_steps
    from knnrefine._engine.refine3 import refine_steps3
    from knnrefine._engine.refine_sphere import refine_steps_sphere
    from knnrefine.cli import common

    for domain, steps in (("plane", refine_steps), ("space", refine_steps3),
                          ("sphere", refine_steps_sphere)):  # fmt: skip
        monkeypatch.setattr("knnrefine._engine.jit.is_ready", lambda d, steps=steps: d is not steps)
        common.announce_compilation(quiet=False, domain=domain)
        assert "compiling the kernels" in capsys.readouterr().err, domain
        monkeypatch.setattr("knnrefine._engine.jit.is_ready", lambda d, steps=steps: d is steps)
        common.announce_compilation(quiet=False, domain=domain)
        assert capsys.readouterr().err == "", domain


def test_first_run_says_it_compiles(capsys, monkeypatch):
    """First run: the kernels compiled for 16-58 s with nothing on screen."""
    from knnrefine.cli import common

    monkeypatch.setattr("knnrefine._engine.jit.is_ready", lambda dispatcher: False)
    common.announce_compilation(quiet=False)
    assert "compiling the kernels for their first use" in capsys.readouterr().err
    common.announce_compilation(quiet=True)
    assert capsys.readouterr().err == ""
    monkeypatch.undo()
    from knnrefine._engine.jit import is_ready
    from knnrefine._engine.refine import refine_steps

    knnrefine.refine(np.random.default_rng(0).random((50, 2)), 3)
    assert is_ready(refine_steps)  # compiled in this process now (or cached before)


def test_colour_bar_is_as_tall_as_the_axes_and_labels_name_the_columns():
    """The colour bar was taller than the (equal-aspect) axes, with two ticks and no unit."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from knnrefine.plot import plot_mesh

    pts = np.random.default_rng(1).random((3000, 2)) * [360, 180] - [180, 90]
    mesh = knnrefine.refine(pts, 10, periodic=(True, False), box=(-180, -90, 180, 90))
    ax = plot_mesh(mesh, pts, labels=("lon", "lat"))
    FigureCanvasAgg(ax.figure).draw()
    cax = ax.child_axes[0]  # the colour bar: an inset of the axes
    a, c = ax.get_window_extent(), cax.get_window_extent()
    assert abs(a.height - c.height) < 0.01 * a.height and abs(a.y0 - c.y0) < 0.01 * a.height
    assert ax.get_xlabel() == "lon" and ax.get_ylabel() == "lat"
    assert "lon, lat" in cax.get_ylabel()
    assert len([t for t in cax.get_yticklabels() if t.get_text()]) >= 3


def test_certificate_wording_for_ordinary_boxes():
    pts = np.random.default_rng(2).random((500, 2))
    text = str(knnrefine.certify(knnrefine.refine(pts, 5), pts))
    assert "Delaunay (of the torus embedding the box): ok" in text
    text = str(knnrefine.certify(knnrefine.refine(pts, 5, periodic=True, box=(0, 0, 1, 1)), pts))
    assert "Delaunay on the torus: ok" in text


def test_missing_gudhi_is_an_import_error_naming_the_extra(monkeypatch, tmp_path, capsys):
    import builtins

    real = builtins.__import__

    def no_gudhi(name, *args, **kwargs):
        if name == "gudhi" or name.startswith("gudhi."):
            raise ImportError("No module named 'gudhi'")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_gudhi)
    from knnrefine.topology import require_gudhi

    with pytest.raises(ImportError, match=r'pip install "knnrefine\[topology\]"'):
        require_gudhi()
    src = tmp_path / "p.npy"
    np.save(src, np.random.default_rng(3).random((200, 2)))
    assert run("cluster", src, "-k", 10) == 1
    assert 'pip install "knnrefine[topology]"' in capsys.readouterr().err


def test_public_methods_say_what_they_do():
    """help() showed undocumented grid, __call__ and subdivide."""
    from knnrefine.density import KnnDensity, KnnDistance

    for cls in (KnnDensity, KnnDistance):
        for name in ("__call__", "grid"):
            assert getattr(cls, name).__doc__, (cls.__name__, name)
        assert "subdivide" in cls.__doc__


@pytest.mark.parametrize("command", ["refine", "density", "cluster", "persistence"])
def test_k_above_n_is_one_refusal_everywhere(tmp_path, capsys, command):
    """k > n: refine returned the initial mesh with exit 0 (certify then PASSED with size nan)
    while density, cluster and persistence refused."""
    src = tmp_path / "five.npy"
    np.save(src, np.random.default_rng(4).random((5, 2)))
    out = tmp_path / ("o.npz" if command in ("refine", "density") else "o.csv")
    assert run(command, src, "-k", 10, "-o", out) == 1
    assert "k = 10 is larger than the number of points, 5" in capsys.readouterr().err
    assert not out.exists()


def test_a_truncated_or_corrupted_npz_is_one_clear_error(tmp_path, csv, points, capsys):
    """regression (issue 28): a truncated .npz mesh raised a bare zipfile.BadZipFile, and
    'knnrefine certify' printed a traceback. A truncated or corrupted mesh, points file or
    part of a partitioned mesh is one InputError naming the file; the CLI exits 1 with one
    line."""
    mesh_path = tmp_path / "m.npz"
    assert run("refine", csv, "-k", 5, "-o", mesh_path, "-q") == 0
    whole = mesh_path.read_bytes()
    flipped = bytearray(whole)
    flipped[len(whole) // 3 : len(whole) // 3 + 64] = bytes(64)
    space = knnrefine.refine(np.random.default_rng(1).random((400, 3)), 10,
                             periodic=True, box=(0, 0, 0, 1, 1, 1))  # fmt: skip
    io.write_mesh(space, str(tmp_path / "s.npz"))
    bad = {
        "truncated.npz": whole[: len(whole) // 2],
        "corrupted.npz": bytes(flipped),
        "truncated3.npz": (tmp_path / "s.npz").read_bytes()[:-200],
    }
    for name, content in bad.items():
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(knnrefine.InputError, match=f"{name}: not a readable"):
            io.read_mesh(str(path))
        capsys.readouterr()
        assert run("certify", path, csv) == 1
        err = capsys.readouterr().err
        assert err.startswith("knnrefine: error:") and name in err and "Traceback" not in err
        assert len(err.strip().splitlines()) == 1
    np.savez(tmp_path / "p.npz", points=points)
    (tmp_path / "p.npz").write_bytes((tmp_path / "p.npz").read_bytes()[:-300])
    with pytest.raises(knnrefine.InputError, match="p.npz: not a readable"):
        io.read_points(str(tmp_path / "p.npz"))
    parts = knnrefine.write_partitioned(io.read_mesh(str(mesh_path)), tmp_path / "parts", 2)
    part = tmp_path / "parts" / parts.manifest["parts"][1]["file"]
    part.write_bytes(part.read_bytes()[:100])
    with pytest.raises(knnrefine.InputError, match="part-00001.npz: not a readable"):
        knnrefine.PartitionedMesh(tmp_path / "parts").to_mesh()


def test_every_help_example_is_well_formed():
    """regression (issue 28): 'knnrefine refine --help' named angles.tsv (the demo writes
    angles.csv) and lost a line continuation (a backslash-newline inside the string joined
    the lines). Every example: continued lines end in ' \\' and go on indented, no command
    holds a run of spaces, and every .csv it reads is one the demo writes."""
    import re

    from knnrefine.cli.main import SUBCOMMANDS

    demo_inputs = {"angles.csv", "quakes.csv", "ring.csv", "blobs.csv"}
    placeholders = {"chi.csv", "counts.csv", "all.csv"}  # templates for the user's own data
    for name, module in SUBCOMMANDS.items():
        lines = module.EXAMPLES.split("\n\n")[0].splitlines()[1:]
        commands, current = [], ""
        for line in lines:
            assert line.startswith("  "), (name, line)
            current += line.strip()
            if line.endswith(" \\"):
                current = current[:-1]
                continue
            commands.append(current)
            current = ""
        assert not current, (name, "a continuation leads nowhere")
        for command in commands:
            assert "knnrefine " + name in command, (name, command)
            assert "  " not in command, (name, command)
            for csv_name in re.findall(r"(\S+\.(?:csv|tsv)) ", command.split(" -o ")[0] + " "):
                assert csv_name in demo_inputs | placeholders, (name, csv_name)


def test_the_refine_help_example_on_the_demo_angles_runs(tmp_path, capsys):
    """The refine help's example on the demo's angles.csv runs as printed."""
    from knnrefine.cli import refine

    assert run("demo", "--out", tmp_path, "-q") == 0
    text = refine.EXAMPLES.replace("\\\n", " ")  # continued lines joined
    line = next(x for x in text.splitlines() if "angles.csv" in x)
    args = line.split()[1:]  # after "knnrefine"
    cwd = os.getcwd()
    try:
        os.chdir(tmp_path)
        assert main(args + ["--quiet", "--force"]) == 0
    finally:
        os.chdir(cwd)
    assert (tmp_path / "angles.npz").exists()


def test_a_periodic_box_smaller_than_the_data_is_reported(tmp_path, capsys):
    """regression (issue 28): '--periodic --box 0 0 0.5 0.5' on points in [0, 1]^2 folded
    them silently with exit 0; the folding is now reported on stderr (exit 0: it may be
    meant, as for unwrapped phases)."""
    path = tmp_path / "u.csv"
    np.savetxt(path, np.random.default_rng(0).random((500, 2)), delimiter=",", header="x,y",
               comments="")  # fmt: skip
    out = tmp_path / "u.npz"
    assert run("refine", path, "-k", 10, "--periodic", "--box", 0, 0, 0.5, 0.5, "-o", out) == 0
    err = capsys.readouterr().err
    assert "knnrefine: warning:" in err and "wrapped into it" in err and "along x" in err


@pytest.mark.parametrize("style", ["hdr", "image"])
def test_density_plot_styles(tmp_path, csv, style):
    """knnrefine density --plot (issue 30): the highest-density regions by default, an image
    with --plot-style image; another style is a usage error before any work."""
    pic = tmp_path / f"{style}.png"
    args = ("density", csv, "--columns", "lon,lat", "--plot", pic, "--plot-style", style, "-q")
    assert run(*args) == 0
    picture_is_real(pic)
    with pytest.raises(SystemExit) as bad:
        run("density", csv, "--columns", "lon,lat", "--plot", pic, "--plot-style", "dots")
    assert bad.value.code == 2


@pytest.mark.parametrize("command, out", [("cluster", "l.csv"), ("persistence", "p.csv")])
def test_cluster_and_persistence_default_k(tmp_path, csv, capsys, command, out):
    """Issue 30: a default k for the mesh (sqrt(n) / 2, at least 10), so that clustering and
    persistence users need not pick one (-k was required)."""
    assert run(command, csv, "--columns", "lon,lat", "-o", tmp_path / out) == 0
    assert "k = 22" in capsys.readouterr().out  # n = 2,000: sqrt(n) / 2 = 22.4


def test_density_grid_over_a_region(tmp_path):
    """--extent (issue 53): the grid covers the region asked, its values the estimate's at
    those centres (beyond the box NaN), and the file records the region; a bad region is a
    usage error before any work."""
    rng = np.random.default_rng(9)
    pts = rng.normal(0.5, 0.1, (2000, 2))
    src = tmp_path / "p.npy"
    np.save(src, pts)
    out = tmp_path / "d.npz"
    args = ("density", src, "--box", 0, 0, 1, 1, "--bandwidth", 1, "--sensitivity", 0.5)
    assert run(*args, "--grid", 20, 10, "--extent", 0.2, 0.5, 1.2, 0.9, "-o", out) == 0
    g = np.load(out)
    np.testing.assert_allclose(g["xs"], 0.2 + (np.arange(20) + 0.5) * 0.05)
    np.testing.assert_allclose(g["ys"], 0.5 + (np.arange(10) + 0.5) * 0.04)
    np.testing.assert_array_equal(g["extent"], [0.2, 0.5, 1.2, 0.9])
    beyond = g["xs"] > 1.0
    assert np.isnan(g["density"][:, beyond]).all() and (g["density"][:, ~beyond] > 0).all()
    from knnrefine.density import AdaptiveDensity

    mesh = knnrefine.refine(pts, int(g["k"]), box=(0, 0, 1, 1))
    density = AdaptiveDensity(mesh, pts, bandwidth=1.0, sensitivity=0.5)
    at = np.stack(np.meshgrid(g["xs"][~beyond], g["ys"]), axis=-1)
    np.testing.assert_allclose(g["density"][:, ~beyond], density(at), rtol=2e-3)
    assert run(*args, "--extent", 0, 1, 1, 0, "-o", tmp_path / "e.npz") == 2
    assert not (tmp_path / "e.npz").exists()
