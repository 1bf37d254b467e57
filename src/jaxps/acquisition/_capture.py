"""A capture: `load_capture` runs the adapter's steps in order on one capture's files.

Frames, lights, ambient subtraction, quality screening, motion (measured and undone), mask,
face crop, per-frame light intensities (estimated and divided out, `"frontal"` by default); each
step is a function of its own in this package, and the result is a `Capture` of numpy arrays
that the jitted core takes as they are.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from jaxtyping import Bool, Float

from ..core._host import aligned, aligned_empty
from ..lights._check import LightCheck, check_lights
from ..lights._directions import lights_from_angles, load_lights, parse_yale_name, validate_lights
from ..ps._intensities import INTENSITY_METHODS, intensity_estimate
from ..ps._photometric_stereo import photometric_stereo
from ._face import bucket_box, crop, detect_face
from ._files import (
    FRAME_EXTENSIONS,
    PathLike,
    _decodes_srgb,
    _exists,
    _frame_paths,
    list_frames,
    load_stack,
    read_image,
    read_mask,
)
from ._quality import (
    QualityReport,
    _check_span,
    flag_inconsistent,
    lights_span,
    only_inconsistent,
    screen_capture,
)
from ._register import _box, _shift, estimate_shifts
from ._stack import _lit_level, _subtract_ambient, mask_from_intensity

__all__ = ["Capture", "load_capture", "target_ratios"]

# Motion that `load_capture(register=True)` undoes, in pixels. Below MIN_SHIFT the frames are left
# as read: on still scenes the estimate reads shading changes as motion, up to 0.12 px on the psm
# objects' 12 frames and 0.23 px on the rendered demo face at 1 MP, while the Yale B faces moved
# up to 1.7-3.5 px (0.9-2.0 px within the five scanner frames). Above MAX_SHIFT a translation is
# not a good enough model (the subject has probably turned as well). MAX_SHIFT was set on those
# frames, 168 px across; a larger window allows as much motion in proportion (`motion_limit`).
MIN_SHIFT, MAX_SHIFT, MAX_SHIFT_ACROSS = 0.5, 4.0, 168


def motion_limit(shape: tuple[int, int], mask: np.ndarray | None = None) -> float:
    """The largest shift, in pixels, that `load_capture` undoes: `MAX_SHIFT` per
    `MAX_SHIFT_ACROSS` pixels of the shorter side of the registration window (the mask's
    bounding box, else the frame), and never less than `MAX_SHIFT`. So a capture read at
    twice the size is registered alike."""
    side = min(shape)
    if mask is not None and mask.any():
        y0, y1, x0, x1 = _box(mask, pad=0)
        side = min(y1 - y0, x1 - x0)
    return MAX_SHIFT * max(1.0, side / MAX_SHIFT_ACROSS)


class Capture(NamedTuple):
    """A loaded capture, ready for `photometric_stereo`.

    - `images`: `(K, H, W)` or `(K, H, W, C)` float32, linear, ambient subtracted, in [0, 1].
    - `lights`: `(K, 3)` float32 unit lights, or None when none were given.
    - `mask`: `(H, W)` bool.
    - `saturated`: `(K, H, W)` bool, samples at the top code value in the raw frame (before the
      ambient subtraction hid it); pass `sample_mask=~saturated` to the solver.
    - `names`: the frame file names, in order.
    - `crop`: `(top, left, height, width)` of the face crop in the original frame, or None.
    - `gains`: `(K,)` factors each frame was multiplied by to equalise its light intensity
      (`1 / intensities`; ones with `intensities="none"`).
    - `dropped`: the names of the frames `check_quality=True` dropped, in order (else empty).
    - `intensities`: `(K,)` the per-frame light intensities estimated (geometric mean 1).
    - `intensity_method`: the estimate used (`"none"`, `"mean"`, `"frontal"`,
      `"semi_calibrated"`).
    - `shifts`: `(K, 2)` (dy, dx) pixels each frame had moved against the reference frame
      (`estimate_shifts`), or None when not measured (`register=False`).
    - `registered`: whether the frames were moved back onto the reference (see `load_capture`).
    - `intensity_fit`: for `intensity_method="semi_calibrated"`, the fit's report (host
      values): `converged`, `fallback` (the frontal start was used), `steps`, `objective`
      (start, used) and `visibility` (`jaxps.flash_visibility` of the lights); else None.
    - `frame_size`: `(height, width)` of the frames as read, before any crop (the frame that
      `crop` is a box of, and in which near lamps' positions are measured).
    - `light_check`: `jaxps.check_lights` of the frames, lights and mask as returned (is the
      lights file mirrored, in another order than the frames, or turned by 180 degrees?), or
      None without lights.
    - `frame_check`: the `jaxps.check_frames` report on the frames as given (every frame,
      the dropped ones with their reasons; the consistency as judged again after the motion
      step, when frames were moved), or None with `check_quality=False` or frames too small
      to check.
    """

    images: np.ndarray
    lights: np.ndarray | None
    mask: np.ndarray
    saturated: np.ndarray
    names: tuple[str, ...]
    crop: tuple[int, int, int, int] | None
    gains: np.ndarray
    dropped: tuple[str, ...] = ()
    intensities: np.ndarray | None = None
    intensity_method: str = "none"
    shifts: np.ndarray | None = None
    registered: bool = False
    intensity_fit: dict | None = None
    frame_size: tuple[int, int] | None = None
    light_check: LightCheck | None = None
    frame_check: QualityReport | None = None


def load_capture(
    frames: PathLike | Sequence[PathLike],
    *,
    lights: PathLike | np.ndarray | None = None,
    yale_names: bool = False,
    ambient: PathLike | None = None,
    mask: PathLike | np.ndarray | str | None = None,
    intensities: str = "frontal",
    crop_face: bool = False,
    crop_multiple: int = 64,
    linearize: str = "auto",
    bits: int | None = None,
    check_quality: bool = True,
    register: bool = True,
    intensity_mask: PathLike | np.ndarray | None = None,
    intensity_normal: Sequence[float] | None = None,
    intensity_ratios: PathLike | Sequence[float] | None = None,
) -> Capture:
    """Load a capture: frames, lights, ambient subtraction, face crop, mask, intensities.

    **Arguments:**
    - `frames`: a folder (see `list_frames`), a list of frame files, or one multi-page TIFF
      file; a multi-page TIFF stands for its pages (named `stack.tif[0]`, `stack.tif[1]`,
      ...), and one page is given as such a name (`ambient="stack.tif[5]"`).
    - `lights`: a `lights.txt` path or a `(K, 3)` array; `"auto"` (with a folder of frames):
      the one `.txt` file in the folder whose name contains "light", so that each capture of
      a batch (`jaxps reconstruct DIR1 DIR2 ... --lights auto`) takes its own calibration; or
      `yale_names=True` to parse Yale-B-style names (`..._P00A+035E+15.pgm`). Each points
      toward its lamp in the camera frame; a set with no light in front of the subject
      (every `l_z <= 0`, as a file of directions from the lamps would give) is refused.
    - `ambient`: the ambient-only control frame, subtracted from every frame and clipped at 0;
      `"auto"` (with a folder of frames): the one file in the folder whose name contains
      "ambient", so that each capture of a batch (`jaxps reconstruct DIR1 DIR2 ...
      --ambient auto`) subtracts its own. A folder's ambient frame is never used unasked:
      without `ambient`, a warning names it.
    - `mask`: a mask image path, a `(H, W)` bool array, `"auto"` (`mask_from_intensity`: the
      mean frame above 5% of its 99th percentile, the largest region), or None (every pixel).
    - `intensities`: how each frame's flash strength is estimated and divided out, one of
      `jaxps.INTENSITY_METHODS` (see `jaxps.intensity_estimate`, estimated over the mask):
      `"frontal"` (default: mean equalisation corrected for each light's obliquity; `"mean"`
      when there are no lights), `"mean"` (the face scanners' mean equalisation),
      `"semi_calibrated"` (the joint fit, K >= 4) or `"none"` (frames as read). On five-light
      Yale B faces against a semi-calibrated 29-light reference (`benchmarks/bench_faces.py`),
      `"none"` costs about 8 degrees of median normal error; see docs/captures.md.
    - `crop_face`: crop to the face found by `detect_face` in the mean frame, grown to sides
      that are multiples of `crop_multiple` pixels (`bucket_box`: captures then share compiled
      programs instead of compiling each stage again for every new box size; 1 keeps the
      detector's box).
    - `linearize`, `bits`: see `read_image` (`bits`: a camera's bit depth, for files that hold
      its codes unscaled, e.g. 12-bit codes in 16-bit PNGs; frames and ambient alike).
    - `check_quality`: run `jaxps.check_frames` on the ambient-subtracted frames (inside
      `mask` when one is given) and drop the flagged ones (logged on logger `"jaxps"`, named
      in `Capture.dropped`; `ValueError` if fewer than 3 remain). On by default: one
      interlace-combed frame of five costs yaleB02 4 degrees of median normal error
      (docs/captures.md); False keeps every frame. `ValueError` too, naming the dropped frames,
      when the frames left are lit from directions that cannot determine a normal (e.g.
      the three of a cross of five left once both side frames are dropped). With
      `register`, a frame flagged only as
      inconsistent with the others (which a frame that moved is) is kept until the motion
      is undone, and the frames' consistency is judged again then (`Capture.frame_check`
      holds the last verdict).
    - `register`: measure each frame's motion against the frame lit closest to the view axis
      (`jaxps.estimate_shifts` on the given mask's box, else the whole frame) and, when the
      largest shift is between `MIN_SHIFT` = 0.5 px and the limit, move the frames back
      (cubic spline) and leave a border as wide as that shift out of the mask. The limit
      (`motion_limit`) is `MAX_SHIFT` = 4 px per 168 px of the shorter side of the mask's box
      (else of the frame), at least 4 px: 4 px on the Yale B frames, 24.4 px on 1280x1024
      ones. With `check_quality`, frames measured further away (moved, or lit too
      differently to measure, as from 70 degrees off axis) are flagged ("moved N px"),
      logged and dropped and the others registered, as long as 3 frames are left whose
      lights span 3-D; otherwise, and with `check_quality=False`, larger motion is logged
      and every frame left as read. The Yale B faces moved up to 1.7-3.5 px between frames;
      registering their five scanner frames lowered the median normal error by 0.6-1.8 degrees
      on every subject (`benchmarks/bench_faces.py --register`; docs/captures.md, "Motion").
    - `intensity_mask`: a mask image path or `(H, W)` bool array (full frame) of a flat, matte
      reference target in view, fixed to the scanner: `intensities` ("frontal" or "mean") is
      estimated over it, on the frames as read (before motion is undone and the face
      cropped), instead of over `mask`, leaving out its pixels saturated in any frame. With
      `intensity_normal`, the target's normal in the camera frame (default: facing the
      camera), "frontal" needs no assumption about the subject's pose (docs/captures.md, "A
      reference target in view").
    - `intensity_ratios`: with `intensity_mask`, `(K,)` factors (or a text file of them, one
      per line, `#` comments) by which the flash at the subject's place exceeds the flash at
      the target, one per frame as given (before any is dropped): the target's estimates are
      multiplied by them. Near lights (a scanner's flashes at about a metre) light the target
      and the face from different distances, a fixed error per lamp; `target_ratios` measures
      it once from frames of a flat board at the subject's place (`jaxps calibrate --board`).

    **Raises:** `FileNotFoundError`/`ValueError` naming the offending file or argument.
    """
    if intensities not in INTENSITY_METHODS:  # before any file is read
        raise ValueError(f"intensities must be one of {INTENSITY_METHODS}, got {intensities!r}")
    if intensity_mask is not None and intensities not in ("frontal", "mean"):
        raise ValueError("intensity_mask: the intensities of a reference target are estimated "
                         f"by 'frontal' or 'mean', not intensities={intensities!r}")
    if intensity_normal is not None and (intensity_mask is None or intensities != "frontal"):
        raise ValueError("intensity_normal is the reference target's normal: it needs "
                         "intensity_mask and intensities='frontal'")
    if intensity_ratios is not None and intensity_mask is None:
        raise ValueError("intensity_ratios scale the flash strengths measured on a reference "
                         "target: they need intensity_mask")
    if isinstance(frames, (str, os.PathLike)) and os.path.isdir(frames):
        paths = list_frames(frames)
        ambient = _folder_ambient(frames, ambient)
        if _is_auto(lights):
            lights = _folder_lights(frames)
    else:
        for what, given in (("ambient", ambient), ("lights", lights)):
            if _is_auto(given):
                raise ValueError(f"{what}='auto' takes the {what} file from a folder of "
                                 f"frames; with files, give the {what} file")
        paths = _frame_paths(frames)
        if not paths:
            raise ValueError("frames: empty list of files")
    # Named before any frame is read: a missing file otherwise reads as a missing frame.
    for what, path in (("lights file", lights), ("ambient frame", ambient), ("mask", mask),
                       ("intensity mask", intensity_mask), ("intensity ratios", intensity_ratios)):
        if isinstance(path, (str, os.PathLike)) and not _is_auto(path) and not _exists(path):
            raise FileNotFoundError(f"{what} not found: {os.fspath(path)}")
    names = tuple(os.path.basename(p) for p in paths)
    ratios = None if intensity_ratios is None else _ratios(intensity_ratios, len(paths))
    images, saturated = load_stack(paths, linearize=linearize, bits=bits)  # names a missing frame
    if len(paths) < 3:
        raise ValueError(f"frames: photometric stereo needs at least 3 frames, got {len(paths)} "
                         f"({', '.join(names)})")

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
    source = f" in {os.fspath(lights)}" if isinstance(lights, (str, os.PathLike)) else ""
    if light_array is not None and len(light_array) != len(paths):
        raise ValueError(f"lights: {len(paths)} frames but {len(light_array)} lights{source} "
                         "(one light per frame, in the frames' order)")
    if light_array is not None and np.all(np.asarray(light_array)[:, 2] <= 0):
        # every visible pixel would come back BACKFACING, and the run would look done
        raise ValueError(
            f"lights: every light{source} has l_z <= 0, behind the subject as the camera sees "
            "it (x right, y up, z toward the camera, each vector pointing toward its lamp). "
            "Directions from the lamps to the subject need their signs flipped")

    if ambient is not None:
        images = _minus_ambient_file(images, ambient, paths[0], linearize=linearize, bits=bits)

    if isinstance(mask, np.ndarray):
        if mask.shape != images.shape[1:3]:
            raise ValueError(f"mask has shape {mask.shape}, frames have {images.shape[1:3]}")
        mask_array = mask.astype(bool)
    elif mask is None or (isinstance(mask, str) and mask == "auto"):
        mask_array = None
    else:
        mask_array = read_mask(mask, images.shape[1:3])
    dark_mask = None  # the warning's words, also put before the frame check's error
    if mask_array is not None:  # before the frame check, which would call every frame dark
        dark, outside = _dark_in_mask(images, mask_array)
        if dark > _DARK_MASK_FRACTION:
            dark_mask = (f"{100 * dark:.0f}% of the mask's pixels are dark in the mean frame, "
                         f"and {100 * outside:.0f}% of the lit pixels lie outside it: is the "
                         "mask inverted (the object black), or another capture's?")
            logging.getLogger("jaxps").warning("load_capture: %s", dark_mask)

    if isinstance(intensity_mask, np.ndarray):
        if intensity_mask.shape != images.shape[1:3]:
            raise ValueError(f"intensity_mask has shape {intensity_mask.shape}, frames have "
                             f"{images.shape[1:3]}")
        target = intensity_mask.astype(bool)
    else:
        target = None if intensity_mask is None else read_mask(intensity_mask,
                                                               images.shape[1:3])
    if target is not None and not target.any():
        raise ValueError("intensity_mask is empty: no pixel of the reference target")

    given, frame_check = names, None
    if check_quality:  # inside the given mask: the frames are judged where they will be used
        try:
            images, saturated, names, light_array, frame_check = screen_capture(
                images, saturated, names, light_array, mask=mask_array,
                spare_inconsistent=register)
        except ValueError as err:
            if dark_mask is None:
                raise
            raise ValueError(f"mask: {dark_mask} The frames were checked inside it: {err}") \
                from None

    method = intensities
    if light_array is None and method in ("frontal", "semi_calibrated"):
        if method == "semi_calibrated":
            raise ValueError("intensities='semi_calibrated' needs lights")
        method = "mean"
    e, fit = np.ones(len(images), np.float32), None
    if target is not None:  # the target stays where it is: measured before any move or crop
        lit = target & ~saturated.any(axis=0)  # a clipped sample is no measure of its flash
        if not lit.any():
            raise ValueError("intensity_mask: every pixel of the reference target is saturated "
                             "in some frame; use a darker (grey) target or a shorter exposure")
        try:
            e = _intensities(images, light_array, lit, method, intensity_normal)[0]
        except ValueError as err:  # asked for by name: an error, not a silent fallback
            raise ValueError(f"intensity_mask: the reference target's intensities: {err}") \
                from err
        if ratios is not None:
            e = e * ratios[_kept(given, names)]
            e = _geometric_unit(e)

    shifts, border = None, 0
    if register:
        images, saturated, shifts, border, far = _register(
            images, saturated, light_array, mask_array, names, drop_far=frame_check is not None)
        kept = np.flatnonzero(~far)
        if far.any():  # moved too far to undo: dropped, as a flagged frame is
            frame_check = _flag_moved(frame_check, names, far, shifts)
        if frame_check is not None and (border or any(map(only_inconsistent,
                                                            frame_check.frames))):
            again, frame_check = _check_again(images[kept], [names[i] for i in kept],
                                              frame_check, mask_array, border)
            kept = kept[again]
            _check_span(light_array, kept, names, frame_check)
        if len(kept) < len(names):
            images, saturated, shifts = images[kept], saturated[kept], shifts[kept]
            names = tuple(names[i] for i in kept)
            light_array = None if light_array is None else light_array[kept]
            if target is not None:  # measured on the frames held before: geometric mean 1 again
                e = _geometric_unit(e[kept])

    box, full_size = None, images.shape[1:3]
    if crop_face:
        box = detect_face(images.mean(axis=0))
        if box is None:
            raise ValueError(f"no face found in the mean of frames {names[0]}...{names[-1]}")
        box = bucket_box(box, images.shape[1:3], multiple=crop_multiple)
        images, saturated = crop(images, box, axis=1), crop(saturated, box, axis=1)
        if mask_array is not None:
            mask_array = crop(mask_array, box)

    if mask_array is None:
        mask_array = (mask_from_intensity(images) if mask == "auto"
                      else np.ones(images.shape[1:3], bool))
    if border:  # rows and columns the shifted frames filled by repeating their edge
        keep = _interior(full_size, border)
        mask_array = mask_array & (keep if box is None else crop(keep, box))
    if target is None:
        try:
            e, fit = _intensities(images, light_array, mask_array, method, saturated=saturated)
        except ValueError as err:  # a black frame: keep the capture, say so
            logging.getLogger("jaxps").warning(
                "load_capture: intensities=%r failed (%s); frames used as read", method, err)
            method = "none"
    if method != "none":
        shape = (-1,) + (1,) * (images.ndim - 1)
        images = np.divide(images, e.reshape(shape),
                           out=aligned_empty(images.shape, np.float32))
    light_check = None
    if light_array is not None:
        light_check = check_lights(images, light_array, mask=mask_array)
        if light_check.flagged:
            logging.getLogger("jaxps").warning("load_capture: %s", light_check.summary())
    return Capture(aligned(images, np.float32), light_array, mask_array,
                   saturated, names, box, (1 / e).astype(np.float32),
                   tuple(n for n in given if n not in names), e, method, shifts, border > 0,
                   fit, tuple(int(v) for v in full_size), light_check, frame_check)


def target_ratios(
    images: Float[np.ndarray, "K H W *C"],
    lights: Float[np.ndarray, "K 3"],
    target: Bool[np.ndarray, "H W"],
    subject: Bool[np.ndarray, "H W"],
    *,
    target_normal: Sequence[float] | None = None,
    subject_normal: Sequence[float] | None = None,
    saturated: Bool[np.ndarray, "K H W"] | None = None,
) -> Float[np.ndarray, " K"]:
    """Per light, the flash at the subject's place over the flash at a reference target:
    the one-time calibration that `load_capture(intensity_ratios=...)` applies.

    A target fixed to the scanner measures each frame's flash strength (`intensity_mask`).
    With near lights it is lit from another distance and angle than the face, by a factor
    that differs from lamp to lamp but not from shot to shot. Image a flat, matte board at
    the subject's place once per light, with the target in view; then the ratios are the
    "frontal" estimate over the board (normal `subject_normal`, default facing the camera)
    over the same estimate over the target (normal `target_normal`), geometric mean 1.

    **Arguments:**
    - `images`: `(K, H, W)` or `(K, H, W, C)` frames of the board, ambient subtracted.
    - `lights`: `(K, 3)` light directions (as for the captures, e.g. `jaxps calibrate`'s).
    - `target`, `subject`: `(H, W)` bool, the reference target and the board.
    - `saturated`: `(K, H, W)` bool, samples clipped in the raw frames, left out.

    **Returns:** `(K,)` float32, geometric mean 1.

    **Raises:** `ValueError` naming `target` or `subject` when a region is empty, black or
    saturated throughout, or faces away from a light.
    """
    images = np.asarray(images, np.float32)
    grey = images if images.ndim == 3 else images.mean(axis=-1)
    clipped = (np.zeros(grey.shape[1:], bool) if saturated is None
               else np.asarray(saturated, bool).any(axis=0))
    estimates = []
    for what, region, normal in (("subject", subject, subject_normal),
                                 ("target", target, target_normal)):
        region = np.asarray(region, bool)
        if region.shape != grey.shape[1:]:
            raise ValueError(f"{what} has shape {region.shape}, frames have {grey.shape[1:]}")
        if not (region & ~clipped).any():
            raise ValueError(f"{what}: no pixel of it is unsaturated in every frame")
        try:
            estimates.append(np.asarray(intensity_estimate(
                grey, lights, mask=region & ~clipped, method="frontal", normal=normal),
                np.float64))
        except ValueError as err:
            raise ValueError(f"{what}: {err}") from err
    ratios = estimates[0] / estimates[1]
    return _geometric_unit(ratios)


def _kept(given, names):
    """Indices into `given` of `names`, the frames the quality checks kept (in order)."""
    kept = []
    for i, name in enumerate(given):
        if len(kept) < len(names) and name == names[len(kept)]:
            kept.append(i)
    return kept


def _ratios(ratios, k):
    """`load_capture`'s `intensity_ratios` as `(k,)` float64: from a text file (one number per
    line, `#` comments) or an array; `ValueError` naming them unless k finite positives."""
    where = ""
    if isinstance(ratios, (str, os.PathLike)):
        where = f" ({os.fspath(ratios)})"
        try:
            ratios = np.loadtxt(ratios, comments="#", ndmin=1, encoding="utf-8-sig")
        except ValueError as err:
            raise ValueError(f"intensity_ratios{where}: not a list of numbers: {err}") from None
    ratios = np.asarray(ratios, np.float64)
    if ratios.shape != (k,):
        raise ValueError(f"intensity_ratios{where}: {k} frames need {k} ratios, got shape "
                         f"{ratios.shape}")
    if not (np.all(np.isfinite(ratios)) and np.all(ratios > 0)):
        raise ValueError(f"intensity_ratios{where}: every ratio must be finite and positive")
    return ratios


def _intensities(images, lights, region, method, normal=None, saturated=None):
    """`load_capture`'s intensities `(K,)` float32 by `method` over `region`, and the
    semi-calibrated fit's report (else None). Raises `ValueError` where the estimate fails,
    e.g. on a black frame."""
    if method == "none":
        return np.ones(len(images), np.float32), None
    grey = images if images.ndim == 3 else images.mean(axis=-1)
    if method == "semi_calibrated":
        return _semi_calibrated(grey, lights, region, ~saturated)
    # "mean" does not look at the lights: without any, give it view-axis placeholders.
    lights = np.tile(np.float32([0, 0, 1]), (len(images), 1)) if lights is None else lights
    e = intensity_estimate(grey, lights, mask=region, method=method, normal=normal)
    return np.asarray(e, np.float32), None


def _semi_calibrated(grey, lights, mask, sample_mask):
    """The semi-calibrated intensities `(K,)` float32 and the fit's report (`Capture`'s
    `intensity_fit`), with a warning on the "jaxps" logger when the fit did not converge."""
    res = photometric_stereo(grey, lights, mask=mask, sample_mask=sample_mask,
                             method="semi_calibrated")
    info = {k: np.asarray(v) for k, v in res.info.items()}
    fit = {"converged": bool(info["converged"]), "fallback": bool(info["fallback"]),
           "steps": int(info["steps"]), "objective": info["objective"].round(8).tolist(),
           "visibility": round(float(info["visibility"]), 6)}
    if not fit["converged"]:
        logging.getLogger("jaxps").warning(
            "load_capture: the semi-calibrated intensity fit stopped after %d steps without "
            "converging%s (flash visibility %.3f; docs/captures.md)", fit["steps"],
            ", and fell back to frontal intensities" if fit["fallback"] else "",
            fit["visibility"])
    return np.asarray(info["intensities"], np.float32), fit


def _minus_ambient_file(images, ambient, frame, **read_options):
    """`images` (a stack the caller owns, read from files like `frame`) with the frame in the
    file `ambient` (`read_image(ambient, **read_options)`) subtracted in place and clipped at
    0; a `ValueError` names the file if it is decoded from sRGB where the frames are not (or
    the other way), if its shape is not the frames', or if it is brighter than the median
    frame over much of the image (`_below_ambient`)."""
    linearize = read_options.get("linearize", "auto")
    decoded = _decodes_srgb(ambient, linearize), _decodes_srgb(frame, linearize)
    if decoded[0] != decoded[1]:
        said = ("read as linear", "decoded from sRGB (an 8-bit PNG)")
        raise ValueError(
            f"ambient frame {os.fspath(ambient)} is {said[decoded[0]]}, but the frames "
            f"({os.path.basename(frame)}) are {said[decoded[1]]}: subtracted, the two would "
            "not be on one scale. Save the ambient frame as the frames are saved.")
    amb = read_image(ambient, **read_options)
    if amb.shape != images.shape[1:]:
        raise ValueError(f"ambient frame {os.fspath(ambient)} has shape {amb.shape}, frames "
                         f"have {images.shape[1:]}")
    fractions, tau = _below_ambient(images, amb)
    fraction = float(np.median(fractions))
    if fraction > _AMBIENT_FRACTION:
        raise ValueError(
            f"ambient frame {os.fspath(ambient)} is brighter than the lit frames: the median "
            f"frame is darker than it by more than {tau:.3g} at {100 * fraction:.0f}% of the "
            "pixels. Is it a lit frame? The ambient frame is taken with every light off.")
    return _subtract_ambient(images, amb, out=images)


# An ambient-only frame is darker than the lit frames, but for noise. In the 64 frames of each
# shared Yale B subject at most 0.25% of the pixels are darker than the subject's ambient frame
# by more than `_below_ambient`'s margin; with one of the five cross frames given as the
# ambient instead, 14-58% of the other four's median frame (benchmarks/input_checks.py).
# Subtracting it anyway clips those pixels at 0 and leaves each frame the difference of two
# lights, which the solve takes for one: wrong normals, with nothing in the status to say so.
_AMBIENT_FRACTION = 0.05


def _below_ambient(images, ambient):
    """`((K,) fractions, tau)`: the fraction of each frame's pixels below `ambient` by more
    than `tau`, a tenth of the median frame's mean (at least 0.02 of full scale, a few codes of
    an 8-bit frame's noise), on every 4th row and column."""
    frames, amb = images[:, ::4, ::4], ambient[::4, ::4]
    axes = tuple(range(1, frames.ndim))
    tau = max(0.1 * float(np.median(frames.mean(axis=axes))), 0.02)
    return np.mean(frames < amb[None] - tau, axis=axes), tau


# A given mask with more of its pixels dark than this gets a warning (`_dark_in_mask`).
_DARK_MASK_FRACTION = 0.5


def _geometric_unit(x):
    """`x` (positive) divided by its geometric mean, as float32: flash strengths are relative."""
    return (x / np.exp(np.mean(np.log(x)))).astype(np.float32)


def _dark_in_mask(images, mask):
    """`(dark, lit_outside)`: the fraction of `mask`'s pixels that are dark in the mean frame
    (below `mask_from_intensity`'s level, `_lit_level`), and the fraction of the
    lit pixels outside `mask`, on every 4th row and column. An inverted mask (the object black)
    on a dark background has both near 1 (docs/acquisition.md, the mask row)."""
    mean = images[:, ::4, ::4].mean(axis=0)
    mean = mean.mean(axis=-1) if mean.ndim == 3 else mean
    inside = mask[::4, ::4]
    lit = mean > _lit_level(mean)
    dark = 1 - float(lit[inside].mean()) if inside.any() else 0.0
    return dark, float((lit & ~inside).sum() / max(lit.sum(), 1))


def _folder_ambient(folder, ambient):
    """`ambient` for a folder capture: the folder's one `*ambient*` frame for `"auto"`; as
    given otherwise, with a warning when the folder holds an ambient frame that is not used."""
    found = sorted(n for n in os.listdir(folder)
                   if "ambient" in n.lower() and n.lower().endswith(FRAME_EXTENSIONS))
    if _is_auto(ambient):
        if len(found) != 1:
            raise ValueError(f"ambient='auto': expected one frame whose name contains 'ambient' "
                             f"in {os.fspath(folder)}, found {found or 'none'}")
        return os.path.join(folder, found[0])
    if ambient is None and found:
        logging.getLogger("jaxps").warning(
            "load_capture: %s holds an ambient frame (%s) that is not subtracted; pass "
            "ambient='auto' (--ambient auto) to use it", os.fspath(folder), ", ".join(found))
    return ambient


def _folder_lights(folder):
    """`lights="auto"` for a folder capture: its one `.txt` file whose name contains
    "light"."""
    found = sorted(n for n in os.listdir(folder)
                   if "light" in n.lower() and n.lower().endswith(".txt"))
    if len(found) != 1:
        raise ValueError(f"lights='auto': expected one .txt file whose name contains 'light' in "
                         f"{os.fspath(folder)}, found {found or 'none'}")
    return os.path.join(folder, found[0])


def _is_auto(ambient):
    return isinstance(ambient, str) and ambient == "auto"


def _interior(shape, border):
    """`(H, W)` bool: True but for the `border` rows and columns at each edge."""
    keep = np.zeros(shape, bool)
    keep[border:-border, border:-border] = True
    return keep


def _check_again(images, names, report, mask, border):
    """`(kept, report)` after the motion step: when the frames were moved (`border` > 0),
    the consistency of the frames now held (`names`: those `report` passed, and those it
    flagged only as inconsistent, which `screen_capture` kept) is judged again on the frames
    as registered (`border` rows and columns at the edges left out); else the first verdict
    stands. The frames flagged are dropped; `kept` indexes `names`. In the report returned,
    the held frames' reasons are the last verdict's, marked when found after the motion was
    undone.

    A frame that moved is inconsistent with the others, so the check before the motion
    step would drop it where registering it keeps it (`benchmarks/input_checks.py`,
    "moved_frame"). And the check flags one frame at a time while five are left, so a frame
    inconsistent for another reason can hide behind a moved one until this second look."""
    held = [f for f in report.frames if not f.flagged or only_inconsistent(f)]  # = names
    checks = list(report.frames)
    if border:
        region = _interior(images.shape[1:3], border)  # the edge: filled by repeating it
        region = region if mask is None else region & mask
        grey = images if images.ndim == 3 else images.mean(axis=-1)
        flagged, incons = flag_inconsistent(grey, region, np.ones(len(held), bool))
        for j, f in enumerate(held):
            checks[f.index] = f._replace(
                reasons=(f"{flagged[j]} (after undoing motion)",) if j in flagged else (),
                measures={**f.measures, "inconsistency": float(incons[j])})
    kept = [j for j, f in enumerate(held) if not checks[f.index].flagged]
    dropped = [names[j] for j, f in enumerate(held) if checks[f.index].flagged]
    if dropped:
        logging.getLogger("jaxps").warning(
            "load_capture: inconsistent with the other frames once their motion was %s, "
            "dropped: %s", "undone" if border else "measured (too small or too large to undo)",
            ", ".join(dropped))
    checks = QualityReport(tuple(checks))
    if len(kept) < 3:
        raise ValueError(f"frames: only {len(kept)} of {len(report.frames)} frames passed the "
                         f"quality checks, need at least 3.\n{checks.summary()}")
    return np.array(kept), checks


def _register(images, saturated, lights, mask, names, drop_far=False):
    """`load_capture`'s motion step: `(images, saturated, shifts, border, far)`. `border` is 0
    when no frame was moved. `far` `(K,)` marks the frames that moved more than
    `motion_limit`, for the caller to drop: with `drop_far`, when at least 3 frames are left
    whose lights span 3-D, the others are registered without them. Otherwise (or without
    `drop_far`) every frame is left as read, and `far` is all False. Both are logged."""
    log = logging.getLogger("jaxps")
    reference = 0 if lights is None else int(np.argmax(np.asarray(lights)[:, 2]))
    shifts = estimate_shifts(images, reference=reference, mask=mask)
    limit = motion_limit(images.shape[1:3], mask)
    size = np.max(np.abs(shifts), axis=1)
    far = size > limit
    if far.any():
        moved = ", ".join(n for n, f in zip(names, far) if f)
        if not (drop_far and (~far).sum() >= 3 and lights_span(lights, ~far)):
            log.warning("load_capture: frames %s moved up to %.1f px against %s (more than "
                        "%.1f px); left unregistered", moved, size.max(), names[reference], limit)
            return images, saturated, shifts, 0, np.zeros(len(names), bool)
        log.warning("load_capture: frames %s moved up to %.1f px against %s (more than %.1f "
                    "px), or are too unlike it to measure: dropped, the others registered",
                    moved, size.max(), names[reference], limit)
    largest = float(size[~far].max())
    if largest < MIN_SHIFT:
        return images, saturated, shifts, 0, far
    undo = np.where(far[:, None], 0.0, -shifts)  # frames to be dropped stay as they are
    # a sample is saturated if a saturated raw sample lies within a pixel of it
    moved_sat = _shift(saturated.astype(np.float32), undo, order=1) > 0
    return (np.clip(_shift(images, undo), 0, 1), moved_sat, shifts,
            int(np.ceil(largest)), far)


def _flag_moved(report, names, far, shifts):
    """`report` with each frame of `names` marked in `far` flagged as having moved too far."""
    checks = list(report.frames)
    for name, f, s in zip(names, far, shifts):
        if f:
            i = next(c.index for c in checks if c.name == name)
            checks[i] = checks[i]._replace(
                reasons=((f"moved {np.max(np.abs(s)):.1f} px, more than a translation "
                          "undoes, or too unlike the reference frame to measure"),))
    return QualityReport(tuple(checks))
