"""Error measures between a reconstruction and a reference: normals (angles) and heights."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ..core._elementwise import atan2_nonneg
from ..core._safe import safe_sqrt

__all__ = [
    "angular_error",
    "angular_stats",
    "fit_scale_offset",
    "height_error_map",
    "height_stats",
    "made",
]


def angular_error(
    normals_a: Float[ArrayLike, "H W 3"],
    normals_b: Float[ArrayLike, "H W 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
) -> Float[Array, "H W"]:
    """Per-pixel angle in degrees between two normal maps (0 outside `mask`).

    Vectors are normalised first; the angle comes from `arctan2(|a x b|, a . b)`, which stays
    accurate near 0 degrees where `arccos` of a float32 dot product does not. A zero vector
    in either map (no normal, as a background pixel often holds) gives 0, not NaN: pass
    `mask` to leave such pixels out of a mean.
    """
    a = jnp.asarray(normals_a)
    b = jnp.asarray(normals_b, a.dtype)
    if a.shape != b.shape or a.ndim != 3 or a.shape[-1] != 3:
        raise ValueError(
            f"normals_a and normals_b must both be (H, W, 3), got {a.shape} and {b.shape}"
        )
    if mask is not None and np.shape(mask) != a.shape[:2]:
        raise ValueError(f"mask must have shape {a.shape[:2]}, got {np.shape(mask)}")
    err = _angular_error(a, b)
    if mask is not None:
        err = jnp.where(jnp.asarray(mask, bool), err, 0)
    return err


@jax.jit
def _angular_error(a, b):
    # Written so that its gradient is finite everywhere: equal normals (|a x b| = 0, a kink)
    # and zero normals (a background pixel) give a zero gradient rather than NaN.
    # On the component planes, not the length-3 axis (cross products, dot products and sums
    # over that axis each cost XLA-CPU a pass over the image), and the polynomial arctangent:
    # one fused loop (`benchmarks/bench_evaluate.py`).
    a = _unit_planes(a)
    b = _unit_planes(b)
    cross = safe_sqrt((a[1] * b[2] - a[2] * b[1]) ** 2 + (a[2] * b[0] - a[0] * b[2]) ** 2
                      + (a[0] * b[1] - a[1] * b[0]) ** 2)
    dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    both_zero = (cross == 0) & (dot == 0)
    return jnp.degrees(atan2_nonneg(cross, jnp.where(both_zero, 1, dot)))


def _unit_planes(v):
    """The three component planes of `(..., 3)` vectors divided by their length (kept when it is
    below 1e-12), each a product with one reciprocal."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    inv = 1 / jnp.maximum(safe_sqrt(x * x + y * y + z * z), 1e-12)
    return x * inv, y * inv, z * inv


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


def _height_pair(height, reference, mask):
    z = np.asarray(height, np.float64)
    ref = np.asarray(reference, np.float64)
    if z.ndim != 2:
        raise ValueError(f"height must be (H, W), got shape {z.shape}")
    if ref.shape != z.shape:
        raise ValueError(f"reference must have the shape of height {z.shape}, got {ref.shape}")
    sel = np.ones(z.shape, bool) if mask is None else np.asarray(mask, bool)
    if sel.shape != z.shape:
        raise ValueError(f"mask must have shape {z.shape}, got {sel.shape}")
    sel = sel & np.isfinite(z) & np.isfinite(ref)
    if sel.sum() < 2:
        raise ValueError("mask has fewer than 2 pixels with finite height and reference")
    return z, ref, sel


def fit_scale_offset(
    height: Float[ArrayLike, "H W"],
    reference: Float[ArrayLike, "H W"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
) -> tuple[float, float]:
    """Least-squares `(s, t)` minimising $\\sum (s z + t - z_{ref})^2$ over `mask`.

    Pixels where either map is not finite are left out. A constant `height` gets `s = 0`.

    **Arguments:**
    - `height`, `reference`: `(H, W)` maps (any units; a negative `s` means opposite axes,
      e.g. a height toward the viewer against a depth away from it).
    - `mask`: `(H, W)` bool (default: all pixels).

    **Returns:** `(s, t)` as floats.
    """
    z, ref, sel = _height_pair(height, reference, mask)
    a = np.stack([z[sel], np.ones(int(sel.sum()))], axis=1)
    (s, t), *_ = np.linalg.lstsq(a, ref[sel], rcond=None)
    return float(s), float(t)


def height_error_map(
    height: Float[ArrayLike, "H W"],
    reference: Float[ArrayLike, "H W"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    align: str = "scale_offset",
) -> np.ndarray:
    """Per-pixel signed error $s z + t - z_{ref}$ after alignment, NaN outside `mask`.

    **Arguments:**
    - `height`, `reference`: `(H, W)` maps.
    - `mask`: `(H, W)` bool (default: all pixels).
    - `align`: `"scale_offset"` (least-squares $s$, $t$: `fit_scale_offset`), `"offset"` ($s = 1$,
      $t$ the mean difference) or `"none"`.

    **Returns:** `(H, W)` float64 error in the reference's unit.
    """
    z, ref, sel = _height_pair(height, reference, mask)
    if align == "scale_offset":
        s, t = fit_scale_offset(z, ref, mask=sel)
    elif align == "offset":
        s, t = 1.0, float(np.mean(ref[sel] - z[sel]))
    elif align == "none":
        s, t = 1.0, 0.0
    else:
        raise ValueError(f"align must be 'scale_offset', 'offset' or 'none', got {align!r}")
    err = np.full(z.shape, np.nan)
    err[sel] = s * z[sel] + t - ref[sel]
    return err


def height_stats(
    height: Float[ArrayLike, "H W"],
    reference: Float[ArrayLike, "H W"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    align: str = "scale_offset",
) -> dict[str, float]:
    """Height error after alignment: MADE (mean absolute), RMS, median and 95th percentile.

    MADE as reported for DiLiGenT by Cao et al. (ECCV 2022): mean $|s z + t - z_{ref}|$ over
    the mask after a least-squares fit of scale $s$ and offset $t$ (`align="scale_offset"`);
    the alignment changes the figure, so it is returned with it.

    **Arguments:** as `height_error_map`.

    **Returns:** dict with `made`, `rms`, `median`, `p95` (reference units), `scale`,
    `offset` (the alignment used) and `pixels`.
    """
    z, ref, sel = _height_pair(height, reference, mask)
    err = height_error_map(z, ref, mask=sel, align=align)
    e = np.abs(err[sel])
    if align == "scale_offset":
        s, t = fit_scale_offset(z, ref, mask=sel)
    else:
        s, t = 1.0, float(np.mean(err[sel] - z[sel] + ref[sel])) if align == "offset" else 0.0
    return {
        "made": float(np.mean(e)),
        "rms": float(np.sqrt(np.mean(e**2))),
        "median": float(np.median(e)),
        "p95": float(np.percentile(e, 95)),
        "scale": s,
        "offset": t,
        "pixels": int(sel.sum()),
    }


def made(
    height: Float[ArrayLike, "H W"],
    reference: Float[ArrayLike, "H W"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
) -> float:
    """Mean absolute depth error after a least-squares scale+offset fit (see `height_stats`)."""
    return height_stats(height, reference, mask=mask)["made"]
