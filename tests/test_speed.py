"""The speed benchmark measures what it says (its figures themselves are not asserted: they
depend on the machine)."""

import subprocess
import sys
from pathlib import Path

import numpy as np

from pipe_nav_core import speed

SAMPLE = Path(__file__).resolve().parents[1] / "bags" / "sample.mcap"


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
