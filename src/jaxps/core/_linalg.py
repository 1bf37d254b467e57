"""Small dense solves written for `vmap` over pixels on XLA-CPU."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array

__all__ = ["REL_DET_MIN", "adjugate3", "normal_equations", "relative_det", "solve3"]

# det(A) / (trace(A)/3)^3 below this marks the usable lights as not spanning 3-D
# (roughly a light-matrix condition number above 1e3).
REL_DET_MIN = 1e-6


def normal_equations(w, lights, ys):
    """The weighted normal equations $A = \\sum_k w_k l_k l_k^T$, $r = \\sum_k w_k y_k l_k$, on
    scalars: `w` K weights, `lights` K `[lx, ly, lz]`, `ys` a list of right-hand sides, each K
    samples. Returns `A` as nested lists (its lower triangle the upper one's values: 6 sums of
    K products, not 9) and one `r` (3 sums) per entry of `ys`."""
    ks = range(len(w))
    wl = [[w[k] * lights[k][p] for p in range(3)] for k in ks]
    upper = {(p, q): sum(wl[k][p] * lights[k][q] for k in ks) for p in range(3)
             for q in range(p, 3)}
    a = [[upper[min(p, q), max(p, q)] for q in range(3)] for p in range(3)]
    return a, [[sum(wl[k][p] * y[k] for k in ks) for p in range(3)] for y in ys]


def adjugate3(a) -> tuple[list, Array]:
    """The adjugate (cofactor matrix, symmetric) and determinant of a symmetric 3x3 `a`,
    indexable as in `solve3`: `adj` as nested lists, so that `a^{-1} = adj / det`."""
    c00 = a[1][1] * a[2][2] - a[1][2] * a[2][1]
    c01 = a[1][2] * a[2][0] - a[1][0] * a[2][2]
    c02 = a[1][0] * a[2][1] - a[1][1] * a[2][0]
    c11 = a[0][0] * a[2][2] - a[0][2] * a[2][0]
    c12 = a[0][1] * a[2][0] - a[0][0] * a[2][1]
    c22 = a[0][0] * a[1][1] - a[0][1] * a[1][0]
    det = a[0][0] * c00 + a[0][1] * c01 + a[0][2] * c02
    return [[c00, c01, c02], [c01, c11, c12], [c02, c12, c22]], det


def relative_det(a, det) -> Array:
    """det(a) / (trace(a)/3)^3: a scale-free conditioning measure (0 when singular)."""
    scale = (a[0][0] + a[1][1] + a[2][2]) / 3
    return det / jnp.maximum(scale**3, jnp.finfo(det.dtype).tiny)


def solve3(a, r) -> tuple[Array, Array]:
    """Solve the symmetric 3x3 system `a x = r` by cofactors.

    `a` is indexable as `a[p][q]` (a `(3, 3)` array or nested lists of per-pixel scalars) and
    `r` as `r[p]` (a `(3, ...)` array or a list of three arrays). Returns the `(3, ...)`
    solution and `relative_det`.

    Written with scalar products only: under `vmap`, a batched matrix product or a reduction
    over a small axis becomes a slow batched op on CPU, while these fuse into one elementwise
    loop over pixels.
    """
    adj, det = adjugate3(a)
    inv_det = 1 / jnp.where(det != 0, det, 1)
    x = [(adj[p][0] * r[0] + adj[p][1] * r[1] + adj[p][2] * r[2]) * inv_det for p in range(3)]
    return jnp.stack(x), relative_det(a, det)
