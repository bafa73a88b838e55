"""The speed benchmark measures what it says (its figures themselves are not asserted: they
depend on the machine)."""

import subprocess
import sys
from pathlib import Path

import numpy as np
from pipe_nav_core.bench import speed

SAMPLE = Path(__file__).resolve().parents[2] / "bags" / "sample.mcap"


def test_peak_memory_is_the_smooth_process_own():
    speed.peak_memory_mb(SAMPLE)  # a cold numba cache compiles (hundreds of MB) in this one
    # neither an earlier, larger child nor this (large) process may count: the rusage of
    # children reports the largest child, and a child starts from its parent's peak at fork
    code = "b = bytearray(1500 * 2**20); b[::4096] = b'x' * len(b[::4096])"
    subprocess.run([sys.executable, "-c", code], check=True)
    ballast = np.ones(1500 * 2**17)  # 1.5 GB resident in this process
    peak, wall = speed.peak_memory_mb(SAMPLE)
    assert ballast[-1] == 1.0
    assert 50.0 < peak < 1200.0
    assert wall > 0.0


def test_markdown_reports_ratios_to_real_time_and_to_rosbags():
    field = {
        "duration_s": 100.0,
        "imu_messages": 1000.0,
        "read_decode_s": 0.5,
        "forward_pass_s": 1.0,
        "smooth_total_s": 2.0,
        "passes": 2.0,
        "outputs_s": 0.25,
        "cli_wall_s": 4.0,
        "rosbags_read_s_extrapolated": 2.0,
        "peak_rss_mb": 512.0,
        "length_km": 1.0,
    }
    online = {"us_per_imu_sample": 7.0, "x_real_time": 140.0}
    md = speed.markdown({"field": field, "online": online}, "pipe-nav bench --speed-only")
    assert "| whole `pipe-nav smooth` process | 25 | 2.00 |" in md
    assert "| read + decode the bag | 200 | 0.25 |" in md
    assert "512 MB" in md and "140.0 x real time" in md


def test_field_bags_in_every_form_are_written_once(tmp_path):
    from pipe_nav_core.io import bag_info, read_bag
    from pipe_nav_core.io.mcapread import read_summary

    forms = (speed.FORMS[6], speed.FORMS[3], speed.FORMS[4])  # directory; lz4 no mag; none
    bags, duration = speed.field_bags(tmp_path, 0.3, 200.0, forms)
    assert 300.0 < duration < 600.0
    d = bags[forms[0]]
    assert d.is_dir() and (d / "metadata.yaml").is_file()
    comps = {}
    for f, p in bags.items():
        one = next(p.glob("*.mcap")) if p.is_dir() else p
        s = read_summary(one)
        comps[f.name] = {ci.compression for ci in s.chunk_indexes}
        assert len(s.chunk_indexes) > 3  # 1 MiB chunks, not one chunk
        assert ("/imu/mag" in bag_info(p).topics) == f.mag
    assert comps == {forms[0].name: {"zstd"}, forms[1].name: {"lz4"}, forms[2].name: {""}}
    a, _ = read_bag(bags[forms[0]])
    b, _ = read_bag(bags[forms[1]])
    assert np.array_equal(a.imu.gyro, b.imu.gyro) and len(a.mag) > 0 and len(b.mag) == 0
    stamp = {f: p.stat().st_mtime_ns for f, p in bags.items()}
    again, _ = speed.field_bags(tmp_path, 0.3, 200.0, forms)
    assert again == bags and {f: p.stat().st_mtime_ns for f, p in again.items()} == stamp


def test_the_rosbag2_forms_are_rewritten_from_the_zstd_bag(tmp_path):
    from pipe_nav_core.io import read_bag
    from pipe_nav_core.io.bagfiles import bag_layout

    forms = tuple(f for f in speed.FORMS if f.rosbag2 is not None)
    assert {f.rosbag2 for f in forms} == {("sqlite3", ""), ("mcap", "file"), ("mcap", "message")}
    bags, _ = speed.field_bags(tmp_path, 0.2, 200.0, forms)
    src, _ = read_bag(tmp_path / "field_0.2km_200hz_mag50hz_zstd_1024k.mcap")
    for f, p in bags.items():
        assert (p / "metadata.yaml").is_file()
        layout = bag_layout(p)
        assert (layout[0].storage, layout[0].compressed) == (f.rosbag2[0], f.rosbag2[1] == "file")
        log, _ = read_bag(p)
        assert np.array_equal(log.imu.gyro, src.imu.gyro) and log.markers == src.markers


def test_markdown_has_a_row_per_bag_form():
    row = {
        "name": "zstd",
        "chunk_size": float(1 << 20),
        "size_mb": 101.4,
        "messages": 1000.0,
        "duration_s": 100.0,
        "read_workers": 2.0,
        "smooth_read_workers": 1.0,
        "read_serial_s": 0.5,
        "read_pooled_s": 0.25,
        "read_pooled_thread_cpu_s": 0.2,
        "cli_wall_s": 1.0,
        "cli_wall_worst_s": 1.25,
        "cli_runs": 3.0,
        "peak_rss_mb": 700.0,
    }
    lz4 = {**row, "name": "lz4", "read_serial_s": 0.4, "cli_wall_s": 0.8, "cli_wall_worst_s": 0.8}
    lines = speed.forms_markdown([row, lz4])
    assert "| read + decode, 2 workers: x real time |" in lines[4]
    assert "| reading thread's CPU: x real time |" in lines[4]
    assert "| whole `pipe-nav smooth`: x real time, best (worst) |" in lines[4]
    assert "the best and the worst of 3 runs" in lines[2]
    assert "| zstd | 101 | 1000 | 200 | 400 | 500 | 100 (80) | 4.0 | 700 |" in lines
    assert "| lz4 | 101 | 1000 | 250 | 400 | 500 | 125 (125) | 3.2 | 700 |" in lines
    field = {
        "duration_s": 100.0,
        "imu_messages": 1000.0,
        "read_decode_s": 0.5,
        "forward_pass_s": 1.0,
        "smooth_total_s": 2.0,
        "passes": 2.0,
        "outputs_s": 0.25,
        "cli_wall_s": 4.0,
        "cli_wall_other_workers_s": 5.0,
        "other_workers": 1.0,
        "smooth_read_workers": 0.0,
        "rosbags_read_s_extrapolated": 2.0,
        "peak_rss_mb": 512.0,
        "length_km": 1.0,
    }
    online = {"us_per_imu_sample": 7.0, "x_real_time": 140.0}
    md = speed.markdown({"field": field, "online": online, "forms": [row]}, "pipe-nav bench")
    assert "### Bag forms" in md and "| zstd | 101 |" in md
    assert "unpacked by 1 worker thread (PIPE_NAV_READ_WORKERS=1; by default" in md
    assert "cores): 20 x real time" in md


def test_a_bag_form_is_smoothed_several_times_best_and_worst_kept(monkeypatch):
    monkeypatch.setattr(speed, "read_seconds", lambda bag, workers, repeat: (1.0, 0.5))
    runs = [(400.0, 5.0), (450.0, 4.0), (420.0, 6.0)]
    row = speed.form_figures(SAMPLE, speed.FORMS[0], 100.0, runs)
    assert (row["cli_wall_s"], row["cli_wall_worst_s"], row["cli_runs"]) == (4.0, 6.0, 3.0)
    assert row["peak_rss_mb"] == 450.0


def test_the_smooth_processes_go_round_the_forms(monkeypatch):
    """One process of every form per round, so that a slow spell of the machine does not
    fall on the runs of one form only."""
    order: list[str] = []

    def run(bag):
        order.append(bag.name)
        return 100.0, float(len(order))

    monkeypatch.setattr(speed, "peak_memory_mb", run)
    runs = speed.smooth_rounds([Path("a.mcap"), Path("b.mcap"), Path("c.mcap")], 2)
    assert order == ["a.mcap", "b.mcap", "c.mcap"] * 2
    assert [w for _, w in runs[1]] == [2.0, 5.0]
