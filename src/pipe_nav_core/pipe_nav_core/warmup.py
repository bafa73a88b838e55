"""Compile (or load from the on-disk cache) every numeric kernel before real data arrives.

numba compiles a kernel on its first call and caches it beside the package; on a fresh install
that first call costs minutes. ``python -m pipe_nav_core.warmup`` runs the live filter and the
smoothers once over a short simulated run so that installers (``.ci/bootstrap``,
``.ci/bootstrap-ros``) leave a warm cache behind, and ekf_node calls :func:`warm_live` before it
declares itself ready, so it follows a bag from its first message.

The ahead-of-time module is then built by a fresh process that finds every kernel in numba's
cache (:func:`_build_aot`): it exports the kernels Python calls, not those only other kernels
call (already in their callers' code), and is built in half the time. Where the package's
prebuilt module fits (:func:`pipe_nav_core.aot.install_prebuilt`) none of this is needed:
``--prebuild`` makes it, and must be run again after any change to a kernel or to this file.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

from pipe_nav_core.config import NavConfig
from pipe_nav_core.types import SensorLog

# The demo run's first 70 s: rest, then two markers (10 s and 62 s), enough for every code path
# of the live filter (alignment, odometer, non-holonomic, magnetometer and marker updates).
_SPAN_S = 70.0
# what the warm-up runs (its kernels' argument types are what the AOT module exports): a new
# number builds the module again where an older warm-up made it (3: the running windows too;
# 4: the trajectory interpolation; 5: the transitions made on the other core; 6: the bag
# reader's CDR decoding)
WARM_UP = 6


@lru_cache(maxsize=1)
def _warmup_run() -> tuple[SensorLog, NavConfig]:
    from pipe_nav_core.sim import simulate
    from pipe_nav_core.smooth.logs import slice_log

    run = simulate("demo", 0)
    log = slice_log(run.log, float(run.log.imu.t[0]), float(run.log.imu.t[0]) + _SPAN_S)
    return log, NavConfig.from_dict(run.scenario.estimator_settings())


def warm_live() -> float:
    """Run the live Navigator over the warm-up run as a bag plays (replay.replay_log), s of
    wall time taken."""
    from pipe_nav_core.app.replay import replay_log

    t0 = time.perf_counter()
    replay_log(*_warmup_run())
    return time.perf_counter() - t0


def warm_smoothers() -> float:
    """Smooth the warm-up run with every method (s of wall time taken)."""
    from pipe_nav_core.smooth.passes import smooth_log

    t0 = time.perf_counter()
    log, config = _warmup_run()
    for method in ("rts", "two-filter", "forward", "graph"):
        smooth_log(log, config, method=method, iterations=2)
    return time.perf_counter() - t0


def warm_reading() -> float:
    """Write the warm-up run as an MCAP bag and read it back, as ``pipe-nav smooth`` reads
    (s of wall time taken)."""
    import tempfile

    from pipe_nav_core.io.bagread import read_bag
    from pipe_nav_core.io.bagwrite import write_sensor_bag

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        write_sensor_bag(f"{tmp}/warm.mcap", _warmup_run()[0])
        read_bag(f"{tmp}/warm.mcap")
    return time.perf_counter() - t0


def warm_products() -> float:
    """Call the products' window kernels (pipe_nav_core.products.windows) as the weld detector does,
    and the trajectory interpolation they all resample with (s of wall time taken)."""
    import numpy as np

    from pipe_nav_core.io.centreline import interpolate_trajectory
    from pipe_nav_core.products.windows import correlate, running_maximum, running_median
    from pipe_nav_core.types import Trajectory

    t0 = time.perf_counter()
    x = np.linspace(0.0, 1.0, 64)
    xyz, q = np.column_stack([x, x, x]), np.tile([0.0, 0.0, 0.0, 1.0], (64, 1))
    interpolate_trajectory(Trajectory(x, x, x, x, xyz, q, x, xyz, xyz), x[1:] - 0.005)
    running_median(x, 5)
    running_median(np.column_stack([x, x]), 5)
    running_maximum(x, 5)
    correlate(np.column_stack([x, x]), np.array([-1.0, 2.0, -1.0]))
    return time.perf_counter() - t0


def _compile_every_kernel(why: str) -> None:
    """Turn this process to numba's JIT kernels (saying ``why``) and run every warm-up: each
    kernel is compiled, or loaded from numba's disk cache where it is there."""
    from pipe_nav_core import jit

    jit.to_jit(why)
    for warm in (warm_live, warm_smoothers, warm_products, warm_reading):
        warm()


def _marker() -> Path:
    from pipe_nav_core import jit

    return jit._PACKAGE / "__pycache__" / "kernels_warm.txt"


def is_warm() -> bool:
    """Whether every kernel has been compiled for the package's current sources, and the
    ahead-of-time module built or found not buildable (a marker beside the package holds the
    kernels' source stamp and the AOT outcome once :func:`ensure_warm` has run), or the
    package's prebuilt module serves (nothing to compile: a kernel Python calls with types it
    does not export is compiled when called)."""
    from pipe_nav_core import jit

    if jit.AOT_PREBUILT:  # the package's prebuilt module, made from these very sources
        return True
    try:
        stamp, _, aot = _marker().read_text(encoding="utf-8").partition("\n")
    except OSError:
        return False
    if stamp != jit._package_stamp() or not aot.endswith(f"(warm-up {WARM_UP})"):
        return False
    # built, but this process could not load it (its format changed since): build it again
    return jit.AOT_LOADED or jit.FORCED_JIT or aot.startswith("aot: failed")


def _unserved(jit: Any) -> str:
    """ "; the prebuilt ones do not serve: WHY" where the package's prebuilt module was not
    installed here, else ""."""
    return f"; the prebuilt ones do not serve: {jit.PREBUILT_MISFIT}" if jit.PREBUILT_MISFIT else ""


def kernels_in_use() -> str:
    """Which numeric kernels this process runs, and why (``pipe-nav --version``)."""
    from pipe_nav_core import aot, jit

    if jit.AOT_PREBUILT:
        return f"kernels prebuilt for {aot.PREBUILT_CPU}, ahead of time"
    if jit.AOT_LOADED:
        return "kernels built on this machine, ahead of time"
    why = "PIPE_NAV_KERNELS=jit" if jit.FORCED_JIT else jit.JIT_REASON
    return f"numba's just-in-time kernels: {why}{_unserved(jit)}"


def ensure_warm(say: Callable[[str], None] | None = None) -> bool:
    """Compile every kernel unless :func:`is_warm`; ``say`` (default: a line on stderr) is told
    first and after, terminal or not, so no one waits in silence. True if it compiled."""
    if is_warm():
        return False
    from pipe_nav_core import jit

    tell = say or (lambda m: print(m, file=sys.stderr, flush=True))
    tell(
        "pipe_nav_core: preparing the numeric kernels for this install (once; compiling them "
        f"takes 4 to 7 minutes on a 2-core machine{_unserved(jit)})"
    )
    t0 = time.perf_counter()
    _compile_every_kernel("the warm-up compiles every kernel and builds the AOT module from them")
    aot = "not built (PIPE_NAV_KERNELS=jit)" if jit.FORCED_JIT else _build_aot(jit, tell)
    try:
        marker = _marker()
        marker.parent.mkdir(exist_ok=True)
        marker.write_text(f"{jit._package_stamp()}\naot: {aot} (warm-up {WARM_UP})",
                          encoding="utf-8")  # fmt: skip
    except OSError:  # a read-only install: numba then compiles in every process anyway
        pass
    tell(f"pipe_nav_core: kernels ready in {time.perf_counter() - t0:.0f} s")
    return True


def _cached_to_disk() -> bool:
    """Whether numba keeps this process's kernels in its on-disk cache (a writable cache
    directory), so that another process loads them instead of compiling them again."""
    from pipe_nav_core.filter import epoch

    return type(getattr(epoch.run_epochs, "_cache", None)).__name__ == "FunctionCache"


def _fresh_build() -> subprocess.Popen[str]:
    """``python -m pipe_nav_core.warmup --build-aot`` (:func:`_build_from_cache`) in a new
    process importing this same package; what it prints comes back through a pipe, what it
    says on stderr is dropped."""
    from pipe_nav_core import jit

    path = os.pathsep.join(p for p in (str(jit._PACKAGE.parent), os.environ.get("PYTHONPATH")) if p)
    return subprocess.Popen(
        [sys.executable, "-m", "pipe_nav_core.warmup", "--build-aot"],
        env={**os.environ, "PYTHONPATH": path},
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )


def _build_aot(jit: Any, tell: Callable[[str], None]) -> str:
    """Build the ahead-of-time module from the kernels the warm-up run calls from Python; what
    came of it, for the marker. Where numba caches to disk it is built by a fresh process that
    loads them from the cache (:func:`_fresh_build`): the kernels only other kernels call are
    in their callers' code and not exported, and the module is built in half the time. Else,
    or where that process fails, this one builds it from every kernel it compiled. A failure
    to build is said and leaves numba's kernels in use."""
    if _cached_to_disk():
        out, _ = (child := _fresh_build()).communicate()
        said = (out.strip().splitlines() or [""])[-1]
        if child.returncode == 0 and said.startswith(("built ", "failed (")):
            return _said(said.removeprefix("built "), tell)
    try:
        return f"{jit.build_aot()} exports"
    except Exception as exc:  # no C compiler, numba without pycc, ...: JIT kernels stay
        return _said(f"failed ({_why(exc)})", tell)


def _why(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {(str(exc).strip().splitlines() or [''])[-1]}"


def _said(outcome: str, tell: Callable[[str], None]) -> str:
    """The AOT build's outcome for the marker; a failure is told."""
    if outcome.startswith("failed ("):
        why = outcome.removeprefix("failed (").removesuffix(")")
        tell(f"pipe_nav_core: kernels stay just-in-time (the ahead-of-time build failed: {why})")
    return outcome


def _build_from_cache() -> int:
    """``--build-aot``: run the warm-up (its kernels loaded from numba's cache) and build the
    AOT module from them, printing "built N exports" or "failed (why)"."""
    from pipe_nav_core import jit

    _compile_every_kernel("the warm-up's AOT build")
    try:
        print(f"built {jit.build_aot()} exports", flush=True)
    except Exception as exc:  # no C compiler, numba without pycc, ...
        print(f"failed ({_why(exc)})", flush=True)
    return 0


def prebuild() -> int:
    """``--prebuild`` (for maintainers, after a change to a kernel, to the warm-up or to the
    pinned numba, llvmlite or NumPy): build the AOT module for :data:`aot.PREBUILT_CPU` from
    the kernels in numba's cache and write it into the package's ``prebuilt/`` folder, which
    a fresh install then takes instead of compiling. Run it in a fresh process after the
    warm-up, so that the module holds the kernels Python calls only."""
    from pipe_nav_core import aot, jit

    _compile_every_kernel("the prebuilt module's build")
    n = jit.build_aot(aot.PREBUILT_CPU)
    out = aot.pack_prebuilt(jit._PACKAGE, jit.fingerprint())
    size = sum(f.stat().st_size for f in out.iterdir())
    print(f"prebuilt {n} exports for {aot.PREBUILT_CPU} into {out} ({size / 1e6:.1f} MB)")
    return 0


def compile_bytecode() -> None:
    """Write the package's bytecode (``__pycache__/*.pyc``) where it is missing or stale.
    Python does not write it itself where PYTHONDONTWRITEBYTECODE is set (as on CI and some
    containers), and every command would then compile the package's sources again on import
    (0.3 s instead of 0.2 s for ``pipe-nav smooth``'s imports)."""
    import compileall

    from pipe_nav_core import jit

    compileall.compile_dir(jit._PACKAGE, quiet=2)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m pipe_nav_core.warmup`` (the installers): :func:`compile_bytecode` and
    :func:`ensure_warm`; with ``--build-aot``, :func:`_build_from_cache` (what
    :func:`ensure_warm` runs); with ``--prebuild``, :func:`prebuild`."""
    args = list(sys.argv[1:] if argv is None else argv)
    if args == ["--build-aot"]:
        return _build_from_cache()
    if args == ["--prebuild"]:
        return prebuild()
    if args:
        print(f"usage: python -m pipe_nav_core.warmup [--build-aot | --prebuild] (got "
              f"{' '.join(args)})", file=sys.stderr)  # fmt: skip
        return 2
    compile_bytecode()
    ensure_warm()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
