"""Error measures between a reconstruction and a reference (``jaxps.evaluate``)."""

from __future__ import annotations

import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from ._render import angular_error

__all__ = ["angular_error", "angular_stats"]


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
