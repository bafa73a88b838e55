"""End to end through the command line: ``pipe-nav smooth`` writes RUN_welds.csv and stores
the welds and the centreline in the smoothed bag; ``pipe-nav locate`` gives a simulated vendor
tally's rows their coordinates (FEATURES.csv and GeoJSON); bad input is one line, exit 2."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
from pipe_nav_core.app.cli import main
from pipe_nav_core.io import write_markers_csv, write_sensor_bag
from pipe_nav_core.io.smoothed_bag import read_smoothed_run
from pipe_nav_core.sim import get_scenario, simulate
from pipe_nav_core.sim.tally import make_tally


@pytest.fixture(scope="module")
def smoothed(tmp_path_factory):
    d = tmp_path_factory.mktemp("locate")
    scn = get_scenario("demo")
    run = simulate(scn, seed=5)
    bag = d / "run.mcap"
    write_sensor_bag(bag, run.log)
    cfg = d / "run.yaml"
    cfg.write_text("".join(f"{k}: {json.dumps(v)}\n" for k, v in scn.estimator_settings().items()))
    assert main(["smooth", str(bag), "--out", str(d / "out") + "/", "--config", str(cfg),
                 "--quiet"]) == 0  # fmt: skip
    sim = make_tally(run.welds, np.random.default_rng(2), n_features=20, missing=0.08,
                     extra=0.04)  # fmt: skip
    sim.write_csv(d / "tally.csv")
    return d, run, sim


def test_smooth_writes_the_weld_log_and_the_bag_carries_it(smoothed):
    d, run, _ = smoothed
    welds_csv = d / "out" / "run_welds.csv"
    lines = welds_csv.read_text().splitlines()
    assert lines[0].startswith("weld,distance_m,latitude_deg,longitude_deg,altitude_m,"
                               "joint_length_m,confidence,sigma_h_m,sigma_v_m")  # fmt: skip
    assert len(lines) - 1 == len(run.welds)
    r = read_smoothed_run(d / "out" / "run_smoothed.mcap")
    assert len(r.welds) == len(run.welds) and r.trajectory.sigma_enu is not None
    assert r.welds[3].distance == pytest.approx(float(lines[4].split(",")[1]))


def test_locate_gives_every_tally_row_its_position(smoothed, capsys):
    d, run, sim = smoothed
    out, gj = d / "features.csv", d / "features.geojson"
    assert main(["locate", str(d / "tally.csv"), "--run", str(d / "out" / "run_smoothed.mcap"),
                 "--out", str(out), "--geojson", str(gj)]) == 0  # fmt: skip
    assert "tally rows located" in capsys.readouterr().out
    with open(out, newline="") as f:
        rows = list(csv.reader(f))
    own = rows[0][:8]
    assert own == ["weld_number", "log_distance_m", "joint_length_m", "distance_to_us_weld_m",
                   "type", "clock", "depth_pct", "comment"]  # fmt: skip
    assert rows[0][8:] == ["distance_m", "latitude_deg", "longitude_deg", "altitude_m",
                           "sigma_h_m", "sigma_v_m", "matched_weld"]  # fmt: skip
    assert len(rows) - 1 == len(sim.rows)
    errs = []
    for row, truth in zip(rows[1:], sim.rows, strict=True):
        assert row[:8] == truth.cells  # the tally's own cells unchanged
        if not math.isfinite(truth.true_distance):
            assert row[14] == ""  # the vendor's false weld: no matched weld
            continue
        lat, lon, h = run.geometry.position(truth.true_distance)
        dn = (math.radians(float(row[9])) - float(lat)) * 6.371e6
        de = (math.radians(float(row[10])) - float(lon)) * 6.371e6 * math.cos(float(lat))
        e = math.sqrt(de**2 + dn**2 + (float(row[11]) - float(h)) ** 2)
        errs.append(e)
        sigma = math.hypot(float(row[12]), float(row[13]))
        assert e < 5.0 * sigma + 0.05
    assert np.sqrt(np.mean(np.square(errs))) < 0.2
    doc = json.loads(gj.read_text())
    assert len(doc["features"]) == len(sim.rows)
    assert doc["features"][0]["properties"]["matched_weld"] is not None


def test_locate_bad_input_is_one_line_exit_2(smoothed, tmp_path, capsys):
    d, _, _ = smoothed
    bad = tmp_path / "bad.csv"
    bad.write_text("weld,log_distance_m\n1,0\n2,twelve\n")
    run = str(d / "out" / "run_smoothed.mcap")
    assert main(["locate", str(bad), "--run", run, "--out", str(tmp_path / "f.csv")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bad.csv:3: log_distance_m 'twelve' is not a number" in err
    assert not (tmp_path / "f.csv").exists()
    assert main(["locate", str(d / "tally.csv"), "--run", str(d / "tally.csv"),
                 "--out", str(tmp_path / "f.csv")]) == 2  # fmt: skip
    assert "not a readable MCAP bag" in capsys.readouterr().err
    assert main(["locate", str(d / "tally.csv"), "--run", run, "--out", run]) == 2
    assert "refusing to overwrite the input" in capsys.readouterr().err
    # a smoothed bag without welds (no magnetometer) names the way out
    log = simulate(get_scenario("demo").with_length(60.0), seed=1).log
    log.mag = type(log.mag)(log.mag.t[:0], log.mag.field[:0])
    write_sensor_bag(tmp_path / "nomag.mcap", log)
    write_markers_csv(tmp_path / "m.csv", log.markers)
    assert main(["smooth", str(tmp_path / "nomag.mcap"), "--out", str(tmp_path / "o") + "/",
                 "--quiet"]) == 0  # fmt: skip
    assert not (tmp_path / "o" / "nomag_welds.csv").exists()
    nomag = str(tmp_path / "o" / "nomag_smoothed.mcap")
    assert main(["locate", str(d / "tally.csv"), "--run", nomag, "--out",
                 str(tmp_path / "f.csv")]) == 2  # fmt: skip
    assert "give them with --welds" in capsys.readouterr().err
