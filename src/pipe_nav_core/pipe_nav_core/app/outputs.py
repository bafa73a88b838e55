"""The outputs of a smoothed run: where each is written (:class:`Outputs`, with the option that
names it), the centreline resampled along the pipe, and the bag, CSV, GeoJSON, KML, plot and
integrity products written all or none (temporary files renamed at the end,
:func:`pipe_nav_core.io.atomic.all_or_none`), the plot drawn meanwhile in a child process.

Positions in the outputs are geodetic (WGS84, degrees and metres) or local ENU metres about
the run's datum; chainage in metres along the pipe.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pipe_nav_core.app.plot_process import PlotProcess
from pipe_nav_core.io import (
    resample_by_chainage,
    write_centreline_csv,
    write_geojson,
    write_kml,
    write_output_bag,
)
from pipe_nav_core.io.atomic import all_or_none, check_output, ensure_not_input
from pipe_nav_core.io.centreline import centreline_text, concat, pieces_of
from pipe_nav_core.io.gis import centreline_coords
from pipe_nav_core.io.products_csv import (
    write_bends_csv,
    write_strain_csv,
    write_strain_features_csv,
)
from pipe_nav_core.io.smoothed_bag import smoothed_attachments
from pipe_nav_core.io.welds_csv import write_welds_csv
from pipe_nav_core.products import IntegrityReport
from pipe_nav_core.smooth.centreline import SmoothResult
from pipe_nav_core.types import Trajectory

Say = Callable[[str], None]  # told each stage as it begins (Progress.stage)


@dataclass
class Outputs:
    """Where to write what (None = do not write)."""

    bag: str | None = None
    csv: str | None = None
    geojson: str | None = None
    kml: str | None = None
    plot: str | None = None
    strain: str | None = None  # the integrity products (products/), named like the centreline
    bends: str | None = None
    strain_features: str | None = None
    welds: str | None = None  # RUN_welds.csv, written when the run has a magnetometer

    # the command-line option that names each output, for messages
    OPTIONS = {"bag": "--out", "csv": "--csv", "geojson": "--geojson", "kml": "--kml",
               "plot": "--plot", "strain": "--csv/--out", "bends": "--csv/--out",
               "strain_features": "--csv/--out", "welds": "--csv/--out"}  # fmt: skip

    def paths(self) -> list[str]:
        return [p for p in (getattr(self, name) for name in self.OPTIONS) if p]

    def with_products(self) -> Outputs:
        """These outputs plus the integrity products beside the centreline CSV (else beside
        the bag): ``RUN_strain.csv``, ``RUN_bends.csv``, ``RUN_strain_features.csv``,
        ``RUN_welds.csv`` where RUN is the CSV's (or bag's) name without ``_centerline``
        (``_smoothed``) and suffix."""
        base = self.csv or self.bag
        if not base:
            return self
        stem = str(Path(base).with_suffix(""))
        for tail in ("_centerline", "_centreline", "_smoothed"):
            if stem.endswith(tail):
                stem = stem[: -len(tail)]
                break
        return replace(self, strain=f"{stem}_strain.csv", bends=f"{stem}_bends.csv",
                       strain_features=f"{stem}_strain_features.csv",
                       welds=f"{stem}_welds.csv")  # fmt: skip

    def check(self, inputs: Sequence[str | os.PathLike[str]], spacing: float) -> None:
        """Before any work: every output writable, none an input, no two the same file, and
        the CSV spacing a positive number; ValueError naming the option otherwise."""
        if not (math.isfinite(spacing) and spacing > 0.0):
            raise ValueError(f"--spacing must be a positive number of metres, not {spacing}")
        seen: dict[str, str] = {}
        for name, option in self.OPTIONS.items():
            path = getattr(self, name)
            if not path:
                continue
            check_output(path, option)
            ensure_not_input(path, inputs)
            real = os.path.realpath(path)
            if real in seen:
                raise ValueError(f"{seen[real]} and {option} name the same file {path}")
            seen[real] = option


def centreline_rows(result: SmoothResult, spacing: float) -> Trajectory:
    """The centreline resampled every ``spacing`` m of chainage plus a row at every marker;
    a centreline in pieces (segments across data gaps) gets no row across its holes. A path
    that is not the pipe (quality.lost_path: its chainage means nothing) is written at its
    own epochs."""
    c = result.centreline
    if result.summary.get("path_lost"):
        return c
    pieces = pieces_of(c)
    rows = []
    for p in pieces:
        times = [m.t for m in result.markers if p.t[0] <= m.t <= p.t[-1]]
        rows.append(resample_by_chainage(p, spacing, times))
    return rows[0] if len(rows) == 1 else concat(rows)


def write_products(
    result: SmoothResult,
    outputs: Outputs,
    *,
    spacing: float = 0.5,
    progress: Say | None = None,
    plotter: PlotProcess | None = None,
    meanwhile: Callable[[], None] | None = None,
) -> Trajectory:
    """Write the bag, CSV, GeoJSON, KML and plot of a smoothing result: all of them or, if
    one fails (or the run is interrupted), none (io.atomic.all_or_none). ``plotter``: a
    child process that draws the plot meanwhile (else it is drawn here); ``meanwhile``: the
    last work on ``result`` that the other outputs need and the plot does not (the welds),
    done while the plot is drawn."""
    say = progress or (lambda _m: None)
    rows = centreline_rows(result, spacing)
    with all_or_none(outputs.paths()) as staged:
        _write_staged(result, outputs, rows, staged, say, plotter, meanwhile)
    return rows


def run_metadata(summary: dict[str, object]) -> dict[str, str]:
    """What the smoothed bag records of its run (MCAP metadata ``pipe_nav``): the quality
    verdict and its reasons, the IMU model and why, the markers used and rejected, the smoothing
    passes run, whether they converged and their epoch rate (Hz; with the markers before which
    the long epochs lost the odometer, when the run was smoothed again at the live filter's),
    and for the graph smoother its iterations and whether it converged."""
    q = summary.get("quality") or {}
    model = summary.get("imu_model") or {}
    return {
        "quality": str(q.get("status", "")),  # type: ignore[union-attr]
        "quality_reasons": "; ".join(q.get("reasons", [])),  # type: ignore[union-attr]
        "imu_model": str(model.get("grade", "")),  # type: ignore[union-attr]
        "imu_model_reason": str(model.get("reason", "")),  # type: ignore[union-attr]
        "markers_used": str(summary.get("markers_used", "")),
        "markers_rejected": str(summary.get("markers_rejected", "")),
        **(
            {
                "passes": str(summary["passes_run"]),
                "passes_converged": str(bool(summary["converged"])).lower(),
                "epoch_rate_hz": f"{float(summary.get('epoch_rate_hz', 0.0)):g}",
            }
            if "converged" in summary
            else {}
        ),  # fmt: skip
        **(
            {"long_epochs_lost_odometer": ",".join(summary["long_epochs_lost_odometer"])}  # type: ignore[arg-type]
            if summary.get("long_epochs_lost_odometer")
            else {}
        ),  # fmt: skip
        **(
            {
                "method": "graph",
                "graph_iterations": str(summary["graph_iterations"]),
                "graph_converged": str(bool(summary.get("graph_converged"))).lower(),
            }
            if "graph_iterations" in summary
            else {}
        ),  # fmt: skip
    }


def _write_staged(
    result: SmoothResult,
    outputs: Outputs,
    rows: Trajectory,
    staged: dict[str, Path],
    say: Say,
    plotter: PlotProcess | None,
    meanwhile: Callable[[], None] | None,
) -> None:
    products = result.products
    bends = products.bends if products else []
    if outputs.plot:  # first: a child process draws it while the others are written
        say("plotting")
        _submit_plot(result, rows, staged[outputs.plot], Path(outputs.plot).stem, plotter)
    # what does not show the welds, while they are found (in the caller's other thread): the
    # files without them, the centreline's text and coordinates for those with them
    text = centreline_text(rows, result.datum) if outputs.csv or outputs.bag else None
    if outputs.csv:
        write_centreline_csv(staged[outputs.csv], rows, result.datum, text)
    if result.products is not None:
        write_products_csv(result.products, outputs, staged)
    coords = centreline_coords(rows) if outputs.geojson or outputs.kml else None
    if meanwhile is not None:
        meanwhile()
    features = products.features if products else []
    if outputs.bag:
        say("writing bag")
        write_output_bag(staged[outputs.bag], path=rows, datum=result.datum,
                         odometry=result.forward, file_name=Path(outputs.bag).name,
                         run_metadata=run_metadata(result.summary), bends=bends,
                         attachments=smoothed_attachments(rows, result.datum, result.welds,
                                                          text))  # fmt: skip
    welds = result.welds or []
    bridges = result.summary.get("bridges") or []  # across data gaps (segments.Bridge)
    if outputs.geojson:
        write_geojson(staged[outputs.geojson], rows, result.markers, bends=bends,
                      strain_features=features, welds=welds, bridges=bridges,
                      coords=coords)  # fmt: skip
    if outputs.kml:
        write_kml(staged[outputs.kml], rows, result.markers, bends=bends,
                  strain_features=features, welds=welds, bridges=bridges,
                  coords=coords)  # fmt: skip
    if outputs.welds and result.welds is not None:
        write_welds_csv(staged[outputs.welds], result.welds)
    if plotter is not None:
        plotter.wait()


def _submit_plot(
    result: SmoothResult, rows: Trajectory, path: Path, title: str, plotter: PlotProcess | None
) -> None:
    from pipe_nav_core.app.plots import plot_report

    markers = [m for m in result.markers if m.name in result.marker_residuals]
    res = np.array([result.marker_residuals[m.name] for m in markers]).reshape(-1, 3)
    args = (path, rows, result.datum, markers, res if len(res) else None)
    kwargs = {"title": title, "integrity": result.products}
    if plotter is None:
        plot_report(*args, **kwargs)
    else:
        plotter.submit(*args, **kwargs)


def write_products_csv(report: IntegrityReport, outputs: Outputs, staged: dict[str, Path]) -> None:
    if outputs.strain:
        write_strain_csv(staged[outputs.strain], report.profile, report.strain_pct,
                         report.sigma_strain_pct)  # fmt: skip
    if outputs.bends:
        write_bends_csv(staged[outputs.bends], report.bends)
    if outputs.strain_features:
        write_strain_features_csv(staged[outputs.strain_features], report.features)
