"""The fault corpus (sim.faults.CORPUS) on a second size of run: the demo pipe at 1.2 km with
13 markers (the per-fault tests use the bundled 300 m sample). Every fault is named, the run
is DEGRADED (not OK, not a silent answer), the centreline stays within 15 cm with its sigmas
covering 95 % of it, and the live replay stays inside its sigmas (or says it is lost)."""

from __future__ import annotations

import math

import pytest
from pipe_nav_core.bench.faults import Size, run_case
from pipe_nav_core.config import NavConfig
from pipe_nav_core.sim import simulate
from pipe_nav_core.sim.faults import CORPUS
from pipe_nav_core.sim.scenarios import get_scenario


@pytest.fixture(scope="module")
def size():
    scn = get_scenario("demo").with_length(1200.0)
    run = simulate(scn, seed=3)
    return Size("demo 1.2 km", run.log, run.truth, NavConfig.from_dict(scn.estimator_settings()))


@pytest.fixture(scope="module")
def clean(size, tmp_path_factory):
    return run_case(size, None, tmp_path_factory.mktemp("clean"))


def test_the_clean_run(clean):
    assert clean.verdict == "OK" and clean.live == "navigating"
    assert clean.max_h < 0.1 and clean.inside >= 0.95 and clean.live_inside >= 0.95


@pytest.mark.parametrize("case", CORPUS, ids=[c.name for c in CORPUS])
def test_each_fault(size, clean, case, tmp_path):
    o = run_case(size, case, tmp_path)
    assert o.named and o.verdict == "DEGRADED", o
    assert o.max_h < max(0.15, 2 * clean.max_h) and o.max_v < max(0.15, 2 * clean.max_v), o
    assert o.inside >= 0.95, o
    assert o.live in ("navigating", "lost"), o
    # published estimates inside their sigmas; a replay lost before its first position
    # (markers on another clock) publishes none
    assert o.live_inside >= 0.95 or (o.live == "lost" and math.isnan(o.live_inside)), o


def test_the_command_line_on_a_damaged_run(size, tmp_path, capsys):
    """pipe-nav smooth on the 30 s gap: every product written, the fault on stderr, exit 0;
    with --strict exit 3 (DEGRADED)."""
    from pipe_nav_core.app.cli import main
    from pipe_nav_core.io import write_sensor_bag

    case = next(c for c in CORPUS if c.name.startswith("data gap"))
    duration = float(size.log.imu.t[-1] - size.log.imu.t[0])
    bag = tmp_path / "gap.mcap"
    write_sensor_bag(bag, case.inject(size.log, duration))
    out = tmp_path / "out"
    assert main(["smooth", str(bag), "--out", f"{out}/", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "data gap of 30.0 s" in err and "quality DEGRADED" in err
    assert sorted(p.name for p in out.iterdir()) == sorted(
        f"gap_{x}" for x in ("smoothed.mcap", "centerline.csv", "centerline.geojson",
                             "centerline.kml", "report.png", "strain.csv", "bends.csv",
                             "strain_features.csv", "welds.csv")
    )  # fmt: skip
    assert main(["smooth", str(bag), "--out", f"{tmp_path}/strict/", "--quiet", "--strict"]) == 3
