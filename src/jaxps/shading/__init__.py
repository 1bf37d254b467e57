"""Shading models: how a pixel's brightness follows from its normal, albedo and the light.

Takes normals, albedo and lights; gives rendered images (Lambert, Oren–Nayar), and, given
images with known normals, Oren–Nayar roughness and the Lambertian check ($I/\\rho$ against
$\\cos\\theta$). Photometric stereo inverts these models; `jaxps.reflectance` chooses among
them.
"""

from ._lambert import render_lambertian
from ._lambertian_check import LambertianCheck, lambertian_check
from ._oren_nayar import (
    OREN_NAYAR_FORMS,
    RoughnessFit,
    fit_roughness,
    oren_nayar,
    render_oren_nayar,
)
from ._plot import plot_lambertian_check

__all__ = [
    "LambertianCheck",
    "OREN_NAYAR_FORMS",
    "RoughnessFit",
    "fit_roughness",
    "lambertian_check",
    "oren_nayar",
    "plot_lambertian_check",
    "render_lambertian",
    "render_oren_nayar",
]
