"""Scenario definitions: everything that describes one simulated pig run, and the named set.

All angles are radians and all quantities SI (m, s, m/s, T) inside a :class:`Scenario`; the
definitions below write degrees through ``math.radians`` for readability. A scenario fixes the
pipe (deterministic: the same line for every seed) and the statistical description of the motion
and of the sensors; :func:`~pipe_nav_core.sim.simulate` draws one run from it for a given seed.

The named scenarios follow the source papers (see /work/shared/seeds/README.md):
``drag180`` (seed 001), ``sag104``/``sag104_deep`` (seed 000), ``undulation90`` (seed 002),
``field10k``/``field10k_sparse`` (seed 003) and ``demo`` (the bundled sample bag).

About 650 lines, one module on purpose: the :class:`Scenario` record and the named scenarios,
each a page of physical parameters taken from its paper; they are read side by side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.model.sensors import ImuSpec, imu_grade
from pipe_nav_core.sim.geometry import Bend, Feature, PipeGeometry, Sag, field_features
from pipe_nav_core.sim.motion import RollTurn, SpeedParams, Stop

FloatArray = NDArray[np.float64]

DEG = math.pi / 180.0
UT = 1e-6  # microtesla in tesla


@dataclass(frozen=True)
class Scenario:
    """One pig run's world and sensors (SI units, radians).

    Location and pipe: ``lat``, ``lon`` (rad) and ``alt`` (m, ellipsoidal) of the launch trap;
    ``azimuth`` (rad clockwise from north) and ``pitch`` (rad up) of the pipe at the launch;
    ``length`` (m), ``pipe_diameter`` (m, the bore), ``pipe_outer_diameter`` (m, for bending
    strain; 0 = not stated, the estimator then uses the bore), ``features`` (Bend, Sag at
    chainages in m);
    ``pipe_seed``: the pipe's identity; it draws the field bends and grade changes (with
    ``field_line``), the girth weld anomalies and the marker survey errors, so scenarios that
    share it are runs through one pipe;
    ``length_scale``: multiplies the length and every chainage (features, stops, roll turns,
    explicit marker chainages); use :meth:`with_length`.

    Motion: ``speed`` (m/s cruise), ``speed_fluctuation`` (relative sigma), ``speed_interval`` (s
    between speed changes), ``accel`` (m/s^2 peak), ``surge_factor``/``surge_duration`` (after
    stops), ``stops`` (chainage m, duration s), ``static_start``/``static_end`` (s at rest in the
    traps); roll (only while moving): ``roll0`` (rad), ``roll_wander`` (rad/s sigma of the
    slow roll rate at cruise speed), ``roll_wander_interval`` (s of cruise between changes),
    ``roll_turns`` (chainage m, signed turns, peak rate rad/s).

    IMU: ``imu_grade`` (consumer | industrial | tactical) or an explicit ``imu_spec``;
    ``imu_rate_hz``; ``imu_mount_rpy`` (rad, imu_link -> base_link as Rz Ry Rx).

    Odometer: ``odo_rate_hz``; ``odo_tick`` (m per count, 0 = none); ``odo_scale_sigma``
    (relative); ``odo_lever_arm`` (m, wheel contact point in base_link; None = (0, 0, -D/2));
    slips about every ``odo_slip_interval`` s (0 = none) lasting ``odo_slip_duration`` s;
    ``odo_speed_window`` (s) of the driver's speed estimate.

    Magnetometer: ``mag_enabled``, ``mag_rate_hz``, Earth field ``mag_declination`` (rad, east
    positive), ``mag_inclination`` (rad, down positive), ``mag_field`` (T); ``mag_attenuation``
    (in-pipe factor mu); ``mag_hard_iron`` (T, imu_link); girth welds every ``weld_spacing`` m
    with anomalies of about ``weld_anomaly`` T over ``weld_width`` m (None = D); ``mag_noise``
    (T per axis). The wheel crossing a weld's bead lifts the pig by ``weld_bump_height`` m over
    ``weld_bump_duration`` s (one sigma), a jolt on the accelerometers (sim/weld_bump.py; 0 =
    off, the default).

    Markers: ``marker_chainages`` (m) or ``marker_spacing`` (m; 0 and the end are always
    markers); ``marker_time_sigma`` (s); ``survey_sigma_h``/``survey_sigma_v`` (m).
    ``t0``: clock time (s) of the first IMU sample.
    """

    name: str
    description: str = ""
    lat: float = 39.9 * DEG
    lon: float = 116.4 * DEG
    alt: float = 50.0
    azimuth: float = 45.0 * DEG
    pitch: float = 0.0
    length: float = 100.0
    pipe_diameter: float = 0.2
    pipe_outer_diameter: float = 0.0
    features: tuple[Feature, ...] = ()
    field_line: bool = False
    pipe_seed: int = 0
    length_scale: float = 1.0
    speed: float = 1.0
    speed_fluctuation: float = 0.08
    speed_interval: float = 8.0
    accel: float = 0.3
    surge_factor: float = 1.6
    surge_duration: float = 4.0
    stops: tuple[Stop, ...] = ()
    static_start: float = 10.0
    static_end: float = 10.0
    roll0: float = 0.0
    roll_wander: float = 0.02
    roll_wander_interval: float = 15.0
    roll_turns: tuple[RollTurn, ...] = ()
    imu_grade: str = "industrial"
    imu_spec: ImuSpec | None = None
    imu_rate_hz: float = 200.0
    imu_mount_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    odo_rate_hz: float = 50.0
    odo_tick: float = 0.005
    odo_scale_sigma: float = 0.005
    odo_lever_arm: tuple[float, float, float] | None = None
    odo_slip_interval: float = 30.0
    odo_slip_duration: tuple[float, float] = (0.05, 0.3)
    odo_speed_window: float = 0.2
    mag_enabled: bool = True
    mag_rate_hz: float = 50.0
    mag_declination: float = -7.0 * DEG
    mag_inclination: float = 59.0 * DEG
    mag_field: float = 54.0 * UT
    mag_attenuation: float = 0.5
    mag_hard_iron: tuple[float, float, float] = (1.5 * UT, -0.8 * UT, 2.0 * UT)
    weld_spacing: float = 12.0
    weld_anomaly: float = 5.0 * UT
    weld_width: float | None = None
    weld_bump_height: float = 0.0
    weld_bump_duration: float = 0.01
    mag_noise: float = 0.2 * UT
    marker_chainages: tuple[float, ...] | None = None
    marker_spacing: float | None = None
    marker_time_sigma: float = 0.02
    survey_sigma_h: float = 0.02
    survey_sigma_v: float = 0.02
    t0: float = 0.0
    tags: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        positive = (
            "length",
            "pipe_diameter",
            "length_scale",
            "speed",
            "accel",
            "imu_rate_hz",
            "odo_rate_hz",
            "mag_rate_hz",
            "mag_field",
        )
        for k in positive:
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"scenario {self.name!r}: {k} must be positive, not {v!r}")
        for k in (
            "static_start",
            "static_end",
            "odo_tick",
            "odo_scale_sigma",
            "mag_noise",
            "weld_bump_height",
            "weld_bump_duration",
            "marker_time_sigma",
            "survey_sigma_h",
            "survey_sigma_v",
            "speed_fluctuation",
            "pipe_outer_diameter",
        ):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"scenario {self.name!r}: {k} must be >= 0, not {v!r}")
        if self.imu_spec is None:
            imu_grade(self.imu_grade)  # raises a clear ValueError for unknown grades
        if 0 < self.pipe_outer_diameter < self.pipe_diameter:
            raise ValueError(f"scenario {self.name!r}: pipe_outer_diameter is below the bore")
        if self.marker_spacing is not None and self.marker_spacing <= 0:
            raise ValueError(f"scenario {self.name!r}: marker_spacing must be positive")

    # -- derived quantities -------------------------------------------------------------------
    @property
    def total_length(self) -> float:
        """Pipe length after ``length_scale``, m."""
        return self.length * self.length_scale

    def with_length(self, length_m: float) -> Scenario:
        """The same scenario stretched (or shrunk) to ``length_m`` m of pipe."""
        return replace(self, length_scale=float(length_m) / self.length)

    def imu_error_spec(self) -> ImuSpec:
        """The true IMU error model (explicit ``imu_spec`` or the named grade)."""
        return self.imu_spec if self.imu_spec is not None else imu_grade(self.imu_grade)

    def lever_arm(self) -> tuple[float, float, float]:
        """Odometer wheel contact point in base_link, m."""
        if self.odo_lever_arm is not None:
            return tuple(float(x) for x in self.odo_lever_arm)  # type: ignore[return-value]
        return (0.0, 0.0, -0.5 * self.pipe_diameter)

    def marker_chainage_list(self) -> FloatArray:
        """Marker chainages (m, increasing; first 0 = launch trap, last = receive trap)."""
        total = self.total_length
        if self.marker_chainages is not None:
            ch = np.asarray(self.marker_chainages, dtype=np.float64) * self.length_scale
        elif self.marker_spacing is not None:
            ch = np.arange(0.0, total, self.marker_spacing)
            if total - ch[-1] < 0.25 * self.marker_spacing and len(ch) > 1:
                ch = ch[:-1]
            ch = np.append(ch, total)
        else:
            ch = np.array([0.0, total])
        ch = np.clip(ch, 0.0, total)
        if ch[0] != 0.0:
            ch = np.insert(ch, 0, 0.0)
        if ch[-1] < total - 1e-9:
            ch = np.append(ch, total)
        return np.unique(ch)

    def scaled_stops(self) -> list[Stop]:
        """Stops with chainages in m after ``length_scale``."""
        k = self.length_scale
        return [Stop(st.chainage * k, st.duration) for st in self.stops]

    def scaled_roll_turns(self) -> list[RollTurn]:
        """Roll turns with chainages in m after ``length_scale``."""
        k = self.length_scale
        return [RollTurn(r.chainage * k, r.turns, r.rate) for r in self.roll_turns]

    def speed_params(self) -> SpeedParams:
        """The speed-profile parameters."""
        return SpeedParams(
            cruise=self.speed,
            fluctuation=self.speed_fluctuation,
            interval=self.speed_interval,
            accel=self.accel,
            surge_factor=self.surge_factor,
            surge_duration=self.surge_duration,
        )

    def pipe_features(self) -> list[Feature]:
        """All features at their scaled chainages (explicit ones plus the field line)."""
        feats: list[Feature] = [f.scaled(self.length_scale) for f in self.features]
        if self.field_line:
            rng = np.random.default_rng([self.pipe_seed, 7001])
            feats += field_features(self.total_length, self.pipe_diameter, rng)
        return feats

    def build_geometry(self) -> PipeGeometry:
        """The pipe centreline (deterministic for the scenario)."""
        return PipeGeometry(
            self.total_length,
            self.lat,
            self.lon,
            self.alt,
            self.azimuth,
            self.pitch,
            self.pipe_features(),
            diameter=self.pipe_diameter,
        )

    def estimator_settings(self) -> dict[str, Any]:
        """What a user would honestly configure the estimator with: nominal, known values only
        (never a realised random error). Keys are :class:`pipe_nav_core.config.NavConfig`
        fields, so ``NavConfig.from_dict(scenario.estimator_settings())`` works."""
        return {
            "imu_grade": self.imu_spec.name if self.imu_spec is not None else self.imu_grade,
            "imu_mount_rpy": tuple(float(x) for x in self.imu_mount_rpy),
            "odometer_lever_arm": self.lever_arm(),
            "pipe_diameter": float(self.pipe_diameter),
            # the pig's hard iron is not calibrated here: a magnetometer inside steel pipe with an
            # unknown hard iron misleads more than it helps, so an honest user leaves it off
            "mag_update": False,
            "mag_declination": float(self.mag_declination),
            "marker_time_sigma": float(self.marker_time_sigma),
            "odometer_scale_sigma": max(float(self.odo_scale_sigma), 1e-4),
            # the outer diameter is a nominal pipe dimension the user knows (strain products)
            **(
                {"pipe_outer_diameter": float(self.pipe_outer_diameter)}
                if self.pipe_outer_diameter > 0
                else {}
            ),
        }


# --------------------------------------------------------------------------------------------
# The named scenarios
# --------------------------------------------------------------------------------------------


def _drag180() -> Scenario:
    d = 0.1
    return Scenario(
        name="drag180",
        pipe_seed=1,
        description=(
            "Seed 001 drag test: 180 m pipe of 0.1 m bore pulled at about 1.5 m/s, consumer "
            "MEMS IMU, wire-rope encoder with 5 mm resolution, magnetometer (Earth field of the "
            "paper's table 2), markers at both ends only, static periods at both ends for the "
            "forward and backward alignments; tight bends (down to 1.5 D) and gentle grades."
        ),
        lat=41.80 * DEG,
        lon=123.40 * DEG,
        alt=60.0,
        azimuth=20.0 * DEG,
        length=180.0,
        pipe_diameter=d,
        features=(
            Bend(22.0, 90.0 * DEG, 1.5 * d, "h"),
            Bend(40.0, 2.0 * DEG, 3.0, "v"),
            Bend(62.0, -2.0 * DEG, 3.0, "v"),
            Bend(75.0, -60.0 * DEG, 3.0 * d, "h"),
            Bend(100.0, -1.5 * DEG, 5.0, "v"),
            Bend(118.0, 45.0 * DEG, 5.0 * d, "h"),
            Bend(135.0, 1.5 * DEG, 5.0, "v"),
            Bend(152.0, -30.0 * DEG, 10.0 * d, "h"),
        ),
        speed=1.5,
        speed_fluctuation=0.05,
        speed_interval=6.0,
        accel=0.5,
        static_start=10.0,
        static_end=10.0,
        roll0=0.1,
        roll_wander=0.02,
        roll_turns=(RollTurn(90.0, 1.0, 2.0),),
        imu_grade="consumer",
        imu_rate_hz=200.0,
        odo_rate_hz=50.0,
        odo_tick=0.005,
        odo_scale_sigma=0.005,
        odo_slip_interval=20.0,
        mag_enabled=True,
        mag_rate_hz=50.0,
        mag_declination=-(9.0 + 18.0 / 60.0) * DEG,
        mag_inclination=59.77 * DEG,
        mag_field=54.1854 * UT,
        mag_attenuation=0.6,
        weld_spacing=12.0,
        weld_anomaly=4.0 * UT,
        mag_noise=0.3 * UT,
        marker_chainages=(0.0, 180.0),
        tags=("seed001", "test_pipe"),
    )


def _sag104(depth: float, name: str) -> Scenario:
    return Scenario(
        name=name,
        description=(
            f"Seed 000 drag test: 103.8 m pipe pulled at about 1 m/s with a {depth:.3f} m sag "
            "in the middle (around chainage 50.5 m), industrial MEMS IMU, odometer, markers at "
            "both ends (about 100 m apart), no magnetometer."
        ),
        lat=30.52 * DEG,
        lon=114.35 * DEG,
        alt=25.0,
        azimuth=62.0 * DEG,
        length=103.8,
        pipe_diameter=0.2,
        features=(Sag(30.5, 40.0, depth, "v"),),
        speed=1.0,
        speed_fluctuation=0.06,
        speed_interval=6.0,
        accel=0.4,
        static_start=10.0,
        static_end=10.0,
        roll0=-0.05,
        roll_wander=0.01,
        imu_grade="industrial",
        imu_rate_hz=200.0,
        odo_rate_hz=50.0,
        odo_tick=0.002,
        odo_scale_sigma=0.003,
        odo_slip_interval=25.0,
        mag_enabled=False,
        marker_chainages=(0.0, 103.8),
        tags=("seed000", "test_pipe"),
    )


def _undulation90() -> Scenario:
    return Scenario(
        name="undulation90",
        pipe_seed=2,
        description=(
            "Seed 002 test pipe (Jiading test field): 90 m trenchless pipe with a 2 m vertical "
            "undulation, pulled by a winch at about 0.6 m/s, consumer MEMS IMU, Hall-effect "
            "wheel encoder, markers at both pipe mouths, no magnetometer."
        ),
        lat=31.38 * DEG,
        lon=121.25 * DEG,
        alt=12.0,
        azimuth=105.0 * DEG,
        length=90.0,
        pipe_diameter=0.3,
        features=(
            Sag(8.0, 74.0, 2.0, "v"),
            Bend(30.0, 6.0 * DEG, 150.0, "h"),
        ),
        speed=0.6,
        speed_fluctuation=0.1,
        speed_interval=5.0,
        accel=0.3,
        static_start=10.0,
        static_end=10.0,
        roll0=0.3,
        roll_wander=0.03,
        imu_grade="consumer",
        imu_rate_hz=200.0,
        odo_rate_hz=50.0,
        odo_tick=0.01,
        odo_scale_sigma=0.01,
        odo_slip_interval=15.0,
        mag_enabled=False,
        marker_chainages=(0.0, 90.0),
        tags=("seed002", "test_pipe"),
    )


def _field10k(spacing: float, name: str) -> Scenario:
    d = 0.219
    return Scenario(
        name=name,
        description=(
            "Seed 003 field line: 10 km of 219 mm products pipeline in hilly terrain, tactical "
            "MEMS IMU (HG4930 class) at 200 Hz, odometer wheel, magnetometer in a thick steel "
            f"pipe, buried magnetic markers every {spacing / 1000:g} km, about 1.85 m/s average "
            "(about 1.5 h) with a few stops, induction bends of 3-5 D and grade changes."
        ),
        lat=36.06 * DEG,
        lon=103.83 * DEG,
        alt=1520.0,
        azimuth=75.0 * DEG,
        length=10_000.0,
        pipe_diameter=d,
        field_line=True,
        pipe_seed=3,
        speed=1.95,
        speed_fluctuation=0.1,
        speed_interval=10.0,
        accel=0.3,
        surge_factor=1.5,
        surge_duration=6.0,
        stops=(Stop(2600.0, 40.0), Stop(5400.0, 90.0), Stop(8100.0, 25.0)),
        static_start=30.0,
        static_end=30.0,
        roll0=0.4,
        roll_wander=0.01,
        roll_wander_interval=30.0,
        roll_turns=(
            RollTurn(1500.0, 1.0, 2.0),
            RollTurn(4200.0, -2.0, 3.0),
            RollTurn(7300.0, 1.0, 1.5),
            RollTurn(9000.0, 3.0, 2.5),
        ),
        imu_grade="tactical",
        imu_rate_hz=200.0,
        odo_rate_hz=50.0,
        odo_tick=0.005,
        odo_scale_sigma=0.01,
        odo_slip_interval=30.0,
        mag_enabled=True,
        mag_rate_hz=20.0,
        mag_declination=-1.9 * DEG,
        mag_inclination=56.5 * DEG,
        mag_field=53.5 * UT,
        mag_attenuation=0.1,
        weld_spacing=12.0,
        weld_anomaly=10.0 * UT,
        mag_noise=0.1 * UT,
        marker_spacing=spacing,
        tags=("seed003", "field"),
    )


def _demo() -> Scenario:
    d = 0.2
    return Scenario(
        name="demo",
        pipe_seed=4,
        description=(
            "Sample for the bundled bag: 300 m of 0.2 m pipe, industrial IMU at 100 Hz, "
            "odometer 50 Hz, magnetometer 20 Hz, markers every 100 m, a 45 deg horizontal bend, "
            "a 0.5 m sag, one stop, one full roll turn; about 3 minutes including rest in the "
            "traps."
        ),
        lat=39.90 * DEG,
        lon=116.40 * DEG,
        alt=45.0,
        azimuth=30.0 * DEG,
        length=300.0,
        pipe_diameter=d,
        features=(
            Bend(60.0, 45.0 * DEG, 3.0 * d, "h"),
            Sag(140.0, 60.0, 0.5, "v"),
            Bend(255.0, -1.0 * DEG, 50.0, "v"),
        ),
        speed=2.0,
        speed_fluctuation=0.08,
        speed_interval=8.0,
        accel=0.4,
        stops=(Stop(230.0, 10.0),),
        static_start=10.0,
        static_end=10.0,
        roll0=0.2,
        roll_wander=0.02,
        roll_turns=(RollTurn(110.0, 1.0, 2.0),),
        imu_grade="industrial",
        imu_rate_hz=100.0,
        odo_rate_hz=50.0,
        odo_tick=0.005,
        odo_scale_sigma=0.005,
        odo_slip_interval=30.0,
        mag_enabled=True,
        mag_rate_hz=20.0,
        mag_declination=-7.0 * DEG,
        mag_inclination=59.0 * DEG,
        mag_field=54.0 * UT,
        mag_attenuation=0.4,
        marker_spacing=100.0,
        tags=("demo",),
    )


def _bends_test() -> Scenario:
    d, od = 0.3, 0.3239  # 12" pipe: bore and outer diameter (12.75 in)
    h, v = "h", "v"
    return Scenario(
        name="bends_test",
        pipe_seed=5,
        description=(
            "Bend test pipe (issue 18): 500 m of 12 in pipe (0.3 m bore, 0.324 m outer "
            "diameter) with 17 bends of 0.5 to 10 deg, 25 m apart, at 3 D, 5 D and 40 D "
            "(outer diameters) and elastic radii of 400 to 1000 m, horizontal, vertical and one "
            "3-D (overlapping horizontal and vertical) bend; the bends of about 1 deg turn by "
            "1.1 deg, so that the 1 deg listing threshold is not a coin toss; pulled at about "
            "1 m/s, industrial MEMS IMU, odometer, markers every 125 m, no magnetometer."
        ),
        lat=31.00 * DEG,
        lon=121.00 * DEG,
        alt=8.0,
        azimuth=80.0 * DEG,
        length=500.0,
        pipe_diameter=d,
        pipe_outer_diameter=od,
        features=(
            Bend(20.0, 10.0 * DEG, 3.0 * od, h),
            Bend(45.0, -10.0 * DEG, 40.0 * od, h),
            Bend(70.0, 5.0 * DEG, 5.0 * od, h),
            Bend(95.0, 2.0 * DEG, 400.0, h),
            Bend(125.0, -1.1 * DEG, 3.0 * od, h),
            Bend(150.0, -0.5 * DEG, 40.0 * od, h),
            Bend(175.0, 1.1 * DEG, 1000.0, h),
            Bend(215.0, -2.0 * DEG, 600.0, h),
            Bend(260.0, 3.0 * DEG, 5.0 * od, v),
            Bend(285.0, -3.0 * DEG, 40.0 * od, v),
            Bend(310.0, 1.1 * DEG, 5.0 * od, v),
            Bend(335.0, -1.1 * DEG, 500.0, v),
            Bend(360.0, 0.5 * DEG, 3.0 * od, v),
            Bend(385.0, -0.5 * DEG, 1000.0, v),
            Bend(410.0, 10.0 * DEG, 40.0 * od, v),
            Bend(440.0, -10.0 * DEG, 3.0 * od, v),
            Bend(470.0, 6.0 * DEG, 5.0 * od, h),
            Bend(470.1, -4.0 * DEG, 5.0 * od, v),
        ),
        speed=1.0,
        speed_fluctuation=0.06,
        speed_interval=6.0,
        accel=0.3,
        static_start=10.0,
        static_end=10.0,
        roll0=0.1,
        roll_wander=0.01,
        imu_grade="industrial",
        imu_rate_hz=200.0,
        odo_rate_hz=50.0,
        odo_tick=0.002,
        odo_scale_sigma=0.003,
        odo_slip_interval=25.0,
        mag_enabled=False,
        marker_spacing=125.0,
        tags=("issue18", "test_pipe", "bends"),
    )


def _strain_span() -> Scenario:
    d, od = 0.889, 0.914  # 36" pipe: bore and outer diameter
    return Scenario(
        name="strain_span",
        pipe_seed=6,
        description=(
            "Strain span (issue 18): 200 m of straight 36 in pipe (0.889 m bore, 0.914 m outer "
            "diameter) with two local ground-movement features over 20 m each: a settlement "
            "(vertical sag, 3.4 cm deep, minimum radius 300 m, peak bending strain 0.152 %, "
            "over the 0.125 % threshold) at 80-100 m and a lateral shift (1 cm, minimum "
            "radius 1000 m, 0.046 %) at 140-160 m; tactical MEMS IMU, odometer, markers every "
            "100 m, no magnetometer, about 1.5 m/s."
        ),
        lat=47.50 * DEG,
        lon=8.50 * DEG,
        alt=420.0,
        azimuth=135.0 * DEG,
        length=200.0,
        pipe_diameter=d,
        pipe_outer_diameter=od,
        features=(
            Sag(80.0, 20.0, 0.033774, "v"),  # minimum radius 300 m
            Sag(140.0, 20.0, 0.010132, "h"),  # minimum radius 1000 m
        ),
        speed=1.5,
        speed_fluctuation=0.06,
        speed_interval=6.0,
        accel=0.3,
        static_start=10.0,
        static_end=10.0,
        roll0=0.0,
        roll_wander=0.01,
        imu_grade="tactical",
        imu_rate_hz=200.0,
        odo_rate_hz=50.0,
        odo_tick=0.005,
        odo_scale_sigma=0.005,
        odo_slip_interval=30.0,
        mag_enabled=False,
        marker_spacing=100.0,
        tags=("issue18", "test_pipe", "strain"),
    )


_REGISTRY = {
    "drag180": _drag180,
    "sag104": lambda: _sag104(0.2, "sag104"),
    "sag104_deep": lambda: _sag104(0.415, "sag104_deep"),
    "undulation90": _undulation90,
    "field10k": lambda: _field10k(1000.0, "field10k"),
    "field10k_sparse": lambda: _field10k(2500.0, "field10k_sparse"),
    "demo": _demo,
    "bends_test": _bends_test,
    "strain_span": _strain_span,
}


def scenario_names() -> list[str]:
    """Names of the built-in scenarios."""
    return list(_REGISTRY)


def get_scenario(name: str) -> Scenario:
    """The built-in scenario ``name``; ValueError naming the valid ones otherwise."""
    try:
        factory = _REGISTRY[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown scenario {name!r}; choose one of {', '.join(scenario_names())}"
        ) from None
    return factory()
