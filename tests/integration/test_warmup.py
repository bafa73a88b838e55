"""pipe_nav_core.warmup: the kernels are compiled once per install, and never in silence."""

from __future__ import annotations

import pytest

from pipe_nav_core import warmup


def test_ensure_warm_compiles_once_and_says_so(tmp_path, monkeypatch):
    marker = tmp_path / "kernels_warm.txt"
    monkeypatch.setattr(warmup, "_marker", lambda: marker)
    # the AOT module of the real install is left as it is (tests/integration/test_aot.py builds one)
    monkeypatch.setattr(warmup, "_build_aot", lambda jit, tell: "not built in this test")
    from pipe_nav_core import jit

    monkeypatch.setattr(jit, "AOT_PREBUILT", False)  # no prebuilt module: the kernels compiled
    monkeypatch.setattr(jit, "PREBUILT_MISFIT", "they are built for numba 0.1, this has 0.2")
    said: list[str] = []
    assert not warmup.is_warm()
    assert warmup.ensure_warm(said.append) is True
    assert len(said) == 2 and "compiling" in said[0] and "kernels ready in" in said[1]
    assert said[0].endswith("; the prebuilt ones do not serve: they are built for numba 0.1, "
                            "this has 0.2)")  # fmt: skip
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


def _child(monkeypatch, code: str) -> list[str]:
    """warmup._fresh_build replaced by a Python process running ``code``; the list of the
    processes started (their code)."""
    import subprocess
    import sys

    started: list[str] = []

    def fresh() -> subprocess.Popen[str]:
        started.append(code)
        return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)

    monkeypatch.setattr(warmup, "_fresh_build", fresh)
    return started


def test_the_aot_module_is_built_by_a_fresh_process_and_its_outcome_kept(monkeypatch):
    from pipe_nav_core import jit

    said: list[str] = []
    built_here: list[int] = []

    def build_here() -> int:
        built_here.append(1)
        return 105

    monkeypatch.setattr(jit, "build_aot", build_here)
    monkeypatch.setattr(warmup, "_cached_to_disk", lambda: True)
    started = _child(monkeypatch, "print('compiling...'); print('built 39 exports')")
    assert warmup._build_aot(jit, said.append) == "39 exports"
    assert len(started) == 1 and said == [] and built_here == []
    _child(monkeypatch, "print('failed (LinkerError: no cc)')")
    assert warmup._build_aot(jit, said.append) == "failed (LinkerError: no cc)"
    assert said == ["pipe_nav_core: kernels stay just-in-time (the ahead-of-time build failed: "
                    "LinkerError: no cc)"]  # fmt: skip
    # the fresh process crashed: this one builds the module from what it compiled
    _child(monkeypatch, "raise SystemExit(1)")
    assert warmup._build_aot(jit, said.append) == "105 exports" and built_here == [1]
    # no disk cache: a fresh process would compile every kernel again
    monkeypatch.setattr(warmup, "_cached_to_disk", lambda: False)
    started = _child(monkeypatch, "print('built 39 exports')")
    assert warmup._build_aot(jit, said.append) == "105 exports" and started == []


def test_the_kernels_are_cached_to_disk_here():
    """The install these tests run in caches numba's kernels to disk, as the fresh process
    building the AOT module needs (where it did not, that process would compile them again)."""
    from pipe_nav_core import jit

    jit.to_jit("the test asks numba's dispatcher")
    assert warmup._cached_to_disk()


def test_the_warm_up_module_names_what_it_was_asked_wrongly(capsys):
    assert warmup.main(["--aot"]) == 2
    assert "(got --aot)" in capsys.readouterr().err


def test_the_prebuilt_module_makes_the_install_warm(tmp_path, monkeypatch):
    """Where the package's prebuilt module serves, there is nothing to compile: no marker is
    needed, ensure_warm says nothing and compiles nothing."""
    from pipe_nav_core import jit

    monkeypatch.setattr(warmup, "_marker", lambda: tmp_path / "none.txt")
    monkeypatch.setattr(jit, "AOT_PREBUILT", True)
    monkeypatch.setattr(warmup, "_compile_every_kernel", lambda why: pytest.fail(why))
    said: list[str] = []
    assert warmup.is_warm() and warmup.ensure_warm(said.append) is False and said == []
    monkeypatch.setattr(jit, "AOT_PREBUILT", False)
    assert not warmup.is_warm()
