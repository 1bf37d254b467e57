"""Near point lights: per-pixel light directions and fall-off over a surface.

A scanner's flashes sit about a metre from the face, so the direction and the irradiance of each
light change across the face: with light $k$ at position $P_k$ and the surface point $X$ of a
pixel, $l_k(X) = (P_k - X)/|P_k - X|$ and the irradiance falls off as
$a_k(X) = (|P_k| / |P_k - X|)^2$ (1 at the origin: the image centre at depth 0), optionally times
an LED's $\\cos^{\\mu}$ lobe around its axis (towards the origin). Both depend on the depth of
$X$, which PS itself estimates: `jaxps.near_photometric_stereo` alternates the two.

Frame: DESIGN.md camera frame (x right, y up, z toward the viewer), orthographic; the pixel at
row r, column c sits at $x = (c - c_0)\\,s$, $y = (r_0 - r)\\,s$ with $s$ = `pixel_size` and
$(r_0, c_0)$ the pixel where the camera axis meets the image (`centre`; by default the image's
centre, $((H-1)/2, (W-1)/2)$), and $z$ is the height. Positions and heights share the unit of
`pixel_size`. For a crop of a frame, `centre` is the frame's centre in the crop's pixels, so that
the points, and so the lights, stay where they were in the frame.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..core._host import has_value, positive_scalar

__all__ = ["near_light_field", "surface_points"]


def surface_points(height: Float[ArrayLike, "H W"], *, pixel_size: float = 1.0,
                   centre: tuple[float, float] | None = None) -> Float[Array, "H W 3"]:
    """Camera-frame points `(H, W, 3)` of a height map (orthographic, origin at `centre`).

    **Arguments:**
    - `height`: `(H, W)` z toward the viewer, in the unit of `pixel_size`.
    - `pixel_size`: size of one pixel in that unit.
    - `centre`: `(row, column)` of the origin, the pixel (fractional, and possibly outside
      this image) where the camera axis meets it; default the image's centre,
      `((H - 1) / 2, (W - 1) / 2)`. For a crop whose top-left corner is at `(top, left)` in an
      `(H0, W0)` frame: `((H0 - 1) / 2 - top, (W0 - 1) / 2 - left)`.

    **Returns:** `(H, W, 3)` points $(x, y, z)$ in the dtype of `height`.
    """
    height = jnp.asarray(height)
    if height.ndim != 2:
        raise ValueError(f"height must be (H, W), got shape {height.shape}")
    if not jnp.issubdtype(height.dtype, jnp.floating):
        height = height.astype(jnp.float32)
    if not positive_scalar(pixel_size):
        raise ValueError(f"pixel_size must be positive and finite, got {pixel_size}")
    h, w = height.shape
    row, col = _centre(centre, h, w)
    x = (jnp.arange(w, dtype=height.dtype) - col) * pixel_size
    y = (row - jnp.arange(h, dtype=height.dtype)) * pixel_size
    xx, yy = jnp.meshgrid(x, y)
    return jnp.stack([xx, yy, height], axis=-1)


def _centre(centre, h, w) -> tuple[float, float]:
    """`surface_points`' `centre` as two floats, checked (None: the image's centre)."""
    if centre is None:
        return (h - 1) / 2, (w - 1) / 2
    try:
        c = np.asarray(centre, np.float64)
    except (TypeError, ValueError):
        c = np.full(1, np.nan)
    if c.shape != (2,) or not np.all(np.isfinite(c)):
        raise ValueError(f"centre must be a finite (row, column) pair, got {centre!r}")
    return float(c[0]), float(c[1])


@functools.partial(jax.jit, static_argnames="mu")
def _field(positions, points, mu):
    """The field, written per component: `(K, H, W)` planes of x, y and z, stacked once at the
    end. As `(K, H, W, 3)` arrays with a norm over the last axis and an `einsum` for the lobe,
    and `cos ** mu` computed everywhere under a traced `where`, a 1 MP field of five lights
    took 92 ms (scratch), most of `near_photometric_stereo`'s time. `mu` is static: with
    mu = 0 no power is computed."""
    tiny = jnp.finfo(points.dtype).tiny
    d = [positions[:, c, None, None] - points[None, ..., c] for c in range(3)]  # (K, H, W) each
    dist = jnp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    safe = jnp.maximum(dist, tiny)
    lights = [dc / safe for dc in d]
    r0 = jnp.linalg.norm(positions, axis=-1)[:, None, None]
    falloff = (r0 / safe) ** 2
    if mu > 0:  # LED lobe: cos(angle between -l and the light's axis, towards the origin)^mu
        axis = -positions / jnp.maximum(r0[:, 0], tiny)  # (K, 3)
        cos_axis = jnp.maximum(-sum(lights[c] * axis[:, c, None, None] for c in range(3)), 0)
        falloff = falloff * cos_axis ** jnp.asarray(mu, points.dtype)
    return jnp.stack(lights, axis=-1), falloff


def near_light_field(
    positions: Float[ArrayLike, "K 3"],
    points: Float[ArrayLike, "H W 3"],
    *,
    mu: float = 0.0,
) -> tuple[Float[Array, "K H W 3"], Float[Array, "K H W"]]:
    """Per-pixel unit light directions and relative irradiance of near point lights.

    $l_k = (P_k - X)/|P_k - X|$, $a_k = (|P_k|/|P_k - X|)^2 \\cos^{\\mu}\\theta_k$ with
    $\\theta_k$ the angle off the light's axis (pointing at the origin); $a_k = 1$ at the origin
    for an isotropic light.

    **Arguments:**
    - `positions`: `(K, 3)` light positions in the camera frame (e.g. 1.2 m from the face).
    - `points`: `(H, W, 3)` surface points (`surface_points(height, pixel_size=...)`).
    - `mu`: LED anisotropy exponent (0 = isotropic point light).

    **Returns:** `lights` `(K, H, W, 3)` unit vectors and `falloff` `(K, H, W)`, in the dtype of
    `points`.
    """
    points = jnp.asarray(points)
    if not jnp.issubdtype(points.dtype, jnp.floating):
        points = points.astype(jnp.float32)
    positions = jnp.asarray(positions, points.dtype)
    if positions.ndim != 2 or positions.shape[-1] != 3:
        raise ValueError(f"positions must be (K, 3), got shape {positions.shape}")
    if points.ndim != 3 or points.shape[-1] != 3:
        raise ValueError(f"points must be (H, W, 3), got shape {points.shape}")
    if has_value(positions):  # inside `jit` or `vmap` the caller keeps them valid
        if not bool(jnp.all(jnp.isfinite(positions))):
            raise ValueError("positions contain NaN or Inf")
        if bool(jnp.any(jnp.linalg.norm(positions, axis=-1) == 0)):
            raise ValueError("positions must not be at the origin (the image centre at depth 0)")
    if not (np.isfinite(mu) and mu >= 0):
        raise ValueError(f"mu must be a finite non-negative number, got {mu}")
    return _field(positions, points, mu=float(mu))
