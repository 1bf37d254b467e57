"""Elementwise functions written so that XLA-CPU fuses and vectorises them in line.

XLA's CPU `atan2` is a scalar library call, several times slower than the polynomial here, and
its `tanh` is slower than the rational form here (`benchmarks/bench_brdf.py --part speed`, the
atan2 and tanh pieces). Both forms use one
reciprocal times a numerator rather than a quotient: XLA-CPU writes a quotient `a / b` of two
computed arrays to memory, as a pass of its own, when it has more than one user, while `1 / b`
stays fused (`benchmarks/fusion_rules.py`). Other dtypes than float32 fall back to `jnp`.
"""

from __future__ import annotations

import math

import jax.numpy as jnp

__all__ = ["atan2_nonneg", "tanh"]


def atan2_nonneg(y, x):
    """$\\arctan2(y, x)$ for $y \\ge 0$ (not both 0), elementwise, in $[0, \\pi]$.

    float32: Cephes `atanf` (argument reduced to $[0, 1]$, then to $|t| \\le \\tan(\\pi/8)$,
    degree-9 odd polynomial; within 4e-7 of numpy, `tests/test_brdf.py`). Other dtypes use
    `jnp.arctan2`.
    """
    if jnp.dtype(y.dtype).itemsize > 4:
        return jnp.arctan2(y, x)
    dtype = y.dtype
    ax = jnp.abs(x)
    big, small = jnp.maximum(ax, y), jnp.minimum(ax, y)  # a = small / big in [0, 1]
    mid = small > 0.41421356 * big  # a > tan(pi/8): reduce to (a - 1) / (a + 1), offset pi/4
    # one reciprocal for both reductions: (a - 1) / (a + 1) = (small - big) / (small + big)
    den = jnp.where(mid, small + big, jnp.where(big > 0, big, jnp.ones((), dtype)))
    t = jnp.where(mid, small - big, small) * (1 / den)
    z = t * t
    poly = (((8.05374449538e-2 * z - 1.38776856032e-1) * z + 1.99777106478e-1) * z
            - 3.33329491539e-1) * z * t + t
    r = jnp.where(mid, poly + jnp.asarray(math.pi / 4, dtype), poly)
    r = jnp.where(y > ax, jnp.asarray(math.pi / 2, dtype) - r, r)
    return jnp.where(x < 0, jnp.asarray(math.pi, dtype) - r, r)


# Eigen's float32 tanh (`ptanh_float`): odd degree-13 over even degree-6 polynomial on
# [-7.9053, 7.9053], where tanh is 1 to float32 precision.
_TANH_P = (-2.76076847742355e-16, 2.00018790482477e-13, -8.60467152213735e-11,
           5.12229709037114e-08, 1.48572235717979e-05, 6.37261928875436e-04,
           4.89352455891786e-03)
_TANH_Q = (1.19825839466702e-06, 1.18534705686654e-04, 2.26843463243900e-03,
           4.89352518554385e-03)


def tanh(x):
    """tanh; float32: the rational form above (within 4e-7 of numpy, `tests/test_brdf.py`),
    other dtypes `jnp.tanh`."""
    if x.dtype != jnp.float32:
        return jnp.tanh(x)
    x = jnp.clip(x, -7.90531110763549805, 7.90531110763549805)
    x2 = x * x
    p, q = _TANH_P[0], _TANH_Q[0]
    for c in _TANH_P[1:]:
        p = p * x2 + c
    for c in _TANH_Q[1:]:
        q = q * x2 + c
    return x * p * (1 / q)
