"""Fixed costs of the command line on the bundled sample (``python -m
pipe_nav_core.bench.startup``).

Times whole ``pipe-nav`` processes, as a user starts them: ``smooth`` of ``bags/sample.mcap``
into every product and ``info`` of the same bag, each the median of ``--repeat`` runs with the
kernels compiled (as ``.ci/bootstrap`` leaves them: ahead of time, and numba's JIT cache for
reference, PIPE_NAV_KERNELS=jit); with ``--cold``, also the first smooth of
a fresh copy of the package (no compiled kernel: what a user would wait without the bootstrap),
once with its prebuilt kernels and once without them (compiled in the run). Prints a Markdown
table: wall seconds and the ratio to the bag's duration (x real time). Wall times are noisy on a
shared machine: run it on a quiet one.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

SAMPLE = Path(__file__).resolve().parents[4] / "bags" / "sample.mcap"


def _wall(argv: Sequence[str], env: dict[str, str] | None = None) -> float:
    t0 = time.perf_counter()
    subprocess.run(argv, check=True, env=env, capture_output=True, timeout=1800)
    return time.perf_counter() - t0


def _duration(bag: Path) -> float:
    from pipe_nav_core.io import read_bag

    log, _ = read_bag(bag)
    return float(log.imu.t[-1] - log.imu.t[0])


def measure(bag: Path, repeat: int, cold: bool) -> list[tuple[str, float, float]]:
    """(what, wall s, x real time) rows."""
    duration = _duration(bag)
    py = sys.executable
    rows: list[tuple[str, float]] = []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"

        def smooth(env: dict[str, str] | None = None) -> float:
            shutil.rmtree(out, ignore_errors=True)
            return _wall([py, "-m", "pipe_nav_core.app.cli", "smooth", str(bag), "--out", f"{out}/",
                          "--quiet"], env)  # fmt: skip

        if cold:
            src = Path(__file__).resolve().parents[1]  # the package
            for what, leave_out in (("the prebuilt kernels installed", ()),
                                    ("the kernels compiled", ("prebuilt",))):  # fmt: skip
                fresh = Path(tmp) / f"fresh{len(rows)}"
                skip = shutil.ignore_patterns("__pycache__", *leave_out)
                shutil.copytree(src, fresh / src.name, ignore=skip)
                env = {**os.environ, "PYTHONPATH": str(fresh)}
                rows.append((f"smooth, fresh install ({what} in the run)", smooth(env)))
        smooth()  # the kernels loaded once, as after the bootstrap
        jit_env = {**os.environ, "PIPE_NAV_KERNELS": "jit"}
        walls, jit_walls = [], []
        for _ in range(repeat):  # alternating, so that both see the same machine
            walls.append(smooth())
            jit_walls.append(smooth(jit_env))
        rows.append(("smooth, every product (median)", statistics.median(walls)))
        rows.append(("smooth, every product (best)", min(walls)))
        rows.append(("smooth with numba's JIT kernels instead (median)",
                     statistics.median(jit_walls)))  # fmt: skip
        info = [_wall([py, "-m", "pipe_nav_core.app.cli", "info", str(bag)]) for _ in range(repeat)]
        rows.append(("info (median)", statistics.median(info)))
        imports = [_wall([py, "-c", "import pipe_nav_core.app.pipeline"]) for _ in range(repeat)]
        rows.append(("import pipe_nav_core.app.pipeline (median)", statistics.median(imports)))
    return [(what, wall, duration / wall) for what, wall in rows]


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipe_nav_core.bench.startup", description=__doc__)
    ap.add_argument("--bag", default=str(SAMPLE), help="bag to smooth (default: the sample)")
    ap.add_argument("--repeat", type=int, default=5, help="runs per figure (median)")
    ap.add_argument("--cold", action="store_true", help="also a fresh install's first smooth")
    args = ap.parse_args(argv)
    bag = Path(args.bag)
    rows = measure(bag, max(1, args.repeat), args.cold)
    print(f"| `pipe-nav` on {bag.name} ({_duration(bag):.0f} s of data) | wall s | x real time |")
    print("|---|---|---|")
    for what, wall, ratio in rows:
        print(f"| {what} | {wall:.2f} | {ratio:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
