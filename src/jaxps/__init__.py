"""jaxps: photometric-stereo face capture and reflectance modelling in JAX."""

import importlib.metadata

from . import evaluate, stability, synthetic
from ._brdf import (
    BRDF_METHODS,
    BRDFFit,
    BRDFModel,
    extrapolation_mask,
    fit_brdf,
    relight,
)
from ._brdf_features import FEATURE_NAMES, brdf_features
from ._brdf_ps import brdf_photometric_stereo
from ._calibration import ChromeCalibration, lights_from_chrome, load_psm, sphere_from_mask
from ._batch import photometric_stereo_batch, reconstruct_many, summary_table
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
from ._near import NearResult, near_light_field, near_photometric_stereo, surface_points
from ._ps import PS_METHODS, photometric_stereo
from ._semicalibrated import INTENSITY_METHODS, intensity_estimate
from ._quality import (
    FrameCheck,
    QualityReport,
    QualityThresholds,
    check_file,
    check_frames,
    drop_flagged,
)
from ._register import Registration, estimate_shifts, register_frames, shift_frames
from ._render import angular_error, render_lambertian
from ._status import Status, status_counts

__version__ = importlib.metadata.version("jaxps")

__all__ = [
    "BRDFFit",
    "BRDFModel",
    "BRDF_METHODS",
    "ChromeCalibration",
    "FEATURE_NAMES",
    "FrameCheck",
    "INTENSITY_METHODS",
    "INTEGRATION_METHODS",
    "IntegrationResult",
    "NearResult",
    "PSResult",
    "PS_METHODS",
    "QualityReport",
    "QualityThresholds",
    "Registration",
    "Status",
    "angular_error",
    "brdf_features",
    "brdf_photometric_stereo",
    "check_file",
    "check_frames",
    "drop_flagged",
    "estimate_shifts",
    "evaluate",
    "extrapolation_mask",
    "fit_brdf",
    "gradients_from_normals",
    "integrability_map",
    "integrate",
    "intensity_estimate",
    "lights_from_angles",
    "lights_from_chrome",
    "load_lights",
    "load_psm",
    "near_light_field",
    "near_photometric_stereo",
    "normals_from_height",
    "parse_yale_name",
    "photometric_stereo",
    "relight",
    "photometric_stereo_batch",
    "reconstruct_many",
    "register_frames",
    "render_lambertian",
    "sphere_from_mask",
    "stability",
    "shift_frames",
    "status_counts",
    "surface_points",
    "summary_table",
    "synthetic",
    "validate_lights",
]
