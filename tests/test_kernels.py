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
from knnrefine.engine import index, refine, triangulation

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
    from knnrefine.engine.jit import python_entry

    own_refcounts(refine.refine_steps)  # a fresh compile types its direct callees

    idx = index.build_index(np.random.default_rng(0).random((200, 2)))
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
    from knnrefine.engine import predicates
    from knnrefine.engine.jit import InternalKernel, python_entry

    assert isinstance(predicates.orient2d, InternalKernel)
    with pytest.raises(TypeError, match="internal engine kernel"):
        predicates.orient2d(0.0, 0.0, 1.0, 0.0, 0.0, 1.0)
    assert python_entry(predicates.orient2d)(0.0, 0.0, 1.0, 0.0, 0.0, 1.0) == 1
    assert not isinstance(refine.refine_steps, InternalKernel)
