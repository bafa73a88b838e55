"""The curated public API of pipe_nav_core (its __init__): every name resolves to the object its
module defines, importing the package alone imports nothing heavy, and the ROS package uses
the core through this API only."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

import pipe_nav_core


def test_every_public_name_is_its_modules_object():
    assert pipe_nav_core.__all__ and set(pipe_nav_core.__all__) <= set(dir(pipe_nav_core))
    for name in pipe_nav_core.__all__:
        if name in pipe_nav_core._MODULES:  # a public module: the module itself
            module = importlib.import_module(f"pipe_nav_core.{pipe_nav_core._MODULES[name]}")
            assert getattr(pipe_nav_core, name) is module, name
            continue
        module = importlib.import_module(f"pipe_nav_core.{pipe_nav_core._API[name]}")
        assert getattr(pipe_nav_core, name) is getattr(module, name), name
    from pipe_nav_core import NavConfig, smooth_bag  # the way a user writes it

    assert NavConfig().mode == "ins" and callable(smooth_bag)


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'smooth_run'"):
        pipe_nav_core.smooth_run  # noqa: B018


def test_importing_the_package_imports_nothing_heavy():
    code = ("import sys, pipe_nav_core; "
            "print(sorted(m for m in ('numpy', 'numba', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


ROS_PACKAGE = Path(__file__).resolve().parents[2] / "src" / "pipe_nav_ros"


def core_imports(path: Path) -> list[tuple[int, str, str]]:
    """(line, module, name) of every import of pipe_nav_core in a source file, also those
    inside functions; name is "" for ``import pipe_nav_core[.x]``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module.split(".")[0] == "pipe_nav_core":
                found += [(node.lineno, node.module, a.name) for a in node.names]
        elif isinstance(node, ast.Import):
            found += [(node.lineno, a.name, "") for a in node.names
                      if a.name.split(".")[0] == "pipe_nav_core"]
    return found


def test_the_ros_package_imports_only_the_public_api():
    """The nodes, their helpers and the launch files import ``from pipe_nav_core import X``
    with X a name of the curated API, never from a submodule, so the API is what they need."""
    files = sorted(ROS_PACKAGE.glob("pipe_nav_ros/*.py")) + sorted(ROS_PACKAGE.glob("launch/*.py"))
    assert len(files) > 10
    wrong = [
        f"{path.relative_to(ROS_PACKAGE)}:{line}: {module} {name}".rstrip()
        for path in files
        for line, module, name in core_imports(path)
        if module != "pipe_nav_core" or name not in pipe_nav_core.__all__
    ]
    assert not wrong, wrong
    assert any(core_imports(path) for path in files)  # the check sees the imports
