"""Motion between the frames of a capture: measure it, and register the frames when it is small.

A walk-through scanner fires its lights a few milliseconds apart; a subject who moves between
frames smears every normal. `estimate_shifts` measures each frame's translation against a
reference frame by phase correlation (Kuglin & Hines 1975) on the face region, refined to
sub-pixel accuracy by the upsampled-DFT search of Guizar-Sicairos, Thurman & Fienup, "Efficient
subpixel image registration algorithms", Opt. Lett. 33(2), 2008 (scikit-image's
`phase_cross_correlation`), with phase normalisation (whitened spectra), which keeps the
albedo detail and discards most of the low-frequency shading that differs between lights. Shifts
are applied by cubic-spline interpolation.

Tried and dropped: correlating each frame with a rendering of the current Lambertian fit under its
own light (to remove the shading difference) made synthetic shifts worse (0.02 px -> 0.1 px)."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

__all__ = ["Registration", "estimate_shifts", "register_frames", "shift_frames"]


class Registration(NamedTuple):
    """Result of `register_frames`.

    - `frames`: `(K, H, W[, C])` frames moved onto the reference (unchanged if not registered).
    - `shifts`: `(K, 2)` measured (dy, dx) in pixels of each frame relative to the reference
      (a frame content moved down/right has positive dy/dx); the reference row is 0.
    - `registered`: whether the frames were moved (all shifts within `max_shift`).
    """

    frames: Float[Array, "K H W *C"]
    shifts: np.ndarray
    registered: bool


def shift_frames(
    frames: Float[ArrayLike, "K H W *C"], shifts: Float[ArrayLike, "K 2"]
) -> Float[Array, "K H W *C"]:
    """Move each frame by `(dy, dx)` pixels: cubic-spline interpolation, edges repeated.

    **Returns:** frames of the same shape and dtype.
    """
    arr = np.asarray(frames)
    shifts = np.asarray(shifts, np.float64)
    if arr.ndim not in (3, 4) or shifts.shape != (arr.shape[0], 2):
        raise ValueError(f"frames (K, H, W[, C]) and shifts (K, 2) expected, got {arr.shape} "
                         f"and {shifts.shape}")
    if not np.all(np.isfinite(shifts)):
        raise ValueError("shifts must be finite")
    from scipy import ndimage  # SciPy and scikit-image load when first used

    out = np.empty_like(arr)
    for i, s in enumerate(shifts):
        full = (s[0], s[1]) + (0.0,) * (arr.ndim - 3)
        out[i] = ndimage.shift(arr[i], full, order=3, mode="nearest")
    return jnp.asarray(out)


def _window(h, w):
    return np.outer(np.hanning(h), np.hanning(w))


def _prepare(img, box, win):
    y0, y1, x0, x1 = box
    crop = img[y0:y1, x0:x1].astype(np.float64)
    crop = crop - crop[win > 0].mean()
    return crop * win


def _box(mask, pad):
    ys, xs = np.nonzero(mask)
    h, w = mask.shape
    return (max(ys.min() - pad, 0), min(ys.max() + pad + 1, h),
            max(xs.min() - pad, 0), min(xs.max() + pad + 1, w))


def estimate_shifts(
    frames: Float[ArrayLike, "K H W *C"],
    *,
    reference: int | Float[ArrayLike, "K H W"] = 0,
    mask: Bool[ArrayLike, "H W"] | None = None,
    upsample: int = 100,
    normalization: str | None = "phase",
) -> np.ndarray:
    """Translation of each frame against a reference by windowed sub-pixel phase correlation.

    **Arguments:**
    - `frames`: `(K, H, W)` or `(K, H, W, C)` (the channel mean is used).
    - `reference`: index of the reference frame, or `(K, H, W)` per-frame reference images
      (e.g. renderings under each frame's own light).
    - `mask`: `(H, W)` region to correlate (the face); its bounding box plus a margin is
      windowed with a Hann window. Default: the whole frame.
    - `upsample`: sub-pixel resolution is 1/`upsample` pixel.

    **Returns:** `(K, 2)` float64 (dy, dx): frame k's content sits at reference position plus
    (dy, dx).
    """
    grey = np.asarray(frames, np.float64)
    if grey.ndim == 4:
        grey = grey.mean(axis=-1)
    if grey.ndim != 3:
        raise ValueError(f"frames must be (K, H, W[, C]), got {np.shape(frames)}")
    k, h, w = grey.shape
    sel = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    if sel.shape != (h, w) or not sel.any():
        raise ValueError(f"mask must be a non-empty (H, W) = {(h, w)} array")
    box = _box(sel, pad=4)
    win = _window(box[1] - box[0], box[3] - box[2])
    if isinstance(reference, (int, np.integer)):
        if not 0 <= reference < k:
            raise ValueError(f"reference must index a frame in [0, {k}), got {reference}")
        refs = np.broadcast_to(grey[reference], grey.shape)
    else:
        refs = np.asarray(reference, np.float64)
        if refs.shape != grey.shape:
            raise ValueError(f"reference images must have shape {grey.shape}, got {refs.shape}")
    from skimage.registration import phase_cross_correlation

    shifts = np.zeros((k, 2))
    for i in range(k):
        a = _prepare(refs[i], box, win)
        b = _prepare(grey[i], box, win)
        if not (np.any(a) and np.any(b)):
            continue
        shift, _, _ = phase_cross_correlation(a, b, upsample_factor=upsample,
                                              normalization=normalization)
        shifts[i] = -shift  # skimage returns the shift that registers b onto a
    return shifts


def register_frames(
    frames: Float[ArrayLike, "K H W *C"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    reference: int = 0,
    max_shift: float = 4.0,
    upsample: int = 100,
) -> Registration:
    """Measure inter-frame motion and, when every shift is within `max_shift` pixels, undo it.

    **Arguments:**
    - `frames`: `(K, H, W)` or `(K, H, W, C)` floating point.
    - `mask`: `(H, W)` face region (default: whole frame).
    - `reference`: the frame that stays put.
    - `max_shift`: larger motion is reported but not corrected (`registered=False`): a subject
      who moved that far has probably also turned, which a translation cannot undo.
    - `upsample`: sub-pixel resolution 1/`upsample`.

    **Returns:** a `Registration`.
    """
    frames = jnp.asarray(frames)
    if not jnp.issubdtype(frames.dtype, jnp.floating):
        raise ValueError(f"frames must be floating point, got {frames.dtype}")
    if not (np.isfinite(max_shift) and max_shift >= 0):
        raise ValueError(f"max_shift must be finite and >= 0, got {max_shift!r}")
    shifts = estimate_shifts(frames, reference=reference, mask=mask, upsample=upsample)
    ok = bool(np.max(np.abs(shifts)) <= max_shift)
    out = shift_frames(frames, -shifts) if ok else frames
    return Registration(out, shifts, ok)
