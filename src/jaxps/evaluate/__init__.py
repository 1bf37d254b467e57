"""Evaluation: how far a reconstruction is from the truth (`jaxps.evaluate`).

Takes normals and height maps with a reference (normal maps, depth scans); gives angular,
$\\ell_2$ and height errors (MADE, RMS), ICP alignment to a scanned point cloud, per-pixel error
maps and their figures; `read_scan` reads a scan's mesh or point file.
"""

from ._icp import (
    ICP_METHODS,
    ICPResult,
    estimate_normals,
    icp,
    points_from_depth,
    points_from_height,
    transform_points,
)
from ._metrics import (
    angular_error,
    angular_stats,
    fit_scale_offset,
    height_error_map,
    height_stats,
    made,
)
from ._plot import plot_error_maps
from ._scan import SCAN_EXTENSIONS, ScanComparison, compare_to_scan, l2_error, read_scan

__all__ = [
    "ICP_METHODS",
    "SCAN_EXTENSIONS",
    "ICPResult",
    "ScanComparison",
    "angular_error",
    "angular_stats",
    "compare_to_scan",
    "estimate_normals",
    "fit_scale_offset",
    "height_error_map",
    "height_stats",
    "icp",
    "l2_error",
    "made",
    "plot_error_maps",
    "points_from_depth",
    "points_from_height",
    "read_scan",
    "transform_points",
]
