"""Girth welds (products/welds.py): detection from the magnetometer on a simulated run, the
joint-length sequence filling a missed weld and dropping a false one, the wheel's jolt on the
bead (sim/weld_bump.py), sequence alignment with missed/extra welds and a scale error, and the
RUN_welds.csv file and the smoothed bag's attachments."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from pipe_nav_core.config import NavConfig
from pipe_nav_core.io.bagwrite import write_output_bag
from pipe_nav_core.io.smoothed_bag import (
    read_smoothed_bag,
    read_smoothed_run,
    smoothed_attachments,
)
from pipe_nav_core.io.welds_csv import WELD_COLUMNS, read_welds_csv, write_welds_csv
from pipe_nav_core.products.welds import detect_welds, jolt_chainages
from pipe_nav_core.sim import get_scenario, simulate
from pipe_nav_core.sim.kinematics import evaluate
from pipe_nav_core.sim.magnetometer import WeldField
from pipe_nav_core.smooth.passes import smooth_log
from pipe_nav_core.types import MagSamples, SensorLog

UT = 1e-6


@pytest.fixture(scope="module")
def demo():
    scn = get_scenario("demo")
    run = simulate(scn, seed=1)
    res = smooth_log(run.log, NavConfig.from_dict(scn.estimator_settings()))
    return run, res


def _true_chainage(run, welds):
    return run.motion.chainage(np.array([w.t for w in welds]))[0]


def _match(run, welds, tol=0.3):
    """(true weld index or -1) per detected weld, by true chainage at its passage time."""
    s = _true_chainage(run, welds)
    out = []
    for x in s:
        k = int(np.argmin(np.abs(run.welds - x)))
        out.append(k if abs(run.welds[k] - x) <= tol else -1)
    return out, s


def test_the_simulated_run_knows_its_welds(demo):
    run, _ = demo
    assert len(run.welds) == 24 and np.all(np.diff(run.welds) > 11.0)
    assert run.weld_field is not None and np.array_equal(run.weld_field.welds, run.welds)
    # the pipe's welds, not the seed's
    assert np.array_equal(simulate(get_scenario("demo").with_length(60.0), seed=7).welds,
                          run.welds[run.welds < 60.0])  # fmt: skip


def test_the_magnetometer_placed_on_the_centreline_in_batches_is_the_same(demo, monkeypatch):
    """At field scale the magnetometer samples are placed on the centreline a batch at a time
    (bounded memory): the welds' residual from batches of a few samples is the same, bit for
    bit."""
    from pipe_nav_core.products import welds

    from pipe_nav_core import batched

    run, res = demo
    whole = welds.mag_residual(run.log, res.centreline)
    monkeypatch.setattr(batched, "BATCH", 7)
    batched = welds.mag_residual(run.log, res.centreline)
    assert all(a.tobytes() == b.tobytes() for a, b in zip(whole, batched))
    assert len(whole[0]) > 1000


def test_the_regressors_kept_in_a_file_give_the_same_welds(demo, monkeypatch):
    """At field scale the field fit's regressors wait in a file between the fits
    (pipe_nav_core.memory): the residual, with and without welds left out of the fit, and the
    welds are the same, bit for bit, and the regressors are in memory only while read."""
    import mmap

    from pipe_nav_core.products import welds

    from pipe_nav_core import memory

    run, res = demo
    in_memory = [welds.mag_residual(run.log, res.centreline, exclude=ex, exclude_half=0.8)
                 for ex in ((), (20.0, 57.5))]  # fmt: skip
    found = detect_welds(run.log, res.centreline, res.datum, pipe_diameter=0.2)
    monkeypatch.setattr(welds, "MAPPED_X_BYTES", 0)
    samples = welds._mag_samples(run.log, res.centreline)
    assert samples is not None and isinstance(samples.x.base.base.obj, mmap.mmap)  # in a file
    in_file = [welds.mag_residual(run.log, res.centreline, exclude=ex, exclude_half=0.8)
               for ex in ((), (20.0, 57.5))]  # fmt: skip
    for a, b in zip(in_memory, in_file):
        assert all(u.tobytes() == v.tobytes() for u, v in zip(a, b))
    again = detect_welds(run.log, res.centreline, res.datum, pipe_diameter=0.2)
    assert repr(again) == repr(found) and len(found) > 10
    before = samples.x.copy()
    memory.let_go(samples.x)  # the values come back from the file
    assert samples.x.tobytes() == before.tobytes()
    assert isinstance(memory.file_array((3, 2), 1 << 20), np.ndarray)  # small: in memory
    assert not memory.file_array((3, 2), 1 << 20).any()


def test_every_weld_found_at_its_chainage_none_false(demo):
    run, res = demo
    welds = detect_welds(run.log, res.centreline, res.datum, pipe_diameter=0.2)
    idx, s = _match(run, welds)
    assert sorted(idx) == list(range(len(run.welds)))  # each once, no false one
    err = s - run.welds[idx]
    # the worst is weld 5, 0.12 m into the 45 deg bend of 3 D (0.6 m radius) at 60 m, where the
    # smoothed attitude turns fastest
    assert np.sqrt(np.mean(err**2)) < 0.05 and np.max(np.abs(err)) < 0.2
    assert np.sort(np.abs(err))[-2] < 0.05
    assert [w.number for w in welds] == list(range(1, len(welds) + 1))
    assert all(w.confidence > 0.5 for w in welds)
    joints = [w.joint_length for w in welds]
    assert math.isnan(joints[-1]) and np.allclose(joints[:-1], np.diff([w.distance for w in welds]))
    for w in welds:
        assert 0.0 < w.sigma_distance < 0.2 and 0.0 < w.sigma_h < 0.5 and 0.0 < w.sigma_v < 0.5
    # positions: the true pipe at the true weld chainage, within a few sigma
    for w, k in zip(welds, idx, strict=True):
        lat, lon, h = run.geometry.position(run.welds[k])
        dn = (w.lat - float(lat)) * 6.371e6
        de = (w.lon - float(lon)) * 6.371e6 * math.cos(w.lat)
        assert math.hypot(de, dn) < 0.25 and abs(w.alt - float(h)) < 0.25


def _without_weld(run, k, extra_at=None, extra_ut=0.0):
    """The run's log with weld k's anomaly removed (and a weak false one added at extra_at)."""
    t = run.log.mag.t
    st = evaluate(run.geometry, run.motion, t)
    wf = run.weld_field
    fields = [(WeldField(wf.welds[k : k + 1], -wf.vectors[k : k + 1], wf.width))]
    if extra_at is not None:
        fields.append(WeldField(np.array([extra_at]), np.array([[extra_ut * UT, 0.0, 0.0]]),
                                wf.width))  # fmt: skip
    b = run.log.mag.field.copy()
    for f in fields:
        b += np.einsum("mij,mi->mj", st.c_nb, f.field_enu(st.s)) @ run.r_base_imu
    log = SensorLog(run.log.imu, run.log.odometer, MagSamples(t, b), run.log.markers)
    return log


def test_a_missed_weld_is_filled_in_and_a_false_one_dropped(demo):
    run, res = demo
    k = 10
    mid = 0.5 * (run.welds[15] + run.welds[16])
    log = _without_weld(run, k, extra_at=mid, extra_ut=1.2)
    raw = detect_welds(log, res.centreline, res.datum, pipe_diameter=0.2, clean=False)
    raw_s = _true_chainage(run, raw)
    assert np.min(np.abs(raw_s - run.welds[k])) > 1.0  # the magnetometer alone misses it
    assert np.min(np.abs(raw_s - mid)) < 0.2  # and sees the false one
    welds = detect_welds(log, res.centreline, res.datum, pipe_diameter=0.2)
    s = _true_chainage(run, welds)
    assert len(welds) == len(run.welds)
    j = int(np.argmin(np.abs(s - run.welds[k])))
    assert abs(s[j] - run.welds[k]) < 0.8 and welds[j].confidence == 0.0
    assert welds[j].sigma_distance > 0.5  # filled in: where in the joint is not known
    assert np.min(np.abs(s - mid)) > 3.0
    assert sum(w.confidence == 0.0 for w in welds) == 1


def test_no_magnetometer_no_welds(demo):
    run, res = demo
    log = SensorLog(run.log.imu, run.log.odometer, markers=run.log.markers)
    assert detect_welds(log, res.centreline, res.datum) == []


def test_weld_bump_is_off_by_default_and_seen_when_on():
    scn = get_scenario("demo").with_length(80.0)
    assert scn.weld_bump_height == 0.0
    plain = simulate(scn, seed=2)
    bumped = simulate(replace(scn, weld_bump_height=5e-4, weld_bump_duration=0.01), seed=2)
    d = bumped.log.imu.accel - plain.log.imu.accel
    assert np.array_equal(bumped.log.imu.gyro, plain.log.imu.gyro)
    assert np.allclose(d[:, :2], 0.0) and 2.0 < np.max(np.abs(d[:, 2])) < 8.0
    changed = plain.log.imu.t[np.abs(d[:, 2]) > 1e-3]
    t_w = plain.motion.chainage(changed)[0]
    assert np.min(np.abs(t_w[:, None] - plain.welds[None, :]), axis=1).max() < 0.3
    # the detector finds the jolts at the welds (on the true trajectory here)
    found = jolt_chainages(bumped.log, bumped.truth)
    near = np.min(np.abs(found[:, None] - plain.welds[None, :]), axis=0)
    assert np.all(near < 0.15)  # every weld's jolt
    # what else it finds is the motion's (curvature steps at bend ends), there without bumps,
    # and a jolt alone never makes a weld (a weak magnetic peak must confirm it)
    other = found[np.min(np.abs(found[:, None] - plain.welds[None, :]), axis=1) > 0.3]
    motion = jolt_chainages(plain.log, plain.truth)
    assert len(other) <= 3 and all(np.min(np.abs(motion - x)) < 0.3 for x in other)


def test_the_jolts_found_before_the_smoothing_give_the_same_welds():
    """The IMU's part of the jolt search (jolt_deviation) is found while the run is smoothed
    (the pipeline's other core): handed in, the jolts and the welds are those found after."""
    from pipe_nav_core.products.welds import jolt_deviation

    scn = replace(get_scenario("demo").with_length(120.0), weld_bump_height=5e-4,
                  weld_bump_duration=0.01)  # fmt: skip
    run = simulate(scn, seed=2)
    res = smooth_log(run.log, NavConfig.from_dict(scn.estimator_settings()))
    after = jolt_chainages(run.log, res.centreline)
    before = jolt_chainages(run.log, res.centreline, deviation=jolt_deviation(run.log.imu))
    assert len(after) >= 5 and after.tobytes() == before.tobytes()
    found = detect_welds(run.log, res.centreline, res.datum, pipe_diameter=0.2)
    given = detect_welds(run.log, res.centreline, res.datum, pipe_diameter=0.2,
                         jolts=jolt_deviation(run.log.imu))  # fmt: skip
    assert repr(given) == repr(found) and len(found) >= 5


def test_welds_csv_round_trip_and_layout(demo, tmp_path):
    run, res = demo
    welds = detect_welds(run.log, res.centreline, res.datum, pipe_diameter=0.2)
    p = tmp_path / "RUN_welds.csv"
    write_welds_csv(p, welds)
    lines = p.read_text().splitlines()
    assert lines[0] == ("weld,distance_m,latitude_deg,longitude_deg,altitude_m,joint_length_m,"
                        "confidence,sigma_h_m,sigma_v_m,time_s,sigma_distance_m")  # fmt: skip
    assert lines[0].split(",") == WELD_COLUMNS
    assert lines[-1].split(",")[5] == "" and "nan" not in p.read_text()
    assert len(lines[1].split(",")[2].split(".")[1]) == 9
    back = read_welds_csv(p)
    assert [w.number for w in back] == [w.number for w in welds]
    assert np.allclose([w.distance for w in back], [w.distance for w in welds], atol=1e-4)
    assert np.allclose([w.lat for w in back], [w.lat for w in welds], atol=1e-10)
    bad = replace(welds[0], sigma_h=float("nan"))
    with pytest.raises(ValueError, match="weld 1: sigma_h_m not finite"):
        write_welds_csv(tmp_path / "bad.csv", [bad, *welds[1:]])
    (tmp_path / "broken.csv").write_text(lines[0] + "\n1,abc,0,0,0,1,1,0,0,0,0\n")
    with pytest.raises(ValueError, match=r"broken.csv:2: distance_m 'abc' is not a number"):
        read_welds_csv(tmp_path / "broken.csv")


def test_smoothed_bag_carries_welds_and_centreline(demo, tmp_path):
    run, res = demo
    welds = detect_welds(run.log, res.centreline, res.datum, pipe_diameter=0.2)
    rows = res.centreline
    sel = np.arange(0, len(rows.t), 50)
    from pipe_nav_core.io.centreline import take

    path = take(rows, sel)
    bag = tmp_path / "run_smoothed.mcap"
    write_output_bag(bag, path=path, datum=res.datum,
                     attachments=smoothed_attachments(path, res.datum, welds))  # fmt: skip
    r = read_smoothed_run(bag)
    assert r.attachments == ["centreline.csv", "welds.csv"]
    assert len(r.welds) == len(welds)
    assert r.trajectory.sigma_enu is not None
    assert np.allclose(r.trajectory.distance, path.distance, atol=1e-4)  # distance_m, not arc
    traj, datum, _ = read_smoothed_bag(bag)  # the old reader still works
    assert len(traj.t) == len(sel) and datum == pytest.approx(res.datum)
    plain = tmp_path / "plain.mcap"
    write_output_bag(plain, path=path, datum=res.datum)
    r = read_smoothed_run(plain)
    assert r.welds == [] and r.attachments == [] and r.trajectory.sigma_enu is None


def test_field_fit_normal_equations_and_the_degenerate_run():
    """The field fit (welds._field_fit) gives least squares' coefficients: through the normal
    equations for a pig that turns and rolls, and from the SVD with the null directions left out
    for one that never turns (its C_nb columns constant, collinear with the constant column),
    where the normal equations are singular."""
    from pipe_nav_core.products.welds import FIT_COND_MAX, _field_fit

    rng = np.random.default_rng(7)
    b = rng.normal(size=(5000, 3))
    turning = np.column_stack([rng.uniform(-1.0, 1.0, size=(5000, 9)), np.ones(5000)])
    assert np.linalg.cond(turning.T @ turning) < FIT_COND_MAX
    ref = np.linalg.lstsq(turning, b, rcond=1e-9)[0]
    np.testing.assert_allclose(_field_fit(turning, b), ref, rtol=1e-9, atol=1e-12)
    straight = np.column_stack([np.tile(rng.uniform(-1.0, 1.0, 9), (5000, 1)), np.ones(5000)])
    straight[:, 0] += 1e-12 * rng.normal(size=5000)  # round-off, not information
    assert np.linalg.cond(straight.T @ straight) > FIT_COND_MAX
    coef = _field_fit(straight, b)
    ref = np.linalg.lstsq(straight, b, rcond=1e-9)[0]
    assert np.isfinite(coef).all()
    np.testing.assert_allclose(straight @ coef, straight @ ref, atol=1e-9)
    np.testing.assert_allclose(coef, ref, atol=1e-9)
