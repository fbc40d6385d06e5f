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


@pytest.mark.parametrize("dispatcher", HOT, ids=lambda d: d.py_func.__name__)
def test_hot_kernels_do_no_reference_counting(dispatcher):
    if not dispatcher.signatures:
        knnrefine.refine(np.random.default_rng(0).random((3000, 2)), 5)  # compiles them all
    assert dispatcher.targetoptions.get("_nrt") is False
    assert own_refcounts(dispatcher) == 0


def test_the_option_matters():
    """The check above can fail: the same refinement kernel compiled with numba's runtime
    counts references around its calls."""
    if not refine.refine_steps.signatures:
        knnrefine.refine(np.random.default_rng(0).random((3000, 2)), 5)
    assert own_refcounts(refine.refine_steps, _nrt=True) > 0
