"""The report PNG: written headless, complete, atomic."""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.app.plots import marker_residuals_enu, plot_report
from pipe_nav_core.io import interpolate_trajectory
from pipe_nav_core.types import Marker
from test_io_support import DATUM, make_traj


def _png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    w, h = struct.unpack(">II", data[16:24])
    return w, h


def _markers(traj, times, offset_m=0.0):
    est = interpolate_trajectory(traj, times)
    dlat = offset_m / 6.37e6
    return [
        Marker(
            f"agm_{i:02d}",
            float(t),
            float(est.lat[i]) + dlat,
            float(est.lon[i]),
            float(est.h[i]) - offset_m,
        )
        for i, t in enumerate(times)
    ]


def test_plot_report_writes_png(tmp_path):
    traj = make_traj(n=2001, seconds=200.0)
    mk = _markers(traj, [0.0, 50.0, 120.0, 200.0], offset_m=0.03)
    p = tmp_path / "report.png"
    plot_report(p, traj, DATUM, mk, title="unit test")
    data = p.read_bytes()
    w, h = _png_size(data)
    assert w >= 1200 and h >= 900
    assert len(data) > 50_000  # four panels with content, not a blank canvas
    assert [x.name for x in tmp_path.iterdir()] == ["report.png"]


def test_residuals_default_to_estimate_minus_survey():
    traj = make_traj(n=201, seconds=20.0)
    mk = _markers(traj, [5.0, 10.0], offset_m=0.05)  # survey 5 cm north and 5 cm lower
    res = marker_residuals_enu(traj, DATUM, mk)
    assert res.shape == (2, 3)
    np.testing.assert_allclose(res[:, 1], -0.05, atol=2e-3)
    np.testing.assert_allclose(res[:, 2], 0.05, atol=1e-3)


@pytest.mark.parametrize("sigma", [True, False])
def test_plot_report_degenerate_inputs(tmp_path, sigma):
    traj = make_traj(n=3, seconds=1.0, with_sigma=sigma)
    p = tmp_path / "r.png"
    plot_report(p, traj, DATUM)  # no markers, tiny trajectory
    assert _png_size(p.read_bytes())[0] > 0
    big = make_traj(n=60001, seconds=6000.0, with_sigma=sigma)  # decimated for drawing
    mk = _markers(big, [100.0, 3000.0])
    plot_report(p, big, DATUM, mk, marker_residuals=np.array([[0.01, -0.02, 0.5], [0, 0, 0]]))
    assert _png_size(p.read_bytes())[0] > 0


def test_plot_report_failure_keeps_old_file(tmp_path):
    p = tmp_path / "r.png"
    p.write_bytes(b"old")
    traj = make_traj(n=11)
    with pytest.raises(ValueError):
        plot_report(p, traj, DATUM, _markers(traj, [0.5]), marker_residuals=np.zeros((2, 2)))
    assert p.read_bytes() == b"old"
    assert [x.name for x in tmp_path.iterdir()] == ["r.png"]


def test_the_plot_process_draws_what_plot_report_draws(tmp_path):
    from pipe_nav_core.app.plot_process import PlotProcess

    traj = make_traj(n=2001, seconds=200.0)
    mk = _markers(traj, [10.0, 150.0], offset_m=0.02)
    inline, child = tmp_path / "inline.png", tmp_path / "child.png"
    plot_report(inline, traj, DATUM, mk, title="r")
    with PlotProcess.start() as plotter:
        assert plotter._process is not None and plotter._process.is_alive()  # forked
        plotter.submit(child, traj, DATUM, mk, title="r")
        plotter.wait()
        process = plotter._process
    assert not process.is_alive()  # ended with the context
    assert child.read_bytes() == inline.read_bytes()


WARM_WORD = """
import json, sys, time
from pipe_nav_core.app.plot_process import PlotProcess

def maps_matplotlib(pid):
    with open(f"/proc/{pid}/maps", encoding="utf-8") as f:
        return "ft2font" in f.read()  # matplotlib's font library, loaded with it

with PlotProcess.start(warm=False) as plotter:
    pid = plotter._process.pid
    time.sleep(1.5)  # more than it takes to import matplotlib
    before = maps_matplotlib(pid)
    plotter.warm()
    deadline = time.monotonic() + 60.0
    while not maps_matplotlib(pid) and time.monotonic() < deadline:
        time.sleep(0.02)
    after = maps_matplotlib(pid)
    from test_io_support import DATUM, make_traj
    plotter.submit(sys.argv[1], make_traj(n=2001, seconds=200.0), DATUM, title="r")
    plotter.wait()
with PlotProcess.start() as plotter:  # at once
    pid = plotter._process.pid
    deadline = time.monotonic() + 60.0
    while not maps_matplotlib(pid) and time.monotonic() < deadline:
        time.sleep(0.02)
    at_once = maps_matplotlib(pid)
print(json.dumps({"before": before, "after": after, "at_once": at_once,
                  "parent": "matplotlib" in sys.modules}))
"""


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="reads /proc/PID/maps")
def test_the_plot_process_loads_matplotlib_on_the_parents_word(tmp_path):
    """Started with warm=False, the child waits with matplotlib until told (in a command, the
    parent reads a large bag on both cores meanwhile); warmed, it draws the same PNG as
    plot_report. Started warm, it loads matplotlib at once. The parent never imports it."""
    inline, child = tmp_path / "inline.png", tmp_path / "child.png"
    plot_report(inline, make_traj(n=2001, seconds=200.0), DATUM, title="r")
    out = subprocess.run([sys.executable, "-c", WARM_WORD, str(child)], capture_output=True,
                         text=True, timeout=300, check=True,
                         env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})  # fmt: skip
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r == {"before": False, "after": True, "at_once": True, "parent": False}
    assert child.read_bytes() == inline.read_bytes()


def test_a_run_that_ends_early_does_not_wait_for_the_plot_process():
    """Closed while it loads matplotlib (a run refused after its bag was read), the child is
    ended there, not waited for."""
    from pipe_nav_core.app.plot_process import PlotProcess

    with PlotProcess.start(warm=False) as plotter:
        process = plotter._process
        plotter.warm()
    assert process.exitcode == -signal.SIGTERM


def test_a_failing_plot_in_the_plot_process_is_raised_and_writes_nothing(tmp_path):
    from pipe_nav_core.app.plot_process import PlotProcess

    p = tmp_path / "r.png"
    traj = make_traj(n=11)
    with PlotProcess.start() as plotter:
        plotter.submit(p, traj, DATUM, _markers(traj, [0.5]), marker_residuals=np.zeros((2, 2)))
        with pytest.raises(RuntimeError, match="the report plot failed: ValueError"):
            plotter.wait()
        plotter.submit(p, traj, DATUM)  # the child serves the next request
        plotter.wait()
    assert _png_size(p.read_bytes())[0] > 0
    assert [x.name for x in tmp_path.iterdir()] == ["r.png"]


def test_the_strain_panel_labels_its_log_axes_with_plain_numbers():
    """The strain (percent) and curvature (1/km) log axes read 0.01, 0.1, 1: plain numbers,
    not powers of ten typeset in mathtext (whose parser cost the plot's child some 0.25 s of
    CPU to build, a third of its warm-up)."""
    import math

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from pipe_nav_core.app import plots
    from pipe_nav_core.config import NavConfig
    from pipe_nav_core.products import integrity_report
    from test_products import arc, pipe

    cfg = NavConfig(imu_grade="tactical", pipe_outer_diameter=0.3, curvature_window=1.0)
    report = integrity_report(pipe(arc(20.0, 0.2, 10.0), lambda s: 0 * s, 60.0), cfg)
    assert report.bends
    fig = Figure()
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    plots._strain_panel(ax, report, 1.0, "m")
    fig.canvas.draw()
    for axes in [ax, *ax.child_axes]:  # the strain axis and its curvature twin
        labels = [t.get_text() for t in axes.get_yticklabels() if t.get_text()]
        assert len(labels) >= 2
        for text in labels:
            assert "$" not in text
            value = float(text)
            assert value > 0 and abs(math.log10(value) - round(math.log10(value))) < 1e-9
