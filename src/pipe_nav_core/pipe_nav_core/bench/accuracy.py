"""``pipe-nav bench``: accuracy of every estimator variant on simulated versions of the papers'
experiments, beside the figures the papers published (shared/seeds/README.md).

Each scenario is simulated for several seeds (reproducible), smoothed with each method, and
scored against the simulator's truth. Results go to a Markdown table (BENCHMARKS.md, with the
command that made it) and to JSON. ``--products`` adds the bend/curvature/strain table per IMU
grade (:mod:`.bench_products`), ``--welds`` the girth weld and tally table
(:mod:`.bench_welds`), ``--runs`` the movement and multi-run fusion table (:mod:`.bench_runs`),
``--speed`` the speed table; ``--X-only`` that table alone.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import platform
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.bench.evaluation import sag_depth, score
from pipe_nav_core.bench.sources import MARKERS_ONLY, variant
from pipe_nav_core.config import NavConfig
from pipe_nav_core.errors import ConfigError
from pipe_nav_core.filter.complementary import complementary_trajectory
from pipe_nav_core.filter.ingest import mount_rotation
from pipe_nav_core.geo import earth
from pipe_nav_core.io.atomic import atomic_write
from pipe_nav_core.sim import SimRun, get_scenario, simulate
from pipe_nav_core.smooth.centreline import interpolate_enu
from pipe_nav_core.smooth.methods import DEFAULT_METHOD, METHODS
from pipe_nav_core.smooth.passes import smooth_log
from pipe_nav_core.types import Datum, Trajectory, markers_sorted

Array = NDArray[np.float64]


@dataclass(frozen=True)
class BenchCase:
    """One scenario of the benchmark: what it mirrors, the paper's figure and our target."""

    scenario: str
    source: str
    description: str
    paper: str
    target: str
    max_h: float | None = None  # m, target on the max horizontal error
    max_v: float | None = None  # m, target on the max vertical error
    ratio: float | None = None  # target on the between-marker ratio 1:N
    sag_m: float | None = None  # m, true sag depth whose estimate must be within 1 cm
    seeds: int = 3  # runs in the full benchmark (the long field lines take one)


CASES = [
    BenchCase(
        "drag180",
        "seed 001",
        "180 m drag test, 0.1 m bore, consumer MEMS, markers at both ends",
        "7.9 m max (north)",
        "max h < 0.5 m",
        max_h=0.5,
    ),
    BenchCase(
        "sag104",
        "seed 000",
        "103.8 m pipe, 0.2 m sag, industrial MEMS, markers 103.8 m apart",
        "5 cm repeatability",
        "max h, v < 2 cm; sag depth within 1 cm",
        max_h=0.02,
        max_v=0.02,
        sag_m=0.2,
    ),
    BenchCase(
        "sag104_deep",
        "seed 000",
        "the same pipe with a 0.415 m sag",
        "5 cm repeatability",
        "max h, v < 2 cm; sag depth within 1 cm",
        max_h=0.02,
        max_v=0.02,
        sag_m=0.415,
    ),
    BenchCase(
        "undulation90",
        "seed 002",
        "90 m test pipe with 2 m vertical undulation, consumer MEMS",
        "0.27 m h, 0.24 m v max",
        "max h, v < 5 cm",
        max_h=0.05,
        max_v=0.05,
    ),
    BenchCase(
        "field10k",
        "seed 003",
        "10 km field line, 219 mm, tactical MEMS (HG4930), markers every 1 km",
        "about 1:1000 (best published pig figure 1:2500)",
        "better than 1:4000",
        ratio=4000.0,
        seeds=1,
    ),
    BenchCase(
        "field10k_sparse",
        "seed 003",
        "the same line with markers every 2.5 km",
        "about 1:1000",
        "better than 1:4000",
        ratio=4000.0,
        seeds=1,
    ),
]
BASELINE = "cf-baseline"
# RTS on the same runs with the markers surveyed exactly (the test-pipe cases): the
# estimator's own error, without the survey error the centreline inherits at the markers
EXACT = "rts, exact survey"
# RTS on the same runs with the IMU and the odometer exact, the markers as simulated (survey
# and passage-time errors): the error the markers alone leave, which no smoother can beat
LIMIT = "markers-only limit"
QUICK = ("sag104", "sag104_deep", "undulation90", "drag180")


def survey_error(run: SimRun) -> tuple[float, float]:
    """Largest horizontal and vertical survey error (m) of a run's markers: the floor of the
    smoothed centreline's error at the markers, which pass through them."""
    true = {m.name: m for m in run.markers_true}
    d = np.array(
        [
            earth.geodetic_to_enu(m.lat, m.lon, m.alt, t.lat, t.lon, t.alt)
            for m in run.log.markers
            if (t := true.get(m.name)) is not None
        ]
    ).reshape(-1, 3)
    if not len(d):
        return math.nan, math.nan
    return float(np.hypot(d[:, 0], d[:, 1]).max()), float(np.abs(d[:, 2]).max())


def _resident_mb() -> float:
    """This process's resident memory, MB (nan where /proc is not there)."""
    try:
        with open("/proc/self/status") as f:
            return next(int(x.split()[1]) for x in f if x.startswith("VmRSS:")) / 1024.0
    except (OSError, StopIteration):
        return math.nan


class ResidentPeak:
    """The largest rise of this process's resident memory (MB) over what it was on entry,
    sampled every ``every`` s in a second thread while the block runs: ``mb`` after it."""

    def __init__(self, every: float = 0.005) -> None:
        self.every, self.mb = every, math.nan
        self._stop = threading.Event()

    def __enter__(self) -> ResidentPeak:
        self._start = self._peak = _resident_mb()

        def sample() -> None:
            while not self._stop.wait(self.every):
                self._peak = max(self._peak, _resident_mb())

        self._thread = threading.Thread(target=sample, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.mb = max(self._peak, _resident_mb()) - self._start


def run_case(
    case: BenchCase,
    seed: int,
    methods: list[str],
    pipe_seed: int | None = None,
    settings: Mapping[str, object] | None = None,
) -> list[dict[str, object]]:
    """Simulate one seed of a case and score each method, the seed 002 baseline and, for the
    test pipes, RTS with the markers surveyed exactly. pipe_seed: another pipe than the
    scenario's own (its marker survey errors, weld anomalies and field bends); settings:
    estimator settings (NavConfig keys) over the scenario's own, in every run."""
    scenario = get_scenario(case.scenario)
    if pipe_seed is not None:
        scenario = replace(scenario, pipe_seed=pipe_seed)
    run = simulate(scenario, seed=seed)
    cfg = NavConfig.from_dict({**run.scenario.estimator_settings(), **(settings or {})})
    duration = float(run.log.imu.t[-1] - run.log.imu.t[0])

    def row(
        run: SimRun, method: str, traj: Trajectory, datum: Datum, elapsed: float
    ) -> dict[str, object]:
        s = score(traj, run.truth, run.log.markers, datum=datum)
        survey_h, survey_v = survey_error(run)
        out: dict[str, object] = {
            "scenario": case.scenario,
            "seed": seed,
            "method": method,
            "max_h": s.max_h,
            "rms_h": s.rms_h,
            "max_v": s.max_v,
            "rms_v": s.rms_v,
            "ratio": s.ratio_between_markers,
            "inside_3sigma": s.inside_3sigma if traj.sigma_enu is not None else None,
            "sigma_h_at_max": s.sigma_h_at_max_h,
            "sigma_v_at_max": s.sigma_v_at_max_v,
            "survey_h": survey_h,
            "survey_v": survey_v,
            "seconds": elapsed,
            "x_real_time": duration / elapsed,
            "_enu_at_chainage": _at_chainage(traj, run.truth),
        }
        if case.sag_m is not None:
            out["sag_error"] = sag_depth(traj, datum=datum) - sag_depth(run.truth, datum=datum)
        return out

    rows = []
    for method in methods:
        with ResidentPeak() as peak:
            t0 = time.perf_counter()
            res = smooth_log(run.log, cfg, method=method)
            elapsed = time.perf_counter() - t0
        rows.append(row(run, method, res.centreline, res.datum, elapsed))
        rows[-1]["passes"] = res.summary.get("passes")
        rows[-1]["peak_mb"] = peak.mb
        del res
    # seed 002's complementary filter with dead reckoning: the published-method baseline
    t0 = time.perf_counter()
    base = complementary_trajectory(run.log.to_base_link(mount_rotation(cfg.imu_mount_rpy)))
    m0 = markers_sorted(run.log.markers)[0]
    datum = Datum(m0.lat, m0.lon, m0.alt)
    rows.append(row(run, BASELINE, base, datum, time.perf_counter() - t0))
    if "rts" in methods and (case.max_h is not None or case.max_v is not None):
        exact = replace(scenario, survey_sigma_h=0.0, survey_sigma_v=0.0)
        run_x = simulate(exact, seed=seed)  # the same sensors and marker times, exact surveys
        t0 = time.perf_counter()
        res = smooth_log(run_x.log, cfg, method="rts")
        rows.append(row(run_x, EXACT, res.centreline, res.datum, time.perf_counter() - t0))
    if "rts" in methods:
        run_m = simulate(variant(scenario, MARKERS_ONLY), seed=seed)  # the same markers
        t0 = time.perf_counter()
        res = smooth_log(run_m.log, cfg, method="rts")
        rows.append(row(run_m, LIMIT, res.centreline, res.datum, time.perf_counter() - t0))
    return rows


def _agg(rows: list[dict[str, object]], key: str, fn) -> float:  # noqa: ANN001
    vals = [float(r[key]) for r in rows if r.get(key) is not None]  # type: ignore[arg-type]
    return float(fn(vals)) if vals else math.nan


CHAINAGE_STEP_M = 0.5


def _at_chainage(est: Trajectory, truth: Trajectory) -> Array:
    """ENU (m, about the truth's start) of the estimate at true chainages 0, 0.5, 1, ... m, found
    through time (the pipe is the same for every seed, so runs compare by chainage)."""
    d = Datum(float(truth.lat[0]), float(truth.lon[0]), float(truth.h[0]))
    moving = np.r_[True, np.diff(truth.distance) > 0]
    grid = np.arange(0.0, truth.distance[-1], CHAINAGE_STEP_M)
    t_at = np.interp(grid, truth.distance[moving], truth.t[moving])
    return interpolate_enu(est, t_at, d)


def repeatability(rows: list[dict[str, object]]) -> float:
    """Largest distance (m) between any two runs' centrelines at the same chainage."""
    runs = [r["_enu_at_chainage"] for r in rows if r.get("_enu_at_chainage") is not None]
    if len(runs) < 2:
        return math.nan
    n = min(len(x) for x in runs)  # type: ignore[arg-type]
    stack = np.stack([np.asarray(x)[:n] for x in runs])
    spread = np.linalg.norm(stack[:, None] - stack[None, :], axis=-1)
    return float(spread.max())


def _cm(x: float) -> str:
    return "" if math.isnan(x) else f"{100 * x:.1f}"


def _mb(x: float) -> str:
    return "" if math.isnan(x) else f"{x:.0f}"


def _pct(x: float) -> str:
    return "" if math.isnan(x) else f"{100 * x:.0f} %"


CONSISTENT = 0.95  # the target share of samples inside 3 sigma, for every estimator
# the default method is judged within this share of the best smoother's max error (worst
# seed), horizontal and vertical each (issue 17)
DEFAULT_WITHIN = 0.10
# every smoother is judged within this factor of the markers-only limit's max error (worst
# seed), horizontal and vertical each (issue 17)
LIMIT_WITHIN = 1.2


def against_limit(rows: list[dict[str, object]]) -> dict[str, tuple[float, float]] | None:
    """Each smoother's (every method but the forward filter) max horizontal and vertical error
    on one scenario's rows as a multiple of the markers-only limit's (worst seed each), by
    method, with the limit itself (m) under LIMIT; None without the limit's rows."""
    worst = _worst(rows, (*METHODS, LIMIT))
    if LIMIT not in worst or len(worst) < 2:
        return None
    lh, lv = worst[LIMIT]
    out = {m: (h / lh, v / lv) for m, (h, v) in worst.items() if m != LIMIT}
    out[LIMIT] = (lh, lv)
    return out


def _worst(rows: list[dict[str, object]], methods: Sequence[str]) -> dict[str, tuple[float, float]]:
    """Max horizontal and vertical error (m, worst seed) of each of ``methods`` with rows, the
    forward filter left out (not a smoother)."""
    return {
        m: (_agg(rs, "max_h", max), _agg(rs, "max_v", max))
        for m in methods
        if m != "forward" and (rs := [r for r in rows if r["method"] == m])
    }


def default_against_best(rows: list[dict[str, object]]) -> dict[str, object] | None:
    """The default method (DEFAULT_METHOD) on one scenario's rows against the best smoother
    (every method but the forward filter), max horizontal and vertical error each (worst
    seed, m): {"h": (default, best, best's method), "v": (...), "within": bool}, whether
    both are within DEFAULT_WITHIN of the best; None without the default's rows."""
    worst = _worst(rows, METHODS)
    if DEFAULT_METHOD not in worst:
        return None
    out: dict[str, object] = {}
    within = True
    for i, axis in enumerate(("h", "v")):
        best = min(worst, key=lambda m: worst[m][i])
        mine, top = worst[DEFAULT_METHOD][i], worst[best][i]
        out[axis] = (mine, top, best)
        within &= mine <= (1.0 + DEFAULT_WITHIN) * top
    out["within"] = within
    return out


def verdict(case: BenchCase, rows: list[dict[str, object]], method: str) -> str:
    """The verdict of one method's rows: the case's accuracy target (worst seed; smoothed
    centrelines only) and CONSISTENT inside 3 sigma (mean over seeds; every method with
    sigmas): 'met', 'NOT met', 'NOT met (3σ)' (accurate, not consistent), for the forward
    filter '3σ met' or '3σ NOT met'; '' without sigmas (the baseline)."""
    in3 = _agg(rows, "inside_3sigma", np.mean)
    if math.isnan(in3):
        return ""
    consistent = in3 >= CONSISTENT
    if method == "forward":
        return "3σ met" if consistent else "3σ NOT met"
    ok = True
    if case.max_h is not None:
        ok &= _agg(rows, "max_h", max) < case.max_h
    if case.max_v is not None:
        ok &= _agg(rows, "max_v", max) < case.max_v
    if case.ratio is not None:
        ok &= _agg(rows, "ratio", min) > case.ratio
    if case.sag_m is not None:
        ok &= _agg(rows, "sag_error", lambda v: max(abs(x) for x in v)) < 0.01
    if not ok:
        return "NOT met"
    return "met" if consistent else "NOT met (3σ)"


def markdown(
    results: dict[str, list[dict[str, object]]],
    command: str,
    max_seeds: int,
    pipe_seed: int | None = None,
    every_case: bool = False,
) -> str:
    """The results table: one row per scenario and method, worst and mean over the seeds
    (through the pipe pipe_seed, else each scenario's own; every_case: the 10 km lines ran
    max_seeds seeds too)."""
    lines = [
        "# Benchmarks",
        "",
        "Accuracy of the estimator on simulated versions of the source papers' experiments",
        f"(shared/seeds/README.md), {'seed 1' if max_seeds == 1 else f'seeds 1 to {max_seeds}'}"
        + ("" if every_case else " (the 10 km lines: seed 1)")
        + ("" if pipe_seed is None else f", every scenario through pipe {pipe_seed}")
        + ". Produced by:",
        "",
        "```",
        command,
        "```",
        "",
        f"Machine: {platform.machine()}, Python {platform.python_version()}.",
        "Errors are against the simulator's truth; max = worst sample of the worst seed,",
        "RMS = mean over seeds; 1:N = marker spacing / max horizontal error between markers",
        "(worst seed); in 3σ = share of samples whose horizontal and vertical errors lie inside",
        "3 sigma (mean over seeds); repeat = largest distance between two seeds' centrelines at",
        "the same chainage (seed 000's repeatability: every seed runs through the same pipe and",
        "is scored against the same marker survey, as in the paper); survey = largest survey",
        "error of the pipe's markers, horizontal / vertical: the smoothed centreline passes",
        "through the surveyed markers, so its error there cannot be smaller.",
        "x real time: run duration / smoothing time (mean over seeds); memory: the largest rise",
        "of the process's resident memory while the method smooths (worst seed; the run's log",
        "is already in memory).",
        "Verdict: the target of the issue (smoothed centrelines, worst seed) and at least",
        f"{CONSISTENT:.0%} of samples inside 3σ (every estimator; the forward filter is judged on",
        "that alone).",
        "",
        "| scenario (mirrors) | paper | method | max h [m] | RMS h [m] | max v [m] | RMS v [m] "
        "| 1:N | in 3σ | sag err [cm] | repeat [cm] | survey h/v [cm] | target | verdict "
        "| x real time | memory [MB] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case in CASES:
        rows_all = results.get(case.scenario)
        if not rows_all:
            continue
        for method in (*METHODS, EXACT, LIMIT, BASELINE):
            rows = [r for r in rows_all if r["method"] == method]
            if not rows:
                continue
            sag_err = _agg(rows, "sag_error", lambda v: max(v, key=abs))
            sag = f"{100 * sag_err:+.1f}" if not math.isnan(sag_err) else ""
            lines.append(
                f"| {case.scenario} ({case.source}) | {case.paper} | {method} "
                f"| {_agg(rows, 'max_h', max):.3f} | {_agg(rows, 'rms_h', np.mean):.3f} "
                f"| {_agg(rows, 'max_v', max):.3f} | {_agg(rows, 'rms_v', np.mean):.3f} "
                f"| {_agg(rows, 'ratio', min):.0f} "
                f"| {_pct(_agg(rows, 'inside_3sigma', np.mean))} "
                f"| {sag} | {_cm(repeatability(rows))} "
                f"| {_cm(_agg(rows, 'survey_h', max))} / {_cm(_agg(rows, 'survey_v', max))} "
                f"| {case.target} "
                f"| {'' if method == LIMIT else verdict(case, rows, method)} "
                f"| {_agg(rows, 'x_real_time', np.mean):.0f} | {_mb(_agg(rows, 'peak_mb', max))} |"
            )
    lines += _default_lines(results)
    lines += _limit_lines(results)
    lines += _spread_lines(results)
    lines += [
        "",
        f"`{BASELINE}`: seed 002's complementary filter (k = 0.02) with odometer dead reckoning,",
        "starting at the first marker with the bearing to the second and using no other marker:",
        "what the published method gives on the same data.",
        "",
        f"`{EXACT}`: RTS on the same runs (same sensor errors and marker times) with the markers",
        "surveyed exactly: the estimator's own error. With the scenarios' 2 cm surveys the",
        "centreline inherits each marker's survey error at the marker, which no estimator can",
        "remove; the test-pipe targets are judged on both.",
        "",
        f"`{LIMIT}`: RTS on the same runs with the IMU and the odometer exact and the markers as",
        "simulated (the same survey and passage-time errors): what the markers alone leave, the",
        "floor of every smoother on the run (the sensors' errors can also cancel a survey's by",
        "chance: a few per cent below it is no better estimator).",
        "",
        "Scenarios:",
        "",
    ]
    lines += [f"- `{c.scenario}`: {c.description}." for c in CASES if c.scenario in results]
    return "\n".join(lines) + "\n"


def _default_lines(results: dict[str, list[dict[str, object]]]) -> list[str]:
    """The table of the default method against the best smoother per scenario."""
    rows = [
        (c.scenario, d) for c in CASES if (d := default_against_best(results.get(c.scenario, [])))
    ]
    if not rows:
        return []
    lines = [
        "",
        f"The default method (`{DEFAULT_METHOD}`) against the best smoother per scenario, max",
        f"error of the worst seed in cm; within: at most {DEFAULT_WITHIN:.0%} above the best,",
        "horizontal and vertical each:",
        "",
        f"| scenario | {DEFAULT_METHOD} h / v | best h | best v | within {DEFAULT_WITHIN:.0%} |",
        "|---|---|---|---|---|",
    ]
    for name, d in rows:
        (h, bh, mh), (v, bv, mv) = d["h"], d["v"]  # type: ignore[misc]
        lines.append(
            f"| {name} | {_cm(h)} / {_cm(v)} | {_cm(bh)} ({mh}) | {_cm(bv)} ({mv}) "
            f"| {'yes' if d['within'] else 'NO'} |"
        )
    return lines


def sigma_at_worst(rows: list[dict[str, object]], method: str) -> tuple[float, float]:
    """The smoother's own horizontal and vertical one-sigma (m) where its error is largest, on
    the seed whose error is largest (each axis on its own); nan without rows or sigmas."""
    rs = [r for r in rows if r["method"] == method]
    if not rs:
        return math.nan, math.nan
    worst_h = max(rs, key=lambda r: float(r["max_h"]))  # type: ignore[arg-type]
    worst_v = max(rs, key=lambda r: float(r["max_v"]))  # type: ignore[arg-type]
    return (float(worst_h.get("sigma_h_at_max", math.nan)),  # type: ignore[arg-type]
            float(worst_v.get("sigma_v_at_max", math.nan)))  # type: ignore[arg-type]  # fmt: skip


def _limit_lines(results: dict[str, list[dict[str, object]]]) -> list[str]:
    """The table of every smoother against the markers-only limit per scenario, with the
    default smoother's own sigma where its error is largest."""
    rows = [(c.scenario, d) for c in CASES if (d := against_limit(results.get(c.scenario, [])))]
    if not rows:
        return []
    methods = [m for m in METHODS if m != "forward" and any(m in d for _, d in rows)]
    lines = [
        "",
        f"Every smoother against the markers-only limit (`{LIMIT}`): its max error over the",
        "limit's, worst seed each, horizontal / vertical; within: every smoother at most",
        f"{LIMIT_WITHIN:g}x the limit, horizontal and vertical each; {DEFAULT_METHOD} sigma: its",
        "own one-sigma where its error is largest (worst seed, each axis on its own), the error",
        "the run's information leaves there, the surveys' and the sensors' together:",
        "",
        f"| scenario | limit h / v [cm] | {' | '.join(methods)} | within {LIMIT_WITHIN:g}x "
        f"| {DEFAULT_METHOD} sigma h / v [cm] |",
        "|---|---|" + "---|" * len(methods) + "---|---|",
    ]
    for name, d in rows:
        lh, lv = d[LIMIT]
        cells = [f"{d[m][0]:.2f} / {d[m][1]:.2f}" if m in d else "" for m in methods]
        ok = all(max(d[m]) <= LIMIT_WITHIN for m in methods if m in d)
        sh, sv = sigma_at_worst(results[name], DEFAULT_METHOD)
        lines.append(
            f"| {name} | {_cm(lh)} / {_cm(lv)} | {' | '.join(cells)} | {'yes' if ok else 'NO'} "
            f"| {_cm(sh)} / {_cm(sv)} |"
        )
    return lines


def _spread_lines(results: dict[str, list[dict[str, object]]]) -> list[str]:
    """Where a scenario ran more than one seed, the table of each smoother's max error per
    seed, mean and worst over the seeds: a change is judged on every seed, not on the worst
    one alone."""
    out = []
    for case in CASES:
        rows_all = results.get(case.scenario, [])
        for method in (*METHODS, EXACT):
            rows = [r for r in rows_all if r["method"] == method]
            if method == "forward" or len({r.get("seed") for r in rows}) < 2:
                continue
            h, v = (
                f"{100 * _agg(rows, key, np.mean):.2f} ({100 * _agg(rows, key, max):.2f})"
                for key in ("max_h", "max_v")
            )
            out.append(f"| {case.scenario} | {method} | {len(rows)} | {h} | {v} |")
    if not out:
        return []
    return [
        "",
        "Each smoother over the seeds: its max error per seed, mean (worst) over them, cm:",
        "",
        "| scenario | method | seeds | max h | max v |",
        "|---|---|---|---|---|",
        *out,
    ]


# the tables beside the accuracy table: option name -> module (run(quick) and markdown(rows,
# command) each)
TABLES = {"products": "products", "welds": "welds", "runs": "runs"}


def setting_overrides(items: Sequence[str]) -> dict[str, object]:
    """``--set KEY=VALUE`` items as estimator settings (each VALUE read as JSON, else as
    text); ConfigError naming the item NavConfig refuses."""
    out: dict[str, object] = {}
    for item in items:
        key, eq, text = item.partition("=")
        if not eq or not key:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        try:
            out[key] = json.loads(text)
        except ValueError:
            out[key] = text
        try:
            NavConfig.from_dict(out)
        except ConfigError as e:
            raise ConfigError(f"--set {item!r}: {e}") from None
    return out


def main(args: argparse.Namespace, before_runs: Callable[[], None] = lambda: None) -> int:
    """Entry of ``pipe-nav bench``; ``before_runs`` is called once the arguments and the
    output paths are checked (the command line compiles the kernels there, if it must)."""
    command = ("pipe-nav bench " + " ".join(sys.argv[2:])).strip()
    extras = [n for n in TABLES if getattr(args, n, False) or getattr(args, f"{n}_only", False)]
    if any(getattr(args, f"{n}_only", False) for n in (*TABLES, "speed")):
        names: list[str] = []
    else:
        names = args.scenarios or (list(QUICK) if args.quick else [c.scenario for c in CASES])
    unknown = set(names) - {c.scenario for c in CASES}
    if unknown:
        raise ValueError(f"unknown benchmark scenario(s): {', '.join(sorted(unknown))}")
    settings = setting_overrides(getattr(args, "set", None) or [])
    seeds = getattr(args, "seeds", None)
    if seeds is not None and seeds < 1:
        raise ConfigError(f"--seeds {seeds}: expected 1 or more")
    for target in (args.out, args.json):  # before the runs: a bad path fails at once
        if target:
            Path(target).parent.mkdir(parents=True, exist_ok=True)
    before_runs()
    max_seeds = seeds or (1 if args.quick else 3)
    methods = list(METHODS)
    results: dict[str, list[dict[str, object]]] = {}
    for case in (c for c in CASES if c.scenario in names):
        results[case.scenario] = []
        for seed in range(1, 1 + (seeds or min(max_seeds, case.seeds))):
            print(f"pipe-nav bench: {case.scenario} seed {seed}", file=sys.stderr, flush=True)
            results[case.scenario] += run_case(case, seed, methods, args.pipe_seed, settings)
    md = (
        markdown(results, command, max_seeds, args.pipe_seed, every_case=seeds is not None)
        if results
        else "# Benchmarks\n\n"
    )
    payload: dict[str, object] = {
        "cases": [asdict(c) for c in CASES if c.scenario in results],
        "results": results,
    }
    for name in extras:
        table = importlib.import_module(f"{__package__}.{TABLES[name]}")
        print(f"pipe-nav bench: {name}", file=sys.stderr, flush=True)
        rows = table.run(quick=args.quick)
        md += "\n" + table.markdown(rows, command)
        payload[name] = rows
    if getattr(args, "speed", False) or getattr(args, "speed_only", False):
        from pipe_nav_core.bench import speed

        print("pipe-nav bench: speed", file=sys.stderr, flush=True)
        sp = speed.run(length_km=getattr(args, "length_km", 10.0))
        md += "\n" + speed.markdown(sp, command)
        payload["speed"] = sp
    for rows in results.values():
        for r in rows:
            r.pop("_enu_at_chainage", None)
    with atomic_write(args.out) as f:
        f.write(md)
    if args.json:
        with atomic_write(args.json) as f:
            json.dump(payload, f, indent=1, default=float)
    print(md)
    return 0
