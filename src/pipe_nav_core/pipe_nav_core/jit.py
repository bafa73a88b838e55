"""Compiled numeric kernels: one place that decides how numba compiles them."""

from __future__ import annotations

import ast
import hashlib
import os
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path
from typing import Any

from numba import njit

_PACKAGE = Path(__file__).resolve().parent


def _module_files() -> dict[str, Path]:
    """Dotted module name (relative to the package; "" for its __init__) -> source file."""
    out = {}
    for p in _PACKAGE.rglob("*.py"):
        if "__pycache__" in p.parts:
            continue
        parts = p.relative_to(_PACKAGE).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules that module ``name`` imports, anywhere in its source."""
    here = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = here[: len(here) - node.level + 1] if node.level > 1 else here
                mod = ".".join([*base, *([node.module] if node.module else [])])
            elif (node.module or "").split(".")[0] == _PACKAGE.name:
                mod = node.module.partition(".")[2]  # type: ignore[union-attr]
            else:
                continue
            found.update(
                m
                for m in (mod, *(f"{mod}.{a.name}".strip(".") for a in node.names))
                if m in modules
            )
        elif isinstance(node, ast.Import):
            for a in node.names:
                head, _, rest = a.name.partition(".")
                if head == _PACKAGE.name and rest in modules:
                    found.add(rest)
    return found


def _kernel_sources() -> list[Path]:
    """The source files a compiled kernel can depend on: the modules that define kernels and
    every package module they import, transitively (a kernel sees only other kernels and the
    globals of its module, frozen at compile time). The command line, I/O, simulator, plots
    and the smoother's orchestration are outside: editing them recompiles nothing."""
    modules = _module_files()
    todo = [m for m, p in modules.items() if "@kernel" in p.read_text(encoding="utf-8")]
    seen = set(todo)
    while todo:
        m = todo.pop()
        new = _imports(m, modules[m], modules) - seen
        seen |= new
        todo.extend(new)
    return sorted(modules[m] for m in seen)


@lru_cache(maxsize=1)
def _package_stamp() -> str:
    """A digest of the source files the kernels depend on (:func:`_kernel_sources`: name,
    mtime, size). numba checks a cached kernel against its own file only, but the kernels call
    one another across modules: a kernel must be recompiled when any of them changes. The list
    of those files is itself cached beside the package, keyed by every file's (name, mtime,
    size), so a process pays for the import analysis only after an edit."""

    def digest(paths: list[Path]) -> str:
        h = hashlib.sha256()
        for p in paths:
            st = p.stat()
            h.update(f"{p.relative_to(_PACKAGE)}:{st.st_mtime_ns}:{st.st_size};".encode())
        return h.hexdigest()

    key = digest(sorted(_module_files().values()))
    memo = _PACKAGE / "__pycache__" / "kernel_sources.txt"
    try:
        stored_key, *names = memo.read_text(encoding="utf-8").split("\n")
        if stored_key == key:
            return digest([_PACKAGE / n for n in names])
    except (OSError, ValueError):
        pass
    sources = _kernel_sources()
    try:
        memo.parent.mkdir(exist_ok=True)
        text = "\n".join([key, *(p.relative_to(_PACKAGE).as_posix() for p in sources)])
        tmp = memo.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(memo)
    except OSError:  # a read-only install: analysed in every process
        pass
    return digest(sources)


def _install_package_locators() -> None:
    """Cache locators for this package's kernels whose source stamp is the package's
    (:func:`_package_stamp`): in the package's __pycache__, else in the user's cache
    directory. Other numba users are not affected. If numba's internals differ from what
    this expects, its own per-file locators stay in use."""
    try:
        from numba.core import caching
    except ImportError:  # pragma: no cover
        return

    def mixin(base: type) -> type:
        class Locator(base):  # type: ignore[misc, valid-type]
            def get_source_stamp(self) -> str:
                return _package_stamp()

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
