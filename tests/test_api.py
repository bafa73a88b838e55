"""The curated public API of pipe_nav_core (its __init__): every name resolves to the object its
module defines, and importing the package alone imports nothing heavy."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

import pipe_nav_core


def test_every_public_name_is_its_modules_object():
    assert pipe_nav_core.__all__ and set(pipe_nav_core.__all__) <= set(dir(pipe_nav_core))
    for name in pipe_nav_core.__all__:
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
