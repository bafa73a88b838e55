"""The IMU noise model from the data (``imu_grade: auto``).

A run says which IMU recorded it: its static spans (odometer still) show the sensor's white
noise, a long one its bias instability (Allan deviation), and the Imu messages may declare
their per-sample variance. :func:`choose` turns those into a model: the named grade
(sensors.GRADES) whose white-noise figures are nearest in log ratio, kept as it is when the
measured figures lie within ``FIT_FACTOR`` of it; else the quietest grade whose gyro noise is not
below the measured one's by more than that factor (bias figures grow with the gyro's class, so
this errs towards the wider model), with the measured white noise (and bias instability, where
measured) as overrides. :func:`wider` gives the next noisier named
grade, for a refit when the smoothed run still shows the model does not fit.

Units: gyro densities rad/sqrt(s), accelerometer m/s/sqrt(s), bias instabilities rad/s and
m/s^2, times s (bag stamps).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.config import AUTO_GRADE, NavConfig
from pipe_nav_core.model.sensors import GRADES, ImuSpec
from pipe_nav_core.types import ImuSamples, SensorLog

MIN_STATIC_S = 2.0  # s: shortest span of a still odometer counted as static
STILL_M = 0.002  # m: odometer change within a static span
EDGE_S = 1.0  # s left out at each end of a static span (the pig settles, or starts to move)
MIN_ALLAN_S = 60.0  # s: shortest static span whose Allan deviation is used
MIN_SAMPLES = 200  # static IMU samples needed to measure the white noise
REST_END_S = 0.25  # s left out before the end of the live filter's initial rest
MIN_REST_SAMPLES = 100  # the same for the live filter's initial rest
FIT_FACTOR = 1.5  # a named grade fits when both white-noise figures are within this factor
NOISIER = ("tactical", "industrial", "consumer")  # named grades, quietest white noise first

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
    # a span runs from its first reading to the last within STILL_M of it. Where the next
    # reading is further than that, the span is that one reading, which takes no time (kept
    # only at the start, or with min_s 0), and so on: the loop jumps to the next step within
    # STILL_M (a reading per step took 0.13 s at 10 km, nearly all of them moving)
    n = len(odo.t)
    far = np.abs(np.diff(odo.distance)) > STILL_M  # far[i]: reading i + 1 from reading i
    near = np.flatnonzero(~far).tolist()
    d, t = odo.distance.tolist(), odo.t.tolist()  # Python floats
    start = 0
    while start < n:
        i = start + 1
        while i < n and not abs(d[i] - d[start]) > STILL_M:
            i += 1
        t0, t1 = t[start], t[i - 1]
        if start == 0:
            t0 = min(t0, float(imu_t[0]))  # rest before the first odometer message
        a, b = max(t0, float(imu_t[0])), min(t1, float(imu_t[-1]))
        if b - a >= min_s:
            spans.append((a, b))
        start = i
        if min_s > 0 and start < n - 1 and far[start]:
            k = bisect.bisect_left(near, start)
            start = near[k] if k < len(near) else n
    return spans


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


def measured_noise(
    log: SensorLog,
    spans: Sequence[tuple[float, float]],
    edges_s: tuple[float, float] = (EDGE_S, EDGE_S),
    min_samples: int = MIN_SAMPLES,
) -> dict[str, Any]:
    """IMU noise in the static spans: per-axis white-noise densities ``gyro_arw`` and
    ``accel_vrw`` from the scatter of the samples about each span's mean (a sample is the mean
    rate over its interval, so its scatter is density / sqrt(dt)) and, for the longest span of
    MIN_ALLAN_S or more, the Allan-deviation floor over 0.664 (``gyro_bias_instability``,
    ``accel_bias_instability``). ``edges_s``: s left out at the start and end of each span.
    {} with fewer than ``min_samples`` static samples."""
    imu = log.imu
    if len(imu.t) < 3 or not spans:
        return {}
    dt = float(np.median(np.diff(imu.t)))
    resid_g, resid_a = [], []
    longest: tuple[float, float] | None = None
    for a, b in spans:
        sel = (imu.t >= a + edges_s[0]) & (imu.t <= b - edges_s[1])
        if sel.sum() < 3:
            continue
        resid_g.append(imu.gyro[sel] - imu.gyro[sel].mean(axis=0))
        resid_a.append(imu.accel[sel] - imu.accel[sel].mean(axis=0))
        if longest is None or b - a > longest[1] - longest[0]:
            longest = (a, b)
    g = np.concatenate(resid_g) if resid_g else np.zeros((0, 3))
    f = np.concatenate(resid_a) if resid_a else np.zeros((0, 3))
    if len(g) < min_samples or not (dt > 0.0):
        return {}
    out: dict[str, Any] = {
        "samples": len(g),
        "sample_period_s": dt,
        "gyro_arw": (g.std(axis=0) * math.sqrt(dt)).tolist(),
        "accel_vrw": (f.std(axis=0) * math.sqrt(dt)).tolist(),
    }
    if longest is not None and longest[1] - longest[0] - sum(edges_s) >= MIN_ALLAN_S:
        sel = (imu.t >= longest[0] + edges_s[0]) & (imu.t <= longest[1] - edges_s[1])
        _, dev_g = allan_deviation(imu.gyro[sel], dt)
        _, dev_a = allan_deviation(imu.accel[sel], dt)
        out["gyro_bias_instability"] = (dev_g.min(axis=0) / 0.664).tolist()
        out["accel_bias_instability"] = (dev_a.min(axis=0) / 0.664).tolist()
    return out


def _log_distance(arw: float, vrw: float, spec: ImuSpec) -> float:
    return abs(math.log(arw / spec.gyro_arw)) + abs(math.log(vrw / spec.accel_vrw))


def nearest_grade(noise: dict[str, Any]) -> str | None:
    """The named grade whose white-noise figures (gyro ARW, accel VRW) are nearest the
    measured ones in log ratio; None without a usable measurement."""
    if not noise:
        return None
    arw, vrw = float(np.mean(noise["gyro_arw"])), float(np.mean(noise["accel_vrw"]))
    if not (arw > 0.0 and vrw > 0.0):
        return None
    return min(GRADES.values(), key=lambda s: _log_distance(arw, vrw, s)).name


@dataclass
class ImuModelChoice:
    """What :func:`choose` decided: the settings to smooth with, the grade (or
    ``"<grade>+measured"``), the figures it rests on and one line of why."""

    config: NavConfig
    grade: str
    reason: str
    measured: dict[str, Any] = field(default_factory=dict)


def _from_declared(declared: dict[str, Any], dt: float) -> dict[str, Any]:
    gv = np.asarray(declared.get("gyro_variance", []), dtype=float)
    av = np.asarray(declared.get("accel_variance", []), dtype=float)
    if len(gv) != 3 or len(av) != 3 or not (np.all(gv > 0) and np.all(av > 0)) or dt <= 0:
        return {}
    return {"gyro_arw": np.sqrt(gv * dt).tolist(), "accel_vrw": np.sqrt(av * dt).tolist()}


def choose(
    log: SensorLog, config: NavConfig, declared: dict[str, Any] | None = None
) -> ImuModelChoice:
    """The IMU model for ``config`` with ``imu_grade: auto`` (returned unchanged otherwise):
    from the static spans' noise, else from the Imu messages' declared variances, else the
    industrial grade with a reason saying nothing measured it."""
    if config.imu_grade != AUTO_GRADE:
        return ImuModelChoice(config, config.imu_grade, "given in the settings")
    noise = measured_noise(log, static_spans(log))
    dt = float(np.median(np.diff(log.imu.t))) if len(log.imu.t) > 1 else 0.0
    return _model(config, noise, "measured in the static spans", declared, dt)


def choose_at_rest(
    t: FloatArray,
    gyro: FloatArray,
    accel: FloatArray,
    config: NavConfig,
    declared: dict[str, Any] | None = None,
) -> ImuModelChoice:
    """:func:`choose` for the live filter, which knows only the start of the initial rest
    when it aligns (``static_alignment_s``, 2 s by default): IMU samples (times s, gyro rad/s,
    specific force m/s^2, imu_link) of the rest, the last REST_END_S before a move left out.
    200 samples measure a noise density to about 5 %."""
    if config.imu_grade != AUTO_GRADE:
        return ImuModelChoice(config, config.imu_grade, "given in the settings")
    log = SensorLog(imu=ImuSamples(t, gyro, accel))
    spans = [(float(t[0]), float(t[-1]))] if len(t) > 1 else []
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    noise = measured_noise(log, spans, (0.0, REST_END_S), MIN_REST_SAMPLES)
    return _model(config, noise, "measured at the initial rest", declared, dt)


def _model(
    config: NavConfig,
    noise: dict[str, Any],
    source: str,
    declared: dict[str, Any] | None,
    dt: float,
) -> ImuModelChoice:
    if not noise and declared:
        noise, source = _from_declared(declared, dt), "declared by the Imu messages"
    grade = nearest_grade(noise)
    if grade is None:
        return ImuModelChoice(
            replace(config, imu_grade="industrial"),
            "industrial",
            "no static span and no declared noise: the industrial grade, unmeasured",
        )
    spec = GRADES[grade]
    arw, vrw = float(np.mean(noise["gyro_arw"])), float(np.mean(noise["accel_vrw"]))
    figures = (
        f"gyro {math.degrees(arw) * 60:.3g} deg/sqrt(h), accel {vrw * 60:.3g} m/s/sqrt(h) {source}"
    )
    fits = (
        max(arw / spec.gyro_arw, spec.gyro_arw / arw) <= FIT_FACTOR
        and max(vrw / spec.accel_vrw, spec.accel_vrw / vrw) <= FIT_FACTOR
    )
    if fits:
        return ImuModelChoice(
            replace(config, imu_grade=grade), grade, f"{figures}: fits {grade}", noise
        )
    grade = next((n for n in NOISIER if GRADES[n].gyro_arw * FIT_FACTOR >= arw), NOISIER[-1])
    spec = GRADES[grade]
    overrides = dict(config.imu_overrides)
    overrides.update(gyro_arw=arw, accel_vrw=vrw)
    for key in ("gyro_bias_instability", "accel_bias_instability"):
        if key in noise:
            overrides[key] = max(float(np.max(noise[key])), getattr(spec, key))
    return ImuModelChoice(
        replace(config, imu_grade=grade, imu_overrides=overrides),
        f"{grade}+measured",
        f"{figures}: no grade fits; {grade} with the measured noise",
        noise,
    )


def wider(choice: ImuModelChoice) -> ImuModelChoice | None:
    """The next noisier named grade after ``choice`` (its overrides dropped), or None when it
    is the noisiest already."""
    name = choice.config.imu_grade
    if name not in NOISIER or name == NOISIER[-1]:
        return None
    nxt = NOISIER[NOISIER.index(name) + 1]
    return ImuModelChoice(
        replace(choice.config, imu_grade=nxt, imu_overrides={}),
        nxt,
        f"{choice.grade} did not fit the run; refitted with {nxt}",
        choice.measured,
    )
