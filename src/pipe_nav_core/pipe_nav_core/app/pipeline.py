"""Bag in, products out: what ``pipe-nav smooth`` / ``pipe-nav replay`` and the smoother node run.

Reads a bag (single .mcap or rosbag2 directory), merges a marker CSV, runs the engine, and
writes the outputs atomically (temporary file, then rename). Never modifies the input and
refuses to write over it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from pipe_nav_core.app.plot_process import PlotProcess
from pipe_nav_core.app.progress import QUIET, Progress
from pipe_nav_core.config import AUTO_GRADE, NavConfig
from pipe_nav_core.faults import quality
from pipe_nav_core.faults.gaps import (
    fill_holes_at_rest,
    fill_short_holes,
    find_holes,
    remove_clock_steps,
)
from pipe_nav_core.faults.imu import without_imu_faults
from pipe_nav_core.faults.markers import smooth_without_outliers
from pipe_nav_core.faults.odometer import find_odometer_faults, without_faults
from pipe_nav_core.filter.estimates import NavEstimate
from pipe_nav_core.filter.live_guard import GuardedNavigator
from pipe_nav_core.io import (
    BagReport,
    TopicNames,
    merge_markers,
    read_bag,
    read_markers_csv,
    resample_by_chainage,
    write_centreline_csv,
    write_geojson,
    write_kml,
    write_output_bag,
)
from pipe_nav_core.io.atomic import all_or_none, check_output, ensure_not_input
from pipe_nav_core.io.centreline import concat, pieces_of, read_centreline_csv
from pipe_nav_core.io.products_csv import (
    write_bends_csv,
    write_strain_csv,
    write_strain_features_csv,
)
from pipe_nav_core.io.smoothed_bag import read_smoothed_bag, smoothed_attachments
from pipe_nav_core.io.welds_csv import write_welds_csv
from pipe_nav_core.model import imu_noise as imu_model
from pipe_nav_core.model.sensors import GRADES
from pipe_nav_core.products import IntegrityReport, integrity_report, read_bends_reference
from pipe_nav_core.products.welds import Weld, detect_welds
from pipe_nav_core.smooth.centreline import SmoothResult
from pipe_nav_core.smooth.chunks import drop_spare
from pipe_nav_core.smooth.passes import smooth_log
from pipe_nav_core.smooth.segments import smooth_segments
from pipe_nav_core.types import Datum, Marker, SensorLog, Trajectory

Say = Callable[[str], None]  # told each stage as it begins (Progress.stage)
MAX_BRIDGED_M = 0.5  # m: the filter carries a gap the pig moved less in; else segments
DEFAULT_TOPICS = TopicNames()


@dataclass
class Outputs:
    """Where to write what (None = do not write)."""

    bag: str | None = None
    csv: str | None = None
    geojson: str | None = None
    kml: str | None = None
    plot: str | None = None
    strain: str | None = None  # the integrity products (products/), named like the centreline
    bends: str | None = None
    strain_features: str | None = None
    welds: str | None = None  # RUN_welds.csv, written when the run has a magnetometer

    # the command-line option that names each output, for messages
    OPTIONS = {"bag": "--out", "csv": "--csv", "geojson": "--geojson", "kml": "--kml",
               "plot": "--plot", "strain": "--csv/--out", "bends": "--csv/--out",
               "strain_features": "--csv/--out", "welds": "--csv/--out"}  # fmt: skip

    def paths(self) -> list[str]:
        return [p for p in (getattr(self, name) for name in self.OPTIONS) if p]

    def with_products(self) -> Outputs:
        """These outputs plus the integrity products beside the centreline CSV (else beside
        the bag): ``RUN_strain.csv``, ``RUN_bends.csv``, ``RUN_strain_features.csv``,
        ``RUN_welds.csv`` where RUN is the CSV's (or bag's) name without ``_centerline``
        (``_smoothed``) and suffix."""
        base = self.csv or self.bag
        if not base:
            return self
        stem = str(Path(base).with_suffix(""))
        for tail in ("_centerline", "_centreline", "_smoothed"):
            if stem.endswith(tail):
                stem = stem[: -len(tail)]
                break
        return replace(self, strain=f"{stem}_strain.csv", bends=f"{stem}_bends.csv",
                       strain_features=f"{stem}_strain_features.csv",
                       welds=f"{stem}_welds.csv")  # fmt: skip

    def check(self, inputs: Sequence[str | os.PathLike[str]], spacing: float) -> None:
        """Before any work: every output writable, none an input, no two the same file, and
        the CSV spacing a positive number; ValueError naming the option otherwise."""
        if not (math.isfinite(spacing) and spacing > 0.0):
            raise ValueError(f"--spacing must be a positive number of metres, not {spacing}")
        seen: dict[str, str] = {}
        for name, option in self.OPTIONS.items():
            path = getattr(self, name)
            if not path:
                continue
            check_output(path, option)
            ensure_not_input(path, inputs)
            real = os.path.realpath(path)
            if real in seen:
                raise ValueError(f"{seen[real]} and {option} name the same file {path}")
            seen[real] = option


@dataclass
class ReplayResult:
    """Forward estimates of the online engine over a bag, its datum and its diagnostics."""

    estimates: list[NavEstimate]
    datum: Datum | None
    diagnostics: dict[str, object] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)  # Navigator.model_warnings


def load_log(
    bag: str | os.PathLike[str],
    *,
    topics: TopicNames = DEFAULT_TOPICS,
    markers_csv: str | os.PathLike[str] | None = None,
    repair: bool = True,
) -> tuple[SensorLog, BagReport]:
    """Read a bag into memory (sorted per topic), leave out saturated IMU samples and shocks
    (imu_faults), re-align its clock steps and name its data gaps (gaps.find_holes; the bag's
    own markers follow its clock), leave out the readings of a stuck or spiking wheel
    (odometer_faults), merge the marker CSV. ``repair=False``: the data as recorded (what
    ekf_node would see; the live guard checks it then)."""
    log, report = read_bag(bag, topics)
    if not repair:
        return _with_markers(log, report, markers_csv)
    log, imu_faults = without_imu_faults(log)
    report.warnings += [f.describe() for f in imu_faults]
    steps = [h for h in find_holes(log) if h.kind == "clock step"]
    log = remove_clock_steps(log, steps)
    log, filled, added = fill_short_holes(log)
    if filled:
        report.warnings.append(
            f"IMU: {added} missing samples in {filled} short hole(s) filled by interpolation"
        )
    log, at_rest = fill_holes_at_rest(log)
    report.warnings += [h.describe() for h in at_rest]
    holes = find_holes(log, short=True)  # what is left: short clock glitches and data gaps
    log = remove_clock_steps(log, holes)
    report.warnings += [h.describe() for h in steps + holes]
    log, faults = without_faults(log, find_odometer_faults(log))
    report.warnings += [f.describe() for f in faults]
    return _with_markers(log, report, markers_csv)


def _with_markers(
    log: SensorLog, report: BagReport, markers_csv: str | os.PathLike[str] | None
) -> tuple[SensorLog, BagReport]:
    """The log with the marker CSV merged in and the markers without a time or outside the
    data left out (named in the report)."""
    if markers_csv is not None:
        log.markers = merge_markers(log.markers, read_markers_csv(markers_csv))
    untimed = [m.name for m in log.markers if not math.isfinite(m.t)]
    if untimed:
        report.warnings.append(
            f"{len(untimed)} marker(s) without a passage time ignored: {', '.join(untimed[:5])}"
        )
        log.markers = [m for m in log.markers if math.isfinite(m.t)]
    log.markers = _markers_inside(log, report)
    return log, report


def _markers_inside(log: SensorLog, report: BagReport) -> list[Marker]:
    """The markers whose passage lies within the IMU data (s of stamps); the others are left
    out and named in a warning, as is a run that keeps only one (nothing then anchors the
    heading)."""
    if len(log.imu.t) == 0 or not log.markers:
        return log.markers
    t0, t1 = float(log.imu.t[0]), float(log.imu.t[-1])
    inside = [m for m in log.markers if t0 <= m.t <= t1]
    outside = [m for m in log.markers if not t0 <= m.t <= t1]
    for m in outside:
        where = f"{t0 - m.t:.1f} s before" if m.t < t0 else f"{m.t - t1:.1f} s after"
        report.warnings.append(f"marker {m.name} passes {where} the data: left out")
    if outside and len(inside) == 1:
        report.warnings.append(
            f"only one marker ({inside[0].name}) within the data: the heading is not anchored"
        )
    return inside


def smooth_bag(
    bag: str | os.PathLike[str],
    outputs: Outputs,
    *,
    config: NavConfig,
    method: str = "rts",
    iterations: int = 2,
    markers_csv: str | os.PathLike[str] | None = None,
    spacing: float = 0.5,
    topics: TopicNames = DEFAULT_TOPICS,
    progress: Progress | None = None,
    bends_reference: str | os.PathLike[str] | None = None,
    plotter: PlotProcess | None = None,
) -> tuple[SmoothResult, BagReport]:
    """Smooth a recorded run, compute its integrity products (bends_reference: a CSV of the
    as-built bends' chainage intervals) and write the requested outputs (the plot in
    ``plotter``'s child process where one is given). ``progress`` is told each stage and the
    fraction of each filter pass done (pipe_nav_core.app.progress)."""
    inputs = [bag] + [p for p in (markers_csv, bends_reference) if p]
    outputs.check(inputs, spacing)
    told = QUIET if progress is None else progress
    reference = read_bends_reference(bends_reference) if bends_reference else None
    say = told.stage
    say("reading bag")
    log, report = load_log(bag, topics=topics, markers_csv=markers_csv)
    _require_imu(log, report, bag, topics)
    if not log.markers:
        left = [w for w in report.warnings if w.startswith("marker ")]
        why = f" ({left[0]}{f' and {len(left) - 1} more' if len(left) > 1 else ''})" if left else ""
        raise ValueError(
            f"{bag}: no markers within the data (topic {topics.markers} or --markers CSV){why}: "
            "nothing ties the run to the ground"
        )

    def smooth(part: SensorLog, reverse: bool = False) -> SmoothResult:
        return smooth_with_imu_model(
            part, config, declared=report.imu_noise_declared, method=method,
            iterations=iterations, progress=told, reverse=reverse,
        )  # fmt: skip

    try:
        result = _smooth_segments(log, report, config, smooth, say)
    finally:
        drop_spare()  # the recordings' chunk arrays kept for the next pass
    report.warnings += result.summary.get("warnings", [])  # type: ignore[operator]
    report.warnings += result.summary.get("marker_warnings", [])  # type: ignore[operator]
    failures = [f"{d}: the centreline does not fit its markers"
                for d in [result.summary.get("marker_disagreement")] if d]  # fmt: skip
    verdict = quality.judge(result.summary, result.centreline, report.warnings, failures)
    result.summary["quality"] = {"status": verdict.status, "reasons": verdict.reasons}
    say("bends and strain")
    result.products = integrity_report(
        result.centreline, result.config or config, spacing=spacing, reference=reference
    )
    result.summary["integrity"] = result.products.summary()

    def find_welds() -> None:
        if len(log.mag.t):
            say("girth welds")
            result.welds = run_welds(log, result, result.config or config)
            result.summary["welds"] = weld_summary(result.welds)

    write_products(result, outputs, spacing=spacing, progress=say, plotter=plotter,
                   meanwhile=find_welds)  # fmt: skip
    return result, report


def _smooth_segments(
    log: SensorLog,
    report: BagReport,
    config: NavConfig,
    smooth: Callable[..., SmoothResult],
    say: Say,
) -> SmoothResult:
    """The run smoothed whole, or in segments between its data gaps (named in the report)."""
    gaps = [h for h in find_holes(log, short=True)
            if h.kind == "data gap" and not h.moved <= MAX_BRIDGED_M]  # fmt: skip
    if not gaps:
        return smooth(log)
    say(f"smoothing {len(gaps) + 1} segments between data gaps")
    result, segments = smooth_segments(log, config, gaps, smooth)
    result.summary["segments"] = [vars(s) for s in segments]
    described = {h.describe() for h in gaps}
    report.warnings = [w for w in report.warnings if w not in described]
    report.warnings += [f"{h.describe()}: the pipe across it is not mapped" for h in gaps]
    report.warnings += [
        f"{s.t1 - s.t0:.1f} s of data from t = {s.t0:.3f} s not mapped ({s.why})"
        for s in segments
        if s.how == "unmapped"
    ]
    return result


def smooth_with_imu_model(
    log: SensorLog,
    config: NavConfig,
    *,
    declared: dict[str, list[float]] | None = None,
    method: str = "rts",
    iterations: int = 2,
    progress: Progress = QUIET,
    reverse: bool = False,
) -> SmoothResult:
    """smooth_log (``reverse``: of a log in reversed time) with ``imu_grade: auto`` resolved
    from the run (imu_model.choose: the static spans, else ``declared``, the variances the Imu
    messages declare: BagReport's imu_noise_declared) and, while the smoothed run still shows
    that the model does not fit (Navigator.model_warnings), refitted with the next noisier
    grade. The summary's ``imu_model`` says which model was used and why; a named grade is used
    as given (its misfit warnings stay). ``progress`` is told each stage and the fraction of
    each filter pass done, of every smoothing run (the marker outliers' too)."""
    say = progress.stage
    choice = imu_model.choose(log, config, declared if config.imu_grade == AUTO_GRADE else None)
    auto = config.imu_grade == AUTO_GRADE
    if auto:
        say(f"IMU model: {choice.grade} ({choice.reason})")

    def run(cfg: NavConfig) -> SmoothResult:
        result, outliers, warnings = smooth_without_outliers(
            log,
            cfg,
            lambda lg: smooth_log(
                lg, cfg, method=method, iterations=iterations, progress=progress, reverse=reverse
            ),  # fmt: skip
            progress,
        )
        s = result.summary
        for key in ("markers_rejected", "markers_total"):
            s[key] = int(s[key]) + len(outliers)  # type: ignore[call-overload]
        s["marker_outliers"] = [o.name for o in outliers]
        s["marker_warnings"] = warnings
        return result

    result = run(choice.config)
    while auto and result.summary.get("warnings"):
        wider = imu_model.wider(choice)
        if wider is None:
            break
        say(f"IMU model: {wider.reason}")
        choice = wider
        result = run(choice.config)
    result.summary["imu_model"] = {
        "grade": choice.grade,
        "reason": choice.reason,
        "auto": auto,
        "measured": choice.measured,
    }
    return result


def centreline_rows(result: SmoothResult, spacing: float) -> Trajectory:
    """The centreline resampled every ``spacing`` m of chainage plus a row at every marker;
    a centreline in pieces (segments across data gaps) gets no row across its holes."""
    c = result.centreline
    pieces = pieces_of(c)
    rows = []
    for p in pieces:
        times = [m.t for m in result.markers if p.t[0] <= m.t <= p.t[-1]]
        rows.append(resample_by_chainage(p, spacing, times))
    return rows[0] if len(rows) == 1 else concat(rows)


def _require_imu(
    log: SensorLog, report: BagReport, bag: str | os.PathLike[str], topics: TopicNames
) -> None:
    """ValueError when the bag gave no IMU sample, naming the type its IMU topic carries."""
    if len(log.imu) == 0:
        found = report.types.get(topics.imu)
        carries = f" (it carries {found})" if found else ""
        raise ValueError(f"{bag}: no IMU samples on {topics.imu}{carries}")


def run_welds(log: SensorLog, result: SmoothResult, config: NavConfig) -> list[Weld]:
    """The girth welds of a smoothed run (products.welds.detect_welds) with the pig's pipe
    diameter and IMU mount."""
    from pipe_nav_core.filter.ingest import mount_rotation

    return detect_welds(log, result.centreline, result.datum, pipe_diameter=config.pipe_diameter,
                        r_base_imu=mount_rotation(config.imu_mount_rpy))  # fmt: skip


def weld_summary(welds: Sequence[Weld]) -> dict[str, object]:
    """What the summary says of the welds: how many, how many filled in, the typical joint."""
    joints = [w.joint_length for w in welds if math.isfinite(w.joint_length)]
    return {"count": len(welds), "filled": sum(w.confidence == 0.0 for w in welds),
            "median_joint_m": float(np.median(joints)) if joints else None}  # fmt: skip


def write_products(
    result: SmoothResult,
    outputs: Outputs,
    *,
    spacing: float = 0.5,
    progress: Say | None = None,
    plotter: PlotProcess | None = None,
    meanwhile: Callable[[], None] | None = None,
) -> Trajectory:
    """Write the bag, CSV, GeoJSON, KML and plot of a smoothing result: all of them or, if
    one fails (or the run is interrupted), none (io.atomic.all_or_none). ``plotter``: a
    child process that draws the plot meanwhile (else it is drawn here); ``meanwhile``: the
    last work on ``result`` that the other outputs need and the plot does not (the welds),
    done while the plot is drawn."""
    say = progress or (lambda _m: None)
    rows = centreline_rows(result, spacing)
    with all_or_none(outputs.paths()) as staged:
        _write_staged(result, outputs, rows, staged, say, plotter, meanwhile)
    return rows


def run_metadata(summary: dict[str, object]) -> dict[str, str]:
    """What the smoothed bag records of its run (MCAP metadata ``pipe_nav``): the quality
    verdict and its reasons, the IMU model and why, the markers used and rejected, and for the
    graph smoother its iterations and whether it converged."""
    q = summary.get("quality") or {}
    model = summary.get("imu_model") or {}
    return {
        "quality": str(q.get("status", "")),  # type: ignore[union-attr]
        "quality_reasons": "; ".join(q.get("reasons", [])),  # type: ignore[union-attr]
        "imu_model": str(model.get("grade", "")),  # type: ignore[union-attr]
        "imu_model_reason": str(model.get("reason", "")),  # type: ignore[union-attr]
        "markers_used": str(summary.get("markers_used", "")),
        "markers_rejected": str(summary.get("markers_rejected", "")),
        **(
            {
                "method": "graph",
                "graph_iterations": str(summary["graph_iterations"]),
                "graph_converged": str(bool(summary.get("graph_converged"))).lower(),
            }
            if "graph_iterations" in summary
            else {}
        ),  # fmt: skip
    }


def _write_staged(
    result: SmoothResult,
    outputs: Outputs,
    rows: Trajectory,
    staged: dict[str, Path],
    say: Say,
    plotter: PlotProcess | None,
    meanwhile: Callable[[], None] | None,
) -> None:
    products = result.products
    bends = products.bends if products else []
    if outputs.plot:  # first: a child process draws it while the others are written
        say("plotting")
        _submit_plot(result, rows, staged[outputs.plot], Path(outputs.plot).stem, plotter)
    if meanwhile is not None:
        meanwhile()
    features = products.features if products else []
    if outputs.bag:
        say("writing bag")
        write_output_bag(staged[outputs.bag], path=rows, datum=result.datum,
                         odometry=result.forward, file_name=Path(outputs.bag).name,
                         run_metadata=run_metadata(result.summary), bends=bends,
                         attachments=smoothed_attachments(rows, result.datum,
                                                          result.welds))  # fmt: skip
    if outputs.csv:
        write_centreline_csv(staged[outputs.csv], rows, result.datum)
    welds = result.welds or []
    bridges = result.summary.get("bridges") or []  # across data gaps (segments.Bridge)
    if outputs.geojson:
        write_geojson(staged[outputs.geojson], rows, result.markers, bends=bends,
                      strain_features=features, welds=welds, bridges=bridges)  # fmt: skip
    if outputs.kml:
        write_kml(staged[outputs.kml], rows, result.markers, bends=bends,
                  strain_features=features, welds=welds, bridges=bridges)  # fmt: skip
    if result.products is not None:
        _write_products_csv(result.products, outputs, staged)
    if outputs.welds and result.welds is not None:
        write_welds_csv(staged[outputs.welds], result.welds)
    if plotter is not None:
        plotter.wait()


def _submit_plot(
    result: SmoothResult, rows: Trajectory, path: Path, title: str, plotter: PlotProcess | None
) -> None:
    from pipe_nav_core.app.plots import plot_report

    markers = [m for m in result.markers if m.name in result.marker_residuals]
    res = np.array([result.marker_residuals[m.name] for m in markers]).reshape(-1, 3)
    args = (path, rows, result.datum, markers, res if len(res) else None)
    kwargs = {"title": title, "integrity": result.products}
    if plotter is None:
        plot_report(*args, **kwargs)
    else:
        plotter.submit(*args, **kwargs)


def _write_products_csv(report: IntegrityReport, outputs: Outputs, staged: dict[str, Path]) -> None:
    if outputs.strain:
        write_strain_csv(staged[outputs.strain], report.profile, report.strain_pct,
                         report.sigma_strain_pct)  # fmt: skip
    if outputs.bends:
        write_bends_csv(staged[outputs.bends], report.bends)
    if outputs.strain_features:
        write_strain_features_csv(staged[outputs.strain_features], report.features)


def replay_log(
    log: SensorLog, config: NavConfig, declared: dict[str, list[float]] | None = None
) -> ReplayResult:
    """Run the online engine over a log exactly as ekf_node does: samples pushed one by one in
    stamp order (the engine's reorder buffer makes arrival order within its window irrelevant).
    declared: the per-sample IMU variances the Imu messages declare (imu_grade auto)."""
    nav = GuardedNavigator(config)
    nav.declared_imu_noise = declared
    events: list[tuple[float, int, int]] = []
    events += [(t, 0, i) for i, t in enumerate(log.imu.t)]
    events += [(t, 1, i) for i, t in enumerate(log.odometer.t)]
    events += [(t, 2, i) for i, t in enumerate(log.mag.t)]
    events += [(m.t, 3, i) for i, m in enumerate(log.markers)]
    events.sort()
    out: list[NavEstimate] = []
    imu, odo, mag = log.imu, log.odometer, log.mag
    for _t, kind, i in events:
        if kind == 0:
            nav.push_imu(imu.t[i], imu.gyro[i], imu.accel[i])
        elif kind == 1:
            nav.push_odometer(odo.t[i], odo.distance[i], odo.speed[i])
        elif kind == 2:
            nav.push_mag(mag.t[i], mag.field[i])
        else:
            nav.push_marker(log.markers[i])
        out.extend(nav.poll())
    out.extend(nav.finish())
    return ReplayResult(out, nav.datum, dict(nav.diagnostics()), nav.model_warnings())


def estimates_to_trajectory(estimates: Sequence[NavEstimate]) -> Trajectory:
    """Forward estimates as a Trajectory (sigmas from the covariance diagonals)."""
    cov = np.array([e.cov_pose for e in estimates]).reshape(-1, 6, 6)
    var = np.einsum("kii->ki", cov)
    return Trajectory(
        t=np.array([e.t for e in estimates]),
        lat=np.array([e.lat for e in estimates]),
        lon=np.array([e.lon for e in estimates]),
        h=np.array([e.h for e in estimates]),
        vel_n=np.array([e.vel_n for e in estimates]).reshape(-1, 3),
        quat_nb=np.array([e.quat_nb for e in estimates]).reshape(-1, 4),
        distance=np.array([e.distance for e in estimates]),
        sigma_enu=np.sqrt(np.maximum(var[:, :3], 0.0)),
        sigma_att=np.sqrt(np.maximum(var[:, 3:], 0.0)),
        cov_pose=cov,
    )


def replay_bag(
    bag: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    config: NavConfig,
    markers_csv: str | os.PathLike[str] | None = None,
    topics: TopicNames = DEFAULT_TOPICS,
) -> tuple[ReplayResult, BagReport]:
    """`pipe-nav replay`: the online estimator over a bag; writes /pipe_nav/odometry."""
    ensure_not_input(out, [bag] + ([markers_csv] if markers_csv else []))
    log, report = load_log(bag, topics=topics, markers_csv=markers_csv, repair=False)
    _require_imu(log, report, bag, topics)
    auto = config.imu_grade == AUTO_GRADE
    result = replay_log(log, config, report.imu_noise_declared if auto else None)
    if not result.estimates:
        raise ValueError(
            f"{bag}: the estimator produced no estimate (no static start or no marker)"
        )
    traj = estimates_to_trajectory(result.estimates)
    datum = result.datum or Datum(traj.lat[0], traj.lon[0], traj.h[0])
    write_output_bag(out, path=None, datum=datum, odometry=traj)
    report.warnings += result.warnings
    if "lost_since" in result.diagnostics:
        d = result.diagnostics
        report.warnings.append(
            f"the live solution was lost at t = {float(d['lost_since']):.3f} s "  # type: ignore[arg-type]
            f"({d['lost_reason']}): {d.get('withheld_lost', 0)} estimates after it withheld"
        )
    return result, report


def products_of_file(
    source: str | os.PathLike[str],
    outputs: Outputs,
    *,
    config: NavConfig,
    spacing: float = 0.5,
    bends_reference: str | os.PathLike[str] | None = None,
) -> tuple[IntegrityReport, list[str]]:
    """`pipe-nav bends`: the integrity products of a run already smoothed, from its smoothed
    MCAP bag or its centreline CSV, with other settings; writes ``outputs``' product files
    (all or none). Returns the report and the notes for the user. The sigmas use the IMU model
    the bag's metadata records when ``config.imu_grade`` is auto (industrial for a CSV)."""
    inputs = [source] + ([bends_reference] if bends_reference else [])
    outputs.check(inputs, spacing)
    reference = read_bends_reference(bends_reference) if bends_reference else None
    notes: list[str] = []
    if str(source).lower().endswith(".csv"):
        traj, _ = read_centreline_csv(source, warn=notes.append)
        model = ""
    else:
        traj, _, metadata = read_smoothed_bag(source)
        model = metadata.get("imu_model", "").split("+")[0]
        notes.append(f"{source}: chainage is the arc length of its path (a Path has no distance_m)")
    if config.imu_grade == AUTO_GRADE:
        grade = model if model in GRADES else "industrial"
        config = replace(config, imu_grade=grade)
        hint = "" if model else " (give --imu-grade)"
        notes.append(f"sigmas from the {grade} IMU model{hint}")
    report = integrity_report(traj, config, spacing=spacing, reference=reference)
    notes += report.notes
    with all_or_none(outputs.paths()) as staged:
        _write_products_csv(report, outputs, staged)
    return report, notes
