"""Compile ahead: a first call's kernels compiled on two cores instead of one.

numba compiles a kernel at its first call, one after another in the calling process, so a
first-ever refinement waits for some two hundred functions on one core (20-30 s here,
docs/benchmarks.md "The first call"). When that call finds the cache empty and the machine
has a second core, ``compiling(domain)`` starts a helper process (``run_helper`` in a
fresh interpreter) that compiles a fixed list of large kernels
(``AHEAD``: the insertion and the cell count the refinement loop calls, the kernels that
assemble the mesh after it) into the same numba cache, for the signatures recorded in
``ahead.json``, writing a marker file after each. The calling process compiles the rest as
before; when it reaches a kernel on the helper's list it waits for the helper's marker
(``jit.await_compiled``) and then loads the kernel from the cache instead of compiling it.

Nothing depends on the helper for correctness: a kernel it has not written (a signature the
record lacks, another numba, the helper killed or failed) is compiled by the caller as
before; the helper is stopped when the call returns. It is not started where numba cannot
cache (nothing to share), on one core or with ``KNNREFINE_THREADS=1`` (``threads.workers``),
without a Python interpreter to start (a frozen application), or with
``KNNREFINE_COMPILE_AHEAD=0``.

``ahead.json`` is written by ``python -c "from knnrefine._engine import ahead; ahead.record()"``
(after a change to these kernels' arguments; a first call in
each domain in a fresh process with an empty cache, reading the signatures numba compiled);
``tests/test_ahead.py`` checks that a run compiles exactly those signatures.
"""

import contextlib
import functools
import importlib
import json
import os
import site
import subprocess
import sys
import tempfile
import time

import numba
from numba import types

from . import jit, threads

MANIFEST = os.path.join(os.path.dirname(os.path.abspath(__file__)), "ahead.json")
ENV = "KNNREFINE_COMPILE_AHEAD"
WAIT_LIMIT = 120.0  # seconds after the helper's start that the caller waits for it at most

# the helper's kernels, in its order ("module:name" in knnrefine._engine): the costliest the
# refinement loop calls (compiled while the caller builds the index and the initial mesh),
# then those that assemble the mesh after the loop (while the caller compiles the loop)
AHEAD = {
    "plane": [
        "triangulation:insert_vertex", "refine:count_cell", "triangulation:circumcentres",
        "embedding:_keep_cells", "embedding:_need_vertices", "embedding:_number_copies",
        "embedding:_vertex_copies", "embedding:_cell_copies",
    ],
    "space": [
        "triangulation3:insert_vertex3", "refine3:sweep_balls3", "triangulation3:unpack_offsets",
        "embedding:_keep_cells", "embedding:_need_vertices", "embedding:_number_copies",
        "embedding:_vertex_copies", "embedding:_cell_copies",
    ],
    "sphere": ["refine_sphere:_insert", "index3:count_in_region3"],
}  # fmt: skip

# each domain's first call whose signatures ``record`` keeps (the benchmark's first call)
RECORD_CALLS = {
    "plane": "knnrefine.refine(np.random.default_rng(0).random((2000, 2)), 10)",
    "space": "knnrefine.refine(np.random.default_rng(0).random((2000, 3)), 10)",
    "sphere": "knnrefine.refine(np.random.default_rng(0).random((2000, 2)) * [360, 180] "
    "- [180, 90], 10, sphere=True)",
}


def kernel_named(name):
    """The dispatcher "module:name" of ``knnrefine._engine``."""
    module, attr = name.split(":")
    return getattr(importlib.import_module(f"{__package__}.{module}"), attr)


def type_spec(t):
    """A JSON-able description of a numba argument type (``type_of_spec`` reads it back):
    scalars, arrays, and named or plain tuples of them, the types kernels take."""
    if isinstance(t, (types.Integer, types.Float, types.Boolean)):
        return str(t)
    if isinstance(t, types.Array):
        return {"array": str(t.dtype), "ndim": t.ndim, "layout": t.layout,
                "readonly": not t.mutable, "aligned": t.aligned}  # fmt: skip
    if isinstance(t, (types.NamedTuple, types.NamedUniTuple)):
        cls = t.instance_class
        return {"named": f"{cls.__module__}:{cls.__qualname__}", "items": [type_spec(u) for u in t]}
    if isinstance(t, types.BaseTuple):
        return {"tuple": [type_spec(u) for u in t]}
    raise TypeError(f"compile ahead: no record for argument type {t!r}")


def type_of_spec(spec):
    """The numba type ``type_spec`` described."""
    if isinstance(spec, str):
        return getattr(types, spec)
    if "array" in spec:
        return types.Array(getattr(types, spec["array"]), spec["ndim"], spec["layout"],
                           readonly=spec["readonly"], aligned=spec["aligned"])  # fmt: skip
    if "tuple" in spec:
        items = [type_of_spec(s) for s in spec["tuple"]]
        return types.Tuple(items) if len(set(items)) > 1 else types.UniTuple(items[0], len(items))
    module, name = spec["named"].split(":")
    cls = getattr(importlib.import_module(module), name)
    items = [type_of_spec(s) for s in spec["items"]]
    if all(u == items[0] for u in items):
        return types.NamedUniTuple(items[0], len(items), cls)
    return types.NamedTuple(items, cls)


def load_manifest():
    """The recorded signatures {domain: [(name, [spec, ...]), ...]} ("numba": the version
    that recorded them, for the reader), or None when the file is missing or unreadable."""
    try:
        with open(MANIFEST) as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def _caches(name):
    """Whether numba keeps this kernel's compiled code in a cache another process reads."""
    cache = getattr(kernel_named(name), "_cache", None)
    return getattr(cache, "_cache_file", None) is not None and getattr(
        cache.save_overload, "__func__", None) is not None  # fmt: skip


STEPS = {
    "plane": "refine:refine_steps", "space": "refine3:refine_steps3",
    "sphere": "refine_sphere:refine_steps_sphere",
}  # fmt: skip


@contextlib.contextmanager
def compiling(domain, announce=None):
    """Around a call in ``domain`` ("plane", "space" or "sphere"): when its refinement loop is not
    compiled yet (nor cached), call ``announce()`` (the "compiling" notice), start the helper
    and have this process wait for the kernels it compiles; stop it at the end."""
    helper = None
    if not jit.is_ready(kernel_named(STEPS[domain])):
        if announce is not None:
            announce()
        helper = _start(domain)
    try:
        yield
    finally:
        if helper is not None:
            process, folder = helper
            jit.await_compiled({})
            if process.poll() is None:
                process.terminate()
                try:
                    process.wait(5)
                except subprocess.TimeoutExpired:
                    process.kill()
            with contextlib.suppress(OSError):
                for name in os.listdir(folder):
                    os.remove(os.path.join(folder, name))
                os.rmdir(folder)


def _start(domain):
    """The helper (process, marker folder), or None where it would not help."""
    if os.environ.get(ENV, "1").strip() == "0" or threads.workers() < 2:
        return None  # switched off, or one core (a process per core, as Dask's, says 1)
    if getattr(sys, "frozen", False) or not os.path.isfile(sys.executable or ""):
        return None  # no interpreter to start (a frozen application's binary is not one)
    manifest = load_manifest()
    if manifest is None or domain not in manifest:
        return None
    entries = manifest[domain]
    if not all(_caches(name) for name, _ in entries):
        return None
    folder = tempfile.mkdtemp(prefix="knnrefine-ahead-")
    env = dict(os.environ)
    parent = os.path.dirname(jit.PACKAGE)
    if parent not in {*site.getsitepackages(), site.getusersitepackages()}:
        # the helper imports this package from where this process did (a checkout put on
        # sys.path, say); an installed one it finds by itself, and site-packages put first
        # on its path would shadow the standard library with any backport installed there
        env["PYTHONPATH"] = os.pathsep.join(p for p in (parent, env.get("PYTHONPATH")) if p)
    try:
        process = subprocess.Popen(
            [sys.executable, "-c", HELPER, domain, folder], env=env,
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
    except OSError:
        os.rmdir(folder)
        return None

    until = time.monotonic() + WAIT_LIMIT
    jit.await_compiled({
        kernel_named(name): functools.partial(
            wait_for, process, os.path.join(folder, str(i)), until)
        for i, (name, _) in enumerate(entries)
    })  # fmt: skip
    return process, folder


def wait_for(process, marker, until):
    """Return when the file ``marker`` exists, the process has ended, or at ``until``
    (``time.monotonic()``: a stuck helper, the caller compiles the kernel itself)."""
    while not os.path.exists(marker) and process.poll() is None and time.monotonic() < until:
        time.sleep(0.005)


def run_helper(domain, folder):
    """The helper's work: compile the recorded signatures in order, a marker after each
    (written whether the compile worked or not: the caller compiles what is missing)."""
    for i, (name, specs) in enumerate(load_manifest()[domain]):
        try:
            kernel_named(name).compile(tuple(type_of_spec(s) for s in specs))
        except Exception:  # noqa: BLE001  the caller compiles it then
            pass
        with open(os.path.join(folder, str(i)), "w"):
            pass


HELPER = "import sys; from knnrefine._engine.ahead import run_helper; run_helper(*sys.argv[1:])"

RECORDER = """
import json, sys
import numpy as np
import knnrefine
from knnrefine._engine import ahead
{call}
out = []
for name in ahead.AHEAD[{domain!r}]:
    sigs = ahead.kernel_named(name).signatures
    if len(sigs) != 1:
        sys.exit(f"{{name}}: {{len(sigs)}} signatures compiled, not one")
    out.append([name, [ahead.type_spec(t) for t in sigs[0]]])
print("RECORD", json.dumps(out))
"""


def record():
    """Write ``ahead.json``: each domain's first call in a fresh process with an empty
    numba cache, and the one signature it compiled for each of ``AHEAD``'s kernels."""
    manifest = {"numba": numba.__version__.split("+")[0]}
    for domain, call in RECORD_CALLS.items():
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, NUMBA_CACHE_DIR=cache, **{ENV: "0"})
            code = RECORDER.format(call=call, domain=domain)
            out = subprocess.run([sys.executable, "-c", code], env=env, check=True,
                                 capture_output=True, text=True).stdout  # fmt: skip
        manifest[domain] = json.loads(out.split("RECORD", 1)[1])
    lines = [f'{{\n "numba": {json.dumps(manifest.pop("numba"))},']
    for d, (domain, entries) in enumerate(manifest.items()):
        rows = ",\n".join(f"  {json.dumps(e)}" for e in entries)
        lines.append(f' "{domain}": [\n{rows}\n ]' + ("," if d < len(manifest) - 1 else ""))
    with open(MANIFEST, "w") as f:
        f.write("\n".join(lines) + "\n}\n")
