"""A capture: `load_capture` runs the adapter's steps in order on one capture's files.

Frames, lights, ambient subtraction, quality screening, mask, face crop, equalisation; each step
is a function of its own in this package, and the result is a `Capture` of numpy arrays that the
jitted core takes as they are.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from ..lights._directions import lights_from_angles, load_lights, parse_yale_name, validate_lights
from ._face import crop, detect_face
from ._files import PathLike, list_frames, load_stack, read_image, read_mask
from ._quality import screen_capture
from ._stack import equalize_mean, mask_from_intensity, subtract_ambient

__all__ = ["Capture", "load_capture"]


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
