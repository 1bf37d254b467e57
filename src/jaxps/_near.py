"""Near point lights: per-pixel light directions and fall-off, and PS that refines them with depth.

A scanner's flashes sit about a metre from the face, so the direction and the irradiance of each
light change across the face: with light $k$ at position $P_k$ and the surface point $X$ of a
pixel, $l_k(X) = (P_k - X)/|P_k - X|$ and the irradiance falls off as
$a_k(X) = (|P_k| / |P_k - X|)^2$ (1 at the origin: the image centre at depth 0), optionally times
an LED's $\\cos^{\\mu}$ lobe around its axis (towards the origin). Both depend on the depth of $X$,
which PS itself estimates: `near_photometric_stereo` alternates PS with per-pixel lights and
integration of the normals into depth (the scheme of e.g. Clark, "Active photometric stereo",
CVPR 1992; Mecca et al., "Near field photometric stereo with point light sources", SIAM J.
Imaging Sci. 7(4), 2014, solve it jointly; the alternation is the common practical form).

Frame: DESIGN.md camera frame (x right, y up, z toward the viewer), orthographic; the pixel at
row r, column c sits at $x = (c - (W-1)/2)\\,s$, $y = ((H-1)/2 - r)\\,s$ with $s$ = `pixel_size`,
and $z$ is the height. Positions and heights share the unit of `pixel_size`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ._integrate import integrate
from ._l2 import PSResult
from ._ps import photometric_stereo
from ._status import Status

__all__ = ["NearResult", "near_light_field", "near_photometric_stereo", "surface_points"]


class NearResult(NamedTuple):
    """Result of `near_photometric_stereo`.

    - `ps`: the final `PSResult` (normals, albedo, status, ...).
    - `height`: `(H, W)` depth (z toward the viewer) in the unit of `pixel_size`.
    - `lights`: `(K, H, W, 3)` the per-pixel unit lights and `falloff` `(K, H, W)` that the
      final PS solve used (from the height before the last update).
    - `steps`: outer iterations run; `converged`: whether the height change fell below `tol`.
    - `changes`: the max height change of each iteration (`(steps,)` numpy).
    """

    ps: PSResult
    height: Float[Array, "H W"]
    lights: Float[Array, "K H W 3"]
    falloff: Float[Array, "K H W"]
    steps: int
    converged: bool
    changes: np.ndarray


def surface_points(height: Float[ArrayLike, "H W"], *, pixel_size: float = 1.0
                   ) -> Float[Array, "H W 3"]:
    """Camera-frame points `(H, W, 3)` of a height map (orthographic, origin at the image centre).

    **Arguments:**
    - `height`: `(H, W)` z toward the viewer, in the unit of `pixel_size`.
    - `pixel_size`: size of one pixel in that unit.

    **Returns:** `(H, W, 3)` points $(x, y, z)$ in the dtype of `height`.
    """
    height = jnp.asarray(height)
    if height.ndim != 2:
        raise ValueError(f"height must be (H, W), got shape {height.shape}")
    if not jnp.issubdtype(height.dtype, jnp.floating):
        height = height.astype(jnp.float32)
    if not (np.isfinite(pixel_size) and pixel_size > 0):
        raise ValueError(f"pixel_size must be positive and finite, got {pixel_size}")
    h, w = height.shape
    x = (jnp.arange(w, dtype=height.dtype) - (w - 1) / 2) * pixel_size
    y = ((h - 1) / 2 - jnp.arange(h, dtype=height.dtype)) * pixel_size
    xx, yy = jnp.meshgrid(x, y)
    return jnp.stack([xx, yy, height], axis=-1)


@jax.jit
def _field(positions, points, mu):
    d = positions[:, None, None, :] - points[None]  # (K, H, W, 3)
    dist = jnp.linalg.norm(d, axis=-1)
    safe = jnp.maximum(dist, jnp.finfo(points.dtype).tiny)
    lights = d / safe[..., None]
    r0 = jnp.linalg.norm(positions, axis=-1)[:, None, None]
    falloff = (r0 / safe) ** 2
    # LED lobe: cos(angle between -l and the light's axis, which points at the origin)^mu.
    axis = -positions / jnp.maximum(r0[:, 0], jnp.finfo(points.dtype).tiny)
    cos_axis = jnp.maximum(jnp.einsum("khwc,kc->khw", -lights, axis), 0)
    falloff = falloff * jnp.where(mu > 0, cos_axis ** mu, 1)
    return lights, falloff


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
    if not bool(jnp.all(jnp.isfinite(positions))):
        raise ValueError("positions contain NaN or Inf")
    if bool(jnp.any(jnp.linalg.norm(positions, axis=-1) == 0)):
        raise ValueError("positions must not be at the origin (the image centre at depth 0)")
    if not (np.isfinite(mu) and mu >= 0):
        raise ValueError(f"mu must be a finite non-negative number, got {mu}")
    return _field(positions, points, jnp.asarray(mu, points.dtype))


def near_photometric_stereo(
    images: Float[ArrayLike, "K H W *C"],
    positions: Float[ArrayLike, "K 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    height0: float | Float[ArrayLike, "H W"] = 0.0,
    pixel_size: float = 1.0,
    mu: float = 0.0,
    method: str = "l2",
    max_steps: int = 10,
    tol: float | None = None,
    **options,
) -> NearResult:
    """Photometric stereo under near point lights, alternating PS and depth.

    Each step: points from the current height -> per-pixel lights and fall-off
    (`near_light_field`) -> `photometric_stereo(images / falloff, lights, method=method)` ->
    `integrate` (Frankot-Chellappa) -> new height, shifted so its mean over `mask` stays that
    of `height0` (PS fixes shape, not distance). Stops when the largest height change over the
    mask is at most `tol` (default 1e-3 of the mean light distance) or after `max_steps`.

    **Arguments:**
    - `images`: `(K, H, W)` or `(K, H, W, C)` linear intensities in [0, 1].
    - `positions`: `(K, 3)` light positions, in the unit of `pixel_size`.
    - `mask`: `(H, W)` bool object pixels (default all).
    - `height0`: initial height: a scalar (a plane) or `(H, W)`.
    - `pixel_size`, `mu`: see `surface_points`, `near_light_field`.
    - `method`, `**options`: the per-pixel solver and its options (`photometric_stereo`).
    - `max_steps`, `tol`: outer step limit and height tolerance.

    **Returns:** `NearResult`.
    """
    images = jnp.asarray(images)
    if images.ndim not in (3, 4):
        raise ValueError(f"images must be (K, H, W) or (K, H, W, C), got shape {images.shape}")
    k, h, w = images.shape[:3]
    positions = np.asarray(positions, np.float64)
    if positions.shape != (k, 3):
        raise ValueError(f"positions must be (K, 3) = ({k}, 3), got {positions.shape}")
    if int(max_steps) != max_steps or max_steps < 1:
        raise ValueError(f"max_steps must be a positive integer, got {max_steps}")
    dtype = images.dtype if jnp.issubdtype(images.dtype, jnp.floating) else jnp.float32
    mask = jnp.ones((h, w), bool) if mask is None else jnp.asarray(mask, bool)
    if mask.shape != (h, w):
        raise ValueError(f"mask must have shape (H, W) = {(h, w)}, got {mask.shape}")
    height = jnp.broadcast_to(jnp.asarray(height0, dtype), (h, w))
    if not bool(jnp.all(jnp.isfinite(height))):
        raise ValueError("height0 must be finite")
    count = jnp.maximum(jnp.sum(mask), 1).astype(dtype)
    level = jnp.sum(jnp.where(mask, height, 0)) / count
    if tol is None:
        tol = 1e-3 * float(np.mean(np.linalg.norm(positions, axis=-1)))
    changes = []
    converged = False
    for _ in range(int(max_steps)):
        lights, falloff = near_light_field(positions, surface_points(height, pixel_size=pixel_size),
                                           mu=mu)
        fall = falloff if images.ndim == 3 else falloff[..., None]
        corrected = images / jnp.maximum(fall, jnp.finfo(dtype).tiny).astype(images.dtype)
        res = photometric_stereo(corrected, lights, mask=mask, method=method, **options)
        ok = mask & (res.status == Status.OK)
        if not bool(jnp.any(ok)):
            break
        z = integrate(res.normals, mask=ok, pixel_size=pixel_size)
        z = z - jnp.sum(jnp.where(mask, z, 0)) / count + level
        new = jnp.where(mask, z, height).astype(dtype)
        change = float(jnp.max(jnp.where(mask, jnp.abs(new - height), 0)))
        changes.append(change)
        height = new
        if change <= tol:
            converged = True
            break
    return NearResult(res, height, lights, falloff, len(changes), converged,
                      np.asarray(changes))
