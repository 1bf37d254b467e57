"""jaxps: photometric-stereo face capture and reflectance modelling in JAX."""

import importlib.metadata

from . import evaluate, synthetic
from ._integrate import (
    INTEGRATION_METHODS,
    IntegrationResult,
    gradients_from_normals,
    integrability_map,
    integrate,
    normals_from_height,
)
from ._lights import lights_from_angles, load_lights, parse_yale_name, validate_lights
from ._l2 import PSResult
from ._ps import PS_METHODS, photometric_stereo
from ._render import angular_error, render_lambertian
from ._status import Status, status_counts

__version__ = importlib.metadata.version("jaxps")

__all__ = [
    "INTEGRATION_METHODS",
    "IntegrationResult",
    "PSResult",
    "PS_METHODS",
    "Status",
    "angular_error",
    "evaluate",
    "gradients_from_normals",
    "integrability_map",
    "integrate",
    "lights_from_angles",
    "load_lights",
    "normals_from_height",
    "parse_yale_name",
    "photometric_stereo",
    "render_lambertian",
    "status_counts",
    "synthetic",
    "validate_lights",
]
