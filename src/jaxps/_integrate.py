"""Normal integration: from a normal map to a height map, and back.

Gradients follow DESIGN.md: $p = \\partial z/\\partial x = -n_x/n_z$ and
$q = \\partial z/\\partial y = -n_y/n_z$ with y up, so one row down is $-1$ in y:
$\\partial z/\\partial \\mathrm{col} = p$ and $\\partial z/\\partial \\mathrm{row} = -q$.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

__all__ = ["INTEGRATION_METHODS", "gradients_from_normals", "integrate", "normals_from_height"]

INTEGRATION_METHODS: tuple[str, ...] = ("fc",)

# n_z is floored here before dividing, so a grazing normal gives a gradient of at most ~20.
_MIN_NZ = 0.05


def _check_normals(normals, mask):
    normals = jnp.asarray(normals)
    if normals.ndim != 3 or normals.shape[-1] != 3:
        raise ValueError(f"normals must be (H, W, 3), got shape {normals.shape}")
    if not jnp.issubdtype(normals.dtype, jnp.floating):
        raise ValueError(f"normals must be floating point, got {normals.dtype}")
    h, w, _ = normals.shape
    if mask is None:
        mask = jnp.ones((h, w), bool)
    else:
        if np.shape(mask) != (h, w):
            raise ValueError(f"mask must have shape (H, W) = {(h, w)}, got {np.shape(mask)}")
        mask = jnp.asarray(mask, bool)
        if not bool(jnp.any(mask)):
            raise ValueError("mask is empty: no pixel to integrate")
    return normals, mask


@jax.jit
def gradients_from_normals(
    normals: Float[Array, "H W 3"], mask: Bool[Array, "H W"]
) -> tuple[Float[Array, "H W"], Float[Array, "H W"]]:
    """Surface gradients `(p, q)` = (dz/dx, dz/dy), y up; 0 outside `mask` and for NaN normals."""
    nx, ny, nz = normals[..., 0], normals[..., 1], normals[..., 2]
    nz = jnp.maximum(nz, _MIN_NZ)
    ok = mask & jnp.all(jnp.isfinite(normals), axis=-1)
    p = jnp.where(ok, -nx / nz, 0)
    q = jnp.where(ok, -ny / nz, 0)
    return p, q


@jax.jit
def _frankot_chellappa(p, q, mask):
    h, w = p.shape
    dzdc, dzdr = p, -q
    wc = 2 * jnp.pi * jnp.fft.rfftfreq(w).astype(p.dtype)
    wr = 2 * jnp.pi * jnp.fft.fftfreq(h).astype(p.dtype)
    wr, wc = wr[:, None], wc[None, :]
    fc = jnp.fft.rfft2(dzdc)
    fr = jnp.fft.rfft2(dzdr)
    denom = jnp.where((wc == 0) & (wr == 0), 1, wc**2 + wr**2)
    ctype = fc.dtype
    z_hat = -1j * (wc.astype(ctype) * fc + wr.astype(ctype) * fr) / denom.astype(ctype)
    z_hat = z_hat.at[0, 0].set(0)
    z = jnp.fft.irfft2(z_hat, s=(h, w)).astype(p.dtype)
    offset = jnp.sum(jnp.where(mask, z, 0)) / jnp.maximum(jnp.sum(mask), 1).astype(z.dtype)
    return z - offset


def integrate(
    normals: Float[ArrayLike, "H W 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    method: str = "fc",
    pixel_size: float = 1.0,
) -> Float[Array, "H W"]:
    """Integrate a normal map into a height map (orthographic camera).

    `"fc"`: Frankot & Chellappa, "A method for enforcing integrability in shape from shading
    algorithms", IEEE TPAMI 10(4), 1988 — the least-squares integrable surface in the Fourier
    basis, $\\hat z = -i(\\omega_x \\hat p + \\omega_y \\hat q) / (\\omega_x^2 + \\omega_y^2)$,
    computed with a real FFT. Borders: the gradient field is treated as periodic over the
    whole image (no padding). Mask: gradients outside `mask` (and of NaN normals) are set to 0,
    so the surface is flat there and the mask's outline can bend the result; `n_z` is floored
    at 0.05 so grazing normals cannot blow up. The height's mean over `mask` is 0.

    **Arguments:**
    - `normals`: `(H, W, 3)` unit normals, n_z >= 0.
    - `mask`: `(H, W)` bool, valid pixels (default: all).
    - `method`: one of `jaxps.INTEGRATION_METHODS`.
    - `pixel_size`: the size of a pixel in the height's unit (default 1: pixel units).

    **Returns:** `(H, W)` height in the dtype of `normals`, z toward the viewer.
    """
    if method not in INTEGRATION_METHODS:
        raise ValueError(f"method must be one of {INTEGRATION_METHODS}, got {method!r}")
    if not (np.isfinite(pixel_size) and pixel_size > 0):
        raise ValueError(f"pixel_size must be positive and finite, got {pixel_size}")
    normals, mask = _check_normals(normals, mask)
    dtype = normals.dtype
    p, q = gradients_from_normals(normals, mask)
    z = _frankot_chellappa(p, q, mask)
    return (z * pixel_size).astype(dtype)


def normals_from_height(
    z: Float[ArrayLike, "H W"], *, pixel_size: float = 1.0
) -> Float[Array, "H W 3"]:
    """Unit normals of a height map, from central differences (one-sided at the borders).

    **Arguments:**
    - `z`: `(H, W)` height, toward the viewer, in the unit of `pixel_size`.
    - `pixel_size`: the size of a pixel in the height's unit.

    **Returns:** `(H, W, 3)` unit normals $(-p, -q, 1)/\\sqrt{1+p^2+q^2}$ in the dtype of `z`.
    """
    z = jnp.asarray(z)
    if z.ndim != 2 or min(z.shape) < 2:
        raise ValueError(f"z must be a 2-D height map of at least 2x2, got shape {z.shape}")
    if not jnp.issubdtype(z.dtype, jnp.floating):
        z = z.astype(jnp.float32)
    return _normals_from_height(z, jnp.asarray(pixel_size, z.dtype))


@jax.jit
def _normals_from_height(z, pixel_size):
    dzdr, dzdc = jnp.gradient(z)
    p = dzdc / pixel_size
    q = -dzdr / pixel_size
    n = jnp.stack([-p, -q, jnp.ones_like(p)], axis=-1)
    return n / jnp.linalg.norm(n, axis=-1, keepdims=True)
