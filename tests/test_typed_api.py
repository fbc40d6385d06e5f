"""Issue 51: the public API is typed. Every function, class and public method named in
``knnrefine.__all__`` and ``knnrefine.plot.__all__`` (reachable as ``knnrefine.plot``): at
least 90% are fully annotated (each parameter but self/cls, and the return); mypy checks
the annotations (.ci/run)."""

import inspect

import knnrefine
import knnrefine.plot


def _callables():
    for module in (knnrefine, knnrefine.plot):
        for name in module.__all__:
            obj = getattr(module, name)
            if inspect.isclass(obj):
                if issubclass(obj, BaseException):
                    continue
                yield f"{name}", obj.__init__
                for attr, member in vars(obj).items():
                    if not attr.startswith("_") and inspect.isfunction(member):
                        yield f"{name}.{attr}", member
            elif inspect.isfunction(obj):
                yield name, obj


def _fully_annotated(fn):
    sig = inspect.signature(fn)
    params = [p for p in sig.parameters.values() if p.name not in ("self", "cls")]
    if any(p.annotation is inspect.Parameter.empty for p in params):
        return False
    return sig.return_annotation is not inspect.Signature.empty


def test_at_least_90_percent_of_the_public_api_is_annotated():
    found = dict(_callables())
    missing = sorted(name for name, fn in found.items() if not _fully_annotated(fn))
    share = 1 - len(missing) / len(found)
    assert len(found) > 50
    assert share >= 0.9, f"{share:.0%} annotated; not: {', '.join(missing)}"
