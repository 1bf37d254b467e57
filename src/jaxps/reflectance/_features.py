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
then 0. Every feature is computed with a guarded two-argument arctangent, so values and gradients
stay finite.

Layout for speed (`_angles_elementwise`): the image-sized work is written as elementwise
expressions on `(K, P)` arrays (P = H W pixels; per-pixel terms `(1, P)`, per-light `(K, 1)`),
not as a per-pixel kernel of 3-vector `cross`/`dot` lifted by `vmap`, and in float32 the
arctangent is a vectorisable polynomial (`core._elementwise.atan2_nonneg`, Cephes `atanf`)
instead of XLA's `atan2`, a scalar call on the CPU (`benchmarks/bench_brdf.py --part speed`,
the atan2 pieces; docs/brdf.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..core._elementwise import atan2_nonneg as _atan2_nonneg

__all__ = ["FEATURE_NAMES", "brdf_features", "pixel_coordinates", "usable_normals"]

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


def _angle_elementwise(cx, cy, cz, dot):
    """`_angle` from the components of the cross product and the dot product (elementwise,
    broadcasting)."""
    dtype = dot.dtype
    c2 = cx * cx + cy * cy + cz * cz
    tiny = jnp.asarray(1e-24, dtype)
    cross = jnp.where(c2 > tiny, jnp.sqrt(jnp.where(c2 > tiny, c2, 1)), 0)
    small = (c2 <= tiny) & (jnp.abs(dot) <= 1e-12)
    return jnp.where(small, jnp.zeros((), dtype),
                     _atan2_nonneg(cross, jnp.where(small, jnp.ones((), dtype), dot)))


def _angles_elementwise(normals, lights):
    """(θi, θr, Δα, n·l) as `(K, P)`, `(1, P)`, `(K, P)`, `(K, P)` arrays (P = H W, row-major).

    The same definitions and guards as `_sample_angles` with view (0, 0, 1), written on whole
    arrays: $n \\times v = (n_y, -n_x, 0)$, $n \\cdot v = n_z$, and the tangent-plane projections
    $l_t = l - (n \\cdot l) n$, $v_t = v - n_z n$. Normals and lights are normalised here.
    `lights`: `(K, 3)` distant, or `(K, P, 3)` per pixel (near lamps).
    """
    dtype = normals.dtype
    # (1, P) planes read in place: a transpose to (3, P) would be a pass of its own
    nx, ny, nz = (normals[..., c].reshape(1, -1) for c in range(3))
    inv = 1 / jnp.maximum(jnp.sqrt(nx * nx + ny * ny + nz * nz), jnp.asarray(1e-12, dtype))
    nx, ny, nz = nx * inv, ny * inv, nz * inv
    lights = lights / jnp.linalg.norm(lights, axis=-1, keepdims=True)
    if lights.ndim == 2:
        lx, ly, lz = lights[:, 0:1], lights[:, 1:2], lights[:, 2:3]  # (K, 1)
    else:
        lx, ly, lz = lights[..., 0], lights[..., 1], lights[..., 2]  # (K, P)
    ndl = nx * lx + ny * ly + nz * lz
    theta_i = _angle_elementwise(ny * lz - nz * ly, nz * lx - nx * lz, nx * ly - ny * lx, ndl)
    theta_r = _angle_elementwise(ny, -nx, jnp.zeros_like(nx), nz)
    ltx, lty, ltz = lx - ndl * nx, ly - ndl * ny, lz - ndl * nz
    vtx, vty, vtz = -nz * nx, -nz * ny, 1 - nz * nz
    delta = _angle_elementwise(lty * vtz - ltz * vty, ltz * vtx - ltx * vtz,
                               ltx * vty - lty * vtx, ltx * vtx + lty * vty + ltz * vtz)
    return theta_i, theta_r, delta, ndl


def _sample_angles(n, light, view):
    """(θi, θr, Δα) for one unit normal `n` (3,), unit light (3,), unit view (3,)."""
    theta_i = _angle(n, light)
    theta_r = _angle(n, view)
    light_t = light - jnp.dot(n, light) * n
    view_t = view - jnp.dot(n, view) * n
    return jnp.stack([theta_i, theta_r, _angle(light_t, view_t)])


def usable_normals(normals) -> np.ndarray:
    """`(H, W)` bool on the host: normals that are finite and not of (near) zero length
    (squared length above 1e-12). The others have no angles: their samples are not fitted or
    scored."""
    n = np.asarray(normals)
    with np.errstate(invalid="ignore", over="ignore"):
        sq = np.sum(n * n, axis=-1)
    return np.isfinite(sq) & (sq > 1e-12)


def pixel_coordinates(h: int, w: int, dtype=jnp.float32) -> Float[Array, "H W 2"]:
    """`(H, W, 2)` pixel positions (x, y) scaled to [-1, 1], x right and y up (row 0 at y=1)."""
    x = 2 * np.arange(w) / max(w - 1, 1) - 1
    y = 1 - 2 * np.arange(h) / max(h - 1, 1)
    xx, yy = np.meshgrid(x, y)
    return jnp.asarray(np.stack([xx, yy], axis=-1), dtype)


def brdf_features(
    normals: Float[ArrayLike, "H W 3"],
    lights: Float[ArrayLike, "K 3"] | Float[ArrayLike, "K H W 3"],
) -> Float[Array, "K H W 5"]:
    """The per-sample BRDF coordinates (θi, θr, Δα, x, y) of every pixel under every light.

    **Arguments:**
    - `normals`: `(H, W, 3)` unit normals in the camera frame (normalised here).
    - `lights`: `(K, 3)` directions toward distant lights, or `(K, H, W, 3)` per pixel (near
      lamps, e.g. `NearResult.lights`); normalised here.

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
    if not (lights.ndim == 2 and lights.shape[-1] == 3
            or lights.shape[1:] == normals.shape and lights.ndim == 4):
        raise ValueError(f"lights must be (K, 3) or (K, H, W, 3) with the normals' (H, W) = "
                         f"{normals.shape[:2]}, got shape {lights.shape}")
    return _features(normals, lights)


@jax.jit
def _features(normals, lights):
    h, w, _ = normals.shape
    k = lights.shape[0]
    if lights.ndim == 4:  # per pixel: (K, P, 3)
        lights = lights.reshape(k, h * w, 3)
    theta_i, theta_r, delta, _ = _angles_elementwise(normals, lights)
    angles = jnp.stack([theta_i, jnp.broadcast_to(theta_r, theta_i.shape), delta], axis=-1)
    xy = jnp.broadcast_to(pixel_coordinates(h, w, normals.dtype), (k, h, w, 2))
    return jnp.concatenate([angles.reshape(k, h, w, 3), xy], axis=-1)
