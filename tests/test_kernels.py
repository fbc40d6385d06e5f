"""How the hot kernels are compiled: no reference counting in their loops.

A numba function that passes arrays (or named tuples of them) to a callee that LLVM does not
inline increments and decrements each array's reference count, atomically, around every call:
with the engine's state (some 30 arrays) that cost about 200 ns per call and a third of the
refinement's time. The hot kernels are compiled without numba's runtime (``kernel(nrt=False)``):
they never allocate, and their calls then pass borrowed arrays.
"""

import re

import numba
import numpy as np
import pytest

import knnrefine
from knnrefine._engine import index, refine, triangulation

HOT = [
    refine.refine_steps,
    refine.sweep_cells,
    refine.queue_all,
    triangulation.insert_vertex,
    index.count_in_disk,
    index.count_in_cell,
]


def own_refcounts(dispatcher, **options):
    """Reference-count calls in the body of the dispatcher's own function, compiled afresh with
    its options, or these (the cached one cannot be inspected)."""
    options = {**dispatcher.targetoptions, "cache": False, **options}
    options.pop("nopython", None)
    fresh = numba.njit(**options)(dispatcher.py_func)
    sig = dispatcher.signatures[0]
    fresh.compile(sig)
    ir = fresh.inspect_llvm(sig)
    name = dispatcher.py_func.__name__
    calls = 0
    for match in re.finditer(r"^define [^\n]*@(\S+?)\(", ir, re.M):
        symbol = match.group(1)
        if name not in symbol or "cpython" in symbol:
            continue
        body = ir[match.start() : ir.index("\n}\n", match.start())]
        calls += len(re.findall(r"@NRT_(?:incref|decref)", body))
    return calls


def type_callees():
    """Type the internal kernels here: a refinement loaded from numba's cache does not."""
    from knnrefine._engine.jit import python_entry

    own_refcounts(refine.refine_steps)  # a fresh compile types its direct callees

    idx = index.forest_of(index.build_index(np.random.default_rng(0).random((200, 2))))
    stack = np.zeros(index.STACK_SIZE, np.int64)
    python_entry(index.count_in_disk)(idx, 0.5, 0.5, 0.01, 5, 1.0, 1.0, stack)
    h = np.array([1.0, -1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0, -1.0]), np.full(4, 0.01)
    mask = np.zeros(index.LEAF_SIZE, np.bool_)
    python_entry(index.count_in_cell)(idx, 0.5, 0.5, *h, 4, 0.02, 5, 1.0, 1.0, stack, mask)


@pytest.mark.slow  # each kernel compiled again to read its LLVM IR: 14 s
@pytest.mark.parametrize("dispatcher", HOT, ids=lambda d: d.py_func.__name__)
def test_hot_kernels_do_no_reference_counting(dispatcher):
    if not dispatcher.signatures:
        knnrefine.refine(np.random.default_rng(0).random((3000, 2)), 5)  # the entry points
    if not dispatcher.signatures:
        type_callees()
    assert dispatcher.targetoptions.get("_nrt") is False
    assert own_refcounts(dispatcher) == 0


@pytest.mark.slow
def test_the_option_matters():
    """The check above can fail: the same refinement kernel compiled with numba's runtime
    counts references around its calls."""
    if not refine.refine_steps.signatures:
        knnrefine.refine(np.random.default_rng(0).random((3000, 2)), 5)
    assert own_refcounts(refine.refine_steps, _nrt=True) > 0


def test_internal_kernels_refuse_python_calls():
    """Kernels compiled without numba's Python wrapper (all but the entry points) would crash
    the interpreter if called from Python; they raise instead, and python_entry calls them."""
    from knnrefine._engine import predicates
    from knnrefine._engine.jit import InternalKernel, python_entry

    assert isinstance(predicates.orient2d, InternalKernel)
    with pytest.raises(TypeError, match="internal engine kernel"):
        predicates.orient2d(0.0, 0.0, 1.0, 0.0, 0.0, 1.0)
    assert python_entry(predicates.orient2d)(0.0, 0.0, 1.0, 0.0, 0.0, 1.0) == 1
    assert not isinstance(refine.refine_steps, InternalKernel)


CALLER = "def caller(a, j):\n    return callee(a, 0) + callee(a, j[0]) + callee(a, np.int64(1))\n"


def _called(jit_callee, jit_caller):
    """A callee compiled by ``jit_callee``, once called by a kernel (``jit_caller``) with a
    constant, an int32 element and an int64."""

    def callee(a, i):
        return a[i] * 2.0

    scope = {"np": np, "callee": jit_callee(callee)}
    exec(CALLER, scope)  # noqa: S102
    caller = jit_caller(scope["caller"])
    assert caller(np.arange(3.0), np.array([2], np.int32)) == 0.0 + 4.0 + 2.0
    return scope["callee"]


def test_kernels_compile_once_for_constants_and_narrower_integers():
    """A kernel called from others with a constant, an int32 and an int64 is compiled once
    (for int64), not once per type: a first call in space compiled eleven such copies, among
    them the 3-D cell count twice (first call 44 -> 32 s)."""
    from knnrefine._engine.jit import kernel

    callee = _called(kernel(cache=False), kernel(entry=True, cache=False))
    assert len(callee.signatures) == 1
    assert [str(t) for t in callee.signatures[0]] == ["array(float64, 1d, C)", "int64"]


def test_numba_alone_compiles_a_copy_per_argument_type():
    """The check above can fail: numba's own dispatcher compiles the same callee three
    times (for the constant 0, for int32 and for int64)."""
    callee = _called(numba.njit(cache=False), numba.njit(cache=False))
    assert len(callee.signatures) == 3


@pytest.mark.slow  # a fresh process compiling the 3-D counts: 5 s
def test_the_ball_count_in_space_and_the_cell_count_share_one_compile(tmp_path):
    """``count_in_ball3`` (a cell with no half-spaces) passes arrays of the cell count's own
    types: it passed module constants, which numba types read-only, and the 3-D cell count
    and its callees were compiled twice on every first call in space. In a fresh process
    with an empty numba cache, after a ball count and a cell count, the cell count has one
    compiled signature."""
    import os
    import subprocess
    import sys

    code = """
import numpy as np
from knnrefine._engine import index3
from knnrefine._engine.jit import python_entry
from knnrefine._engine.index import forest_of
idx = forest_of(index3.build_index3(np.random.default_rng(0).random((300, 3))))
stack = np.zeros(128, np.int64)
period = np.ones(3)
c = np.full(3, 0.5)
python_entry(index3.count_in_ball3)(idx, c, 0.01, 5, period, stack)
h, hc = np.array([[0.1, 0.0, 0.0]]), np.array([0.005])
python_entry(index3.count_in_cell3)(idx, c, h, hc, 1, 0.01, 5, period, stack)
print(len(index3.count_in_cell3.signatures), len(index3.count_in_region3.signatures))
"""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=600)  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.split() == ["1", "1"]


@pytest.mark.slow  # a fresh process compiling the 3-D predicates: 5 s
def test_the_exact_insphere_compiles_no_error_message(tmp_path):
    """The exact insphere assigned an array to a row of another, for which numba compiles
    its shape-mismatch message (string formatting: 1.7 s of type inference on every first
    call in space). Compiled afresh, its code holds no such message."""
    import os
    import subprocess
    import sys

    code = """
import numpy as np
from knnrefine._engine import predicates3
from knnrefine._engine.jit import python_entry
p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float) / 2
print(python_entry(predicates3.insphere)(p))
ir = "".join(predicates3._insphere_exact.inspect_llvm().values())
print("message" if "cannot assign slice" in ir else "none", len(ir) > 1000)
"""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=600)  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.split()[1:] == ["none", "True"]


@pytest.mark.slow  # two fresh processes compiling one small kernel each: 5 s
def test_a_kernel_cached_before_its_callee_changed_is_compiled_again(tmp_path):
    """numba keeps a cached kernel while its own file is unchanged, though its code holds
    the kernels it calls from other files: after an upgrade in place (pip leaves numba's
    cache files in ``__pycache__``) or an edit of a callee's file, the caller came back from
    the cache with the callee's old code (CI's site-packages held sphere kernels cached
    months of commits before). In a copy of the package, ``metric.running_sums`` (cached)
    calls ``geometry.plus_compensated``; after an edit of geometry.py alone, a new process
    gets the new code."""
    import os
    import shutil
    import subprocess
    import sys

    copy = tmp_path / "pkg" / "knnrefine"
    shutil.copytree(os.path.dirname(knnrefine.__file__), copy,
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    code = """
import numpy as np, knnrefine
from knnrefine._metric import running_sums
print(knnrefine.__file__)
print(running_sums(np.ones((1, 3))).tolist())
"""
    env = dict(os.environ, PYTHONPATH=str(tmp_path / "pkg"), NUMBA_CACHE_DIR=str(tmp_path / "c"),
               KNNREFINE_COMPILE_AHEAD="0")  # fmt: skip

    def run():
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                             text=True, timeout=600, cwd=tmp_path)  # fmt: skip
        assert out.returncode == 0, out.stderr[-3000:]
        return out.stdout.split("\n")

    where, before = run()[:2]
    assert where.startswith(str(copy)) and before == "[[1.0, 2.0, 3.0]]"
    geometry = copy / "_engine" / "geometry.py"
    text = geometry.read_text()
    assert text.count("    return t, c\n") == 1
    geometry.write_text(text.replace("    return t, c\n", "    return t + 1.0, c\n"))
    assert run()[1] != before  # the callee's new code, not the cached caller's old one


def test_the_sources_fingerprint_covers_what_kernels_hold(tmp_path):
    """Every kernel's cache index is stamped with ``jit.sources_fingerprint()``: it changes
    with any file of ``_engine/`` (constants such as ``state.py``'s are compiled into the
    kernels) and any other file that defines kernels, not with the rest (the API, the
    compile machinery: ``jit.COMPILE_MACHINERY``)."""
    import shutil

    from knnrefine._engine import jit, refine

    stamp = refine.refine_steps._cache._cache_file._source_stamp
    assert stamp[1] == jit.sources_fingerprint()
    root = tmp_path / "knnrefine"
    shutil.copytree(jit.PACKAGE, root, ignore=shutil.ignore_patterns("__pycache__", "data"))
    before = jit.sources_fingerprint(str(root))
    cases = (("_engine/state.py", True), ("_metric.py", True), ("api.py", False),
             ("_engine/shipped.py", False), ("_engine/ahead.py", False))  # fmt: skip
    for name, changes in cases:
        path = root / name
        text = path.read_text()
        path.write_text(text + "\n# edited\n")
        assert (jit.sources_fingerprint(str(root)) != before) == changes, name
        path.write_text(text)
    assert jit.sources_fingerprint(str(root)) == before
