"""Compile (or load from the on-disk cache) every numeric kernel before real data arrives.

numba compiles a kernel on its first call and caches it beside the package; on a fresh install
that first call costs minutes. ``python -m pipe_nav_core.warmup`` runs the live filter and the
smoothers once over a short simulated run so that installers (``.ci/bootstrap``,
``.ci/bootstrap-ros``) leave a warm cache behind, and ekf_node calls :func:`warm_live` before it
declares itself ready, so it follows a bag from its first message.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
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


def _marker() -> Path:
    from pipe_nav_core import jit

    return jit._PACKAGE / "__pycache__" / "kernels_warm.txt"


def is_warm() -> bool:
    """Whether every kernel has been compiled for the package's current sources, and the
    ahead-of-time module built or found not buildable (a marker beside the package holds the
    kernels' source stamp and the AOT outcome once :func:`ensure_warm` has run)."""
    from pipe_nav_core import jit

    try:
        stamp, _, aot = _marker().read_text(encoding="utf-8").partition("\n")
    except OSError:
        return False
    if stamp != jit._package_stamp() or not aot.endswith(f"(warm-up {WARM_UP})"):
        return False
    # built, but this process could not load it (its format changed since): build it again
    return jit.AOT_LOADED or jit.FORCED_JIT or aot.startswith("aot: failed")


def ensure_warm(say: Callable[[str], None] | None = None) -> bool:
    """Compile every kernel unless :func:`is_warm`; ``say`` (default: a line on stderr) is told
    first and after, terminal or not, so no one waits in silence. True if it compiled."""
    if is_warm():
        return False
    from pipe_nav_core import jit

    tell = say or (lambda m: print(m, file=sys.stderr, flush=True))
    tell(
        "pipe_nav_core: preparing the numeric kernels for this install (once; compiling "
        "them takes about 4 minutes on a 2-core machine)"
    )
    t0 = time.perf_counter()
    jit.to_jit("the warm-up compiles every kernel and builds the AOT module from them")
    warm_live()
    warm_smoothers()
    warm_products()
    warm_reading()
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


def _build_aot(jit: Any, tell: Callable[[str], None]) -> str:
    """Build the ahead-of-time module from the kernels this process compiled (jit.build_aot);
    what came of it, for the marker. A failure is said and leaves numba's kernels in use."""
    try:
        return f"{jit.build_aot()} exports"
    except Exception as exc:  # no C compiler, numba without pycc, ...: JIT kernels stay
        why = f"{type(exc).__name__}: {(str(exc).strip().splitlines() or [''])[-1]}"
        tell(f"pipe_nav_core: kernels stay just-in-time (the ahead-of-time build failed: {why})")
        return f"failed ({why})"


def compile_bytecode() -> None:
    """Write the package's bytecode (``__pycache__/*.pyc``) where it is missing or stale.
    Python does not write it itself where PYTHONDONTWRITEBYTECODE is set (as on CI and some
    containers), and every command would then compile the package's sources again on import
    (0.3 s instead of 0.2 s for ``pipe-nav smooth``'s imports)."""
    import compileall

    from pipe_nav_core import jit

    compileall.compile_dir(jit._PACKAGE, quiet=2)


def main() -> int:
    """``python -m pipe_nav_core.warmup`` (the installers): :func:`compile_bytecode` and
    :func:`ensure_warm`."""
    compile_bytecode()
    ensure_warm()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
