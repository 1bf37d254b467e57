"""Error measures between a reconstruction and a reference (``jaxps.evaluate``)."""

from __future__ import annotations

import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from ._error_maps import ScanComparison, compare_to_scan, l2_error, plot_error_maps
from ._icp import (
    ICP_METHODS,
    ICPResult,
    estimate_normals,
    icp,
    points_from_depth,
    points_from_height,
    transform_points,
)
from ._render import angular_error

__all__ = [
    "ICP_METHODS",
    "ICPResult",
    "ScanComparison",
    "angular_error",
    "angular_stats",
    "compare_to_scan",
    "estimate_normals",
    "icp",
    "l2_error",
    "plot_error_maps",
    "points_from_depth",
    "points_from_height",
    "transform_points",
]


def angular_stats(
    normals: Float[ArrayLike, "H W 3"],
    reference: Float[ArrayLike, "H W 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
) -> dict[str, float]:
    """Median, mean, RMS and 95th percentile of the angular error (degrees) over `mask`."""
    err = np.asarray(angular_error(normals, reference))
    sel = np.ones(err.shape, bool) if mask is None else np.asarray(mask, bool)
    if not sel.any():
        raise ValueError("mask is empty: no pixel to evaluate")
    e = err[sel].astype(np.float64)
    return {
        "median_deg": float(np.median(e)),
        "mean_deg": float(np.mean(e)),
        "rms_deg": float(np.sqrt(np.mean(e**2))),
        "p95_deg": float(np.percentile(e, 95)),
        "pixels": int(e.size),
    }
