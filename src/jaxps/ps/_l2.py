"""Calibrated Lambertian photometric stereo: a one-pixel least-squares kernel lifted with vmap.

Woodham, "Photometric method for determining surface orientation from multiple images",
Optical Engineering 19(1), 1980. For a pixel with intensities $i \\in \\mathbb{R}^K$ under unit
lights $L \\in \\mathbb{R}^{K \\times 3}$, Lambert's law $i = L b$ with $b = \\rho n$ gives the
least-squares $b = (L^T W L)^{-1} L^T W i$ over the usable samples ($W$ a 0/1 diagonal); albedo
$\\rho = |b|$ and normal $n = b / |b|$. When every sample of a pixel is usable and the lights are
shared, $b = L^+ i$ with the pseudo-inverse $L^+$ computed once for the whole image.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..core._linalg import REL_DET_MIN, solve3
from ..core._status import Status, first_status

__all__ = ["PSResult", "ps_l2"]


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


def _pixel_l2(i, usable, inside, lights, pinv, thresholds, weighted):
    """Solve one pixel. `i` is `(K, C)` (C=1 for grey), `usable` `(K,)` bool, `inside` the
    pixel's mask bit, `lights` `(K, 3)`.

    `pinv` is the shared `(3, K)` pseudo-inverse (None for per-pixel lights), used when every
    sample is usable. With `weighted=False` (static) it is used for every pixel and the
    per-pixel normal equations are skipped; the last output says whether this pixel dropped a
    sample and so needs the weighted solve. `thresholds` = (dark, saturation, shadow) as traced
    scalars. Sums over the K samples and 3 axes are unrolled in Python (K is static and small)
    so that, once vmapped, every operation is elementwise over pixels (see `solve3`).

    Returns the final (normal, albedo, status, n_used, residual, needs_weights): failed and
    masked pixels already carry their status and the defaults normal (0, 0, 1), albedo 0.
    """
    dark, saturation, shadow = thresholds
    dtype = i.dtype
    ks = range(i.shape[0])
    finite = [jnp.all(jnp.isfinite(i[k])) for k in ks]
    ik = [jnp.where(finite[k], i[k], 0) for k in ks]  # (C,) each
    grey = [jnp.mean(x) for x in ik]
    unsat = [finite[k] & usable[k] & ~jnp.any(ik[k] >= saturation) for k in ks]
    used = [unsat[k] & (grey[k] >= shadow) for k in ks]
    w = [u.astype(dtype) for u in used]

    # Normal equations A b = r with A = L^T W L, r = L^T W i; or b = L^+ i when all are used.
    # Without per-pixel weights A = L^T L is built from the unbatched lights: computed once.
    wl = [[w[k] * lights[k, p] for p in range(3)] for k in ks] if weighted else lights
    a = [[sum(wl[k][p] * lights[k, q] for k in ks) for q in range(3)] for p in range(3)]
    grey_only = i.shape[-1] == 1
    r = None if grey_only and not weighted else [sum(wl[k][p] * ik[k] for k in ks)
                                                 for p in range(3)]  # (C,) each
    if pinv is not None:
        b_shared = jnp.stack([sum(pinv[p, k] * ik[k] for k in ks) for p in range(3)])
    if not weighted:
        b, rel_det = b_shared, jnp.ones((), dtype)
    else:
        b, rel_det = solve3(a, r)  # (3, C)
        if pinv is not None:
            b = jnp.where(functools.reduce(jnp.logical_and, used), b_shared, b)

    bg = [jnp.mean(b[p]) for p in range(3)]
    rho_grey = jnp.sqrt(bg[0] ** 2 + bg[1] ** 2 + bg[2] ** 2)
    inv_rho = 1 / jnp.where(rho_grey > 0, rho_grey, 1)
    n = [x * inv_rho for x in bg]
    if grey_only:
        rho = rho_grey[None]
    else:
        # Shared normal, per-channel albedo: rho_c = n.(L^T W i_c) / n.(L^T W L) n.
        nan = sum(n[p] * a[p][q] * n[q] for p in range(3) for q in range(3))
        rho = sum(n[p] * r[p] for p in range(3)) / jnp.maximum(nan, jnp.finfo(dtype).tiny)

    shade = [lights[k, 0] * n[0] + lights[k, 1] * n[1] + lights[k, 2] * n[2] for k in ks]
    n_used = sum(u.astype(jnp.int32) for u in used)
    sq = sum(w[k] * jnp.mean(ik[k] - rho * shade[k]) ** 2 for k in ks)
    residual = jnp.sqrt(sq / jnp.maximum(n_used, 1).astype(dtype))

    n_finite = sum(f.astype(jnp.int32) for f in finite)
    brightest = functools.reduce(jnp.maximum, [jnp.where(finite[k], grey[k], -jnp.inf)
                                               for k in ks])
    status = first_status([
        (~inside, Status.MASKED),
        (n_finite < 3, Status.INVALID),
        (brightest <= dark, Status.DARK),
        (sum(u.astype(jnp.int32) for u in unsat) < 3, Status.SATURATED),
        (n_used < 3, Status.TOO_FEW_LIGHTS),
        (rel_det < REL_DET_MIN, Status.DEGENERATE),
        (~(rho_grey > 0), Status.DARK),
        (n[2] < 0, Status.BACKFACING),
    ])
    ok = status == Status.OK
    normal = jnp.stack([jnp.where(ok, n[0], 0), jnp.where(ok, n[1], 0), jnp.where(ok, n[2], 1)])
    needs_weights = inside & ~functools.reduce(jnp.logical_and, used)
    return (normal, jnp.where(ok, rho, 0), status, n_used, jnp.where(ok, residual, 0),
            needs_weights)


@jax.jit
def ps_l2(images, lights, mask, sample_mask, thresholds):
    """Jitted core. `images` `(K, H, W, C)`; `lights` `(K, 3)` or `(K, H, W, 3)`."""
    k, h, w, c = images.shape
    flat = images.reshape(k, h * w, c)
    usable = sample_mask.reshape(k, h * w)
    inside = mask.reshape(h * w)
    shared = lights.ndim == 2
    if shared:
        pinv = jnp.linalg.pinv(lights)
        light_axis = None
    else:
        lights = lights.reshape(k, h * w, 3)
        lights = lights / jnp.linalg.norm(lights, axis=-1, keepdims=True)
        pinv = None
        light_axis = 1

    def solve(weighted):
        kernel = jax.vmap(functools.partial(_pixel_l2, weighted=weighted),
                          in_axes=(1, 1, 0, light_axis, None, None))
        return kernel(flat, usable, inside, lights, pinv, thresholds)[:5]

    if shared:
        # Most captures have no pixel that drops a sample: the cheap pass with the shared
        # pseudo-inverse is then the answer, and the per-pixel normal equations are skipped.
        *fast, needs_weights = jax.vmap(
            functools.partial(_pixel_l2, weighted=False),
            in_axes=(1, 1, 0, None, None, None))(flat, usable, inside, lights, pinv, thresholds)
        out = jax.lax.cond(jnp.any(needs_weights), lambda: solve(True), lambda: tuple(fast))
    else:
        out = solve(True)
    normals, albedo, status, n_used, residual = out
    return PSResult(normals.reshape(h, w, 3), albedo.reshape(h, w, c), status.reshape(h, w),
                    n_used.reshape(h, w), residual.reshape(h, w))
