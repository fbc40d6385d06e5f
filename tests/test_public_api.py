"""The public API is typed and documented: every public function and method (the package's
``__all__``, their classes' public methods, ``Persistence``, the Dask functions) has type
hints on every parameter and its return, and a numpy-style docstring with a Parameters
section when it takes any and a Returns section when it returns something; each class
documents its constructor. mypy checks the annotations themselves (``.ci/run``)."""

import inspect

import pytest

import knnrefine
from knnrefine.topology import Persistence


def public_callables():
    found = []

    def add_class(name, cls):
        found.append((name, cls))
        for member, obj in vars(cls).items():
            if member.startswith("_") and member not in ("__init__", "__call__"):
                continue
            if isinstance(obj, (classmethod, staticmethod)):
                obj = obj.__func__
            if inspect.isfunction(obj):
                found.append((f"{name}.{member}", obj))

    for name in knnrefine.__all__:
        obj = getattr(knnrefine, name)
        if inspect.isclass(obj) and not issubclass(obj, BaseException):
            add_class(name, obj)
        elif inspect.isfunction(obj):
            found.append((name, obj))
        elif inspect.ismodule(obj):
            for member in dir(obj):
                fn = getattr(obj, member)
                if inspect.isfunction(fn) and fn.__module__ == obj.__name__:
                    if not member.startswith("_"):
                        found.append((f"{name}.{member}", fn))
    add_class("Persistence", Persistence)
    try:
        from knnrefine.scale import distributed
    except ImportError:  # pragma: no cover - dask is an extra
        distributed = None
    if distributed is not None:
        for member in ("refine", "certify", "density", "partitions"):
            found.append((f"distributed.{member}", getattr(distributed, member)))
    return found


PUBLIC = public_callables()
GENERATED = {"__init__"}  # dataclasses' constructors: their classes document the fields


def params_of(fn):
    return [p for p in inspect.signature(fn).parameters if p not in ("self", "cls")]


@pytest.mark.parametrize("name, obj", PUBLIC, ids=[n for n, _ in PUBLIC])
def test_public_callable_is_typed_and_documented(name, obj):
    doc = inspect.getdoc(obj) or ""
    if inspect.isclass(obj):
        assert doc, f"{name} has no docstring"
        fields = "Parameters" in doc or "Attributes" in doc
        assert fields, f"{name}'s docstring documents no Parameters or Attributes"
        return
    if name.endswith(".__init__"):
        cls_doc = inspect.getdoc(getattr(knnrefine, name.split(".")[0], None) or Persistence)
        if obj.__qualname__.endswith("__init__") and "<" not in obj.__qualname__:
            assert "return" in obj.__annotations__, f"{name} has no return annotation"
            bare = [p for p in params_of(obj) if p not in obj.__annotations__]
            bare = [p for p in bare if not p.startswith("*")]
            assert not bare, f"{name}: parameters without a type hint: {', '.join(bare)}"
        assert cls_doc, f"{name}'s class has no docstring"
        return
    assert "return" in obj.__annotations__, f"{name} has no return annotation"
    plain = [
        p.name
        for p in inspect.signature(obj).parameters.values()
        if p.name not in ("self", "cls") and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    ]
    bare = [p for p in plain if p not in obj.__annotations__]
    assert not bare, f"{name}: parameters without a type hint: {', '.join(bare)}"
    assert doc, f"{name} has no docstring"
    if params_of(obj):
        assert "Parameters\n----------" in doc, f"{name}'s docstring has no Parameters section"
    if obj.__annotations__["return"] not in (None, "None"):
        assert "Returns\n-------" in doc, f"{name}'s docstring has no Returns section"
