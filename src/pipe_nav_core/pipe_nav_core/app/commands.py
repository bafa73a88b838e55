"""The commands of ``pipe-nav`` on one bag: ``smooth``, ``replay``, ``simulate``, ``config`` and
``info``, with what they share: the settings from --config / --set / options, the progress bar,
the exit statuses and the one-line user error (:class:`CliError`).

Each ``cmd_*`` takes the parsed arguments (:func:`pipe_nav_core.app.cli.build_parser`) and
returns the exit status; the numeric modules are imported inside, so ``pipe-nav -h`` and
``pipe-nav info`` stay fast.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipe_nav_core.config import ConfigError, NavConfig
from pipe_nav_core.errors import CliError

if TYPE_CHECKING:
    from pipe_nav_core.app.plot_process import PlotProcess


EXIT_ERROR = 2


EXIT_NOT_OK = 3  # smooth --strict: the run's quality verdict is not OK


EXIT_INTERNAL = 70  # an internal error (EX_SOFTWARE): a bug, not the input


# bytes up to which a bag's plot child loads matplotlib as the command starts (the start-up
# leaves a core idle and the reading is short: the 2 MB sample's 0.1 s); beyond them once the
# bag is read (the 10 km run's 101 MB: reading and the first pass keep both cores busy 2.5 s)
PLOT_WARM_AT_ONCE_MAX_BYTES = 16 << 20
SIM_EPOCH = 1780272000.0  # 2026-06-01T00:00:00Z: simulated bags carry realistic stamps


def one_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


def load_config(args: argparse.Namespace) -> NavConfig:
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
            raise CliError(f"{option}: {one_line(exc)}") from None
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


def warm_kernels() -> None:
    """Compile the kernels first if this install has not (a line on stderr says so)."""
    from pipe_nav_core.warmup import ensure_warm

    ensure_warm(lambda m: print(f"pipe-nav: {m.partition(': ')[2]}", file=sys.stderr))


def cmd_smooth(args: argparse.Namespace) -> int:
    from pipe_nav_core.app.plot_process import PlotProcess

    # forked first, before the numeric imports: it loads matplotlib while this one smooths
    # (a large bag's once it is read: pipeline.smooth_bag tells it)
    wants_plot = bool(args.plot) or out_is_dir(args.out)
    try:
        warm = bag_bytes(args.input) <= PLOT_WARM_AT_ONCE_MAX_BYTES
    except OSError:  # the reading names why
        warm = True
    with PlotProcess.start(warm) if wants_plot else PlotProcess(None, None) as plotter:
        return _smooth(args, plotter)


def bag_bytes(path: str | os.PathLike[str]) -> int:
    """The bytes of a bag file, or of every file in a rosbag2 folder (OSError where it cannot
    be read). Here, not in io, whose import the plot's child is forked before."""
    p = Path(path)
    return sum(f.stat().st_size for f in p.iterdir()) if p.is_dir() else p.stat().st_size


def out_is_dir(out: str) -> bool:
    """--out names a directory (the products are written into it, named like the bag)."""
    return out.endswith(("/", "\\")) or Path(out).is_dir()


def run_in_folder(folder: str, input_path: str) -> str:
    """--out DIR/: the folder made, and the path in it named like the input without its
    suffix, which the outputs' names extend (``DIR/run`` -> ``DIR/run_bends.csv``)."""
    from pipe_nav_core.io.bagfiles import bag_stem

    Path(folder).mkdir(parents=True, exist_ok=True)
    return str(Path(folder) / bag_stem(input_path))


def _smooth(args: argparse.Namespace, plotter: PlotProcess) -> int:
    from pipe_nav_core.app.outputs import Outputs
    from pipe_nav_core.app.pipeline import smooth_bag
    from pipe_nav_core.io.bagfiles import bag_files

    cfg = load_config(args)
    if out_is_dir(args.out):
        run = run_in_folder(args.out, args.input)
        outputs = Outputs(
            bag=f"{run}_smoothed.mcap",
            csv=args.csv or f"{run}_centerline.csv",
            geojson=args.geojson or f"{run}_centerline.geojson",
            kml=args.kml or f"{run}_centerline.kml",
            plot=args.plot or f"{run}_report.png",
        )
    else:
        outputs = Outputs(
            bag=str(Path(args.out)),
            csv=args.csv,
            geojson=args.geojson,
            kml=args.kml,
            plot=args.plot,
        )
    outputs = outputs.with_products()
    bag_files(args.input)  # a bad bag path fails at once, not after a first compile
    warm_kernels()
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


def format_max_strain(s: dict[str, Any]) -> str:
    """The largest strain of an IntegrityReport.summary() for people: ``13.5487 % (in bend
    54), 0.3532 % outside bends``."""
    where = f" (in bend {s['max_strain_bend']})" if s.get("max_strain_bend") else ""
    return (f"{s['max_strain_pct']:.4f} %{where}, "
            f"{s['max_strain_outside_bends_pct']:.4f} % outside bends")  # fmt: skip


def _print_summary(s: dict[str, Any], method: str) -> None:
    print(f"smoothed with {method}:")
    print(f"  distance            {s['distance_m']:.2f} m in {s['duration_s']:.1f} s")
    print(
        f"  markers             {s['markers_used']} used, {s['markers_rejected']} rejected, "
        f"{s['markers_total']} in total"
    )
    rej = s.get("rejected_updates") or {}
    print("  rejected updates    " + (", ".join(f"{k} {v}" for k, v in rej.items()) or "none"))
    if s.get("straight_pipe_updates"):
        curves = float(s.get("gentle_curves_m") or 0.0)  # left out of the straight sections
        print(f"  straight pipe       {s['straight_pipe_updates']} updates"
              + (f"; gentle curves {curves:.1f} m left out" if curves else ""))  # fmt: skip
    if s.get("section_direction_updates"):
        print(f"  section direction   {s['section_direction_updates']} updates")
    print(f"  odometer scale      {s['odometer_scale']:.5f}")
    print("  gyro bias           " + " ".join(f"{x:+.2f}" for x in s["gyro_bias_deg_h"]) + " deg/h")
    print("  accel bias          " + " ".join(f"{x:+.3f}" for x in s["accel_bias_mg"]) + " mg")
    print(f"  max sigma between markers (horizontal) {s['max_sigma_h_between_markers_m']:.3f} m")
    print(f"  max marker residual {s['max_marker_residual_m']:.3f} m")
    if "converged" in s:
        lost = s.get("long_epochs_lost_odometer")
        why = f": the long epochs lost the odometer before {lost[0]}" if lost else ""
        print(
            f"  passes              {s['passes_run']} "
            + ("(converged" if s["converged"] else "(NOT converged: more --iterations may help")
            + f"; last attitude step {1e3 * float(s['last_step_rad']):.3f} mrad; epochs at "
            + f"{float(s.get('epoch_rate_hz', 0.0)):g} Hz{why})"
        )
    products = s.get("integrity") or {}
    if products:
        print(
            f"  bends               {products['bends']} (window "
            f"{products['curvature_window_m']:.2f} m), strain features "
            f"{products['strain_features']}, max strain {format_max_strain(products)}"
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
    from pipe_nav_core.app.replay import replay_bag
    from pipe_nav_core.io.bagfiles import bag_files

    cfg = load_config(args)
    bag_files(args.input)  # a bad bag path fails at once, not after a first compile
    warm_kernels()
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

    for name, value in load_config(args).to_dict().items():
        if name in ANGLE_FIELDS:
            name, value = f"{name}_deg", degrees_of(value)
        if name == "imu_overrides":
            print("imu_overrides: {" + ", ".join(f"{k}: {v!r}" for k, v in value.items()) + "}")
        else:
            print(f"{name}: {yaml_value(value)}")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from pipe_nav_core.app.info import describe_bag, format_info

    info = describe_bag(args.input, load_config(args), _topics(args), args.markers)
    print(json.dumps(info, indent=2) if args.json else format_info(info))
    return 0
