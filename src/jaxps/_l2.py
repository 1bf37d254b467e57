"""Calibrated Lambertian photometric stereo: a one-pixel least-squares kernel lifted with vmap.

Woodham, "Photometric method for determining surface orientation from multiple images",
Optical Engineering 19(1), 1980. For a pixel with intensities $i \\in \\mathbb{R}^K$ under unit
lights $L \\in \\mathbb{R}^{K \\times 3}$, Lambert's law $i = L b$ with $b = \\rho n$ gives the
least-squares $b = (L^T W L)^{-1} L^T W i$ over the usable samples ($W$ a 0/1 diagonal); albedo
$\\rho = |b|$ and normal $n = b / |b|$. When every sample of a pixel is usable and the lights are
shared, $b = L^+ i$ with the pseudo-inverse $L^+$ computed once for the whole image.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ._status import Status

__all__ = ["PSResult", "ps_l2", "solve3"]

# det(A) / (trace(A)/3)^3 below this marks the usable lights as not spanning 3-D
# (roughly a light-matrix condition number above 1e3).
_REL_DET_MIN = 1e-6


class PSResult(NamedTuple):
    """Per-pixel photometric-stereo result.

    - `normals`: `(H, W, 3)` unit normals (camera frame, n_z >= 0 where `status == 0`).
    - `albedo`: `(H, W)` for grey stacks, `(H, W, C)` for colour stacks.
    - `status`: `(H, W)` int32 codes from `jaxps.Status` (0 = ok).
    - `n_used`: `(H, W)` int32 number of samples the solve used.
    - `residual`: `(H, W)` RMS of $i - \\rho\\, l \\cdot n$ over the used samples (grey mean for
      colour).
    - `info`: method-specific extras (e.g. step counts, per-frame light intensities), or None.
    """

    normals: Float[Array, "H W 3"]
    albedo: Float[Array, "H W *C"]
    status: Int[Array, "H W"]
    n_used: Int[Array, "H W"]
    residual: Float[Array, "H W"]
    info: dict | None = None


def solve3(a: Array, r: Array) -> tuple[Array, Array]:
    """Solve the symmetric 3x3 system `a x = r` (r may be `(3,)` or `(3, C)`) by cofactors.

    Returns the solution and det(a) / (trace(a)/3)^3, a scale-free conditioning measure.
    Written out so that a vmapped batch stays elementwise and fuses (no batched LAPACK call).
    """
    c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    c11 = a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]
    c12 = a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]
    c22 = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
    cof = jnp.stack([jnp.stack([c00, c01, c02]), jnp.stack([c01, c11, c12]),
                     jnp.stack([c02, c12, c22])])
    scale = jnp.trace(a) / 3
    rel_det = det / jnp.maximum(scale**3, jnp.finfo(a.dtype).tiny)
    safe_det = jnp.where(jnp.abs(det) > 0, det, 1)
    return cof @ r / safe_det, rel_det


def _pixel_l2(i, usable, lights, pinv, all_shared, thresholds):
    """Solve one pixel. `i` is `(K, C)` (C=1 for grey), `usable` `(K,)` bool, `lights` `(K, 3)`.

    `pinv` is the shared `(3, K)` pseudo-inverse (used when every sample is usable and
    `all_shared`), and `thresholds` = (dark, saturation, shadow) as traced scalars.
    """
    dark, saturation, shadow = thresholds
    finite = jnp.all(jnp.isfinite(i), axis=-1)
    i = jnp.where(finite[:, None], i, 0)
    grey = jnp.mean(i, axis=-1)
    saturated = jnp.any(i >= saturation, axis=-1)
    unsat = finite & ~saturated & usable
    used = unsat & (grey >= shadow)
    w = used.astype(i.dtype)

    a = jnp.einsum("k,ki,kj->ij", w, lights, lights)
    r = lights.T @ (w[:, None] * i)  # (3, C)
    b_weighted, rel_det = solve3(a, r)
    every = jnp.all(used) & all_shared
    b = jnp.where(every, pinv @ i, b_weighted)  # (3, C)

    b_grey = jnp.mean(b, axis=-1)
    rho_grey = jnp.linalg.norm(b_grey)
    n = b_grey / jnp.where(rho_grey > 0, rho_grey, 1)
    # Shared normal, per-channel albedo: rho_c = n.(L^T W i_c) / n.(L^T W L) n (equals |b| in grey).
    rho = (n @ r) / jnp.maximum(n @ a @ n, jnp.finfo(i.dtype).tiny)

    shade = lights @ n  # (K,)
    res = jnp.mean(i - rho[None, :] * shade[:, None], axis=-1)
    n_used = jnp.sum(used)
    residual = jnp.sqrt(jnp.sum(w * res**2) / jnp.maximum(n_used, 1).astype(i.dtype))

    n_finite = jnp.sum(finite)
    status = jnp.select(
        [
            n_finite < 3,
            jnp.max(jnp.where(finite, grey, -jnp.inf)) <= dark,
            jnp.sum(unsat) < 3,
            n_used < 3,
            rel_det < _REL_DET_MIN,
            ~(rho_grey > 0),
            n[2] < 0,
        ],
        [Status.INVALID, Status.DARK, Status.SATURATED, Status.TOO_FEW_LIGHTS,
         Status.DEGENERATE, Status.DARK, Status.BACKFACING],
        Status.OK,
    )
    return n, rho, status, n_used, residual


@jax.jit
def ps_l2(images, lights, mask, sample_mask, thresholds):
    """Jitted core. `images` `(K, H, W, C)`; `lights` `(K, 3)` or `(K, H, W, 3)`."""
    k, h, w, c = images.shape
    flat = images.reshape(k, h * w, c)
    usable = sample_mask.reshape(k, h * w)
    shared = lights.ndim == 2
    if shared:
        pinv = jnp.linalg.pinv(lights)
        light_axis = None
    else:
        lights = lights.reshape(k, h * w, 3)
        lights = lights / jnp.linalg.norm(lights, axis=-1, keepdims=True)
        pinv = jnp.zeros((3, k), images.dtype)
        light_axis = 1
    kernel = jax.vmap(_pixel_l2, in_axes=(1, 1, light_axis, None, None, None))
    n, rho, status, n_used, residual = kernel(flat, usable, lights, pinv, shared, thresholds)

    keep = mask.reshape(-1) & (status == Status.OK)
    status = jnp.where(mask.reshape(-1), status, Status.MASKED).astype(jnp.int32)
    normals = jnp.where(keep[:, None], n, jnp.array([0, 0, 1], images.dtype))
    albedo = jnp.where(keep[:, None], rho, 0)
    residual = jnp.where(keep, residual, 0)
    return PSResult(
        normals.reshape(h, w, 3),
        albedo.reshape(h, w, c),
        status.reshape(h, w),
        n_used.astype(jnp.int32).reshape(h, w),
        residual.reshape(h, w),
    )


