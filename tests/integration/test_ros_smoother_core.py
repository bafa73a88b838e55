"""smoother_node's work (SmootherJob) without ROS: smooth a simulated bag, build the messages."""

from __future__ import annotations

import pytest
from pipe_nav_ros.params import smoother_node_settings  # noqa: E402
from pipe_nav_ros.smoother_core import DONE, ERROR, FAILED, OK, WARN, SmootherJob  # noqa: E402

from pipe_nav_core import NavConfig, SensorLog, rosmsg, simulate, write_sensor_bag  # noqa: E402

TYPES = rosmsg.rosbags_types()


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    run = simulate("demo", 1)
    log, t_end = run.log, 90.0
    path = tmp_path_factory.mktemp("smooth") / "run.mcap"
    write_sensor_bag(
        path,
        SensorLog(
            imu=log.imu.slice(log.imu.t <= t_end),
            odometer=log.odometer.slice(log.odometer.t <= t_end),
            mag=log.mag.slice(log.mag.t <= t_end),
            markers=[m for m in log.markers if m.t <= t_end],
        ),
    )
    return path, NavConfig.from_dict(run.scenario.estimator_settings())


def test_smoother_job_writes_the_bag_and_builds_latched_messages(bag, tmp_path):
    path, config = bag
    settings = smoother_node_settings(
        {"bag": str(path), "output": str(tmp_path / "out.mcap"), "csv": str(tmp_path / "c.csv")}
    )
    job = SmootherJob(settings, config, TYPES)
    job.run()
    assert job.state == DONE, job.error
    assert (tmp_path / "out.mcap").is_file() and (tmp_path / "c.csv").is_file()
    path_msg, datum_msg = job.messages()
    ts = rosmsg.jazzy_typestore()
    path_msg = ts.deserialize_cdr(
        ts.serialize_cdr(path_msg, "nav_msgs/msg/Path"), "nav_msgs/msg/Path"
    )
    assert path_msg.header.frame_id == "map" and len(path_msg.poses) > 10
    t, enu, _ = rosmsg.path_from_msg(path_msg)
    assert (t[1:] >= t[:-1]).all()
    datum = rosmsg.datum_from_msg(datum_msg)
    assert datum == pytest.approx(job.result.datum)
    level, message, values = job.health()
    assert level in (OK, WARN) and "done" in message and values["state"] == DONE
    diag = job.diagnostics(5.0)
    assert diag.status[0].name == "pipe_nav: smoother_node"


def test_smoother_job_reports_failure(bag, tmp_path):
    path, config = bag
    settings = smoother_node_settings(
        {"bag": str(path), "output": str(tmp_path / "out.mcap"), "method": "no-such-method"}
    )
    job = SmootherJob(settings, config, TYPES)
    job.run()
    assert job.state == FAILED and job.error
    level, message, _ = job.health()
    assert level == ERROR and "failed" in message
    with pytest.raises(RuntimeError):
        job.messages()


def test_the_job_hears_every_stage_and_the_fraction_of_each_pass(bag, tmp_path, monkeypatch):
    """smooth_bag tells the job (pipe_nav_core.app.progress.Progress) each stage and how far each
    filter pass is, so /diagnostics shows a percentage while it runs (it said 'progress ?'
    until the end: the fraction never reached the job's thread)."""
    from pipe_nav_ros import smoother_core

    heard: list[tuple[str, object]] = []
    real_stage, real_fraction = smoother_core._Told.stage, smoother_core._Told.fraction

    def stage(self, text):  # noqa: ANN001, ANN202
        heard.append(("stage", text))
        real_stage(self, text)
        assert self.job.stage == text and self.job.fraction == 0.0

    def fraction(self, done):  # noqa: ANN001, ANN202
        heard.append(("fraction", done))
        real_fraction(self, done)
        assert self.job.fraction == done
        assert self.job.health()[2]["progress"] == f"{100.0 * done:.1f} %"

    monkeypatch.setattr(smoother_core._Told, "stage", stage)
    monkeypatch.setattr(smoother_core._Told, "fraction", fraction)
    path, config = bag
    settings = smoother_node_settings({"bag": str(path), "output": str(tmp_path / "o.mcap")})
    job = SmootherJob(settings, config, TYPES)
    job.run()
    assert job.state == DONE, job.error
    stages = [v for k, v in heard if k == "stage"]
    fractions = [v for k, v in heard if k == "fraction"]
    assert "reading bag" in stages and any(str(s).startswith("RTS smoother") for s in stages)
    assert fractions and all(0.0 < f <= 1.0 for f in fractions) and 1.0 in fractions
    assert job.fraction == 1.0 and job.stage == "done"
