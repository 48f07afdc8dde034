"""The layers of zernet hold: every import between its top-level packages goes down the table below.

Every ``.py`` file under ``zernet/`` is parsed (not imported), and every import in it is read: at module
level and inside functions, absolute and relative, and ``importlib.import_module("zernet...")`` with a
literal name. Each is mapped to the top-level packages of the importer and the imported
(``zernet.training.loop`` -> ``training``; ``zernet.io_utils`` -> ``io_utils``), and an import between two
packages is allowed only from a higher layer to a lower one. ``docs/ARCHITECTURE.md`` shows the same table.
"""

import ast
import pathlib

import pytest

import zernet

PACKAGE = pathlib.Path(zernet.__file__).parent

#: The layers, lowest first: a package may import the packages of the layers below its own, nothing in its
#: own layer or above. ``zernet`` is the root package itself (its ``__version__``).
LAYERS = (
    ("zernet", "zernike", "fourier", "threads", "io_utils", "metrics", "viz", "distributed"),
    ("geometry",),
    ("operators",),
    ("nn",),
    ("data",),
    ("inference", "pyg"),
    ("training",),
    ("matching",),
    ("cli",),
)

#: The modules of ``matching`` that train its models; the rest of ``matching`` (the library) sits below them.
MATCHING_TRAINERS = ("zernet.matching.train", "zernet.matching.train_template")


def _module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported_names(path: pathlib.Path) -> list[tuple[str, int]]:
    """(imported module, line) for every import of ``path``, relative ones made absolute; for
    ``from package import name`` both ``package`` and ``package.name`` (the name may be a module)."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module
            found.append((source, node.lineno))
            found += [(f"{source}.{alias.name}", node.lineno) for alias in node.names]
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", None)) in (
            "import_module",
            "__import__",
        ):
            if node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
                found.append((node.args[0].value, node.lineno))
    return found


def _top_level(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _package_imports() -> list[tuple[str, str, str]]:
    """(importer, imported, where) for every import from one top-level package of zernet to another."""
    known = {_top_level(_module_name(path)) for path in PACKAGE.rglob("*.py")}
    edges = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        importer = _top_level(_module_name(path))
        for name, line in _imported_names(path):
            if name.split(".")[0] != "zernet":
                continue
            imported = _top_level(name)
            if imported not in known:  # ``from zernet import __version__``: the root package itself
                imported = "zernet"
            where = f"{path.relative_to(PACKAGE.parent)}:{line}"
            if imported != importer and (imported, where) not in edges:  # one report per import statement
                edges[imported, where] = (importer, imported, f"{where} imports {name}")
    return list(edges.values())


def _layer_of() -> dict[str, int]:
    return {package: rank for rank, layer in enumerate(LAYERS) for package in layer}


def test_every_top_level_package_is_in_the_table():
    packages = {_top_level(_module_name(path)) for path in PACKAGE.rglob("*.py")}
    assert packages - set(_layer_of()) == set(), "add the new package to LAYERS (and docs/ARCHITECTURE.md)"
    assert set(_layer_of()) - packages == set(), "LAYERS names a package that no longer exists"


def test_imports_reach_function_bodies_and_relative_imports():
    """The reader sees what the rules are about: an import inside a function and a relative one."""
    names = {name for name, _ in _imported_names(PACKAGE / "nn" / "models" / "registry.py")}
    assert "zernet.nn.models.baselines" in names  # from .baselines import FeaStNet
    names = {name for name, _ in _imported_names(PACKAGE / "data" / "features.py")}
    assert "zernet.operators.spectral" in names  # imported inside heat_kernel_descriptors


def test_imports_go_down_the_layers():
    layer = _layer_of()
    upward = [where for importer, imported, where in _package_imports() if layer[imported] >= layer[importer]]
    assert upward == [], "imports against the layer order (docs/ARCHITECTURE.md):\n" + "\n".join(upward)


def test_no_cycle_between_top_level_packages():
    graph: dict[str, set[str]] = {}
    for importer, imported, _ in _package_imports():
        graph.setdefault(importer, set()).add(imported)
    finished: set[str] = set()

    def visit(package: str, path: tuple[str, ...]):
        if package in path:
            pytest.fail("import cycle: " + " -> ".join(path[path.index(package) :] + (package,)))
        if package in finished:
            return
        for imported in sorted(graph.get(package, ())):
            visit(imported, path + (package,))
        finished.add(package)

    for package in sorted(graph):
        visit(package, ())


def test_matching_library_does_not_import_its_trainers():
    library = [
        path for path in sorted((PACKAGE / "matching").rglob("*.py")) if _module_name(path) not in MATCHING_TRAINERS
    ]
    wrong = [
        f"{path.relative_to(PACKAGE.parent)}:{line} imports {name}"
        for path in library
        for name, line in _imported_names(path)
        if name in MATCHING_TRAINERS
    ]
    assert wrong == []
