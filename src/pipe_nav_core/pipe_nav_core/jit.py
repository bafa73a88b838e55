"""Compiled numeric kernels: one place that decides how numba compiles them."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from numba import njit

_PACKAGE = Path(__file__).resolve().parent


def _package_stamp() -> str:
    """A digest of every source file of the package (name, mtime, size). numba checks a cached
    kernel against its own file only, but the kernels call one another across modules: a
    kernel must be recompiled when any of them changes."""
    h = hashlib.sha256()
    for p in sorted(_PACKAGE.rglob("*.py")):
        st = p.stat()
        h.update(f"{p.relative_to(_PACKAGE)}:{st.st_mtime_ns}:{st.st_size};".encode())
    return h.hexdigest()


def _install_package_locators() -> None:
    """Cache locators for this package's kernels whose source stamp is the package's
    (:func:`_package_stamp`): in the package's __pycache__, else in the user's cache
    directory. Other numba users are not affected. If numba's internals differ from what
    this expects, its own per-file locators stay in use."""
    try:
        from numba.core import caching
    except ImportError:  # pragma: no cover
        return
    stamp = _package_stamp()

    def mixin(base: type) -> type:
        class Locator(base):  # type: ignore[misc, valid-type]
            def get_source_stamp(self) -> str:
                return stamp

            @classmethod
            def from_function(cls, py_func: Callable[..., Any], py_file: str) -> Any:
                if not Path(py_file).resolve().is_relative_to(_PACKAGE):
                    return None
                return super().from_function(py_func, py_file)

        Locator.__name__ = f"PipeNav{base.__name__}"
        return Locator

    try:
        impl = getattr(caching, "CacheImpl", None) or caching._CacheImpl
        bases = (caching.InTreeCacheLocator, caching.UserWideCacheLocator)
        ours = [mixin(b) for b in bases]
        impl._locator_classes = [*ours, *impl._locator_classes]
    except AttributeError:  # pragma: no cover
        return


if not os.environ.get("NUMBA_CACHE_LOCATOR_CLASSES"):
    _install_package_locators()


def kernel(func: Callable[..., Any] | None = None, *, nogil: bool = False) -> Any:
    """func compiled with numba, cached on disk where numba finds a writable cache directory
    (next to the source file, ~/.cache/numba or NUMBA_CACHE_DIR) and recompiled whenever any
    source file of the package changes, else compiled in every process. ``@kernel`` or
    ``@kernel(nogil=True)`` (the compiled code releases the GIL: it can run in a thread while
    the caller works).

    error_model="numpy": a zero interval gives inf/nan as in numpy, not ZeroDivisionError.
    """
    if func is None:
        return lambda f: kernel(f, nogil=nogil)
    try:
        return njit(cache=True, error_model="numpy", nogil=nogil)(func)
    except RuntimeError:  # "cannot cache function ...: no locator available"
        return njit(error_model="numpy", nogil=nogil)(func)
