"""Speed and memory benchmark (``pipe-nav bench --speed``): the stages of ``pipe-nav smooth`` on
a simulated field run, as ratios to real time and to merely reading the bag with rosbags, the
peak resident memory of a whole ``pipe-nav smooth`` process, and the online engine's cost per
IMU sample with a 1 kHz IMU. The same run written in the bag forms others write (:data:`FORMS`:
zstd, lz4 and uncompressed 1 MiB chunks as rosbag2's MCAP storage writes them, with and
without a magnetometer, and the rosbag2 directory form) gives one row each: reading and
decoding it with our reader, serially and as by default (the chunks decompressed and
CRC-checked by a worker thread ahead of the decoding), and the whole ``pipe-nav smooth``
process on it. Absolute times are noisy on shared machines; the ratios are what to compare.
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from pipe_nav_core.app.commands import bag_bytes
from pipe_nav_core.app.outputs import Outputs, write_products
from pipe_nav_core.app.replay import replay_log
from pipe_nav_core.bench.rosbag2_forms import rewrite
from pipe_nav_core.config import NavConfig
from pipe_nav_core.io import bag_info, read_bag, write_rosbag2_metadata, write_sensor_bag
from pipe_nav_core.io.bagread import READ_WORKERS_ENV, read_workers
from pipe_nav_core.io.topics import DEFAULT_TOPICS
from pipe_nav_core.sim import get_scenario, simulate
from pipe_nav_core.smooth.forward import run_forward
from pipe_nav_core.smooth.passes import smooth_log
from pipe_nav_core.types import empty_mag


def _rosbags_read_seconds(bag: Path, limit: int = 200_000) -> tuple[float, int]:
    """Seconds rosbags needs to read and deserialize ``limit`` messages, and the total count."""
    from rosbags.highlevel import AnyReader

    from pipe_nav_core.io import write_rosbag2_metadata

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


ROSBAG2_CHUNK_SIZE = 1 << 20  # bytes of records per chunk (rosbag2's MCAP storage: zstd, 1 MiB)
SMOOTH_REPEAT = 3  # rounds of smooth processes of every bag form (best and worst reported)
FIELD_MAG_RATE_HZ = 50.0  # Hz: the magnetometer of the field bags (the others' bag of issue 21)


@dataclass(frozen=True)
class BagForm:
    """One way of writing the field run to a bag.

    compression: chunk compression, ``zstd``, ``lz4`` or ``""`` (none); chunk_size: bytes of
    uncompressed records per chunk; mag: with the magnetometer topic; directory: a rosbag2
    directory (``metadata.yaml`` beside the ``.mcap``) instead of a single ``.mcap``;
    rosbag2: (storage, compression mode) of a rosbag2 directory written again by rosbags
    from the form without it (:mod:`.rosbag2_forms`).
    """

    name: str
    compression: str
    chunk_size: int = ROSBAG2_CHUNK_SIZE
    mag: bool = True
    directory: bool = False
    rosbag2: tuple[str, str] | None = None

    def stem(self) -> str:
        """File name part that tells the form apart."""
        comp = self.compression or "none"
        kib = self.chunk_size // 1024
        tail = "_dir" if self.directory else ""
        if self.rosbag2 is not None:
            tail = f"_rosbag2_{self.rosbag2[0]}_{self.rosbag2[1] or 'plain'}"
        return f"{comp}_{kib}k" + ("" if self.mag else "_nomag") + tail


FORMS = (
    BagForm("zstd", "zstd"),
    BagForm("zstd, no magnetometer", "zstd", mag=False),
    BagForm("lz4", "lz4"),
    BagForm("lz4, no magnetometer", "lz4", mag=False),
    BagForm("uncompressed", ""),
    BagForm("uncompressed, no magnetometer", "", mag=False),
    BagForm("rosbag2 directory (metadata.yaml + zstd .mcap)", "zstd", directory=True),
    BagForm("rosbag2 sqlite3 (.db3, written by rosbags)", "zstd", rosbag2=("sqlite3", "")),
    BagForm("rosbag2, zstd-compressed files (rosbags)", "zstd", rosbag2=("mcap", "file")),
    BagForm("rosbag2, zstd-compressed messages (rosbags)", "zstd", rosbag2=("mcap", "message")),
)
QUICK_FORMS = (FORMS[0], FORMS[2], FORMS[4], FORMS[6])


def _form_path(out_dir: Path, base: str, form: BagForm) -> tuple[Path, Path]:
    """(the bag to read, the file whose existence says it was written completely)."""
    name = f"{base}_{form.stem()}"
    if form.directory or form.rosbag2 is not None:
        d = out_dir / name
        return d, d / "metadata.yaml"
    bag = out_dir / f"{name}.mcap"
    return bag, bag


def field_bags(
    out_dir: Path, length_km: float, imu_rate_hz: float, forms: Sequence[BagForm] = FORMS
) -> tuple[dict[BagForm, Path], float]:
    """The simulated field run (IMU at ``imu_rate_hz``, odometer 50 Hz, magnetometer
    :data:`FIELD_MAG_RATE_HZ`, markers) written in each of ``forms`` under ``out_dir`` (made
    once and cached), and its duration in s (first to last IMU stamp)."""
    base = f"field_{length_km:g}km_{imu_rate_hz:g}hz_mag{FIELD_MAG_RATE_HZ:g}hz"
    paths = {f: _form_path(out_dir, base, f) for f in forms}
    missing = [f for f, (_, done) in paths.items() if not done.exists()]
    if missing:
        sc = dataclasses.replace(
            get_scenario("field10k").with_length(length_km * 1000.0),
            mag_enabled=True,
            mag_rate_hz=FIELD_MAG_RATE_HZ,
        )
        log = simulate(sc, seed=1, imu_rate_hz=imu_rate_hz, truth_every=100).log
        for f in sorted(missing, key=lambda f: f.rosbag2 is not None):  # their sources first
            bag, _ = paths[f]
            lg = log if f.mag else dataclasses.replace(log, mag=empty_mag())
            if f.rosbag2 is not None:
                src = dataclasses.replace(f, name="", rosbag2=None)
                src_bag, done = _form_path(out_dir, base, src)
                if not done.exists():
                    write_sensor_bag(src_bag, lg, compression=src.compression,
                                     chunk_size=src.chunk_size)  # fmt: skip
                shutil.rmtree(bag, ignore_errors=True)  # a rewrite cut short before
                rewrite(src_bag, bag, *f.rosbag2)
            elif f.directory:
                bag.mkdir(parents=True, exist_ok=True)
                one = bag / f"{bag.name}_0.mcap"
                write_sensor_bag(one, lg, compression=f.compression, chunk_size=f.chunk_size)
                write_rosbag2_metadata(one)
            else:
                write_sensor_bag(bag, lg, compression=f.compression, chunk_size=f.chunk_size)
    info = bag_info(paths[forms[0]][0])
    imu = info.topics[DEFAULT_TOPICS.imu]
    if imu.start is None or imu.end is None:
        raise ValueError(f"{paths[forms[0]][0]}: no IMU messages in the field bag")
    return {f: p for f, (p, _) in paths.items()}, float(imu.end - imu.start)


def read_seconds(bag: Path, workers: int, repeat: int = 2) -> tuple[float, float]:
    """Best wall time (s) of ``repeat`` reads (read + decode + checks) of a bag with
    ``read_bag(workers=workers)``, and the calling thread's CPU time (s) in that read: what
    the read takes when the worker threads have cores of their own, which on a busy machine
    its wall time does not tell."""
    best, cpu = math.inf, math.inf
    for _ in range(max(1, repeat)):
        t0, c0 = time.perf_counter(), time.thread_time()
        read_bag(bag, workers=workers)
        wall = time.perf_counter() - t0
        if wall < best:
            best, cpu = wall, time.thread_time() - c0
    return best, cpu


def form_figures(
    bag: Path,
    form: BagForm,
    duration: float,
    runs: Sequence[tuple[float, float]],
    repeat: int = 2,
) -> dict:
    """One row of the bag-form table: size, messages, read + decode time serially and with
    the pool (s, the best of ``repeat``; with the pool also the reading thread's CPU time),
    and of the whole ``pipe-nav smooth`` processes ``runs`` ((peak MB, wall s) each, from
    :func:`smooth_rounds`) the best and worst wall time (s; the best, like the read's, is
    what the machine's other load did not slow) and the largest peak memory (MB)."""
    workers = read_workers()
    info = bag_info(bag)
    serial, _ = read_seconds(bag, 0, repeat)
    pooled, pooled_cpu = read_seconds(bag, workers, repeat) if workers else (serial, serial)
    peak = max(p for p, _ in runs)
    walls = [w for _, w in runs]
    return {
        "name": form.name,
        "compression": form.compression,
        "chunk_size": float(form.chunk_size),
        "mag": form.mag,
        "directory": form.directory,
        "size_mb": bag_bytes(bag) / 2**20,
        "messages": float(info.message_count),
        "duration_s": duration,
        "read_workers": float(workers),
        "smooth_read_workers": float(read_workers(beside=1)),  # what pipe-nav smooth reads with
        "read_serial_s": serial,
        "read_pooled_s": pooled,
        "read_pooled_thread_cpu_s": pooled_cpu,
        "cli_wall_s": min(walls),
        "cli_wall_worst_s": max(walls),
        "cli_runs": float(len(walls)),
        "peak_rss_mb": peak,
    }


def smooth_rounds(bags: Sequence[Path], rounds: int) -> list[list[tuple[float, float]]]:
    """(peak MB, wall s) of ``rounds`` whole ``pipe-nav smooth`` processes of each bag, a
    round being one process of every bag in turn: a slow spell of the machine (whose speed
    drifts by a third within minutes) falls on all of the forms, not on the one measured
    then."""
    runs: list[list[tuple[float, float]]] = [[] for _ in bags]
    for _ in range(max(1, rounds)):
        for got, bag in zip(runs, bags, strict=True):
            got.append(peak_memory_mb(bag))
    return runs


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


# run in the measured child: pipe-nav smooth as the command runs it (cli.run: BLAS on one
# thread, out of the process at once, without the interpreter's teardown), then its own
# high-water mark (VmHWM, kB) into the file argv[1]. The rusage of a child is no measure:
# Linux starts it from the parent's peak at fork, so a large benchmark process would report
# its own size.
_CHILD = """
import os, sys
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
from pipe_nav_core.app.cli import main
rc = main(sys.argv[2:])
try:
    with open("/proc/self/status") as f:
        hwm = next(line.split()[1] for line in f if line.startswith("VmHWM:"))
    with open(sys.argv[1], "w") as f:
        f.write(hwm)
except (OSError, StopIteration):
    pass
sys.stdout.flush()
sys.stderr.flush()
os._exit(rc)
"""


def peak_memory_mb(bag: Path, env: Mapping[str, str] | None = None) -> tuple[float, float]:
    """Peak resident memory (MB) and wall time (s) of a whole ``pipe-nav smooth`` process
    (its own high-water mark on Linux; elsewhere the child's rusage, which can include the
    parent's size at fork). ``env``: variables set for the child on top of ours."""
    with tempfile.TemporaryDirectory() as tmp:
        hwm = Path(tmp) / "hwm"
        cmd = [sys.executable, "-c", _CHILD, str(hwm), "smooth", str(bag)]
        cmd += ["--out", f"{tmp}/", "--quiet", "--imu-grade", "tactical"]
        t0 = time.perf_counter()
        child = subprocess.Popen(cmd, env={**os.environ, **env} if env else None)
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
    out_dir: str | Path = "bench_out",
    length_km: float = 10.0,
    imu_rate_hz: float = 200.0,
    quick: bool = False,
) -> dict:
    """All speed figures for one field run length: the stages and the online engine
    (``field``, ``online``) and one row per bag form (``forms``; ``quick``: four forms, one
    read each instead of the best of two, one smooth process per form instead of
    SMOOTH_REPEAT, no serial-read smooth process)."""
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    forms = QUICK_FORMS if quick else FORMS
    bags, duration = field_bags(d, length_km, imu_rate_hz, forms)
    bag = bags[forms[0]]
    stages = smooth_stages(bag, duration)
    rb_s, rb_n = _rosbags_read_seconds(bag)
    total_msgs = rb_n
    stages["rosbags_read_s_extrapolated"] = rb_s * (total_msgs / min(total_msgs, 200_000))
    stages["length_km"] = length_km
    print("pipe-nav bench: speed, the smooth processes of every form", file=sys.stderr)
    runs = smooth_rounds([bags[f] for f in forms], 1 if quick else SMOOTH_REPEAT)
    rows = []
    for f, form_runs in zip(forms, runs, strict=True):
        print(f"pipe-nav bench: speed, {f.name}", file=sys.stderr, flush=True)
        rows.append(form_figures(bags[f], f, duration, form_runs, repeat=1 if quick else 2))
    stages["peak_rss_mb"] = rows[0]["peak_rss_mb"]
    stages["cli_wall_s"] = rows[0]["cli_wall_s"]
    if not quick:  # the process with the chunk workers it does not have by default, or none
        stages["smooth_read_workers"] = rows[0]["smooth_read_workers"]
        other = 1 if stages["smooth_read_workers"] == 0 else 0
        _, wall = peak_memory_mb(bag, {READ_WORKERS_ENV: str(other)})
        stages["cli_wall_other_workers_s"], stages["other_workers"] = wall, float(other)
    online = online_cost()
    return {"field": stages, "online": online, "forms": rows}


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
    ]
    if "cli_wall_other_workers_s" in f:
        k = int(f["other_workers"])
        how = "in its reading thread" if k == 0 else f"by {k} worker thread{'s' * (k > 1)}"
        lines += [
            "",
            f"Whole `pipe-nav smooth` process with the chunks unpacked {how} "
            f"({READ_WORKERS_ENV}={k}; by default {int(f['smooth_read_workers'])} beside the first "
            f"pass on {os.cpu_count()} cores): "
            f"{dur / f['cli_wall_other_workers_s']:.0f} x real time.",
        ]
    lines += [
        "",
        f"Online engine (ekf_node's code path), 1 kHz IMU with odometer and magnetometer: "
        f"{o['us_per_imu_sample']:.0f} us of CPU per IMU sample, "
        f"{o['x_real_time']:.1f} x real time.",
        "",
    ]
    if res.get("forms"):
        lines += forms_markdown(res["forms"])
    return "\n".join(lines)


def forms_markdown(rows: Sequence[Mapping]) -> list[str]:
    """The bag-form table (lines): per form the read + decode time serially and with the
    worker threads, the reading thread's CPU time in the latter and the whole
    ``pipe-nav smooth`` process, as x real time, the process's time over the pooled read's,
    and its peak memory."""
    r0 = rows[0]
    workers = int(r0["read_workers"])
    smooth = int(r0["smooth_read_workers"])
    plural = "" if workers == 1 else "s"
    chunk = f"{r0['chunk_size'] / 2**20:g} MiB"
    runs = int(r0["cli_runs"])
    lines = [
        "### Bag forms",
        "",
        f"The same run ({r0['duration_s'] / 3600:.2f} h; IMU 200 Hz, odometer 50 Hz, "
        f"magnetometer {FIELD_MAG_RATE_HZ:g} Hz unless without) written as others write it: "
        f"chunks of {chunk} of records, as rosbag2's MCAP storage writes them (zstd by "
        "default). Read + decode: `read_bag` (every check included), in one thread "
        f"(`workers=0`) and as by default, with {workers} worker thread{plural} decompressing "
        f"and CRC-checking the chunks ahead ({os.cpu_count()} cores); smooth: the whole "
        "`pipe-nav smooth` process (imports and outputs included), the best and the worst "
        f"of {runs} run{'' if runs == 1 else 's'} (one of every form in turn); smooth / "
        "read: the process's best time over the default read's; reading thread: its CPU time "
        "in the default read, the read's time when the workers have cores of their own; reads: "
        f"the best of two. `pipe-nav smooth` unpacks the chunks with {smooth} worker "
        f"thread{'' if smooth == 1 else 's'}: the first filter pass runs beside its reading.",
        "",
        "| bag form | MB | messages | read + decode, 1 thread: x real time "
        f"| read + decode, {workers} worker{plural}: x real time "
        "| reading thread's CPU: x real time "
        "| whole `pipe-nav smooth`: x real time, best (worst) | smooth / read | peak MB |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        dur = r["duration_s"]
        worst = r["cli_wall_worst_s"]
        lines.append(
            f"| {r['name']} | {r['size_mb']:.0f} | {r['messages']:.0f} "
            f"| {dur / r['read_serial_s']:.0f} | {dur / r['read_pooled_s']:.0f} "
            f"| {dur / r['read_pooled_thread_cpu_s']:.0f} "
            f"| {dur / r['cli_wall_s']:.0f} ({dur / worst:.0f}) "
            f"| {r['cli_wall_s'] / r['read_pooled_s']:.1f} "
            f"| {r['peak_rss_mb']:.0f} |"
        )
    lines.append("")
    return lines
