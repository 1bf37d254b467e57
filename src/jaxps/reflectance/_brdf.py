"""Data-driven BRDF from a few photometric-stereo images, and relighting under new lights.

The five-source NIR face-scanner paper fits, per face, a three-layer feed-forward network from
the per-sample coordinates (θi, θr, Δα, x, y) (see `jaxps.brdf_features`) to the observed
intensity, trained with Levenberg–Marquardt on ~100,000 random samples, and compares it by eye
with Delaunay-triangulated linear interpolation over (θi, θr, Δα) and with Lambertian
re-rendering. Measured on real faces with held-out lights (docs/brdf.md) that design extrapolates
wildly outside the few training lights' angles and underfits albedo, so the default here keeps
the paper's inputs and solver but predicts a *bounded correction to Lambert's law*:

$$ I = \\rho \\max(0, \\cos\\theta_i) + a\\, w(u)\\, B \\tanh g(\\tilde u, x, y) $$

- $g$ is the MLP (tanh hidden layers, default 5-10-10-1 as in the paper);
- $u = (\\theta_i - \\theta_r,\\ \\theta_i + \\theta_r,\\ \\Delta\\alpha)$ are the paper's angles
  in coordinates where the training samples fill a box (lights within $\\gamma$ of the view
  axis give $|\\theta_i - \\theta_r| \\le \\gamma$); $\\tilde u$ is $u$ clamped to the training box
  and rescaled to [-1, 1], so the network never sees an input it was not trained on;
- $w \\in [0, 1]$ is the training data's support at (θi, θr, Δα): a 0/1 occupancy grid of the
  training samples (7.5° cells, at least 3 samples each) interpolated trilinearly. The box alone
  is not enough: on Yale B, inside-box but unseen combinations of angles were where the
  correction hurt. So the model degrades to Lambert's law where it has no data; samples with
  $w < 0.5$ are flagged by `extrapolation_mask`;
- $B$ bounds the correction (`bound`, default 0.5); $a = \\rho$ for `method="mlp_ratio"` (the
  network models $I/\\rho$, albedo a known factor) and $a = \\bar\\rho$ (the median albedo) for
  `method="mlp"` (the network models intensity; albedo enters only through $x, y$).

Training frames are fitted as $I_k = g_k \\cdot (\\ldots)$ with one brightness factor $g_k$ per
frame ($\\prod_k g_k = 1$; `frame_gains=True`, the default): a flash that fired brighter or
dimmer is then not learned as reflectance, and `relight` renders at $g = 1$. Yale B's flashes
vary by about ±10%: on subject B01 this turns the correction from worse than Lambert's law to
better on held-out lights, on B02 it costs 0.13-0.15 gray and stays better (docs/brdf.md).

`lambertian_base=False` gives the paper's plain design ($I = \\bar\\rho\\, g$ or
$I = \\rho\\, g$, unclamped inputs) for comparison.

How much correction five lights justify: `fit_brdf(..., shrink="loo")` scales $B$ by a factor
$s \\in [0, 1]$ chosen by leave-one-light-out cross-validation on the training frames (normals
re-estimated without the left-out frame; one-standard-error rule), so the model falls back to
Lambert's law ($s = 0$) when the correction does not predict unseen training lights.

Relighting (`relight`) evaluates the same formula feature-major: every image-sized quantity is
a `(K, H W)` array and the MLP's small matrix products are unrolled into multiply-adds over
whole arrays, so XLA emits a few fused elementwise loops (docs/brdf.md, "Speed").

Training: optimistix `LevenbergMarquardt` over the flattened parameter vector
(`jax.flatten_util.ravel_pytree`). The residual carries a `jax.custom_jvp` whose tangent is
$J\\,\\delta p$ with $J$ (N x P) built once per step from per-sample gradients
(`vmap(grad)`): reverse mode per sample costs about one forward pass each, whereas
optimistix's default (forward mode through `jax.linearize`, then P JVPs to materialise $J$ for
the QR) took 6 s / 7.7 GB against 0.14 s / 0.6 GB at N = 100,000 (measured on the project's
2-core machine before this module was written). The damped step then solves the
P x P normal equations by Cholesky (`lineax.Normal(lineax.Cholesky())`): with P ≈ 200 this is
one N x P x P product per step, cheaper than QR of the (N+P) x P stack and exact, unlike a
matrix-free CG whose iteration count would grow with the network's conditioning. Subsampling is
the paper's: N random samples (default 100,000) out of all masked pixel-light pairs.

Baselines: `method="delaunay"` (scipy's Delaunay triangulation of (θi, θr, Δα), linear
interpolation of $I/\\rho$; outside the convex hull, and in the degenerate flat simplices that
the samples of few lights produce, it returns Lambert's $\\max(0, \\cos\\theta_i)$ and flags the
sample) and `method="lambertian"`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, ArrayLike, Bool, Float
from threadpoolctl import threadpool_limits

from ..core._elementwise import tanh as _tanh
from ..core._host import CpuTuned
from ..core._random import as_key
from ..lights._directions import frame_count_error
from . import _parametric
from ._auto import fit_auto, lolo_folds
from ._features import (
    _angles_elementwise,
    _features,
    pixel_coordinates,
    usable_normals,
)

__all__ = [
    "BRDF_METHODS",
    "BRDFFit",
    "BRDFModel",
    "extrapolation_mask",
    "fit_brdf",
    "relight",
]

BRDF_METHODS = ("mlp", "mlp_ratio", "delaunay", "lambertian", "auto",
                *_parametric.PARAMETRIC_METHODS)
# `fit_brdf(method="auto")`'s default candidates: the ones its settings were chosen with
# (benchmarks/bench_relight.py). Delaunay is a slow reference, worse than Lambert held out;
# the parametric models are candidates on request (`candidates=`).
AUTO_CANDIDATES = ("mlp", "mlp_ratio")


class BRDFFit(NamedTuple):
    """How a BRDF fit went, in the training images' units.

    - `steps`: solver steps taken (0 for the non-iterative methods).
    - `converged`: the solver met its tolerances within `max_steps` (True when not iterative).
    - `mse`, `rmse`: mean squared / root-mean-square error over the training samples.
    - `r`: Pearson correlation between fitted and observed training intensities (the paper's R).
    - `n_samples`: training samples used.
    - `seconds`: wall time of the fit (compile included).
    - `message`: the solver's result message.
    - `shrink`: the factor $s$ the correction was scaled by (`fit_brdf(..., shrink="loo")`;
      1.0 without shrinkage). `mse`, `rmse`, `r` are those of the shrunk model.
    - `loo_rmse`: with `shrink="loo"`, the leave-one-light-out report: RMSE over the K left-out
      frames pooled, `"lambertian"`, `"full"`, `"shrunk"` (correction scaled by 0, 1 and $s$);
      `"pooled_factor"` ($s^*$ before the one-SE rule), `"mse_diff_mean"`, `"mse_diff_se"`
      (per-fold MSE change at $s^*$ against Lambert, and its standard error) and the per-fold
      RMSEs `"folds_lambertian"`, `"folds_full"`, and `"skipped_folds"` (indices of the
      left-out frames whose fold was skipped: the other lights did not span 3-D); else None.
    - `frame_gains`: with `fit_brdf(..., frame_gains=True)`, the `K` fitted brightness factors
      of the training frames (geometric mean 1; the model renders at 1); else None.
    - `n_params`: free parameters beyond the normal and albedo per pixel that Lambert's law
      also has (0 for `"lambertian"`; the network's weights; for `"delaunay"` one per training
      sample; for the parametric models the shape parameters and specular albedos), plus K - 1
      frame gains where fitted. `method="auto"`'s information criterion counts them.
    - `choice`: with `method="auto"`, what was picked and why: `"choice"`, `"reason"`, and
      (with K >= 5) the leave-one-light-out RMSE of Lambert and each candidate (`"lolo_rmse"`;
      `"gated_lolo_rmse"`: the candidate kept only in its `"kept_cells"`), the information
      criterion of each model fitted on all K frames (`"bic"`) and the candidates it ruled
      out (`"bic_rejected"`: BIC not below Lambert's), `"regions"`, `"margin"`, `"folds"`,
      `"gate_fraction"`; else None. The other figures are the chosen
      method's fit on every pixel (before the gate).
    """

    steps: int
    converged: bool
    mse: float
    rmse: float
    r: float
    n_samples: int
    seconds: float
    message: str
    shrink: float = 1.0
    loo_rmse: dict | None = None
    frame_gains: tuple[float, ...] | None = None
    choice: dict | None = None
    n_params: int = 0


class BRDFModel(eqx.Module):
    """A fitted BRDF. Use it with `relight` and `extrapolation_mask`.

    - `method`: one of `BRDF_METHODS`.
    - `params`: MLP weights `((W1, b1), (W2, b2), (W3, b3))` (None for other methods).
    - `box_lo`, `box_hi`: `(3,)` training range of $u = (θi-θr, θi+θr, Δα)$ in radians.
    - `support`: `(G_i, G_r, G_α)` 0/1 occupancy of the (θi, θr, Δα) grid by training samples
      (cells of `cell` radians; a cell is occupied with at least `min_count` samples).
    - `rho_ref`: median albedo over the masked pixels whose albedo and normal are finite (and
      the normal not zero): the correction's scale for `method="mlp"`.
    - `fit`: a `BRDFFit`.
    - `gate`: `(H, W)` weight of the model against Lambert's law per pixel (`method="auto"`'s
      per-region choice: `relight` renders $L + \\text{gate} (M - L)$), or None (the model
      everywhere).
    """

    method: str = eqx.field(static=True)
    params: tuple | None
    box_lo: Array
    box_hi: Array
    support: Array
    rho_ref: Array
    bound: float = eqx.field(static=True)
    cell: float = eqx.field(static=True)
    lambertian_base: bool = eqx.field(static=True)
    use_xy: bool = eqx.field(static=True)
    interpolator: object = eqx.field(static=True, default=None)
    fit: BRDFFit | None = eqx.field(static=True, default=None)
    gate: Array | None = None


# ----------------------------------------------------------------------------- one sample


def _box_coords(f):
    """(θi-θr, θi+θr, Δα) from feature vectors (θi, θr, Δα, x, y) along the last axis; numpy
    in, numpy out (`fit_brdf` summarises its samples on the host)."""
    xp = np if isinstance(f, np.ndarray) else jnp
    return xp.stack([f[..., 0] - f[..., 1], f[..., 0] + f[..., 1], f[..., 2]], axis=-1)


def _mlp(params, z):
    for w, b in params[:-1]:
        z = jnp.tanh(w @ z + b)
    w, b = params[-1]
    return (w @ z + b)[0]


def _predict_one(params, f, rho, box_lo, box_hi, support, rho_ref, bound, cell, base, ratio,
                 use_xy):
    """Predicted intensity of one sample with features `f` (5,) and albedo `rho` ()."""
    u = _box_coords(f)
    span = jnp.maximum(box_hi - box_lo, jnp.asarray(1e-6, f.dtype))
    amp = rho if ratio else rho_ref
    xy = f[3:] if use_xy else jnp.zeros_like(f[3:])
    if not base:  # the paper's plain network: unclamped inputs, no Lambertian term
        z = jnp.concatenate([2 * (u - box_lo) / span - 1, xy])
        return amp * _mlp(params, z)
    clamped = jnp.clip(u, box_lo, box_hi)
    z = jnp.concatenate([2 * (clamped - box_lo) / span - 1, xy])
    weight = _support_weight(support, (f[0], f[1], f[2]), cell)
    lambert = rho * jnp.maximum(jnp.cos(f[0]), 0)
    return lambert + amp * weight * bound * jnp.tanh(_mlp(params, z))


def _support_weight(support, angles, cell):
    """Trilinear interpolation of the 0/1 occupancy grid at (θi, θr, Δα): 1 amid training data,
    0 one cell away from it. `angles` is a sequence of three arrays of one shape (or scalars).

    Cell centres sit at (j + 1/2) `cell`; indices are clamped to the grid (the semantics of
    `jax.scipy.ndimage.map_coordinates(support, angles / cell - 1/2, order=1, mode="nearest")`).
    The grid is padded by one edge cell on every side, so the clamp is one `clip` of the lower
    corner per axis and the eight corners are one flat index plus constant offsets: eight
    gathers in the same fused elementwise kernel, with less index arithmetic than clamping
    each corner's three indices apart (docs/brdf.md, "Speed").
    """
    shape = support.shape
    padded = jnp.pad(support, 1, mode="edge")
    flat = padded.reshape(-1)
    strides = (padded.shape[1] * padded.shape[2], padded.shape[2], 1)
    base, weights = 0, []
    for a, size, stride in zip(angles, shape, strides):
        c = a / cell - 0.5
        lower = jnp.floor(c)
        upper_weight = c - lower
        # the lower corner, -1..size-1 (beyond, both corners clamp alike), is padded row 0..size
        base = base + (jnp.clip(lower.astype(jnp.int32), -1, size - 1) + 1) * stride
        weights.append((1 - upper_weight, upper_weight))
    out = None
    for b0, w0 in enumerate(weights[0]):
        for b1, w1 in enumerate(weights[1]):
            for b2, w2 in enumerate(weights[2]):
                offset = b0 * strides[0] + b1 * strides[1] + b2
                term = (w0 * w1 * w2) * flat[base + offset]
                out = term if out is None else out + term
    return out


def _support_grid(angles, cell, min_count):
    """0/1 occupancy `(G_i, G_r, G_α)` of (θi in [0, π], θr in [0, π/2], Δα in [0, π])."""
    angles = np.asarray(angles, np.float64)
    shape = tuple(int(math.ceil(top / cell)) for top in (math.pi, math.pi / 2, math.pi))
    idx = [np.clip((angles[:, i] / cell).astype(int), 0, shape[i] - 1) for i in range(3)]
    counts = np.zeros(shape, np.int64)
    np.add.at(counts, tuple(idx), 1)
    return counts >= min_count


def _init_mlp(key, sizes, dtype):
    params = []
    keys = jax.random.split(key, len(sizes) - 1)
    for i, (k, n_in, n_out) in enumerate(zip(keys, sizes[:-1], sizes[1:])):
        scale = 1.0 / math.sqrt(n_in) if i < len(sizes) - 2 else 1e-2
        w = scale * jax.random.normal(k, (n_out, n_in), dtype)
        params.append((w, jnp.zeros((n_out,), dtype)))
    return tuple(params)


# ----------------------------------------------------------------------------- training


def _train_mlp(params, log_gains, feats, rho, target, frame, box_lo, box_hi, support, rho_ref, *,
               bound, cell, base, ratio, use_xy, fit_gains, solver, max_steps):
    """LM on the flat parameters (and, with `fit_gains`, the `(K,)` log-gains of the frames,
    centred so their geometric mean is 1). `frame`: `(N,)` frame index of each sample."""
    flat_mlp, unravel = ravel_pytree(params)
    n_mlp = flat_mlp.size
    flat0 = jnp.concatenate([flat_mlp, log_gains]) if fit_gains else flat_mlp

    def centred(p):
        g = p[n_mlp:]
        return g - jnp.mean(g)

    def pred(p, f, r, k):
        out = _predict_one(unravel(p[:n_mlp]), f, r, box_lo, box_hi, support, rho_ref, bound,
                           cell, base, ratio, use_xy)
        return out * jnp.exp(centred(p)[k]) if fit_gains else out

    @jax.custom_jvp
    def residuals(p, args):
        f, r, t, k = args
        return jax.vmap(pred, in_axes=(None, 0, 0, 0))(p, f, r, k) - t

    @residuals.defjvp
    def _residuals_jvp(primals, tangents):
        p, (f, r, t, k) = primals
        dp, _ = tangents
        # Per-sample reverse mode: J is (N, P) at about the cost of N forward passes.
        value, jac = jax.vmap(jax.value_and_grad(pred), in_axes=(None, 0, 0, 0))(p, f, r, k)
        return value - t, jac @ dp

    args = (feats, rho, target, frame)
    sol = optx.least_squares(residuals, solver, flat0, args=args, max_steps=max_steps,
                             throw=False)
    res = residuals(sol.value, args)
    gains = jnp.exp(centred(sol.value)) if fit_gains else jnp.ones_like(log_gains)
    return (unravel(sol.value[:n_mlp]), gains, sol.stats["num_steps"],
            sol.result == optx.RESULTS.successful, res)


_train_mlp_jit = eqx.filter_jit(_train_mlp)


def _fit_stats(pred, target):
    pred = np.asarray(pred, np.float64)
    target = np.asarray(target, np.float64)
    mse = float(np.mean((pred - target) ** 2))
    sp, st = np.std(pred), np.std(target)
    r = float(np.mean((pred - pred.mean()) * (target - target.mean())) / (sp * st)) \
        if sp > 0 and st > 0 else 0.0
    return mse, math.sqrt(mse), r


# ----------------------------------------------------------------------------- public API


def _check_images(images):
    """`images` (an array) if it is a floating `(K, H, W)` stack, else `ValueError`; float16
    and bfloat16 as float32 (optimistix's solves failed on them)."""
    if not jnp.issubdtype(images.dtype, jnp.floating) or images.ndim != 3:
        raise ValueError(
            f"images must be a floating (K, H, W) grey stack, got {images.dtype} {images.shape}")
    return images.astype(jnp.float32) if jnp.finfo(images.dtype).bits < 32 else images


def _check_inputs(images, normals, albedo, lights, mask):
    images = _check_images(jnp.asarray(images))
    k, h, w = images.shape
    dtype = images.dtype
    normals = _check_normals(normals, (h, w), dtype)
    albedo = _check_albedo(albedo, (h, w), dtype)
    lights = _check_lights(lights, dtype, (h, w))
    if lights.shape[0] != k:
        raise frame_count_error(images.shape, lights.shape[0])
    if mask is None:
        mask = np.ones((h, w), bool)
    mask = np.asarray(mask)
    if mask.shape != (h, w):
        raise ValueError(f"mask must have shape (H, W) = {(h, w)}, got {mask.shape}")
    mask = mask.astype(bool)
    if not mask.any():
        raise ValueError("mask is empty: no pixel to fit")
    return images, normals, albedo, lights, mask


def _check_normals(normals, hw, dtype):
    normals = jnp.asarray(normals, dtype)
    if normals.shape != (*hw, 3):
        raise ValueError(f"normals must be (H, W, 3) = {(*hw, 3)}, got {normals.shape}")
    return normals


def _check_albedo(albedo, hw, dtype):
    albedo = jnp.asarray(albedo, dtype)
    if albedo.shape != hw:
        raise ValueError(f"albedo must be (H, W) = {hw}, got {albedo.shape}")
    return albedo


def _check_lights(lights, dtype, hw=None):
    """`lights` as unit vectors of `dtype`, checked: `(K, 3)` (or one `(3,)`) distant lights,
    or, where the image size `hw` is given, `(K, H, W, 3)` per-pixel ones (near lamps). Under
    jit or grad only the shape is checked."""
    traced = isinstance(lights, jax.core.Tracer)
    if not traced:
        lights = np.asarray(lights, np.float64)
    per_pixel = hw is not None and lights.ndim == 4
    if per_pixel:
        if lights.shape[1:] != (*hw, 3):
            raise ValueError(f"per-pixel lights must be (K, H, W, 3) with (H, W) = {hw}, got "
                             f"shape {lights.shape}")
    else:
        if lights.shape == (3,):
            lights = lights[None]
        if lights.ndim != 2 or lights.shape[1] != 3:
            raise ValueError(f"lights must be (K, 3) or (3,), got shape {lights.shape}")
    if traced:
        lights = lights.astype(dtype)
        return lights / jnp.linalg.norm(lights, axis=-1, keepdims=True)
    if not np.all(np.isfinite(lights)):
        raise ValueError("lights contain NaN or Inf")
    norms = np.linalg.norm(lights, axis=-1, keepdims=True)
    zero = np.flatnonzero((norms < 1e-8).reshape(len(lights), -1).any(axis=1))
    if zero.size:
        raise ValueError(f"lights {zero.tolist()} are zero vectors")
    lights = lights / norms
    below = np.flatnonzero((lights[..., 2] <= 0).reshape(len(lights), -1).any(axis=1))
    if below.size:
        raise ValueError(
            f"lights {below.tolist()} are at or below the horizon (l_z <= 0)"
            f"{' at some pixel' if per_pixel else ''}: a light behind the image plane cannot "
            "light the visible surface")
    return lights.astype(dtype)  # numpy: a jit takes it as is; jnp.asarray dispatches a convert


def fit_brdf(
    images: Float[ArrayLike, "K H W"],
    normals: Float[ArrayLike, "H W 3"],
    albedo: Float[ArrayLike, "H W"],
    lights: Float[ArrayLike, "K 3"] | Float[ArrayLike, "K H W 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    method: str = "wrap_ggx",
    key: jax.Array | int | None = None,
    n_samples: int = 100_000,
    hidden: tuple[int, ...] = (10, 10),
    bound: float = 0.5,
    support_deg: float = 7.5,
    min_count: int = 3,
    lambertian_base: bool = True,
    use_xy: bool = True,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 30,
    saturation: float = 1.0,
    shrink: str | None = None,
    ps_method: str = "l2",
    frame_gains: bool = True,
    candidates: tuple[str, ...] | None = None,
    regions: int = 1,
    margin: float = 3.0,
    region: int | None = _parametric.REGION_PX,
    refine_normals: bool = True,
) -> BRDFModel:
    """Fit a BRDF to K images of one object with known normals, albedo and lights.

    **Arguments:**
    - `images`: `(K, H, W)` grey, floating, linear (ambient subtracted).
    - `normals`: `(H, W, 3)` unit normals, `albedo`: `(H, W)` (e.g. from
      `jaxps.photometric_stereo` on the same images), in the images' units.
    - `lights`: `(K, 3)` directions toward the lights, above the horizon (l_z > 0), or
      `(K, H, W, 3)` per pixel, for near lamps (`NearResult.lights` of
      `jaxps.near_photometric_stereo`, with `images` divided by its `falloff`); every method
      takes either.
    - `mask`: `(H, W)` bool, pixels to learn from (default all; must not be empty).
    - `method`: `"wrap_ggx"` (the default: wrap diffuse + GGX lobe, normals refined jointly;
      the only model below Lambert's law on held-out lights on all five shared Yale B faces,
      raw and gain-invariant, `benchmarks/bench_relight.py`; DESIGN.md named `"mlp"`), `"mlp"`
      (network on intensity, the paper's model), `"mlp_ratio"`
      (network on $I/\\rho$; same held-out error on Yale B, see docs/brdf.md),
      `"delaunay"` or `"lambertian"` (see the module docstring), or `"auto"`: the
      candidates' leave-one-light-out error on the training frames decides, per face region,
      between Lambert's law and the best candidate, which must also have a lower Bayesian
      information criterion than Lambert's law (K >= 5; K + 1 fits per candidate; see
      docs/brdf.md, "Choosing a model"). `model.fit.choice` says what was picked
      and why. Or a parametric model,
      a diffuse term plus a specular lobe that moves with the light (`"ggx"`, `"blinn_phong"`,
      `"wrap"`, `"oren_nayar"`, `"wrap_ggx"`, `"oren_nayar_ggx"`: diffuse Lambert unless
      named; `"wrap_ggx_residual"` adds a bounded MLP over the half/difference angles;
      docs/brdf.md, "Parametric models"). For those,
      `key`, `n_samples` (pixels drawn: `n_samples // K`), `solver`, `max_steps`,
      `saturation`, `frame_gains`, `region` and `refine_normals` apply.
    - `key`: PRNG key or int seed (`jax.random.key(seed)`) for sampling and initialisation
      (default `jax.random.key(0)`).
    - `n_samples`: random pixel-light samples to train on (paper: ~100,000). Samples that are
      non-finite or at/above `saturation`, and the samples of pixels whose albedo is not > 0
      (NaN included) or whose normal is non-finite or of zero length, are never drawn (for the
      parametric methods: never fitted; such a pixel keeps its given normal).
    - `hidden`: hidden-layer widths of the MLP (paper: two layers, 5-10-10-1 in total).
    - `bound`: the correction's bound $B$ (in units of albedo).
    - `support_deg`, `min_count`: cell size (degrees) of the (θi, θr, Δα) support grid and the
      training samples a cell needs to count as supported.
    - `lambertian_base`: False gives the paper's plain network (no Lambertian term, no
      clamping, no fade).
    - `use_xy`: feed the pixel position to the network (the paper's design; default True).
    - `solver`: an optimistix least-squares solver (default
      `LevenbergMarquardt(rtol=1e-4, atol=1e-6, linear_solver=lineax.Normal(lineax.Cholesky()))`).
    - `max_steps`: the solver's step limit; one LM step uses every sample once (an epoch; the
      paper trained ~200). 30 keeps 100,000 samples under ~30 s on 2 CPU cores.
    - `shrink`: `"loo"` scales the fitted correction by a factor $s \\in [0, 1]$ chosen by
      leave-one-light-out cross-validation on the training frames only: for each frame $j$,
      normals and albedo are re-estimated from the other K-1 frames
      (`photometric_stereo(method=ps_method)`, K >= 5; a fold whose K-1 lights do not span
      3-D is skipped, and at least two folds must remain), the same model is fitted on those K-1
      frames, and its correction $c_j$ and Lambert's prediction $L_j$ of the left-out frame are
      compared with the frame $I_j$; $s^*$ minimises the pooled squared error
      $\\sum_j \\lVert I_j - L_j - s\\, c_j \\rVert^2$ (closed form, clipped to [0, 1]; 0 when the
      folds predict no correction), and is kept only if its per-fold gain over Lambert's law
      exceeds one standard error (else $s = 0$, Lambert's law: the model is no more than the
      data justify). Costs K + 1 fits. MLP methods with `lambertian_base=True` only.
    - `ps_method`: the photometric-stereo method for the folds of `shrink="loo"` (use the one
      that gave `normals` and `albedo`).
    - `candidates`, `regions`, `margin`: `method="auto"` only: the methods to choose among
      (default `AUTO_CANDIDATES`, the MLPs; any method of `BRDF_METHODS` but `"lambertian"`
      and `"auto"` may be given), the `regions` x `regions` grid over the
      mask's bounding box, and the standard errors by which a candidate must beat Lambert's
      law in a region (chosen leave-one-subject-out on Yale B, docs/brdf.md).
    - `frame_gains`: MLP methods: fit one brightness factor per training frame with the
      network, $I_k = g_k\\, f(\\cdot)$ with $\\prod_k g_k = 1$, so that a flash that fired
      brighter or dimmer in one frame is not learned as reflectance; `relight` renders at
      $g = 1$ and `model.fit.frame_gains` reports them. Default True (Yale B's flashes vary
      by about ±10%, see docs/brdf.md); False is the paper's training.
    - `region`: parametric methods: side in pixels of the square blocks that share one
      specular albedo (None: one for the whole mask).
    - `refine_normals`: parametric methods: re-solve each pixel's normal with the fitted lobe
      (two rounds of normals, then shared parameters); the model keeps the refined normals and
      `relight` renders with them on the fitted grid (its `normals` argument is then unused).
      Default True: chosen leave-one-subject-out on Yale B (docs/brdf.md).

    **Returns:** a `BRDFModel`; `model.fit` is a `BRDFFit` (steps, converged, mse, rmse, R).

    **Raises:** `ValueError` for mismatched shapes, a light at or below the horizon, an empty
    mask, an unknown method, an option out of range (`n_samples`, `support_deg`, `min_count`,
    `bound`, `hidden`, `max_steps`, ...) or no usable sample.
    """
    t0 = time.perf_counter()
    if method not in BRDF_METHODS:
        raise ValueError(f"method must be one of {BRDF_METHODS}, got {method!r}")
    if shrink not in (None, "loo"):
        raise ValueError(f"shrink must be None or 'loo', got {shrink!r}")
    if shrink is not None and (method not in ("mlp", "mlp_ratio") or not lambertian_base):
        raise ValueError("shrink='loo' scales the correction to Lambert's law: it needs "
                         "method 'mlp' or 'mlp_ratio' with lambertian_base=True")
    images, normals, albedo, lights, mask = _check_inputs(images, normals, albedo, lights, mask)
    if int(n_samples) < images.shape[0]:  # n_samples // K pixels are drawn
        raise ValueError(f"n_samples must be at least K = {images.shape[0]} (one pixel per "
                         f"light), got {n_samples!r}")
    if not (np.isfinite(support_deg) and support_deg > 0):
        raise ValueError(f"support_deg must be a positive number of degrees, got {support_deg!r}")
    if int(min_count) < 0:
        raise ValueError(f"min_count must be >= 0 samples, got {min_count!r}")
    if not (np.isfinite(bound) and bound > 0):
        raise ValueError(f"bound must be positive (in units of albedo), got {bound!r}")
    if any(int(width) < 1 for width in hidden):
        raise ValueError(f"hidden must be layer widths >= 1, got {hidden!r}")
    if int(max_steps) < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps!r}")
    if method == "auto":
        if candidates is None:
            candidates = AUTO_CANDIDATES
        bad = [m for m in candidates if m not in BRDF_METHODS or m in ("lambertian", "auto")]
        if bad or not candidates:
            raise ValueError(f"candidates must be methods of {BRDF_METHODS} other than "
                             f"'lambertian' and 'auto', got {candidates!r}")
        if int(regions) < 1:
            raise ValueError(f"regions must be >= 1, got {regions!r}")
        options = {"key": key, "n_samples": n_samples, "hidden": hidden, "bound": bound,
                   "support_deg": support_deg, "min_count": min_count,
                   "lambertian_base": lambertian_base, "use_xy": use_xy, "solver": solver,
                   "max_steps": max_steps, "saturation": saturation,
                   "ps_method": ps_method, "frame_gains": frame_gains, "region": region,
                   "refine_normals": refine_normals}
        return fit_auto(fit_brdf, relight, images, normals, albedo, lights, mask=mask,
                        candidates=tuple(candidates), regions=int(regions), margin=float(margin),
                        ps_method=ps_method, saturation=saturation, options=options)
    if shrink is not None and images.shape[0] < 5:
        raise ValueError(
            f"shrink='loo' needs K >= 5 frames, got {images.shape[0]}: with K-1 = 3 frames per "
            "fold Lambert's law fits each fold exactly, its correction is zero and the test "
            "says nothing")
    dtype = images.dtype
    key = as_key(key, default=0)
    k, h, w = images.shape

    # The samples are drawn and summarised on the host: each eager jnp op here traced and
    # lowered a small program of its own in every new process (a command-line run paid ~30).
    feats = np.asarray(_features(normals, lights))  # (K, H, W, 5)
    images_np, albedo_np = np.asarray(images), np.asarray(albedo)
    known = mask & np.isfinite(albedo_np) & usable_normals(normals)  # rho_ref's pixels
    usable = (known & (albedo_np > 0))[None] & np.isfinite(images_np) & (images_np < saturation)
    idx = np.flatnonzero(usable.reshape(-1))
    if idx.size == 0:
        raise ValueError(
            "no usable sample: the albedo is not > 0 at any masked pixel"
            if not np.any(mask & (albedo_np > 0)) else
            "no usable sample: every masked sample is non-finite or saturated, or its pixel's "
            "albedo is not > 0 or its normal is non-finite or zero")
    key_sample, key_init = jax.random.split(key)
    if idx.size > n_samples:
        pick = np.asarray(jax.random.choice(key_sample, idx.size, (n_samples,), replace=False))
        idx = np.sort(idx[pick])
    f_host = feats.reshape(-1, 5)[idx]
    u = _box_coords(f_host)
    cell = math.radians(support_deg)
    f, frame, rho, target, box_lo, box_hi, rho_ref, support = jax.device_put((
        f_host, (idx // (h * w)).astype(np.int32),
        np.broadcast_to(albedo_np, (k, h, w)).reshape(-1)[idx], images_np.reshape(-1)[idx],
        u.min(0), u.max(0), np.median(albedo_np[known]).astype(dtype),
        _support_grid(f_host[:, :3], cell, min_count).astype(dtype)))

    common = dict(box_lo=box_lo, box_hi=box_hi, support=support, rho_ref=rho_ref,
                  bound=float(bound), cell=cell,
                  lambertian_base=bool(lambertian_base), use_xy=bool(use_xy))
    if method == "lambertian":
        pred = rho * jnp.maximum(jnp.cos(f[:, 0]), 0)
        model = BRDFModel(method, None, **common)
        return _with_fit(model, pred, target, 0, True, t0, "closed form", n_params=0)
    if method == "delaunay":
        ang = np.asarray(f[:, :3], np.float64)
        ratio = np.asarray(target, np.float64) / np.asarray(rho, np.float64)
        lin = _DelaunayBRDF(ang, ratio)
        pred = rho * jnp.asarray(lin(ang), dtype)
        model = BRDFModel(method, None, **common, interpolator=lin)
        return _with_fit(model, pred, target, 0, True, t0, "interpolates the samples",
                         n_params=int(np.size(target)))
    if method in _parametric.PARAMETRIC_METHODS:
        params, gains, steps, ok, msg, pred, target, n_params = _parametric.fit(
            images, normals, albedo, lights, mask, usable, method=method, key=key_sample,
            n_samples=n_samples, solver=solver, max_steps=max_steps, frame_gains=frame_gains,
            region=region, refine_normals=refine_normals)
        extra = {"frame_gains": tuple(float(g) for g in np.asarray(gains))} if frame_gains else {}
        msg += f"; shape parameters {np.asarray(params.shape).round(4).tolist()}"
        return _with_fit(BRDFModel(method, params, **common), pred, target, steps, ok, t0, msg,
                         n_params=n_params, **extra)

    ratio = method == "mlp_ratio"
    params = _init_mlp(key_init, (5, *hidden, 1), dtype)
    if solver is None:
        solver = optx.LevenbergMarquardt(rtol=1e-4, atol=1e-6,
                                         linear_solver=lx.Normal(lx.Cholesky()))
    params, gains, steps, ok, res = _train_mlp_jit(
        params, jnp.zeros((k,), dtype), f, rho, target, frame, box_lo, box_hi, support, rho_ref,
        bound=float(bound), cell=cell, base=bool(lambertian_base), ratio=ratio,
        use_xy=bool(use_xy), fit_gains=bool(frame_gains), solver=solver, max_steps=int(max_steps))
    model = BRDFModel(method, params, **common)
    msg = "converged" if bool(ok) else f"stopped at max_steps={max_steps} or failed"
    gain = gains[frame]
    pred = res + target  # the training fit, frame gains included
    extra = {"frame_gains": tuple(float(g) for g in np.asarray(gains))} if frame_gains else {}
    extra["n_params"] = (sum(int(np.size(a)) for layer in params for a in layer)
                         + (k - 1) * bool(frame_gains))
    if shrink is None:
        return _with_fit(model, pred, target, int(steps), bool(ok), t0, msg, **extra)
    options = dict(method=method, key=key, n_samples=n_samples, hidden=hidden, bound=bound,
                   support_deg=support_deg, min_count=min_count, lambertian_base=True,
                   use_xy=use_xy, solver=solver, max_steps=max_steps, saturation=saturation,
                   frame_gains=frame_gains)
    factor, loo = _loo_shrink(images, lights, mask, ps_method, options)
    lambert = rho * jnp.maximum(jnp.cos(f[:, 0]), 0)
    model = dataclasses.replace(model, bound=float(bound) * factor)
    msg += f"; correction scaled by {factor:.3f} (leave-one-light-out)"
    shrunk = gain * (lambert + factor * (pred / gain - lambert))
    return _with_fit(model, shrunk, target, int(steps), bool(ok), t0, msg, shrink=factor,
                     loo_rmse=loo, **extra)


def _loo_shrink(images, lights, mask, ps_method, options):
    """The shrinkage factor of `fit_brdf(..., shrink="loo")` and its leave-one-light-out report.

    $s^*$ minimises the pooled squared error over the folds (closed form, clipped to [0, 1]).
    It is kept only if it beats Lambert's law ($s = 0$) by more than one standard error of the
    per-fold differences of mean squared error (the "one-standard-error rule": the simplest
    model within one SE of the best; Hastie, Tibshirani & Friedman, *The Elements of Statistical
    Learning*, 2nd ed., §7.10). With five lights the folds differ a lot; a pooled gain carried
    by one fold is not evidence that the correction transfers to new lights.
    """
    k = images.shape[0]
    options = dict(options)
    method = options.pop("method")
    done = lolo_folds(fit_brdf, relight, images, lights, mask, [method], ps_method=ps_method,
                      saturation=options["saturation"], options=options)
    folds = [((obs - lam)[ok], (preds[method] - lam)[ok]) for _, obs, ok, lam, preds in done]
    skipped = sorted(set(range(k)) - {j for j, *_ in done})
    if len(folds) < 2:
        raise ValueError(f"shrink='loo': only {len(folds)} of {k} leave-one-out folds have "
                         "lights spanning 3-D; it needs at least 2")
    num = sum(float(r @ c) for r, c in folds)
    den = sum(float(c @ c) for _, c in folds)
    pooled = float(np.clip(num / den, 0.0, 1.0)) if den > 0 else 0.0

    def fold_mse(s):
        return np.array([np.mean((r - s * c) ** 2) for r, c in folds])

    diff = fold_mse(pooled) - fold_mse(0.0)  # < 0: the correction helps that fold
    se = float(np.std(diff, ddof=1) / math.sqrt(len(folds)))
    factor = pooled if float(np.mean(diff)) + se < 0 else 0.0
    resid = np.concatenate([r for r, _ in folds])
    corr = np.concatenate([c for _, c in folds])
    loo = {name: float(np.sqrt(np.mean((resid - s * corr) ** 2)))
           for name, s in (("lambertian", 0.0), ("full", 1.0), ("shrunk", factor))}
    loo.update(pooled_factor=pooled, mse_diff_mean=float(np.mean(diff)), mse_diff_se=se,
               folds_lambertian=np.sqrt(fold_mse(0.0)).tolist(),
               folds_full=np.sqrt(fold_mse(1.0)).tolist(), skipped_folds=skipped)
    return factor, loo


def _with_fit(model, pred, target, steps, converged, t0, message, **extra):
    mse, rmse, r = _fit_stats(pred, target)
    fit = BRDFFit(steps, converged, mse, rmse, r, int(np.size(target)),
                  time.perf_counter() - t0, message, **extra)
    return dataclasses.replace(model, fit=fit)


class _DelaunayBRDF:
    """Linear interpolation of $I/\\rho$ on a Delaunay triangulation of (θi, θr, Δα)."""

    def __init__(self, points, values):
        # imported here: scipy.spatial and scipy.interpolate took 0.4-0.8 s of every import of
        # jaxps.reflectance (every `jaxps relight`), and only this baseline uses them
        import scipy.interpolate
        import scipy.spatial

        # scipy computes one 3x3 LAPACK call per simplex; with a multi-threaded BLAS each small
        # call pays thread start-up (measured 35x slower on 2 cores), so keep BLAS to 1 thread.
        with threadpool_limits(1, user_api="blas"):
            self.tri = scipy.spatial.Delaunay(points)
            self.tri.transform  # noqa: B018 (computed lazily; pay it here, single-threaded)
        self.interp = scipy.interpolate.LinearNDInterpolator(self.tri, values, fill_value=np.nan)

    def __call__(self, angles):
        with threadpool_limits(1, user_api="blas"):
            out = self.interp(angles)
        outside = ~np.isfinite(out)
        lambert = np.maximum(np.cos(angles[..., 0]), 0)
        return np.where(outside, lambert, out)

    def outside(self, angles):
        """Outside the hull, or in a degenerate (flat) simplex where scipy returns NaN: the samples
        of one light lie on a 2-D surface in (θi, θr, Δα), so slivers are common."""
        with threadpool_limits(1, user_api="blas"):
            return ~np.isfinite(self.interp(angles))


def relight(
    model: BRDFModel,
    normals: Float[ArrayLike, "H W 3"],
    albedo: Float[ArrayLike, "H W"],
    lights: Float[ArrayLike, "K 3"] | Float[ArrayLike, "K H W 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
) -> Float[Array, "K H W"]:
    """Render `normals` and `albedo` under new `lights` with a fitted BRDF.

    **Arguments:**
    - `model`: from `fit_brdf`.
    - `normals`: `(H, W, 3)` unit normals; `albedo`: `(H, W)` in the training images' units.
    - `lights`: `(K, 3)` (or one `(3,)`) directions toward distant lights, l_z > 0, or
      `(K, H, W, 3)` per pixel (near lamps, `jaxps.near_light_field`; multiply the images by
      its fall-off to see them as the lamps light the face).
    - `mask`: `(H, W)` bool, pixels to render (default all); 0 elsewhere.

    **Returns:** `(K, H, W)` images in the training images' units and the dtype of `normals`
    (jitted for the MLP methods; the Delaunay baseline runs in scipy). Lambert's term is clamped
    at 0 (attached shadows); cast shadows are not modelled.
    """
    normals = jnp.asarray(normals)
    if not jnp.issubdtype(normals.dtype, jnp.floating):
        normals = normals.astype(jnp.float32)
    if normals.ndim != 3 or normals.shape[-1] != 3:
        raise ValueError(f"normals must be (H, W, 3), got {normals.shape}")
    hw = normals.shape[:2]
    albedo = _check_albedo(albedo, hw, normals.dtype)
    lights = _check_lights(lights, normals.dtype, hw)
    if mask is not None and np.shape(mask) != hw:
        raise ValueError(f"mask must have shape (H, W) = {hw}, got {np.shape(mask)}")
    if model.gate is not None:  # method="auto": Lambert's law outside the gate
        if model.gate.shape != hw:
            raise ValueError(f"the model's gate is {model.gate.shape}, normals are {hw}")
        full, lam = (relight(dataclasses.replace(model, **kw), normals, albedo, lights, mask=mask)
                     for kw in ({"gate": None}, {"gate": None, "method": "lambertian"}))
        return lam + model.gate.astype(lam.dtype)[None] * (full - lam)
    if model.method == "delaunay":
        sel = np.ones(hw, bool) if mask is None else np.asarray(mask, bool)
        f = np.asarray(_features(normals, lights), np.float64)[:, sel]  # (K, M, 5)
        ratio = np.zeros((lights.shape[0], *hw))
        ratio[:, sel] = model.interpolator(f[..., :3].reshape(-1, 3)).reshape(f.shape[:2])
        return jnp.asarray(ratio, normals.dtype) * albedo[None]
    if model.method in _parametric.PARAMETRIC_METHODS:
        if model.params.specular.shape != hw:
            raise ValueError(f"normals must be (H, W, 3) = {(*model.params.specular.shape, 3)}"
                             f" (the grid the parametric model was fitted on), got {(*hw, 3)}")
        out = _parametric.render(model.method, model.params, normals, albedo, lights)
        return out if mask is None else jnp.where(jnp.asarray(mask, bool)[None], out,
                                                  jnp.zeros((), out.dtype))
    out = _relight(*_relight_args(model), normals, albedo, lights)
    if mask is not None:
        out = jnp.where(jnp.asarray(mask, bool)[None], out, jnp.zeros((), out.dtype))
    return out


def _relight_args(model):
    """The static settings and the arrays of `model` that `_relight_kernel` reads: a plain
    `jit` of these dispatches faster than `equinox.filter_jit` of the whole model, and never
    sees the fit report (a static field, which would recompile every new fit)."""
    return ((model.method, model.bound, model.cell, model.lambertian_base, model.use_xy),
            (model.params, model.box_lo, model.box_hi, model.support, model.rho_ref))


def _relight_kernel(config, arrays, normals, albedo, lights):
    """`(K, H, W)` images, feature-major: every image-sized quantity is a `(K, P)` array
    (P = H W; per-pixel terms `(1, P)`), so the whole render is elementwise work that XLA fuses
    and vectorises. The same model as `_predict_one` (tests/test_brdf.py checks it against a
    numpy reference): the small matrix products of the MLP are unrolled into multiply-adds over
    whole arrays (a per-sample `w @ z` under `vmap`, or a `(10, 10) @ (10, P)` GEMM, were 3-10x
    slower on the CPU), and cos θi is n·l."""
    method, bound, cell, lambertian_base, use_xy = config
    params, box_lo, box_hi, support, rho_ref = arrays
    dtype = normals.dtype
    k = lights.shape[0]
    h, w, _ = normals.shape
    if lights.ndim == 4:  # per pixel: (K, P, 3)
        lights = lights.reshape(k, h * w, 3)
    theta_i, theta_r, delta, cos_i = _angles_elementwise(normals, lights)
    rho = albedo.reshape(1, -1)
    lambert = rho * jnp.maximum(cos_i, 0)
    if method == "lambertian":
        return lambert.reshape(k, h, w)
    params = jax.tree.map(lambda a: a.astype(dtype), params)
    box_lo, box_hi = box_lo.astype(dtype), box_hi.astype(dtype)
    span = jnp.maximum(box_hi - box_lo, jnp.asarray(1e-6, dtype))
    u = [theta_i - theta_r, theta_i + theta_r, delta]
    if lambertian_base:
        u = [jnp.clip(u[j], box_lo[j], box_hi[j]) for j in range(3)]
    z = [2 * (u[j] - box_lo[j]) / span[j] - 1 for j in range(3)]
    if use_xy:  # a row and a column broadcast in the kernel, not two image constants
        xy = pixel_coordinates(h, w, dtype)
        x = jnp.broadcast_to(xy[0, :, 0][None], (h, w)).reshape(1, -1)
        y = jnp.broadcast_to(xy[:, 0, 1][:, None], (h, w)).reshape(1, -1)
    else:
        x = y = jnp.zeros((1, 1), dtype)
    g = _mlp_elementwise(params, [*z, x, y])
    amp = rho if method == "mlp_ratio" else rho_ref.astype(dtype)
    if not lambertian_base:
        out = amp * g
    else:
        weight = _support_weight(support.astype(dtype), (theta_i, theta_r, delta), cell)
        out = lambert + amp * weight * bound * _tanh(g)
    return jnp.broadcast_to(out, (k, h * w)).reshape(k, h, w)


# Compiled with 512-bit vectors on the CPU outside any trace (`CpuTuned`): AVX-512 for this
# elementwise kernel (tanh, the angle polynomials) gave bit-identical results, 9.9 -> 8.6 ms
# median for a 700x850 MLP relight on this project's CPU, in the same rounds
# (`benchmarks/bench_brdf.py --part speed`, whose "default vector width" row calls `.plain`).
# A preference only: CPUs without AVX-512 keep their width, other backends ignore it.
_WIDE_VECTORS = {"xla_cpu_prefer_vector_width": 512}
_relight = CpuTuned(_relight_kernel, _WIDE_VECTORS, static_argnums=0)


def _mlp_elementwise(params, rows):
    """`_mlp` on a list of input arrays (one per input unit, broadcasting against each other):
    every unit is a sum of scalar-times-array terms, so the network is elementwise."""
    for layer, (w, b) in enumerate(params):
        n_out, n_in = w.shape
        out = []
        for o in range(n_out):
            acc = b[o] + w[o, 0] * rows[0]
            for i in range(1, n_in):
                acc = acc + w[o, i] * rows[i]
            out.append(acc)
        rows = out if layer == len(params) - 1 else [_tanh(a) for a in out]
    return rows[0]


def extrapolation_mask(
    model: BRDFModel,
    normals: Float[ArrayLike, "H W 3"],
    lights: Float[ArrayLike, "K 3"] | Float[ArrayLike, "K H W 3"],
) -> Bool[Array, "K H W"]:
    """`(K, H, W)` bool: samples where `model` has no training data nearby, under `(K, 3)`
    distant or `(K, H, W, 3)` per-pixel lights.

    For the MLP methods and Lambertian: (θi, θr, Δα) where the support grid's interpolated
    occupancy is below 0.5 (the MLP's correction is scaled by that occupancy, so it fades to
    Lambert's law there); for Delaunay: (θi, θr, Δα) outside the triangulation's convex
    hull or in a degenerate simplex (Lambert's law is returned there).
    """
    normals = jnp.asarray(normals)
    if not jnp.issubdtype(normals.dtype, jnp.floating):
        normals = normals.astype(jnp.float32)
    if normals.ndim != 3 or normals.shape[-1] != 3:
        raise ValueError(f"normals must be (H, W, 3), got {normals.shape}")
    lights = _check_lights(lights, normals.dtype, normals.shape[:2])
    f = _features(normals, lights)
    if model.method == "delaunay":
        ang = np.asarray(f[..., :3], np.float64)
        return jnp.asarray(model.interpolator.outside(ang.reshape(-1, 3)).reshape(ang.shape[:3]))
    return _support_weight_jit(model.support.astype(f.dtype), f, model.cell) < 0.5


@eqx.filter_jit
def _support_weight_jit(support, f, cell):
    return _support_weight(support, (f[..., 0], f[..., 1], f[..., 2]), cell)

