"""Photometric stereo: per-pixel normals and albedo from K >= 3 images under known lights.

Takes `(K, H, W[, C])` linear images and `(K, 3)` (or per-pixel `(K, H, W, 3)`) lights; gives a
`PSResult` of `(H, W, 3)` normals, albedo and a status code per pixel. `photometric_stereo`
chooses the solver by `method=`: least squares (`"l2"`), the robust `"barsky"`, `"irls"` and
`"sbl"`, `"semi_calibrated"` (per-frame intensities) and `"oren_nayar"`; near point lights and
many captures at once have entry points of their own.
"""

from ._batch import photometric_stereo_batch
from ._intensities import INTENSITY_METHODS, intensity_estimate
from ._l2 import PSResult
from ._near import NearResult, near_photometric_stereo
from ._photometric_stereo import PS_METHODS, photometric_stereo

__all__ = [
    "INTENSITY_METHODS",
    "NearResult",
    "PSResult",
    "PS_METHODS",
    "intensity_estimate",
    "near_photometric_stereo",
    "photometric_stereo",
    "photometric_stereo_batch",
]
