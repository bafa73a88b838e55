"""The accuracy benchmark: its rows and the table it writes."""

from pipe_nav_core import bench


def test_test_pipe_case_scores_rts_with_and_without_survey_error():
    case = next(c for c in bench.CASES if c.scenario == "sag104")
    rows = bench.run_case(case, 1, ["rts"])
    by = {r["method"]: r for r in rows}
    assert set(by) == {"rts", bench.EXACT, bench.BASELINE}
    # the same runs: only the markers' survey error differs, and at the markers the
    # centreline carries it (seed 1's survey is 4.4 cm off vertically at the launch marker)
    assert by[bench.EXACT]["max_v"] < 0.5 * by["rts"]["max_v"]
    assert by[bench.EXACT]["max_h"] < by["rts"]["max_h"]
    md = bench.markdown({"sag104": rows}, "pipe-nav bench --scenarios sag104", 1)
    line = next(x for x in md.splitlines() if f"| {bench.EXACT} |" in x)
    assert "| met |" in line or "| NOT met |" in line
    assert "surveyed exactly" in md
