"""Compiled numeric kernels: one place that decides how numba compiles them."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from numba import njit


def kernel(func: Callable[..., Any]) -> Callable[..., Any]:
    """func compiled with numba, cached on disk where numba finds a writable cache directory
    (next to the source file, ~/.cache/numba or NUMBA_CACHE_DIR), else compiled in every
    process.

    error_model="numpy": a zero interval gives inf/nan as in numpy, not ZeroDivisionError.
    """
    try:
        return njit(cache=True, error_model="numpy")(func)
    except RuntimeError:  # "cannot cache function ...: no locator available"
        return njit(error_model="numpy")(func)
