"""Kernels compiled when the package is built (``_engine/shipped.py``, issue 54): found by an
installed copy on any machine of the platform, listed completely, and, in a built install,
a first call that compiles nothing."""

import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

import knnrefine
from knnrefine._engine import ahead, jit, shipped

# a small listed kernel, and a call of it (the probe prints what numba did)
SMALL = "knnrefine._metric:running_sums"
PROBE = textwrap.dedent("""
    import json, sys
    import numpy as np
    from knnrefine import _metric
    from knnrefine._engine import jit
    if sys.argv[1] == "host only":
        jit.PORTABLE_CPU = ("no such cpu", "")
    sums = _metric.running_sums(np.arange(12.0).reshape(3, 4))
    assert sums[2, 3] == 8 + 9 + 10 + 11
    d = _metric.running_sums.dispatcher
    print(json.dumps({"hits": sum(d.stats.cache_hits.values()),
                      "misses": sum(d.stats.cache_misses.values())}))
""")


def _environment(site, **more):
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env.update(PYTHONPATH=str(site), HOME=str(site / "home"), **more)
    return env


def _run(args, env):
    out = subprocess.run([sys.executable, *args], capture_output=True, text=True, env=env,
                         timeout=600)  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def test_the_list_names_kernels_with_signatures_that_read_back():
    """``kernels.json`` lists kernels that exist, with argument types numba reads back, and
    says which numba and numpy recorded it."""
    with open(shipped.MANIFEST) as f:
        head = json.load(f)["recorded with"]
    assert set(head) == {"numba", "numpy"}
    entries = shipped.load_manifest()
    assert len(entries) > 100
    names = {name for name, _ in entries}
    for name in ("knnrefine._engine.refine:refine_steps", "knnrefine._engine.refine3:refine_steps3",
                 "knnrefine._engine.refine_sphere:refine_steps_sphere", SMALL,
                 "knnrefine._engine.binned:stamp", "knnrefine._engine.binned:stamp3"):  # fmt: skip
        assert name in names, name
    for name, specs in entries:
        assert isinstance(shipped.dispatcher_named(name), jit.Kernel), name
        [ahead.type_of_spec(s) for s in specs]


def test_plain_tuple_arguments_are_listed_regression():
    """The tiles' kernels take plain tuples of arrays: the list could not record them
    ("compile ahead: no record for argument type Tuple(...)"), so the tiles compiled at
    their first call."""
    from numba import types

    arr = types.Array(types.int32, 2, "C")
    for t in (types.Tuple((arr, types.Array(types.float64, 1, "C"), types.int64)),
              types.UniTuple(arr, 3)):  # fmt: skip
        assert ahead.type_of_spec(json.loads(json.dumps(ahead.type_spec(t)))) == t


def test_kernels_built_for_the_portable_cpu_are_loaded_by_an_install(tmp_path):
    """A kernel compiled as the build compiles it (NUMBA_CPU_NAME=generic, into the package's
    own __pycache__) is loaded, not compiled, by a process on this machine's CPU after its
    source files were written anew (an install does: numba's own stamp, the file's time,
    would have discarded it). Without the portable look-up it is compiled again: the check
    can fail."""
    site = tmp_path / "site"
    shutil.copytree(Path(knnrefine.__file__).parent, site / "knnrefine",
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    (site / "home").mkdir()
    listed = [e for e in shipped.load_manifest() if e[0] == SMALL]
    assert listed
    manifest = tmp_path / "kernels.json"
    manifest.write_text(json.dumps({"recorded with": {}, "kernels": listed}))
    build = "import sys; from knnrefine._engine import shipped; shipped.build(*sys.argv[1:])"
    _run(["-c", build, str(site), str(manifest)], _environment(site))
    marker = json.loads((site / "knnrefine" / "_engine" / shipped.MARKER).read_text())
    assert marker["failed"] == [] and marker["signatures"] == len(listed)
    assert marker["cpu"] == ["generic", ""]
    later = time.time() + 100
    for path in (site / "knnrefine").rglob("*.py"):
        os.utime(path, (later, later))
    probe = site / "probe.py"
    probe.write_text(PROBE)
    found = json.loads(_run([str(probe), "portable"], _environment(site)))
    assert found == {"hits": 1, "misses": 0}
    host_only = json.loads(_run([str(probe), "host only"], _environment(site)))
    assert host_only == {"hits": 0, "misses": 1}


UPGRADE = textwrap.dedent("""
    import json, os, sys
    import numpy as np
    from knnrefine._engine import jit, lattice, shipped
    if sys.argv[1] == "host only":
        jit.PORTABLE_CPU = ("no such cpu", "")
    compiled = shipped.compiles()
    t, out = np.linspace(0.0, 0.9, 7), np.empty((7, 4))
    lattice.catmull_rom_rows(t, out)
    expected = out.copy()
    d = lattice.catmull_rom_rows
    shipped.HOST_FAMILIES["small"] = ("knnrefine._engine.lattice:catmull_rom_rows",)
    before = list(d.overloads.values())
    host_code = list(shipped.host_keys(d).values())
    states = [shipped.upgrade("small")]
    if sys.argv[1] == "wait":
        states.append(shipped.upgrade("small", wait=True))
    out[:] = 0.0
    lattice.catmull_rom_rows(t, out)
    print(json.dumps({"states": states, "host code": host_code,
                      "same code": list(d.overloads.values()) == before,
                      "right": bool((out == expected).all()), "compiled": compiled,
                      "hits": sum(d.stats.cache_hits.values()),
                      "misses": sum(d.stats.cache_misses.values()),
                      "folder": sorted(os.listdir(d._cache._cache_path))}))
""")


def test_a_family_is_compiled_for_this_cpu_in_the_background(tmp_path):
    """In an install whose kernels came portable, the first call of a family's kernels (here
    a small one, as ``HOST_FAMILIES`` names the kernel sums in space) starts a process that
    compiles them for this machine's CPU; once it is done, the next call loads
    its code in place of the portable code (the process compiles nothing itself), and a later
    process finds this CPU's code at once (it loads with the portable look-up off).
    ``KNNREFINE_HOST_KERNELS=0`` keeps the portable code."""
    site = tmp_path / "site"
    shutil.copytree(Path(knnrefine.__file__).parent, site / "knnrefine",
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    (site / "home").mkdir()
    listed = [
        e for e in shipped.load_manifest() if e[0] == "knnrefine._engine.lattice:catmull_rom_rows"
    ]
    assert listed
    manifest = site / "knnrefine" / "_engine" / "kernels.json"
    manifest.write_text(json.dumps({"recorded with": {}, "kernels": listed}))
    build = "import sys; from knnrefine._engine import shipped; shipped.build(*sys.argv[1:])"
    _run(["-c", build, str(site)], _environment(site))
    probe = site / "probe.py"
    probe.write_text(UPGRADE)
    kept = json.loads(_run([str(probe), "wait"], _environment(site, **{shipped.HOST_ENV: "0"})))
    assert kept["states"] == ["off", "off"] and kept["same code"]
    assert kept["host code"] == [False]  # the portable code only, so far
    env = _environment(site)
    env.pop(shipped.HOST_ENV, None)
    first = json.loads(_run([str(probe), "wait"], env))
    assert first["states"] == ["compiling", "done"], first
    assert not first["same code"] and first["right"] and first["compiled"] == []
    assert first["hits"] == 2 and first["misses"] == 0  # the portable code, then this CPU's
    assert not any(name.endswith(".lock") for name in first["folder"])
    later = json.loads(_run([str(probe), "host only"], env))
    assert later["states"] == ["done"] and later["compiled"] == []
    assert later["hits"] == 1 and later["misses"] == 0


def test_the_estimators_fit_asks_for_the_kernel_sums_of_this_cpu(monkeypatch):
    """Every fit of the estimator calls ``upgrade`` for the listed kernel sums in space (the
    first starts their compile, a later one swaps them in), and every kernel a family names
    is listed (built with the package: there is portable code to replace)."""
    asked = []
    monkeypatch.setattr(shipped, "upgrade", lambda family, wait=False: asked.append(family))
    import numpy as np

    knnrefine.KnnDensityEstimator().fit(np.random.default_rng(0).random((300, 3)))
    assert asked == ["kernel sums in space"]
    listed = {name for name, _ in shipped.load_manifest()}
    for family, patterns in shipped.HOST_FAMILIES.items():
        for pattern in patterns:
            assert any(shipped.in_family(n, family) for n in listed if n.startswith(pattern)), (
                pattern
            )
    assert shipped.upgrade.__module__ != shipped.__name__  # the stand-in was called


def test_a_changed_source_or_numpy_compiles_again(monkeypatch):
    """The index's stamp: the kernels' sources and numpy's version (a kernel compiled
    against other sources or another numpy is not loaded)."""
    stamp = jit.source_stamp()
    assert stamp[1] == jit.sources_fingerprint()
    import numpy

    monkeypatch.setattr(numpy, "__version__", "0.0.1")
    assert jit.source_stamp() != stamp


@pytest.mark.slow
def test_the_list_holds_every_signature_the_public_calls_compile():
    """After the recorded uses (``shipped.WORKLOAD``: every domain, every use, sizes that take
    the binned and thinned searches and the tiles, the CLI) and other calls not in it, every
    kernel signature this process loaded or compiled is listed: a kernel whose arguments
    changed fails here (then: ``python -c "from knnrefine._engine import shipped;
    shipped.record()"``)."""
    code = textwrap.dedent("""
        import json
        import numpy as np
        import knnrefine
        from knnrefine._engine import shipped
        exec(shipped.WORKLOAD)
        rng = np.random.default_rng(5)
        pts = rng.normal(size=(20000, 3))
        knnrefine.KnnDensityEstimator().fit(pts, sample_weight=rng.random(20000))
        lonlat = rng.random((8000, 2)) * [360, 180] - [180, 90]
        est = knnrefine.KnnDensityEstimator(sphere=True).fit(lonlat)
        est.score_samples(lonlat[:10])
        print("SIGS", json.dumps(shipped.compiled_signatures()))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=1200)  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    seen = {json.dumps(e) for e in json.loads(out.stdout.split("SIGS", 1)[1])}
    listed = {json.dumps(list(e)) for e in shipped.load_manifest()}
    assert not seen - listed, sorted(seen - listed)[:5]


FIRST_CALLS = textwrap.dedent("""
    import json, sys, time
    from knnrefine._engine import shipped
    compiled = shipped.compiles()
    import numpy as np
    import knnrefine
    rng = np.random.default_rng(3)
    times = {}
    for name, pts, options in (("plane", rng.random((3000, 2)), {}),
                               ("space", rng.random((3000, 3)), {}),
                               ("sphere", rng.random((3000, 2)) * [360, 180] - [180, 90],
                                {"sphere": True})):
        t = time.perf_counter()
        mesh = knnrefine.refine(pts, 10, **options)
        knnrefine.certify(mesh, pts)
        times[name] = time.perf_counter() - t
    est = knnrefine.KnnDensityEstimator().fit(rng.random((3000, 2)))
    t = time.perf_counter()
    knnrefine.KnnDensityEstimator().fit(rng.random((10000, 2))).grid()
    times["estimator 10^4"] = time.perf_counter() - t
    print("FIRST", json.dumps({"compiled": compiled, "times": times,
                               "file": knnrefine.__file__}))
""")


@pytest.mark.slow
def test_an_installed_build_compiles_nothing_at_its_first_calls(tmp_path):
    """In an install built with its kernels (a wheel, ``pip install .``: CI's), a new process's
    first calls in every domain (refine, certify, the estimator at 3,000 then 10,000 points)
    compile no kernel: every one is loaded."""
    marker = shipped.build_marker()
    if marker is None:
        pytest.skip("this knnrefine was not built with its kernels (an editable install)")
    assert marker["failed"] == []
    import numba
    import numpy

    if (marker["numba"], marker["numpy"]) != (numba.__version__, numpy.__version__):
        pytest.skip(f"built with numba {marker['numba']} and numpy {marker['numpy']}, run with "
                    f"{numba.__version__} and {numpy.__version__}: its kernels compile at "
                    "first use (the fallback)")  # fmt: skip
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    out = subprocess.run([sys.executable, "-c", FIRST_CALLS], capture_output=True, text=True,
                         timeout=600, env=env, cwd=tmp_path)  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout.split("FIRST", 1)[1])
    assert Path(result["file"]).parent == Path(knnrefine.__file__).parent
    assert result["compiled"] == []


def test_import_knnrefine_loads_neither_numba_nor_scipy():
    """``import knnrefine`` is lazy (issue 54: under 0.5 s): numba and scipy load with the
    first public name used."""
    code = textwrap.dedent("""
        import sys, time
        t = time.perf_counter()
        import knnrefine
        seconds = time.perf_counter() - t
        before = sorted(m for m in ("numba", "scipy", "pandas", "matplotlib") if m in sys.modules)
        knnrefine.refine
        after = sorted(m for m in ("numba", "scipy") if m in sys.modules)
        print(before, after, seconds)
    """)
    out = _run(["-c", code], {**os.environ}).split("]")
    assert out[0].strip() == "["
    assert out[1].strip() == "['numba', 'scipy'"


def test_certify_and_cluster_stay_the_functions_after_their_modules_are_imported():
    """Regression: with the lazy package, importing the module ``knnrefine.cluster`` (or the
    subpackage ``knnrefine.certify``) first bound the package's attribute to the module:
    ``knnrefine.cluster(mesh, points)`` raised "'module' object is not callable"."""
    code = textwrap.dedent("""
        import importlib
        import knnrefine
        importlib.import_module("knnrefine.cluster")
        from knnrefine.certify import Certificate
        import knnrefine.certify
        print(callable(knnrefine.cluster), callable(knnrefine.certify),
              knnrefine.cluster.__module__, knnrefine.certify.__module__)
    """)
    assert _run(["-c", code], {**os.environ}).split() == [
        "True", "True", "knnrefine.cluster", "knnrefine.api"]  # fmt: skip


def test_the_package_pickles_by_name():
    """Regression: the package's module class broke cloudpickle (Dask's), which pickled the
    module referenced by a function by value: "cannot pickle '_Package' object"."""
    cloudpickle = pytest.importorskip("cloudpickle")
    import pickle

    assert pickle.loads(cloudpickle.dumps(knnrefine)) is knnrefine

    def uses():
        return knnrefine.refine

    assert pickle.loads(cloudpickle.dumps(uses))() is knnrefine.refine


def test_an_assigned_stand_in_for_cluster_or_certify_is_kept(monkeypatch):
    """The lazy package ignores only the import system's binding of the modules ``cluster``
    and ``certify``: a stand-in assigned to the names (a test's monkeypatch) is used, and
    the function comes back when it is undone."""
    real = knnrefine.cluster

    def stand_in(*args, **kwargs):
        return "stand-in"

    monkeypatch.setattr(knnrefine, "cluster", stand_in)
    assert knnrefine.cluster() == "stand-in"
    monkeypatch.undo()
    assert knnrefine.cluster is real
