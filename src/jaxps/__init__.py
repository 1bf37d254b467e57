"""jaxps: photometric-stereo face capture and reflectance modelling in JAX.

One subpackage per stage, in the order data flows: `acquisition` (frame files to a capture),
`lights`, `ps` (photometric stereo), `integration` (normals to height), `shading` (Lambert and
Oren–Nayar models), `reflectance` (model choice, learned BRDF, relighting), `evaluate`, and
`report` (files and pages for people), with `cli` on top and `core` (status codes, per-pixel
solvers) underneath. The public names of `core`, `lights`, `ps`, `integration`, `shading` and
`reflectance` are all here at the top level too; `acquisition`, `evaluate`, `report` and `cli`
keep theirs under their own name (a few, such as `check_frames`, are also here).
"""

import importlib
import importlib.metadata

# Subpackages and names load on first use (PEP 562), so `import jaxps` is instant and
# `jaxps --help` does not wait for jax; `jaxps.ps`, `jaxps.photometric_stereo` and
# `from jaxps import photometric_stereo` work as if imported here.
_SUBPACKAGES = (
    "acquisition",
    "cli",
    "core",
    "evaluate",
    "integration",
    "lights",
    "ps",
    "reflectance",
    "report",
    "shading",
    "stability",
    "synthetic",
)
_NAMES = {
    "acquisition": (
        "FrameCheck", "QualityReport", "QualityThresholds", "Registration", "check_file",
        "check_frames", "drop_flagged", "estimate_shifts", "load_psm", "register_frames",
        "shift_frames",
    ),
    "cli": (
        "reconstruct_many", "summary_table",
    ),
    "core": (
        "BatchedLM", "Status", "status_counts",
    ),
    "evaluate": (
        "angular_error",
    ),
    "integration": (
        "INTEGRATION_METHODS", "IntegrationResult", "gradients_from_normals", "integrability_map",
        "integrate", "normals_from_height",
    ),
    "lights": (
        "ChromeCalibration", "LightCheck", "angles_from_lights", "check_lights",
        "lights_from_angles", "lights_from_chrome",
        "load_lights", "near_light_field", "parse_yale_name", "save_lights", "sphere_from_mask",
        "surface_points", "validate_lights",
    ),
    "ps": (
        "INTENSITY_METHODS", "PS_METHODS", "NearResult", "PSResult", "flash_visibility",
        "intensity_estimate",
        "near_photometric_stereo", "photometric_stereo", "photometric_stereo_batch",
        "release_batch_outputs",
    ),
    "reflectance": (
        "BRDF_METHODS", "FEATURE_NAMES", "BRDFFit", "BRDFModel", "ModelChoice", "brdf_features",
        "brdf_photometric_stereo", "compare_models", "extrapolation_mask", "fit_brdf", "relight",
        "RelightScore", "score_relighting",
    ),
    "shading": (
        "OREN_NAYAR_FORMS", "LambertianCheck", "RoughnessFit", "fit_roughness", "lambertian_check",
        "oren_nayar", "plot_lambertian_check", "render_lambertian", "render_oren_nayar",
    ),
}
_HOME = {name: sub for sub, names in _NAMES.items() for name in names}


__version__ = importlib.metadata.version("jaxps")

__all__ = [
    # Subpackages, in pipeline order, and the shared modules.
    "acquisition",
    "lights",
    "ps",
    "integration",
    "shading",
    "reflectance",
    "evaluate",
    "report",
    "cli",
    "core",
    "synthetic",
    "stability",
    # Names, alphabetically.
    "BRDFFit",
    "BRDFModel",
    "BRDF_METHODS",
    "BatchedLM",
    "ChromeCalibration",
    "FEATURE_NAMES",
    "FrameCheck",
    "INTENSITY_METHODS",
    "INTEGRATION_METHODS",
    "IntegrationResult",
    "LambertianCheck",
    "LightCheck",
    "ModelChoice",
    "NearResult",
    "OREN_NAYAR_FORMS",
    "PSResult",
    "PS_METHODS",
    "QualityReport",
    "QualityThresholds",
    "Registration",
    "RelightScore",
    "RoughnessFit",
    "Status",
    "angles_from_lights",
    "angular_error",
    "brdf_features",
    "brdf_photometric_stereo",
    "check_file",
    "check_frames",
    "check_lights",
    "compare_models",
    "drop_flagged",
    "estimate_shifts",
    "extrapolation_mask",
    "fit_brdf",
    "fit_roughness",
    "flash_visibility",
    "gradients_from_normals",
    "integrability_map",
    "integrate",
    "intensity_estimate",
    "lambertian_check",
    "lights_from_angles",
    "lights_from_chrome",
    "load_lights",
    "load_psm",
    "near_light_field",
    "near_photometric_stereo",
    "normals_from_height",
    "oren_nayar",
    "parse_yale_name",
    "photometric_stereo",
    "photometric_stereo_batch",
    "plot_lambertian_check",
    "reconstruct_many",
    "register_frames",
    "release_batch_outputs",
    "relight",
    "render_lambertian",
    "render_oren_nayar",
    "save_lights",
    "score_relighting",
    "shift_frames",
    "sphere_from_mask",
    "status_counts",
    "summary_table",
    "surface_points",
    "validate_lights",
]


def __getattr__(name):
    if name in _SUBPACKAGES:
        return importlib.import_module(f"{__name__}.{name}")
    if name in _HOME:
        return getattr(importlib.import_module(f"{__name__}.{_HOME[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
