"""Throughput of the bag reader and writer against rosbags (a script, not a test).

    python -m pipe_nav_core.io.bench [--seconds 7500] [--imu-hz 200] [--baseline 200000]

Builds a synthetic run (default: 7500 s at 200 Hz IMU = 1.5 million IMU messages, odometer at
50 Hz, magnetometer at 20 Hz, a marker every 100 s), writes it with :func:`write_sensor_bag`,
reads it back with :func:`read_bag` and :func:`iter_bag`, and times the same work done the
usual way on the first ``--baseline`` messages: rosbags' MCAP storage reader plus
``deserialize_cdr`` per message, the ``mcap`` library's reader (raw records only, no
deserialization) and rosbags' rosbag2 writer with ``serialize_cdr`` per message.
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from pipe_nav_core.io.bagread import concat_logs, iter_bag, read_bag
from pipe_nav_core.io.bagwrite import write_sensor_bag
from pipe_nav_core.io.rosmsg import jazzy_typestore
from pipe_nav_core.types import ImuSamples, MagSamples, Marker, OdometerSamples, SensorLog


def synthetic_log(seconds: float, imu_hz: int) -> SensorLog:
    rng = np.random.default_rng(0)
    n = int(seconds * imu_hz)
    t = np.arange(1, n + 1) / imu_hz
    no, nm = int(seconds * 50), int(seconds * 20)
    to = np.arange(1, no + 1) / 50.0
    tm = np.arange(1, nm + 1) / 20.0
    return SensorLog(
        imu=ImuSamples(t, rng.normal(size=(n, 3)) * 0.01, rng.normal(size=(n, 3)) + [0, 0, 9.8]),
        odometer=OdometerSamples(to, to * 1.33, np.full(no, 1.33)),
        mag=MagSamples(tm, rng.normal(size=(nm, 3)) * 1e-5),
        markers=[
            Marker(f"agm_{k:03d}", float(k * 100.0), math.radians(52.0), math.radians(5.0), 0.0)
            for k in range(int(seconds // 100) + 1)
        ],
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=7500.0)
    ap.add_argument("--imu-hz", type=int, default=200)
    ap.add_argument("--baseline", type=int, default=200_000, help="messages for rosbags/mcap")
    args = ap.parse_args(argv)

    log = synthetic_log(args.seconds, args.imu_hz)
    total = len(log.imu) + len(log.odometer) + len(log.mag) + len(log.markers)
    print(f"synthetic run: {total:,} messages ({len(log.imu):,} IMU)")
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "bench.mcap"
        t0 = time.perf_counter()
        write_sensor_bag(bag, log)
        dt_w = time.perf_counter() - t0
        size = os.path.getsize(bag)
        print(
            f"write_sensor_bag: {dt_w:6.2f} s  {total / dt_w / 1e6:5.2f} M msg/s  "
            f"({size / 1e6:.0f} MB)"
        )

        t0 = time.perf_counter()
        got, _ = read_bag(bag)
        dt_r = time.perf_counter() - t0
        print(f"read_bag:         {dt_r:6.2f} s  {total / dt_r / 1e6:5.2f} M msg/s")
        t0 = time.perf_counter()
        n_chunks = 0
        parts = []
        for c in iter_bag(bag, chunk_seconds=60.0):
            parts.append(c)
            n_chunks += 1
        dt_i = time.perf_counter() - t0
        print(
            f"iter_bag (60 s):  {dt_i:6.2f} s  {total / dt_i / 1e6:5.2f} M msg/s  "
            f"({n_chunks} chunks)"
        )
        assert np.array_equal(concat_logs(parts).imu.t, got.imu.t)

        # --- baselines on the first N messages
        nb = min(args.baseline, total)
        ts = jazzy_typestore()
        from rosbags.rosbag2.storage_mcap import McapReader

        rd = McapReader(bag)
        rd.open()
        t0 = time.perf_counter()
        k = 0
        for conn, _, raw in rd.messages(rd.connections):
            ts.deserialize_cdr(raw, conn.msgtype)
            k += 1
            if k >= nb:
                break
        dt_b = time.perf_counter() - t0
        rd.close()
        print(
            f"rosbags read+deserialize: {k / dt_b / 1e6:5.3f} M msg/s "
            f"(-> {total / (k / dt_b):6.1f} s for the whole run)"
        )

        from mcap.reader import make_reader

        with open(bag, "rb") as f:
            r = make_reader(f)
            t0 = time.perf_counter()
            k = 0
            for _ in r.iter_messages():
                k += 1
                if k >= nb:
                    break
            dt_m = time.perf_counter() - t0
        print(
            f"mcap iter_messages (raw, no decoding): {k / dt_m / 1e6:5.3f} M msg/s "
            f"(-> {total / (k / dt_m):6.1f} s)"
        )

        from rosbags.rosbag2 import StoragePlugin, Writer

        from pipe_nav_core.io import rosmsg

        types = rosmsg.rosbags_types()
        t0 = time.perf_counter()
        with Writer(Path(tmp) / "rb", version=9, storage_plugin=StoragePlugin.MCAP) as w:
            conn = w.add_connection("/imu/data", "sensor_msgs/msg/Imu", typestore=ts)
            for i in range(nb):
                m = rosmsg.imu_to_msg(types, log.imu.t[i], log.imu.gyro[i], log.imu.accel[i])
                w.write(conn, int(log.imu.t[i] * 1e9), ts.serialize_cdr(m, "sensor_msgs/msg/Imu"))
        dt_rw = time.perf_counter() - t0
        print(
            f"rosbags build+serialize+write: {nb / dt_rw / 1e6:5.3f} M msg/s "
            f"(-> {total / (nb / dt_rw):6.1f} s)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
