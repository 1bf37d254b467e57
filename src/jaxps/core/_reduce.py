"""Reductions over a short leading axis (the K lights), written for XLA-CPU.

XLA-CPU reduces the short major axis of a `(K, N)` array far slower than the same sum written as
K - 1 elementwise adds, which fuse with the producers: 25.0 ms against 0.8 ms for `sum(x * y)`
over K = 5, N = 2**20 on the project's 2-core machine (`benchmarks/bench_reflectance.py`,
"xla_reduction"). The one-pixel kernels of `ps/_l2.py` unroll their sums for the same
reason; this is the image-wide form.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array

# Above this many terms a real reduction is the better code.
_UNROLL_MAX = 32


def sum0(x: Array) -> Array:
    """`jnp.sum(x, axis=0)`, unrolled when the leading axis is short; booleans count as int32."""
    if x.dtype == jnp.bool_:
        x = x.astype(jnp.int32)
    if x.shape[0] > _UNROLL_MAX or x.shape[0] == 0:
        return jnp.sum(x, axis=0)
    out = x[0]
    for k in range(1, x.shape[0]):
        out = out + x[k]
    return out
