"""pipe_nav_core.warmup: the kernels are compiled once per install, and never in silence."""

from __future__ import annotations

from pipe_nav_core import warmup


def test_ensure_warm_compiles_once_and_says_so(tmp_path, monkeypatch):
    marker = tmp_path / "kernels_warm.txt"
    monkeypatch.setattr(warmup, "_marker", lambda: marker)
    # the AOT module of the real install is left as it is (tests/integration/test_aot.py builds one)
    monkeypatch.setattr(warmup, "_build_aot", lambda jit, tell: "not built in this test")
    said: list[str] = []
    assert not warmup.is_warm()
    assert warmup.ensure_warm(said.append) is True
    assert len(said) == 2 and "compiling" in said[0] and "kernels ready in" in said[1]
    assert warmup.is_warm() and marker.is_file()
    said.clear()
    assert warmup.ensure_warm(said.append) is False and said == []
    marker.write_text("another source stamp")  # the package changed since
    assert not warmup.is_warm()


def test_the_warm_up_run_has_every_kind_of_measurement():
    log, config = warmup._warmup_run()
    assert len(log.markers) >= 2 and len(log.odometer.t) and len(log.mag.t)


def test_the_installer_writes_the_package_bytecode(tmp_path, monkeypatch):
    """compile_bytecode writes every module's .pyc even where PYTHONDONTWRITEBYTECODE keeps
    Python from writing it (a copy of two modules stands for the package)."""
    import shutil
    import sys

    from pipe_nav_core import jit

    pkg = tmp_path / "pkg"
    (pkg / "io").mkdir(parents=True)
    shutil.copy(jit._PACKAGE / "errors.py", pkg / "errors.py")
    shutil.copy(jit._PACKAGE / "io" / "stamps.py", pkg / "io" / "stamps.py")
    monkeypatch.setattr(jit, "_PACKAGE", pkg)
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    warmup.compile_bytecode()
    tag = sys.implementation.cache_tag
    assert (pkg / "__pycache__" / f"errors.{tag}.pyc").is_file()
    assert (pkg / "io" / "__pycache__" / f"stamps.{tag}.pyc").is_file()
