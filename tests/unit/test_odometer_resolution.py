"""The odometer encoder's resolution (odometer_resolution.py): configured, or learnt from the
readings independently of how the epochs batch them."""

from __future__ import annotations

import numpy as np
from pipe_nav_core.filter.odometer_resolution import FLOOR_M, OdometerResolution
from pipe_nav_core.types import OdometerSamples


def _readings() -> OdometerSamples:
    """A 4 mm encoder read at 10 Hz: 2 or 3 counts per reading, one count once at 6 s."""
    steps = np.r_[np.zeros(5), np.tile([2.0, 3.0], 27), 1.0, np.full(40, 2.0)]
    t = 0.1 * np.arange(len(steps))
    return OdometerSamples(t, 0.004 * np.cumsum(steps), np.full(len(t), 0.1))


def test_learnt_resolution_does_not_depend_on_the_batching():
    odo = _readings()
    times = np.arange(0.05, 10.0, 0.25)
    whole = OdometerResolution(0.0).at_times(odo, times)
    one = OdometerResolution(0.0)
    single = np.array([one.at(odo, t) for t in times])
    np.testing.assert_array_equal(whole, single)
    assert whole[0] == FLOOR_M  # before any step: nothing learnt
    assert np.isclose(whole[times < 5.9], 0.008).sum() > 10  # two counts, the smallest step
    assert np.isclose(whole[-1], 0.004) and one.value == whole[-1]


def test_configured_resolution_is_used_as_it_is():
    res = OdometerResolution(0.01)
    np.testing.assert_array_equal(res.at_times(_readings(), np.array([0.0, 5.0])), [0.01, 0.01])
