"""Kernels compiled when the package is built, so that a user's first call loads them.

numba compiles a kernel at its first call; a first refinement waited 10-30 s for it
(docs/benchmarks.md, "The first call"). Here the build of the package (``setup.py``'s
``build_py``, run by ``pip install .``, ``pip wheel .`` and ``python -m build``) compiles
every kernel signature that the public calls need, listed in ``kernels.json``, into the
built package's ``__pycache__`` folders, which the wheel then carries:

* for a CPU that every machine of the platform runs (``NUMBA_CPU_NAME=generic``), found by
  any machine's process through ``jit.PORTABLE_CPU`` (a signature missing for the
  machine's own CPU is looked up for the portable one before it is compiled);
* under the stamp ``jit.source_stamp()`` (the kernels' sources and numpy's version), which
  an install keeps (numba's own stamp, the source file's time, an install changes); and
  numba's own version, which numba checks itself.

An installed copy whose numba or numpy differ from the build's, a changed source, an
editable install (nothing is built) or a signature the list lacks: the kernel is compiled
at its first call as before (with ``ahead.py``'s helper and the "compiling" notice).
``build_marker()`` says what was built, for which numba and numpy.

``kernels.json`` is written by ``python -c "from knnrefine._engine import shipped;
shipped.record()"``: ``WORKLOAD`` (every public use in every domain, at sizes that take the
binned and thinned smoothing searches, threads, the tiles of runs over 2 million points in
the plane or 300,000 in space (taken at a small size), the CLI's demo) run
in a fresh process with an empty numba cache, then every kernel's compiled signatures.
``tests/test_shipped.py`` checks that the public calls compile nothing the list lacks.

Where this machine's own code ran measurably faster than the portable code (the kernel
sums of the density estimator in space, ``HOST_FAMILIES``), ``upgrade`` compiles it in the
background after a first call and uses it from then on (in this process once it is done, in
later processes at once).
"""

import importlib
import inspect
import json
import os
import subprocess
import sys
import tempfile
import time

import numba
import numpy

from . import ahead, jit, threads

MANIFEST = os.path.join(os.path.dirname(os.path.abspath(__file__)), "kernels.json")
MARKER = "shipped.json"  # written beside this file in a built package: what was compiled

# the uses whose kernels are listed (recorded in a fresh process: every signature compiled)
WORKLOAD = r"""
import contextlib, io, os, tempfile
from concurrent.futures import ThreadPoolExecutor
import numpy as np
import knnrefine
from knnrefine.cli.main import main as cli

rng = np.random.default_rng(0)
plane, space = rng.random((3000, 2)), rng.random((3000, 3))
lonlat = rng.random((3000, 2)) * [360, 180] - [180, 90]
weights = rng.random(3000) + 0.5
square, cube = (0.0, 0.0, 1.0, 1.0), (0.0, 0.0, 0.0, 1.0, 1.0, 1.0)
cases = ((plane, {}), (plane, {"periodic": True, "box": square}),
         (plane, {"periodic": (True, False), "box": square}), (space, {}),
         (space, {"periodic": True, "box": cube}), (lonlat, {"sphere": True}))
for pts, options in cases:
    mesh = knnrefine.refine(pts, 10, **options)
    knnrefine.certify(mesh, pts)
    weighted = knnrefine.refine(pts, 10, weights=weights, **options)
    knnrefine.certify(weighted, pts, weights=weights)
    knnrefine.KnnDistance(mesh, pts)(pts[:100])
    knnrefine.KnnDistance(weighted, pts, weights=weights)(pts[:100])
    mesh.d_m2(pts[:100])
    knnrefine.cluster(mesh, pts)
    knnrefine.cluster(weighted, pts, noise=True, weights=weights)
    est = knnrefine.KnnDensityEstimator(**options).fit(pts)
    est.score_samples(pts[:100])
    est.grid()
    knnrefine.KnnDensityEstimator(method="knn", **options).fit(pts).grid()
    knnrefine.KnnDensityEstimator(k="cv", **options).fit(pts[:1500])
    with contextlib.suppress(ImportError):
        from knnrefine.topology import Persistence
        Persistence(mesh, pts).diagram(1)
    if "sphere" not in options:
        box = square if pts.shape[1] == 2 else cube
        knnrefine.knn_cdf(pts, [5, 10], [0.01, 0.05], box, queries=10000,
                          periodic=options.get("periodic") is True)
# continued runs (start=): the tree grown, the cavities reopened (by walks; by balls)
for pts, options in ((plane, {"box": square}), (space, {"box": cube}), (lonlat, {"sphere": True})):
    for w in (None, weights):
        mesh = knnrefine.refine(pts, 10, weights=w, **options)
        more = np.concatenate([pts, pts[:1] + rng.random((100, pts.shape[1])) * 1e-3])
        grown = knnrefine.refine(more, start=mesh,
                                 weights=None if w is None else np.concatenate([w, w[:100]]))
        # continued again: the small tree merged into the large (past 1/8 of its points)
        knnrefine.refine(np.concatenate([more, pts[: len(pts) // 8]]), start=grown,
                         weights=None if w is None else np.concatenate([w, w[:100],
                                                                        w[: len(pts) // 8]]))
        # twice as many new points as old (each again): the cells asked, not the points
        knnrefine.refine(np.concatenate([pts] * 3), start=mesh,
                         weights=None if w is None else np.concatenate([w] * 3))
for n, dim in ((10_000, 2), (50_000, 2), (10_000, 3), (50_000, 3)):
    pts = np.random.default_rng(1).random((n, dim))
    est = knnrefine.KnnDensityEstimator().fit(pts)
    est.grid()
    est.score_samples(pts[:100])
    knnrefine.certify(est.mesh_, pts)
big = np.random.default_rng(2).random((200_000, 2))
knnrefine.certify(knnrefine.refine(big, 50), big)
for pts in (big, np.random.default_rng(3).random((100_000, 3))):  # one process, threads
    knnrefine.certify(knnrefine.refine(pts, 50, workers=2), pts, workers=2)
os.environ["KNNREFINE_TILES"] = "always"  # the tiles of large runs, at a small size
with ThreadPoolExecutor(2) as pool:  # stands for processes: its tiles take the same calls
    for pts, box in ((plane, square), (space, cube)):
        pts = np.concatenate([pts] * 10) + rng.random((30000, pts.shape[1])) * 1e-3
        pts = np.clip(pts, 0.0, 1.0)
        for options in ({}, {"weights": rng.random(len(pts)) + 0.5},
                        {"periodic": True, "box": box}, {"executor": pool}):
            mesh = knnrefine.refine(pts, 20, workers=2, **options)
            knnrefine.certify(mesh, pts, workers=2, weights=options.get("weights"))
del os.environ["KNNREFINE_TILES"]
with tempfile.TemporaryDirectory() as out, contextlib.redirect_stdout(io.StringIO()):
    cli(["demo", "-q", "--out", out])
"""

RECORDER = """
import json, sys
from knnrefine._engine import shipped
exec(shipped.WORKLOAD)
print("RECORD", json.dumps(shipped.compiled_signatures()))
"""


def _kernels():
    """Every kernel of the package loaded in this process: {"module:qualname": dispatcher}
    (lazy kernels once made)."""
    found = {}
    for name, module in list(sys.modules.items()):
        if not name.startswith(jit.__name__.split(".")[0] + ".") or module is None:
            continue
        for value in list(vars(module).values()):
            if isinstance(value, jit._LazyKernel):
                value = value.dispatcher
            if isinstance(value, jit.Kernel):
                func = value.py_func
                found[f"{func.__module__}:{func.__qualname__}"] = value
    return found


def compiled_signatures():
    """[["module:qualname", [type spec, ...]], ...]: every signature of every kernel loaded
    or compiled in this process, sorted."""
    out = []
    for name, dispatcher in sorted(_kernels().items()):
        for sig in dispatcher.signatures:
            out.append([name, [ahead.type_spec(t) for t in sig]])
    return sorted(out, key=json.dumps)


def record():
    """Write ``kernels.json``: ``WORKLOAD`` in a fresh process with an empty numba cache,
    then every signature its kernels compiled."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, **{ahead.ENV: "0"})
        done = subprocess.run([sys.executable, "-c", RECORDER], env=env, capture_output=True,
                              text=True)  # fmt: skip
    if done.returncode != 0:
        raise RuntimeError(f"the workload failed:\n{done.stderr[-3000:]}")
    out = done.stdout
    entries = json.loads(out.split("RECORD", 1)[1])
    head = {"numba": numba.__version__.split("+")[0], "numpy": numpy.__version__}
    rows = ",\n".join(f"  {json.dumps(e)}" for e in entries)
    with open(MANIFEST, "w") as f:
        f.write(f'{{\n "recorded with": {json.dumps(head)},\n "kernels": [\n{rows}\n ]\n}}\n')


def load_manifest(path=None):
    """The listed signatures [(name, [spec, ...]), ...] (of ``kernels.json``, or the file
    ``path``), or [] when the file is missing."""
    try:
        with open(path or MANIFEST) as f:
            return [tuple(e) for e in json.load(f)["kernels"]]
    except (OSError, ValueError, KeyError):
        return []


def dispatcher_named(name):
    """The kernel "module:qualname" (a lazy one made now)."""
    module, attr = name.split(":")
    value = getattr(importlib.import_module(module), attr)
    if isinstance(value, jit._LazyKernel):
        value = value.made()
    return value


def _callees(dispatcher):
    """The kernels ``dispatcher``'s code calls by a global name (its module's or imported)."""
    func = dispatcher.py_func
    out = []
    for name in func.__code__.co_names:
        value = func.__globals__.get(name)
        if isinstance(value, jit._LazyKernel):
            value = value.made()
        if isinstance(value, jit.Kernel) and value is not dispatcher:
            out.append(value)
    return out


def _compiled_with(dispatcher):
    """The kernels compiling ``dispatcher`` compiles: itself and every kernel it calls,
    directly or not, as {id: (dispatcher, lines of source)}."""
    found, todo = {}, [dispatcher]
    while todo:
        d = todo.pop()
        if id(d) not in found:
            found[id(d)] = (d, len(inspect.getsource(d.py_func).splitlines()))
            todo.extend(_callees(d))
    return found


def shares(entries, parts):
    """``entries`` split into ``parts`` lists to compile in as many processes: each module's
    kernels in one list, the modules placed (the largest first) where the most lines of
    kernel source a process compiles, its kernels' and every kernel they call (which a
    process compiles once, whoever calls it), stays least; its source lines stand for a
    kernel's compile time."""
    by_module = {}
    for entry in entries:
        by_module.setdefault(entry[0].split(":")[0], []).append(entry)
    closure = {}
    for module, group in by_module.items():
        closure[module] = {}
        for name in {name for name, _ in group}:
            closure[module].update(_compiled_with(dispatcher_named(name)))

    def lines(kernels):
        return sum(size for _, size in kernels.values())

    out = [[] for _ in range(parts)]
    held = [{} for _ in range(parts)]
    for module in sorted(by_module, key=lambda m: (-lines(closure[m]), m)):

        def after(i, kernels=closure[module]):
            merged = lines({**held[i], **kernels})
            others = max((lines(held[j]) for j in range(parts) if j != i), default=0)
            return max(merged, others), merged - lines(held[i]), i

        best = min(range(parts), key=after)
        out[best].extend(by_module[module])
        held[best].update(closure[module])
    return out


def compile_listed(part=0, parts=1, manifest=None):
    """Compile (or load, when cached) the signatures listed (``load_manifest(manifest)``)
    of share ``part`` of ``parts`` (``shares``) in this process; returns [(name, error)] of
    those that failed."""
    failed = []
    for name, specs in shares(load_manifest(manifest), parts)[part]:
        try:
            dispatcher_named(name).compile(tuple(ahead.type_of_spec(s) for s in specs))
        except Exception as exc:  # noqa: BLE001  the user's first call compiles it then
            failed.append((name, repr(exc)))
    return failed


COMPILER = """
import json, sys
from knnrefine._engine import shipped
part, parts, manifest = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
print("FAILED", json.dumps(shipped.compile_listed(part, parts, manifest)))
"""


def build(package_root, manifest=None, log=print):
    """Compile the listed kernels into the package at ``package_root`` (the folder holding
    ``knnrefine/``, a build's ``build/lib``), for the portable CPU, in one process per core;
    then once more in one process, which loads what those wrote and compiles what they
    missed (two processes may write one kernel's index at once: the last one's stays).
    Writes ``shipped.json`` beside this file there. Returns the marker's content.
    ``manifest``: another list than ``kernels.json`` (tests)."""
    t0 = time.perf_counter()
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env.update(NUMBA_CPU_NAME=jit.PORTABLE_CPU[0], NUMBA_CPU_FEATURES=jit.PORTABLE_CPU[1],
               PYTHONPATH=os.pathsep.join([package_root, env.get("PYTHONPATH", "")]),
               **{ahead.ENV: "0"})  # fmt: skip
    manifest = os.path.abspath(manifest or MANIFEST)
    entries = load_manifest(manifest)
    parts = max(1, min(threads.workers(), 4))

    def run(part, count):
        return subprocess.Popen([sys.executable, "-c", COMPILER, str(part), str(count), manifest],
                                env=env, stdout=subprocess.PIPE, text=True)  # fmt: skip

    processes = [run(p, parts) for p in range(parts)]
    for p in processes:
        p.communicate()
    last = run(0, 1)
    out, _ = last.communicate()
    failed = json.loads(out.split("FAILED", 1)[1]) if "FAILED" in out else [["all", "no report"]]
    marker = {
        "numba": numba.__version__, "numpy": numpy.__version__,
        "cpu": list(jit.PORTABLE_CPU), "signatures": len(entries), "failed": failed,
        "seconds": round(time.perf_counter() - t0, 1), "processes": parts,
    }  # fmt: skip
    path = os.path.join(package_root, *__name__.split(".")[:-1], MARKER)
    with open(path, "w") as f:
        json.dump(marker, f, indent=1)
    log(f"knnrefine: compiled {len(entries) - len(failed)} of {len(entries)} kernel signatures "
        f"in {marker['seconds']} s ({parts} processes)")  # fmt: skip
    return marker


def build_marker():
    """What the build compiled (``build``'s marker), or None (an editable install, a
    checkout, or a build that could not compile)."""
    try:
        with open(os.path.join(os.path.dirname(os.path.abspath(__file__)), MARKER)) as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def in_use():
    """Whether this install's kernels were compiled when it was built, for the numba and
    numpy it runs with (else they compile at first use)."""
    marker = build_marker()
    return (
        bool(marker)
        and (marker["numba"], marker["numpy"]) == (numba.__version__, numpy.__version__)
        and len(marker["failed"]) < marker["signatures"]
    )


def compiles():
    """A list that numba's compiles in this process append to from now on (each compiled
    function's qualified name): how tests and benchmarks see that a call compiled nothing."""
    from numba.core import event

    names = []

    class Listener(event.Listener):
        def on_start(self, ev):
            names.append(ev.data["dispatcher"].py_func.__qualname__)

        def on_end(self, ev):
            pass

    event.register("numba:compile", Listener())
    return names


# -- this machine's own code, compiled in the background ---------------------------------------

# kernel families whose code compiled for this machine's CPU ran measurably faster than the
# portable code the package is built with (``benchmarks/portable_code.py``, docs/benchmarks.md,
# "Kernels built with the package"): their kernels, "module" (all of it) or "module:name".
# The estimator in space took 1.17x as long in portable code, 1.06x with these upgraded; in
# the plane 1.08x either way, refine and certify 0.92-1.06x: they keep the portable code.
HOST_FAMILIES = {
    "kernel sums in space": (
        "knnrefine._engine.kernelsum3", "knnrefine._engine.lattice:draw3",
        *(f"knnrefine._engine.binned:{name}3"
          for name in ("assign_levels", "deposit", "own_terms", "read_sums", "stamp")),
    ),
}  # fmt: skip
HOST_ENV = "KNNREFINE_HOST_KERNELS"  # "0": keep the portable code, compile nothing
STALE_LOCK = 1800.0  # seconds after which a compiling process's lock is taken for lost

_host: dict = {}  # family: its compiling process, "another" (one elsewhere), "done" or "off"
_retired: list = []  # the portable code replaced (kept: a thread may still run it)

HOST_COMPILER = """
import json, os, sys
if hasattr(os, "nice"):
    os.nice(19)  # behind the user's own work
from knnrefine._engine import jit, shipped
jit.PORTABLE_CPU = ("none", "")  # compile for this CPU: never load the portable code
family, lock = sys.argv[1], sys.argv[2]
shipped.HOST_FAMILIES[family] = tuple(json.loads(sys.argv[3]))
try:
    shipped.compile_family(family)
finally:
    os.remove(lock)
"""


def in_family(name, family):
    """Whether the kernel "module:qualname" is one of ``family``'s (``HOST_FAMILIES``)."""
    return any(name == p or name.split(":")[0] == p for p in HOST_FAMILIES[family])


def family_kernels(family):
    """The entry kernels of ``family`` (``HOST_FAMILIES``) loaded in this process."""
    return [d for name, d in sorted(_kernels().items())
            if in_family(name, family) and type(d) is jit.Kernel]  # fmt: skip


def compile_family(family, manifest=None):
    """Compile (or load) the listed signatures of ``family``'s entry kernels in this process
    (their callees with them); returns [(name, error)] of those that failed."""
    failed = []
    for name, specs in load_manifest(manifest):
        if not in_family(name, family):
            continue
        dispatcher = dispatcher_named(name)
        if type(dispatcher) is not jit.Kernel:
            continue
        try:
            dispatcher.compile(tuple(ahead.type_of_spec(s) for s in specs))
        except Exception as exc:  # noqa: BLE001  the portable code stays in use
            failed.append((name, repr(exc)))
    return failed


def host_keys(dispatcher):
    """{signature: whether the cache holds code for this machine's CPU}, for the signatures
    in use here; None where no cache can take such code (a read-only install reading its
    shipped kernels, no cache, or this process itself runs the portable CPU)."""
    cache = getattr(dispatcher, "_cache", None)
    cache_file = getattr(cache, "_cache_file", None)
    if cache_file is None or not hasattr(cache, "_index_key"):
        return None
    if isinstance(getattr(cache._impl, "locator", None), jit.ShippedCacheLocator):
        return None
    codegen = dispatcher.targetctx.codegen()
    if tuple(codegen.magic_tuple()[1:]) == jit.PORTABLE_CPU:
        return None
    index = cache_file._load_index()
    return {sig: cache._index_key(sig, codegen) in index for sig in dispatcher.signatures}


def _lock_path(family):
    """The lock a process compiling ``family`` holds, in the cache folder of its kernels."""
    cache = getattr(dispatcher_named(_first_listed(family)), "_cache", None)
    folder = getattr(cache, "_cache_path", None)
    return folder and os.path.join(folder, f"host-{family.replace(' ', '-')}.lock")


def _first_listed(family):
    return next(n for n, _ in load_manifest() if in_family(n, family))


def _start(family):
    """After a first call of ``family``: start the background compile where its kernels
    were loaded as portable code and the cache can keep this CPU's (else "off"; "done" when
    this CPU's code is in use already; "another" while another process compiles it; None
    while none of its kernels was called yet)."""
    if os.environ.get(HOST_ENV, "").strip() == "0" or not in_use():
        return "off"
    found = [host_keys(d) for d in family_kernels(family)]
    if any(keys is None for keys in found):
        return "off"
    if not any(found):
        return None
    if all(all(keys.values()) for keys in found):
        return "done"
    lock = _lock_path(family)
    if not lock:
        return "off"
    try:
        if time.time() - os.path.getmtime(lock) < STALE_LOCK:
            return "another"
        os.remove(lock)
    except OSError:
        pass
    try:
        os.close(os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except OSError:
        return "another" if os.path.exists(lock) else "off"
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CPU_NAME", "NUMBA_CPU_FEATURES")}
    env.update({ahead.ENV: "0", HOST_ENV: "0"})
    try:
        return subprocess.Popen([sys.executable, "-c", HOST_COMPILER, family, lock,
                                 json.dumps(HOST_FAMILIES[family])], env=env,
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True)  # fmt: skip
    except OSError:
        os.remove(lock)
        return "off"


def _swap(family):
    """Load this CPU's code of ``family``'s kernels in place of the portable code: each
    kernel whose every signature in use here the cache now holds for this CPU (another is
    left as it is: reloading it could mean compiling it here)."""
    from numba.core.compiler_lock import global_compiler_lock

    with global_compiler_lock:
        for dispatcher in family_kernels(family):
            keys = host_keys(dispatcher)
            if not keys or not all(keys.values()):
                continue
            sigs = list(dispatcher.overloads)
            _retired.append(list(dispatcher.overloads.values()))
            dispatcher._reset_overloads()
            for sig in sigs:
                dispatcher.compile(sig)


def upgrade(family, wait=False):
    """Called after each call of ``family`` (``HOST_FAMILIES``): the first starts a process
    that compiles the family's kernels for this machine's CPU in the background, at the
    lowest priority, into the cache (where its kernels came portable with the package and
    the cache can keep code); a later call, once that process is done, loads its code in
    place of the portable code, which later processes then load at once. ``KNNREFINE_HOST_
    KERNELS=0`` keeps the portable code. ``wait``: wait for the compile (tests,
    benchmarks). Returns the state: "off", "compiling", "another" (a process elsewhere
    compiles it) or "done". Never raises: the portable code stays in use."""
    try:
        state = _host.get(family)
        if state is None:
            state = _start(family)
            if state is None:  # not called yet: nothing to decide
                return "off"
            _host[family] = state
        if state in ("off", "done"):
            return state
        if isinstance(state, subprocess.Popen):
            if wait:
                state.wait()
            if state.poll() is None:
                return "compiling"
        else:  # another process's compile: done when its lock is gone
            lock = _lock_path(family)
            while wait and os.path.exists(lock):
                time.sleep(0.5)
            if os.path.exists(lock):
                return "another"
        _swap(family)
        _host[family] = "done"
    except Exception:  # noqa: BLE001  the portable code stays in use
        _host[family] = "off"
    return _host[family]
