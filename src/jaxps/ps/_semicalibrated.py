"""Semi-calibrated photometric stereo: per-frame light intensities fitted with albedo and normals.

Light directions are known, but each frame's light *intensity* $e_k$ is not (a flash that fires a
little brighter or dimmer each time). Lambert's law becomes $i_{kp} = e_k\\, l_k \\cdot b_p$ with
$b_p = \\rho_p n_p$. We solve

$$\\min_{e}\\ \\frac{\\sum_{k,p} w_{kp} (i_{kp} - e_k\\, l_k \\cdot b_p(e))^2}
       {\\sum_{k,p} w_{kp} i_{kp}^2}
  + \\lambda \\sum_k (\\log e_k - \\log e^0_k)^2,$$

where $b_p(e)$ is the per-pixel weighted least-squares solution for fixed intensities (variable
projection: the normals are eliminated in closed form, so only the $K$ intensities are iterated on)
and $w_{kp}$ keeps the usable samples (finite, unsaturated, above the shadow and dark thresholds,
inside the mask). This is the joint least-squares problem of Cho, Matsushita, Tai & Kweon,
"Semi-Calibrated Photometric Stereo", TPAMI 2018 (CVPR 2016 short version), solved by
Levenberg–Marquardt over $\\log e$ (optimistix) rather than by their alternating updates: the
alternating scheme converges linearly and needed several hundred steps on real five-light faces;
the fixed points are the same. The first term is the paper's; the optional second term (weight
`prior_weight`, default 0) pulls the intensities toward the "frontal" estimate below.

**Scale ambiguity.** $(e, b) \\to (s e, b / s)$ leaves the images unchanged, so the intensities are
returned with geometric mean 1 ($\\prod_k e_k = 1$); albedo is then relative to that mean light.

**Frontal estimate** (`_frontal`; `intensity_estimate(..., method="frontal")` in
`_intensities.py` explains it): the face scanners' mean-intensity equalisation corrected for each
light's obliquity.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..core._linalg import REL_DET_MIN, solve3
from ..core._status import Status
from ._l2 import PSResult, ps_l2

__all__ = ["ps_semi_calibrated"]


def _geo_normalise(e):
    return e / jnp.exp(jnp.mean(jnp.log(e)))


def _usable(images, mask, sample_mask, thresholds):
    """`(K, P)` grey samples and `(K, P)` 0/1 weights of the samples a fit may use."""
    dark, saturation, shadow = thresholds
    finite = jnp.all(jnp.isfinite(images), axis=-1)
    clean = jnp.where(finite[..., None], images, 0)
    grey = jnp.mean(clean, axis=-1)
    saturated = jnp.any(clean >= saturation, axis=-1)
    ok = finite & ~saturated & sample_mask & mask[None] & (grey > dark) & (grey >= shadow)
    return grey, ok.astype(images.dtype)


def _pixel_b(i, w, lights_e):
    """One pixel: weighted least-squares $b$ for lights already scaled by intensity.

    `i` `(K,)`, `w` `(K,)` 0/1, `lights_e` `(K, 3)`. Returns `b` `(3,)` and whether it is usable.
    """
    a = jnp.einsum("k,ki,kj->ij", w, lights_e, lights_e)
    r = lights_e.T @ (w * i)
    b, rel_det = solve3(a, r)
    good = (jnp.sum(w) >= 3) & (rel_det > REL_DET_MIN)
    return jnp.where(good, b, 0), good


def _residuals(x, args):
    """Variable-projection residuals: data term over the sub-sampled pixels, then the prior."""
    grey, w, lights, log_e0, prior_scale, data_scale = args
    log_e = jnp.concatenate([jnp.zeros((1,), x.dtype), x])
    log_e = log_e - jnp.mean(log_e)
    e = jnp.exp(log_e)
    lights_e = e[:, None] * lights
    b, good = jax.vmap(_pixel_b, in_axes=(1, 1, None))(grey, w, lights_e)  # (P, 3), (P,)
    pred = lights_e @ b.T  # (K, P)
    data = (w * good[None].astype(w.dtype) * (grey - pred) / data_scale).reshape(-1)
    prior = prior_scale * (log_e - log_e0)
    return jnp.concatenate([data, prior])


def _frontal(grey, w, lights):
    """Intensities from per-frame means over commonly usable pixels and the frontal prior."""
    common = jnp.prod(w, axis=0)  # pixels usable in every frame
    n = jnp.maximum(jnp.sum(common), 1)
    means = jnp.sum(grey * common[None], axis=1) / n
    tiny = jnp.finfo(grey.dtype).tiny
    e = jnp.maximum(means, tiny) / jnp.maximum(lights[:, 2], 1e-3)
    return _geo_normalise(e), jnp.sum(common) > 0


@eqx.filter_jit
def _fit_intensities(images, lights, mask, sample_mask, thresholds, stride, solver, max_steps,
                     prior_weight):
    sub = images[:, ::stride, ::stride]
    grey, w = _usable(sub, mask[::stride, ::stride], sample_mask[:, ::stride, ::stride],
                      thresholds)
    k = grey.shape[0]
    grey = grey.reshape(k, -1)
    w = w.reshape(k, -1)
    e0, have_common = _frontal(grey, w, lights)
    data_scale = jnp.sqrt(jnp.maximum(jnp.sum(w * grey**2), jnp.finfo(grey.dtype).tiny))
    prior_scale = jnp.sqrt(jnp.asarray(prior_weight, grey.dtype))
    log_e0 = jnp.log(e0)
    x0 = (log_e0 - log_e0[0])[1:]
    sol = optx.least_squares(
        _residuals, solver, x0,
        args=(grey, w, lights, log_e0, prior_scale, data_scale),
        max_steps=max_steps, throw=False,
    )
    log_e = jnp.concatenate([jnp.zeros((1,), x0.dtype), sol.value])
    e = _geo_normalise(jnp.exp(log_e - jnp.mean(log_e)))
    finite = jnp.all(jnp.isfinite(e)) & jnp.all(e > 0)
    converged = (sol.result == optx.RESULTS.successful) & finite & have_common
    e = jnp.where(finite, e, e0)
    return e, e0, converged, sol.stats["num_steps"]


def ps_semi_calibrated(
    images, lights, mask, sample_mask, thresholds, *,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 100,
    prior_weight: float = 0.0,
    max_pixels: int = 65536,
    intensities=None,
) -> PSResult:
    """Solver `"semi_calibrated"`: per-frame intensities, then calibrated L2 PS with them.

    Called through `jaxps.photometric_stereo(images, lights, method="semi_calibrated", ...)`.

    **Arguments** (keyword options of `photometric_stereo`):
    - `solver`: an optimistix least-squares solver for the intensities (default
      `optx.LevenbergMarquardt(rtol=1e-6, atol=1e-8)`).
    - `max_steps`: step limit of that solver.
    - `prior_weight`: $\\lambda$ above; 0 (default) is the paper's pure joint least squares.
    - `max_pixels`: the intensities are fitted on a regular sub-grid of at most about this many
      pixels (K numbers need few pixels); the normals are then solved at every pixel.
    - `intensities`: `(K,)` known intensities; skips the fit (calibrated PS with scaled lights).

    **Returns:** a `PSResult` whose `info` holds `intensities` `(K,)` (geometric mean 1),
    `frontal_intensities` `(K,)` (the closed-form start), `converged` (bool scalar) and
    `steps`. If the fit did not converge, solved pixels get `Status.NOT_CONVERGED` (with the
    default outputs), so nothing is silently trusted.
    """
    k, h, w, _ = images.shape
    if lights.ndim != 2:
        raise ValueError("lights: method='semi_calibrated' needs (K, 3) distant lights")
    if k < 4:
        raise ValueError(
            f"images: semi-calibrated photometric stereo needs K >= 4 frames (got K={k}); "
            "with 3 frames every intensity set fits exactly"
        )
    if not (isinstance(max_steps, int) and max_steps >= 1):
        raise ValueError(f"max_steps must be a positive int, got {max_steps!r}")
    if not (np.isfinite(prior_weight) and prior_weight >= 0):
        raise ValueError(f"prior_weight must be finite and >= 0, got {prior_weight!r}")
    if not (isinstance(max_pixels, int) and max_pixels >= 16):
        raise ValueError(f"max_pixels must be an int >= 16, got {max_pixels!r}")
    dtype = images.dtype
    if intensities is not None:
        e = jnp.asarray(intensities, dtype)
        if e.shape != (k,) or not bool(jnp.all(jnp.isfinite(e)) & jnp.all(e > 0)):
            raise ValueError(f"intensities must be ({k},) finite and positive, got {e}")
        e = _geo_normalise(e)
        e0, converged, steps = e, jnp.asarray(True), jnp.asarray(0)
    else:
        if solver is None:
            solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-8)
        stride = max(1, math.ceil(math.sqrt(h * w / max_pixels)))
        e, e0, converged, steps = _fit_intensities(
            images, lights, mask, sample_mask, thresholds, stride, solver, max_steps,
            prior_weight,
        )
    return _finish(images, lights, mask, sample_mask, thresholds, e, e0, converged, steps)


@jax.jit
def _finish(images, lights, mask, sample_mask, thresholds, e, e0, converged, steps):
    res = ps_l2(images, e[:, None].astype(lights.dtype) * lights, mask, sample_mask, thresholds)
    failed = (res.status == Status.OK) & ~converged
    status = jnp.where(failed, Status.NOT_CONVERGED, res.status).astype(jnp.int32)
    keep = status == Status.OK
    default_n = jnp.array([0, 0, 1], res.normals.dtype)
    return PSResult(
        jnp.where(keep[..., None], res.normals, default_n),
        jnp.where(keep[..., None], res.albedo, 0),
        status,
        res.n_used,
        jnp.where(keep, res.residual, 0),
        {"intensities": e, "frontal_intensities": e0, "converged": converged,
         "steps": jnp.asarray(steps, jnp.int32)},
    )
