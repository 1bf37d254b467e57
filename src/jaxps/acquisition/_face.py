"""Face detection (OpenCV's Lienhart–Maydt Haar cascade) and cropping to the face's box."""

from __future__ import annotations

import os

import numpy as np
from jaxtyping import Float

__all__ = ["bucket_box", "crop", "detect_face"]


def detect_face(
    image: Float[np.ndarray, "H W *C"], *, pad: float = 0.3, min_size: int = 40
) -> tuple[int, int, int, int] | None:
    """Find the largest frontal face with OpenCV's Lienhart–Maydt Haar cascade.

    Lienhart & Maydt, "An extended set of Haar-like features for rapid object detection",
    ICIP 2002 (`haarcascade_frontalface_alt2.xml`, shipped with opencv 4.x). The image is padded
    by `pad` times its size on every side first: on tightly cropped faces the cascade otherwise
    misses the face or fires on a cheek.

    **Returns:** `(top, left, height, width)` in `image`'s pixels, clipped to the image, or None.
    """
    img = np.asarray(image, dtype=np.float32)
    if img.ndim not in (2, 3) or img.size == 0:
        raise ValueError(f"image must be a non-empty (H, W) or (H, W, C) array, got shape "
                         f"{img.shape}")
    if not (np.isfinite(pad) and pad >= 0):
        raise ValueError(f"pad must be finite and >= 0 (a fraction of the image's size), "
                         f"got {pad}")
    if not (isinstance(min_size, (int, np.integer)) and min_size >= 1):
        raise ValueError(f"min_size must be a positive int (pixels), got {min_size!r}")
    import cv2

    if img.ndim == 3:
        img = img.mean(axis=-1)
    img = np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0)  # a dead pixel is no face
    # Cascades were trained on gamma-encoded 8-bit images: stretch to the 99th percentile.
    top = float(np.percentile(img, 99)) or 1.0
    grey8 = (np.clip(img / top, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    h, w = grey8.shape
    ph, pw = int(pad * h), int(pad * w)
    padded = cv2.copyMakeBorder(grey8, ph, ph, pw, pw, cv2.BORDER_CONSTANT, value=0)
    path = os.path.join(cv2.data.haarcascades, "haarcascade_frontalface_alt2.xml")
    cascade = cv2.CascadeClassifier(path)
    if cascade.empty():
        raise RuntimeError(f"OpenCV Haar cascade missing at {path} (opencv 5.x ships none)")
    faces = cascade.detectMultiScale(padded, scaleFactor=1.05, minNeighbors=4,
                                     minSize=(min_size, min_size))
    if len(faces) == 0:
        return None
    x, y, fw, fh = max(faces, key=lambda f: f[2] * f[3])
    t, l = max(int(y) - ph, 0), max(int(x) - pw, 0)
    b, r = min(int(y + fh) - ph, h), min(int(x + fw) - pw, w)
    return t, l, b - t, r - l


def crop(array: np.ndarray, box: tuple[int, int, int, int], *, axis: int = 0) -> np.ndarray:
    """Crop the two image axes starting at `axis` (0 for `(H, W, ...)`, 1 for `(K, H, W, ...)`).

    `box` is `(top, left, height, width)` (as `detect_face` and `bucket_box` return it) and
    must lie inside the image: a box that runs over an edge raises rather than return a
    smaller crop than asked for.
    """
    t, l, h, w = (int(v) for v in box)
    full = np.shape(array)[axis:axis + 2]
    if len(full) != 2:
        raise ValueError(f"array must have two image axes from axis={axis}, got shape "
                         f"{np.shape(array)}")
    if not (h >= 1 and w >= 1 and 0 <= t and t + h <= full[0] and 0 <= l and l + w <= full[1]):
        raise ValueError(f"box (top, left, height, width) = {tuple(box)} does not lie inside "
                         f"the image's {full[0]} x {full[1]} pixels")
    index = (slice(None),) * axis + (slice(t, t + h), slice(l, l + w))
    return array[index]


def bucket_box(
    box: tuple[int, int, int, int], shape: tuple[int, int], *, multiple: int = 64
) -> tuple[int, int, int, int]:
    """Grow `box` = (top, left, height, width) about its centre to sides that are multiples of
    `multiple` pixels, kept inside an image of `shape` = (H, W) (shifted inward at an edge; a
    side longer than the image becomes the whole image).

    Every new image size costs a compile of each jitted stage (about a second per size on a
    CPU); face boxes differ from capture to capture by a few pixels, so rounding them up lets
    the captures of a session share compiled programs. The extra margin is real image, not
    padding: results inside the original box do not change. `multiple=1` returns `box`.
    """
    if not (isinstance(multiple, int) and multiple >= 1):
        raise ValueError(f"multiple must be a positive int, got {multiple!r}")
    out = []
    for start, size, full in ((box[0], box[2], shape[0]), (box[1], box[3], shape[1])):
        grown = min(-(-size // multiple) * multiple, full)
        first = min(max(start - (grown - size) // 2, 0), full - grown)
        out.append((first, grown))
    (t, h), (l, w) = out
    return t, l, h, w
