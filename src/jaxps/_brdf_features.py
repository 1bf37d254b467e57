"""Per-sample BRDF coordinates (θi, θr, Δα, x, y) from normals, lights and the view direction.

The five-source NIR face-scanner paper models a face's reflectance as a function of, per pixel
and light, the incidence zenith $\\theta_i$, the view zenith $\\theta_r$ (both measured from the
surface normal), the azimuth difference $\\Delta\\alpha$ of light and view about the normal
(isotropy assumed: only the difference matters, folded to $[0, \\pi]$) and the pixel position.

Conventions (DESIGN.md camera frame, orthographic view $v = (0, 0, 1)$):

| feature | definition | range | unit |
|---|---|---|---|
| `theta_i` | $\\arccos(n \\cdot l)$ | $[0, \\pi]$ ($> \\pi/2$: attached shadow) | radians |
| `theta_r` | $\\arccos(n \\cdot v) = \\arccos n_z$ | $[0, \\pi/2]$ for $n_z \\ge 0$ | radians |
| `delta_alpha` | angle between $l$ and $v$ projected on the tangent plane | $[0, \\pi]$ | radians |
| `x` | $2\\,c/(W-1) - 1$ for column $c$ | $[-1, 1]$, right positive | — |
| `y` | $1 - 2\\,r/(H-1)$ for row $r$ | $[-1, 1]$, up positive | — |

$\\Delta\\alpha$ is undefined where either projection vanishes ($n = v$ or $n = \\pm l$); it is
then 0. Every feature is computed with guarded `arctan2`, so values and gradients stay finite.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

__all__ = ["FEATURE_NAMES", "brdf_features", "pixel_coordinates"]

FEATURE_NAMES = ("theta_i", "theta_r", "delta_alpha", "x", "y")


def _angle(a, b):
    """Angle between 3-vectors `a` and `b` (need not be unit), 0 when either is ~0."""
    c = jnp.cross(a, b)
    c2 = jnp.dot(c, c)
    tiny = jnp.asarray(1e-24, a.dtype)
    # double-where: sqrt and arctan2 never see the singular point, so gradients stay finite
    cross = jnp.where(c2 > tiny, jnp.sqrt(jnp.where(c2 > tiny, c2, 1)), 0)
    dot = jnp.dot(a, b)
    small = (c2 <= tiny) & (jnp.abs(dot) <= 1e-12)
    return jnp.where(small, jnp.zeros((), a.dtype),
                     jnp.arctan2(cross, jnp.where(small, jnp.ones((), a.dtype), dot)))


def _sample_angles(n, light, view):
    """(θi, θr, Δα) for one unit normal `n` (3,), unit light (3,), unit view (3,)."""
    theta_i = _angle(n, light)
    theta_r = _angle(n, view)
    light_t = light - jnp.dot(n, light) * n
    view_t = view - jnp.dot(n, view) * n
    return jnp.stack([theta_i, theta_r, _angle(light_t, view_t)])


def pixel_coordinates(h: int, w: int, dtype=jnp.float32) -> Float[Array, "H W 2"]:
    """`(H, W, 2)` pixel positions (x, y) scaled to [-1, 1], x right and y up (row 0 at y=1)."""
    x = 2 * np.arange(w) / max(w - 1, 1) - 1
    y = 1 - 2 * np.arange(h) / max(h - 1, 1)
    xx, yy = np.meshgrid(x, y)
    return jnp.asarray(np.stack([xx, yy], axis=-1), dtype)


def brdf_features(
    normals: Float[ArrayLike, "H W 3"],
    lights: Float[ArrayLike, "K 3"],
) -> Float[Array, "K H W 5"]:
    """The per-sample BRDF coordinates (θi, θr, Δα, x, y) of every pixel under every light.

    **Arguments:**
    - `normals`: `(H, W, 3)` unit normals in the camera frame (normalised here).
    - `lights`: `(K, 3)` directions toward distant lights (normalised here).

    **Returns:** `(K, H, W, 5)` features in the dtype of `normals`, ordered as
    `jaxps.FEATURE_NAMES`: angles in radians, x and y in [-1, 1] (see the module docstring for
    ranges). The view direction is the orthographic camera axis (0, 0, 1).
    """
    normals = jnp.asarray(normals)
    if not jnp.issubdtype(normals.dtype, jnp.floating):
        raise ValueError(f"normals must be floating point, got dtype {normals.dtype}")
    if normals.ndim != 3 or normals.shape[-1] != 3:
        raise ValueError(f"normals must be (H, W, 3), got shape {normals.shape}")
    lights = jnp.asarray(lights, normals.dtype)
    if lights.ndim != 2 or lights.shape[-1] != 3:
        raise ValueError(f"lights must be (K, 3), got shape {lights.shape}")
    return _features(normals, lights)


@jax.jit
def _features(normals, lights):
    h, w, _ = normals.shape
    dtype = normals.dtype
    n = normals / jnp.maximum(jnp.linalg.norm(normals, axis=-1, keepdims=True),
                              jnp.asarray(1e-12, dtype))
    lights = lights / jnp.linalg.norm(lights, axis=-1, keepdims=True)
    view = jnp.array([0, 0, 1], dtype)
    per_pixel = jax.vmap(_sample_angles, in_axes=(0, None, None))
    per_light = jax.vmap(per_pixel, in_axes=(None, 0, None))
    angles = per_light(n.reshape(-1, 3), lights, view).reshape(-1, h, w, 3)
    xy = jnp.broadcast_to(pixel_coordinates(h, w, dtype), (lights.shape[0], h, w, 2))
    return jnp.concatenate([angles, xy], axis=-1)
