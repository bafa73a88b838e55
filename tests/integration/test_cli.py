"""The pipe-nav command line on the bundled sample bag: outputs, formats, accuracy, bad input."""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.app.cli import main
from pipe_nav_core.app.commands import load_config
from pipe_nav_core.bench.evaluation import score
from pipe_nav_core.io import CENTRELINE_HEADER, read_centreline_csv

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "bags" / "sample.mcap"
TRUTH = ROOT / "bags" / "sample.truth.csv"
SURVEY = ROOT / "bags" / "sample.markers.csv"


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def smoothed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("smooth")
    before = _sha(SAMPLE)
    assert main(["smooth", str(SAMPLE), "--out", f"{out}/", "--quiet"]) == 0
    assert _sha(SAMPLE) == before, "the input bag was modified"
    return out


def test_smooth_writes_every_product(smoothed: Path):
    names = sorted(p.name for p in smoothed.iterdir())
    assert names == [
        "sample_bends.csv",
        "sample_centerline.csv",
        "sample_centerline.geojson",
        "sample_centerline.kml",
        "sample_report.png",
        "sample_smoothed.mcap",
        "sample_strain.csv",
        "sample_strain_features.csv",
        "sample_welds.csv",
    ]
    assert (smoothed / "sample_report.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    welds = (smoothed / "sample_welds.csv").read_text().splitlines()
    assert welds[0].startswith("weld,distance_m,latitude_deg,longitude_deg,altitude_m,"
                               "joint_length_m,confidence,sigma_h_m,sigma_v_m")  # fmt: skip
    gj = json.loads((smoothed / "sample_centerline.geojson").read_text())
    kinds = [f["properties"]["kind"] for f in gj["features"]]
    assert kinds.count("weld") == len(welds) - 1 > 10  # girth welds every ~12 m of 300 m
    assert (smoothed / "sample_centerline.kml").read_text().count("girth weld ") == len(welds) - 1
    line = next(f for f in gj["features"] if f["geometry"]["type"] == "LineString")
    lon, lat, _ = line["geometry"]["coordinates"][0]
    assert 116.3 < lon < 116.5 and 39.8 < lat < 40.0  # [lon, lat] order, degrees


def test_centreline_csv_format_and_accuracy(smoothed: Path):
    path = smoothed / "sample_centerline.csv"
    with path.open() as f:
        header = f.readline().strip()
    assert header == (
        "time_s,distance_m,latitude_deg,longitude_deg,altitude_m,east_m,north_m,up_m,"
        "roll_deg,pitch_deg,azimuth_deg,sigma_east_m,sigma_north_m,sigma_up_m"
    )
    assert header == CENTRELINE_HEADER
    rows = list(csv.DictReader(path.open()))
    d = np.array([float(r["distance_m"]) for r in rows])
    t = np.array([float(r["time_s"]) for r in rows])
    assert np.all(np.diff(t) > 0)
    # one row per 0.5 m of chainage plus one per marker
    n_markers = sum(1 for _ in SURVEY.open()) - 1
    assert abs(len(rows) - (d[-1] / 0.5 + 1 + n_markers)) <= n_markers + 2
    est, _ = read_centreline_csv(path)
    truth, datum = read_centreline_csv(TRUTH)
    s = score(est, truth, datum=datum)
    assert s.max_h < 0.15 and s.max_v < 0.15, s


def test_output_bag_decodes_with_rosbags(smoothed: Path):
    from rosbags.highlevel import AnyReader

    out = smoothed / "sample_smoothed.mcap"
    from pipe_nav_core.io import write_rosbag2_metadata

    work = smoothed / "as_dir"
    work.mkdir()
    shutil.copy(out, work / out.name)
    write_rosbag2_metadata(work / out.name)
    with AnyReader([work]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types["/pipe_nav/path"] == "nav_msgs/msg/Path"
        assert types["/pipe_nav/datum"] == "sensor_msgs/msg/NavSatFix"
        assert types["/pipe_nav/odometry"] == "nav_msgs/msg/Odometry"
        seen = set()
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == "/pipe_nav/path" and "path" not in seen:
                assert msg.header.frame_id == "map"
                assert len(msg.poses) > 500
                assert msg.poses[0].header.frame_id == "map"
                seen.add("path")
            elif conn.topic == "/pipe_nav/odometry" and "odom" not in seen:
                assert msg.header.frame_id == "map" and msg.child_frame_id == "base_link"
                seen.add("odom")
        assert seen == {"path", "odom"}


def test_replay_writes_odometry(tmp_path: Path):
    out = tmp_path / "replay.mcap"
    assert main(["replay", str(SAMPLE), "--out", str(out), "--quiet"]) == 0
    from pipe_nav_core.io import bag_info

    info = bag_info(out)
    odo = info.topics["/pipe_nav/odometry"]
    assert odo.count > 1000  # one per 0.1 s filter epoch over a 190 s run
    # the full 6x6 pose covariance, as ekf_node publishes it (position/attitude correlations)
    from pipe_nav_core.io import write_rosbag2_metadata
    from rosbags.highlevel import AnyReader

    write_rosbag2_metadata(out)
    with AnyReader([tmp_path]) as reader:
        conn = next(c for c in reader.connections if c.topic == "/pipe_nav/odometry")
        msgs = [reader.deserialize(raw, conn.msgtype) for _, _, raw in reader.messages([conn])]
    cov = np.array(msgs[len(msgs) // 2].pose.covariance).reshape(6, 6)
    np.testing.assert_allclose(cov, cov.T)
    assert np.all(np.diag(cov) > 0)
    assert np.abs(cov[:3, 3:]).max() > 0  # cross terms are there


def _run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pipe_nav_core.app.cli", *args],
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.mark.parametrize(
    "content",
    [b"", b"this is not a bag at all", b"\x89MCAP0\r\n" + b"\x00" * 40],
)
def test_bad_input_gives_one_line_error(tmp_path: Path, content: bytes):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(content)
    r = _run_cli("smooth", str(bad), "--out", str(tmp_path / "o.mcap"))
    assert r.returncode != 0
    assert "Traceback" not in r.stderr
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("pipe-nav: error:"), r.stderr
    assert not (tmp_path / "o.mcap").exists()


def test_missing_input_and_bad_setting(tmp_path: Path):
    r = _run_cli("smooth", str(tmp_path / "nope.mcap"), "--out", str(tmp_path / "o.mcap"))
    assert r.returncode != 0 and "Traceback" not in r.stderr and "nope.mcap" in r.stderr
    r = _run_cli("smooth", str(SAMPLE), "--out", str(tmp_path / "o.mcap"), "--set", "mode=warp")
    assert r.returncode != 0 and "mode" in r.stderr and "Traceback" not in r.stderr


def test_refuses_to_overwrite_the_input(tmp_path: Path):
    copy = tmp_path / "in.mcap"
    shutil.copy(SAMPLE, copy)
    before = _sha(copy)
    r = _run_cli("smooth", str(copy), "--out", str(copy))
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert _sha(copy) == before


def test_simulate_then_evaluate(tmp_path: Path):
    out = tmp_path / "run.mcap"
    assert (
        main(["simulate", "--scenario", "sag104", "--seed", "4", "--out", str(out), "--quiet"]) == 0
    )
    assert (
        out.exists()
        and (tmp_path / "run.truth.csv").exists()
        and (tmp_path / "run.markers.csv").exists()
        and (tmp_path / "run.config.yaml").exists()
    )
    r = _run_cli(
        "evaluate",
        str(tmp_path / "run.truth.csv"),
        "--truth",
        str(tmp_path / "run.truth.csv"),
        "--json",
    )
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["max_h"] == pytest.approx(0.0, abs=1e-6)


def test_simulated_run_smooths_with_its_settings_file(tmp_path: Path, capsys):
    """simulate writes the estimator settings its user would know (RUN.config.yaml): a
    consumer-MEMS run smooths with them to centimetres and no warning; so it does without them
    (the IMU model measured from the run); a wrong named grade does not fit and smooth says so."""
    from pipe_nav_core.config import NavConfig
    from pipe_nav_core.sim import get_scenario

    out = tmp_path / "run.mcap"
    assert main(["simulate", "--scenario", "drag180", "--seed", "1", "--out", str(out)]) == 0
    config = tmp_path / "run.config.yaml"
    assert f"--config {config.name}" in capsys.readouterr().out
    parser_args = argparse.Namespace(config=str(config), set=None, mode=None, imu_grade=None)
    assert load_config(parser_args) == NavConfig.from_dict(
        get_scenario("drag180").estimator_settings()
    )
    line = tmp_path / "c.csv"
    assert main(["smooth", str(out), "--out", str(tmp_path / "s.mcap"), "--csv", str(line),
                 "--config", str(config), "--quiet"]) == 0  # fmt: skip
    assert "--imu-grade" not in capsys.readouterr().err
    r = _run_cli("evaluate", str(line), "--truth", str(tmp_path / "run.truth.csv"), "--json")
    assert json.loads(r.stdout)["max_h"] < 0.3
    # without them the noise model is measured from the run (imu_grade auto): no warning
    assert main(["smooth", str(out), "--out", str(tmp_path / "d.mcap"), "--quiet"]) == 0
    assert "warning" not in capsys.readouterr().err
    # a wrong named grade is honoured, and warned about
    assert main(["smooth", str(out), "--out", str(tmp_path / "w.mcap"), "--quiet",
                 "--imu-grade", "industrial"]) == 0  # fmt: skip
    assert "check imu_grade (--imu-grade)" in capsys.readouterr().err


def test_survey_csv_without_passage_times(tmp_path: Path):
    """A survey known before the run has no passage times: read as NaN, kept in file order;
    merged with a bag, each survey row takes the passage time of the bag's marker of the same
    name; a row no bag marker times is ignored with a warning."""
    from pipe_nav_core.io import read_markers_csv

    lines = SURVEY.read_text().splitlines()
    survey = tmp_path / "survey.csv"
    rows = [lines[0]] + [",".join([r.split(",")[0], ""] + r.split(",")[2:]) for r in lines[1:]]
    rows.append("agm_99,,39.9,116.4,45.0,0.02,0.02")
    survey.write_text("\n".join(rows) + "\n")
    ms = read_markers_csv(survey)
    assert [m.name for m in ms] == [r.split(",")[0] for r in lines[1:]] + ["agm_99"]
    assert all(np.isnan(m.t) for m in ms)
    r = _run_cli("smooth", str(SAMPLE), "--out", str(tmp_path / "o.mcap"), "--markers", str(survey))
    assert r.returncode == 0, r.stderr
    assert "without a passage time" in r.stderr


def test_bench_makes_its_output_folders_and_fails_at_once_on_a_bad_path(
    tmp_path, capsys, monkeypatch
):
    blocker = tmp_path / "file"
    blocker.write_text("")
    bad = blocker / "sub" / "BENCH.md"
    assert main(["bench", "--speed-only", "--out", str(bad), "--json", ""]) != 0
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "pipe-nav" in err, err
    assert "speed" not in err  # nothing ran
    from pipe_nav_core.bench import speed

    monkeypatch.setattr(speed, "run", lambda length_km: {"x_real_time": 1.0})
    monkeypatch.setattr(speed, "markdown", lambda sp, command: "speed table\n")
    out, js = tmp_path / "a" / "b" / "BENCH.md", tmp_path / "c" / "bench.json"
    assert main(["bench", "--speed-only", "--out", str(out), "--json", str(js)]) == 0
    assert "speed table" in out.read_text()
    assert json.loads(js.read_text())["speed"] == {"x_real_time": 1.0}


def test_a_bad_path_fails_before_the_kernels_are_compiled(tmp_path, capsys, monkeypatch):
    """A first run compiles the kernels for minutes: a bag that is not there, or an output
    folder that cannot be made, is said before that, not after."""
    from pipe_nav_core.app import commands, integrity_commands

    def compile_first() -> None:
        raise AssertionError("the kernels were warmed before the path was checked")

    monkeypatch.setattr(commands, "warm_kernels", compile_first)
    monkeypatch.setattr(integrity_commands, "warm_kernels", compile_first)
    missing = tmp_path / "nope.mcap"
    blocker = tmp_path / "file"
    blocker.write_text("")
    for argv in (
        ["smooth", str(missing), "--out", f"{tmp_path}/out/"],
        ["replay", str(missing), "--out", str(tmp_path / "r.mcap")],
        ["bench", "--speed-only", "--out", str(blocker / "sub" / "B.md"), "--json", ""],
    ):
        assert main(argv) != 0
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1, err
        assert str(missing) in err or str(blocker) in err, err


@pytest.mark.parametrize("raw", ["0,0,-0.05", "[0,0,-0.05]", "0 0 -0.05", "0, 0, -0.05"])
def test_set_accepts_every_triple_syntax(raw: str):
    args = argparse.Namespace(config=None, set=[f"odometer_lever_arm={raw}"], mode=None,
                              imu_grade=None, mount_rpy_deg=None)  # fmt: skip
    assert load_config(args).odometer_lever_arm == pytest.approx((0.0, 0.0, -0.05))


def test_setting_errors_name_the_option_typed(tmp_path: Path):
    config = tmp_path / "pig.yaml"
    config.write_text("filter_rate_hz: -3\n")
    for extra, named in (
        (["--set", "odometer_lever_arm=0,0"], "--set odometer_lever_arm=0,0:"),
        (["--set", "filter_rate_hz=5", "--set", "mode=warp"], "--set mode=warp:"),
        (["--config", str(config)], f"--config {config}:"),
    ):
        r = _run_cli("smooth", str(SAMPLE), "--out", str(tmp_path / "o.mcap"), *extra)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and named in lines[0], r.stderr
    assert not (tmp_path / "o.mcap").exists()


def test_usage_errors_are_one_line(tmp_path: Path):
    for argv in (
        ["smooth"],
        ["frob"],
        ["smooth", str(SAMPLE), "--out", "x.mcap", "--imu-grade", "x"],
    ):
        r = _run_cli(*argv)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and ": error: " in lines[0], r.stderr


@pytest.mark.parametrize(
    ("extra", "named"),
    [
        (["--out", "/no/such/folder/o.mcap"], "--out /no/such/folder/o.mcap: no such folder"),
        (["--out", "o.mcap", "--csv", "same.txt", "--kml", "same.txt"], "--csv and --kml"),
        (["--out", "o.mcap", "--csv", "afile/c.csv"], "afile is a file, not a folder"),
        (["--out", "o.mcap", "--spacing", "0"], "--spacing must be a positive number"),
        (["--out", "o.mcap", "--spacing", "nan"], "--spacing must be a positive number"),
        (["--out", "o.mcap", "--plot", "."], "--plot .: is a folder"),
    ],
)
def test_every_output_is_checked_before_any_work(tmp_path, extra, named):
    (tmp_path / "afile").write_text("")
    r = subprocess.run(
        [sys.executable, "-m", "pipe_nav_core.app.cli", "smooth", str(SAMPLE), *extra],
        capture_output=True, text=True, cwd=tmp_path, timeout=60,
    )  # fmt: skip
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and named in lines[0], r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]  # nothing written


def test_a_failing_product_leaves_no_product(tmp_path, monkeypatch, capsys):
    from pipe_nav_core.app import plots

    def broken(*_a, **_k):
        raise OSError("disk full")

    monkeypatch.setattr(plots, "plot_report", broken)
    assert main(["smooth", str(SAMPLE), "--out", f"{tmp_path}/", "--quiet"]) == 2
    assert "disk full" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []  # neither the products written before nor staged files


def test_sigterm_while_writing_leaves_nothing_behind(tmp_path):
    import signal
    import time

    code = (
        "import sys, time; from pipe_nav_core.app import cli, plots\n"
        "plots.plot_report = lambda *a, **k: time.sleep(60)\n"
        "sys.exit(cli.main(sys.argv[1:]))\n"
    )
    out = tmp_path / "out"
    out.mkdir()
    proc = subprocess.Popen([sys.executable, "-c", code, "smooth", str(SAMPLE), "--out",
                             f"{out}/", "--quiet"], stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        end = time.monotonic() + 120
        while not any(p.suffix == ".part" for p in out.iterdir()):  # the bag, CSV... staged
            assert proc.poll() is None and time.monotonic() < end, "never got to the plot"
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM and "terminated" in err, err
    assert list(out.iterdir()) == []


def test_an_imu_topic_of_another_type_is_named(tmp_path):
    from pipe_nav_core.io import TopicNames, write_sensor_bag
    from pipe_nav_core.sim import simulate

    run = simulate("demo", 0)
    bag = tmp_path / "swapped.mcap"
    write_sensor_bag(bag, run.log, topics=TopicNames(imu="/imu/raw", odometer="/imu/data"))
    r = _run_cli("smooth", str(bag), "--out", str(tmp_path / "o.mcap"))
    assert r.returncode == 2 and "(it carries nav_msgs/msg/Odometry)" in r.stderr, r.stderr


def test_evaluate_a_centreline_cut_short(tmp_path):
    run = tmp_path / "run.mcap"
    assert main(["simulate", "--scenario", "demo", "--seed", "1", "--out", str(run)]) == 0
    truth = tmp_path / "run.truth.csv"
    text = truth.read_text()
    cut = tmp_path / "cut.csv"
    cut.write_text(text[: len(text) // 2 + 7])  # ends inside a row, as a crash leaves it
    r = _run_cli("evaluate", str(cut), "--truth", str(truth), "--json")
    assert r.returncode == 0, r.stderr
    assert r.stderr.count("\n") == 1 and "cut short" in r.stderr and "Warning" not in r.stderr
    assert json.loads(r.stdout)["max_h"] < 1e-6  # the rows kept are the truth's own
    lines = text.splitlines()
    lines[5] = ",".join(lines[5].split(",")[:4])
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines) + "\n")
    r = _run_cli("evaluate", str(bad), "--truth", str(truth))
    assert r.returncode == 2 and "bad.csv:6: fewer fields" in r.stderr, r.stderr


def test_a_clock_step_loses_the_live_solution_honestly(tmp_path):
    """A clock that steps an hour ahead halfway (which made the live filter write NaN): the
    replay, as ekf_node, says the solution was lost there and writes the odometry up to it,
    finite throughout (``smooth`` undoes the step: test_gaps)."""

    from pipe_nav_core.app.pipeline import load_log
    from pipe_nav_core.io import write_sensor_bag
    from pipe_nav_core.sim.faults import clock_step

    log, _ = load_log(SAMPLE)
    bag = tmp_path / "step.mcap"
    write_sensor_bag(bag, clock_step(log, 100.0, 3600.0))
    out = tmp_path / "r.mcap"
    r = _run_cli("replay", str(bag), "--out", str(out))
    assert r.returncode == 0 and "live solution was lost" in r.stderr, r.stderr
    assert "rejected" not in r.stderr  # no misfit blamed on the IMU model
    from pipe_nav_core.io import write_rosbag2_metadata
    from rosbags.highlevel import AnyReader

    write_rosbag2_metadata(out)
    with AnyReader([tmp_path]) as reader:
        conn = next(c for c in reader.connections if c.topic == "/pipe_nav/odometry")
        xs = [reader.deserialize(raw, conn.msgtype).pose.pose.position.x
              for _, _, raw in reader.messages([conn])]  # fmt: skip
    assert 500 < len(xs) < 1500 and np.isfinite(xs).all()


def test_the_writers_refuse_non_finite_samples(tmp_path):
    import dataclasses

    from pipe_nav_core.io import (
        read_centreline_csv,
        write_centreline_csv,
        write_geojson,
        write_kml,
        write_output_bag,
    )

    truth = tmp_path / "run.truth.csv"
    assert (
        main(["simulate", "--scenario", "demo", "--seed", "1", "--out", str(tmp_path / "run.mcap")])
        == 0
    )
    traj, datum = read_centreline_csv(truth)
    h = traj.h.copy()
    h[7] = np.nan
    bad = dataclasses.replace(traj, h=h)
    for write, name in (
        (lambda p: write_centreline_csv(p, bad, datum), "c.csv"),
        (lambda p: write_geojson(p, bad), "c.geojson"),
        (lambda p: write_kml(p, bad), "c.kml"),
        (lambda p: write_output_bag(p, path=bad, datum=datum), "c.mcap"),
    ):
        with pytest.raises(ValueError, match="1 of .* samples are not finite"):
            write(tmp_path / name)
        assert not (tmp_path / name).exists()


def test_the_sample_bends_are_those_of_its_pipe(smoothed: Path):
    """The bundled run's pipe (sim scenario demo): a 45 deg bend of 3 D at 60 m, a 0.5 m sag
    over 60 m from 140 m (three lobes: 0.65, 1.3, 0.65 of its peak angle) and a 1 deg crest of
    50 m radius at 255 m."""
    import csv

    with (smoothed / "sample_bends.csv").open() as f:
        rows = list(csv.DictReader(f))
    got = [(r["direction"], r["class"], float(r["angle_deg"]), float(r["radius_m"])) for r in rows]
    assert [g[:2] for g in got] == [("right", "induction"), ("over", "elastic"),
                                    ("sag", "elastic"), ("over", "elastic"),
                                    ("over", "elastic")]  # fmt: skip
    assert abs(got[0][2] - 45.0) < 0.1 and abs(got[0][3] - 0.6) < 0.03
    assert abs(float(rows[0]["apex_m"]) - (60.0 + 0.3 * 45 * math.pi / 180)) < 0.3
    assert abs(got[1][2] * 2 - got[2][2]) < 0.1 and abs(got[3][2] * 2 - got[2][2]) < 0.1
    assert abs(got[4][2] - 1.0) < 0.05 and abs(got[4][3] - 50.0) < 5.0
    for r in rows:
        assert 0 < float(r["sigma_angle_deg"]) < 0.1


def test_bends_recomputes_from_the_smoothed_bag_with_other_settings(smoothed: Path, capsys):
    run = smoothed / "again"
    args = ["bends", str(smoothed / "sample_smoothed.mcap"), "--out", str(run), "--window", "2",
            "--thresholds", "0.5", "--outer-diameter", "0.22"]  # fmt: skip
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "curvature window 2.00 m, outer diameter 0.220 m" in out
    text = (smoothed / "again_bends.csv").read_text().splitlines()
    assert len(text) == 1 + 5
    features = (smoothed / "again_strain_features.csv").read_text().splitlines()
    assert all(line.split(",")[1] == "0.500" for line in features[1:]) and len(features) >= 2


def test_bends_into_a_folder_names_the_products_like_the_input(smoothed: Path, capsys):
    """--out DIR/ as for smooth: the folder is made and the products are named like the input
    (they were hidden files DIR/.csv_bends.csv); the summary names the bend the largest strain
    is in and the largest strain outside bends."""
    folder = smoothed / "products"
    assert main(["bends", str(smoothed / "sample_smoothed.mcap"), "--out", f"{folder}/"]) == 0
    out = capsys.readouterr().out
    names = sorted(p.name for p in folder.iterdir())
    assert names == ["sample_bends.csv", "sample_strain.csv", "sample_strain_features.csv"]
    assert re.search(r"max strain [0-9.]+ % \(in bend 1\), [0-9.]+ % outside bends", out)


def test_bends_refuses_what_is_not_a_smoothed_run(tmp_path: Path, capsys):
    assert main(["bends", str(SAMPLE), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a smoothed bag" in err[0] and str(SAMPLE) in err[0]
    assert not list(tmp_path.iterdir())


def test_a_bug_is_an_internal_error_and_debug_shows_its_traceback(tmp_path, monkeypatch, capsys):
    from pipe_nav_core.app import pipeline

    from pipe_nav_core import errors

    def broken(*_a, **_k):
        raise TypeError("unsupported operand")

    monkeypatch.setattr(pipeline, "smooth_bag", broken)
    assert main(["smooth", str(SAMPLE), "--out", f"{tmp_path}/", "--quiet"]) == 70
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "internal error: TypeError: unsupported operand" in err[0], err
    with pytest.raises(TypeError):  # --debug: the exception itself, its traceback shown
        main(["--debug", "smooth", str(SAMPLE), "--out", f"{tmp_path}/", "--quiet"])
    # an input error stays one line, and every one of them is a PipeNavError
    r = _run_cli("smooth", str(tmp_path / "missing.mcap"), "--out", str(tmp_path / "o.mcap"))
    assert r.returncode == 2 and "Traceback" not in r.stderr and "missing.mcap" in r.stderr
    from pipe_nav_core.errors import MarkerCsvError
    from pipe_nav_core.io import BagError

    assert issubclass(BagError, errors.PipeNavError)
    assert issubclass(MarkerCsvError, errors.InputError) and issubclass(MarkerCsvError, ValueError)
    from pipe_nav_core.io import mcapread

    from pipe_nav_core import config

    assert config.ConfigError is errors.ConfigError and issubclass(errors.ConfigError, ValueError)
    assert issubclass(errors.ConfigError, errors.InputError)
    assert issubclass(errors.McapFormatError, errors.PipeNavError)
    assert mcapread.McapFormatError is errors.McapFormatError


def test_a_simulated_run_with_a_magnetometer_has_a_vendor_tally_to_locate(tmp_path: Path):
    """simulate writes RUN.tally.csv (the vendor's welds and features, scale error and missed
    welds included); locate puts every row of it on the smoothed run."""
    run = tmp_path / "run.mcap"
    assert main(["simulate", "--scenario", "demo", "--seed", "3", "--out", str(run),
                 "--quiet"]) == 0  # fmt: skip
    tally = tmp_path / "run.tally.csv"
    rows = list(csv.DictReader(tally.open()))
    assert sum(r["type"] == "girth weld" for r in rows) > 15 and len(rows) > 30
    assert main(["smooth", str(run), "--out", f"{tmp_path}/", "--quiet"]) == 0
    feats = tmp_path / "features.csv"
    assert main(["locate", str(tally), "--run", str(tmp_path / "run_smoothed.mcap"),
                 "--out", str(feats), "--quiet"]) == 0  # fmt: skip
    located = list(csv.DictReader(feats.open()))
    assert len(located) == len(rows)
    assert sum(bool(r["matched_weld"]) for r in located) >= 0.9 * len(rows)


def test_the_graph_smoother_says_its_iterations(tmp_path: Path, capsys):
    """--method graph: the summary and the smoothed bag's metadata say how the batch
    smoother went (Gauss-Newton iterations after the RTS passes, converged or not)."""
    from pipe_nav_core.io.smoothed_bag import read_smoothed_bag

    assert main(["smooth", str(SAMPLE), "--out", f"{tmp_path}/", "--method", "graph"]) == 0
    out = capsys.readouterr().out
    (line,) = [x for x in out.splitlines() if x.strip().startswith("graph ")]
    assert "Gauss-Newton iteration(s) after 2 RTS pass(es), converged" in line
    _, _, meta = read_smoothed_bag(tmp_path / "sample_smoothed.mcap")
    assert meta["method"] == "graph" and meta["graph_converged"] == "true"
    assert int(meta["graph_iterations"]) >= 1
