"""What a driver node does with a decoded sample, without rclpy: calibrate it and build messages.

The node (``driver_node.py``) only moves samples from a source into :meth:`DriverCore.messages`
and publishes what comes back, so the calibration and the message contents are tested with
rosbags' message classes here and hold the same with rclpy's.

Calibration applied here (documented in the README):
- IMU: nothing but the raw-unit scales; samples stay in ``imu_link``; the mount rotation
  imu_link -> base_link is the estimator's ``imu_mount_rpy_deg`` (ekf_node), not the driver's.
- Odometer: counts -> distance = ticks * wheel_circumference_m / ticks_per_turn since the first
  sample, speed over ``speed_window_s`` (:class:`~pipe_nav_ros.sources.TickOdometer`).
- Magnetometer: field = soft_iron (raw - hard_iron), tesla in imu_link. Keep the estimator's
  ``mag_hard_iron`` at zero when the driver corrects it (else it is subtracted twice).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import Any

from pipe_nav_core import Marker, rosmsg

from .sources import (
    ImuSample,
    MagCalibration,
    MagSample,
    OdoSample,
    Sample,
    Scales,
    TickOdometer,
    TickSample,
)

SENSOR, MARKER = "sensor", "marker"


class DriverCore:
    """Calibration and message building of one driver node.

    settings: validated values of :func:`pipe_nav_ros.params.driver_settings_from_params`;
    types: the message classes (:func:`pipe_nav_ros.msg_types.rclpy_types` or rosbags').
    """

    def __init__(self, settings: Mapping[str, Any], types: Any) -> None:
        self.settings = dict(settings)
        self.kind = self.settings["kind"]
        self.types = types
        s = self.settings
        self.scales = Scales(
            gyro=s.get("gyro_scale", 1.0),
            accel=s.get("accel_scale", 1.0),
            field=s.get("field_scale", 1e-6),
        )
        self.odometer: TickOdometer | None = None
        self.mag_cal: MagCalibration | None = None
        if self.kind == "odometer":
            self.odometer = TickOdometer(
                s["wheel_circumference_m"],
                s["ticks_per_turn"],
                s["speed_window_s"],
                s["counter_bits"],
            )
        elif self.kind == "mag":
            self.mag_cal = MagCalibration(tuple(s["hard_iron"]), tuple(s["soft_iron"]))
        self.published = 0

    def messages(self, sample: Sample, stamp: float) -> list[tuple[str, Any]]:
        """The messages for one sample stamped ``stamp`` (s): [(SENSOR | MARKER, msg)]."""
        types, s = self.types, self.settings
        if isinstance(sample, Marker):
            return [(MARKER, rosmsg.marker_to_msg(types, replace(sample, t=stamp)))]
        if isinstance(sample, ImuSample):
            msg = rosmsg.imu_to_msg(
                types,
                stamp,
                sample.gyro,
                sample.accel,
                frame_id=s["frame_id"],
                gyro_var=s["angular_velocity_variance"],
                accel_var=s["linear_acceleration_variance"],
            )
        elif isinstance(sample, (TickSample, OdoSample)):
            if isinstance(sample, TickSample):
                assert self.odometer is not None
                # speed from the source clock: device intervals are exact, arrivals jitter
                distance, speed = self.odometer.update(sample.t, sample.ticks)
            else:
                distance, speed = sample.distance, sample.speed
            msg = rosmsg.wheel_to_msg(types, stamp, distance, speed)
            msg.header.frame_id = s["frame_id"]
            msg.child_frame_id = s["child_frame_id"]
        elif isinstance(sample, MagSample):
            assert self.mag_cal is not None
            msg = rosmsg.mag_to_msg(types, stamp, self.mag_cal.apply(sample.field), s["frame_id"])
        else:  # pragma: no cover - the Sample union is closed
            raise TypeError(f"unknown sample {sample!r}")
        self.published += 1
        return [(SENSOR, msg)]
