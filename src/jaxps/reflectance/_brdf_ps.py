"""BRDF-in-the-loop photometric stereo: re-estimate normals and albedo with a fitted BRDF.

The five-source face-scanner paper's stated future work: instead of Lambert's law, invert the
BRDF fitted to the same images (`jaxps.fit_brdf`) per pixel, refit the BRDF on the new normals,
and iterate. Each pixel solves

$$ \\min_{p, q, \\rho} \\sum_k \\big(I_k - f(n(p, q), \\rho; l_k)\\big)^2,\\quad
   n = (-p, -q, 1)/\\|(-p, -q, 1)\\| $$

with the per-pixel Levenberg–Marquardt of `core/_batched_lm.py` (a one-pixel kernel lifted with
`jax.vmap`, run in tiles and rounds; optimistix under `vmap` did the same two orders of
magnitude slower), started from the current normals and albedo; $f$ is the model's `relight`
for one sample.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from ..core._batched_lm import BatchedLM, map_pixels, solve_pixels
from ..core._progress import ProgressHook, Stages
from ..core._random import as_key
from ..core._status import Status
from ..ps import PSResult, photometric_stereo
from ._brdf import BRDF_METHODS, _predict_one, fit_brdf
from ._features import _sample_angles, pixel_coordinates

__all__ = ["brdf_photometric_stereo"]


def _pixel_residual(y, args):
    model, intensities, lights, xy = args
    p, q, rho = y[0], y[1], y[2]
    n = jnp.stack([-p, -q, jnp.ones_like(p)])
    n = n / jnp.linalg.norm(n)
    view = jnp.array([0, 0, 1], n.dtype)

    def one(light):
        f = jnp.concatenate([_sample_angles(n, light, view), xy])
        if model.method == "lambertian":
            return rho * jnp.maximum(jnp.cos(f[0]), 0)
        return _predict_one(model.params, f, rho, model.box_lo, model.box_hi, model.support,
                            model.rho_ref, model.bound, model.cell, model.lambertian_base,
                            model.method == "mlp_ratio", model.use_xy)

    return jax.vmap(one)(lights) - intensities


@eqx.filter_jit
def _solve_pixels(model, images, lights, normals, albedo, xy, max_steps):
    k = images.shape[0]
    flat = images.reshape(k, -1)  # (K, N): pixel axis last, as `solve_pixels` wants
    pix = xy.reshape(-1, 2).T
    n = normals.reshape(-1, 3)
    nz = jnp.maximum(n[:, 2], 1e-3)
    y0 = (-n[:, 0] / nz, -n[:, 1] / nz, albedo.reshape(-1))

    def fn(y, a):
        return _pixel_residual(y, (model, a[0], lights, a[1]))

    y, ok, _ = solve_pixels(fn, y0, (flat, pix), jnp.ones(flat.shape[1], bool),
                            BatchedLM(rtol=1e-5, atol=1e-7), max_steps=max_steps)
    nn = jnp.stack([-y[0], -y[1], jnp.ones_like(y[0])], axis=-1)
    nn = nn / jnp.linalg.norm(nn, axis=-1, keepdims=True)
    res = map_pixels(fn, y, (flat, pix))
    return nn, y[2], ok, jnp.sqrt(jnp.mean(res**2, axis=0))


def brdf_photometric_stereo(
    images: Float[ArrayLike, "K H W"],
    lights: Float[ArrayLike, "K 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    method: str = "mlp_ratio",
    iterations: int = 2,
    key: jax.Array | int | None = None,
    max_steps: int = 20,
    progress: ProgressHook | None = None,
    **fit_options,
) -> PSResult:
    """Photometric stereo with the BRDF fitted to the same images, iterated.

    L2 photometric stereo gives the first normals and albedo; then `iterations` times: fit the
    BRDF (`fit_brdf(..., method=method, key=key)`) on the current normals and albedo, and
    re-solve every pixel's normal and albedo under that BRDF (module docstring), against the
    frames divided by the fit's frame gains (`BRDFFit.frame_gains`) when it has them.

    **Arguments:**
    - `images`: `(K, H, W)` grey, floating, linear; `lights`: `(K, 3)` above the horizon.
    - `mask`: `(H, W)` bool pixels to solve (default all).
    - `method`: a `jaxps.BRDF_METHODS` name other than `"delaunay"` (not differentiable).
    - `iterations`: BRDF fit + per-pixel re-solve rounds (0 returns L2 photometric stereo).
    - `key` (a JAX PRNG key or an int seed), `**fit_options`: passed to `fit_brdf`.
    - `max_steps`: per-pixel LM step limit.
    - `progress`: a hook told of each stage as it starts (the L2 solve, then each round's fit
      and re-solve): `jaxps.report.progress_bar()` draws a bar on stderr. `info["times_s"]`
      has the stages' times either way (a first call's include compiling).

    **Returns:** a `PSResult`; `status` is `NOT_CONVERGED` where a pixel's last solve hit its
    step limit, and `info` holds `{"models": [...], "iterations": iterations, "times_s":
    {stage: seconds}}` (the stages "l2", "fit 1", "solve 1", "fit 2", ...).
    """
    if method not in BRDF_METHODS or method == "delaunay":
        raise ValueError(f"method must be one of {BRDF_METHODS} except 'delaunay', got {method!r}")
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    key = as_key(key)
    images = jnp.asarray(images)
    with Stages(1 + 2 * iterations, progress) as stages:
        res = stages.run("L2 photometric stereo", photometric_stereo, images, lights, mask=mask,
                         time_key="l2")
        h, w = images.shape[1:]
        ok = np.asarray(res.status) == Status.OK
        if not ok.any():
            raise ValueError("no pixel solved by L2 photometric stereo: nothing to refine")
        lights_j = jnp.asarray(res.normals.dtype.type(1) * np.asarray(lights, np.float32))
        lights_j = lights_j / jnp.linalg.norm(lights_j, axis=-1, keepdims=True)
        xy = pixel_coordinates(h, w, images.dtype)
        normals, albedo, status, residual = res.normals, res.albedo, res.status, res.residual
        models = []
        for i in range(1, iterations + 1):
            model = stages.run(f"fit {method} ({i}/{iterations})", fit_brdf, images, normals,
                               albedo, lights_j, mask=ok, method=method, key=key,
                               time_key=f"fit {i}", **fit_options)
            models.append(model)
            # the fit explains frame k as g_k times the model, so re-solve against I_k / g_k
            frames = images
            if model.fit.frame_gains is not None:
                frames = images / jnp.asarray(model.fit.frame_gains, images.dtype)[:, None, None]
            n, rho, conv, rms = stages.run(f"re-solve pixels ({i}/{iterations})", _solve_pixels,
                                           model, frames, lights_j, normals, albedo, xy, max_steps,
                                           time_key=f"solve {i}")
            good = jnp.asarray(ok).reshape(-1) & jnp.all(jnp.isfinite(n), axis=-1) & (rho > 0)
            normals = jnp.where(good[:, None], n, normals.reshape(-1, 3)).reshape(h, w, 3)
            albedo = jnp.where(good, rho, albedo.reshape(-1)).reshape(h, w)
            residual = jnp.where(good, rms, residual.reshape(-1)).reshape(h, w)
            status = jnp.where(jnp.asarray(ok) & ~conv.reshape(h, w), Status.NOT_CONVERGED,
                               res.status).astype(jnp.int32)
        return PSResult(normals.astype(images.dtype), albedo.astype(images.dtype), status,
                        res.n_used, residual.astype(images.dtype),
                        {"models": models, "iterations": iterations, "times_s": stages.times})
