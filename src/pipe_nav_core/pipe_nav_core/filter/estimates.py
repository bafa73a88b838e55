"""What a filter pass produces: an estimate per epoch (:class:`NavEstimate`, for the live
node and the replay) and the smoothers' recording
(:class:`~pipe_nav_core.smooth.recording.Recording`),
and the signs that its IMU noise model does not fit the data (:func:`model_warnings`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.anchoring import FreeHeading
from pipe_nav_core.filter.epoch import Batch
from pipe_nav_core.filter.kalman import ErrorStateKF
from pipe_nav_core.model.sensors import ImuSpec
from pipe_nav_core.model.state import SV_DIST, SV_H, SV_LAT, SV_LON, SV_Q, SV_T, SV_VEL, Layout
from pipe_nav_core.smooth.recording import Recording

Array = NDArray[np.float64]


@dataclass
class NavEstimate:
    """Estimate at the end of one filter epoch.

    t s; lat, lon rad; h m; vel_n (3,) m/s ENU; quat_nb (4,) [x,y,z,w] base_link->ENU;
    omega_b (3,) rad/s bias-corrected body rate; cov_pose (6, 6) over [E, N, U (m),
    rotation about E, N, U (rad)]; cov_vel_n (3, 3) (m/s)^2; distance m calibrated chainage;
    status: "static" or "moving".
    """

    t: float
    lat: float
    lon: float
    h: float
    vel_n: Array
    quat_nb: Array
    omega_b: Array
    cov_pose: Array
    cov_vel_n: Array
    distance: float
    status: str


# a gate that rejects more than this share of an update kind (out of at least MIN_UPDATES) is
# fighting a filter that trusts its model more than the data
REJECTED_SHARE, MIN_UPDATES = 0.1, 50
# an estimated gyro bias this many times the grade's turn-on bias means another grade of IMU
BIAS_FACTOR = 5.0


def model_warnings(
    diag: dict[str, int | float | str], gyro_bias: Array, spec: ImuSpec
) -> list[str]:
    """One line per sign that the IMU noise model does not fit the data: a gate that rejects
    many odometer or non-holonomic updates, or a gyro bias (rad/s, base_link) far beyond the
    grade's turn-on bias. Both show a filter more confident than its sensors, whose centreline
    and sigmas are not to be trusted. Most of the non-holonomic updates rejected also names the
    IMU's mount: the pig moving sideways in base_link."""
    out = []
    for kind in ("nhc", "odometer"):
        acc = int(diag.get(f"accepted_{kind}", 0))
        rej = int(diag.get(f"rejected_{kind}", 0))
        if acc + rej >= MIN_UPDATES and rej > REJECTED_SHARE * (acc + rej):
            # most of the NHC rejected: the pig moves sideways in base_link, an IMU mounted
            # otherwise than configured (90 deg about z: 95 % on the sample)
            mount = (
                " and the IMU's mount (imu_mount_rpy)"
                if kind == "nhc" and 2 * rej > acc + rej
                else ""
            )
            out.append(
                f"{rej / (acc + rej):.0%} of the {kind} updates were rejected: the filter trusts "
                f"its IMU model ({spec.name}) more than the data; check imu_grade (--imu-grade)"
                f"{mount}"
            )
    worst = float(np.max(np.abs(gyro_bias))) if len(gyro_bias) else 0.0
    if worst > BIAS_FACTOR * spec.gyro_turn_on_bias:
        out.append(
            f"estimated gyro bias {np.degrees(worst) * 3600:.0f} deg/h is "
            f"{worst / spec.gyro_turn_on_bias:.0f} times the {spec.name} grade's turn-on bias "
            f"({np.degrees(spec.gyro_turn_on_bias) * 3600:.0f} deg/h); "
            "check imu_grade (--imu-grade)"
        )
    return out


class Reporter:
    """The estimates (emit: one per epoch, collected until :meth:`poll`) and the recording
    (record, linearized: the pass runs about a reference trajectory) of one pass."""

    def __init__(
        self,
        config: NavConfig,
        layout: Layout,
        *,
        emit: bool,
        record: bool,
        reference: Array | None,
    ) -> None:
        self.layout = layout
        self.emit = emit
        self.linearized = reference is not None
        self.recording = Recording(layout, reference=reference) if record else None
        pose = [*range(layout.pos.start, layout.pos.stop)]
        pose += range(layout.att.start, layout.att.stop)
        self._pose_ix = np.ix_(pose, pose)  # [position, attitude] rows/columns of P
        # without velocity states (dead reckoning) the velocity's covariance is the odometer's
        self._cov_vel = np.eye(3) * config.odometer_speed_sigma**2
        self._out: list[NavEstimate] = []

    def poll(self) -> list[NavEstimate]:
        """Estimates produced since the last call, in time order."""
        out, self._out = self._out, []
        return out

    def alignment(self, sv: Array, kf: ErrorStateKF, free: FreeHeading | None) -> None:
        """The aligned state sv (flat) with its prior: epoch 0 of the recording (no
        transition), and a static estimate."""
        rec = self.recording
        if rec is not None:
            n = self.layout.n
            zero = np.zeros(n)
            rec.add_epoch(
                sv.copy(),
                dx=zero,
                P_upd=kf.P,
                P_pred=kf.P,
                phi=np.eye(n),
                x_upd=kf.x.copy() if self.linearized else None,
                end_offset=zero if self.linearized else None,
            )
        if self.emit:
            self._out.append(self._estimate(sv, kf.P, np.zeros(3), "static", free))

    def batch(self, batch: Batch, ends: NDArray[np.int64], imu_t: Array,
              free: FreeHeading | None) -> None:  # fmt: skip
        """A batch's epochs (ending at the IMU samples ends of the buffer imu_t, s) into the
        recording and the estimates; free: the heading prior kept outside the filter."""
        nb = len(ends)
        rec = self.recording
        if rec is not None:
            lin = self.linearized
            rec.add_epochs(
                batch.sv[:nb],
                dx=batch.dx[:nb],
                P_upd=batch.P_upd[:nb],
                P_pred=batch.P_pred[:nb],
                phi=batch.phi[:nb],
                x_upd=batch.x_upd[:nb] if lin else None,
                end_offset=batch.end_offset[:nb] if lin else None,
            )
            b = batch
            rec.add_blocks(ends, imu_t, b.s_odo, b.lat, b.lon, b.h, b.q)
        if self.emit:
            for e in range(nb):
                status = "static" if batch.stopped[e] else "moving"
                self._out.append(
                    self._estimate(batch.sv[e], batch.P_upd[e], batch.omega[e], status, free)
                )

    def _estimate(
        self, v: Array, P: Array, omega: Array, status: str, free: FreeHeading | None
    ) -> NavEstimate:
        """The estimate of flat state v with covariance P (n, n) and body rate omega."""
        lay = self.layout
        if free is not None and v[SV_T] < free.until:  # the heading prior kept outside P
            P = P + free.covariance(v[SV_LAT], v[SV_LON], v[SV_H], v[SV_VEL], lay)
        cov_vel = P[lay.vel, lay.vel].copy() if lay.vel is not None else self._cov_vel.copy()
        return NavEstimate(
            t=float(v[SV_T]),
            lat=float(v[SV_LAT]),
            lon=float(v[SV_LON]),
            h=float(v[SV_H]),
            vel_n=v[SV_VEL].copy(),
            quat_nb=v[SV_Q].copy(),
            omega_b=omega.copy(),
            cov_pose=P[self._pose_ix],
            cov_vel_n=cov_vel,
            distance=float(v[SV_DIST]),
            status=status,
        )
