"""Which light layouts can self-calibrate their flash strengths: `flash_visibility`.

A module of its own, with no optimiser, so that importing `jaxps.ps` (as `load_capture` and
`jaxps reconstruct` do) does not load equinox and optimistix, which only the semi-calibrated
fit uses (`_semicalibrated.py`, imported when that method runs).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

__all__ = ["flash_visibility", "visibility_spectrum"]


def flash_visibility(lights: Float[ArrayLike, "K 3"]) -> Float[Array, ""] | np.floating:
    """How strongly the weakest change of the flash strengths shows in the data: the smallest
    singular value of $\\delta \\mapsto N\\,\\mathrm{diag}(\\delta)\\,L$ over the $K-1$
    directions other than a common scale, for unit lights $L$ `(K, 3)` and $N$ `(K-3, K)`
    orthonormal rows spanning the null space of $L^T$.

    Scaling frame $k$ by $1 + \\delta_k$ leaves every pixel exactly Lambertian (with other
    normals) where $\\mathrm{diag}(\\delta) L = L A$ for some $3 \\times 3$ $A$; $N$ measures the
    part that is not. 0 means some intensities cannot be told from the data at all; for
    lights near the view axis, $\\delta$ linear in the lights' offsets nearly is such a change
    and tilts the recovered face. Scale-free; measured values and what they did on real
    faces are in docs/captures.md ("Which lights can self-calibrate").

    Works on numpy lights (float64, on the host) and inside `jit`. `jax.grad` gives its
    derivative in the lights where that smallest value is simple (a symmetric layout such as
    the five-light cross repeats it, where only one-sided derivatives exist), so a lamp
    layout can be optimised for it.
    """
    return visibility_spectrum(lights)[np.shape(lights)[0] - 2]


def visibility_spectrum(lights):
    """Every singular value of `flash_visibility`'s map, largest first (numpy for host
    lights, JAX for traced ones). For K >= 5 the last is the common scale's 0; K = 4 gives
    the three others."""
    xp = jnp if isinstance(lights, jax.core.Tracer) else np
    lights = lights if xp is jnp else np.asarray(lights, np.float64)
    if lights.ndim != 2 or lights.shape[1] != 3 or lights.shape[0] < 4:
        raise ValueError(f"lights must be (K, 3) with K >= 4, got {lights.shape}")
    norms = xp.linalg.norm(lights, axis=-1, keepdims=True)
    if xp is np and not (np.isfinite(norms).all() and (norms > 0).all()):
        bad = np.flatnonzero(~(np.isfinite(norms[:, 0]) & (norms[:, 0] > 0))).tolist()
        raise ValueError(f"lights must be finite, non-zero directions; rows {bad} are not")
    lights = lights / norms
    k = lights.shape[0]
    # N^T N is the projector onto the null space of L^T, and N^T keeps lengths, so the
    # projector gives the same singular values as N (and K - 3 more zeros for K = 4). Unlike
    # a full SVD's basis it has a derivative: `jax.grad` passes through `flash_visibility`.
    proj = xp.eye(k) - lights @ xp.linalg.solve(lights.T @ lights, lights.T)
    jac = (proj[:, :, None] * lights[None]).transpose(0, 2, 1).reshape(-1, k)
    return xp.linalg.svd(jac, compute_uv=False)[:min(3 * (k - 3), k)]
