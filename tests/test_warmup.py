"""pipe_nav_core.warmup: the kernels are compiled once per install, and never in silence."""

from __future__ import annotations

from pipe_nav_core import warmup


def test_ensure_warm_compiles_once_and_says_so(tmp_path, monkeypatch):
    marker = tmp_path / "kernels_warm.txt"
    monkeypatch.setattr(warmup, "_marker", lambda: marker)
    # the AOT module of the real install is left as it is (tests/test_aot.py builds one)
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
