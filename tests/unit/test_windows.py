"""pipe_nav_core.products.windows: the running median, maximum and symmetric correlation equal
scipy.ndimage's (mode="nearest") bit for bit, on random series, ties and short series."""

from __future__ import annotations

import numpy as np
import pytest
from pipe_nav_core.products.windows import correlate, running_maximum, running_median
from scipy import ndimage


def _series(seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(n).cumsum()
    x[rng.integers(0, n, n // 5)] = 0.5  # ties
    return x


@pytest.mark.parametrize("n", [1, 2, 7, 50, 3001])
@pytest.mark.parametrize("size", [1, 3, 9, 201])
def test_running_median_equals_scipy(n: int, size: int) -> None:
    x = _series(n + size, n)
    ref = ndimage.median_filter(x, size=size, mode="nearest")
    assert np.array_equal(running_median(x, size), ref)


def test_running_median_of_columns() -> None:
    x = np.column_stack([_series(1, 500), _series(2, 500), _series(3, 500)])
    ref = ndimage.median_filter(x, size=(21, 1), mode="nearest")
    out = running_median(x, 21)
    assert out.shape == x.shape
    assert np.array_equal(out, ref)


@pytest.mark.parametrize("n", [1, 5, 400])
@pytest.mark.parametrize("size", [1, 3, 41, 801])
def test_running_maximum_equals_scipy(n: int, size: int) -> None:
    x = _series(7 * n + size, n)
    ref = ndimage.maximum_filter1d(x, size=size, mode="nearest")
    assert np.array_equal(running_maximum(x, size), ref)


@pytest.mark.parametrize("half", [1, 6, 40])
def test_correlate_equals_scipy_bit_for_bit(half: int) -> None:
    t = np.arange(-half, half + 1) * 0.05
    g = np.exp(-0.5 * (t / 0.07) ** 2)
    g -= g.mean()
    g /= np.linalg.norm(g)
    x = np.column_stack([_series(4, 1000), _series(5, 1000)]) * 1e-7
    ref = ndimage.correlate1d(x, g, axis=0, mode="nearest")
    assert np.array_equal(correlate(x, g), ref)
    assert np.array_equal(correlate(x[:, 0], g), ref[:, 0])


def test_windows_refuse_even_sizes_and_asymmetric_weights() -> None:
    with pytest.raises(ValueError, match="odd number of samples, not 4"):
        running_median(np.zeros(10), 4)
    with pytest.raises(ValueError, match="odd"):
        running_maximum(np.zeros(10), 0)
    with pytest.raises(ValueError, match="symmetric"):
        correlate(np.zeros(10), np.array([1.0, 2.0, 3.0]))
