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

from ..core._host import NO_YNN, CpuTuned, cpu_top_level
from ..core._linalg import REL_DET_MIN, solve3
from ._l2 import PSResult, ps_l2_eager
from ._visibility import flash_visibility

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


def _objective(x, args):
    r = _residuals(x, args)
    return jnp.sum(r * r)


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
    args = (grey, w, lights, log_e0, prior_scale, data_scale)
    sol = optx.least_squares(_residuals, solver, x0, args=args, max_steps=max_steps,
                             throw=False)
    log_e = jnp.concatenate([jnp.zeros((1,), x0.dtype), sol.value])
    e = _geo_normalise(jnp.exp(log_e - jnp.mean(log_e)))
    start_cost, end_cost = _objective(x0, args), _objective(sol.value, args)
    # Usable: finite and no worse than the closed-form start. A fit that stopped at its step
    # limit but lowered the objective is kept (its pixels are solved as usual; `converged`
    # says it stopped early); anything else falls back to the start.
    usable = (jnp.all(jnp.isfinite(e)) & jnp.all(e > 0) & jnp.isfinite(end_cost)
              & (end_cost <= start_cost))
    converged = (sol.result == optx.RESULTS.successful) & usable & have_common
    e = jnp.where(usable, e, e0)
    costs = jnp.stack([start_cost, jnp.where(usable, end_cost, start_cost)])
    return e, e0, converged, ~usable | ~have_common, sol.stats["num_steps"], costs


# Without YNNPACK fusions (`core._host.NO_YNN`): the LM steps' sums over the K frames ran
# faster in XLA's own loops (`benchmarks/bench_ynn.py`).
_fit_intensities = CpuTuned(_fit_intensities, NO_YNN, jit=eqx.filter_jit)


def _default_solver(dtype) -> optx.LevenbergMarquardt:
    """The intensity fit's default: Levenberg–Marquardt stopping when a step changes the
    log-intensities and the objective by less than `rtol` (relative) + `atol`.

    The tolerances follow the dtype: the objective is a sum over up to ~65k pixels times K
    frames, whose float32 rounding (~1e-6 relative) is above a 1e-6 test, so a float32 fit at
    the optimum kept stepping to its limit (a 29-light face: 100 steps, not converged, at the
    intensities it had reached in ~20). 1e-4 is 0.01% of an intensity, far below what the
    normals can feel.
    """
    if jnp.finfo(dtype).bits <= 32:
        return optx.LevenbergMarquardt(rtol=1e-4, atol=1e-6)
    return optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10)


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
      `_default_solver(dtype)`: Levenberg–Marquardt, `rtol=1e-4, atol=1e-6` in float32).
    - `max_steps`: step limit of that solver.
    - `prior_weight`: $\\lambda$ above; 0 (default) is the paper's pure joint least squares.
    - `max_pixels`: the intensities are fitted on a regular sub-grid of at most about this many
      pixels (K numbers need few pixels); the normals are then solved at every pixel.
    - `intensities`: `(K,)` known intensities; skips the fit (calibrated PS with scaled lights).

    **Returns:** a `PSResult` whose `info` holds `intensities` `(K,)` (geometric mean 1),
    `frontal_intensities` `(K,)` (the closed-form start), `converged` (bool scalar: the fit
    met its stopping rule), `fallback` (bool scalar: the fit was unusable, non-finite or worse
    than its start, and the start was used instead), `steps` and `objective` `(2,)` (the
    normalised objective at the start and at the intensities used) and `visibility`
    (`flash_visibility` of the lights: near 0, the frames cannot tell some flash strengths
    from a tilt of the surface, and the fit may trade one for the other). The capture is never
    discarded: a fit that stopped at `max_steps` but lowered the objective keeps its
    intensities, a failed one falls back to the frontal start; per-pixel `status` is that of
    the L2 solve with the intensities used, and `converged`/`fallback` say which case it was.
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
        fallback, costs = jnp.asarray(False), jnp.zeros((2,), dtype)
    else:
        if solver is None:
            solver = _default_solver(dtype)
        stride = max(1, math.ceil(math.sqrt(h * w / max_pixels)))
        e, e0, converged, fallback, steps, costs = _fit_intensities(
            images, lights, mask, sample_mask, thresholds, stride, solver, max_steps,
            prior_weight,
        )
    return _finish(images, lights, mask, sample_mask, thresholds, e, e0, converged,
                   fallback, steps, costs)


def _finish(images, lights, mask, sample_mask, thresholds, e, e0, converged, fallback, steps,
            costs):
    """Calibrated L2 with the intensities `e` folded into the lights, and the fit's `info`.
    Outside a trace the scaled lights are formed on the host, so that `ps_l2_eager` takes
    L2's branch there and compiles only the solve it runs."""
    if cpu_top_level(images, lights, e, mask, sample_mask, thresholds):
        lights_e = (np.asarray(e, np.float64)[:, None] * np.asarray(lights, np.float64))
        lights_e = lights_e.astype(lights.dtype)
    else:
        lights_e = e[:, None].astype(lights.dtype) * lights
    res = ps_l2_eager(images, lights_e, mask, sample_mask, thresholds)
    return PSResult(
        res.normals, res.albedo, res.status, res.n_used, res.residual,
        {"intensities": e, "frontal_intensities": e0, "converged": converged,
         "fallback": fallback, "steps": jnp.asarray(steps, jnp.int32),
         "objective": costs,
         "visibility": jnp.asarray(flash_visibility(lights), images.dtype)},
    )
