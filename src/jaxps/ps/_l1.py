"""Exact L1 photometric stereo: the least-absolute-residual normal, found without iterating.

Robust photometric stereo often minimises the L1 misfit $\\sum_k |i_k - l_k^T b|$ over a pixel's
usable samples, so that a shadowed or specular sample pulls the fit far less than under least
squares (Ikehata et al., "Robust photometric stereo using sparse regression", CVPR 2012, whose
`L1_residual_min` runs iteratively reweighted least squares; `method="irls"` here). This is a
linear program in $b \\in \\mathbb{R}^3$, and a linear program attains its optimum at a vertex:
some 3 residuals are zero (Barrodale & Roberts, "An improved algorithm for discrete l1 linear
approximation", SIAM J. Numer. Anal. 10(5), 1973). With the handful of lights of a scanner there
are only $\\binom{K}{3}$ vertices (10 for K = 5), so every one is solved (a 3x3 inverse per light
triple, computed once per image) and the cheapest kept: the exact optimum in one pass, where
IRLS approaches it over tens of reweighted solves.
"""

from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np

from ..core._fusion import computed_once
from ..core._safe import safe_divide
from ..core._status import Status
from ._l2 import PSResult, _count, _finish, _samples

__all__ = ["MAX_L1_LIGHTS", "ps_l1"]

# C(K, 3) triples are unrolled: 56 at K = 8. More lights make the kernel (and its compile) grow
# as K^4; `method="irls"` handles them.
MAX_L1_LIGHTS = 8
# A light triple whose |det| (unit vectors: at most 1) is below this does not span 3-D.
_DET_MIN = 1e-3


def _shade(lights, b, k):
    return lights[k, 0] * b[0] + lights[k, 1] * b[1] + lights[k, 2] * b[2]


def _pixel_search(x, usable, lights, thresholds, triples):
    """The index into `triples` of one pixel's cheapest vertex (-1 if no usable triple spans
    3-D). `x`: K samples, each a list of C channel scalars; `usable`: K bools; `lights`:
    `(K, 3)`; `triples`: `[((p, q, r), inverse (3, 3), valid), ...]` of every light triple."""
    ks = range(len(x))
    dtype = x[0][0].dtype
    _, g, used, _ = _samples(x, usable, thresholds)
    best, index = jnp.full((), jnp.inf, dtype), jnp.full((), -1, jnp.int32)
    for t, ((p, q, r), inv, valid) in enumerate(triples):
        b = [inv[a, 0] * g[p] + inv[a, 1] * g[q] + inv[a, 2] * g[r] for a in range(3)]
        cost = sum(jnp.where(used[k], jnp.abs(g[k] - _shade(lights, b, k)), 0) for k in ks)
        cost = jnp.where(valid & used[p] & used[q] & used[r], cost, jnp.inf)
        better = cost < best  # strictly: the first of equal costs wins
        best = jnp.where(better, cost, best)
        index = jnp.where(better, t, index)
    return index


def _pixel_vertex(x, usable, index, thresholds, triples):
    """$b$ of one pixel's vertex `index` (zero for -1), from its grey samples."""
    g = _samples(x, usable, thresholds)[1]
    b = [jnp.zeros((), g[0].dtype)] * 3
    for t, ((p, q, r), inv, _) in enumerate(triples):
        b = [jnp.where(index == t, inv[a, 0] * g[p] + inv[a, 1] * g[q] + inv[a, 2] * g[r], b[a])
             for a in range(3)]
    return b


def _pixel_finish(x, usable, inside, index, b, lights, thresholds, outlier):
    """One pixel's outputs (those of `_l2._finish`) at its vertex `b`, found as `index`:
    n_used and residual over the inliers, the colour albedo by least squares over them."""
    ks = range(len(x))
    dtype = x[0][0].dtype
    x, g, used, cases = _samples(x, usable, thresholds)
    n_used = _count(used)
    scale = sum(jnp.where(used[k], g[k], 0) for k in ks) / jnp.maximum(n_used, 1).astype(dtype)
    res = [g[k] - _shade(lights, b, k) for k in ks]
    inlier = [used[k] & (jnp.abs(res[k]) <= outlier * scale) for k in ks]
    sq = sum(jnp.where(inlier[k], res[k] ** 2, 0) for k in ks)

    def colour_albedo(n):  # per channel, least squares over the inliers at the L1 normal
        s = [jnp.where(inlier[k], _shade(lights, n, k), 0) for k in ks]
        ss = sum(v * v for v in s)
        return [safe_divide(sum(s[k] * x[k][c] for k in ks), ss) for c in range(len(x[0]))]

    cases.append((index < 0, Status.DEGENERATE))  # no usable triple spans 3-D
    colour_albedo = None if len(x[0]) == 1 else colour_albedo
    return _finish(lambda: (b, sq, colour_albedo), _count(inlier), cases, inside)


def ps_l1(images, lights, mask, sample_mask, thresholds, *, threshold: float = 0.05) -> PSResult:
    """Exact L1 photometric stereo (the solver behind `method="l1"`).

    Per pixel, the $b = \\rho n$ minimising $\\sum_k |i_k - l_k^T b|$ over the usable samples
    (finite, unsaturated, above the shadow threshold, allowed by `sample_mask`), found by
    trying every light triple's exact solve (see the module docstring). Colour stacks fit the
    channel-mean intensities; each channel's albedo is then the least-squares one over the
    inliers. `n_used` counts the inliers ($|r_k| \\le$ `threshold` x the mean used intensity) and
    `residual` is their RMS, as for the other robust methods.

    **Arguments** (besides the solver arguments of `photometric_stereo`):
    - `threshold`: inlier bound for `n_used` / `residual`, relative to the mean intensity.

    **Raises:** `ValueError` for per-pixel `(K, H, W, 3)` lights or more than `MAX_L1_LIGHTS`
    lights (use `method="irls"`), or a non-positive `threshold`.
    """
    k = images.shape[0]
    if lights.ndim != 2:
        raise ValueError("method='l1' needs shared (K, 3) lights; for per-pixel lights use "
                         "method='irls'")
    if k > MAX_L1_LIGHTS:
        raise ValueError(f"method='l1' tries all C(K, 3) light triples and takes at most "
                         f"K={MAX_L1_LIGHTS} lights, got K={k}; use method='irls'")
    if not (np.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold must be a positive finite number, got {threshold}")
    return _ps_l1(images, lights, mask, sample_mask, thresholds, threshold)


@jax.jit
def _ps_l1(images, lights, mask, sample_mask, thresholds, threshold):
    k, h, w, c = images.shape
    x = [[images[i, :, :, j].reshape(-1) for j in range(c)] for i in range(k)]
    usable = [sample_mask[i].reshape(-1) for i in range(k)]
    triples = []
    for t in itertools.combinations(range(k), 3):
        sub = lights[jnp.array(t)]
        det = jnp.linalg.det(sub)
        valid = jnp.abs(det) > _DET_MIN
        inv = jnp.linalg.inv(jnp.where(valid, sub, jnp.eye(3, dtype=sub.dtype)))
        triples.append((t, inv, valid))
    # The search, then the winning vertex, each computed once: left free, XLA-CPU computed
    # the whole search again in each loop over the image that read b, 0.176-0.179
    # against 0.044-0.050 s at 1 MP, K=5, the same results to the bit
    # (`benchmarks/bench_robust.py`; docs/robust.md, "Searches computed once").
    lifted = jax.vmap(functools.partial(_pixel_search, triples=triples),
                      in_axes=(0, 0, None, None))
    index = computed_once(lifted, x, usable, lights, thresholds, key=thresholds[0])
    lifted = jax.vmap(functools.partial(_pixel_vertex, triples=triples),
                      in_axes=(0, 0, 0, None))
    b = computed_once(lifted, x, usable, index, thresholds, key=thresholds[0])
    kernel = functools.partial(_pixel_finish, outlier=threshold)
    normal, albedo, status, n_used, residual = jax.vmap(
        kernel, in_axes=(0, 0, 0, 0, 0, None, None))(x, usable, mask.reshape(-1), index, b,
                                                     lights, thresholds)
    return PSResult(jnp.stack(normal, -1).reshape(h, w, 3),
                    jnp.stack(albedo, -1).reshape(h, w, c), status.reshape(h, w),
                    n_used.reshape(h, w), residual.reshape(h, w))
