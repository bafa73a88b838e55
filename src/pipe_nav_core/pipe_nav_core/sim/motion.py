"""Pig motion along the pipe: chainage s(t) and roll angle about the pipe axis phi(t).

The speed ds/dt is a :class:`~.profiles.RampProfile` in time (levels joined by quintic
transitions), so s(t) is C3 and the acceleration C1: the pig rests in the launch trap, accelerates,
cruises with random speed changes, stops (and surges away again) at chosen chainages, and comes to
rest exactly at the end of the pipe in the receive trap. The roll is a function of the chainage
(the pig rolls as it moves, never at rest): a slow random wander plus pulses that make whole turns
at a few rad/s. Functions take time in s unless stated.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pipe_nav_core.sim.profiles import RampProfile

FloatArray = NDArray[np.float64]

_PEAK = 1.875  # max of dS/dx for the quintic smootherstep


@dataclass(frozen=True)
class Stop:
    """A stop of the pig: chainage m where it halts, duration s it stays there."""

    chainage: float
    duration: float


@dataclass(frozen=True)
class RollTurn:
    """A roll episode: starting at chainage m, ``turns`` whole turns (sign = direction,
    positive = right side down), peak roll rate ``rate`` rad/s."""

    chainage: float
    turns: float
    rate: float


@dataclass(frozen=True)
class SpeedParams:
    """Speed-profile parameters.

    cruise: m/s mean speed; fluctuation: relative one-sigma of the cruise speed levels;
    interval: s, mean time between speed changes; accel: m/s^2, peak acceleration of starts,
    stops and speed changes; surge_factor: speed after a stop relative to cruise;
    surge_duration: s; min_transition: s, shortest speed transition.
    """

    cruise: float
    fluctuation: float = 0.08
    interval: float = 8.0
    accel: float = 0.3
    surge_factor: float = 1.6
    surge_duration: float = 4.0
    min_transition: float = 0.6


def build_speed_profile(
    length: float,
    t_move: float,
    params: SpeedParams,
    stops: Sequence[Stop],
    rng: np.random.Generator,
) -> RampProfile:
    """Speed profile (m/s versus s) that starts moving at ``t_move`` and ends at rest at chainage
    ``length`` exactly, halting at each stop's chainage for its duration."""
    if params.cruise <= 0.0 or params.accel <= 0.0:
        raise ValueError("cruise speed and acceleration must be positive")
    starts: list[float] = []
    durs: list[float] = []
    levels: list[float] = [0.0]
    pending = sorted((st for st in stops if 0.0 < st.chainage < length), key=lambda x: x.chainage)
    margin = 0.02 * params.cruise

    def ramp(dv: float, accel: float = params.accel) -> float:
        return max(params.min_transition, _PEAK * abs(dv) / accel)

    def level() -> float:
        v = params.cruise * (1.0 + params.fluctuation * rng.standard_normal())
        return float(np.clip(v, 0.3 * params.cruise, 2.0 * params.cruise))

    def add(t0: float, dur: float, to: float) -> None:
        starts.append(t0)
        durs.append(dur)
        levels.append(to)

    t, s, v = t_move, 0.0, 0.0
    forced_hold: float | None = None
    target = level()
    while True:
        # (Re)start from rest: choose a reachable level before the next stop.
        nxt = pending[0].chainage if pending else length
        if v == 0.0:
            for _ in range(60):
                tr = ramp(target, 2.0 * params.accel if forced_hold else params.accel)
                if s + 0.5 * target * tr + 0.5 * target * ramp(target) + margin < nxt:
                    break
                target *= 0.7
            else:
                raise ValueError("pipe section too short for the speed profile")
            add(t, tr, target)
            t += tr
            s += 0.5 * target * tr
            v = target
        hold = (
            forced_hold
            if forced_hold is not None
            else float(np.clip(rng.exponential(params.interval), 0.5, 4.0 * params.interval))
        )
        forced_hold = None
        new = level()
        tr = ramp(new - v)
        s_after = s + v * hold + 0.5 * (v + new) * tr
        if s_after + 0.5 * new * ramp(new) + margin < nxt:
            t += hold
            add(t, tr, new)
            t += tr
            s, v = s_after, new
            continue
        # Stop exactly at the next stop (or the end) from the current level.
        tst = ramp(v)
        hold = (nxt - s - 0.5 * v * tst) / v
        if hold < 0.0:  # pragma: no cover - prevented by the look-ahead above
            raise ValueError("internal error: cannot stop at the requested chainage")
        t += hold
        add(t, tst, 0.0)
        t += tst
        s, v = nxt, 0.0
        if not pending:
            break
        t += pending.pop(0).duration
        target = params.cruise * params.surge_factor
        forced_hold = params.surge_duration
    return RampProfile(starts, durs, levels, u0=t_move)


def build_roll_profiles(
    length: float,
    speed: RampProfile,
    cruise: float,
    wander_sigma: float,
    wander_interval: float,
    turns: Sequence[RollTurn],
    rng: np.random.Generator,
    max_roll_accel: float = 6.0,
) -> tuple[RampProfile, RampProfile]:
    """Roll profiles over the chainage, in rad per metre travelled (the pig rolls as it moves, so
    it never rolls while it rests in a trap or at a stop).

    Slow wander: levels N(0, wander_sigma / cruise) rad/m (wander_sigma in rad/s at the cruise
    speed, m/s), held about wander_interval s of cruise travel, with smooth transitions.
    Whole turns: for each RollTurn a pulse starting at its chainage (delayed if it would overlap
    the previous one) whose peak is its rate (rad/s) at the speed the pig has when it gets there
    and whose integral is 2 pi turns. max_roll_accel: rad/s^2, sets the pulse ramps.
    Returns (wander, turns) RampProfiles with u in m.
    """
    starts: list[float] = []
    durs: list[float] = []
    levels: list[float] = [0.0]
    if wander_sigma > 0.0 and wander_interval > 0.0:
        step = wander_interval * cruise
        u = rng.uniform(0.0, step)
        while True:
            tr = rng.uniform(1.0, 3.0) * cruise
            if u + tr >= length:
                break
            starts.append(u)
            durs.append(tr)
            levels.append(float(rng.normal(0.0, wander_sigma / cruise)))
            u += tr + max(0.5 * cruise, rng.exponential(step))
    wander = RampProfile(starts, durs, levels)

    starts, durs, levels = [], [], [0.0]
    u_free = 0.0
    t_lo, t_hi = speed.u0, speed.end
    for rt in sorted(turns, key=lambda r: r.chainage):
        if rt.turns == 0.0 or rt.rate <= 0.0:
            continue
        a = max(float(rt.chainage), u_free)
        t_a = float(speed.invert_integral(a, t_lo, t_hi))
        v = max(float(speed.value(t_a)), 0.3 * cruise)
        angle = 2.0 * math.pi * abs(rt.turns)
        k = rt.rate / v  # rad/m
        lr = max(0.2, _PEAK * rt.rate / max_roll_accel) * v  # m
        if k * lr > angle:  # too few turns for that peak: lower the peak
            k = angle / lr
        hold = angle / k - lr
        if a + 2.0 * lr + hold >= length:
            raise ValueError(f"roll turn at chainage {rt.chainage} m does not fit before the end")
        starts += [a, a + lr + hold]
        durs += [lr, lr]
        levels += [math.copysign(k, rt.turns), 0.0]
        u_free = a + 2.0 * lr + hold + 0.5 * v
    pulses = RampProfile(starts, durs, levels)
    return wander, pulses


class PigMotion:
    """Chainage and roll of the pig versus time.

    speed: RampProfile of ds/dt (m/s) whose integral from t_move is s (m); roll0: rad at rest in
    the launch trap; roll_profiles: RampProfiles over the chainage of the roll per metre
    travelled (rad/m), summed; length: m (s is clipped to it); t_begin, t_end: s, the run's time
    span (the pig rests before t_move and after t_arrive).
    """

    def __init__(
        self,
        speed: RampProfile,
        roll0: float,
        roll_profiles: Sequence[RampProfile],
        length: float,
        t_begin: float,
        t_end: float,
    ) -> None:
        self.speed = speed
        self.roll0 = float(roll0)
        self.roll_profiles = list(roll_profiles)
        self.length = float(length)
        self.t_begin = float(t_begin)
        self.t_end = float(t_end)
        self.t_move = float(speed.u0)
        self.t_arrive = float(speed.end)

    def chainage(self, t: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(s m, ds/dt m/s, d2s/dt2 m/s^2) at times t (s)."""
        t = np.asarray(t, dtype=np.float64)
        s = np.clip(self.speed.integral(t), 0.0, self.length)
        s = np.where(t <= self.t_move, 0.0, s)
        return s, self.speed.value(t), self.speed.deriv(t)

    def roll(
        self, t: ArrayLike, s: FloatArray | None = None, sd: FloatArray | None = None
    ) -> tuple[FloatArray, FloatArray]:
        """(roll rad, roll rate rad/s) at times t (s); roll about the body x axis, right side
        down positive. The rate is (roll per metre) * ds/dt. s, sd: the chainage (m) and speed
        (m/s) at t if already known."""
        if s is None or sd is None:
            s, sd, _ = self.chainage(t)
        phi = np.full(s.shape, self.roll0)
        per_m = np.zeros(s.shape)
        for p in self.roll_profiles:
            phi = phi + p.integral(s)
            per_m = per_m + p.value(s)
        return phi, per_m * sd

    def time_at_chainage(self, s: ArrayLike) -> FloatArray:
        """First time (s) at which the pig reaches chainage s (m); t_move for s <= 0 and the
        arrival time for s >= length."""
        s = np.asarray(s, dtype=np.float64)
        t = self.speed.invert_integral(s, self.t_move, self.t_arrive)
        t = np.where(s <= 0.0, self.t_move, t)
        return np.where(s >= self.length, self.t_arrive, t)
