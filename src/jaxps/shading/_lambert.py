"""Lambert's law, forward: images from normals, albedo and lights."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

__all__ = ["render_lambertian"]


def render_lambertian(
    normals: Float[ArrayLike, "H W 3"],
    albedo: Float[ArrayLike, "H W *C"],
    lights: Float[ArrayLike, "K 3"] | Float[ArrayLike, "K H W 3"],
) -> Float[Array, "K H W *C"]:
    """Render $I_k = \\rho \\max(0, l_k \\cdot n)$ (attached shadows clamp at 0, no cast shadows).

    **Arguments:**
    - `normals`: `(H, W, 3)` unit normals, floating point.
    - `albedo`: `(H, W)` grey or `(H, W, C)` colour.
    - `lights`: `(K, 3)` distant lights or `(K, H, W, 3)` per-pixel lights (not normalised
      here, so a light vector's length acts as its intensity). Distant lights must be finite
      (checked unless traced); per-pixel lights are not checked (that would be a pass over
      the image).

    **Returns:** `(K, H, W)` or `(K, H, W, C)` images in the dtype of `normals`.

    **Raises:** `ValueError` for mismatched shapes, integer normals or non-finite distant
    lights.
    """
    normals = jnp.asarray(normals)
    if not jnp.issubdtype(normals.dtype, jnp.floating):
        raise ValueError(f"normals must be floating point, got dtype {normals.dtype}")
    if (np.ndim(lights) == 2 and not isinstance(lights, jax.core.Tracer)
            and not np.all(np.isfinite(np.asarray(lights)))):
        raise ValueError("lights contain NaN or Inf")
    albedo = jnp.asarray(albedo, normals.dtype)
    lights = jnp.asarray(lights, normals.dtype)
    if normals.ndim != 3 or normals.shape[-1] != 3:
        raise ValueError(f"normals must be (H, W, 3), got {normals.shape}")
    if albedo.shape[:2] != normals.shape[:2] or albedo.ndim not in (2, 3):
        raise ValueError(
            f"albedo must be (H, W) or (H, W, C) with (H, W) = {normals.shape[:2]}, "
            f"got {albedo.shape}"
        )
    if lights.shape[-1] != 3 or lights.ndim not in (2, 4):
        raise ValueError(f"lights must be (K, 3) or (K, H, W, 3), got {lights.shape}")
    if lights.ndim == 4 and lights.shape[1:3] != normals.shape[:2]:
        raise ValueError(f"per-pixel lights {lights.shape} do not match normals {normals.shape}")
    return _render(normals, albedo, lights)


@jax.jit
def _render(normals, albedo, lights):
    # l . n as three multiply-adds over whole planes: one fused loop over the image, where
    # an einsum was a dot XLA-CPU ran on its own, then another pass for the clamp
    # (`benchmarks/bench_evaluate.py`, the render_lambertian rows)
    n = [normals[..., c] for c in range(3)]
    if lights.ndim == 2:
        shade = sum(lights[:, c, None, None] * n[c][None] for c in range(3))
    else:
        shade = sum(lights[..., c] * n[c][None] for c in range(3))
    shade = jnp.maximum(shade, 0)
    if albedo.ndim == 3:
        return shade[..., None] * albedo[None]
    return shade * albedo[None]
