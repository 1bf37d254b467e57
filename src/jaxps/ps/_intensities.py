"""Per-frame light intensities of a capture, by one of several estimates.

A flash fires a little brighter or dimmer each time; dividing frame $k$ by its intensity $e_k$
equalises a stack. `"mean"` is the face scanners' equalisation, `"semi_calibrated"` the joint
fit of `ps_semi_calibrated` (Cho et al., TPAMI 2018), and:

**Frontal estimate** (`intensity_estimate(..., method="frontal")`): with no shadows, the mean of
frame $k$ over the face is $\\bar i_k = e_k\\, l_k \\cdot \\bar b$; taking the mean face normal
$\\bar b$ along the view axis (a face looking at the camera) gives
$e_k \\propto \\bar i_k / l_{k,z}$.
This is the face scanners' mean-intensity equalisation corrected for each light's obliquity.

**A reference target** (`method="frontal", mask=target, normal=d`): a matte, flat target of
known normal $d$ in view (on the scanner, not on the subject). Over it
$\\bar i_k = e_k \\rho\\, l_k \\cdot d$ holds exactly for a Lambertian surface and distant
lights, so $e_k \\propto \\bar i_k / l_k \\cdot d$ needs no assumption about the face's pose,
which five near-frontal frames cannot tell from the flash strengths (docs/captures.md, "A
reference target in view").
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ..core._host import to_device
from ..lights._directions import validate_lights
from ._photometric_stereo import photometric_stereo

__all__ = ["INTENSITY_METHODS", "intensity_estimate"]

INTENSITY_METHODS = ("none", "mean", "frontal", "semi_calibrated")


def intensity_estimate(
    images: Float[ArrayLike, "K H W *C"],
    lights: Float[ArrayLike, "K 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    method: str = "semi_calibrated",
    normal: Float[ArrayLike, "3"] | None = None,
    **options,
) -> Float[Array, " K"]:
    """Per-frame light intensities, geometric mean 1, by one of `INTENSITY_METHODS`.

    - `"none"`: all ones.
    - `"mean"`: the face scanners' equalisation, $e_k \\propto$ mean of frame $k$ over `mask`.
    - `"frontal"`: mean equalisation divided by each light's $l \\cdot d$, $d$ the mean normal
      over `mask`: `normal`, or the view axis (a face looking at the camera; see the module
      docstring).
    - `"semi_calibrated"`: the joint least-squares fit of `ps_semi_calibrated` (options passed on).

    Divide frame $k$ by $e_k$ to equalise a stack.

    **Arguments:**
    - `images`: `(K, H, W)` or `(K, H, W, C)` floating point in [0, 1].
    - `lights`: `(K, 3)` light directions.
    - `mask`: `(H, W)` bool region to use (default: all pixels). `"mean"` and `"frontal"`
      average the pixels in it that are finite in every frame.
    - `normal`: `(3,)` the mean normal of the region in `mask`, for `"frontal"` (default
      `(0, 0, 1)`, the view axis). With `mask` on a flat matte target of known orientation,
      the intensities are exact for a Lambertian target.

    **Returns:** `(K,)` intensities in the dtype of `images`.

    **Raises:** `ValueError` for an unknown method, a wrong shape or dtype, an empty mask, a
    bad light set (`validate_lights`), a light with $l \\cdot d \\le 0$ for `"frontal"`, or a
    frame whose mean over the mask is not positive; for a `normal` with another method than
    `"frontal"`, not a finite, non-zero `(3,)` vector, or facing away from a light.
    """
    if method not in INTENSITY_METHODS:
        raise ValueError(f"method must be one of {INTENSITY_METHODS}, got {method!r}")
    if normal is not None:
        if method != "frontal":
            raise ValueError(f"normal is the mean normal of the 'frontal' estimate; "
                             f"method={method!r} takes none")
        normal = np.asarray(normal, np.float64)
        if normal.shape != (3,) or not np.all(np.isfinite(normal)) or not normal.any():
            raise ValueError(f"normal must be a finite, non-zero (3,) vector, got {normal!r}")
        normal = normal / np.linalg.norm(normal)
    # Host-side (numpy) for "mean"/"frontal": a few sums, and no small jitted ops to trace and
    # compile in a fresh process (the command line pays for each).
    if not hasattr(images, "dtype"):
        images = np.asarray(images)
    shape, dtype = np.shape(images), np.dtype(images.dtype)
    if len(shape) not in (3, 4) or not np.issubdtype(dtype, np.floating):
        raise ValueError(f"images must be floating (K, H, W[, C]), got {shape} {dtype}")
    k = shape[0]
    if method == "none":
        return to_device(np.ones(k, dtype))
    if mask is not None:
        if np.shape(mask) != shape[1:3]:
            raise ValueError(f"mask must have shape {shape[1:3]}, got {np.shape(mask)}")
        if not np.any(mask):
            raise ValueError("mask is empty")
    if method == "semi_calibrated":
        res = photometric_stereo(images, lights, mask=mask, method="semi_calibrated",
                                 **options)
        return res.info["intensities"].astype(dtype)
    lights = np.asarray(lights, np.float64)
    if lights.shape != (k, 3):
        raise ValueError(f"lights must be ({k}, 3), got {lights.shape}")
    validate_lights(lights)  # finite, non-zero, spanning 3-D
    lights = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    facing = lights @ (np.array([0.0, 0.0, 1.0]) if normal is None else normal)
    if method == "frontal" and normal is not None and np.any(facing <= 0):
        bad = np.flatnonzero(facing <= 0)
        raise ValueError(f"normal {normal.round(4).tolist()} faces away from light(s) "
                         f"{bad.tolist()} (l . normal <= 0): they do not light the region")
    if method == "frontal" and normal is None and np.any(lights[:, 2] <= 0):
        bad = np.flatnonzero(lights[:, 2] <= 0)
        raise ValueError(
            f"lights: the frontal estimate divides by each light's l_z, which must be > 0 "
            f"(toward the viewer); light(s) {bad.tolist()} have l_z = "
            f"{np.round(lights[bad, 2], 4).tolist()} (a flipped sign convention? For lights "
            "behind the face plane take the \"mean\" estimate)")
    grey = np.asarray(images)
    if grey.ndim == 4:
        grey = grey.mean(axis=-1)
    sel = np.ones(grey.shape[1:], bool) if mask is None else np.asarray(mask, bool)
    means = grey[:, sel].mean(axis=1, dtype=np.float64)
    if not np.all(np.isfinite(means)):  # NaN or Inf pixels: the pixels finite in every frame
        values = grey[:, sel]
        values = values[:, np.isfinite(values).all(axis=0)]
        if values.shape[1] == 0:
            raise ValueError("images: no pixel in the mask is finite in every frame")
        means = values.mean(axis=1, dtype=np.float64)
    if np.any(~np.isfinite(means)) or np.any(means <= 0):
        raise ValueError(f"images: frame means over the mask must be positive, got {means}")
    if method == "frontal":
        means = means / np.maximum(facing, 1e-3)
    e = means / np.exp(np.mean(np.log(means)))
    return to_device(e.astype(dtype))
