"""Photometric stereo under near point lights: alternate PS with per-pixel lights and depth.

The per-pixel lights and fall-off of near point lights (`jaxps.lights`, `near_light_field`)
depend on the depth of each surface point, which PS itself estimates:
`near_photometric_stereo` alternates PS with per-pixel lights and integration of the normals
into depth (the scheme of e.g. Clark, "Active photometric stereo", CVPR 1992; Mecca et al.,
"Near field photometric stereo with point light sources", SIAM J. Imaging Sci. 7(4), 2014, solve
it jointly; the alternation is the common practical form). Frame and units: see
`jaxps.lights.surface_points`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ..core._status import Status
from ..integration import INTEGRATION_METHODS, integrate
from ..lights._near import _centre, near_light_field, surface_points
from ._l2 import PSResult, working_dtype
from ._photometric_stereo import _check_images, photometric_stereo

__all__ = ["NearResult", "near_photometric_stereo"]


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


def near_photometric_stereo(
    images: Float[ArrayLike, "K H W *C"],
    positions: Float[ArrayLike, "K 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    height0: float | Float[ArrayLike, "H W"] = 0.0,
    pixel_size: float = 1.0,
    centre: tuple[float, float] | None = None,
    mu: float = 0.0,
    method: str = "l2",
    integration: str = "lsq",
    max_steps: int = 10,
    tol: float | None = None,
    **options,
) -> NearResult:
    """Photometric stereo under near point lights, alternating PS and depth.

    Each step: points from the current height -> per-pixel lights and fall-off
    (`near_light_field`) -> `photometric_stereo(images / falloff, lights, method=method)` ->
    `integrate(method=integration)` -> new height, shifted so its mean over `mask` stays that
    of `height0` (PS fixes shape, not distance). Stops when the largest height change over the
    mask is at most `tol` (default 1e-3 of the mean light distance) or after `max_steps`.

    **Arguments:**
    - `images`: `(K, H, W)` or `(K, H, W, C)` linear intensities in [0, 1].
    - `positions`: `(K, 3)` light positions, in the unit of `pixel_size`.
    - `mask`: `(H, W)` bool object pixels (default all).
    - `height0`: initial height: a scalar (a plane) or `(H, W)`.
    - `pixel_size`, `centre`, `mu`: see `surface_points`, `near_light_field`. For a crop of
      the frame the positions were measured in, `centre` is that frame's centre in the crop's
      pixels (`surface_points`).
    - `method`, `**options`: the per-pixel solver and its options (`photometric_stereo`).
    - `integration`: `integrate`'s method for each step's height. `"lsq"` (least squares over
      the pixels solved) by default: on a synthetic face its height was closer to the truth
      than Frankot–Chellappa's (`"fc"`, the default until the twenty-seventh session, whose
      periodic boundary bends the outline) by 1.4x with noise and 50x without, for the same
      normals; `"fc"` took a third of the time at 1 MP (docs/robust.md, "Near point
      lights"). Pass `"fc"` where only the normals matter.
    - `max_steps`, `tol`: outer step limit and height tolerance.

    **Returns:** `NearResult`, in the dtype of `images` (float16 and bfloat16 frames are solved
    in float32).
    """
    images = jnp.asarray(_check_images(images)[0])  # floating (K, H, W[, C]), else a ValueError
    if working_dtype(images.dtype) != images.dtype:
        # A lamp a metre away is ~1e6 square millimetres off, past float16's range (the fall-off
        # was NaN): solve in float32, answer in the images' dtype.
        out = near_photometric_stereo(
            images.astype(working_dtype(images.dtype)), positions, mask=mask, height0=height0,
            pixel_size=pixel_size, centre=centre, mu=mu, method=method, integration=integration,
            max_steps=max_steps, tol=tol, **options)
        dt = images.dtype
        ps = out.ps._replace(normals=out.ps.normals.astype(dt), albedo=out.ps.albedo.astype(dt),
                             residual=out.ps.residual.astype(dt))
        return out._replace(ps=ps, height=out.height.astype(dt), lights=out.lights.astype(dt),
                            falloff=out.falloff.astype(dt))
    k, h, w = images.shape[:3]
    positions = np.asarray(positions, np.float64)
    if positions.shape != (k, 3):
        raise ValueError(f"positions must be (K, 3) = ({k}, 3), got {positions.shape}")
    if int(max_steps) != max_steps or max_steps < 1:
        raise ValueError(f"max_steps must be a positive integer, got {max_steps}")
    if tol is not None and not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be positive and finite (or None), got {tol}")
    if integration not in INTEGRATION_METHODS:
        raise ValueError(f"integration must be one of {INTEGRATION_METHODS}, got "
                         f"{integration!r}")
    _centre(centre, h, w)  # a bad centre fails here, before any solve
    if np.shape(height0) not in ((), (h, w)):
        raise ValueError(f"height0 must be a scalar or (H, W) = {(h, w)}, got shape "
                         f"{np.shape(height0)}")
    dtype = images.dtype
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
        lights, falloff = near_light_field(positions, surface_points(height, pixel_size=pixel_size,
                                                                  centre=centre), mu=mu)
        fall = falloff if images.ndim == 3 else falloff[..., None]
        corrected = images / jnp.maximum(fall, jnp.finfo(dtype).tiny).astype(images.dtype)
        res = photometric_stereo(corrected, lights, mask=mask, method=method, **options)
        ok = mask & (res.status == Status.OK)
        if not bool(jnp.any(ok)):
            break
        z = integrate(res.normals, mask=ok, pixel_size=pixel_size, method=integration)
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
