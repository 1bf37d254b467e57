"""Acquisition adapter (eager, numpy): frame stacks from files to linear float32 images.

Reads PGM/PNG/TIFF frames (8- or 16-bit, grey or colour), subtracts the ambient-only control
frame, equalises mean intensity across frames (as the four-source scanner does), detects and crops
the face with OpenCV's Lienhart–Maydt Haar cascade, and builds a mask. Nothing here is jitted: it
runs once per capture and hands numpy arrays to the jitted core.

Intensities follow DESIGN.md: float32 in [0, 1] (8-bit / 255, 16-bit / 65535), linear in
radiance; gamma-encoded sources (8-bit PNG/JPEG by default) are decoded from sRGB with
colour-science.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from typing import NamedTuple

import cv2
import numpy as np
from jaxtyping import Bool, Float

from ._lights import lights_from_angles, load_lights, parse_yale_name, validate_lights

__all__ = [
    "Capture",
    "FRAME_EXTENSIONS",
    "crop",
    "detect_face",
    "equalize_mean",
    "list_frames",
    "load_capture",
    "load_stack",
    "mask_from_intensity",
    "read_image",
    "read_mask",
    "subtract_ambient",
]

FRAME_EXTENSIONS = (".pgm", ".ppm", ".png", ".tif", ".tiff")
_SRGB_EXTENSIONS = (".png", ".jpg", ".jpeg")
# Files in a frame folder whose names contain these words are not frames.
_NOT_FRAMES = re.compile(r"mask|ambient", re.IGNORECASE)

PathLike = str | os.PathLike


class Capture(NamedTuple):
    """A loaded capture, ready for `photometric_stereo`.

    - `images`: `(K, H, W)` or `(K, H, W, C)` float32, linear, ambient subtracted, in [0, 1].
    - `lights`: `(K, 3)` float32 unit lights, or None when none were given.
    - `mask`: `(H, W)` bool.
    - `saturated`: `(K, H, W)` bool, samples at the top code value in the raw frame (before the
      ambient subtraction hid it); pass `sample_mask=~saturated` to the solver.
    - `names`: the frame file names, in order.
    - `crop`: `(top, left, height, width)` of the face crop in the original frame, or None.
    - `gains`: `(K,)` factors applied by mean equalisation (ones when not equalised).
    - `dropped`: the names of the frames `check_quality=True` dropped, in order (else empty).
    """

    images: np.ndarray
    lights: np.ndarray | None
    mask: np.ndarray
    saturated: np.ndarray
    names: tuple[str, ...]
    crop: tuple[int, int, int, int] | None
    gains: np.ndarray
    dropped: tuple[str, ...] = ()


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_frames(folder: PathLike) -> list[str]:
    """Frame files in `folder` (PGM/PPM/PNG/TIFF), in natural order (``x.2`` before ``x.10``).

    Files whose names contain "mask" or "ambient" are skipped: pass those explicitly.

    **Raises:** `FileNotFoundError` if `folder` does not exist or holds no frame file.
    """
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"frame folder not found: {folder}")
    names = [
        n for n in os.listdir(folder)
        if n.lower().endswith(FRAME_EXTENSIONS) and not _NOT_FRAMES.search(n)
    ]
    if not names:
        raise FileNotFoundError(
            f"no frame files ({', '.join(FRAME_EXTENSIONS)}) in folder {folder}"
        )
    return [os.path.join(folder, n) for n in sorted(names, key=_natural_key)]


def read_image(path: PathLike, *, linearize: str = "auto") -> Float[np.ndarray, "H W *C"]:
    """Read one frame as float32 in [0, 1]: `(H, W)` grey or `(H, W, 3)` RGB.

    Uses `cv2.imread(..., IMREAD_UNCHANGED)`, which keeps 16 bits (imageio and
    `skimage.io.imread` silently return 16-bit PNGs as 8-bit with Pillow 13). An alpha channel is
    dropped; colour comes back in RGB order.

    **Arguments:**
    - `path`: the file.
    - `linearize`: `"auto"` decodes 8-bit PNG/JPEG from sRGB and leaves PGM/TIFF and 16-bit
      files linear; `"srgb"` always decodes; `"none"` never does.

    **Raises:** `FileNotFoundError` if the file is missing, `ValueError` naming the file if it
    cannot be decoded or has an unsupported bit depth.
    """
    path = os.fspath(path)
    if linearize not in ("auto", "srgb", "none"):
        raise ValueError(f"linearize must be 'auto', 'srgb' or 'none', got {linearize!r}")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"frame not found: {path}")
    raw = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ValueError(f"cannot read image {path}: not a decodable PGM/PNG/TIFF file")
    if raw.ndim == 3:
        raw = raw[..., :3][..., ::-1] if raw.shape[-1] >= 3 else raw[..., 0]
    if raw.dtype == np.uint8:
        img = raw.astype(np.float32) / 255
    elif raw.dtype == np.uint16:
        img = raw.astype(np.float32) / 65535
    elif raw.dtype in (np.float32, np.float64):
        img = raw.astype(np.float32)
    else:
        raise ValueError(f"image {path} has unsupported pixel type {raw.dtype}")
    if not np.all(np.isfinite(img)):
        raise ValueError(f"image {path} contains NaN or Inf")
    decode = linearize == "srgb" or (
        linearize == "auto" and raw.dtype == np.uint8 and path.lower().endswith(_SRGB_EXTENSIONS)
    )
    if decode:
        import colour  # deferred: importing colour-science takes ~1 s

        img = np.asarray(colour.cctf_decoding(img, function="sRGB"), dtype=np.float32)
    return np.ascontiguousarray(img)


def load_stack(
    paths: Sequence[PathLike], *, linearize: str = "auto"
) -> tuple[Float[np.ndarray, "K H W *C"], Bool[np.ndarray, "K H W"]]:
    """Read frames into a `(K, H, W)` or `(K, H, W, C)` stack, with a saturation map.

    Returns the stack and a `(K, H, W)` bool array of samples at the top code value (any
    channel). **Raises:** `ValueError` naming the first file whose size or channels differ from
    the first frame's, or an empty list.
    """
    if len(paths) == 0:
        raise ValueError("no frames given")
    frames = []
    for p in paths:
        img = read_image(p, linearize=linearize)
        if frames and img.shape != frames[0].shape:
            raise ValueError(
                f"frame {os.fspath(p)} has shape {img.shape}, but {os.fspath(paths[0])} has "
                f"{frames[0].shape}: all frames must be the same size and channels"
            )
        frames.append(img)
    stack = np.stack(frames)
    saturated = stack >= 1.0
    if stack.ndim == 4:
        saturated = saturated.any(axis=-1)
    return stack, saturated


def subtract_ambient(
    images: Float[np.ndarray, "K H W *C"], ambient: Float[np.ndarray, "H W *C"]
) -> Float[np.ndarray, "K H W *C"]:
    """Subtract the ambient-only control frame from every frame and clip at 0."""
    images, ambient = np.asarray(images), np.asarray(ambient, dtype=images.dtype)
    if ambient.shape != images.shape[1:]:
        raise ValueError(
            f"ambient frame has shape {ambient.shape}, frames have {images.shape[1:]}"
        )
    return np.maximum(images - ambient[None], 0)


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
    if img.ndim == 3:
        img = img.mean(axis=-1)
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
    """Crop the two image axes starting at `axis` (0 for `(H, W, ...)`, 1 for `(K, H, W, ...)`)."""
    t, l, h, w = box
    index = (slice(None),) * axis + (slice(t, t + h), slice(l, l + w))
    return array[index]


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

    mean = np.asarray(images, dtype=np.float32).mean(axis=0)
    if mean.ndim == 3:
        mean = mean.mean(axis=-1)
    if np.ptp(mean) == 0:
        raise ValueError("images are constant: cannot derive a mask from intensity")
    if threshold is None:
        threshold = 0.05 * float(np.percentile(mean, 99))
    elif threshold == "otsu":
        from skimage import filters

        threshold = float(filters.threshold_otsu(mean))
    mask = ndimage.binary_opening(mean > float(threshold), iterations=1)
    labels, count = ndimage.label(mask)
    if count == 0:
        raise ValueError(f"no pixel of the mean image is above the mask threshold {threshold}")
    largest = np.argmax(np.bincount(labels.ravel())[1:]) + 1
    return ndimage.binary_fill_holes(labels == largest)


def read_mask(path: PathLike, shape: tuple[int, int] | None = None) -> Bool[np.ndarray, "H W"]:
    """Read a mask image (non-zero = inside). **Raises:** `ValueError` if `shape` differs."""
    img = read_image(path, linearize="none")
    mask = (img.max(axis=-1) if img.ndim == 3 else img) > 0
    if shape is not None and mask.shape != tuple(shape):
        raise ValueError(f"mask {os.fspath(path)} has shape {mask.shape}, frames have {shape}")
    return mask


def load_capture(
    frames: PathLike | Sequence[PathLike],
    *,
    lights: PathLike | np.ndarray | None = None,
    yale_names: bool = False,
    ambient: PathLike | None = None,
    mask: PathLike | np.ndarray | str | None = None,
    equalize: bool = False,
    crop_face: bool = False,
    linearize: str = "auto",
    check_quality: bool = False,
) -> Capture:
    """Load a capture: frames, lights, ambient subtraction, equalisation, face crop, mask.

    **Arguments:**
    - `frames`: a folder (see `list_frames`) or a list of frame files.
    - `lights`: a `lights.txt` path or a `(K, 3)` array; or `yale_names=True` to parse
      Yale-B-style names (`..._P00A+035E+15.pgm`).
    - `ambient`: the ambient-only control frame, subtracted from every frame and clipped at 0.
    - `mask`: a mask image path, a `(H, W)` bool array, `"auto"` (Otsu on the mean image), or
      None (every pixel).
    - `equalize`: scale frames to equal mean intensity over the mask (`equalize_mean`).
    - `crop_face`: crop to the face found by `detect_face` in the mean frame.
    - `linearize`: see `read_image`.
    - `check_quality`: run `jaxps.check_frames` on the ambient-subtracted frames and drop the
      flagged ones (logged on logger `"jaxps"`; `ValueError` if fewer than 3 remain).

    **Raises:** `FileNotFoundError`/`ValueError` naming the offending file or argument.
    """
    if isinstance(frames, (str, os.PathLike)):
        paths = list_frames(frames)
    else:
        paths = [os.fspath(p) for p in frames]
        if not paths:
            raise ValueError("frames: empty list of files")
    names = tuple(os.path.basename(p) for p in paths)
    images, saturated = load_stack(paths, linearize=linearize)

    if yale_names:
        if lights is not None:
            raise ValueError("give either lights or yale_names=True, not both")
        angles = [parse_yale_name(n) for n in names]
        missing = [n for n, a in zip(names, angles) if a is None]
        if missing:
            raise ValueError(f"cannot parse a Yale B light from frame name(s) {missing}")
        az, el = zip(*angles)
        light_array = lights_from_angles(az, el)
    elif lights is None:
        light_array = None
    elif isinstance(lights, (str, os.PathLike)):
        light_array = load_lights(lights)
    else:
        light_array = validate_lights(lights)
    if light_array is not None and len(light_array) != len(paths):
        raise ValueError(f"{len(paths)} frames but {len(light_array)} lights")

    if ambient is not None:
        amb = read_image(ambient, linearize=linearize)
        if amb.shape != images.shape[1:]:
            raise ValueError(
                f"ambient frame {os.fspath(ambient)} has shape {amb.shape}, frames have "
                f"{images.shape[1:]}"
            )
        images = subtract_ambient(images, amb)

    given = names
    if check_quality:
        from ._quality import screen_capture

        images, saturated, names, light_array, _ = screen_capture(
            images, saturated, names, light_array)

    if isinstance(mask, np.ndarray):
        if mask.shape != images.shape[1:3]:
            raise ValueError(f"mask has shape {mask.shape}, frames have {images.shape[1:3]}")
        mask_array = mask.astype(bool)
    elif mask is None or (isinstance(mask, str) and mask == "auto"):
        mask_array = None
    else:
        mask_array = read_mask(mask, images.shape[1:3])

    box = None
    if crop_face:
        box = detect_face(images.mean(axis=0))
        if box is None:
            raise ValueError(f"no face found in the mean of frames {names[0]}...{names[-1]}")
        images, saturated = crop(images, box, axis=1), crop(saturated, box, axis=1)
        if mask_array is not None:
            mask_array = crop(mask_array, box)

    if mask_array is None:
        mask_array = (mask_from_intensity(images) if mask == "auto"
                      else np.ones(images.shape[1:3], bool))
    gains = np.ones(len(images), np.float32)
    if equalize:
        images, gains = equalize_mean(images, mask=mask_array)
    return Capture(np.ascontiguousarray(images, dtype=np.float32), light_array, mask_array,
                   saturated, names, box, gains, tuple(n for n in given if n not in names))
