"""Acquisition adapter (eager, numpy): from frame files to a capture ready for the solvers.

Takes frame files (PGM/PNG/TIFF/BMP, 8/16-bit, grey or colour), an ambient frame, lights and a mask;
gives a `Capture` of linear float32 `(K, H, W[, C])` images, lights, mask and saturation map,
optionally equalised, cropped to the Haar-detected face and screened for bad frames.

Intensities follow DESIGN.md: float32 in [0, 1] (8-bit / 255, 16-bit / 65535), linear in
radiance; gamma-encoded sources (8-bit PNG/JPEG by default) are decoded from sRGB with
colour-science. It runs once per capture and hands numpy arrays to the jitted core; OpenCV and
colour-science load on first use.
"""

from ._capture import Capture, load_capture, target_ratios
from ._face import bucket_box, crop, detect_face
from ._files import FRAME_EXTENSIONS, list_frames, load_stack, read_image, read_mask
from ._psm import load_psm
from ._quality import (
    FrameCheck,
    QualityReport,
    QualityThresholds,
    check_file,
    check_frames,
    drop_flagged,
)
from ._register import Registration, estimate_shifts, register_frames, shift_frames
from ._stack import equalize_mean, mask_from_intensity, subtract_ambient

__all__ = [
    "Capture",
    "FRAME_EXTENSIONS",
    "FrameCheck",
    "QualityReport",
    "QualityThresholds",
    "Registration",
    "check_file",
    "check_frames",
    "bucket_box",
    "crop",
    "detect_face",
    "drop_flagged",
    "equalize_mean",
    "estimate_shifts",
    "list_frames",
    "load_capture",
    "load_psm",
    "load_stack",
    "mask_from_intensity",
    "read_image",
    "read_mask",
    "register_frames",
    "shift_frames",
    "subtract_ambient",
    "target_ratios",
]
