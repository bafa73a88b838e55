"""Many runs at once: the per-run work of the commands that take several runs (``compare``,
``fuse``, and :func:`smooth_many`) in parallel processes on this machine
(concurrent.futures.ProcessPoolExecutor, the default), or on a Dask distributed cluster
(``--dask-scheduler ADDRESS``: dask.distributed.Client(ADDRESS), the ``cluster`` extra).

:func:`map_runs` is the one entry point: the same picklable, module-level function over the
items, results in the items' order, the first failure raised as it was (a ValueError stays a
ValueError, so the command line still names the user's input). One item, or ``workers=1``,
runs in this process. The per-run tasks are the functions below (reading a smoothed bag and
computing its integrity products; smoothing one bag); they take and return plain data, so a
result does not depend on where it was computed.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any, TypeVar

from pipe_nav_core.config import NavConfig

T = TypeVar("T")
R = TypeVar("R")

MAX_WORKERS = 8  # local processes at most (each holds one run in memory)
DASK_CONNECT_TIMEOUT_S = 30.0  # to reach the --dask-scheduler


def default_workers(n_items: int) -> int:
    """Local worker processes for n_items: one per item, at most the CPUs (and MAX_WORKERS)."""
    return max(1, min(n_items, os.cpu_count() or 1, MAX_WORKERS))


def map_runs(
    fn: Callable[[T], R],
    items: Sequence[T],
    *,
    workers: int | None = None,
    dask_scheduler: str | None = None,
) -> list[R]:
    """[fn(x) for x in items], computed in parallel: on the Dask cluster at ``dask_scheduler``
    (an address such as ``tcp://host:8786``) when given, else in ``workers`` local processes
    (default :func:`default_workers`; 1 = in this process). ``fn`` must be picklable (a
    module-level function, or a functools.partial of one)."""
    items = list(items)
    if workers is not None and int(workers) < 1:
        raise ValueError(f"--workers must be at least 1, not {workers}")
    if dask_scheduler:
        return _on_dask(fn, items, dask_scheduler)
    n = default_workers(len(items)) if workers is None else min(int(workers), len(items))
    if n <= 1:
        return [fn(x) for x in items]
    # forkserver: no copy of this process's threads and locks (fork's hazard), cheaper than spawn
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["pipe_nav_core.app.runs", "pipe_nav_core.products.movement"])
    with ProcessPoolExecutor(max_workers=n, mp_context=ctx) as pool:
        return list(pool.map(fn, items))


def _on_dask(fn: Callable[[T], R], items: list[T], address: str) -> list[R]:
    try:
        from dask.distributed import Client
    except ImportError:
        raise ValueError("--dask-scheduler needs dask.distributed: pip install "
                         "'pipe_nav_core[cluster]'") from None  # fmt: skip
    try:
        client = Client(address, timeout=DASK_CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise ValueError(f"--dask-scheduler {address}: cannot connect ({exc})") from None
    with client:
        futures = client.map(fn, items, pure=False)
        return client.gather(futures)


# -------------------------------------------------------------------- per-run tasks


def load_run(path: str) -> Any:
    """A smoothed bag read back (trajectory with sigmas, datum, metadata, welds)."""
    from pipe_nav_core.io.smoothed_bag import read_smoothed_run

    return read_smoothed_run(path)


def config_for(metadata: dict[str, str], config: NavConfig) -> NavConfig:
    """``config`` with the IMU grade the bag's metadata records when it says ``auto``."""
    from dataclasses import replace

    from pipe_nav_core.config import AUTO_GRADE
    from pipe_nav_core.model.sensors import GRADES

    if config.imu_grade != AUTO_GRADE:
        return config
    model = metadata.get("imu_model", "").split("+")[0]
    return replace(config, imu_grade=model if model in GRADES else "industrial")


def load_run_with_products(job: tuple[str, NavConfig]) -> tuple[Any, Any]:
    """(the smoothed run, its integrity report) of job = (smoothed bag path, settings)."""
    from pipe_nav_core.products import integrity_report

    path, config = job
    run = load_run(path)
    return run, integrity_report(run.trajectory, config_for(run.metadata, config))


def compare_files(
    path_a: str,
    path_b: str,
    out_csv: str,
    config: NavConfig,
    *,
    threshold: float | None = None,
    n_sigma: float | None = None,
    workers: int | None = None,
    dask_scheduler: str | None = None,
) -> tuple[Any, list[str]]:
    """`pipe-nav compare A B --out MOVEMENT.csv`: both smoothed bags read and their integrity
    products computed in parallel, compared (products.movement.compare_runs), and MOVEMENT.csv
    with MOVEMENT.geojson and MOVEMENT.png beside it written all or none. Returns the report
    and the written paths."""
    from pathlib import Path

    from pipe_nav_core.io.atomic import all_or_none, check_output, ensure_not_input
    from pipe_nav_core.io.movement_files import (
        plot_movement,
        write_movement_csv,
        write_movement_geojson,
    )
    from pipe_nav_core.products.movement import MOVEMENT_N_SIGMA, MOVEMENT_THRESHOLD_M, compare_runs

    stem = Path(out_csv).with_suffix("")
    paths = [str(out_csv), f"{stem}.geojson", f"{stem}.png"]
    for p in paths:
        check_output(p, "--out")
        ensure_not_input(p, [path_a, path_b])
    (run_a, rep_a), (run_b, rep_b) = map_runs(
        load_run_with_products, [(str(path_a), config), (str(path_b), config)],
        workers=workers, dask_scheduler=dask_scheduler)  # fmt: skip
    report = compare_runs(run_a, run_b, config_for(run_a.metadata, config),
                          threshold=MOVEMENT_THRESHOLD_M if threshold is None else threshold,
                          n_sigma=MOVEMENT_N_SIGMA if n_sigma is None else n_sigma,
                          reports=(rep_a, rep_b))  # fmt: skip
    with all_or_none(paths) as staged:
        write_movement_csv(staged[paths[0]], report)
        write_movement_geojson(staged[paths[1]], report, stem.name)
        plot_movement(staged[paths[2]], report, f"{Path(path_b).name} - {Path(path_a).name}")
    return report, paths


def fuse_files(
    paths: Sequence[str],
    out_csv: str,
    *,
    workers: int | None = None,
    dask_scheduler: str | None = None,
    **settings: float,
) -> Any:
    """`pipe-nav fuse RUN... --out FUSED.csv`: the smoothed bags read in parallel, fused
    (products.fusion.fuse_runs with ``settings``) and the fused centreline CSV written.
    Returns the FusionResult."""
    from pipe_nav_core.io.atomic import check_output, ensure_not_input
    from pipe_nav_core.io.centreline import write_centreline_csv
    from pipe_nav_core.products.fusion import fuse_runs

    check_output(out_csv, "--out")
    ensure_not_input(out_csv, list(paths))
    runs = map_runs(load_run, [str(p) for p in paths], workers=workers,
                    dask_scheduler=dask_scheduler)  # fmt: skip
    result = fuse_runs(runs, **settings)
    write_centreline_csv(out_csv, result.centreline, result.datum)
    return result


def smooth_one(job: tuple[str, str, NavConfig]) -> str:
    """Smooth job = (bag, output .mcap, settings) with every product beside the output, as
    ``pipe-nav smooth BAG --out OUT`` does; returns the output path."""
    from pipe_nav_core.app.outputs import Outputs
    from pipe_nav_core.app.pipeline import smooth_bag

    bag, out, config = job
    smooth_bag(bag, Outputs(bag=out).with_products(), config=config)
    return out


def smooth_many(
    bags: Sequence[str],
    outs: Sequence[str],
    config: NavConfig,
    *,
    workers: int | None = None,
    dask_scheduler: str | None = None,
) -> list[str]:
    """Smooth several bags in parallel (see :func:`map_runs`); returns the outputs."""
    if len(bags) != len(outs):
        raise ValueError("smooth_many: one output per bag")
    jobs = [(str(b), str(o), config) for b, o in zip(bags, outs, strict=True)]
    return map_runs(smooth_one, jobs, workers=workers, dask_scheduler=dask_scheduler)


__all__ = [
    "MAX_WORKERS",
    "compare_files",
    "fuse_files",
    "config_for",
    "default_workers",
    "load_run",
    "load_run_with_products",
    "map_runs",
    "smooth_many",
    "smooth_one",
]
