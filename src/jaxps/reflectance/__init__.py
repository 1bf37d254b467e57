"""Reflectance: which model a solved capture needs, a learned BRDF, and relighting.

Takes images with the normals and albedo photometric stereo gave them; gives a model choice
(Lambert or Oren–Nayar), an MLP BRDF over $(\\theta_i, \\theta_r, \\Delta\\alpha, x, y)$ with
Delaunay and Lambertian baselines, relit images scored on held-out lights against Lambert's law,
and normals re-solved with the BRDF in the loop.
"""

from ._brdf import BRDF_METHODS, BRDFFit, BRDFModel, extrapolation_mask, fit_brdf, relight
from ._brdf_ps import brdf_photometric_stereo
from ._features import FEATURE_NAMES, brdf_features
from ._model_choice import ModelChoice, compare_models
from ._score import RelightScore, score_relighting

__all__ = [
    "BRDF_METHODS",
    "FEATURE_NAMES",
    "BRDFFit",
    "BRDFModel",
    "ModelChoice",
    "RelightScore",
    "brdf_features",
    "brdf_photometric_stereo",
    "compare_models",
    "extrapolation_mask",
    "fit_brdf",
    "relight",
    "score_relighting",
]
