"""A stop is claimed only where the odometer's count can see one (filter.planner)."""

from collections import defaultdict

import numpy as np
from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.ingest import STOP_MARGIN_S, Inbox
from pipe_nav_core.filter.odometer_resolution import OdometerResolution
from pipe_nav_core.filter.planner import epoch_inputs, plan
from pipe_nav_core.types import MagSamples, OdometerSamples

TICK = 0.01  # m per count
STOP_SPEED = 0.002  # m/s, the configured stop threshold


def _distance(t):
    """True distance (m) at t (s): at rest to 5 s, 0.3 m/s^2 to 0.6 m/s at 7 s, cruise to
    9.065 s, -0.3 m/s^2 to rest at 11.065 s (2.439 m: 9 mm past a count), at rest to 16 s."""
    t = np.asarray(t, dtype=np.float64)
    a = 0.3
    d = np.where(t > 5.0, 0.5 * a * (np.minimum(t, 7.0) - 5.0) ** 2, 0.0)
    d = d + np.where(t > 7.0, 0.6 * (np.minimum(t, 9.065) - 7.0), 0.0)
    u = np.clip(t - 9.065, 0.0, 2.0)
    return d + 0.6 * u - 0.5 * a * u**2


def _speed(t):
    return np.gradient(_distance(t), t)


def _inbox(t_last, horizon):
    """An inbox holding 200 Hz IMU samples and a 50 Hz, 1 cm count up to t_last (s)."""
    ib = Inbox(NavConfig(), defaultdict(int), None)
    t_imu = np.arange(0.0, t_last + 1e-9, 0.005)
    t_odo = np.arange(0.0, t_last + 1e-9, 0.02)
    count = np.floor(_distance(t_odo) / TICK + 1e-9) * TICK
    odo = OdometerSamples(t_odo, count, np.zeros(len(t_odo)))
    z = np.zeros((len(t_imu), 3))
    ib.add(t_imu, z, z + [0.0, 0.0, 9.8], odo, MagSamples(np.empty(0), np.empty((0, 3))), [],
           horizon)  # fmt: skip
    return ib


def _epochs(ib):
    ends, _, still = plan(ib, 0.0, 0.1, None, STOP_SPEED)
    inp = epoch_inputs(ib, 0.0, ends, np.empty((0, 2)), OdometerResolution(TICK), still)
    t_end = ib.imu_t[ends]
    return np.r_[0.0, t_end[:-1]], t_end, inp


def test_a_pig_creeping_under_one_count_is_not_stopped():
    t_start, t_end, inp = _epochs(_inbox(16.0, np.inf))
    fine = np.linspace(0.0, 16.0, 160001)
    moving = np.array([np.abs(_speed(fine)[(fine >= a) & (fine <= b)]).max() > STOP_SPEED
                       for a, b in zip(t_start, t_end, strict=True)])  # fmt: skip
    # the case in point: epochs where the pig moves and the count stood still over them and
    # the epoch before (the old test, speed under the threshold twice, took them for stops)
    count = np.interp(np.r_[0.0, t_end], inp.imu_t, inp.s_odo)  # readings at the ends
    quiet = (np.diff(count) == 0) & (np.diff(count, prepend=count[0])[:-1] == 0)
    assert (moving & quiet).sum() >= 3
    # no epoch of the moving pig is still, and every epoch of the rests is, but for the
    # margin to the count's last change before it and to its first after (and the log's start)
    assert not (inp.still & moving).any()
    last_count = 11.065 - np.sqrt(2.0 * 0.009 / 0.3)  # the count's last change, s
    rest = ((t_start >= STOP_MARGIN_S) & (t_end <= 5.0 - STOP_MARGIN_S)) | (
        t_start >= last_count + STOP_MARGIN_S
    )
    assert rest.sum() >= 80 and inp.still[rest].all()


def test_an_epoch_still_so_far_waits_for_the_count_after_it():
    # the data in up to 4 s, the pig at rest: the epochs wait for the readings 0.5 s after
    # them, which decide whether they are stops
    _, t_end, inp = _epochs(_inbox(4.0, 4.0))
    assert 4.0 - STOP_MARGIN_S - 0.1 < t_end[-1] <= 4.0 - STOP_MARGIN_S + 1e-9
    # up to 8 s, the pig moving since 5 s: its epochs do not wait
    _, t_moving, inp_moving = _epochs(_inbox(8.0, 8.0))
    assert t_moving[-1] > 8.0 - 0.1 - 1e-9
    # the same stops as with the whole log in
    _, _, inp_all = _epochs(_inbox(16.0, np.inf))
    for part in (inp, inp_moving):
        assert np.array_equal(part.still, inp_all.still[: len(part.still)])
