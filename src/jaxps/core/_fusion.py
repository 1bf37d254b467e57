"""Keeping XLA-CPU from computing a costly intermediate again in every loop that reads it."""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["computed_once"]


def computed_once(fn, *args, key):
    """`fn(*args)`, computed once and written to memory.

    XLA-CPU fuses a computation into every loop over the image that reads its result, so a
    costly one read by several outputs (a search, a solve) is computed again in each, and
    `jax.lax.optimization_barrier` does not stop it: XLA-CPU removes the barrier before
    fusing. XLA does not fuse across a `lax.cond`, so `fn` runs inside one whose two branches
    are both `fn`. The predicate is `isnan(key)`: `key` must be a traced scalar that XLA
    cannot evaluate while compiling (a parameter of the program). Where a `vmap` over
    captures leaves `key` unbatched the `cond` stays a `cond`; on a batched predicate it
    becomes a select that runs both branches.
    """
    return jax.lax.cond(jnp.isnan(key), fn, fn, *args)
