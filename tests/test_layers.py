"""The package's layers (docs/data-structure.md): every import of every module, those inside
functions too, read from the source; no module imports one above its layer, and no modules
import each other in a circle (issue 51)."""

import ast
from fnmatch import fnmatch
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "knnrefine"

# the layers, lowest first: a module may import its own layer's modules (without a circle)
# and those below; the key is the module's path under the package, a folder for all in it,
# ``*`` for any one folder (each domain's package: ``knnrefine._domains``)
LAYERS = [
    ["errors.py", "data/"],
    ["_engine/"],
    ["_metric.py", "_sampling.py"],
    ["_validation.py"],
    ["_options.py", "mesh.py"],
    ["_domains/__init__.py", "_domains/box.py"],
    ["_domains/*/run.py"],
    ["certify/_predicates.py", "certify/_tree.py", "certify/_rows.py"],
    ["certify/certificate.py", "certify/common.py", "certify/steps.py", "certify/__init__.py"],
    ["_domains/*/certify.py", "_domains/*/density.py", "_domains/*/__init__.py"],
    ["_pipeline.py"],
    ["certify/", "density/", "cluster.py", "topology.py", "plot.py", "io.py", "datasets.py"],
    ["scale/"],
    ["api.py"],
    ["__init__.py"],
    ["cli/"],
]


def _layer(module):
    for i, names in enumerate(LAYERS):
        for name in names:
            if fnmatch(module, name) or (name.endswith("/") and module.startswith(name)):
                return i
    raise AssertionError(f"{module} is in no layer of tests/test_layers.py: add it")


def _modules():
    return {
        str(path.relative_to(PACKAGE)): path
        for path in sorted(PACKAGE.rglob("*.py"))
        if "__pycache__" not in path.parts
    }


def _resolve(module, level, name, known):
    """The module file an ``import`` in ``module`` names (relative or absolute), or None
    outside the package."""
    if level == 0:
        if not name or not name.startswith("knnrefine"):
            return None
        parts = name.split(".")[1:]
    else:
        base = module.split("/")[:-1]
        if level > 1:
            base = base[: len(base) - (level - 1)]
        parts = base + (name.split(".") if name else [])
    for candidate in ("/".join(parts) + ".py", "/".join(parts + ["__init__.py"])):
        if candidate in known:
            return candidate
    return None


def imports():
    """{module: {module it imports}} over the package, `from . import x` as x's module."""
    known = _modules()
    graph = {}
    for module, path in known.items():
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                target = _resolve(module, node.level, node.module, known)
                for alias in node.names:  # `from . import run`: the module run
                    named = f"{node.module or ''}.{alias.name}".strip(".")
                    sub = _resolve(module, node.level, named, known)
                    if sub is not None and sub != target:
                        found.add(sub)
                if target is not None:
                    found.add(target)
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    target = _resolve(module, 0, alias.name, known)
                    if target is not None:
                        found.add(target)
        found.discard(module)
        graph[module] = found
    return graph


def test_no_module_imports_one_above_its_layer():
    up = [
        f"{module} -> {target}"
        for module, targets in imports().items()
        for target in targets
        if _layer(target) > _layer(module) and not target.endswith("__init__.py")
    ]
    assert up == [], "imports back up a layer:\n" + "\n".join(up)


def test_no_import_circles():
    graph = {m: {t for t in ts if not t.endswith("__init__.py")} for m, ts in imports().items()}
    circles = []
    state = {}

    def visit(module, path):
        state[module] = "open"
        for target in sorted(graph.get(module, ())):
            if state.get(target) == "open":
                circles.append(" -> ".join(path[path.index(target) :] + [target]))
            elif target not in state:
                visit(target, path + [target])
        state[module] = "done"

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    assert circles == [], "import circles:\n" + "\n".join(circles)


@pytest.mark.parametrize("module", sorted(_modules()))
def test_every_module_is_in_a_layer_and_on_the_map(module):
    _layer(module)
    text = (PACKAGE.parents[1] / "docs" / "data-structure.md").read_text()
    assert Path(module).name in text, f"{module} is not on docs/data-structure.md's map"


# what every domain's package offers (``knnrefine._domains``): the same modules, the same names
PROTOCOL = {
    "run.py": ("checked", "refine"),
    "certify.py": ("Geometry", "Points", "checked_points"),
    "density.py": (
        "Pieces",
        "index_of",
        "points_of",
        "to_frame",
        "flat_radius",
        "build",
        "complex_of",
    ),  # fmt: skip
}


@pytest.mark.parametrize("domain", ["plane", "space", "sphere"])
def test_every_domain_is_a_package_of_the_same_modules_and_names(domain):
    import importlib

    from knnrefine._domains import NAMES, PARTS

    assert set(NAMES) == {p.name for p in (PACKAGE / "_domains").iterdir() if p.is_dir()
                          and p.name != "__pycache__"}  # fmt: skip
    files = {p.name for p in (PACKAGE / "_domains" / domain).glob("*.py")}
    assert files == {"__init__.py", *(f"{name}.py" for name in PARTS)} == {"__init__.py", *PROTOCOL}
    for module, names in PROTOCOL.items():
        loaded = importlib.import_module(f"knnrefine._domains.{domain}.{module[:-3]}")
        missing = [name for name in names if not callable(getattr(loaded, name, None))]
        assert missing == [], f"_domains/{domain}/{module} lacks {missing}"


def test_no_domain_imports_another():
    across = [
        f"{module} -> {target}"
        for module, targets in imports().items()
        if module.startswith("_domains/") and module.count("/") == 2
        for target in targets
        if target.startswith("_domains/") and target.count("/") == 2
        and target.split("/")[1] != module.split("/")[1]
    ]  # fmt: skip
    assert across == []
