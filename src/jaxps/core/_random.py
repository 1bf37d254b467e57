"""PRNG keys from either a JAX key or a plain integer seed.

Users try `key=0` first; JAX wants `jax.random.key(0)`. Every public function that takes a
`key` passes it through `as_key`, so both work and give the same numbers.
"""

from __future__ import annotations

import jax
import numpy as np

__all__ = ["as_key"]


def as_key(key, *, default: int | None = None, name: str = "key") -> jax.Array | None:
    """`key` as a JAX PRNG key: an int (or NumPy integer) seed becomes `jax.random.key(seed)`,
    a JAX key passes through, and None becomes `jax.random.key(default)` (or stays None when
    `default` is None)."""
    if key is None:
        return None if default is None else jax.random.key(default)
    if isinstance(key, (bool, np.bool_)):
        raise TypeError(f"{name} must be a JAX PRNG key or an int seed, got {key!r}")
    if isinstance(key, (int, np.integer)):
        return jax.random.key(int(key))
    if isinstance(key, jax.Array):
        return key
    raise TypeError(f"{name} must be a JAX PRNG key or an int seed, got {type(key).__name__}")
