"""The flat state vector the measurement kernels take, and the measurements' registration."""

import inspect
import re

import numpy as np
import pytest
from measurement_check import MODES, random_state
from pipe_nav_core.filter import epoch
from pipe_nav_core.model import measurements
from pipe_nav_core.model.state import Layout, NavState, inject_many


@pytest.mark.parametrize("mode", MODES)
def test_flat_state_vector_round_trip_and_batch_injection(mode):
    rng = np.random.default_rng(5)
    layout = Layout(mode, gyro_errors=True, accel_errors=True)
    s = random_state(rng)
    s.gm, s.am = rng.normal(0, 1e-3, (3, 3)), rng.normal(0, 1e-3, (3, 3))
    s.odoq = rng.normal(size=2)
    v = s.vector()
    np.testing.assert_array_equal(NavState.from_vector(v).vector(), v)
    dx = rng.normal(0, 1e-2, (5, layout.n))
    many = inject_many(np.stack([v] * 5), dx, layout)
    for row, d in zip(many, dx, strict=True):
        np.testing.assert_allclose(row, s.inject(d, layout).vector(), rtol=0, atol=1e-15)
    assert not np.allclose(many[0], v)  # the corrections did move the state


def test_the_registry_derives_the_epoch_updates_and_the_statistics():
    """One line (measurements.MEASUREMENTS) registers a measurement: the epoch's update
    sequence, the statistics' kinds and counters derive from it, each measurement's statistics
    at its own rows; the names are those the reports have always used."""
    regs = measurements.MEASUREMENTS
    assert [u[2] for u in measurements.UPDATES] == [m.apply for m in regs]
    for (kind, event, _), m in zip(measurements.UPDATES, regs, strict=True):
        assert measurements.KINDS[kind : kind + len(m.KINDS)] == m.KINDS
        assert measurements.COUNTERS[event : event + len(m.EVENTS)] == m.EVENTS
    assert measurements.KINDS == ("nhc", "odometer", "zupt", "zaru", "straight", "direction",
                                  "tilt", "mag", "marker")  # fmt: skip
    assert measurements.COUNTERS == ("epochs", "epochs_without_odometer", "odometer_excluded",
                                     "tilt_gated_motion", "mag_disturbed")  # fmt: skip
    assert measurements.COUNTERS[measurements.C_EPOCHS] == "epochs"
    # the epoch loops over the registry: no measurement is named in it
    src = inspect.getsource(epoch._updates.py_func)
    assert "literal_unroll(UPDATES)" in src
    names = "|".join(m.__name__.rpartition(".")[2] for m in regs)
    assert not re.search(r"\b(" + names + r")\.", src)
