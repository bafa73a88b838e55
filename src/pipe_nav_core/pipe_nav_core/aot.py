"""Ahead-of-time compiled kernels: the ones a command calls, in one extension module.

Loading numba and its first cached kernel costs about 0.6 s in every process, a third of
smoothing the bundled sample. So the installer (:mod:`pipe_nav_core.warmup`), once numba has
compiled every kernel, builds the kernels that Python calls (with the argument types it called
them with) into one extension module with numba.pycc; later processes import that module (a
millisecond, numba not imported) and :mod:`pipe_nav_core.jit` routes each call to the export
whose argument types match, exactly as numba's dispatcher would choose the specialization.

The module is valid for one source stamp of the kernels (jit._package_stamp) and one CPU: a
sidecar JSON beside it records both and, per export, the kernel and its argument types. An
export is the same compiled code numba would run (a trampoline calling the kernel, so the
kernel keeps its own compile options), and it releases the GIL as ``@kernel(nogil=True)``.
Where the build fails (no C compiler, numba without pycc) the kernels stay just-in-time.

The package also carries the module prebuilt (``prebuilt/``: the module xz-compressed and its
sidecar), built for any x86-64 CPU with AVX2 and FMA (:data:`PREBUILT_CPU`) from the kernels'
exact sources with the numba, llvmlite and NumPy that ``.ci/constraints.txt`` pins. Where all of
that fits, a fresh install takes it (:func:`install_prebuilt`, a second) instead of compiling
for minutes; where anything differs it is not used.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import json
import lzma
import os
import shutil
import sys
import tempfile
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

MODULE = "_pipe_nav_kernels"  # the extension module's name (its PyInit symbol)
FORMAT = 1  # of the sidecar: a module built by another version of this file is not loaded
SIDECAR = "kernels_aot.json"
PREBUILT = "prebuilt"  # the package's folder holding the prebuilt module and its sidecar
PREBUILT_CPU = "x86-64-v3"  # LLVM's name for x86-64 with AVX2, FMA, BMI2 (2013 on)
# the /proc/cpuinfo flags x86-64-v3 code needs (its levels 2 and 3; "abm" is LZCNT, "pni" SSE3)
_PREBUILT_FLAGS = frozenset(
    ["avx", "avx2", "bmi1", "bmi2", "f16c", "fma", "movbe", "xsave", "abm", "cx16", "lahf_lm",
     "popcnt", "sse4_1", "sse4_2", "ssse3", "pni"]
)  # fmt: skip
Check = Callable[..., bool]
Loaded = tuple[Callable[..., Any], int, list[dict[str, Any]]]  # fn, arity, specs
Export = tuple[Check, Callable[..., Any], int, list[dict[str, Any]]]  # check, fn, arity, specs


class Module(NamedTuple):
    """A loaded module: its exports by kernel ("module:qualname"), without their checks
    (:func:`checked`), and the target it was prebuilt for (None: built on this machine)."""

    exports: dict[str, list[Loaded]]
    prebuilt: str | None


def _cpu() -> str:
    """The CPU the exports are built for and run on: its model name in /proc/cpuinfo (the
    platform's name where there is none)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.partition(":")[2].strip()
    except OSError:
        pass
    return sys.platform


# --- loading (no numba) ----------------------------------------------------------------------


def _check_source(spec: dict[str, Any], expr: str) -> str:
    """A Python expression true when the value ``expr`` has numba's type ``spec``."""
    kind = spec["k"]
    if kind == "a":
        flags = f"{expr}.flags"
        layout = {"C": f" and {flags}.c_contiguous", "F": f" and {flags}.f_contiguous"}
        return (
            f"(type({expr}) is _nd and {expr}.dtype == _dt[{spec['dt']!r}] and "
            f"{expr}.ndim == {spec['nd']} and {flags}.writeable is {not spec['ro']} and "
            f"{flags}.aligned{layout.get(spec['l'], '')})"
        )
    if kind == "f":
        return f"(type({expr}) in _floats)"
    if kind == "i":
        return f"(type({expr}) in _ints)"
    if kind == "b":
        return f"(type({expr}) in _bools)"
    items = spec["items"]
    head = (
        f"type({expr}).__qualname__ == {spec['cls'].rpartition('.')[2]!r} and "
        f"type({expr}).__module__ == {spec['cls'].rpartition('.')[0]!r}"
        if kind == "nt"
        else f"type({expr}) is tuple"
    )
    parts = [f"{head} and len({expr}) == {len(items)}"]
    parts += [_check_source(s, f"{expr}[{i}]") for i, s in enumerate(items)]
    return "(" + " and ".join(parts) + ")"


_CHECK_GLOBALS = {
    "_nd": np.ndarray,
    "_dt": {
        name: np.dtype(name) for name in ("float64", "float32", "int64", "int32", "uint8", "bool")
    },
    "_floats": (float, np.float64),
    "_ints": (int, np.int64),
    "_bools": (bool, np.bool_),
}


def _checker(specs: list[dict[str, Any]]) -> Check:
    """A function of the call's arguments, true when they have exactly these numba types."""
    names = [f"a{i}" for i in range(len(specs))]
    body = " and ".join(_check_source(s, n) for s, n in zip(specs, names)) or "True"
    src = f"def check({', '.join(names)}):\n    return {body}\n"
    ns = dict(_CHECK_GLOBALS)
    exec(src, ns)  # noqa: S102  (generated from the sidecar's type specs only)
    return ns["check"]  # type: ignore[no-any-return]


def coerced(args: tuple[Any, ...], specs: list[dict[str, Any]]) -> tuple[Any, ...] | None:
    """args with each array made a writable C-contiguous copy where its export wants one and
    only its layout or write flag differ (the same numbers, so the same result as numba's
    specialization for the other layout); None when a dtype, rank or other type differs."""
    out = []
    for a, s in zip(args, specs):
        if s["k"] == "a" and isinstance(a, np.ndarray):
            if a.dtype != np.dtype(s["dt"]) or a.ndim != s["nd"] or s["l"] not in "CA":
                return None
            if not (a.flags.c_contiguous and a.flags.writeable):
                a = np.array(a, order="C")
        out.append(a)
    return tuple(out)


def checked(loaded: list[Loaded]) -> list[Export]:
    """A kernel's exports as :func:`load` gives them, each with the check of its argument
    types (made when the kernel is first called: making them all costs 0.05 s, and a command
    calls some of the kernels only)."""
    return [(_checker(specs), fn, arity, specs) for fn, arity, specs in loaded]


def _sidecar(package: Path) -> dict[str, Any]:
    """The sidecar of the module in the package's ``__pycache__`` (raises OSError or ValueError
    where there is none or it is unreadable)."""
    meta = json.loads((package / "__pycache__" / SIDECAR).read_text(encoding="utf-8"))
    if not isinstance(meta, dict):
        raise ValueError(SIDECAR)
    return meta


def _cpu_flags() -> frozenset[str]:
    """This CPU's feature flags in /proc/cpuinfo (none where it cannot be read)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("flags"):
                    return frozenset(line.partition(":")[2].split())
    except OSError:
        pass
    return frozenset()


def _misfit(meta: dict[str, Any], fingerprint: dict[str, str]) -> str | None:
    """Why a prebuilt module with this sidecar cannot serve an install of this ``fingerprint``
    on this CPU, in words for its user; None where it can."""
    theirs = meta.get("fingerprint") or {}
    if meta.get("format") != FORMAT or meta.get("target") != PREBUILT_CPU:
        return "they are of another format"
    for key, what in (("abi", "Python"), ("numba", "numba"), ("llvmlite", "llvmlite"),
                      ("numpy", "NumPy")):  # fmt: skip
        if theirs.get(key) != fingerprint[key]:
            return (
                f"they are built for {what} {theirs.get(key)}, this install has {fingerprint[key]}"
            )
    if theirs.get("sources") != fingerprint["sources"]:
        return "the kernels' sources have changed since they were built"
    if missing := _PREBUILT_FLAGS - _cpu_flags():
        return f"this CPU lacks {' '.join(sorted(missing))}, which {PREBUILT_CPU} code needs"
    return None


def install_prebuilt(package: Path, stamp: str, fingerprint: dict[str, str]) -> str | None:
    """Install the package's prebuilt module as the module of this ``stamp``, where it was built
    for exactly this ``fingerprint`` (the kernels' source digest, the interpreter's extension
    suffix, numba's, llvmlite's and NumPy's versions) and this CPU runs its code. None once
    installed; else why not, in words for the user (nothing then written). The module and its
    sidecar are written under new names and then renamed into place, so nothing is left
    half-written."""
    try:
        meta = json.loads((package / PREBUILT / SIDECAR).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return "the package has none"
    try:
        if why := _misfit(meta, fingerprint):
            return why
        cache = package / "__pycache__"
        cache.mkdir(exist_ok=True)
        name = f"kernels-{stamp[:16]}{fingerprint['abi']}"
        tmp = cache / f"{name}.{os.getpid()}.tmp"
        try:
            with lzma.open(package / PREBUILT / meta["file"]) as src, open(tmp, "wb") as dst:
                shutil.copyfileobj(src, dst)
            tmp.replace(cache / name)
        finally:
            tmp.unlink(missing_ok=True)
        _write_sidecar(cache, {"format": FORMAT, "stamp": stamp, "cpu": _cpu(), "file": name,
                               "prebuilt": PREBUILT_CPU, "exports": meta["exports"]})  # fmt: skip
        return None
    except (OSError, ValueError, KeyError, TypeError, EOFError, lzma.LZMAError) as exc:
        return f"installing them failed ({type(exc).__name__}: {exc})"


def pack_prebuilt(package: Path, fingerprint: dict[str, str]) -> Path:
    """Write the module built in the package's ``__pycache__`` (for :data:`PREBUILT_CPU`) and
    its exports into the package's ``prebuilt/`` folder for this ``fingerprint``; returns the
    folder. Raises ValueError where the module there was built for another CPU."""
    meta = _sidecar(package)
    if meta.get("target") != PREBUILT_CPU:
        raise ValueError(f"the module in __pycache__ is built for {meta.get('target')}")
    out = package / PREBUILT
    out.mkdir(exist_ok=True)
    name = "kernels.so.xz"
    tmp = out / f"{name}.{os.getpid()}.tmp"
    with open(package / "__pycache__" / meta["file"], "rb") as src:
        tmp.write_bytes(lzma.compress(src.read(), preset=9))
    tmp.replace(out / name)
    _write_sidecar(out, {"format": FORMAT, "fingerprint": fingerprint, "target": PREBUILT_CPU,
                         "file": name, "exports": meta["exports"]})  # fmt: skip
    return out


def _write_sidecar(folder: Path, meta: dict[str, Any]) -> None:
    tmp = folder / f"{SIDECAR}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(meta), encoding="utf-8")
    tmp.replace(folder / SIDECAR)


def load(package: Path, stamp: str) -> Module | None:
    """The module built (or the prebuilt one installed) for this stamp and CPU; None when there
    is none (not built, stale, built elsewhere or failing to load)."""
    try:
        meta = _sidecar(package)
        if (meta.get("format"), meta.get("stamp"), meta.get("cpu")) != (FORMAT, stamp, _cpu()):
            return None
        path = package / "__pycache__" / meta["file"]
        loader = importlib.machinery.ExtensionFileLoader(MODULE, str(path))
        spec = importlib.util.spec_from_file_location(MODULE, path, loader=loader)
        if spec is None:
            return None
        module = importlib.util.module_from_spec(spec)
        loader.exec_module(module)
        _preload_lapack()
        exports: dict[str, list[Loaded]] = {}
        for e in meta["exports"]:
            fn = getattr(module, e["symbol"])
            exports.setdefault(e["kernel"], []).append((fn, len(e["args"]), e["args"]))
        return Module(exports, meta.get("prebuilt"))
    except (OSError, ValueError, KeyError, ImportError, AttributeError, SyntaxError):
        return None


def _preload_lapack() -> None:
    """Load scipy.linalg.cython_blas and cython_lapack alone, where they are not loaded yet.

    numba's compiled linear algebra takes its BLAS and LAPACK from these two modules, importing
    them on a kernel's first call; imported the usual way, scipy.linalg's ``__init__`` runs
    first (about 0.2 s, more than a short run's first filter pass). Loaded alone (about 20 ms),
    they are in ``sys.modules`` when numba asks, and a later ``import scipy.linalg`` uses
    them."""
    try:
        scipy_spec = importlib.util.find_spec("scipy")
    except (ImportError, ValueError):
        return
    if scipy_spec is None or not scipy_spec.submodule_search_locations:
        return
    where = [os.path.join(p, "linalg") for p in scipy_spec.submodule_search_locations]
    for name in ("scipy.linalg.cython_blas", "scipy.linalg.cython_lapack"):
        if name in sys.modules:
            continue
        try:
            spec = importlib.machinery.PathFinder.find_spec(name, where)
            if spec is None or spec.loader is None:
                return
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
        except (ImportError, OSError):  # numba then imports it the usual way
            return
        sys.modules[name] = module


# --- building (numba) ------------------------------------------------------------------------


def _spec(t: Any) -> dict[str, Any] | None:
    """numba type -> the sidecar's spec of it; None for a type the exports do not take."""
    from numba.core import types

    if isinstance(t, types.Omitted):
        return {"k": "o"}
    if isinstance(t, types.Array) and str(t.dtype) in _CHECK_GLOBALS["_dt"] and t.aligned:
        return {"k": "a", "dt": str(t.dtype), "nd": t.ndim, "l": t.layout, "ro": not t.mutable}
    if t == types.float64:
        return {"k": "f"}
    if t == types.int64:
        return {"k": "i"}
    if t == types.boolean:
        return {"k": "b"}
    if isinstance(t, types.BaseTuple):
        items = [_spec(x) for x in t.types]
        if any(s is None or s["k"] == "o" for s in items):
            return None
        if isinstance(t, (types.NamedTuple, types.NamedUniTuple)):
            cls = t.instance_class
            return {"k": "nt", "cls": f"{cls.__module__}.{cls.__qualname__}", "items": items}
        return {"k": "t", "items": items}
    return None


def _entries(dispatchers: Iterable[tuple[str, Any]]) -> list[tuple[str, Any, Any, list[Any]]]:
    """(kernel key, dispatcher, numba signature, arg specs) of every specialization Python
    called, leaving out those with a type the exports do not take."""
    out = []
    for key, disp in dispatchers:
        for argtypes in disp.signatures:
            specs = [_spec(t) for t in argtypes]
            if all(s is not None for s in specs):
                out.append((key, disp, disp.overloads[argtypes].signature, specs))
    return out


def build(
    package: Path, stamp: str, dispatchers: Iterable[tuple[str, Any]], target: str | None = None
) -> int:
    """Compile the specializations of these (key, numba dispatcher) pairs that this process
    has compiled into the extension module for this CPU (or for LLVM's CPU ``target``, which
    this one must run) and write its sidecar; returns how many exports. Raises (anything
    numba.pycc or the C compiler raise) when it cannot."""
    from llvmlite import binding

    with warnings.catch_warnings():  # pending deprecation since numba 0.57, no replacement yet
        warnings.simplefilter("ignore")
        from numba.pycc import CC
        from numba.pycc import compiler as pycc_compiler

    entries = _entries(dispatchers)
    cache = package / "__pycache__"
    cache.mkdir(exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="pipe_nav_aot_"))
    real_compile = pycc_compiler.compile_extra
    nogil: dict[int, bool] = {}

    def compile_extra(typingctx: Any, targetctx: Any, func: Any, args: Any, ret: Any,
                      flags: Any, *rest: Any, **kw: Any) -> Any:  # fmt: skip
        flags.release_gil = nogil.get(id(func), False)  # as the kernel's @kernel(nogil=...)
        return real_compile(typingctx, targetctx, func, args, ret, flags, *rest, **kw)

    try:
        cc = CC(MODULE)
        cc.output_dir = str(work)
        cc.verbose = False
        cc.target_cpu = target or binding.get_host_cpu_name()
        meta_exports = []
        for i, (key, disp, sig, specs) in enumerate(entries):
            passed = [t for t, s in zip(sig.args, specs) if s["k"] != "o"]
            names = ", ".join(f"a{j}" for j in range(len(passed)))
            ns: dict[str, Any] = {"kernel": disp}
            exec(f"def trampoline({names}):\n    return kernel({names})\n", ns)  # noqa: S102
            symbol = f"k{i}"
            nogil[id(ns["trampoline"])] = bool(disp.targetoptions.get("nogil"))
            cc.export(symbol, sig.return_type(*passed))(ns["trampoline"])
            meta_exports.append({"kernel": key, "symbol": symbol,
                                 "args": [s for s in specs if s["k"] != "o"]})  # fmt: skip
        pycc_compiler.compile_extra = compile_extra
        try:
            cc.compile()
        finally:
            pycc_compiler.compile_extra = real_compile
        built = next(work.glob(f"{MODULE}*"))
        name = f"kernels-{stamp[:16]}{''.join(built.suffixes)}"
        tmp = cache / f"{name}.{os.getpid()}.tmp"
        shutil.copyfile(built, tmp)
        tmp.replace(cache / name)  # a new name: a process holding the old one is unaffected
        _write_sidecar(cache, {"format": FORMAT, "stamp": stamp, "cpu": _cpu(), "file": name,
                               "target": cc.target_cpu, "exports": meta_exports})  # fmt: skip
        for old in cache.glob("kernels-*"):
            if old.name != name and not old.name.endswith(".tmp"):
                old.unlink(missing_ok=True)
        return len(meta_exports)
    finally:
        shutil.rmtree(work, ignore_errors=True)
