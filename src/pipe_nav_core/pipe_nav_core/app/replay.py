"""The forward estimates of the online engine over a bag (``pipe-nav replay``, the replay
launch file).

The replay runs the live engine (:class:`pipe_nav_core.filter.live_guard.GuardedNavigator`) on
the bag's samples in arrival order, as ekf_node would; positions geodetic (WGS84) and ENU
metres about the first fix, attitude base_link -> ENU.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from pipe_nav_core.app.pipeline import DEFAULT_TOPICS, load_log, require_imu
from pipe_nav_core.config import AUTO_GRADE, NavConfig
from pipe_nav_core.filter.estimates import NavEstimate
from pipe_nav_core.filter.live_guard import GuardedNavigator
from pipe_nav_core.io import (
    BagReport,
    TopicNames,
    write_output_bag,
)
from pipe_nav_core.io.atomic import ensure_not_input
from pipe_nav_core.types import Datum, SensorLog, Trajectory


@dataclass
class ReplayResult:
    """Forward estimates of the online engine over a bag, its datum and its diagnostics."""

    estimates: list[NavEstimate]
    datum: Datum | None
    diagnostics: dict[str, object] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)  # Navigator.model_warnings


def replay_log(
    log: SensorLog, config: NavConfig, declared: dict[str, list[float]] | None = None
) -> ReplayResult:
    """Run the online engine over a log exactly as ekf_node does: samples pushed one by one in
    stamp order (the engine's reorder buffer makes arrival order within its window irrelevant).
    declared: the per-sample IMU variances the Imu messages declare (imu_grade auto)."""
    nav = GuardedNavigator(config)
    nav.declared_imu_noise = declared
    out: list[NavEstimate] = []
    # Python floats and lists, as a message's fields are: numpy rows cost more per sample
    imu_t, gyro, accel = log.imu.t.tolist(), log.imu.gyro.tolist(), log.imu.accel.tolist()
    odo_t, dist, speed = (x.tolist() for x in (log.odometer.t, log.odometer.distance,
                                               log.odometer.speed))  # fmt: skip
    mag_t, mag = log.mag.t.tolist(), log.mag.field.tolist()
    events: list[tuple[float, int, int]] = []
    events += [(t, 0, i) for i, t in enumerate(imu_t)]
    events += [(t, 1, i) for i, t in enumerate(odo_t)]
    events += [(t, 2, i) for i, t in enumerate(mag_t)]
    events += [(m.t, 3, i) for i, m in enumerate(log.markers)]
    events.sort()
    for _t, kind, i in events:
        if kind == 0:
            nav.push_imu(imu_t[i], gyro[i], accel[i])
        elif kind == 1:
            nav.push_odometer(odo_t[i], dist[i], speed[i])
        elif kind == 2:
            nav.push_mag(mag_t[i], mag[i])
        else:
            nav.push_marker(log.markers[i])
        out.extend(nav.poll())
    out.extend(nav.finish())
    return ReplayResult(out, nav.datum, dict(nav.diagnostics()), nav.model_warnings())


def estimates_to_trajectory(estimates: Sequence[NavEstimate]) -> Trajectory:
    """Forward estimates as a Trajectory (sigmas from the covariance diagonals)."""
    cov = np.array([e.cov_pose for e in estimates]).reshape(-1, 6, 6)
    var = np.einsum("kii->ki", cov)
    return Trajectory(
        t=np.array([e.t for e in estimates]),
        lat=np.array([e.lat for e in estimates]),
        lon=np.array([e.lon for e in estimates]),
        h=np.array([e.h for e in estimates]),
        vel_n=np.array([e.vel_n for e in estimates]).reshape(-1, 3),
        quat_nb=np.array([e.quat_nb for e in estimates]).reshape(-1, 4),
        distance=np.array([e.distance for e in estimates]),
        sigma_enu=np.sqrt(np.maximum(var[:, :3], 0.0)),
        sigma_att=np.sqrt(np.maximum(var[:, 3:], 0.0)),
        cov_pose=cov,
    )


def replay_bag(
    bag: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    config: NavConfig,
    markers_csv: str | os.PathLike[str] | None = None,
    topics: TopicNames = DEFAULT_TOPICS,
) -> tuple[ReplayResult, BagReport]:
    """`pipe-nav replay`: the online estimator over a bag; writes /pipe_nav/odometry."""
    ensure_not_input(out, [bag] + ([markers_csv] if markers_csv else []))
    log, report = load_log(bag, topics=topics, markers_csv=markers_csv, repair=False)
    require_imu(log, report, bag, topics)
    auto = config.imu_grade == AUTO_GRADE
    result = replay_log(log, config, report.imu_noise_declared if auto else None)
    if not result.estimates:
        raise ValueError(
            f"{bag}: the estimator produced no estimate (no static start or no marker)"
        )
    traj = estimates_to_trajectory(result.estimates)
    datum = result.datum or Datum(traj.lat[0], traj.lon[0], traj.h[0])
    write_output_bag(out, path=None, datum=datum, odometry=traj)
    report.warnings += result.warnings
    if "lost_since" in result.diagnostics:
        d = result.diagnostics
        report.warnings.append(
            f"the live solution was lost at t = {float(d['lost_since']):.3f} s "  # type: ignore[arg-type]
            f"({d['lost_reason']}): {d.get('withheld_lost', 0)} estimates after it withheld"
        )
    return result, report
