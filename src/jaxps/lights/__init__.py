"""Lights: where each frame's light comes from, as unit vectors in the camera frame.

Takes Yale B angles, `lights.txt` files (`load_lights`, `save_lights`), frames of a chrome
sphere, or near point-light positions with a surface; gives `(K, 3)` directions, or
`(K, H, W, 3)` per-pixel directions and `(K, H, W)` fall-off for near lights, checked to span
3-D; `check_lights` checks a lights file's axes and order against the shape its frames
give.
"""

from ._check import LightCheck, check_lights
from ._chrome import ChromeCalibration, lights_from_chrome, sphere_from_mask
from ._directions import (
    angles_from_lights,
    lights_from_angles,
    load_lights,
    parse_yale_name,
    save_lights,
    validate_lights,
)
from ._near import near_light_field, surface_points

__all__ = [
    "ChromeCalibration",
    "LightCheck",
    "angles_from_lights",
    "check_lights",
    "lights_from_angles",
    "lights_from_chrome",
    "load_lights",
    "near_light_field",
    "parse_yale_name",
    "save_lights",
    "sphere_from_mask",
    "surface_points",
    "validate_lights",
]
