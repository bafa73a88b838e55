"""Bag-level pipeline behaviour: the IMU mounting rotation and the marker CSV."""

import dataclasses

import numpy as np
import pytest
from pipe_nav_core.bench.evaluation import score
from pipe_nav_core.config import NavConfig
from pipe_nav_core.sim import get_scenario, simulate
from pipe_nav_core.smooth.passes import smooth_log


def test_imu_mount_rotation_is_applied():
    """An IMU mounted 10 deg rolled, 5 deg pitched and 20 deg yawed in the pig: with the mount
    configured the result is as good as an aligned IMU's; ignoring it ruins the heading."""
    mount = (0.17, -0.09, 0.35)
    sc = dataclasses.replace(get_scenario("sag104"), imu_mount_rpy=mount)
    run = simulate(sc, seed=2)
    good = NavConfig.from_dict(sc.estimator_settings())
    assert good.imu_mount_rpy == mount
    r = smooth_log(run.log, good)
    s = score(r.centreline, run.truth, run.log.markers, datum=r.datum)
    assert s.max_h < 0.1 and s.max_v < 0.1, s
    bad = dataclasses.replace(good, imu_mount_rpy=(0.0, 0.0, 0.0))
    r_bad = smooth_log(run.log, bad, iterations=1)
    s_bad = score(r_bad.centreline, run.truth, run.log.markers, datum=r_bad.datum)
    assert s_bad.max_h > 5 * s.max_h


def test_mount_rotation_is_the_extrinsic_xyz_euler_rotation():
    from pipe_nav_core.filter.ingest import mount_rotation
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    for rpy in rng.uniform(-3.2, 3.2, size=(20, 3)):
        want = Rotation.from_euler("xyz", rpy).as_matrix()
        np.testing.assert_allclose(mount_rotation(rpy), want, atol=1e-14)


def test_markers_outside_the_data_are_left_out_and_named(tmp_path):
    from pathlib import Path

    from pipe_nav_core.app.outputs import Outputs
    from pipe_nav_core.app.pipeline import smooth_bag
    from pipe_nav_core.io import read_markers_csv, write_markers_csv

    bags = Path(__file__).resolve().parents[2] / "bags"
    survey = read_markers_csv(bags / "sample.markers.csv")
    early = dataclasses.replace(survey[1], name="agm_early", t=survey[0].t - 600.0)
    late = dataclasses.replace(survey[2], name="agm_late", t=survey[-1].t + 900.0)
    extra = tmp_path / "extra.csv"
    write_markers_csv(extra, [early, late])
    cfg = NavConfig()
    base, _ = smooth_bag(bags / "sample.mcap", Outputs(), config=cfg, iterations=1)
    got, report = smooth_bag(bags / "sample.mcap", Outputs(), config=cfg, iterations=1,
                             markers_csv=extra)  # fmt: skip
    assert any("agm_early passes" in w and "s before the data" in w for w in report.warnings)
    assert any("agm_late passes" in w and "after the data" in w for w in report.warnings)
    np.testing.assert_array_equal(got.centreline.lat, base.centreline.lat)
    assert [m.name for m in got.markers] == [m.name for m in base.markers]


def test_a_run_with_no_marker_inside_its_data_is_refused(tmp_path):
    from pathlib import Path

    from pipe_nav_core.app.outputs import Outputs
    from pipe_nav_core.app.pipeline import load_log, smooth_bag
    from pipe_nav_core.io import read_markers_csv, write_markers_csv
    from pipe_nav_core.io.bagwrite import write_sensor_bag

    bags = Path(__file__).resolve().parents[2] / "bags"
    log, _ = load_log(bags / "sample.mcap")
    bare = tmp_path / "bare.mcap"
    write_sensor_bag(bare, dataclasses.replace(log, markers=[]))
    survey = read_markers_csv(bags / "sample.markers.csv")
    away = tmp_path / "away.csv"
    # an hour and 7 s: no offset clocks are known to be apart by (an hour is re-timed:
    # test_faults_marker_clock), so it is named and not moved
    write_markers_csv(away, [dataclasses.replace(m, t=m.t + 3607.0) for m in survey])
    with pytest.raises(ValueError, match="no markers within the data .*marker agm_00 passes"):
        smooth_bag(bare, Outputs(), config=NavConfig(), markers_csv=away)
    one = tmp_path / "one.csv"
    write_markers_csv(one, [survey[0], dataclasses.replace(survey[1], t=survey[1].t + 3600)])
    _, report = load_log(bare, markers_csv=one)
    assert any("the heading is not anchored" in w for w in report.warnings)


def test_welds_found_beside_the_bends_fail_the_run_whole(tmp_path, monkeypatch):
    """The welds run in a second thread while the bends and strain are found: what they
    find is the run's, and when they fail the run fails with their error and writes nothing."""
    from pathlib import Path

    from pipe_nav_core.app import pipeline
    from pipe_nav_core.app.outputs import Outputs

    sample = Path(__file__).resolve().parents[2] / "bags" / "sample.mcap"
    found, _ = pipeline.smooth_bag(sample, Outputs(), config=NavConfig(), iterations=1)
    assert found.welds, "the sample has welds"
    again = pipeline.run_welds(pipeline.load_log(sample)[0], found, found.config or NavConfig())
    assert [w.distance for w in found.welds] == [w.distance for w in again]
    monkeypatch.setattr(pipeline, "WELDS_BESIDE_BENDS_MAX", 0)  # a long run: after the bends
    after, _ = pipeline.smooth_bag(sample, Outputs(), config=NavConfig(), iterations=1)
    assert list(map(repr, after.welds)) == list(map(repr, found.welds))  # nan joint lengths
    monkeypatch.undo()

    def broken(*_args: object) -> None:
        raise RuntimeError("weld finder broke")

    monkeypatch.setattr(pipeline, "run_welds", broken)
    out = Outputs(bag=str(tmp_path / "o.mcap"), csv=str(tmp_path / "o.csv"))
    with pytest.raises(RuntimeError, match="weld finder broke"):
        pipeline.smooth_bag(sample, out, config=NavConfig(), iterations=1)
    assert not list(tmp_path.iterdir())


def test_the_imu_read_from_a_file_changes_no_output(tmp_path, monkeypatch):
    """At field scale the IMU samples are read from a file (in memory only while a filter pass
    or the welds' jolt check reads them): every output file is the same bytes as with the IMU
    in memory throughout, with the welds beside the bends or after them."""
    from pathlib import Path

    from pipe_nav_core.app import pipeline
    from pipe_nav_core.app.outputs import Outputs
    from pipe_nav_core.smooth import logs

    from pipe_nav_core import memory

    sample = Path(__file__).resolve().parents[2] / "bags" / "sample.mcap"
    names = ("o.mcap", "o.csv", "o_bends.csv", "o_strain.csv", "o_welds.csv")

    def run(folder: Path) -> list[bytes]:
        folder.mkdir()
        out = Outputs(bag=str(folder / names[0]), csv=str(folder / names[1]),
                      bends=str(folder / names[2]), strain=str(folder / names[3]),
                      welds=str(folder / names[4]))  # fmt: skip
        result, _ = pipeline.smooth_bag(sample, out, config=NavConfig(), iterations=2)
        assert result.welds
        return [(folder / n).read_bytes() for n in names]

    plain = run(tmp_path / "plain")
    monkeypatch.setattr(logs, "MAP_IMU_BYTES", 0)
    read = []
    real = logs.map_imu

    def spy(imu):
        real(imu)
        read.append(memory.mapping(imu.accel) is not None)

    monkeypatch.setattr(pipeline, "map_imu", spy)
    assert run(tmp_path / "mapped") == plain
    monkeypatch.setattr(pipeline, "WELDS_BESIDE_BENDS_MAX", 0)  # the welds after the bends
    assert run(tmp_path / "after") == plain
    assert read == [True, True]  # mapped in both runs


@pytest.mark.parametrize("warm", [True, False])
def test_a_plot_child_not_warm_is_told_once_the_bag_is_read(tmp_path, warm):
    """smooth_bag tells the plot's child to load matplotlib once the bag is read (the first
    pass then goes on alone: a core to spare), unless it was told at its start."""
    from pathlib import Path

    from pipe_nav_core.app import pipeline
    from pipe_nav_core.app.outputs import Outputs
    from pipe_nav_core.app.plot_process import PlotProcess

    said: list[str] = []

    class Told(PlotProcess):
        def warm(self) -> None:
            said.append("warm again" if self._told else "warm")
            super().warm()

    class Stages:
        def stage(self, text: str) -> None:
            said.append(text)

        def fraction(self, done: float) -> None:
            pass

    sample = Path(__file__).resolve().parents[2] / "bags" / "sample.mcap"
    out = Outputs(bag=str(tmp_path / "o.mcap"), plot=str(tmp_path / "o.png"))
    with Told.start(warm) as plotter:
        pipeline.smooth_bag(sample, out, config=NavConfig(), progress=Stages(), plotter=plotter)
    assert (tmp_path / "o.png").stat().st_size > 0
    told = said.index("warm again" if warm else "warm")
    assert said.count("warm") == (0 if warm else 1)
    assert said.index("reading bag") < told < said.index("bends and strain")


def test_the_smooth_command_warms_the_plot_child_at_once_for_a_small_bag(tmp_path, monkeypatch):
    """At once for the 2 MB sample; with the limit below its size, once it is read."""
    from pathlib import Path

    from pipe_nav_core.app import cli, commands
    from pipe_nav_core.app.plot_process import PlotProcess

    started: list[bool] = []
    real = PlotProcess.start.__func__

    def start(cls, warm=True):  # noqa: ANN001, ANN202
        started.append(warm)
        return real(cls, warm)

    monkeypatch.setattr(PlotProcess, "start", classmethod(start))
    sample = Path(__file__).resolve().parents[2] / "bags" / "sample.mcap"
    assert cli.main(["smooth", str(sample), "--out", f"{tmp_path / 'a'}/", "--quiet"]) == 0
    monkeypatch.setattr(commands, "PLOT_WARM_AT_ONCE_MAX_BYTES", sample.stat().st_size - 1)
    assert cli.main(["smooth", str(sample), "--out", f"{tmp_path / 'b'}/", "--quiet"]) == 0
    assert started == [True, False]
    assert (tmp_path / "a" / "sample_report.png").read_bytes() == (
        tmp_path / "b" / "sample_report.png"
    ).read_bytes()
