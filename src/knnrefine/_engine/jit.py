"""``kernel``: numba's ``njit(cache=True)``, made to work on any install.

numba caches compiled kernels in the ``__pycache__`` beside the source when it can write
there, else in the user's cache directory (``~/.cache/numba`` or ``NUMBA_CACHE_DIR``). It
raises at import ("cannot cache function ...: no locator available") when neither is
writable, and it never *reads* a ``__pycache__`` it cannot write, so a read-only install
recompiles (about a minute) even when compiled kernels were shipped with it.

Here:

* kernels shipped in a read-only ``__pycache__`` of this package (for example by running
  ``knnrefine demo`` once as the installing user) are loaded from there and never written;
  a signature they lack is compiled for the process only;
* with no usable cache at all, kernels are compiled in memory for the process, after one
  ``KernelCacheWarning`` saying how to keep them (``NUMBA_CACHE_DIR``).

Entry points: only the kernels the Python layer calls (``kernel(entry=True)``) get numba's
CPython wrapper, the code that unboxes Python arguments; the others are called from kernels
only and are compiled without it (a wrapper that unboxes a named tuple of ten arrays is
larger than most kernels; without them the first compile went from 12.8 to 11.8 s,
docs/benchmarks.md). Calling one of them
from Python raises ``TypeError`` (not numba's crash); ``python_entry`` makes a callable for
tests and debugging.
"""

import hashlib
import inspect
import os
import tempfile
import warnings

import numpy
from numba import njit, types
from numba.core.caching import FunctionCache, InTreeCacheLocator
from numba.core.registry import CPUDispatcher

PACKAGE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class KernelCacheWarning(RuntimeWarning):
    """numba cannot cache knnrefine's kernels here: they are compiled for this process only."""


def _writable(path):
    try:
        tempfile.TemporaryFile(dir=path).close()
        return True
    except OSError:
        return False


class ShippedCacheLocator(InTreeCacheLocator):
    """Reads kernels compiled into this package's own ``__pycache__`` when that folder holds
    compiled kernels but cannot be written (where it can, numba's in-tree locator serves as
    usual). A kernel missing from it is compiled for the process, without a warning."""

    @classmethod
    def from_function(cls, py_func, py_file):
        if not os.path.abspath(py_file).startswith(PACKAGE + os.sep):
            return None
        self = cls(py_func, py_file)
        path = self.get_cache_path()
        if not os.path.isdir(path) or _writable(path):
            return None
        if not any(name.endswith(".nbi") for name in os.listdir(path)):
            return None
        return self

    def ensure_cache_path(self):
        """The folder exists; nothing is ever written to it (see ``_never_save``)."""


_locators = FunctionCache._impl_class._locator_classes
if ShippedCacheLocator not in _locators:
    _locators.insert(0, ShippedCacheLocator)

_warned: list = []


def _never_save(dispatcher):
    """A dispatcher reading shipped kernels compiles what they lack for the process only."""
    cache = getattr(dispatcher, "_cache", None)
    impl = getattr(cache, "_impl", None)
    if isinstance(getattr(impl, "locator", None), ShippedCacheLocator):
        cache.save_overload = lambda sig, data: None


def _widened(t):
    """The argument type a kernel is compiled for when another kernel calls it with type t:
    a constant (numba's ``Literal``) as its plain type, a narrower signed integer (an int32
    array's element) as int64. numba would otherwise compile the callee, and every callee
    below it not yet compiled for those types, once more for each of them (a first call in
    space compiled eleven such copies)."""
    t = types.unliteral(t)
    if isinstance(t, types.Integer) and t.signed and t.bitwidth < 64:
        return types.int64
    return t


_awaited: dict = {}


def await_compiled(waits):
    """Before compiling each kernel of ``waits`` (dispatcher: a function that returns when
    another process has compiled it into the cache, ``ahead.py``), call that function once,
    so that the kernel is loaded rather than compiled twice; ``{}`` forgets them all."""
    _awaited.clear()
    _awaited.update(waits)


class Kernel(CPUDispatcher):
    """A kernel: numba's dispatcher, compiled once per argument type up to ``_widened``
    when called from other kernels (numba converts the call's arguments)."""

    def get_call_template(self, args, kws):
        args = tuple(_widened(a) for a in args)
        return super().get_call_template(args, {k: _widened(v) for k, v in kws.items()})

    def compile(self, sig):
        wait = _awaited.pop(self, None) if _awaited else None
        if wait is not None:
            wait()
        return super().compile(sig)


class InternalKernel(Kernel):
    """A kernel compiled without a Python entry: callable from other kernels only."""

    def __call__(self, *args, **kwargs):
        raise TypeError(
            f"{self.py_func.__module__}.{self.py_func.__name__} is an internal engine kernel, "
            "compiled to be called from other kernels only; call it through "
            "knnrefine._engine.jit.python_entry(kernel) from Python"
        )


def python_entry(dispatcher):
    """A Python-callable (uncached) jitted function that calls the internal kernel
    ``dispatcher`` with the same arguments: for tests and debugging."""
    names = list(inspect.signature(dispatcher.py_func).parameters)
    args = ", ".join(names)
    scope = {"target": dispatcher}
    exec(f"def entry({args}):\n    return target({args})\n", scope)
    return njit(cache=False)(scope["entry"])


def kernel(entry=False, lazy=False, **options):
    """``njit(cache=True, **options)``, falling back to an uncached ``njit`` where numba has
    nowhere to keep compiled code. ``entry``: the kernel is called from Python (see the module
    docstring); otherwise only from other kernels. ``lazy`` (entry kernels only): numba sees
    the function at its first call, not at import, so that a module of rarely used kernels
    outside ``_engine/`` (whose ``__pycache__`` a read-only install may ship without them)
    imports without a ``KernelCacheWarning``."""
    if lazy:
        return lambda func: _LazyKernel(func, options)

    # set on every kernel, never inherited: numba compiles a callee with its first caller's
    # flags unless the callee sets its own
    options["_nrt"] = options.pop("nrt", True)
    options["no_cfunc_wrapper"] = True  # nothing here calls kernels through C pointers
    if not entry:
        options["no_cpython_wrapper"] = True

    def wrap(func):
        dispatcher = _dispatcher(func, options)
        dispatcher.__class__ = Kernel if entry else InternalKernel
        return dispatcher

    return wrap


class _LazyKernel:
    """An entry kernel compiled (or loaded from the cache) at its first call."""

    def __init__(self, func, options):
        self.func, self.options, self.dispatcher = func, options, None
        self.__doc__, self.__name__ = func.__doc__, func.__name__

    def made(self):
        """The dispatcher, made now if it is not yet."""
        if self.dispatcher is None:
            self.dispatcher = kernel(entry=True, **self.options)(self.func)
        return self.dispatcher

    def __call__(self, *args):
        return self.made()(*args)


def _dispatcher(func, options):
    """The cached dispatcher, or an uncached one where numba cannot cache (or the option
    ``cache=False`` asks for one: tests compiling kernels afresh)."""
    if not options.pop("cache", True):
        return njit(cache=False, **options)(func)
    try:
        dispatcher = njit(cache=True, **options)(func)
    except RuntimeError as exc:
        if "no locator available" not in str(exc):
            raise
        if not _warned:
            _warned.append(True)
            warnings.warn(
                "knnrefine: numba has no writable place to cache compiled kernels (the "
                "package folder is read-only and there is no writable cache directory), so "
                "they are compiled for this process only (10 s or more on first use); set "
                "NUMBA_CACHE_DIR to a writable folder to keep them",
                KernelCacheWarning,
                stacklevel=4,
            )
        return njit(cache=False, **options)(func)
    _never_save(dispatcher)
    _stamp_with_sources(dispatcher)
    _load_portable(dispatcher)
    return dispatcher


_fingerprint: list = []
# files of ``_engine/`` that run the compiles and hold no kernel code (their edits need not
# compile every kernel again)
COMPILE_MACHINERY = ("ahead.py", "shipped.py")


def sources_fingerprint(root=PACKAGE):
    """A hash, by relative path and content, of the source files under ``root`` that a
    compiled kernel may hold code or constants of: every file of ``_engine/`` (but
    ``COMPILE_MACHINERY``) and every other file that defines kernels (``@kernel``)."""
    if root == PACKAGE and _fingerprint:
        return _fingerprint[0]
    digest = hashlib.sha256()
    for folder, dirs, files in os.walk(root):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        for name in sorted(f for f in files if f.endswith(".py")):
            path = os.path.join(folder, name)
            with open(path, "rb") as f:
                text = f.read()
            engine = os.path.basename(folder) == "_engine" and name not in COMPILE_MACHINERY
            if b"@kernel" in text or engine:
                digest.update(os.path.relpath(path, root).encode() + b"\0" + text + b"\0")
    value = digest.hexdigest()
    if root == PACKAGE:
        _fingerprint.append(value)
    return value


def source_stamp():
    """The stamp of every kernel's cache index: the kernels' sources (``sources_fingerprint``)
    and numpy's version, not the source file's time and size as numba's own (an install
    writes the files anew: kernels compiled when the package was built would never be
    found; numpy's version, as compiled code may hold its ABI)."""
    return ("knnrefine", sources_fingerprint(), numpy.__version__)


def _stamp_with_sources(dispatcher):
    """numba keeps a cached kernel while its own source file is unchanged, but the code it
    compiled holds the kernels it calls from other files (inlined or linked): after an
    upgrade, or an edit of such a file, a caller came back from the cache with its callees'
    old code. The index's stamp is therefore ``source_stamp()``: a change to any kernel's
    source compiles every kernel again."""
    cache_file = getattr(getattr(dispatcher, "_cache", None), "_cache_file", None)
    if cache_file is not None and hasattr(cache_file, "_source_stamp"):
        cache_file._source_stamp = source_stamp()


# the CPU that the kernels built with the package are compiled for (``_engine/shipped.py``,
# with NUMBA_CPU_NAME=generic): code every machine of the platform runs, and the key its
# cache entries carry (numba's magic tuple: target triple, CPU name, CPU features)
PORTABLE_CPU = ("generic", "")


def _load_portable(dispatcher):
    """A signature missing from the cache for this machine's CPU is looked up for the
    portable one (``PORTABLE_CPU``) before it is compiled: the kernels the package was
    built with. This process's own compiles are kept for its CPU, as numba keeps them."""
    cache = getattr(dispatcher, "_cache", None)
    host = getattr(cache, "_load_overload", None)
    if host is None or not hasattr(cache, "_index_key"):
        return

    def load_overload(sig, target_context):
        data = host(sig, target_context)
        if data is None and cache._enabled:
            sig_key, magic, code = cache._index_key(sig, target_context.codegen())
            portable = (magic[0], *PORTABLE_CPU)
            if portable != tuple(magic):
                data = cache._cache_file.load((sig_key, portable, code))
                if data is not None:
                    data = cache._impl.rebuild(target_context, data)
        return data

    cache._load_overload = load_overload


def is_ready(dispatcher):
    """Whether calling this kernel will not compile it: compiled in this process already, or
    its index is in a cache numba reads (an index for another signature counts as ready: a
    planning figure for the 'compiling' notice, not a promise)."""
    if dispatcher.signatures:
        return True
    cache_file = getattr(getattr(dispatcher, "_cache", None), "_cache_file", None)
    index = getattr(cache_file, "_index_path", None)
    return bool(index) and os.path.exists(index)
