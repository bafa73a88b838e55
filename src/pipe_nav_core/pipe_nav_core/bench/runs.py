"""The runs benchmark: run-to-run movement against the injected ground movement, and multi-run
fusion against the single run, on simulated runs through one pipe.

Every run is simulated, smoothed with the scenario's honest settings and its welds detected
from its magnetometer (products.welds.detect_welds), exactly what ``pipe-nav smooth`` gives
``compare`` and ``fuse``; the truth is the simulator's.

- Movement (:func:`movement_case`): run A through the pipe, run B (another seed) through the
  pipe after a :class:`~pipe_nav_core.sim.movement.GroundMovement`; per compared weld the
  displacement error against the exact field (moved minus original pipe at the weld's true
  chainage), whether the movement is found (a movement interval over the moved stretch), its
  size error at the peak weld, and the significant points and largest |d| outside it (false
  movement). A case without movement gives the false rate through an unmoved pipe.
- Fusion (:func:`fusion_case`): 5 runs (seeds 1-5) through one pipe fused 1, 2, 3, 5 at a time
  (the first n), the fused line's horizontal error against the truth of the reference run at
  its times (RMS and max, m; per 100 m of chainage between markers as the published figure),
  against the single run's; and the fused sigma.

``python -m pipe_nav_core.bench.runs [--quick] [--out BENCH_RUNS.md]`` prints the Markdown tables.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.bench.evaluation import trajectory_enu
from pipe_nav_core.config import NavConfig
from pipe_nav_core.io.smoothed_bag import SmoothedRun
from pipe_nav_core.products.fusion import fuse_runs
from pipe_nav_core.products.movement import MovementReport, compare_runs
from pipe_nav_core.products.welds import detect_welds
from pipe_nav_core.sim import SimRun, get_scenario, simulate
from pipe_nav_core.sim.movement import GroundMovement, moved_scenario, true_displacement
from pipe_nav_core.sim.scenarios import Scenario
from pipe_nav_core.smooth.passes import smooth_log

FloatArray = NDArray[np.float64]

MOVEMENT_SCENARIO = "demo"  # 300 m, industrial IMU, markers every 100 m, magnetometer
FUSION_SCENARIO = "demo"
FUSION_MARKER_SPACING_M = 150.0  # fusion case: markers every 150 m ...
FUSION_GRADE = "consumer"  # ... and a consumer IMU: a single run's error near the 12 cm figure
PUBLISHED_SINGLE_M = 0.12  # m per 100 m, one run (issue 19)
PUBLISHED_FIVE_M = 0.03  # m per 100 m, five runs


def smoothed(
    scn: Scenario, seed: int, config: NavConfig | None = None
) -> tuple[SimRun, SmoothedRun]:
    """Simulate a run of ``scn``, smooth it and detect its welds: (the SimRun, the smoothed run
    as ``read_smoothed_run`` would give it)."""
    run = simulate(scn, seed)
    cfg = config or NavConfig.from_dict(scn.estimator_settings())
    res = smooth_log(run.log, cfg)
    welds = detect_welds(run.log, res.centreline, res.datum, pipe_diameter=scn.pipe_diameter,
                         r_base_imu=run.r_base_imu)  # fmt: skip
    return run, SmoothedRun(res.centreline, res.datum, {}, welds)


def true_chainage_of_welds(run: SimRun, sm: SmoothedRun) -> FloatArray:
    """True chainage (m) of the detected welds of ``sm`` (through their passage times)."""
    t = np.array([w.t for w in sm.welds])
    return np.interp(t, run.truth.t, run.truth.distance)


def score_movement(
    report: MovementReport,
    run_a: SimRun,
    sm_a: SmoothedRun,
    scn: Scenario,
    movements: Sequence[GroundMovement],
) -> dict[str, Any]:
    """Displacement errors of a comparison against the injected field (see the module doc)."""
    s_true = true_chainage_of_welds(run_a, sm_a)
    by_number = {w.number: s for w, s in zip(sm_a.welds, s_true, strict=True)}
    pts = [p for p in report.points if p.anchor == "weld"]
    s = np.array([by_number[p.weld] for p in pts])
    d = np.array([p.d_enu for p in pts]).reshape(-1, 3)
    truth = true_displacement(scn, movements, s, sm_a.datum) if movements else 0.0 * d
    err = d - truth
    moved = np.zeros(len(pts), dtype=bool)
    for m in movements:
        moved |= (s > m.start) & (s < m.end)
    outside = ~moved
    row: dict[str, Any] = {
        "points": len(pts),
        "rms_error_m": float(np.sqrt(np.mean(np.sum(err**2, axis=1)))) if len(pts) else 0.0,
        "max_error_m": float(np.linalg.norm(err, axis=1).max()) if len(pts) else 0.0,
        "false_points": int(sum(p.significant for p, o in zip(pts, outside, strict=True) if o)),
        "max_d_outside_m": float(np.linalg.norm(d[outside], axis=1).max()) if outside.any()
        else 0.0,
        "max_sigmas_outside": float(max((p.mahalanobis for p, o in zip(pts, outside, strict=True)
                                         if o), default=0.0)),
    }  # fmt: skip
    if movements:
        inside = np.flatnonzero(moved)
        k = int(inside[np.argmax(np.linalg.norm(truth[inside], axis=1))])
        near = [pts[i].distance for i in inside]
        found = [iv for iv in report.intervals
                 if any(iv.start_m - 1 <= x <= iv.end_m + 1 for x in near)]  # fmt: skip
        row.update(
            true_peak_m=float(np.linalg.norm(truth[k])),
            measured_peak_m=float(np.linalg.norm(d[k])),
            peak_size_error_m=float(np.linalg.norm(d[k]) - np.linalg.norm(truth[k])),
            peak_vector_error_m=float(np.linalg.norm(err[k])),
            found=bool(found and pts[k].significant),
        )
    return row


def movement_case(
    movements: Sequence[GroundMovement], seeds: tuple[int, int] = (1, 2), name: str = ""
) -> dict[str, Any]:
    """Run A (seeds[0]) through the pipe, run B (seeds[1]) through it after ``movements``."""
    scn = get_scenario(MOVEMENT_SCENARIO)
    cfg = NavConfig.from_dict(scn.estimator_settings())
    t0 = time.perf_counter()
    run_a, sm_a = smoothed(scn, seeds[0], cfg)
    _, sm_b = smoothed(moved_scenario(scn, movements), seeds[1], cfg)
    t1 = time.perf_counter()
    report = compare_runs(sm_a, sm_b, cfg)
    row = score_movement(report, run_a, sm_a, scn, movements)
    row.update(case=name, seeds=list(seeds), intervals=len(report.intervals),
               compare_s=time.perf_counter() - t1, smooth_s=t1 - t0)  # fmt: skip
    return row


def _error_h(traj: Any, datum: Any, run: SimRun) -> FloatArray:
    """Horizontal position error (N,) m of a trajectory against the run's truth at its times."""
    tr = run.truth
    e = trajectory_enu(traj, datum)
    te = trajectory_enu(tr, datum)
    ref = np.column_stack([np.interp(traj.t, tr.t, te[:, k]) for k in range(3)])
    return np.hypot(e[:, 0] - ref[:, 0], e[:, 1] - ref[:, 1])


def fusion_case(counts: Sequence[int] = (1, 2, 3, 5), seeds: Sequence[int] = (1, 2, 3, 4, 5)
                ) -> list[dict[str, Any]]:  # fmt: skip
    """The fused line's error for each count of runs (the first n of ``seeds``)."""
    scn = replace(get_scenario(FUSION_SCENARIO), marker_spacing=FUSION_MARKER_SPACING_M,
                  imu_grade=FUSION_GRADE)  # fmt: skip
    cfg = NavConfig.from_dict(scn.estimator_settings())
    runs = [smoothed(scn, s, cfg) for s in seeds[: max(counts)]]
    singles = [_error_h(sm.trajectory, sm.datum, run) for run, sm in runs]
    rows = []
    for n in counts:
        t0 = time.perf_counter()
        fused = fuse_runs([sm for _, sm in runs[:n]])
        dt = time.perf_counter() - t0
        err = _error_h(fused.centreline, fused.datum, runs[0][0])
        sig = fused.centreline.sigma_enu
        rows.append({
            "runs": n,
            "rms_h_m": float(np.sqrt(np.mean(err**2))),
            "max_h_m": float(err.max()),
            "single_rms_h_m": float(np.sqrt(np.mean(singles[0] ** 2))),
            "single_max_h_m": float(singles[0].max()),
            "mean_single_rms_h_m": float(np.mean([np.sqrt(np.mean(e**2)) for e in singles[:n]])),
            "sigma_h_m": float(np.mean(np.hypot(sig[:, 0], sig[:, 1]))),
            "max_residual_rms_h_m": float(max(r.rms_h for r in fused.residuals)),
            "fuse_s": dt,
        })  # fmt: skip
    return rows


def run(quick: bool = False) -> dict[str, Any]:
    """Both benchmarks; quick: the movement cases only for one seed pair and fusion 1 and 5."""
    seed_pairs = [(1, 2)] if quick else [(1, 2), (3, 4), (5, 6)]
    target = [GroundMovement(140.0, 50.0, lateral=0.10, settlement=0.0)]
    example = [GroundMovement(140.0, 60.0, lateral=0.20, settlement=0.05)]
    moves = []
    for pair in seed_pairs:
        moves.append(movement_case([], pair, "no movement"))
        moves.append(movement_case(target, pair, "10 cm lateral over 50 m"))
        moves.append(movement_case(example, pair, "20 cm lateral + 5 cm settlement over 60 m"))
    fusion = fusion_case((1, 5) if quick else (1, 2, 3, 5))
    return {"movement": moves, "fusion": fusion}


def markdown(result: dict[str, Any], command: str = "python -m pipe_nav_core.bench.runs") -> str:
    """The two tables as Markdown."""
    lines = [
        "## Runs: movement between runs and multi-run fusion",
        "",
        f"`{command}`; {MOVEMENT_SCENARIO} pipe (300 m, industrial IMU, markers every 100 m, "
        "welds detected from the magnetometer); run B through the pipe after the ground moved "
        "(sim/movement.py), displacement per matched weld against the exact field.",
        "",
        "| case | seeds | welds | RMS error | max error | true peak | measured | size error | "
        "found | false points | max \\|d\\| outside | max sigmas outside |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["movement"]:

        def cm(k: str, r: dict[str, Any] = r) -> str:
            return f"{100 * r[k]:.1f} cm" if k in r else "-"

        found = ("yes" if r["found"] else "NO") if "found" in r else "-"
        lines.append(
            f"| {r['case']} | {r['seeds'][0]},{r['seeds'][1]} | {r['points']} | "
            f"{cm('rms_error_m')} | {cm('max_error_m')} | {cm('true_peak_m')} | "
            f"{cm('measured_peak_m')} | {cm('peak_size_error_m')} | {found} | "
            f"{r['false_points']} | {cm('max_d_outside_m')} | {r['max_sigmas_outside']:.2f} |"
        )
    lines += [
        "",
        f"Fusion: {FUSION_SCENARIO} pipe with markers every {FUSION_MARKER_SPACING_M:g} m and a "
        f"{FUSION_GRADE} IMU, seeds 1-5, the first n runs fused (products/fusion.py); "
        "horizontal error of the fused line against the truth of run 1 at its times. "
        f"Published: {100 * PUBLISHED_SINGLE_M:g} cm per 100 m for one run, "
        f"{100 * PUBLISHED_FIVE_M:g} cm with five.",
        "",
        "| runs | RMS h | max h | run 1 alone RMS / max | mean single RMS | fused sigma_h | "
        "largest run residual RMS | fuse time |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in result["fusion"]:
        lines.append(
            f"| {r['runs']} | {100 * r['rms_h_m']:.1f} cm | {100 * r['max_h_m']:.1f} cm | "
            f"{100 * r['single_rms_h_m']:.1f} / {100 * r['single_max_h_m']:.1f} cm | "
            f"{100 * r['mean_single_rms_h_m']:.1f} cm | {100 * r['sigma_h_m']:.1f} cm | "
            f"{100 * r['max_residual_rms_h_m']:.1f} cm | {r['fuse_s']:.2f} s |"
        )
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pipe_nav_core.bench.runs")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", help="write the Markdown here too")
    args = ap.parse_args(argv)
    md = markdown(run(quick=args.quick))
    print(md)
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            f.write(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())

__all__ = ["fusion_case", "markdown", "movement_case", "run", "score_movement", "smoothed"]
