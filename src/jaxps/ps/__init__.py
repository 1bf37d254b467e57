"""Photometric stereo: per-pixel normals and albedo from K >= 3 images under known lights.

Takes `(K, H, W[, C])` linear images and `(K, 3)` or per-pixel `(K, H, W, 3)` lights; gives a
`PSResult`: `(H, W, 3)` normals, albedo and a status code per pixel. One module per solver
family, chosen by `photometric_stereo(method=...)` (`PS_METHODS`).
"""

from ._batch import photometric_stereo_batch, release_batch_outputs
from ._intensities import INTENSITY_METHODS, intensity_estimate
from ._l2 import PSResult
from ._near import NearResult, near_photometric_stereo
from ._photometric_stereo import PS_METHODS, photometric_stereo
from ._visibility import flash_visibility

__all__ = [
    "INTENSITY_METHODS",
    "NearResult",
    "PSResult",
    "PS_METHODS",
    "flash_visibility",
    "intensity_estimate",
    "near_photometric_stereo",
    "photometric_stereo",
    "photometric_stereo_batch",
    "release_batch_outputs",
]
