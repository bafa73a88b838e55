"""Many runs at once (runs.py): local processes and a Dask cluster give what one process gives."""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import pytest
from pipe_nav_core.app.runs import default_workers, map_runs
from pipe_nav_core.config import NavConfig


def _work(x: int, scale: float = 1.0) -> tuple[int, float, int]:
    """Deterministic numeric work whose result names the process that did it (pid)."""
    import os

    rng = np.random.default_rng(x)
    return x, float(np.linalg.norm(rng.standard_normal(1000)) * scale), os.getpid()


def _fails(x: int) -> int:
    if x == 2:
        raise ValueError(f"item {x}: bad input")
    return x


def test_parallel_processes_give_the_serial_results_in_order():
    items = list(range(6))
    serial = map_runs(_work, items, workers=1)
    parallel = map_runs(functools.partial(_work, scale=1.0), items, workers=2)
    assert [r[:2] for r in parallel] == [r[:2] for r in serial]
    import os

    assert {r[2] for r in serial} == {os.getpid()}
    assert os.getpid() not in {r[2] for r in parallel}  # done in worker processes


def test_a_failure_is_raised_as_it_was():
    with pytest.raises(ValueError, match="item 2: bad input"):
        map_runs(_fails, [1, 2, 3], workers=2)
    with pytest.raises(ValueError, match="at least 1"):
        map_runs(_fails, [1], workers=0)
    assert default_workers(1) == 1 and default_workers(100) >= 1


def test_on_a_dask_local_cluster(monkeypatch):
    distributed = pytest.importorskip("dask.distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:  # fmt: skip
        out = map_runs(_work, list(range(4)), dask_scheduler=cluster.scheduler_address)
    assert [r[:2] for r in out] == [r[:2] for r in map_runs(_work, list(range(4)), workers=1)]
    from pipe_nav_core.app import runs

    monkeypatch.setattr(runs, "DASK_CONNECT_TIMEOUT_S", 1.0)
    with pytest.raises(ValueError, match="cannot connect"):
        map_runs(_work, [1], dask_scheduler="tcp://127.0.0.1:9")  # nothing listens there


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """Two smoothed bags of a short pipe (pipe-nav smooth)."""
    import json

    from pipe_nav_core.app.cli import main
    from pipe_nav_core.io import write_sensor_bag
    from pipe_nav_core.sim import get_scenario, simulate

    tmp = tmp_path_factory.mktemp("runs")
    scn = get_scenario("demo").with_length(100.0)
    cfg = tmp / "cfg.json"
    cfg.write_text(json.dumps({k: list(v) if isinstance(v, tuple) else v
                               for k, v in scn.estimator_settings().items()}))  # fmt: skip
    out = []
    for seed in (1, 2):
        raw = tmp / f"r{seed}.mcap"
        write_sensor_bag(str(raw), simulate(scn, seed).log)
        out.append(str(tmp / f"r{seed}_smoothed.mcap"))
        assert main(["smooth", str(raw), "--out", out[-1], "--config", str(cfg)]) == 0
    return out


def test_compare_and_fuse_in_parallel_equal_serial(bags, tmp_path: Path):
    from pipe_nav_core.app.runs import compare_files, fuse_files

    cfg = NavConfig()
    (tmp_path / "s").mkdir()
    (tmp_path / "p").mkdir()
    rep_s, paths_s = compare_files(*bags, str(tmp_path / "s" / "M.csv"), cfg, workers=1)
    rep_p, paths_p = compare_files(*bags, str(tmp_path / "p" / "M.csv"), cfg, workers=2)
    assert Path(paths_s[0]).read_text() == Path(paths_p[0]).read_text()
    assert Path(paths_s[1]).read_text() == Path(paths_p[1]).read_text()
    assert len(rep_s.points) >= 5
    fs = fuse_files(bags, str(tmp_path / "s" / "F.csv"), workers=1)
    fp = fuse_files(bags, str(tmp_path / "p" / "F.csv"), workers=2)
    assert (tmp_path / "s" / "F.csv").read_text() == (tmp_path / "p" / "F.csv").read_text()
    assert fs.residuals == fp.residuals and math.isfinite(fs.residuals[1].rms_h)


def test_fuse_on_a_dask_cluster_equals_serial(bags, tmp_path: Path):
    distributed = pytest.importorskip("dask.distributed")
    from pipe_nav_core.app.runs import fuse_files

    fuse_files(bags, str(tmp_path / "serial.csv"), workers=1)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:  # fmt: skip
        fuse_files(bags, str(tmp_path / "dask.csv"), dask_scheduler=cluster.scheduler_address)
    assert (tmp_path / "serial.csv").read_text() == (tmp_path / "dask.csv").read_text()
