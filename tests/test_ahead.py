"""Compile ahead (``_engine/ahead.py``): a first call's large kernels compiled by a helper
process into the shared numba cache while the caller compiles the rest."""

import os
import subprocess
import sys
import time

import numpy as np
import pytest
from numba import types

import knnrefine
from knnrefine._engine import ahead, jit
from knnrefine._engine.state import Probe, TorusMesh


def _array(dtype, ndim, layout="C", readonly=False):
    return types.Array(dtype, ndim, layout, readonly=readonly)


def test_type_specs_read_back():
    """What the record writes reads back as the same numba type (the helper compiles exactly
    the caller's signature, or numba would compile the caller's again)."""
    mesh = types.NamedTuple([_array(types.int32, 2), _array(types.int8, 3),
                             _array(types.float64, 1)], TorusMesh)  # fmt: skip
    probe = types.NamedUniTuple(_array(types.float64, 1), 5, Probe)
    for t in (types.float64, types.int64, types.boolean, types.int32, _array(types.uint32, 1),
              _array(types.float64, 2, "A"), _array(types.float64, 1, readonly=True), mesh,
              probe):  # fmt: skip
        spec = ahead.type_spec(t)
        assert ahead.type_of_spec(spec) == t, t
    with pytest.raises(TypeError, match="unicode"):
        ahead.type_spec(types.unicode_type)


def _compiled(dispatcher):
    """The signatures this process compiled or numba's cache holds for ``dispatcher``."""
    cached = dispatcher._cache._cache_file._load_index()
    return set(dispatcher.overloads) | {key[0] for key in cached}


@pytest.mark.parametrize("domain", sorted(ahead.RECORD_CALLS))
def test_the_recorded_signatures_are_the_ones_a_run_compiles(domain):
    """``ahead.json`` is current: after the recorded first call, every kernel on the helper's
    list has the recorded signature compiled or cached. A kernel whose arguments changed
    fails here (then: ``python -c "from knnrefine._engine import ahead; ahead.record()"``)."""
    manifest = ahead.load_manifest()
    assert manifest is not None
    assert [name for name, _ in manifest[domain]] == ahead.AHEAD[domain]
    exec(ahead.RECORD_CALLS[domain], {"np": np, "knnrefine": knnrefine})
    for name, specs in manifest[domain]:
        sig = tuple(ahead.type_of_spec(s) for s in specs)
        assert sig in _compiled(ahead.kernel_named(name)), name


def test_a_kernel_waits_once_before_it_compiles():
    """``jit.await_compiled``: the wait registered for a kernel runs before its compile, once
    (the helper's kernel is then loaded, not compiled twice)."""
    calls = []
    kernel = jit.kernel(entry=True, cache=False)(_plus_one)
    jit.await_compiled({kernel: lambda: calls.append(time.perf_counter())})
    try:
        assert kernel(1) == 2 and len(calls) == 1
        assert kernel(1.5) == 2.5 and len(calls) == 1  # another signature: no second wait
    finally:
        jit.await_compiled({})


def _plus_one(x):
    return x + 1


def test_wait_for_returns_on_the_marker_the_helper_ending_or_the_limit(tmp_path):
    """The caller never hangs on the helper: it waits for the kernel's marker, but no longer
    than the helper lives or the limit."""
    marker = tmp_path / "0"
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        t = time.perf_counter()
        ahead.wait_for(sleeper, str(marker), t + 0.2)  # neither: the limit
        assert 0.2 <= time.perf_counter() - t < 5
        marker.touch()
        t = time.perf_counter()
        ahead.wait_for(sleeper, str(marker), t + 60)  # the marker
        assert time.perf_counter() - t < 1
    finally:
        sleeper.kill()
        sleeper.wait()
    t = time.perf_counter()
    ahead.wait_for(sleeper, str(tmp_path / "1"), t + 60)  # the helper has ended
    assert time.perf_counter() - t < 1


def test_no_helper_on_one_core_switched_off_frozen_or_without_a_record(monkeypatch):
    """The helper starts only where it can help: two threads or more (``KNNREFINE_THREADS=1``
    asks for one core), not switched off by ``KNNREFINE_COMPILE_AHEAD=0``, an interpreter to
    start (a frozen application would start itself), a record to read."""
    started = []
    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: started.append(a))
    monkeypatch.setenv("KNNREFINE_THREADS", "1")
    assert ahead._start("plane") is None
    monkeypatch.setenv("KNNREFINE_THREADS", "2")
    monkeypatch.setenv(ahead.ENV, "0")
    assert ahead._start("plane") is None
    monkeypatch.delenv(ahead.ENV)
    monkeypatch.setattr(sys, "frozen", True, raising=False)
    assert ahead._start("plane") is None
    monkeypatch.delattr(sys, "frozen")
    monkeypatch.setattr(ahead, "MANIFEST", os.devnull)
    assert ahead._start("plane") is None
    assert started == []
    monkeypatch.undo()
    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: started.append(a) or _Ended())
    monkeypatch.setenv("KNNREFINE_THREADS", "2")
    helper = ahead._start("plane")  # the same conditions with a record: it starts
    try:
        assert helper is not None and len(started) == 1
    finally:
        jit.await_compiled({})
        os.rmdir(helper[1])


class _Ended:
    def poll(self):
        return 0


@pytest.mark.slow  # a fresh process compiling the sphere's kernels
def test_a_first_call_loads_the_helpers_kernels(tmp_path):
    """In a fresh process with an empty numba cache, a first call on the sphere finds the
    kernels on the helper's list in the cache (the helper compiled them; the caller waited
    and loaded them: no cache miss), and its mesh certifies (here, from the file it wrote:
    certify's own kernels compiled in that process as well took a minute of CI)."""
    code = f"""
import numpy as np, knnrefine
from knnrefine._engine import ahead
p = np.random.default_rng(0).random((2000, 2)) * [360, 180] - [180, 90]
mesh = knnrefine.refine(p, 10, sphere=True)
for name in ahead.AHEAD["sphere"]:
    d = ahead.kernel_named(name)
    print(name, sum(d._cache_hits.values()), sum(d._cache_misses.values()))
knnrefine.io.write_mesh(mesh, {str(tmp_path / "mesh.npz")!r})
"""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    env.pop(ahead.ENV, None)
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=600)  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    lines = run.stdout.split("\n")
    for line, name in zip(lines[:-1], ahead.AHEAD["sphere"], strict=True):
        assert line.split() == [name, "1", "0"], run.stdout
    p = np.random.default_rng(0).random((2000, 2)) * [360, 180] - [180, 90]
    assert knnrefine.certify(knnrefine.io.read_mesh(tmp_path / "mesh.npz"), p)


def test_a_stuck_helper_is_stopped_when_the_call_returns(monkeypatch):
    """A helper that never finishes (here: one that sleeps) delays no kernel past the wait's
    limit and does not outlive the call: ``compiling`` stops it and removes its folder."""
    made = []
    popen = subprocess.Popen

    def spy(*args, **kwargs):
        made.append(popen(*args, **kwargs))
        return made[-1]

    monkeypatch.setattr(ahead, "HELPER", "import time; time.sleep(60)")
    monkeypatch.setattr(subprocess, "Popen", spy)
    monkeypatch.setattr(jit, "is_ready", lambda dispatcher: False)
    monkeypatch.setenv("KNNREFINE_THREADS", "2")
    monkeypatch.delenv(ahead.ENV, raising=False)
    announced = []
    with ahead.compiling("plane", lambda: announced.append(True)):
        (process,) = made
        assert process.poll() is None and jit._awaited  # running, its kernels awaited
        folder = process.args[-1]
        assert os.path.isdir(folder)
    assert announced == [True]
    assert process.poll() is not None and not os.path.exists(folder) and not jit._awaited
