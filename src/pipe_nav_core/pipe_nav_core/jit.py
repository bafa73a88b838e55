"""Compiled numeric kernels: one place that decides how they are compiled and called.

A kernel is a nopython function compiled by numba (``@kernel``). Where the installer has built
the ahead-of-time module for the current sources, or the package's prebuilt one fits them and
this machine (:mod:`pipe_nav_core.aot`; installed on the first import), a kernel called
from Python runs its AOT export and numba is not even imported; a call that no export fits
(argument types the installer never saw, or a kernel Python never called there) turns the
whole process to numba's just-in-time kernels, cached on disk (:func:`to_jit`). The results
are the same either way (the same compiled code; tested bit for bit on the sample).
``PIPE_NAV_KERNELS=jit`` makes a process use numba from the start.

Names: a kernel over a model's flat arrays ends in ``_k`` (``inject_k``, ``predict_k``,
``zero_rate_k``; private ones too: ``_ins_k``), and where a NumPy or NavState front end exists
it has the same name without it; the measurement protocol's kernels are named by their role in
every measurement module (``inputs_k``, ``apply``, ``rows``); the small algebra the kernels
share is named by what it computes (``qmul``, ``cross3``, ``inv3``).
"""

from __future__ import annotations

import ast
import hashlib
import inspect
import os
import sys
import threading
import warnings
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path
from typing import Any

from pipe_nav_core import aot

_PACKAGE = Path(__file__).resolve().parent
_PREFIX = __name__.rpartition(".")[0] + "."  # of this package's module names
# PIPE_NAV_KERNELS=jit: numba's JIT kernels from the start (no AOT module loaded or built)
FORCED_JIT = os.environ.get("PIPE_NAV_KERNELS") == "jit"


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
    seen.discard("aot")  # builds and loads the AOT module: no kernel's code depends on it
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


def fingerprint() -> dict[str, str]:
    """What a prebuilt AOT module must have been built from to serve here (aot.install_prebuilt):
    the digest of the contents of the kernels' source files and of the warm-up (which chooses
    the exports), the interpreter's extension-module suffix, and numba's, llvmlite's and
    NumPy's versions (read from their metadata: numba is not imported)."""
    import sysconfig
    from importlib import metadata

    h = hashlib.sha256()
    for p in [*_kernel_sources(), _PACKAGE / "warmup.py"]:
        h.update(f"{p.relative_to(_PACKAGE).as_posix()}:".encode())
        h.update(hashlib.sha256(p.read_bytes()).digest())
    versions = {name: metadata.version(name) for name in ("numba", "llvmlite", "numpy")}
    return {"sources": h.hexdigest(), "abi": str(sysconfig.get_config_var("EXT_SUFFIX")),
            **versions}  # fmt: skip


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


_NUMBA_READY = False


def literal_unroll(container: Any) -> Any:
    """numba's ``literal_unroll`` in a kernel: a loop over a tuple of differently typed items
    (functions, say), compiled into straight code item by item; in Python the container.
    This stand-in keeps numba unimported where the AOT kernels serve: numba's own replaces it
    in the package's modules as soon as numba is imported (:func:`_numba_njit`), before any
    kernel compiles."""
    return container


def _rebind_package(new_value: Callable[[Any], Any]) -> None:
    """In every loaded module of this package, each global ``value`` replaced by
    ``new_value(value)`` where that is another object (a kernel's callees are resolved through
    its module's globals)."""
    for name, module in list(sys.modules.items()):
        if module is not None and name.startswith(_PREFIX):
            for attr, value in list(vars(module).items()):
                new = new_value(value)
                if new is not value:
                    setattr(module, attr, new)


def _numba_njit(**options: Any) -> Any:
    """numba.njit, numba imported (and this package's cache locators installed, and its
    literal_unroll bound in the package's modules) on first use."""
    global _NUMBA_READY
    from numba import literal_unroll as numba_unroll
    from numba import njit as numba_njit

    if not _NUMBA_READY:
        if not os.environ.get("NUMBA_CACHE_LOCATOR_CLASSES"):
            _install_package_locators()
        # typing a literal_unroll over a tuple of kernels (measurements.UPDATES) unifies their
        # function types and says so; the calls stay direct, each to its own kernel
        warnings.filterwarnings("ignore", "First-class function type feature is experimental")
        stand_in = globals()["literal_unroll"]
        _rebind_package(lambda value: numba_unroll if value is stand_in else value)
        _NUMBA_READY = True
    return numba_njit(**options)


njit = _numba_njit  # what kernel() compiles with (a test may replace it)


def _compile(func: Callable[..., Any], nogil: bool, decorate: Callable[..., Any]) -> Any:
    """func as a numba dispatcher, cached on disk where numba finds a writable cache
    directory, else compiled in every process."""
    try:
        return decorate(cache=True, error_model="numpy", nogil=nogil)(func)
    except RuntimeError:  # "cannot cache function ...: no locator available"
        return decorate(error_model="numpy", nogil=nogil)(func)


class AotKernel:
    """A kernel as the AOT module serves it: each call runs the export whose argument types
    match (as numba's dispatcher picks a specialization), an array with only another layout
    copied to the layout an export takes; any other call turns the process to JIT
    (:func:`to_jit`) and runs the numba dispatcher."""

    def __init__(self, func: Callable[..., Any], nogil: bool, exports: list[aot.Loaded]) -> None:
        self.py_func = func
        self.nogil = nogil
        self.loaded = exports
        self.exports: list[aot.Export] | None = None  # with their checks, from the first call
        self.dispatcher: Any = None
        self.__name__ = func.__name__
        self.__qualname__ = func.__qualname__
        self.__module__ = func.__module__
        self.__doc__ = func.__doc__
        self.__wrapped__ = func

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if self.dispatcher is None:
            if kwargs:
                args = inspect.signature(self.py_func).bind(*args, **kwargs).args
                kwargs = {}
            exports = self.exports
            if exports is None:
                exports = self.exports = aot.checked(self.loaded)
            for check, fn, arity, _ in exports:
                if len(args) == arity and check(*args):
                    return fn(*args)
            for check, fn, arity, specs in exports:
                if len(args) == arity:
                    fitted = aot.coerced(args, specs)
                    if fitted is not None and check(*fitted):
                        return fn(*fitted)
            to_jit(f"{self.__module__}.{self.__qualname__} called with other argument types")
        return self.dispatcher(*args, **kwargs)

    def __repr__(self) -> str:
        return f"<AOT kernel {self.__module__}.{self.__qualname__}>"


_KERNELS: list[AotKernel] = []
_SWITCH = threading.Lock()
JIT_REASON: str | None = None  # why this process runs numba's JIT kernels (None: AOT)
PREBUILT_MISFIT: str | None = None  # why the package's prebuilt module was not installed here


def _load_module() -> aot.Module | None:
    """The AOT module for these sources: the module built here, else the package's prebuilt one
    where it fits (installed first), else None."""
    if FORCED_JIT:
        return None
    global PREBUILT_MISFIT
    stamp = _package_stamp()
    module = aot.load(_PACKAGE, stamp)
    if module is None:
        try:
            PREBUILT_MISFIT = aot.install_prebuilt(_PACKAGE, stamp, fingerprint())
        except Exception as exc:  # a package's metadata or a source unreadable, ...
            PREBUILT_MISFIT = f"{type(exc).__name__}: {exc}"
        if PREBUILT_MISFIT is None:
            module = aot.load(_PACKAGE, stamp)
    return module


_MODULE = _load_module()
_EXPORTS = _MODULE.exports if _MODULE else None
AOT_LOADED = _EXPORTS is not None  # this process started on the AOT module
# ... and that module is the package's prebuilt one, made for exactly these sources
AOT_PREBUILT = bool(_MODULE and _MODULE.prebuilt)
del _MODULE
if _EXPORTS is None:
    JIT_REASON = "no ahead-of-time module for these sources"


def _rebound(value: Any) -> Any:
    """value with each AOT kernel, also inside tuples (a registry of kernels), replaced by its
    numba dispatcher; value itself where it holds none."""
    if isinstance(value, AotKernel):
        return value.dispatcher
    if type(value) is tuple:
        items = tuple(_rebound(v) for v in value)
        return items if any(a is not b for a, b in zip(items, value)) else value
    return value


def to_jit(reason: str) -> None:
    """Turn this process to numba's JIT kernels: every AOT kernel gets its dispatcher and the
    package's modules are rebound to the dispatchers, also in tuples of kernels (numba
    resolves a kernel's callees through its module's globals). ``PIPE_NAV_AOT_DEBUG=1`` says
    why on stderr."""
    global _EXPORTS, JIT_REASON
    with _SWITCH:
        if _EXPORTS is None:
            return
        if os.environ.get("PIPE_NAV_AOT_DEBUG"):
            print(f"pipe_nav_core: JIT kernels from here on: {reason}", file=sys.stderr)
        for k in _KERNELS:
            k.dispatcher = _compile(k.py_func, k.nogil, _numba_njit)
        _rebind_package(_rebound)
        _EXPORTS = None
        JIT_REASON = reason


def kernel(func: Callable[..., Any] | None = None, *, nogil: bool = False) -> Any:
    """func compiled: ``@kernel`` or ``@kernel(nogil=True)`` (the compiled code releases the
    GIL: it can run in a thread while the caller works). Its AOT export where the module is
    built (:class:`AotKernel`), else numba's dispatcher, cached on disk where numba finds a
    writable cache directory (next to the source file, ~/.cache/numba or NUMBA_CACHE_DIR) and
    recompiled whenever any source file the kernels depend on changes.

    error_model="numpy": a zero interval gives inf/nan as in numpy, not ZeroDivisionError.
    """
    if func is None:
        return lambda f: kernel(f, nogil=nogil)
    if _EXPORTS is not None:
        if func.__module__.startswith(_PREFIX):
            k = AotKernel(func, nogil, _EXPORTS.get(f"{func.__module__}:{func.__qualname__}", []))
            _KERNELS.append(k)
            return k
        to_jit(f"a kernel from outside the package: {func.__module__}.{func.__qualname__}")
    return _compile(func, nogil, njit)


def build_aot(target: str | None = None) -> int:
    """Build the AOT module from the kernels this process has compiled with numba (run the
    work first: pipe_nav_core.warmup does), for this CPU or LLVM's CPU ``target``; returns the
    number of exports."""
    from numba.core.registry import CPUDispatcher

    found = {}
    for name, module in list(sys.modules.items()):
        if module is None or not name.startswith(_PREFIX):
            continue
        for value in list(vars(module).values()):
            if isinstance(value, CPUDispatcher) and value.py_func.__module__ == name:
                found[f"{name}:{value.py_func.__qualname__}"] = value
    return aot.build(_PACKAGE, _package_stamp(), sorted(found.items()), target)
