"""The vendor tally: the simulated tally (sim/tally.py), reading tally CSVs in their layouts and
refusing bad ones (io/tally_csv.py), and locating a tally on a run (products/tally.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pipe_nav_core.io.tally_csv import parse_tally, read_tally_csv
from pipe_nav_core.products.tally import locate_tally
from pipe_nav_core.products.welds import detect_welds
from pipe_nav_core.sim import get_scenario, simulate
from pipe_nav_core.sim.tally import TALLY_COLUMNS, make_tally


@pytest.fixture(scope="module")
def run():
    return simulate(get_scenario("demo"), seed=3)


def test_simulated_tally_has_the_vendor_errors(run, tmp_path):
    t = make_tally(run.welds, np.random.default_rng(1), n_features=15, missing=0.1, extra=0.05)
    assert 0.001 <= abs(t.scale_error) <= 0.01
    welds = [r for r in t.rows if r.weld]
    assert len(welds) == len(run.welds) - len(t.missing) + t.extra and t.extra == 1
    assert sum(not r.weld for r in t.rows) == 15
    for r in welds:
        if r.true_weld >= 0:
            log = float(r.cells[1])
            assert log == pytest.approx((1 + t.scale_error) * run.welds[r.true_weld], abs=0.05)
    p = tmp_path / "tally.csv"
    t.write_csv(p)
    tally = read_tally_csv(p)
    assert tally.header == TALLY_COLUMNS and len(tally.rows) == len(t.rows)
    assert [r.weld for r in tally.rows] == [r.weld for r in t.rows]


def test_other_layouts_are_read():
    text = ("GW No.;Log Distance [m];Joint Length (m);Feature;Clock;Extra\n"
            "10;100.0;12.1;Girth Weld;;x\n"
            ";104.5;;Metal Loss;3:30;y\n"
            "11;112.1;11.9;GW;;\n"
            "12;124.0;;girth weld;;\n")  # fmt: skip
    t = parse_tally(text, "v.csv")
    assert [r.weld for r in t.rows] == [True, False, True, True]
    f = t.rows[1]
    assert f.log == 104.5 and f.clock == 3.5 and f.kind == "Metal Loss" and f.cells[-1] == "y"
    # joint lengths only: log distances are their running sum; features from the weld above
    text = ("weld,joint_length_m,distance_to_us_weld_m,type\n"
            "1,12.0,,\n,,3.0,dent\n2,11.5,,\n3,,,\n")  # fmt: skip
    t = parse_tally(text, "j.csv")
    assert [r.log for r in t.welds()] == [0.0, 12.0, 23.5]
    assert t.rows[1].number == 1 and t.rows[1].rel == 3.0 and not t.rows[1].weld


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "bad.csv: empty file"),
        ("name,comment\na,b\n", "bad.csv:1: no log distance or joint length column"),
        ("weld,log_distance_m\n1,12.0\n2,abc\n", "bad.csv:3: log_distance_m 'abc' is not a number"),
        ("weld,log_distance_m,type,clock\n1,0,gw,\n,5,dent,14:00\n",
         "bad.csv:3: clock '14:00' is not a clock position"),
        ("weld,log_distance_m,distance_to_us_weld_m,type\n1,0,,gw\n7,,2.0,dent\n",
         "bad.csv:3: upstream weld 7 is not in the tally"),
        ("weld,log_distance_m,type\n1,0,gw\n,,dent\n",
         "bad.csv:3: a feature needs its log distance"),
        ("log_distance_m,type\n5.0,dent\n", "bad.csv: no girth weld rows"),
        ("weld,joint_length_m\n1,12\n2,-3\n", "bad.csv:3: joint_length_m -3.0 must be a finite"),
        ("weld,joint_length_m\n1,\n2,\n3,\n", "bad.csv:2: weld without a log distance or a joint"),
    ],
)
def test_bad_tally_input_is_one_line_naming_file_line_and_column(text, message):
    with pytest.raises(ValueError) as exc:
        parse_tally(text, "bad.csv")
    assert str(exc.value).startswith(message) and "\n" not in str(exc.value)


def test_tally_features_located_on_the_run(run):
    """On the true trajectory (the estimator's error left out): the tally's scale error and
    its missed and extra welds do not move a feature by more than a few centimetres."""
    welds = detect_welds(run.log, run.truth, run.datum, pipe_diameter=0.2)
    sim = make_tally(run.welds, np.random.default_rng(4), n_features=25, scale_error=-0.008,
                     missing=0.1, extra=0.05)  # fmt: skip
    import io as _io

    buf = _io.StringIO()
    buf.write(",".join(TALLY_COLUMNS) + "\n" + "".join(",".join(r.cells) + "\n" for r in sim.rows))
    tally = parse_tally(buf.getvalue(), "sim.csv")
    loc = locate_tally(tally, welds, run.truth)
    assert loc.scale == pytest.approx(1 / 0.992, abs=5e-4)
    errs = []
    for lr, truth in zip(loc.rows, sim.rows, strict=True):
        if not math.isfinite(truth.true_distance):
            assert lr.matched_weld is None  # the vendor's false weld matches nothing
            continue
        lat, lon, h = run.geometry.position(truth.true_distance)
        dn = (lr.lat - float(lat)) * 6.371e6
        de = (lr.lon - float(lon)) * 6.371e6 * math.cos(lr.lat)
        errs.append(math.sqrt(de**2 + dn**2 + (lr.alt - float(h)) ** 2))
        assert lr.sigma_h > 0 and lr.sigma_v >= 0
        if truth.weld:
            assert lr.matched_weld is not None
            assert welds[lr.matched_weld - 1].distance == pytest.approx(lr.distance)
    # (the worst: near the weld in the 3 D bend, found 0.17 m off along the pipe)
    assert max(errs) < 0.25 and np.sqrt(np.mean(np.square(errs))) < 0.06


def test_a_tally_of_another_pipe_does_not_match(run):
    welds = detect_welds(run.log, run.truth, run.datum, pipe_diameter=0.2)
    rng = np.random.default_rng(9)
    other = np.cumsum(rng.uniform(6.0, 18.0, 25))
    text = "log_distance_m,type\n" + "".join(f"{x:.3f},gw\n" for x in other)
    with pytest.raises(ValueError, match="match the run"):
        locate_tally(parse_tally(text, "other.csv"), welds, run.truth)
