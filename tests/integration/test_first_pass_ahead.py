"""The first smoothing pass run while the bag is read (smooth.ahead): taken only where it is the
run's own, and then the same bytes in every output as the pass run after the reading."""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path

import pytest
from pipe_nav_core.app import pipeline
from pipe_nav_core.app.outputs import Outputs
from pipe_nav_core.config import NavConfig
from pipe_nav_core.io import read_bag, write_sensor_bag
from pipe_nav_core.smooth import ahead as ahead_module
from pipe_nav_core.smooth.ahead import FirstPassAhead
from pipe_nav_core.smooth.passes import epoch_config

SAMPLE = Path(__file__).resolve().parents[2] / "bags" / "sample.mcap"
NAMES = ("o.mcap", "o.csv", "o_bends.csv", "o_strain.csv", "o_welds.csv")
TAKEN = "forward filter (run while the bag was read)"


class Stages:
    def __init__(self) -> None:
        self.said: list[str] = []

    def stage(self, text: str) -> None:
        self.said.append(text)

    def fraction(self, done: float) -> None:
        pass


def smooth(bag: Path, folder: Path, method: str = "rts") -> tuple[list[bytes], list[str]]:
    folder.mkdir()
    out = Outputs(bag=str(folder / NAMES[0]), csv=str(folder / NAMES[1]),
                  bends=str(folder / NAMES[2]), strain=str(folder / NAMES[3]),
                  welds=str(folder / NAMES[4]))  # fmt: skip
    told = Stages()
    pipeline.smooth_bag(bag, out, config=NavConfig(), method=method, progress=told)
    return [(folder / n).read_bytes() for n in NAMES], told.said


def no_thread_left() -> bool:
    """No first-pass thread alive: smooth_bag stops and waits for its own when it ends."""
    return not any(t.name == "pipe-nav first pass" for t in threading.enumerate())


@pytest.mark.parametrize("method", ["rts", "two-filter"])
def test_the_first_pass_run_while_reading_gives_the_same_bytes(tmp_path, monkeypatch, method):
    ahead, said = smooth(SAMPLE, tmp_path / "ahead", method)
    assert TAKEN in said and said[0] == "reading bag"
    monkeypatch.setattr(pipeline, "AHEAD_MAX_MESSAGES", -1)  # the bag is too long for it
    after, said = smooth(SAMPLE, tmp_path / "after", method)
    assert TAKEN not in said and said[0] == "reading bag"
    assert ahead == after
    assert no_thread_left()


def read_with(ahead: FirstPassAhead):
    log, report = read_bag(SAMPLE, pieces=ahead)
    ahead.finish(log)
    return log, report


def test_a_first_pass_that_is_not_the_runs_is_not_taken():
    """Taken for the log read, its markers and its configuration before the heading search,
    the method, forward in time, and once; for anything else smooth_log runs its own."""
    from pipe_nav_core.model import imu_noise as imu_model

    def given(log, report, method="rts"):
        cfg = imu_model.choose(log, NavConfig(), report.imu_noise_declared).config
        return epoch_config(cfg, method)

    log, report = read_with(a := FirstPassAhead(NavConfig(), "rts"))
    cfg = given(log, report)
    got = a.take(log, cfg, "rts", False)
    assert got is not None and got[1].recording is not None
    assert got[0].heading_source == "fixed"  # the heading search ran
    assert a.take(log, cfg, "rts", False) is None  # once
    log, report = read_with(a := FirstPassAhead(NavConfig(), "rts"))
    assert a.take(dataclasses.replace(log), given(log, report), "rts", False) is None
    log, report = read_with(a := FirstPassAhead(NavConfig(), "rts"))
    log.markers = log.markers[1:]  # as when a marker outside the data is left out
    assert a.take(log, given(log, report), "rts", False) is None
    log, report = read_with(a := FirstPassAhead(NavConfig(), "rts"))
    other = dataclasses.replace(given(log, report), imu_grade="consumer")
    assert a.take(log, other, "rts", False) is None
    log, report = read_with(a := FirstPassAhead(NavConfig(), "rts"))
    assert a.take(log, given(log, report), "rts", True) is None  # reversed time
    log, report = read_with(a := FirstPassAhead(NavConfig(), "rts"))
    assert a.take(log, given(log, report, "two-filter"), "two-filter", False) is None
    assert no_thread_left()


def test_a_repaired_bag_is_smoothed_after_its_reading(tmp_path, monkeypatch):
    """A shock in the IMU: the reading's repairs make another log, so the pass run beside the
    reading (on the samples as recorded) is dropped, and the outputs are those without it."""
    log, _ = read_bag(SAMPLE)
    accel = log.imu.accel.copy()
    accel[4000:4003] = [0.0, 0.0, 300.0]  # 30 g: a shock, left out by the repairs
    bag = tmp_path / "shock.mcap"
    write_sensor_bag(bag, dataclasses.replace(log, imu=dataclasses.replace(log.imu, accel=accel)))
    made = []
    real = pipeline.first_pass_ahead
    monkeypatch.setattr(pipeline, "first_pass_ahead", lambda *a: made.append(real(*a)) or made[-1])
    ahead, said = smooth(bag, tmp_path / "ahead")
    assert made and isinstance(made[0], FirstPassAhead)  # it ran beside the reading
    assert TAKEN not in said
    monkeypatch.setattr(pipeline, "AHEAD_MAX_MESSAGES", -1)
    after, _ = smooth(bag, tmp_path / "after")
    assert ahead == after
    assert no_thread_left()


def test_a_first_pass_that_fails_beside_the_reading_is_run_again(tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("a fault in the pass beside the reading")

    after, _ = smooth(SAMPLE, tmp_path / "plain")
    monkeypatch.setattr(ahead_module, "smoothing_config", broken)
    again, said = smooth(SAMPLE, tmp_path / "broken")
    assert TAKEN not in said and again == after
    assert no_thread_left()


def test_a_reading_that_fails_stops_the_thread(monkeypatch):
    """The reading fails after handing out a few chunks (a disk error, an interrupt): its
    error reaches the caller, and the thread beside it stops."""
    real = pipeline.read_bag
    told = []

    def failing(bag, topics, pieces=None, workers=None, spill_imu_bytes=None):
        def some(piece, report):
            if len(told) == 2:
                raise OSError("the disk went away")
            told.append(piece)
            pieces(piece, report)

        return real(bag, topics, pieces=some, workers=workers, spill_imu_bytes=spill_imu_bytes)

    monkeypatch.setattr(pipeline, "read_bag", failing)
    with pytest.raises(OSError, match="the disk went away"):
        pipeline.smooth_bag(SAMPLE, Outputs(), config=NavConfig())
    assert len(told) == 2
    assert no_thread_left()


@pytest.mark.parametrize("cores", [2, 4])
def test_the_reading_leaves_a_core_to_the_first_pass(monkeypatch, cores):
    """On two cores the chunks are unpacked in the reading thread (a worker thread would take
    CPU from the pass beside it, which the run waits for); with more, by one worker. Without
    the pass, the reading's own default."""
    monkeypatch.delenv("PIPE_NAV_READ_WORKERS", raising=False)
    monkeypatch.setattr(pipeline.os, "cpu_count", lambda: cores)
    real, asked = pipeline.read_bag, []

    def spy(bag, topics, pieces=None, workers=None, spill_imu_bytes=None):
        asked.append(workers)
        return real(bag, topics, pieces=pieces, workers=workers, spill_imu_bytes=spill_imu_bytes)

    monkeypatch.setattr(pipeline, "read_bag", spy)
    with FirstPassAhead(NavConfig(), "rts") as ahead:
        pipeline.load_log(SAMPLE, ahead=ahead)
    pipeline.load_log(SAMPLE)
    assert asked == [0 if cores == 2 else 1, None]
