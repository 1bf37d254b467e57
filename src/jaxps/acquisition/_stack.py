"""Per-capture corrections of a loaded `(K, H, W[, C])` stack: ambient, equalisation, mask."""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool, Float

__all__ = ["equalize_mean", "mask_from_intensity", "subtract_ambient"]


def subtract_ambient(
    images: Float[np.ndarray, "K H W *C"], ambient: Float[np.ndarray, "H W *C"]
) -> Float[np.ndarray, "K H W *C"]:
    """Subtract the ambient-only control frame from every frame and clip at 0."""
    images, ambient = np.asarray(images), np.asarray(ambient, dtype=images.dtype)
    if ambient.shape != images.shape[1:]:
        raise ValueError(
            f"ambient frame has shape {ambient.shape}, frames have {images.shape[1:]}"
        )
    return _subtract_ambient(images, ambient, np.empty_like(images))


def _subtract_ambient(images, ambient, out):
    """`subtract_ambient` without its checks, written into `out` (which may be `images`:
    `load_capture` subtracts in place from the stack it owns)."""
    np.subtract(images, ambient, out=out)
    return np.maximum(out, 0, out=out)


def equalize_mean(
    images: Float[np.ndarray, "K H W *C"], *, mask: Bool[np.ndarray, "H W"] | None = None
) -> tuple[Float[np.ndarray, "K H W *C"], Float[np.ndarray, " K"]]:
    """Scale each frame so its mean over `mask` equals the mean over all frames.

    The four-source scanner's correction for flash-to-flash intensity differences (a crude
    stand-in for estimating per-frame light intensities). Returns the scaled stack and the `(K,)`
    gains applied. **Raises:** `ValueError` if a frame has zero mean over the mask.
    """
    images = np.asarray(images)
    sel = np.ones(images.shape[1:3], bool) if mask is None else np.asarray(mask, bool)
    if sel.shape != images.shape[1:3]:
        raise ValueError(f"mask has shape {sel.shape}, frames have {images.shape[1:3]}")
    means = np.array([f[sel].mean() for f in images], dtype=np.float64)
    if np.any(means <= 0):
        raise ValueError(f"frames {np.flatnonzero(means <= 0).tolist()} have zero mean: "
                         "cannot equalise a dark frame")
    gains = (means.mean() / means).astype(np.float32)
    shape = (-1,) + (1,) * (images.ndim - 1)
    return (images * gains.reshape(shape)).astype(images.dtype), gains


def _lit_level(mean) -> float:
    """`mask_from_intensity`'s default level: 5% of the mean image's 99th percentile."""
    return 0.05 * float(np.percentile(mean, 99))


def mask_from_intensity(
    images: Float[np.ndarray, "K H W *C"], *, threshold: float | str | None = None
) -> Bool[np.ndarray, "H W"]:
    """A foreground mask from the mean image over frames.

    Default threshold: 5% of the mean image's 99th percentile, which keeps dark-albedo regions
    of a face (brows, eyes, beard) that Otsu's threshold (`threshold="otsu"`) cuts away; a
    number is used as an absolute threshold. Specks are removed, holes filled, and only the
    largest connected region is kept.
    """
    from scipy import ndimage

    if isinstance(threshold, str) and threshold != "otsu":
        raise ValueError(f"threshold must be a number, 'otsu' or None, got {threshold!r}")
    if threshold is not None and not isinstance(threshold, str) and not np.isfinite(threshold):
        raise ValueError(f"threshold must be finite, got {threshold}")
    mean = np.asarray(images, dtype=np.float32).mean(axis=0)
    if mean.ndim == 3:
        mean = mean.mean(axis=-1)
    if np.ptp(mean) == 0:
        raise ValueError("images are constant: cannot derive a mask from intensity")
    if threshold is None:
        threshold = _lit_level(mean)
    elif threshold == "otsu":
        from skimage import filters

        threshold = float(filters.threshold_otsu(mean))
    mask = ndimage.binary_opening(mean > float(threshold), iterations=1)
    labels, count = ndimage.label(mask)
    if count == 0:
        raise ValueError(f"no pixel of the mean image is above the mask threshold {threshold}")
    largest = np.argmax(np.bincount(labels.ravel())[1:]) + 1
    return ndimage.binary_fill_holes(labels == largest)
