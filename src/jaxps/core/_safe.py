"""Square roots, divisions and lengths whose gradients stay finite where the value is 0.

The `jnp.where` trap: `jnp.where(x > 0, jnp.sqrt(x), 0)` has the right value at `x = 0`, but
its gradient is NaN there, because the discarded branch still sends back the infinite slope of
the square root (times 0). The fix is to give the unsafe operation a safe input first, as
jax-md's `safe_mask` does. Every pixel that fails (dark, masked, no usable sample) goes
through these, so that it gets a zero gradient, not NaN.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array

__all__ = ["safe_divide", "safe_norm", "safe_sqrt"]


def safe_sqrt(x) -> Array:
    """sqrt(max(x, 0)), with gradient 0 (not inf or NaN) where x <= 0."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1)), 0)


def safe_divide(num, den) -> Array:
    """num / den, and 0 with a zero gradient where den is below the dtype's eps (a pixel with
    no usable sample, a zero normal)."""
    ok = den > jnp.finfo(den.dtype).eps
    return jnp.where(ok, num / jnp.where(ok, den, 1), 0)


def safe_norm(v, axis: int = -1) -> Array:
    """|v| along `axis`, with gradient 0 at v = 0 instead of NaN."""
    return safe_sqrt(jnp.sum(v * v, axis=axis))
