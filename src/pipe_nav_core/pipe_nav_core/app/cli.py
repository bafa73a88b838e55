"""The ``pipe-nav`` command line (INTERFACES.md).

    pipe-nav smooth IN --out OUT.mcap|DIR/ [--csv F] [--geojson F] [--kml F] [--plot F.png]
    pipe-nav replay IN --out OUT.mcap
    pipe-nav simulate --scenario NAME --seed N --out RUN.mcap
    pipe-nav info IN [--json]
    pipe-nav config [--template]
    pipe-nav locate TALLY.csv --run SMOOTHED.mcap --out FEATURES.csv [--geojson F]
    pipe-nav compare A_SMOOTHED.mcap B_SMOOTHED.mcap --out MOVEMENT.csv [--dask-scheduler ADDR]
    pipe-nav fuse RUN_SMOOTHED.mcap... --out FUSED.csv [--dask-scheduler ADDR]
    pipe-nav evaluate CENTERLINE.csv --truth TRUTH.csv
    pipe-nav bench [--quick]

Errors are one line on stderr with a non-zero exit status, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from pipe_nav_core.config import ConfigError, NavConfig
from pipe_nav_core.errors import PipeNavError

if TYPE_CHECKING:
    from pipe_nav_core.app.plot_process import PlotProcess
    from pipe_nav_core.products import IntegrityReport

EXIT_ERROR = 2
EXIT_NOT_OK = 3  # smooth --strict: the run's quality verdict is not OK
EXIT_INTERNAL = 70  # an internal error (EX_SOFTWARE): a bug, not the input
SIM_EPOCH = 1780272000.0  # 2026-06-01T00:00:00Z: simulated bags carry realistic stamps


class CliError(PipeNavError):
    """A user error with a one-line message."""


def _load_config(args: argparse.Namespace) -> NavConfig:
    """The settings of --config, then each --set, then the dedicated options, validated one
    source at a time so that an error names the option the user typed."""
    sources: list[tuple[str, dict[str, Any]]] = []
    if getattr(args, "config", None):
        sources.append((f"--config {args.config}", _read_config_file(args.config)))
    for item in getattr(args, "set", None) or []:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise CliError(f"--set expects KEY=VALUE, not {item!r}")
        sources.append((f"--set {item}", {key.strip(): _parse_value(raw.strip())}))
    for option, field, value in (
        ("--mode", "mode", getattr(args, "mode", None)),
        ("--imu-grade", "imu_grade", getattr(args, "imu_grade", None)),
        ("--mount-rpy-deg", "imu_mount_rpy_deg", getattr(args, "mount_rpy_deg", None)),
    ):
        if value:
            sources.append((option, {field: list(value) if field.endswith("_deg") else value}))
    values: dict[str, Any] = {}
    for option, more in sources:
        values.update(more)
        try:
            NavConfig.from_dict(values)
        except ConfigError as exc:
            raise CliError(f"{option}: {_one_line(exc)}") from None
    return NavConfig.from_dict(values)


_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def _parse_value(raw: str) -> Any:
    """A --set value: JSON (``3``, ``true``, ``[0, 0, -0.05]``), a list of numbers separated
    by commas or spaces (``0,0,-0.05``, ``0 0 -0.05``), else the string itself."""
    try:
        return json.loads(raw)
    except json.JSONDecodeError:
        pass
    parts = [x for x in re.split(r"[,\s]+", raw.strip("[]() ")) if x]
    if len(parts) > 1 and all(re.fullmatch(_NUMBER, x) for x in parts):
        return [float(x) for x in parts]
    return raw


def _read_config_file(path: str) -> dict[str, Any]:
    """A flat mapping of settings from YAML or JSON; a ROS parameter file
    (``node: ros__parameters: {...}``) is accepted too."""
    from ruamel.yaml import YAML, YAMLError

    try:
        text = Path(path).read_text(encoding="utf-8")
        data = YAML(typ="safe", pure=True).load(text)
    except OSError as exc:
        raise CliError(f"{path}: {exc.strerror or exc}") from None
    except YAMLError as exc:
        raise CliError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise CliError(f"{path}: expected a mapping of settings")
    for value in data.values():
        if isinstance(value, dict) and "ros__parameters" in value:
            data = value["ros__parameters"]
            break
    return {
        k: v for k, v in data.items() if k in NavConfig.__dataclass_fields__ or k.endswith("_deg")
    }


def _topics(args: argparse.Namespace):  # noqa: ANN202
    from pipe_nav_core.io import TopicNames

    return TopicNames(
        imu=args.imu_topic, odometer=args.odom_topic, mag=args.mag_topic, markers=args.markers_topic
    )


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="YAML/JSON file of estimator settings (or the ROS ekf.yaml)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override one setting")
    p.add_argument("--mode", choices=["ins", "dr"], help="mechanization (default ins)")
    p.add_argument(
        "--imu-grade",
        choices=["auto", "consumer", "industrial", "tactical"],
        help="IMU noise model (default auto: measured from the run)",
    )
    p.add_argument(
        "--mount-rpy-deg",
        type=float,
        nargs=3,
        metavar=("R", "P", "Y"),
        help="imu_link in base_link",
    )
    p.add_argument("--markers", help="marker CSV adding to or replacing the bag's /markers")
    p.add_argument("--imu-topic", default="/imu/data")
    p.add_argument("--odom-topic", default="/odom/wheel")
    p.add_argument("--mag-topic", default="/imu/mag")
    p.add_argument("--markers-topic", default="/markers")
    p.add_argument("--quiet", action="store_true", help="no progress output")


class _Progress:
    """A progress bar on stderr: the stage as its label, the fraction of the current pass as
    its fill. Nothing at all when stderr is not a terminal or with --quiet."""

    def __init__(self) -> None:
        from tqdm import tqdm

        self.bar = tqdm(
            total=100,
            file=sys.stderr,
            leave=False,
            unit="%",
            bar_format=("{desc:<48} {percentage:3.0f}% |{bar:30}| {elapsed}"),
        )

    def stage(self, msg: str) -> None:
        self.bar.set_description_str(f"pipe-nav: {msg}")
        self.bar.n = 0
        self.bar.refresh()

    def fraction(self, f: float) -> None:
        self.bar.n = round(100 * f)
        self.bar.refresh()

    def close(self) -> None:
        self.bar.close()


def _progress(quiet: bool) -> _Progress | None:
    return None if quiet or not sys.stderr.isatty() else _Progress()


def _warm_kernels() -> None:
    """Compile the kernels first if this install has not (a line on stderr says so)."""
    from pipe_nav_core.warmup import ensure_warm

    ensure_warm(lambda m: print(f"pipe-nav: {m.partition(': ')[2]}", file=sys.stderr))


def cmd_smooth(args: argparse.Namespace) -> int:
    from pipe_nav_core.app.plot_process import PlotProcess

    # forked first, before the numeric imports: it loads matplotlib while this one smooths
    wants_plot = bool(args.plot) or _out_is_dir(args.out)
    with PlotProcess.start() if wants_plot else PlotProcess(None, None) as plotter:
        return _smooth(args, plotter)


def _out_is_dir(out: str) -> bool:
    """--out names a directory (the products are written into it, named like the bag)."""
    return out.endswith(("/", "\\")) or Path(out).is_dir()


def _smooth(args: argparse.Namespace, plotter: PlotProcess) -> int:
    from pipe_nav_core.app.pipeline import Outputs, smooth_bag

    cfg = _load_config(args)
    out = Path(args.out)
    stem = Path(str(args.input).rstrip("/")).stem
    if _out_is_dir(args.out):
        out.mkdir(parents=True, exist_ok=True)
        outputs = Outputs(
            bag=str(out / f"{stem}_smoothed.mcap"),
            csv=args.csv or str(out / f"{stem}_centerline.csv"),
            geojson=args.geojson or str(out / f"{stem}_centerline.geojson"),
            kml=args.kml or str(out / f"{stem}_centerline.kml"),
            plot=args.plot or str(out / f"{stem}_report.png"),
        )
    else:
        outputs = Outputs(
            bag=str(out), csv=args.csv, geojson=args.geojson, kml=args.kml, plot=args.plot
        )
    outputs = outputs.with_products()
    _warm_kernels()
    bar = _progress(args.quiet)
    try:
        result, report = smooth_bag(
            args.input,
            outputs,
            config=cfg,
            method=args.method,
            iterations=args.iterations,
            markers_csv=args.markers,
            spacing=args.spacing,
            topics=_topics(args),
            progress=bar,
            bends_reference=args.bends_reference,
            plotter=plotter,
        )
    finally:
        if bar is not None:
            bar.close()
    for w in report.warnings:
        print(f"pipe-nav: warning: {w}", file=sys.stderr)
    if not args.quiet:
        _print_summary(result.summary, args.method)
        print("outputs:")
        for p in outputs.paths():
            print(f"  {p}")
    status = (result.summary.get("quality") or {}).get("status", "OK")
    if status != "OK":
        print(f"pipe-nav: quality {status} (see the summary)", file=sys.stderr)
    return EXIT_NOT_OK if args.strict and status != "OK" else 0


def _print_summary(s: dict[str, Any], method: str) -> None:
    print(f"smoothed with {method}:")
    print(f"  distance            {s['distance_m']:.2f} m in {s['duration_s']:.1f} s")
    print(
        f"  markers             {s['markers_used']} used, {s['markers_rejected']} rejected, "
        f"{s['markers_total']} in total"
    )
    rej = s.get("rejected_updates") or {}
    print("  rejected updates    " + (", ".join(f"{k} {v}" for k, v in rej.items()) or "none"))
    print(f"  odometer scale      {s['odometer_scale']:.5f}")
    print("  gyro bias           " + " ".join(f"{x:+.2f}" for x in s["gyro_bias_deg_h"]) + " deg/h")
    print("  accel bias          " + " ".join(f"{x:+.3f}" for x in s["accel_bias_mg"]) + " mg")
    print(f"  max sigma between markers (horizontal) {s['max_sigma_h_between_markers_m']:.3f} m")
    print(f"  max marker residual {s['max_marker_residual_m']:.3f} m")
    products = s.get("integrity") or {}
    if products:
        print(
            f"  bends               {products['bends']} (window "
            f"{products['curvature_window_m']:.2f} m), strain features "
            f"{products['strain_features']}, max strain "
            f"{products['max_strain_pct']:.4f} %"
            + "".join(f"; {n}" for n in products.get("notes", []))
        )
    if "graph_iterations" in s:
        gated = s.get("graph_factors_gated") or {}
        down = s.get("graph_markers_downweighted") or []
        print(
            f"  graph               {s['graph_iterations']} Gauss-Newton iteration(s) after "
            f"{s.get('passes_run', '?')} RTS pass(es), "
            + ("converged" if s.get("graph_converged") else "NOT converged")
            + f"; markers downweighted: {', '.join(down) or 'none'}; factors gated: "
            + (", ".join(f"{k} {v}" for k, v in gated.items()) or "none")
        )
    model = s.get("imu_model") or {}
    if model:
        how = model["reason"] if model.get("auto") else "given"
        print(f"  IMU model           {model['grade']} ({how})")
    q = s.get("quality") or {}
    if q:
        reasons = "; ".join(q["reasons"])
        print(f"  quality             {q['status']}" + (f": {reasons}" if reasons else ""))


def cmd_replay(args: argparse.Namespace) -> int:
    from pipe_nav_core.app.pipeline import replay_bag

    cfg = _load_config(args)
    _warm_kernels()
    result, report = replay_bag(
        args.input, args.out, config=cfg, markers_csv=args.markers, topics=_topics(args)
    )
    for w in report.warnings:
        print(f"pipe-nav: warning: {w}", file=sys.stderr)
    if not args.quiet:
        d = result.diagnostics
        print(f"replayed {len(result.estimates)} estimates -> {args.out}")
        rej = {k: v for k, v in d.items() if str(k).startswith(("rejected_", "late_")) and v}
        print("  rejected/late: " + (", ".join(f"{k} {v}" for k, v in rej.items()) or "none"))
        if "imu_model" in d:
            print(f"  IMU model: {d['imu_model']} ({d['imu_model_reason']})")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    import dataclasses

    import numpy as np

    from pipe_nav_core.io import write_centreline_csv, write_markers_csv, write_sensor_bag
    from pipe_nav_core.io.atomic import ensure_not_input
    from pipe_nav_core.sim import get_scenario, simulate
    from pipe_nav_core.sim.tally import make_tally
    from pipe_nav_core.sim.truth_products import truth_product_paths, write_truth_products

    out = Path(args.out)
    scenario = dataclasses.replace(get_scenario(args.scenario), t0=float(args.t0))
    run = simulate(scenario, seed=args.seed)
    truth_csv = out.with_name(out.stem + ".truth.csv")
    markers_csv = out.with_name(out.stem + ".markers.csv")
    config_yaml = out.with_name(out.stem + ".config.yaml")
    tally_csv = out.with_name(out.stem + ".tally.csv")
    for p in (out, truth_csv, markers_csv, config_yaml, tally_csv, *truth_product_paths(out)):
        ensure_not_input(str(p), [])
    write_sensor_bag(str(out), run.log)
    write_centreline_csv(str(truth_csv), run.truth, run.datum)
    truth_strain, truth_bends = write_truth_products(out, run)
    write_markers_csv(str(markers_csv), run.log.markers)
    _write_settings(config_yaml, scenario.estimator_settings(), out.name)
    if scenario.mag_enabled:  # a vendor's tally of the pipe's welds and features (locate)
        make_tally(run.welds, np.random.default_rng([args.seed, 19])).write_csv(tally_csv)
    if not args.quiet:
        print(f"simulated {args.scenario} (seed {args.seed}): {len(run.log.imu)} IMU samples")
        print(f"  bag    {out}\n  truth  {truth_csv}\n  survey {markers_csv}")
        print(f"  truth of the products {truth_strain}, {truth_bends}")
        if scenario.mag_enabled:
            print(f"  vendor tally {tally_csv} (pipe-nav locate {tally_csv.name} --run ...)")
        print(f"  settings {config_yaml} (pipe-nav smooth {out.name} --config {config_yaml.name})")
    return 0


def _write_settings(path: Path, settings: dict[str, Any], bag_name: str) -> None:
    """The estimator settings of a simulated run as a --config file (SI units, radians)."""
    from ruamel.yaml import YAML

    from pipe_nav_core.io.atomic import atomic_write

    yaml = YAML(typ="safe", pure=True)
    yaml.default_flow_style = None
    with atomic_write(path) as f:
        f.write(
            "# Estimator settings for this simulated run: what its user would know (IMU grade,\n"
            "# mounting, pipe, odometer), never its realised errors. SI units, radians.\n"
            f"# pipe-nav smooth {bag_name} --config {path.name}\n"
        )
        yaml.dump({k: list(v) if isinstance(v, tuple) else v for k, v in settings.items()}, f)


def cmd_config(args: argparse.Namespace) -> int:
    """--template: the settings file of one pig; else every setting in effect after --config
    and --set (angles in degrees), as YAML that --config reads back."""
    if args.template:
        from pipe_nav_core.app.settings_template import template_text

        print(template_text(), end="")
        return 0
    from pipe_nav_core.app.settings_template import degrees_of, yaml_value
    from pipe_nav_core.config import ANGLE_FIELDS

    for name, value in _load_config(args).to_dict().items():
        if name in ANGLE_FIELDS:
            name, value = f"{name}_deg", degrees_of(value)
        if name == "imu_overrides":
            print("imu_overrides: {" + ", ".join(f"{k}: {v!r}" for k, v in value.items()) + "}")
        else:
            print(f"{name}: {yaml_value(value)}")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from pipe_nav_core.app.info import describe_bag, format_info

    info = describe_bag(args.input, _load_config(args), _topics(args), args.markers)
    print(json.dumps(info, indent=2) if args.json else format_info(info))
    return 0


def cmd_bends(args: argparse.Namespace) -> int:
    from pipe_nav_core.app.pipeline import Outputs, products_of_file

    for name, value in (
        ("curvature_window", args.window),
        ("strain_thresholds", args.thresholds),
        ("bend_min_angle_deg", args.min_angle_deg),
        ("pipe_outer_diameter", args.outer_diameter),
    ):
        if value is not None:
            args.set = (args.set or []) + [f"{name}={json.dumps(value)}"]
    cfg = _load_config(args)
    src = str(args.input).rstrip("/")
    outputs = Outputs(csv=args.out + ".csv" if args.out else src).with_products()
    outputs = Outputs(strain=outputs.strain, bends=outputs.bends,
                      strain_features=outputs.strain_features)  # fmt: skip
    report, notes = products_of_file(src, outputs, config=cfg, spacing=args.spacing,
                                     bends_reference=args.bends_reference)  # fmt: skip
    for note in notes:
        print(f"pipe-nav: note: {note}", file=sys.stderr)
    if not args.quiet:
        print(format_bends(report))
        print("outputs:")
        for p in outputs.paths():
            print(f"  {p}")
    return 0


def format_bends(report: IntegrityReport) -> str:
    """The bend list and strain features as a table for people."""
    s = report.summary()
    lines = [
        f"curvature window {report.window:.2f} m, outer diameter {report.outer_diameter:.3f} m; "
        f"max strain {s['max_strain_pct']:.4f} %",
        f"{'bend':>4} {'apex_m':>10} {'angle_deg':>10} {'radius_m':>10} {'radius_D':>9} "
        f"{'direction':>10} class",
    ]
    lines += [
        f"{b.number:>4} {b.apex_m:>10.2f} {math.degrees(b.angle):>10.2f} {b.radius:>10.2f} "
        f"{b.radius_d:>9.1f} {b.direction:>10} {b.kind}"
        for b in report.bends
    ]
    lines.append(f"strain features over {', '.join(f'{t:g} %' for t in report.thresholds_pct)}: "
                 f"{len(report.features)}")  # fmt: skip
    lines += [
        f"  {x.number:>3} {x.start_m:.1f}-{x.end_m:.1f} m peak {x.peak_pct:.4f} % "
        f"(over {x.threshold_pct:g} %)"
        + (f", bend {x.bend}" if x.bend else ", no bend")
        + (
            ""
            if x.construction is None
            else (", as-built" if x.construction else ", not construction-related")
        )
        for x in report.features
    ]
    return "\n".join(lines)


def cmd_evaluate(args: argparse.Namespace) -> int:
    from pipe_nav_core.bench.evaluation import score
    from pipe_nav_core.io import read_centreline_csv, read_markers_csv

    def warn(message: str) -> None:
        print(f"pipe-nav: warning: {message}", file=sys.stderr)

    est, datum = read_centreline_csv(args.centreline, warn)
    truth, tdatum = read_centreline_csv(args.truth, warn)
    markers = read_markers_csv(args.markers) if args.markers else None
    sc = score(est, truth, markers, datum=datum or tdatum)
    data = {
        k: (None if isinstance(v, float) and not math.isfinite(v) else v)
        for k, v in vars(sc).items()
    }
    if args.json:
        print(json.dumps(data, indent=2))
    else:
        for k, v in data.items():
            print(f"{k:28s} {v}")
    return 0


def cmd_locate(args: argparse.Namespace) -> int:
    from pipe_nav_core.io.atomic import check_output, ensure_not_input
    from pipe_nav_core.io.smoothed_bag import CENTRELINE_ATTACHMENT, read_smoothed_run
    from pipe_nav_core.io.tally_csv import read_tally_csv, write_located
    from pipe_nav_core.io.welds_csv import read_welds_csv
    from pipe_nav_core.products.tally import locate_tally

    inputs = [args.tally, args.run] + ([args.welds] if args.welds else [])
    for path, option in ((args.out, "--out"), (args.geojson, "--geojson")):
        if path:
            check_output(path, option)
            ensure_not_input(path, inputs)
    if args.out and args.geojson and Path(args.out).resolve() == Path(args.geojson).resolve():
        raise CliError(f"--out and --geojson name the same file {args.out}")
    if not (0.0 < args.scale_tolerance < 0.2):
        raise CliError(f"--scale-tolerance must be between 0 and 0.2, not {args.scale_tolerance}")
    tally = read_tally_csv(args.tally)
    run = read_smoothed_run(args.run)
    welds = read_welds_csv(args.welds) if args.welds else run.welds
    if not welds:
        raise CliError(f"{args.run}: no girth welds in it (smoothed without a magnetometer?): "
                       "give them with --welds RUN_welds.csv")  # fmt: skip
    if CENTRELINE_ATTACHMENT not in run.attachments:
        print(f"pipe-nav: note: {args.run}: no centreline.csv in it: chainage is the arc length "
              "of its path and the sigmas are unknown", file=sys.stderr)  # fmt: skip
    loc = locate_tally(tally, welds, run.trajectory, scale_tolerance=args.scale_tolerance)
    write_located(args.out, args.geojson, tally, loc.rows)
    for note in loc.notes:
        print(f"pipe-nav: note: {note}", file=sys.stderr)
    if not args.quiet:
        feats = [r for r in loc.rows if not r.row.weld]
        alone = sum(r.matched_weld is None for r in loc.rows)
        print(f"{len(loc.rows)} tally rows located ({len(feats)} features), "
              f"{alone} without a matched weld")  # fmt: skip
        print("outputs:")
        for p in (args.out, args.geojson):
            if p:
                print(f"  {p}")
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    from pipe_nav_core.app.runs import compare_files

    cfg = _load_config(args)
    report, paths = compare_files(args.run_a, args.run_b, args.out, cfg,
                                  threshold=args.threshold, n_sigma=args.n_sigma,
                                  workers=args.workers,
                                  dask_scheduler=args.dask_scheduler)  # fmt: skip
    for note in report.notes:
        print(f"pipe-nav: note: {note}", file=sys.stderr)
    if not args.quiet:
        s = report.summary()
        print(f"{s['points']} points compared ({s['weld_pairs']} welds, {s['bend_pairs']} "
              f"bends), largest displacement {s['max_displacement_m']:.3f} m; "
              f"{s['intervals']} movement interval(s) over {report.n_sigma:g} sigma and "
              f"{report.threshold:g} m")  # fmt: skip
        for iv in report.intervals:
            print(
                f"  {iv.number:>3} {iv.start_m:.1f}-{iv.end_m:.1f} m peak "
                f"{iv.peak_magnitude:.3f} m at {iv.peak_m:.1f} m ({iv.points} points)"
            )
        print("outputs:")
        for p in paths:
            print(f"  {p}")
    return 0


def cmd_fuse(args: argparse.Namespace) -> int:
    import numpy as np

    from pipe_nav_core.app.runs import fuse_files

    settings = {k: v for k, v in (("spacing", args.spacing), ("error_spacing", args.error_spacing),
                                  ("correlation_length", args.correlation_length),
                                  ("white_sigma", args.white_sigma)) if v is not None}  # fmt: skip
    result = fuse_files(args.runs, args.out, workers=args.workers,
                        dask_scheduler=args.dask_scheduler, **settings)  # fmt: skip
    for note in result.notes:
        print(f"pipe-nav: note: {note}", file=sys.stderr)
    if not args.quiet:
        line = result.centreline
        span = float(line.distance[-1] - line.distance[0])
        sig_h = float(np.mean(np.hypot(line.sigma_enu[:, 0], line.sigma_enu[:, 1])))
        print(f"{len(args.runs)} runs fused over {span:.1f} m; mean fused sigma_h {sig_h:.3f} m")
        print(f"{'run':>4} {'welds':>6} {'rms_h_m':>8} {'max_h_m':>8} {'rms_v_m':>8} "
              f"{'max_v_m':>8}  file")  # fmt: skip
        for r, path in zip(result.residuals, args.runs, strict=True):
            print(f"{r.index:>4} {r.welds_matched:>6} {r.rms_h:>8.3f} {r.max_h:>8.3f} "
                  f"{r.rms_v:>8.3f} {r.max_v:>8.3f}  {path}")  # fmt: skip
        print(f"output:\n  {args.out}")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from pipe_nav_core.bench.accuracy import main as bench_main

    _warm_kernels()
    return bench_main(args)


class _Parser(argparse.ArgumentParser):
    """argparse with the command line's one-line errors (``pipe-nav smooth: error: ...``,
    exit status 2) instead of the usage block; ``-h`` still prints the usage."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_ERROR, f"{self.prog}: error: {message} (see {self.prog} -h)\n")


def _add_runs_options(p: argparse.ArgumentParser) -> None:
    """Where the per-run work of a command over several runs is done (pipe_nav_core.app.runs)."""
    p.add_argument("--workers", type=int, help="local processes (default: one per run, "
                   "at most the CPUs)")  # fmt: skip
    p.add_argument(
        "--dask-scheduler",
        metavar="ADDRESS",
        help="run on this Dask distributed cluster (tcp://host:8786) instead",
    )


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="pipe-nav", description="Pipeline pig navigation (ROS-free core).")
    ap.add_argument("--debug", action="store_true",
                    help="on an error, the Python traceback instead of one line")  # fmt: skip
    sub = ap.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("smooth", help="smooth a recorded bag into a centreline")
    p.add_argument("input", help="bag: a .mcap file or a rosbag2 directory")
    p.add_argument(
        "--out", required=True, help="output .mcap, or a folder (ending in /) for all outputs"
    )
    p.add_argument("--csv", help="centreline CSV")
    p.add_argument("--geojson", help="centreline GeoJSON")
    p.add_argument("--kml", help="centreline KML")
    p.add_argument("--plot", help="report PNG")
    p.add_argument("--method", default="rts", choices=["rts", "two-filter", "forward", "graph"])
    p.add_argument("--iterations", type=int, default=2, help="re-linearization passes (default 2)")
    p.add_argument("--spacing", type=float, default=0.5, help="CSV row spacing, m of chainage")
    p.add_argument("--strict", action="store_true", help="exit 3 unless the quality verdict is OK")
    p.add_argument("--bends-reference", metavar="CSV",
                   help="as-built bends (start_m,end_m): strain features outside them are "
                   "marked not construction-related")  # fmt: skip
    _add_common(p)
    p.set_defaults(func=cmd_smooth)

    p = sub.add_parser("replay", help="run the online estimator over a bag as ekf_node does")
    p.add_argument("input")
    p.add_argument("--out", required=True, help="output .mcap with /pipe_nav/odometry")
    _add_common(p)
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("simulate", help="simulate a pig run into a bag plus its truth")
    p.add_argument("--scenario", required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="output .mcap (truth and survey CSVs beside it)")
    p.add_argument(
        "--t0",
        type=float,
        default=SIM_EPOCH,
        help="UNIX time of the first sample, s (default 2026-06-01)",
    )
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("config", help="a settings file for a pig, or the settings in effect")
    p.add_argument("--template", action="store_true", help="the settings file of one pig")
    p.add_argument("--config", help="YAML/JSON file of estimator settings (or the ROS ekf.yaml)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override one setting")
    p.set_defaults(func=cmd_config)

    p = sub.add_parser("info", help="what a bag holds, before smoothing it")
    p.add_argument("input", help="bag: a .mcap file or a rosbag2 directory")
    p.add_argument("--json", action="store_true", help="the same as JSON")
    _add_common(p)
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("bends", help="bends and strain of a smoothed run, with other settings")
    p.add_argument("input", help="a smoothed .mcap (pipe-nav smooth --out) or a centreline CSV")
    p.add_argument("--out", metavar="RUN",
                   help="write RUN_strain.csv, RUN_bends.csv, RUN_strain_features.csv "
                   "(default: beside the input, named like it)")  # fmt: skip
    p.add_argument("--window", type=float, help="curvature window, m of chainage")
    p.add_argument("--thresholds", type=float, nargs="+", metavar="PCT",
                   help="strain feature thresholds, percent")  # fmt: skip
    p.add_argument("--min-angle-deg", type=float, help="smallest bend listed, deg")
    p.add_argument("--outer-diameter", type=float, help="pipe outer diameter, m")
    p.add_argument("--spacing", type=float, default=0.5, help="strain row spacing, m")
    p.add_argument("--bends-reference", metavar="CSV", help="as-built bends (start_m,end_m)")
    p.add_argument("--config", help="YAML/JSON file of settings")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override one setting")
    p.add_argument("--imu-grade", choices=["auto", "consumer", "industrial", "tactical"],
                   help="IMU noise model of the sigmas (default: the bag's)")  # fmt: skip
    p.add_argument("--quiet", action="store_true", help="no table")
    p.set_defaults(func=cmd_bends)

    p = sub.add_parser("locate", help="give a vendor tally's welds and features coordinates")
    p.add_argument("tally", help="the ILI vendor's pipe tally CSV (README: accepted columns)")
    p.add_argument("--run", required=True, help="the smoothed .mcap (pipe-nav smooth --out)")
    p.add_argument("--out", required=True, help="FEATURES.csv: the tally's columns + positions")
    p.add_argument("--geojson", help="also the located rows as GeoJSON points")
    p.add_argument("--welds", help="RUN_welds.csv to use instead of the bag's welds")
    p.add_argument("--scale-tolerance", type=float, default=0.01,
                   help="vendor odometer scale error to allow (default 0.01 = 1 %%)")  # fmt: skip
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_locate)

    p = sub.add_parser("evaluate", help="score a centreline CSV against a truth CSV")
    p.add_argument("centreline")
    p.add_argument("--truth", required=True, help="truth in the centreline CSV format")
    p.add_argument("--markers", help="marker CSV (for the between-markers figures)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("compare", help="movement of the pipe between two smoothed runs")
    p.add_argument("run_a", help="the earlier run: a smoothed .mcap (pipe-nav smooth --out)")
    p.add_argument("run_b", help="the later run, through the same pipe")
    p.add_argument(
        "--out",
        required=True,
        metavar="MOVEMENT.csv",
        help="the movement CSV (its .geojson and .png are written beside it)",
    )
    p.add_argument(
        "--threshold",
        type=float,
        metavar="M",
        help="smallest displacement reported as movement, m (default 0.05)",
    )
    p.add_argument("--n-sigma", type=float, help="and over this many sigma (default 3)")
    _add_runs_options(p)
    p.add_argument("--config", help="YAML/JSON file of settings (curvature and bends)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override one setting")
    p.add_argument(
        "--imu-grade",
        choices=["auto", "consumer", "industrial", "tactical"],
        help="IMU noise model of the curvature sigmas (default: the bag's)",
    )
    p.add_argument("--quiet", action="store_true", help="no summary")
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser("fuse", help="one centreline from several runs through one pipe")
    p.add_argument(
        "runs",
        nargs="+",
        metavar="RUN",
        help="smoothed .mcap bags; the first gives the chainage and the map frame",
    )
    p.add_argument("--out", required=True, metavar="FUSED.csv", help="fused centreline CSV")
    p.add_argument("--spacing", type=float, help="row spacing, m of chainage (default 0.5)")
    p.add_argument("--error-spacing", type=float, help="nodes of each run's error, m (10)")
    p.add_argument(
        "--correlation-length",
        type=float,
        help="of each run's error along the pipe, m (default 50)",
    )
    p.add_argument("--white-sigma", type=float, help="position noise beyond it, m (0.005)")
    _add_runs_options(p)
    p.add_argument("--quiet", action="store_true", help="no residual table")
    p.set_defaults(func=cmd_fuse)

    p = sub.add_parser("bench", help="accuracy (and speed) benchmark on simulated runs")
    p.add_argument("--quick", action="store_true", help="fewer scenarios and seeds")
    p.add_argument("--speed", action="store_true", help="also run the speed benchmark")
    p.add_argument("--speed-only", action="store_true", help="only the speed benchmark")
    p.add_argument(
        "--products", action="store_true", help="also the bend/strain table per IMU grade"
    )
    p.add_argument("--products-only", action="store_true", help="only the bend/strain table")
    p.add_argument("--welds", action="store_true", help="also the girth weld and tally table")
    p.add_argument("--welds-only", action="store_true", help="only the weld table")
    p.add_argument("--runs", action="store_true", help="also the movement and fusion table")
    p.add_argument("--runs-only", action="store_true", help="only the movement/fusion table")
    p.add_argument("--length-km", type=float, default=10.0, help="field run length for --speed")
    p.add_argument("--out", default="BENCHMARKS.md", help="Markdown table")
    p.add_argument("--json", default="bench_out/benchmarks.json", help="JSON results")
    p.add_argument("--scenarios", nargs="*", help="subset of scenarios")
    p.add_argument(
        "--pipe-seed",
        type=int,
        help="run through another pipe: marker surveys, weld anomalies, field bends drawn anew",
    )
    p.set_defaults(func=cmd_bench)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if main_thread else None
    try:
        return int(args.func(args) or 0)
    except _Terminated:
        print("pipe-nav: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print("pipe-nav: interrupted", file=sys.stderr)
        return 130
    except (PipeNavError, ValueError, OSError, KeyError) as exc:
        if args.debug:
            raise
        print(f"pipe-nav: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_ERROR
    except Exception as exc:  # a bug: one line (the traceback with --debug)
        if args.debug:
            raise
        print(f"pipe-nav: internal error: {type(exc).__name__}: {_one_line(exc)} (a bug; "
              "`pipe-nav --debug ...` shows where)", file=sys.stderr)  # fmt: skip
        return EXIT_INTERNAL
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous or signal.SIG_DFL)


def run() -> NoReturn:
    """The ``pipe-nav`` command: main(), then out of the process at once. Everything is written
    and closed by then; the interpreter's teardown of numba, numpy and matplotlib would add
    about 0.4 s to every command (a fifth of smoothing the sample).

    BLAS runs on one thread here (OPENBLAS_NUM_THREADS=1 unless the user set it, before numpy
    is imported): its matrices are small (states of 30, fits of 10 columns), and its spinning
    helper threads took the core that the plot process, the recording's packing thread and the
    bag readers use, making a 1 ms least-squares fit take 25 ms."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that every output being written is cleaned up."""


def _terminate(signum: int, frame: object) -> None:
    raise _Terminated()


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


if __name__ == "__main__":
    run()
