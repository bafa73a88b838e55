"""Bag in, smoothed run out: what ``pipe-nav smooth`` and the smoother node run; and the
integrity products of a run smoothed before (``pipe-nav bends``).

Reads a bag (single .mcap or rosbag2 directory), merges a marker CSV, runs the engine, and
writes the outputs atomically (temporary file, then rename). Never modifies the input and
refuses to write over it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import replace

import numpy as np

from pipe_nav_core.app.outputs import Outputs, Say, write_products, write_products_csv
from pipe_nav_core.app.plot_process import PlotProcess
from pipe_nav_core.app.progress import QUIET, Progress
from pipe_nav_core.background import Background
from pipe_nav_core.config import AUTO_GRADE, NavConfig
from pipe_nav_core.faults import clock_offset, mag_clock, marker_clock, quality
from pipe_nav_core.faults.gaps import (
    fill_holes_at_rest,
    fill_short_holes,
    find_holes,
    remove_clock_steps,
)
from pipe_nav_core.faults.imu import without_imu_faults
from pipe_nav_core.faults.markers import smooth_without_outliers
from pipe_nav_core.faults.odometer import find_odometer_faults, without_faults
from pipe_nav_core.io import (
    BagReport,
    TopicNames,
    merge_markers,
    read_bag,
    read_markers_csv,
)
from pipe_nav_core.io.atomic import all_or_none
from pipe_nav_core.io.baginfo import message_count
from pipe_nav_core.io.bagread import read_workers
from pipe_nav_core.io.centreline import read_centreline_csv
from pipe_nav_core.io.smoothed_bag import read_smoothed_bag
from pipe_nav_core.memory import trim_heap
from pipe_nav_core.model import imu_noise as imu_model
from pipe_nav_core.model.sensors import GRADES
from pipe_nav_core.products import (
    IntegrityReport,
    integrity_report,
    no_products,
    read_bends_reference,
)
from pipe_nav_core.products.welds import Weld, detect_welds, jolt_deviation
from pipe_nav_core.smooth import logs as smooth_logs
from pipe_nav_core.smooth.ahead import FirstPassAhead
from pipe_nav_core.smooth.centreline import SmoothResult
from pipe_nav_core.smooth.chunks import drop_spare
from pipe_nav_core.smooth.logs import let_go, map_imu
from pipe_nav_core.smooth.methods import DEFAULT_METHOD, MAX_PASSES
from pipe_nav_core.smooth.passes import smooth_log
from pipe_nav_core.smooth.segments import smooth_segments
from pipe_nav_core.types import Marker, SensorLog

MAX_BRIDGED_M = 0.5  # m: the filter carries a gap the pig moved less in; else segments
# magnetometer samples up to which the welds are found beside the bends and strain (1 M: some
# 40 km of run at 50 Hz); longer runs find them after, to keep the peak memory down
WELDS_BESIDE_BENDS_MAX = 1_000_000
# messages up to which the first pass runs while the bag is read (smooth.ahead): some 20 km of
# run at the speed bench's rates, 0.3 GB of chunks held beside the log they are joined into
AHEAD_MAX_MESSAGES = 4_000_000


DEFAULT_TOPICS = TopicNames()


def load_log(
    bag: str | os.PathLike[str],
    *,
    topics: TopicNames = DEFAULT_TOPICS,
    markers_csv: str | os.PathLike[str] | None = None,
    repair: bool = True,
    ahead: FirstPassAhead | None = None,
    spill_imu_bytes: int | None = None,
    mount: np.ndarray | None = None,
) -> tuple[SensorLog, BagReport]:
    """Read a bag into memory (sorted per topic), leave out saturated IMU samples and shocks
    (imu_faults), re-align its clock steps and name its data gaps (gaps.find_holes; the bag's
    own markers follow its clock), re-time an IMU whose clock is offset from the odometer's
    (clock_offset; ``mount``: (3, 3) imu_link -> base_link, identity if None), leave out the
    readings of a stuck or spiking wheel (odometer_faults), merge the marker CSV.
    ``repair=False``: the data as recorded (what ekf_node would see; the live guard checks it
    then). ``ahead``: told the bag's time chunks as they are read, and the log read.
    ``spill_imu_bytes``: an IMU larger than this is gathered in files as it is read and mapped
    from them, read-only (io.read_bag)."""
    # failing: the ahead's context stops it; its pass is one busy thread beside the reading
    workers = read_workers(beside=1) if ahead is not None else None
    log, report = read_bag(bag, topics, pieces=ahead, workers=workers,
                           spill_imu_bytes=spill_imu_bytes)  # fmt: skip
    if ahead is not None:
        ahead.finish(log)
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
    log, clock = clock_offset.taken_out(log, np.eye(3) if mount is None else mount)
    if clock is not None and clock.named:
        report.warn(clock.describe())
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
    out (``report.markers_outside``) and named in a warning, as is a run that keeps only one
    (nothing then anchors the heading)."""
    if len(log.imu.t) == 0 or not log.markers:
        return log.markers
    t0, t1 = float(log.imu.t[0]), float(log.imu.t[-1])
    inside = [m for m in log.markers if t0 <= m.t <= t1]
    report.markers_outside = [m for m in log.markers if not t0 <= m.t <= t1]
    report.warnings += _outside_warnings(log, inside, report.markers_outside)
    return inside


def _outside_warnings(log: SensorLog, inside: list[Marker], outside: list[Marker]) -> list[str]:
    """What :func:`_markers_inside` says of the markers ``outside`` the data of ``log``, with
    ``inside`` within it."""
    t0, t1 = float(log.imu.t[0]), float(log.imu.t[-1])
    lines = [f"marker {m.name} passes "
             + (f"{t0 - m.t:.1f} s before" if m.t < t0 else f"{m.t - t1:.1f} s after")
             + " the data: left out" for m in outside]  # fmt: skip
    if outside and len(inside) == 1:
        lines.append(
            f"only one marker ({inside[0].name}) within the data: the heading is not anchored"
        )
    return lines


def smooth_bag(
    bag: str | os.PathLike[str],
    outputs: Outputs,
    *,
    config: NavConfig,
    method: str = DEFAULT_METHOD,
    iterations: int = MAX_PASSES,
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
    with first_pass_ahead(bag, config, method, markers_csv) as ahead:
        say("reading bag")
        log, report = load_log(bag, topics=topics, markers_csv=markers_csv, ahead=ahead,
                               spill_imu_bytes=smooth_logs.MAP_IMU_BYTES,
                               mount=imu_mount(config))  # fmt: skip
        require_imu(log, report, bag, topics)
        map_imu(log.imu)  # large: read from a file (mapped as read unless repaired)
        trim_heap(len(log.imu))  # what a long run's reading freed (pieces, temporaries)
        if len(log.markers) < 2 and report.markers_outside:  # hours off: none left to smooth
            say("the markers' passages lie outside the data: measuring their clock")
            log = _on_the_bags_clock(log, report, config)[1] or log
        require_markers(log, report, bag, topics)
        if plotter is not None:  # (unless told at its start) the first pass goes on alone
            plotter.warm()

        # the IMU's part of the weld search on the other core while the run is smoothed (when the
        # welds are found beside the bends: their working set is small then)
        jolts: Background | None = None
        if 0 < len(log.mag.t) <= WELDS_BESIDE_BENDS_MAX:
            jolts = Background("pipe-nav-jolts", jolt_deviation, log.imu, imu_mount(config))

        def smooth(part: SensorLog, reverse: bool = False) -> SmoothResult:
            return smooth_with_imu_model(
                part, config, declared=report.imu_noise_declared, method=method,
                iterations=iterations, progress=told, reverse=reverse, ahead=ahead,
            )  # fmt: skip

        try:
            result = _smooth_segments(log, report, config, smooth, say)
            if result.summary.get("marker_disagreement"):  # seconds off: they fit nowhere
                say("the markers disagree with the run: measuring their clock")
                log, result = _retried_on_the_bags_clock(log, report, result, config, smooth, say)
        finally:
            drop_spare()  # the recordings' chunk arrays kept for the next pass
            trim_heap(len(log.imu))  # and what the passes freed, not under the products' own
    report.warnings += result.summary.get("warnings", [])  # type: ignore[operator]
    report.warnings += result.summary.get("marker_warnings", [])  # type: ignore[operator]
    failures = [f"{d}: the centreline does not fit its markers"
                for d in [result.summary.get("marker_disagreement")] if d]  # fmt: skip
    lost = quality.lost_path(result.centreline, log.odometer)
    failures += [lost] if lost else []
    if len(log.mag.t) and not lost:  # before the welds are found in its field
        log, mag = mag_clock.taken_out(log, result.centreline)
        if mag is not None and mag.retime:
            report.warn(mag.describe())
    verdict = quality.judge(result.summary, result.centreline, report.warnings, failures)
    result.summary["quality"] = {"status": verdict.status, "reasons": verdict.reasons}
    result.summary["path_lost"] = bool(lost)
    # the welds on the other core while the bends and strain are found (both read the
    # smoothed run only; numpy and the kernels let go of the GIL for most of their time),
    # unless the run is so long that their working sets together would raise the peak
    # memory (some 400 bytes per magnetometer sample: 1 GB at 100 km)
    cfg = result.config or config
    welds: Background | None = None
    if jolts is not None and not lost:
        welds = Background("pipe-nav-welds", run_welds, log, result, cfg, jolts.result())
    say("bends and strain")
    if lost:  # no products of a path that is not the pipe (their grid is of its length)
        result.products = no_products(cfg, "no integrity products of a lost path")
    else:
        result.products = integrity_report(result.centreline, cfg, spacing=spacing,
                                           reference=reference)  # fmt: skip
    result.summary["integrity"] = result.products.summary()

    def find_welds() -> None:
        if lost:  # nothing to place them on: an empty tally
            result.welds = [] if len(log.mag.t) else None
            if jolts is not None:
                jolts.result()  # its thread reads the IMU, which let_go releases below
        elif len(log.mag.t):
            say("girth welds")
            trim_heap(len(log.imu))  # what the bends and the writing freed
            found = welds.result() if welds is not None else run_welds(log, result, cfg)
            result.welds = found
            result.summary["welds"] = weld_summary(found)
        let_go(log.imu)  # what the jolt check read (when the IMU is read from a file)

    write_products(result, outputs, spacing=spacing, progress=say, plotter=plotter,
                   meanwhile=find_welds)  # fmt: skip
    return result, report


def first_pass_ahead(
    bag: str | os.PathLike[str],
    config: NavConfig,
    method: str,
    markers_csv: str | os.PathLike[str] | None,
) -> AbstractContextManager[FirstPassAhead | None]:
    """The first pass run while ``bag`` is read (smooth.ahead; its thread stops when the
    context ends), where it can be the run's: the markers in the bag (not in a CSV that comes
    after it), and a bag whose MCAP summaries or rosbag2 metadata count at most
    AHEAD_MAX_MESSAGES (the chunks are held until the log is joined from them: twice the log's
    memory while it is read); else None."""
    if markers_csv is not None:
        return nullcontext()
    try:
        total = message_count(bag)
    except Exception:  # noqa: BLE001 - nothing to go by: the reading names the bag's faults
        return nullcontext()
    if total is None:
        return nullcontext()
    return FirstPassAhead(config, method) if total <= AHEAD_MAX_MESSAGES else nullcontext()


def _on_the_bags_clock(
    log: SensorLog, report: BagReport, config: NavConfig
) -> tuple[marker_clock.MarkerClock | None, SensorLog | None]:
    """The markers' clock against the bag's (faults.marker_clock, on every marker: those
    outside the data too) and, where it is to be taken out, ``log`` with them re-timed (named
    in the report, whose warnings about markers outside the data are made again), else None
    (the offset named where it is to be said: not one clocks are known to be apart by)."""
    markers = log.markers + report.markers_outside
    dr = imu_model.choose(log, config, report.imu_noise_declared).config
    found = marker_clock.measure(log, markers, dr)
    if found is None or not found.retime:
        if found is not None and found.named:
            report.warn(found.describe(
                "not re-timed, as it is not an offset clocks are known to be apart by (GPS "
                "time's 18 s, a time zone's quarter hours): correct the markers' times"
            ))  # fmt: skip
        return found, None
    said = set(_outside_warnings(log, log.markers, report.markers_outside))
    report.warnings = [w for w in report.warnings if w not in said]
    moved = replace(log, markers=marker_clock.retimed(markers, found))
    moved.markers = _markers_inside(moved, report)
    report.warn(found.describe())
    return found, moved


def _retried_on_the_bags_clock(
    log: SensorLog,
    report: BagReport,
    result: SmoothResult,
    config: NavConfig,
    smooth: Callable[..., SmoothResult],
    say: Say,
) -> tuple[SensorLog, SmoothResult]:
    """The run smoothed again with its markers re-timed where their clock is found off the
    bag's (:func:`_on_the_bags_clock`) and the markers then agree with it; else ``log`` and
    ``result`` as they were (the report too, but for the offset named)."""
    kept = (list(report.warnings), list(report.markers_outside))
    clock, moved = _on_the_bags_clock(log, report, config)
    if clock is None or moved is None:
        return log, result
    if len(moved.markers) >= 2:
        say("smoothing again with the markers re-timed")
        try:
            again = _smooth_segments(moved, report, config, smooth, say)
        except ValueError:  # no solution re-timed either: the run as it was, and the offset said
            again = None
        if again is not None and not again.summary.get("marker_disagreement"):
            report.warnings = list(dict.fromkeys(report.warnings))  # a gap's, said twice
            return moved, again
    report.warnings, report.markers_outside = kept
    report.warn(clock.describe("not re-timed: the markers disagree with the run re-timed so too"))
    return log, result


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
    method: str = DEFAULT_METHOD,
    iterations: int = MAX_PASSES,
    progress: Progress = QUIET,
    reverse: bool = False,
    ahead: FirstPassAhead | None = None,
) -> SmoothResult:
    """smooth_log (``reverse``: of a log in reversed time) with ``imu_grade: auto`` resolved
    from the run (imu_model.choose: the static spans, else ``declared``, the variances the Imu
    messages declare: BagReport's imu_noise_declared) and, while the smoothed run still shows
    that the model does not fit (Navigator.model_warnings), refitted with the next noisier
    grade. The summary's ``imu_model`` says which model was used and why; a named grade is used
    as given (its misfit warnings stay). ``progress`` is told each stage and the fraction of
    each filter pass done, of every smoothing run (the marker outliers' too). ``ahead``: the
    first pass run while the bag was read (smooth_log takes it where it is this log's)."""
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
                lg,
                cfg,
                method=method,
                iterations=iterations,
                progress=progress,
                reverse=reverse,
                ahead=ahead,
            ),
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


def require_imu(
    log: SensorLog, report: BagReport, bag: str | os.PathLike[str], topics: TopicNames
) -> None:
    """ValueError when the bag gave no IMU sample, naming the type its IMU topic carries."""
    if len(log.imu) == 0:
        found = report.types.get(topics.imu)
        carries = f" (it carries {found})" if found else ""
        raise ValueError(f"{bag}: no IMU samples on {topics.imu}{carries}")


def require_markers(
    log: SensorLog, report: BagReport, bag: str | os.PathLike[str], topics: TopicNames
) -> None:
    """ValueError when no marker lies within the data, naming those left out."""
    if log.markers:
        return
    left = [w for w in report.warnings if w.startswith("marker ")]
    why = f" ({left[0]}{f' and {len(left) - 1} more' if len(left) > 1 else ''})" if left else ""
    raise ValueError(
        f"{bag}: no markers within the data (topic {topics.markers} or --markers CSV){why}: "
        "nothing ties the run to the ground"
    )


def run_welds(
    log: SensorLog, result: SmoothResult, config: NavConfig, jolts: np.ndarray | None = None
) -> list[Weld]:
    """The girth welds of a smoothed run (products.welds.detect_welds) with the pig's pipe
    diameter and IMU mount (``jolts``: the IMU's jolt_deviation, when found before)."""
    return detect_welds(log, result.centreline, result.datum, pipe_diameter=config.pipe_diameter,
                        r_base_imu=imu_mount(config), jolts=jolts)  # fmt: skip


def imu_mount(config: NavConfig) -> np.ndarray:
    """(3, 3) imu_link -> base_link of the configured IMU mount."""
    from pipe_nav_core.filter.ingest import mount_rotation

    return mount_rotation(config.imu_mount_rpy)


def weld_summary(welds: Sequence[Weld]) -> dict[str, object]:
    """What the summary says of the welds: how many, how many filled in, the typical joint."""
    joints = [w.joint_length for w in welds if math.isfinite(w.joint_length)]
    return {"count": len(welds), "filled": sum(w.confidence == 0.0 for w in welds),
            "median_joint_m": float(np.median(joints)) if joints else None}  # fmt: skip


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
        write_products_csv(report, outputs, staged)
    return report, notes
