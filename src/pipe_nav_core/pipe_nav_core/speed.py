"""Speed and memory benchmark (``pipe-nav bench --speed``): the stages of ``pipe-nav smooth`` on
a simulated field run, as ratios to real time and to merely reading the bag with rosbags, the
peak resident memory of a whole ``pipe-nav smooth`` process, and the online engine's cost per
IMU sample with a 1 kHz IMU. Absolute times are noisy on shared machines; the ratios are what
to compare.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .config import NavConfig
from .io import read_bag, write_sensor_bag
from .pipeline import Outputs, replay_log, write_products
from .sim import get_scenario, simulate
from .smoother import run_forward, smooth_log


def _rosbags_read_seconds(bag: Path, limit: int = 200_000) -> tuple[float, int]:
    """Seconds rosbags needs to read and deserialize ``limit`` messages, and the total count."""
    from rosbags.highlevel import AnyReader

    from .io import write_rosbag2_metadata

    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp) / "bag"
        d.mkdir()
        (d / bag.name).symlink_to(bag.resolve())
        write_rosbag2_metadata(d / bag.name)
        with AnyReader([d]) as reader:
            total = sum(c.msgcount for c in reader.connections)
            n = 0
            t0 = time.perf_counter()
            for conn, _, raw in reader.messages():
                reader.deserialize(raw, conn.msgtype)
                n += 1
                if n >= limit:
                    break
            return time.perf_counter() - t0, total if n >= limit else n


def field_run(out_dir: Path, length_km: float, imu_rate_hz: float) -> tuple[Path, float]:
    """The simulated field bag (made once and cached) and its duration in s."""
    name = f"field_{length_km:g}km_{imu_rate_hz:g}hz.mcap"
    bag = out_dir / name
    sc = get_scenario("field10k").with_length(length_km * 1000.0)
    if not bag.exists():
        run = simulate(sc, seed=1, imu_rate_hz=imu_rate_hz, truth_every=100)
        write_sensor_bag(bag, run.log)
    log, _ = read_bag(bag)
    return bag, float(log.imu.t[-1] - log.imu.t[0])


def smooth_stages(bag: Path, duration: float) -> dict[str, float]:
    """Seconds per stage of pipe-nav smooth, in-process."""
    sc = get_scenario("field10k")
    cfg = NavConfig.from_dict(sc.estimator_settings())
    out: dict[str, float] = {"duration_s": duration}
    t0 = time.perf_counter()
    log, _ = read_bag(bag)
    out["read_decode_s"] = time.perf_counter() - t0
    out["imu_messages"] = float(len(log.imu))
    t0 = time.perf_counter()
    run_forward(log, cfg)
    out["forward_pass_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = smooth_log(log, cfg, method="rts")
    out["smooth_total_s"] = time.perf_counter() - t0
    out["passes"] = float(res.summary.get("passes_run", res.summary.get("passes", 1)))
    with tempfile.TemporaryDirectory() as tmp:
        o = Outputs(
            bag=f"{tmp}/o.mcap",
            csv=f"{tmp}/o.csv",
            geojson=f"{tmp}/o.geojson",
            kml=f"{tmp}/o.kml",
            plot=f"{tmp}/o.png",
        )
        t0 = time.perf_counter()
        write_products(res, o)
        out["outputs_s"] = time.perf_counter() - t0
    return out


# run in the measured child: pipe-nav smooth, then its own high-water mark (VmHWM, kB) into
# the file argv[1]. The rusage of a child is no measure: Linux starts it from the parent's
# peak at fork, so a large benchmark process would report its own size.
_CHILD = """
import sys
from pipe_nav_core.cli import main
rc = main(sys.argv[2:])
try:
    with open("/proc/self/status") as f:
        hwm = next(line.split()[1] for line in f if line.startswith("VmHWM:"))
    with open(sys.argv[1], "w") as f:
        f.write(hwm)
except (OSError, StopIteration):
    pass
sys.exit(rc)
"""


def peak_memory_mb(bag: Path) -> tuple[float, float]:
    """Peak resident memory (MB) and wall time (s) of a whole ``pipe-nav smooth`` process
    (its own high-water mark on Linux; elsewhere the child's rusage, which can include the
    parent's size at fork)."""
    with tempfile.TemporaryDirectory() as tmp:
        hwm = Path(tmp) / "hwm"
        cmd = [sys.executable, "-c", _CHILD, str(hwm), "smooth", str(bag)]
        cmd += ["--out", f"{tmp}/", "--quiet", "--imu-grade", "tactical"]
        t0 = time.perf_counter()
        child = subprocess.Popen(cmd)
        _, status, usage = os.wait4(child.pid, 0)
        wall = time.perf_counter() - t0
        child.returncode = os.waitstatus_to_exitcode(status)
        if child.returncode:
            raise subprocess.CalledProcessError(child.returncode, cmd)
        kb = float(hwm.read_text()) if hwm.exists() else float(usage.ru_maxrss)
    return kb / 1024.0, wall


def online_cost(seconds: float = 60.0) -> dict[str, float]:
    """The online engine (ekf_node's code path) on a 1 kHz IMU with odometer and magnetometer:
    microseconds of CPU per IMU sample and the ratio to real time."""
    sc = dataclasses.replace(get_scenario("demo"), imu_rate_hz=1000.0, mag_enabled=True)
    run = simulate(sc, seed=3)
    log = run.log
    t_end = log.imu.t[0] + seconds
    cut = dataclasses.replace(
        log,
        imu=log.imu.slice(log.imu.t <= t_end),
        odometer=log.odometer.slice(log.odometer.t <= t_end),
        mag=log.mag.slice(log.mag.t <= t_end),
        markers=[m for m in log.markers if m.t <= t_end],
    )
    cfg = NavConfig.from_dict({**sc.estimator_settings(), "mag_update": True})
    t0 = time.process_time()
    replay_log(cut, cfg)
    cpu = time.process_time() - t0
    n = len(cut.imu)
    return {
        "imu_samples": float(n),
        "us_per_imu_sample": 1e6 * cpu / n,
        "x_real_time": seconds / cpu,
    }


def run(
    out_dir: str | Path = "bench_out", length_km: float = 10.0, imu_rate_hz: float = 200.0
) -> dict:
    """All speed figures for one field run length."""
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    bag, duration = field_run(d, length_km, imu_rate_hz)
    stages = smooth_stages(bag, duration)
    rb_s, rb_n = _rosbags_read_seconds(bag)
    total_msgs = rb_n
    stages["rosbags_read_s_extrapolated"] = rb_s * (total_msgs / min(total_msgs, 200_000))
    peak, wall = peak_memory_mb(bag)
    stages["peak_rss_mb"] = peak
    stages["cli_wall_s"] = wall
    stages["length_km"] = length_km
    online = online_cost()
    return {"field": stages, "online": online}


def markdown(res: dict, command: str) -> str:
    """The speed section of BENCHMARKS.md."""
    f, o = res["field"], res["online"]
    dur = f["duration_s"]
    rows = [
        ("read + decode the bag", f["read_decode_s"]),
        ("one forward filter pass", f["forward_pass_s"]),
        (f"smoother, all passes ({f['passes']:.0f})", f["smooth_total_s"]),
        ("outputs (bag, CSV, GeoJSON, KML, PNG)", f["outputs_s"]),
        ("whole `pipe-nav smooth` process", f["cli_wall_s"]),
        ("rosbags: read + deserialize (reference floor)", f["rosbags_read_s_extrapolated"]),
    ]
    floor = f["rosbags_read_s_extrapolated"]
    lines = [
        "## Speed and memory",
        "",
        f"Simulated field run of {f['length_km']:g} km, {f['imu_messages']:.0f} IMU messages, "
        f"{dur / 3600:.2f} h of pig time. Produced by:",
        "",
        "```",
        command,
        "```",
        "",
        "| stage | x real time | x rosbags read |",
        "|---|---|---|",
    ]
    lines += [f"| {name} | {dur / s:.0f} | {s / floor:.2f} |" for name, s in rows]
    lines += [
        "",
        f"Peak resident memory of `pipe-nav smooth`: {f['peak_rss_mb']:.0f} MB.",
        "",
        f"Online engine (ekf_node's code path), 1 kHz IMU with odometer and magnetometer: "
        f"{o['us_per_imu_sample']:.0f} us of CPU per IMU sample, "
        f"{o['x_real_time']:.1f} x real time.",
        "",
    ]
    return "\n".join(lines)
