"""The commands of ``pipe-nav`` on smoothed runs and their products: ``bends``, ``locate``,
``compare``, ``fuse``, ``evaluate`` and ``bench``.

Each ``cmd_*`` takes the parsed arguments (:func:`pipe_nav_core.app.cli.build_parser`) and
returns the exit status.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pipe_nav_core.products import IntegrityReport
from pipe_nav_core.app.commands import (
    format_max_strain,
    load_config,
    out_is_dir,
    run_in_folder,
    warm_kernels,
)
from pipe_nav_core.errors import CliError


def cmd_bends(args: argparse.Namespace) -> int:
    from pipe_nav_core.app.outputs import Outputs
    from pipe_nav_core.app.pipeline import products_of_file

    for name, value in (
        ("curvature_window", args.window),
        ("strain_thresholds", args.thresholds),
        ("bend_min_angle_deg", args.min_angle_deg),
        ("pipe_outer_diameter", args.outer_diameter),
    ):
        if value is not None:
            args.set = (args.set or []) + [f"{name}={json.dumps(value)}"]
    cfg = load_config(args)
    src = str(args.input).rstrip("/")
    run = args.out
    if run and out_is_dir(run):  # a folder, as for smooth: the products named like the input
        run = run_in_folder(run, src)
    outputs = Outputs(csv=run + ".csv" if run else src).with_products()
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
        f"max strain {format_max_strain(s)}",
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

    cfg = load_config(args)
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

    return bench_main(args, before_runs=warm_kernels)
