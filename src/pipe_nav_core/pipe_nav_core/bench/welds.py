"""``pipe-nav bench`` welds table: girth weld detection and vendor tally location on smoothed
simulated runs, per IMU grade, against the simulator's truth.

Per run: the welds :func:`.products.welds.detect_welds` finds on the smoothed centreline are
matched one to one to the true welds by TRUE chainage at their passage time (within
``MATCH_M``): detection rate = matched / true, false = detections matching none (also per km).
Chainage error: true chainage at the detected passage time minus the weld's (the detector's
own error, the odometer's scale left out), and the run's ``distance_m`` minus the true chainage
(what a user sees, scale included). Position error: 3-D, the weld's WGS84 position against the
true pipe at the true weld. Tally: a simulated vendor tally (sim/tally.py; scale error
``TALLY_SCALE``, ``TALLY_MISSING`` of the welds missed, ``TALLY_EXTRA`` extra, 40 features)
located on the run (products/tally.py), each row's 3-D error against the true pipe.
"""

from __future__ import annotations

import math
import platform
import sys
import time
from dataclasses import replace
from typing import Any

import numpy as np

from pipe_nav_core.app.pipeline import run_welds, smooth_with_imu_model
from pipe_nav_core.bench.products import cell
from pipe_nav_core.config import NavConfig
from pipe_nav_core.geo.earth import geodetic_to_enu
from pipe_nav_core.io.tally_csv import parse_tally
from pipe_nav_core.products.tally import locate_tally
from pipe_nav_core.sim import get_scenario, simulate
from pipe_nav_core.sim.tally import TALLY_COLUMNS, make_tally

GRADES = ("consumer", "industrial", "tactical")
MATCH_M = 0.5  # m, a detection this close (true chainage) to a true weld is that weld
TALLY_SCALE = 0.005
TALLY_MISSING = 0.03
TALLY_EXTRA = 0.01
CASES = (("demo", None, "300 m, 0.2 m pipe, 2 m/s, magnetometer 20 Hz, 5 µT welds"),
         ("drag180", None, "180 m, 0.1 m bore, tight bends, magnetometer 50 Hz"),
         ("field10k", 2000.0, "field line (first 2 km), 219 mm, magnetometer 20 Hz, 10 µT "
          "welds in thick pipe"))  # fmt: skip


def _errors_3d(lat, lon, alt, geometry, s_true) -> np.ndarray:  # noqa: ANN001
    lat0, lon0, h0 = geometry.position(0.0)
    t_lat, t_lon, t_h = geometry.position(np.asarray(s_true))
    a = geodetic_to_enu(np.asarray(lat), np.asarray(lon), np.asarray(alt), float(lat0),
                        float(lon0), float(h0))  # fmt: skip
    b = geodetic_to_enu(np.asarray(t_lat), np.asarray(t_lon), np.asarray(t_h), float(lat0),
                        float(lon0), float(h0))  # fmt: skip
    return np.linalg.norm(np.asarray(a).reshape(-1, 3) - np.asarray(b).reshape(-1, 3), axis=1)


def run_case(scenario: str, grade: str, length: float | None, seed: int = 1) -> dict[str, Any]:
    """One simulated run: smoothed, welds detected and scored, a tally located and scored."""
    scn = replace(get_scenario(scenario), imu_grade=grade)
    if length:
        scn = scn.with_length(length)
    run = simulate(scn, seed=seed)
    cfg = NavConfig.from_dict(scn.estimator_settings())
    res = smooth_with_imu_model(run.log, cfg, method="rts")
    t0 = time.perf_counter()
    welds = run_welds(run.log, res, res.config or cfg)
    elapsed = time.perf_counter() - t0
    s_det = run.motion.chainage(np.array([w.t for w in welds]))[0]
    tw = run.welds
    nearest = [int(np.argmin(np.abs(tw - s))) for s in s_det]
    pairs = sorted((abs(s - tw[k]), i, k) for i, (s, k) in enumerate(zip(s_det, nearest,
                   strict=True)) if abs(s - tw[k]) <= MATCH_M)  # fmt: skip
    used_i: set[int] = set()
    used_k: set[int] = set()
    for _, i, k in pairs:
        if i not in used_i and k not in used_k:
            used_i.add(i)
            used_k.add(k)
    match = {i: k for _, i, k in pairs if i in used_i}
    ii = np.array(sorted(match))
    kk = np.array([match[i] for i in ii])
    err_s = s_det[ii] - tw[kk] if len(ii) else np.empty(0)
    err_d = np.array([welds[i].distance for i in ii]) - tw[kk] if len(ii) else np.empty(0)
    pos = np.empty(0)
    if len(ii):
        pos = _errors_3d([welds[i].lat for i in ii], [welds[i].lon for i in ii],
                         [welds[i].alt for i in ii], run.geometry, tw[kk])  # fmt: skip
    km = scn.total_length / 1000.0
    row: dict[str, Any] = {
        "scenario": scenario, "grade": grade, "length_m": scn.total_length, "seed": seed,
        "welds_true": len(tw), "welds_found": len(used_k), "detected": len(welds),
        "filled": sum(w.confidence == 0.0 for w in welds),
        "false": len(welds) - len(used_i), "false_per_km": (len(welds) - len(used_i)) / km,
        "detection_rate": len(used_k) / max(1, len(tw)),
        "chainage_err_rms_m": float(np.sqrt(np.mean(err_s**2))) if len(err_s) else math.nan,
        "chainage_err_max_m": float(np.max(np.abs(err_s))) if len(err_s) else math.nan,
        "distance_err_max_m": float(np.max(np.abs(err_d))) if len(err_d) else math.nan,
        "weld_pos_err_rms_m": float(np.sqrt(np.mean(pos**2))) if len(pos) else math.nan,
        "weld_pos_err_max_m": float(np.max(pos)) if len(pos) else math.nan,
        "weld_sigma_h_median_m": (float(np.median([w.sigma_h for w in welds])) if welds
                                  else math.nan),
        "welds_seconds": elapsed,
    }  # fmt: skip
    sim = make_tally(tw, np.random.default_rng([seed, 19]), n_features=40,
                     scale_error=TALLY_SCALE, missing=TALLY_MISSING, extra=TALLY_EXTRA)  # fmt: skip
    text = ",".join(TALLY_COLUMNS) + "\n" + "".join(",".join(r.cells) + "\n" for r in sim.rows)
    try:
        loc = locate_tally(parse_tally(text, "tally.csv"), welds, res.centreline)
    except ValueError as exc:
        row.update(tally_error=str(exc))
        return row
    real = [(lr, tr) for lr, tr in zip(loc.rows, sim.rows, strict=True)
            if math.isfinite(tr.true_distance)]  # fmt: skip
    feats = [(lr, tr) for lr, tr in real if not tr.weld]
    e = _errors_3d([lr.lat for lr, _ in feats], [lr.lon for lr, _ in feats],
                   [lr.alt for lr, _ in feats], run.geometry,
                   [tr.true_distance for _, tr in feats])  # fmt: skip
    sig = np.array([math.hypot(lr.sigma_h, lr.sigma_v) for lr, _ in feats])
    row.update(
        tally_rows=len(sim.rows), tally_welds_matched=len(loc.pairs),
        tally_scale_err=loc.scale * (1 + TALLY_SCALE) - 1.0,
        feature_err_rms_m=float(np.sqrt(np.mean(e**2))), feature_err_max_m=float(np.max(e)),
        feature_within_3sigma=float(np.mean(e <= 3.0 * sig)),
    )  # fmt: skip
    return row


def run(quick: bool = False, seed: int = 1, grades: tuple[str, ...] = GRADES
        ) -> list[dict[str, Any]]:  # fmt: skip
    """Every case for every grade (quick: the demo only)."""
    rows = []
    for scenario, length, _ in CASES[:1] if quick else CASES:
        for grade in grades:
            print(f"pipe-nav bench: welds {scenario} {grade}", file=sys.stderr, flush=True)
            try:
                rows.append(run_case(scenario, grade, length, seed))
            except Exception as exc:  # noqa: BLE001 - one failed case must not lose the table
                rows.append({"scenario": scenario, "grade": grade, "error": repr(exc)})
    return rows


def markdown(rows: list[dict[str, Any]], command: str) -> str:
    """The welds-and-tally table."""
    lines = [
        "## Girth welds and the vendor tally",
        "",
        "Welds detected from the magnetometer on smoothed simulated runs (RTS as pipe-nav smooth,",
        "one seed) against the simulator's welds, matched in true chainage within "
        f"{MATCH_M} m; a vendor tally (scale error {TALLY_SCALE * 100:g} %, "
        f"{TALLY_MISSING * 100:g} % of the welds missed, {TALLY_EXTRA * 100:g} % extra, 40 "
        "features) located on each run. Produced by:",
        "",
        "```",
        command,
        "```",
        "",
        f"Machine: {platform.machine()}, Python {platform.python_version()}.",
        "chainage err: the detector's (true chainage at the detected passage); distance_m err:",
        "the run's chainage against the true (odometer scale included); weld and feature errors",
        "3-D against the true pipe.",
        "",
        "| scenario | IMU | welds found/true | detection rate | false (per km) | filled "
        "| chainage err RMS / max [m] | distance_m err max [m] | weld 3-D err RMS / max [m] "
        "| tally welds matched | feature 3-D err RMS / max [m] | features within 3σ |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['scenario']} | {r['grade']} |" + " |" * 9
                         + f" ERROR {r['error']} |")  # fmt: skip
            continue
        name = r["scenario"] + (f" ({r['length_m'] / 1000:g} km)" if r["scenario"] == "field10k"
                                else "")  # fmt: skip
        lines.append(
            f"| {name} | {r['grade']} | {r['welds_found']}/{r['welds_true']} "
            f"| {r['detection_rate'] * 100:.1f} % | {r['false']} ({r['false_per_km']:.1f}) "
            f"| {r['filled']} | {cell(r['chainage_err_rms_m'], '.3f')} / "
            f"{cell(r['chainage_err_max_m'], '.3f')} | {cell(r['distance_err_max_m'], '.2f')} "
            f"| {cell(r['weld_pos_err_rms_m'], '.3f')} / {cell(r['weld_pos_err_max_m'], '.3f')} "
            f"| {r.get('tally_welds_matched', '')} "
            f"| {cell(r.get('feature_err_rms_m'), '.3f')} "
            f"/ {cell(r.get('feature_err_max_m'), '.3f')} "
            f"| {cell(100 * r.get('feature_within_3sigma', math.nan), '.0f')} % |"
        )
    lines += ["", "Scenarios:", ""]
    lines += [f"- `{s}`: {d}." for s, _, d in CASES if any(r["scenario"] == s for r in rows)]
    return "\n".join(lines) + "\n"


def main() -> None:  # pragma: no cover - a command
    quick = "--quick" in sys.argv
    rows = run(quick=quick)
    print(markdown(rows, "python -m pipe_nav_core.bench.welds" + (" --quick" if quick else "")))


if __name__ == "__main__":  # pragma: no cover
    main()


__all__ = ["CASES", "GRADES", "markdown", "run", "run_case"]
