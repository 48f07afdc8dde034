"""zernet.geometry is float64 numpy/scipy: none of its modules (``polar/`` included) imports torch, and
every one of them imports in a process where torch cannot be imported (what they import from zernet's lower
layers too). The old import paths are gone."""

import ast
import pathlib
import subprocess
import sys

import pytest

import zernet.geometry

GEOMETRY = pathlib.Path(zernet.geometry.__file__).parent


def _imported_modules(path: pathlib.Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


MODULES = sorted(GEOMETRY.rglob("*.py"))


def _module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(GEOMETRY.parent.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def test_the_scan_covers_the_polar_backends():
    names = {_module_name(path) for path in MODULES}
    assert {"zernet.geometry", "zernet.geometry.polar", "zernet.geometry.polar.front"} <= names


@pytest.mark.parametrize("path", MODULES, ids=lambda path: str(path.relative_to(GEOMETRY)))
def test_no_geometry_module_imports_torch(path):
    torch_imports = {name for name in _imported_modules(path) if name.split(".")[0] == "torch"}
    assert not torch_imports, f"{path.name} imports {sorted(torch_imports)}"


def test_geometry_imports_in_a_process_without_torch():
    # sys.modules["torch"] = None makes every `import torch` raise ImportError, also in the zernet modules
    # geometry imports (io_utils, threads).
    imports = "; ".join(f"import {_module_name(path)}" for path in MODULES)
    code = f"import sys; sys.modules['torch'] = None; {imports}"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr


def test_old_import_paths_are_gone():
    """The deprecated re-export modules of 0.1 were removed in 0.2 (CHANGELOG.md)."""
    import importlib

    for name in (
        "zernet.surface",
        "zernet.polar",
        "zernet.membrane",
        "zernet.patches",
        "zernet.train",
        "zernet.nn.geometry",
        "zernet.nn.baselines",
        "zernet.data.base",
    ):
        with pytest.raises(ModuleNotFoundError):
            importlib.import_module(name)
