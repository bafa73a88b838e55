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
import os
import signal
import sys
import threading
from collections.abc import Sequence
from typing import TYPE_CHECKING, NoReturn

from pipe_nav_core.errors import PipeNavError
from pipe_nav_core.smooth.methods import DEFAULT_METHOD, MAX_PASSES, METHODS

if TYPE_CHECKING:
    pass
from pipe_nav_core.app.commands import (
    EXIT_ERROR,
    EXIT_INTERNAL,
    SIM_EPOCH,
    cmd_config,
    cmd_info,
    cmd_replay,
    cmd_simulate,
    cmd_smooth,
    one_line,
)
from pipe_nav_core.app.integrity_commands import (
    cmd_bench,
    cmd_bends,
    cmd_compare,
    cmd_evaluate,
    cmd_fuse,
    cmd_locate,
)


class _Parser(argparse.ArgumentParser):
    """argparse with the command line's one-line errors (``pipe-nav smooth: error: ...``,
    exit status 2) instead of the usage block; ``-h`` still prints the usage."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_ERROR, f"{self.prog}: error: {message} (see {self.prog} -h)\n")


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


def _add_runs_options(p: argparse.ArgumentParser) -> None:
    """Where the per-run work of a command over several runs is done (pipe_nav_core.app.runs)."""
    p.add_argument("--workers", type=int, help="local processes (default: one per run, "
                   "at most the CPUs)")  # fmt: skip
    p.add_argument(
        "--dask-scheduler",
        metavar="ADDRESS",
        help="run on this Dask distributed cluster (tcp://host:8786) instead",
    )


class _Version(argparse.Action):
    """``--version``: the package's version and the kernels in use on stdout, then exit 0."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kw: object) -> None:
        super().__init__(option_strings, dest, nargs=0, help="the version and the kernels in use")

    def __call__(self, parser: argparse.ArgumentParser, *_: object) -> NoReturn:
        from importlib import metadata

        try:
            version = metadata.version("pipe_nav_core")
        except metadata.PackageNotFoundError:  # imported from a folder, not installed
            version = "(not installed)"
        from pipe_nav_core.warmup import kernels_in_use

        print(f"pipe-nav {version} ({kernels_in_use()})", flush=True)
        parser.exit(0)


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="pipe-nav", description="Pipeline pig navigation (ROS-free core).")
    ap.add_argument("--debug", action="store_true",
                    help="on an error, the Python traceback instead of one line")  # fmt: skip
    ap.add_argument("--version", action=_Version)
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
    p.add_argument("--method", default=DEFAULT_METHOD, choices=METHODS,
                   help=f"smoother (default {DEFAULT_METHOD})")  # fmt: skip
    p.add_argument("--iterations", type=int, default=MAX_PASSES,
                   help=f"smoothing passes at most, fewer once converged "
                   f"(default {MAX_PASSES})")  # fmt: skip
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
                   help="write RUN_strain.csv, RUN_bends.csv, RUN_strain_features.csv, or into "
                   "a folder (ending in /) named like the input (default: beside the input, "
                   "named like it)")  # fmt: skip
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
    p.add_argument(
        "--seeds",
        type=int,
        help="seeds 1 to N of every scenario (default 3, the 10 km lines 1; --quick 1)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an estimator setting for every run, as in a settings file (repeatable), "
        "e.g. straight_pipe_sigma=0.001",
    )
    p.set_defaults(func=cmd_bench)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    main_thread = threading.current_thread() is threading.main_thread()
    if main_thread:
        from pipe_nav_core.memory import keep_freed, limit_arenas, small_pages

        limit_arenas()  # before the command starts its threads
        keep_freed()
        small_pages()
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
        print(f"pipe-nav: error: {one_line(exc)}", file=sys.stderr)
        return EXIT_ERROR
    except Exception as exc:  # a bug: one line (the traceback with --debug)
        if args.debug:
            raise
        print(f"pipe-nav: internal error: {type(exc).__name__}: {one_line(exc)} (a bug; "
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


if __name__ == "__main__":
    run()
