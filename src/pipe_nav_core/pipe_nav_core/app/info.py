"""What a user checks in a bag before smoothing it (``pipe-nav info BAG``).

Per input topic: message type, count, rate and stamp gaps; the run's duration and odometer
distance; the markers (surveyed or not); the static spans (odometer still for at least
``MIN_STATIC_S``); the IMU noise measured in them (white-noise density from the sample scatter,
and the Allan deviation of the longest span where it is long enough for a bias-instability
figure); the per-sample noise the Imu messages declare; the IMU grade the settings use
against the one whose noise figures are nearest the measured ones; and the IMU's clock against
the odometer's (faults.clock_offset: measured at the pig's starts and stops; where pipe-nav
smooth would re-time the IMU, the static spans and the noise are measured as it re-times it).
Times are s from the bag's first stamp, angles in the text in degrees (radians in the JSON's
``*_rad`` fields), SI otherwise.
"""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.config import NavConfig
from pipe_nav_core.faults import clock_offset
from pipe_nav_core.filter.ingest import mount_rotation
from pipe_nav_core.io import TopicNames, merge_markers, read_bag, read_markers_csv
from pipe_nav_core.io.topics import DEFAULT_TOPICS
from pipe_nav_core.model.imu_noise import choose, measured_noise, nearest_grade, static_spans

GAP_FACTOR = 5.0  # a stamp step over this many median periods is a gap

FloatArray = NDArray[np.float64]


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
    log, clock = clock_offset.taken_out(log, mount_rotation(cfg.imu_mount_rpy))  # as smooth
    if clock is not None and clock.named:
        report.warn(clock.describe("pipe-nav smooth re-times the IMU and the magnetometer to "
                                   "the odometer's clock"))  # fmt: skip
    spans = static_spans(log)
    noise = measured_noise(log, spans)
    declared = report.imu_noise_declared
    chosen = choose(log, cfg, declared)
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
        "imu_noise_declared": declared,
        "imu_grade": {
            "configured": cfg.imu_grade,
            "gyro_arw": spec.gyro_arw,
            "accel_vrw": spec.accel_vrw,
            "nearest_to_measured": nearest_grade(noise),
            "smooth_would_use": chosen.grade,
            "reason": chosen.reason,
        },
        "imu_clock": None
        if clock is None
        else {
            "offset_s": clock.first,
            "offset_at_end_s": clock.last,
            "events": clock.events,
            "retimed_by_smooth": clock.retime,
            "irregular": clock.irregular,
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
    if g["configured"] == "auto":
        text = f"IMU grade:       auto -> {g['smooth_would_use']} ({g['reason']})"
    elif g["nearest_to_measured"] and g["nearest_to_measured"] != g["configured"]:
        text += (
            f"; the measured noise is nearest '{g['nearest_to_measured']}': "
            f"consider --imu-grade {g['nearest_to_measured']}"
        )
    lines.append(text)
    for w in info["warnings"]:
        lines.append(f"Warning:         {w}")
    return "\n".join(lines)
