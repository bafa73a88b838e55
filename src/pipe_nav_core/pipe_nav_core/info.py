"""What a user checks in a bag before smoothing it (``pipe-nav info BAG``).

Per input topic: message type, count, rate and stamp gaps; the run's duration and odometer
distance; the markers (surveyed or not); the static spans (odometer still for at least
``MIN_STATIC_S``); the IMU noise measured in them (white-noise density from the sample scatter,
and the Allan deviation of the longest span where it is long enough for a bias-instability
figure); the per-sample noise the Imu messages declare; and the IMU grade the settings use
against the one whose noise figures are nearest the measured ones. Times are s from the bag's
first stamp, angles in the text in degrees (radians in the JSON's ``*_rad`` fields), SI
otherwise.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .config import NavConfig
from .io import TopicNames, merge_markers, read_bag, read_markers_csv
from .io.topics import DEFAULT_TOPICS
from .sensors import GRADES, ImuSpec
from .types import SensorLog

MIN_STATIC_S = 2.0  # s: shortest span of a still odometer counted as static
STILL_M = 0.002  # m: odometer change within a static span
GAP_FACTOR = 5.0  # a stamp step over this many median periods is a gap
MIN_ALLAN_S = 60.0  # s: shortest static span whose Allan deviation is reported
EDGE_S = 1.0  # s left out at each end of a static span (the pig settles, or starts to move)

FloatArray = NDArray[np.float64]


def static_spans(log: SensorLog, min_s: float = MIN_STATIC_S) -> list[tuple[float, float]]:
    """(start, end) times, s (bag stamps), where the odometer moved less than STILL_M for at
    least ``min_s`` and IMU samples exist; the whole IMU span when there is no odometer."""
    imu_t = log.imu.t
    if len(imu_t) < 2:
        return []
    odo = log.odometer
    if len(odo.t) < 2:
        return [(float(imu_t[0]), float(imu_t[-1]))]
    spans: list[tuple[float, float]] = []
    start = 0
    d = odo.distance
    for i in range(1, len(odo.t) + 1):
        if i == len(odo.t) or abs(d[i] - d[start]) > STILL_M:
            t0, t1 = float(odo.t[start]), float(odo.t[i - 1])
            if start == 0:
                t0 = min(t0, float(imu_t[0]))  # rest before the first odometer message
            if t1 - t0 >= min_s:
                spans.append((max(t0, float(imu_t[0])), min(t1, float(imu_t[-1]))))
            start = i
    return [(a, b) for a, b in spans if b - a >= min_s]


def allan_deviation(x: FloatArray, dt: float) -> tuple[FloatArray, FloatArray]:
    """Non-overlapping Allan deviation of a rate signal ``x`` (N, k) sampled every ``dt`` s:
    (tau (M,) s, adev (M, k) in x's unit), for cluster sizes 1, 2, 4, ... up to N / 9."""
    taus, devs = [], []
    m = 1
    while len(x) // m >= 9:
        n = len(x) // m
        means = x[: n * m].reshape(n, m, -1).mean(axis=1)
        devs.append(np.sqrt(0.5 * np.mean(np.diff(means, axis=0) ** 2, axis=0)))
        taus.append(m * dt)
        m *= 2
    return np.array(taus), np.array(devs).reshape(len(taus), -1)


def measured_noise(log: SensorLog, spans: Sequence[tuple[float, float]]) -> dict[str, Any]:
    """IMU noise in the static spans: per-axis white-noise densities (gyro rad/sqrt(s), accel
    m/s/sqrt(s)) from the scatter of the samples about each span's mean (a sample is the mean
    rate over its interval, so its scatter is density / sqrt(dt)) and, for the longest span of
    MIN_ALLAN_S or more, the Allan-deviation floor (bias instability, rad/s and m/s^2)."""
    imu = log.imu
    if len(imu.t) < 3 or not spans:
        return {}
    dt = float(np.median(np.diff(imu.t)))
    resid_g, resid_a, n_total = [], [], 0
    longest: tuple[float, float] | None = None
    for a, b in spans:
        a, b = a + EDGE_S, b - EDGE_S
        sel = (imu.t >= a) & (imu.t <= b)
        if sel.sum() < 3:
            continue
        resid_g.append(imu.gyro[sel] - imu.gyro[sel].mean(axis=0))
        resid_a.append(imu.accel[sel] - imu.accel[sel].mean(axis=0))
        n_total += int(sel.sum())
        if longest is None or b - a > longest[1] - longest[0]:
            longest = (a, b)
    if not resid_g:
        return {}
    g = np.concatenate(resid_g)
    f = np.concatenate(resid_a)
    out: dict[str, Any] = {
        "samples": n_total,
        "sample_period_s": dt,
        "gyro_arw": (g.std(axis=0) * math.sqrt(dt)).tolist(),
        "accel_vrw": (f.std(axis=0) * math.sqrt(dt)).tolist(),
    }
    if longest is not None and longest[1] - longest[0] >= MIN_ALLAN_S:
        sel = (imu.t >= longest[0]) & (imu.t <= longest[1])
        _, dev_g = allan_deviation(imu.gyro[sel], dt)
        _, dev_a = allan_deviation(imu.accel[sel], dt)
        # the floor of the Allan deviation is 0.664 times the bias instability (flicker)
        out["gyro_bias_instability"] = (dev_g.min(axis=0) / 0.664).tolist()
        out["accel_bias_instability"] = (dev_a.min(axis=0) / 0.664).tolist()
    return out


def nearest_grade(noise: dict[str, Any]) -> str | None:
    """The named grade whose white-noise figures (gyro ARW, accel VRW) are nearest the
    measured ones in log ratio; None without a measurement."""
    if not noise:
        return None
    arw = float(np.mean(noise["gyro_arw"]))
    vrw = float(np.mean(noise["accel_vrw"]))

    def distance(spec: ImuSpec) -> float:
        return abs(math.log(arw / spec.gyro_arw)) + abs(math.log(vrw / spec.accel_vrw))

    if not (arw > 0.0 and vrw > 0.0):
        return None
    return min(GRADES.values(), key=distance).name


def _declared_noise(path: str | os.PathLike[str], topic: str) -> dict[str, Any]:
    """The per-sample variances (diagonals) the first Imu message declares, or {}."""
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_typestore

    from .io.bagread import bag_files

    store = get_typestore(Stores.ROS2_JAZZY)
    for f in bag_files(path):
        try:
            with open(f, "rb") as fh:
                for _s, _c, message in make_reader(fh).iter_messages(topics=[topic]):
                    msg = store.deserialize_cdr(message.data, "sensor_msgs/msg/Imu")
                    gv = np.asarray(msg.angular_velocity_covariance, dtype=float)[[0, 4, 8]]
                    av = np.asarray(msg.linear_acceleration_covariance, dtype=float)[[0, 4, 8]]
                    return {"gyro_variance": gv.tolist(), "accel_variance": av.tolist()}
        except Exception:  # an unreadable first message says nothing about the noise
            return {}
    return {}


def _gaps(t: FloatArray, t0: float) -> dict[str, Any]:
    if len(t) < 2:
        return {"median_period_s": None, "largest_gap_s": None, "gaps": 0}
    dt = np.diff(t)
    med = float(np.median(dt))
    k = int(np.argmax(dt))
    return {
        "median_period_s": med,
        "largest_gap_s": float(dt[k]),
        "largest_gap_at_s": float(t[k] - t0),
        "gaps": int(np.sum(dt > GAP_FACTOR * med)) if med > 0 else 0,
    }


def describe_bag(
    path: str | os.PathLike[str],
    config: NavConfig | None = None,
    topics: TopicNames = DEFAULT_TOPICS,
    markers_csv: str | os.PathLike[str] | None = None,
) -> dict[str, Any]:
    """Everything ``pipe-nav info`` reports, as a JSON-ready mapping (see the module
    docstring); ``markers_csv`` adds to or replaces the bag's markers as in smoothing. Raises
    BagError for a bag that cannot be read at all."""
    cfg = config or NavConfig()
    log, report = read_bag(path, topics)
    if markers_csv is not None:
        log.markers = merge_markers(log.markers, read_markers_csv(markers_csv))
    stamps = [x.t for x in (log.imu, log.odometer, log.mag) if len(x.t)]
    stamps += [np.array([m.t for m in log.markers if math.isfinite(m.t)])]
    stamps = [s for s in stamps if len(s)]
    t0 = min(float(s[0]) for s in stamps) if stamps else 0.0
    t1 = max(float(s[-1]) for s in stamps) if stamps else 0.0
    series = {topics.imu: log.imu.t, topics.odometer: log.odometer.t, topics.mag: log.mag.t}
    topic_rows = []
    for name, typename in sorted(report.types.items()):
        t = series.get(name)
        count = report.counts.get(name, 0)
        row: dict[str, Any] = {"topic": name, "type": typename, "count": count}
        if t is not None and len(t) > 1:
            row["rate_hz"] = (len(t) - 1) / float(t[-1] - t[0]) if t[-1] > t[0] else None
            row.update(_gaps(t, t0))
        if report.skipped_by_topic.get(name):
            row["skipped"] = dict(report.skipped_by_topic[name])
        topic_rows.append(row)
    spans = static_spans(log)
    noise = measured_noise(log, spans)
    spec = cfg.imu_spec()
    odo = log.odometer
    return {
        "bag": str(path),
        "files": list(report.files),
        "duration_s": t1 - t0,
        "start_stamp_s": t0,
        "distance_m": float(odo.distance[-1] - odo.distance[0]) if len(odo.t) else 0.0,
        "max_speed_mps": float(np.max(np.abs(odo.speed))) if len(odo.t) else 0.0,
        "topics": topic_rows,
        "markers": [
            {
                "name": m.name,
                "time_s": m.t - t0,
                "surveyed": all(math.isfinite(v) for v in (m.lat, m.lon, m.alt)),
                "sigma_enu_m": list(m.sigma_enu),
            }
            for m in log.markers
        ],
        "static_spans_s": [[a - t0, b - t0] for a, b in spans],
        "imu_noise_measured": noise,
        "imu_noise_declared": _declared_noise(path, topics.imu),
        "imu_grade": {
            "configured": cfg.imu_grade,
            "gyro_arw": spec.gyro_arw,
            "accel_vrw": spec.accel_vrw,
            "nearest_to_measured": nearest_grade(noise),
        },
        "warnings": list(report.warnings),
        "truncated": report.truncated,
    }


def _deg_per_sqrt_h(x: float) -> float:
    return math.degrees(x) * 60.0


def _mps_per_sqrt_h(x: float) -> float:
    return x * 60.0


def format_info(info: dict[str, Any]) -> str:
    """The text of ``pipe-nav info`` (in the style of ``ros2 bag info``)."""
    lines = [
        f"Bag:             {info['bag']}",
        f"Files:           {', '.join(info['files'])}",
        f"Duration:        {info['duration_s']:.3f} s",
        f"Distance:        {info['distance_m']:.2f} m (odometer), max speed "
        f"{info['max_speed_mps']:.2f} m/s",
        "Topics:",
    ]
    for row in info["topics"]:
        text = f"  {row['topic']:<14} {row['type']:<28} {row['count']:>9} msgs"
        if row.get("rate_hz"):
            text += f"  {row['rate_hz']:8.2f} Hz"
        if row.get("gaps"):
            text += (
                f"  {row['gaps']} gap(s) over {GAP_FACTOR:g} periods, largest "
                f"{row['largest_gap_s']:.3f} s at {row['largest_gap_at_s']:.1f} s"
            )
        if row.get("skipped"):
            text += "  skipped " + ", ".join(f"{k} {v}" for k, v in row["skipped"].items())
        lines.append(text)
    lines.append(f"Markers:         {len(info['markers'])}")
    for m in info["markers"]:
        state = "surveyed" if m["surveyed"] else "not surveyed"
        lines.append(f"  {m['name']:<14} at {m['time_s']:9.3f} s  {state}")
    spans = info["static_spans_s"]
    lines.append(
        "Static spans:    "
        + (", ".join(f"{a:.1f}-{b:.1f} s" for a, b in spans) if spans else "none")
    )
    noise = info["imu_noise_measured"]
    if noise:
        arw = ", ".join(f"{_deg_per_sqrt_h(x):.3f}" for x in noise["gyro_arw"])
        vrw = ", ".join(f"{_mps_per_sqrt_h(x):.4f}" for x in noise["accel_vrw"])
        lines.append(f"IMU noise (static, {noise['samples']} samples):")
        lines.append(f"  gyro ARW        {arw} deg/sqrt(h) (x, y, z)")
        lines.append(f"  accel VRW       {vrw} m/s/sqrt(h)")
        if "gyro_bias_instability" in noise:
            bi = ", ".join(f"{math.degrees(x) * 3600:.2f}" for x in noise["gyro_bias_instability"])
            lines.append(f"  gyro bias inst. {bi} deg/h (Allan floor)")
    else:
        lines.append("IMU noise:       not measured (no static span)")
    declared = info["imu_noise_declared"]
    if declared and not any(declared["gyro_variance"] + declared["accel_variance"]):
        lines.append("IMU declares:    no noise (zero covariances: unknown)")
    elif declared:
        gv = declared["gyro_variance"]
        lines.append(
            "IMU declares:    gyro variance "
            + ", ".join(f"{v:.3g}" for v in gv)
            + " (rad/s)^2, accel variance "
            + ", ".join(f"{v:.3g}" for v in declared["accel_variance"])
            + " (m/s^2)^2 per sample"
        )
    g = info["imu_grade"]
    text = (
        f"IMU grade:       {g['configured']} (ARW {_deg_per_sqrt_h(g['gyro_arw']):.3f} "
        f"deg/sqrt(h), VRW {_mps_per_sqrt_h(g['accel_vrw']):.4f} m/s/sqrt(h))"
    )
    if g["nearest_to_measured"] and g["nearest_to_measured"] != g["configured"]:
        text += (
            f"; the measured noise is nearest '{g['nearest_to_measured']}': "
            f"consider --imu-grade {g['nearest_to_measured']}"
        )
    lines.append(text)
    for w in info["warnings"]:
        lines.append(f"Warning:         {w}")
    return "\n".join(lines)
