"""File input and output of the ROS-free core (INTERFACES.md): ROS 2 bags (MCAP), marker and
centreline CSV, GeoJSON and KML; ROS message conversion lives in :mod:`.rosmsg`.

Modules: :mod:`.topics` (names, BagError, BagReport), :mod:`.stamps` (exact ns <-> s),
:mod:`.cdr` (vectorized CDR), :mod:`.mcapread` (the MCAP scanner, with :mod:`.mcaprecords`
and :mod:`.mcapchunks`) / :mod:`.mcapwrite` (MCAP records),
:mod:`.bagread` (the reader, with :mod:`.bagfiles`, :mod:`.bagdecode`, :mod:`.topic_checks`),
:mod:`.baginfo` (cheap metadata), :mod:`.bagwrite`, :mod:`.rosmsg`, :mod:`.markers_csv`,
:mod:`.centreline`, :mod:`.gis`, :mod:`.atomic`.
"""

from __future__ import annotations

from pipe_nav_core.errors import BagError, CentrelineCsvError, MarkerCsvError, OutputIsInputError
from pipe_nav_core.io.atomic import atomic_path, atomic_write, ensure_not_input
from pipe_nav_core.io.bagfiles import bag_files, bag_stem
from pipe_nav_core.io.baginfo import BagInfo, TopicInfo, bag_info, bag_time_range
from pipe_nav_core.io.bagread import concat_logs, iter_bag, read_bag
from pipe_nav_core.io.bagwrite import write_output_bag, write_sensor_bag
from pipe_nav_core.io.centreline import (
    CENTRELINE_COLUMNS,
    CENTRELINE_HEADER,
    interpolate_trajectory,
    read_centreline_csv,
    resample_by_chainage,
    write_centreline_csv,
)
from pipe_nav_core.io.gis import write_geojson, write_kml
from pipe_nav_core.io.markers_csv import (
    MARKER_COLUMNS,
    merge_markers,
    read_markers_csv,
    write_markers_csv,
)
from pipe_nav_core.io.rosbag2_metadata import write_rosbag2_metadata
from pipe_nav_core.io.topics import BagReport, TopicNames

__all__ = [
    "CENTRELINE_COLUMNS",
    "CENTRELINE_HEADER",
    "MARKER_COLUMNS",
    "BagError",
    "BagInfo",
    "BagReport",
    "CentrelineCsvError",
    "MarkerCsvError",
    "OutputIsInputError",
    "TopicInfo",
    "TopicNames",
    "atomic_path",
    "atomic_write",
    "bag_files",
    "bag_stem",
    "bag_info",
    "bag_time_range",
    "concat_logs",
    "ensure_not_input",
    "interpolate_trajectory",
    "iter_bag",
    "merge_markers",
    "read_bag",
    "read_centreline_csv",
    "read_markers_csv",
    "resample_by_chainage",
    "write_centreline_csv",
    "write_geojson",
    "write_kml",
    "write_markers_csv",
    "write_output_bag",
    "write_rosbag2_metadata",
    "write_sensor_bag",
]
