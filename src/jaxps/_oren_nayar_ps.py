"""Oren–Nayar-aware photometric stereo: normal, albedo and roughness per pixel.

Lambertian photometric stereo (Woodham 1980) read with the Oren–Nayar model (SIGGRAPH 1994,
qualitative form by default; see `_oren_nayar.py`) in place of Lambert's law. Per pixel the
unknowns are the surface gradient $(p, q)$ (so $n = (-p, -q, 1)/\\|\\cdot\\|$ always faces the
camera), the albedo $\\rho$ and $s = \\sigma^2$. The albedo is eliminated in closed form
(variable projection, $\\rho = \\sum I f / \\sum f^2$), leaving a 3-parameter least-squares
problem per pixel, started from the Lambertian (`l2`) solution and $\\sigma = $ `sigma0`, and
solved for all pixels at once by the batched Levenberg–Marquardt of `_batched_lm.py` (step
limit, per-pixel convergence flag). View direction $v = (0, 0, 1)$.

`sigma=` chooses what is shared: `"pixel"` (joint per-pixel fit), `"global"` (joint per-pixel
fit, then one $\\sigma$ fitted to those normals with optimistix, then the normals re-solved
with it fixed), or a known $\\sigma$ (a scalar or an `(H, W)` map), with only $(p, q)$ fitted.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._batched_lm import BatchedLM, batched_least_squares
from ._l2 import PSResult, ps_l2
from ._oren_nayar import SIGMA_MAX, _check_form, _shading, fit_roughness
from ._status import Status

__all__ = ["ps_oren_nayar"]

# A joint (p, q, sigma) fit with a free albedo needs more samples than unknowns.
_MIN_SAMPLES_JOINT = 5


def _normal(y):
    """Unit normals `(N, 3)` from gradients `y[:, 0] = p`, `y[:, 1] = q`."""
    p, q = y[:, 0], y[:, 1]
    inv = jax.lax.rsqrt(1 + p * p + q * q)
    return jnp.stack([-p * inv, -q * inv, inv], axis=-1)


def _model(y, s, lights, form):
    """$f$ `(K, N)` for gradients `y` `(N, >=2)` and $s$ `(N,)`."""
    n = _normal(y)
    cos_i = lights @ n.T
    cos_r = n[:, 2][None]
    p = lights[:, 2:3] - cos_i * cos_r
    return _shading(cos_i, cos_r, p, s[None], form)


def _albedo(i, w, f):
    num = jnp.sum(w * i * f, axis=0)
    den = jnp.sum(w * f * f, axis=0)
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1), 0)


def _residual_joint(y, data):
    i, w, lights, form = data
    f = _model(y, y[:, 2], lights, form)
    return w * (i - _albedo(i, w, f)[None] * f)


def _residual_fixed(y, data):
    i, w, lights, form, s = data
    f = _model(y, s, lights, form)
    return w * (i - _albedo(i, w, f)[None] * f)


def _gradients(n):
    nz = jnp.maximum(n[:, 2], 0.05)
    return jnp.stack([-n[:, 0] / nz, -n[:, 1] / nz], axis=-1)


def _solve(grey, w, lights, y0, s_fixed, s_max, form, solver, max_steps):
    dtype = grey.dtype
    if s_fixed is None:
        fn = lambda y, d: _residual_joint(y, d + (form,))  # noqa: E731
        lower = jnp.asarray([-jnp.inf, -jnp.inf, 0], dtype)
        upper = jnp.asarray([jnp.inf, jnp.inf, s_max], dtype)
        return batched_least_squares(fn, y0, (grey, w, lights), solver, max_steps=max_steps,
                                     lower=lower, upper=upper)
    fn = lambda y, d: _residual_fixed(y, d[:3] + (form, d[3]))  # noqa: E731
    return batched_least_squares(fn, y0[:, :2], (grey, w, lights, s_fixed), solver,
                                 max_steps=max_steps)


def ps_oren_nayar(images, lights, mask, sample_mask, thresholds, *, sigma="pixel",
                  form="qualitative", solver=None, max_steps=50, sigma0=0.2,
                  sigma_max=SIGMA_MAX):
    """`jaxps.photometric_stereo(..., method="oren_nayar")`: see the module docstring.

    **Options:**
    - `sigma`: `"pixel"` (default), `"global"`, or a known roughness (radians) as a scalar or
      `(H, W)` array.
    - `form`: `"qualitative"` (default) or `"full"` Oren–Nayar.
    - `solver`: a `jaxps.BatchedLM` (default `BatchedLM()`); `max_steps`: its step limit.
    - `sigma0`: starting roughness; `sigma_max`: its upper bound (radians).

    **Returns:** a `PSResult`; `info` holds `sigma` (`(H, W)` radians, or the global value
    broadcast), `sigma_status` (`(H, W)` `Status`: `AT_BOUND` where $\\sigma$ ended on 0 or
    `sigma_max`, `TOO_FEW_LIGHTS` where fewer than 5 samples leave $\\sigma$ unfitted and the
    Lambertian answer is kept) and `steps` (`(H, W)` int32). Pixels whose solve hits the
    step limit get `NOT_CONVERGED` with the DESIGN failure outputs.
    """
    _check_form(form)
    if np.ndim(lights) != 2:
        raise ValueError("method='oren_nayar' needs distant lights (K, 3), not per-pixel lights")
    if solver is None:
        solver = BatchedLM()
    if not isinstance(solver, BatchedLM):
        raise ValueError(f"solver must be a jaxps.BatchedLM, got {type(solver).__name__}")
    if not (0 < sigma_max <= np.pi / 2) or not (0 <= sigma0 < sigma_max):
        raise ValueError(f"need 0 <= sigma0 < sigma_max <= pi/2, got {sigma0}, {sigma_max}")
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    k, h, w, c = images.shape
    dtype = images.dtype
    fixed = None
    if not isinstance(sigma, str):
        fixed = jnp.asarray(sigma, dtype)
        if fixed.shape not in ((), (h, w)):
            raise ValueError(f"sigma must be 'pixel', 'global', a scalar or (H, W), got shape "
                             f"{fixed.shape}")
        if bool(jnp.any(~jnp.isfinite(fixed) | (fixed < 0))):
            raise ValueError("sigma must be finite and >= 0 (radians)")
        fixed = jnp.broadcast_to(fixed, (h, w))
    elif sigma not in ("pixel", "global"):
        raise ValueError(f"sigma must be 'pixel', 'global', a scalar or (H, W), got {sigma!r}")
    return _ps_oren_nayar(images, lights, mask, sample_mask, thresholds, fixed, sigma == "global",
                          form, solver, int(max_steps), sigma0, sigma_max)


def _ps_oren_nayar(images, lights, mask, sample_mask, thresholds, fixed, pool, form, solver,
                   max_steps, sigma0, sigma_max):
    k, h, w, c = images.shape
    dtype = images.dtype
    base = ps_l2(images, lights, mask, sample_mask, thresholds)
    core = eqx.filter_jit(_core)
    out = core(images, lights, mask, sample_mask, thresholds, base, fixed,
               jnp.asarray(sigma0**2, dtype), jnp.asarray(sigma_max**2, dtype), solver,
               form=form, max_steps=max_steps, pool_stage=False)
    if pool:
        normals, _, status, _, _, info = out
        good = mask & (status == Status.OK) & (info["sigma_status"] != Status.TOO_FEW_LIGHTS)
        grey_images = jnp.mean(images, axis=-1)
        fit = fit_roughness(grey_images, normals, base.albedo[..., 0], lights, mask=good,
                            form=form, sample_mask=sample_mask, sigma_max=sigma_max)
        steps0 = info["steps"]
        out = core(images, lights, mask, sample_mask, thresholds, base,
                   jnp.broadcast_to(fit.sigma, (h, w)), jnp.asarray(sigma0**2, dtype),
                   jnp.asarray(sigma_max**2, dtype), solver, form=form, max_steps=max_steps,
                   pool_stage=True)
        info = dict(out.info)
        info["steps"] = info["steps"] + steps0
        info["sigma_status"] = jnp.where(mask, fit.status, Status.MASKED).astype(jnp.int32)
        out = out._replace(info=info)
    return out


def _core(images, lights, mask, sample_mask, thresholds, base, fixed, s0, s_max, solver, *,
          form, max_steps, pool_stage):
    k, h, w, c = images.shape
    dtype = images.dtype
    dark, saturation, shadow = thresholds
    flat = images.reshape(k, h * w, c)
    finite = jnp.all(jnp.isfinite(flat), axis=-1)
    flat = jnp.where(finite[..., None], flat, 0)
    grey = jnp.mean(flat, axis=-1)
    used = (finite & ~jnp.any(flat >= saturation, axis=-1) & sample_mask.reshape(k, -1)
            & (grey >= shadow))
    status0 = base.status.reshape(-1)
    ok0 = status0 == Status.OK
    n_used = jnp.sum(used, axis=0)
    joint = fixed is None
    enough = ok0 & ((n_used >= _MIN_SAMPLES_JOINT) if joint else (n_used >= 3))
    wgt = (used & enough[None]).astype(dtype)

    n0 = base.normals.reshape(-1, 3)
    y0 = jnp.concatenate([_gradients(n0), jnp.full((h * w, 1), s0, dtype)], axis=-1)
    s_fixed = None if joint else (fixed.reshape(-1) ** 2).astype(dtype)
    y, done, steps = _solve(grey, wgt, lights, y0, s_fixed, s_max, form, solver, max_steps)

    normals = _normal(y)
    s = y[:, 2] if joint else s_fixed
    s = jnp.clip(s, 0, s_max)
    # Too few samples for the joint fit: keep the Lambertian answer, sigma 0.
    keep_l2 = ok0 & ~enough
    normals = jnp.where(keep_l2[:, None], n0, normals)
    s = jnp.where(keep_l2, 0, s)
    f = _model(jnp.concatenate([_gradients(normals), s[:, None]], axis=-1), s,
               lights, form)  # (K, N)
    wu = used.astype(dtype)
    rho = jnp.stack([_albedo(flat[..., j], wu, f) for j in range(c)], axis=-1)  # (N, C)
    res = jnp.mean(flat - rho[None] * f[..., None], axis=-1)
    residual = jnp.sqrt(jnp.sum(wu * res**2, axis=0) / jnp.maximum(n_used, 1).astype(dtype))

    status = jnp.where(ok0 & enough & ~done, Status.NOT_CONVERGED, status0)
    status = jnp.where(mask.reshape(-1), status, Status.MASKED).astype(jnp.int32)
    good = status == Status.OK
    normals = jnp.where(good[:, None], normals, jnp.asarray([0, 0, 1], dtype))
    rho = jnp.where(good[:, None], rho, 0)
    residual = jnp.where(good, residual, 0)
    sigma = jnp.where(good, jnp.sqrt(s), 0)
    at_bound = joint & ((s <= 0) | (s >= s_max))
    sig_status = jnp.where(keep_l2, Status.TOO_FEW_LIGHTS,
                           jnp.where(at_bound, Status.AT_BOUND, Status.OK))
    sig_status = jnp.where(good | keep_l2, sig_status, status).astype(jnp.int32)
    info = {"sigma": sigma.reshape(h, w), "sigma_status": sig_status.reshape(h, w),
            "steps": jnp.where(mask.reshape(-1), steps, 0).astype(jnp.int32).reshape(h, w)}
    return PSResult(normals.reshape(h, w, 3), rho.reshape(h, w, c), status.reshape(h, w),
                    n_used.astype(jnp.int32).reshape(h, w), residual.reshape(h, w), info)
