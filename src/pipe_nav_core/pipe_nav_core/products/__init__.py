"""What a run says about the pipe, computed from the smoothed solution (never from the raw
sensors a second time): the curvature profile, bending strain, the bend list and the strain
features (:mod:`.curvature`, :mod:`.strain`, :mod:`.bends`), bundled by :mod:`.integrity`."""

from __future__ import annotations

from pipe_nav_core.products.bends import BEND_CLASSES, PipeBend, find_bends
from pipe_nav_core.products.curvature import (
    AxisTrack,
    CurvatureProfile,
    axis_track,
    curvature_profile,
)
from pipe_nav_core.products.integrity import IntegrityReport, integrity_report, no_products
from pipe_nav_core.products.strain import (
    StrainFeature,
    read_bends_reference,
    strain_features,
    strain_pct,
)

__all__ = [
    "BEND_CLASSES",
    "AxisTrack",
    "CurvatureProfile",
    "IntegrityReport",
    "PipeBend",
    "StrainFeature",
    "axis_track",
    "curvature_profile",
    "find_bends",
    "integrity_report",
    "no_products",
    "read_bends_reference",
    "strain_features",
    "strain_pct",
]
