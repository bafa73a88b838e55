"""The fault corpus as a benchmark: every fault of sim.faults.CORPUS injected into runs of
several sizes, smoothed (``pipe-nav smooth``) and replayed (``pipe-nav replay``, as ekf_node),
scored against the simulator's truth: the verdict, whether the fault was named, the error and
how much of it the sigmas cover. ``python -m pipe_nav_core.bench.faults [--quick]`` prints the
Markdown table BENCHMARKS.md shows.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from pipe_nav_core.app.outputs import Outputs
from pipe_nav_core.app.pipeline import load_log, smooth_bag
from pipe_nav_core.app.replay import estimates_to_trajectory, replay_log
from pipe_nav_core.bench.evaluation import score
from pipe_nav_core.config import NavConfig
from pipe_nav_core.io import read_centreline_csv, write_sensor_bag
from pipe_nav_core.sim import simulate
from pipe_nav_core.sim.faults import CORPUS, FaultCase
from pipe_nav_core.sim.scenarios import get_scenario
from pipe_nav_core.types import SensorLog, Trajectory

BAGS = Path(__file__).resolve().parents[4] / "bags"


@dataclass(frozen=True)
class Size:
    """A run to damage: its name, log, truth and the settings its user would give."""

    name: str
    log: SensorLog
    truth: Trajectory
    config: NavConfig


def sizes(quick: bool = False) -> list[Size]:
    """The bundled sample (300 m), the demo pipe at 1.2 km and, unless quick, a 3 km field
    line with a tactical IMU."""
    out = []
    scn = get_scenario("demo").with_length(1200.0)
    run = simulate(scn, seed=3)
    out.append(Size("demo 1.2 km, industrial", run.log, run.truth,
                    NavConfig.from_dict(scn.estimator_settings())))  # fmt: skip
    if (BAGS / "sample.mcap").exists():
        log = load_log(BAGS / "sample.mcap", repair=False)[0]
        truth = read_centreline_csv(BAGS / "sample.truth.csv")[0]
        out.insert(0, Size("sample 300 m, industrial", log, truth, NavConfig()))
    if not quick:
        scn = get_scenario("field10k").with_length(3000.0)
        run = simulate(scn, seed=0)
        out.append(Size("field line 3 km, tactical", run.log, run.truth,
                        NavConfig.from_dict(scn.estimator_settings())))  # fmt: skip
    return out


@dataclass(frozen=True)
class Outcome:
    """What one damaged run gave: smooth's verdict, whether a warning named the fault, its max
    horizontal / vertical error (m) and the share of rows inside 3 sigma; the replay's state
    and share inside 3 sigma; wall time of the smoothing (s)."""

    verdict: str
    named: bool
    max_h: float
    max_v: float
    inside: float
    live: str
    live_inside: float
    wall_s: float


def run_case(size: Size, case: FaultCase | None, work: Path) -> Outcome:
    """Smooth and replay ``size`` damaged by ``case`` (None: clean)."""
    duration = float(size.log.imu.t[-1] - size.log.imu.t[0])
    log = case.inject(size.log, duration) if case else size.log
    bag = work / "run.mcap"
    write_sensor_bag(bag, log)
    csv = work / "run.csv"
    t0 = time.perf_counter()
    result, report = smooth_bag(bag, Outputs(csv=str(csv)), config=size.config)
    wall = time.perf_counter() - t0
    est = read_centreline_csv(csv)[0]
    s = score(est, size.truth)
    named = case is None or any(case.named in w for w in report.warnings)
    live = replay_log(load_log(bag, repair=False)[0], size.config)
    lt = estimates_to_trajectory(live.estimates)
    ls = score(lt, size.truth) if len(lt.t) else None
    csv.unlink()
    return Outcome(str(result.summary["quality"]["status"]), named, s.max_h, s.max_v,
                   s.inside_3sigma, str(live.diagnostics.get("state", "")),
                   ls.inside_3sigma if ls else math.nan, wall)  # fmt: skip


def table(quick: bool = False) -> str:
    """The Markdown table of the corpus over the sizes."""
    lines = [
        "| run | fault | smooth verdict | named | max h / v (m) | inside 3 sigma | replay | "
        "replay inside 3 sigma |",
        "|---|---|---|---|---|---|---|---|",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        for size in sizes(quick):
            for case in (None, *CORPUS):
                o = run_case(size, case, Path(tmp))
                lines.append(
                    f"| {size.name} | {case.name if case else 'none'} | {o.verdict} | "
                    f"{'yes' if o.named else 'NO'} | {o.max_h:.3f} / {o.max_v:.3f} | "
                    f"{100 * o.inside:.0f} % | {o.live} | {100 * o.live_inside:.0f} % |"
                )
                print(lines[-1], flush=True)
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="without the 3 km run")
    ap.add_argument("--out", help="also write the table to this file")
    args = ap.parse_args()
    text = table(args.quick)
    if args.out:
        Path(args.out).write_text(text + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
