"""Oren–Nayar-aware photometric stereo: normal, albedo and roughness per pixel.

Lambertian photometric stereo (Woodham 1980) read with the Oren–Nayar model (SIGGRAPH 1994,
qualitative form by default; see `shading/_oren_nayar.py`) in place of Lambert's law. Per pixel
the unknowns are the surface gradient $(p, q)$ (so $n = (-p, -q, 1)/\\|\\cdot\\|$ always faces the
camera), the albedo $\\rho$ and $s = \\sigma^2$. The albedo is eliminated in closed form
(variable projection, $\\rho = \\sum I f / \\sum f^2$), leaving a 3-parameter least-squares
problem per pixel, started from the Lambertian (`l2`) solution and $\\sigma = $ `sigma0`, and
solved for all pixels at once by the batched Levenberg–Marquardt of `core/_batched_lm.py` (step
limit, per-pixel convergence flag). View direction $v = (0, 0, 1)$.

`sigma=` chooses what is shared: `"pixel"` (joint per-pixel fit), `"global"` (joint per-pixel
fit, then one $\\sigma$ fitted to those normals with optimistix, then the normals re-solved
with it fixed), or a known $\\sigma$ (a scalar or an `(H, W)` map), with only $(p, q)$ fitted.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..core._batched_lm import BatchedLM, map_pixels, solve_pixels
from ..core._linalg import solve3
from ..core._reduce import sum0
from ..core._status import Status
from ..shading._oren_nayar import (
    SIGMA_MAX,
    _albedo,
    _basis,
    _check_form,
    _exact_pixels,
    _geometry,
    _shading,
    fit_roughness,
)
from ._l2 import PSResult, ps_l2_eager

__all__ = ["ps_oren_nayar"]

# A joint (p, q, sigma) fit with a free albedo needs more samples than unknowns.
_MIN_SAMPLES_JOINT = 5
# Closed-form alternation rounds before the LM (see `_start`).
_START_STEPS = 2


def _unit(p, q):
    """Unit normal `(n_x, n_y, n_z)` from the gradient $(p, q)$: $(-p, -q, 1)/\\|\\cdot\\|$."""
    inv = jax.lax.rsqrt(1 + p * p + q * q)
    return -p * inv, -q * inv, inv


def _start(i, w, n, s, lights, s_max, joint, form, steps):
    """A cheap start for the LM: `steps` rounds of (exact $s$ for the normal, qualitative form
    only; then the normal from Lambertian least squares on the images divided by the current
    Oren–Nayar/Lambert ratio). Each round is closed form; the alternation alone converges
    slowly where $\\sigma$ and the normal are coupled, hence the LM after it."""
    exact = joint and form == "qualitative"
    m = [[sum0(w * lights[:, a] * lights[:, b]) for b in range(3)] for a in range(3)]
    for _ in range(steps):
        cos_i, cos_r, p = _geometry(n, lights)
        if exact:
            c, g = _basis(cos_i, cos_r, p, form)
            s = _exact_pixels((i, w, (c, g), None), s_max)
        f = _shading(cos_i, cos_r, p, s, form)
        ratio = jnp.where(cos_i > 0, f / jnp.where(cos_i > 0, cos_i, 1), 1)
        ratio = jnp.where(ratio > 0, ratio, 1)
        x, _ = solve3(m, [sum0(w * lights[:, a] * i / ratio) for a in range(3)])
        norm = jnp.sqrt(x[0] ** 2 + x[1] ** 2 + x[2] ** 2)
        good = (norm > 0) & (x[2] > 0)
        n = jnp.where(good, x / jnp.where(good, norm, 1), n)
    return n, s


def _pixel_start(i, w, n0, s0, lights, s_max, *, joint, form):
    """One pixel's LM start `(p, q, s)` from its Lambertian normal `n0` `(3,)` (see `_start`)."""
    n, s = _start(i, w, n0, s0, lights, s_max, joint, form, _START_STEPS)
    nz = jnp.maximum(n[2], 0.05)
    return -n[0] / nz, -n[1] / nz, s


def _resid(y, a, lights, joint, form):
    """One pixel's residuals $w (I - \\rho f)$ over `y` = $(p, q)$, or $(p, q, s)$ when joint;
    `a` = (i, w, fixed s). The albedo is eliminated in closed form (variable projection).

    Projecting $s$ out exactly too (as `_start` does) would leave a 2-parameter problem, but
    the JVP of that closed form made an LM step 10x slower on XLA-CPU; measured, not kept.
    """
    i, w, s = a
    f = _shading(*_geometry(jnp.stack(_unit(y[0], y[1])), lights), y[2] if joint else s, form)
    return w * (i - _albedo(i, w, f) * f)


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
    _, h, w, _ = images.shape
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
    _, h, w, _ = images.shape
    dtype = images.dtype
    # BatchedLM is a while_loop, which reverse mode cannot differentiate: this solver's outputs
    # are constants to `jax.grad` (zero gradients, documented in docs/photometric_stereo.md).
    images, lights = jax.lax.stop_gradient(images), jax.lax.stop_gradient(lights)
    base = ps_l2_eager(images, lights, mask, sample_mask, thresholds)
    core = eqx.filter_jit(_core)
    out = core(images, lights, mask, sample_mask, thresholds, base, fixed,
               jnp.asarray(sigma0**2, dtype), jnp.asarray(sigma_max**2, dtype), solver,
               form=form, max_steps=max_steps)
    if pool:
        normals, _, status, _, _, info = out
        good = mask & (status == Status.OK) & (info["sigma_status"] != Status.TOO_FEW_LIGHTS)
        grey_images = jnp.mean(images, axis=-1)
        fit = fit_roughness(grey_images, normals, base.albedo[..., 0], lights, mask=good,
                            form=form, sample_mask=sample_mask, sigma_max=sigma_max)
        steps0 = info["steps"]
        out = core(images, lights, mask, sample_mask, thresholds, base,
                   jnp.broadcast_to(fit.sigma, (h, w)), jnp.asarray(sigma0**2, dtype),
                   jnp.asarray(sigma_max**2, dtype), solver, form=form, max_steps=max_steps)
        info = dict(out.info)
        info["steps"] = info["steps"] + steps0
        info["sigma_status"] = jnp.where(mask, fit.status, Status.MASKED).astype(jnp.int32)
        out = out._replace(info=info)
    return out


def _core(images, lights, mask, sample_mask, thresholds, base, fixed, s0, s_max, solver, *,
          form, max_steps):
    k, h, w, c = images.shape
    dtype = images.dtype
    _, saturation, shadow = thresholds
    flat = images.reshape(k, h * w, c)
    finite = jnp.all(jnp.isfinite(flat), axis=-1)
    flat = jnp.where(finite[..., None], flat, 0)
    grey = jnp.mean(flat, axis=-1)
    used = (finite & ~jnp.any(flat >= saturation, axis=-1) & sample_mask.reshape(k, -1)
            & (grey >= shadow))
    status0 = base.status.reshape(-1)
    ok0 = status0 == Status.OK
    n_used = sum0(used)
    joint = fixed is None
    enough = ok0 & ((n_used >= _MIN_SAMPLES_JOINT) if joint else (n_used >= 3))
    wgt = (used & enough[None]).astype(dtype)

    n0 = base.normals.reshape(-1, 3)
    s_start = jnp.full((h * w,), s0, dtype) if joint else (fixed.reshape(-1) ** 2).astype(dtype)
    p, q, s = map_pixels(functools.partial(_pixel_start, lights=lights, s_max=s_max,
                                           joint=joint, form=form), grey, wgt, n0.T, s_start,
                         tile=None)
    fn = functools.partial(_resid, lights=lights, joint=joint, form=form)
    bounds = {"lower": (None, None, 0), "upper": (None, None, s_max)} if joint else {}
    y, done, steps = solve_pixels(fn, (p, q, s) if joint else (p, q), (grey, wgt, s),
                                  ok0 & enough, solver, max_steps=max_steps, **bounds)
    normals = jnp.stack(_unit(y[0], y[1]), axis=-1)
    s = y[2] if joint else s
    s = jnp.clip(s, 0, s_max)
    # Too few samples for the joint fit: keep the Lambertian answer, sigma 0.
    keep_l2 = ok0 & ~enough
    normals = jnp.where(keep_l2[:, None], n0, normals)
    s = jnp.where(keep_l2, 0, s)
    cos_i, cos_r, p = _geometry(normals, lights)  # (K, N), (N,), (K, N)
    f = _shading(cos_i, cos_r[None], p, s[None], form)
    wu = used.astype(dtype)
    rho = jnp.stack([_albedo(flat[..., j], wu, f) for j in range(c)], axis=-1)  # (N, C)
    res = jnp.mean(flat - rho[None] * f[..., None], axis=-1)
    residual = jnp.sqrt(sum0(wu * res**2) / jnp.maximum(n_used, 1).astype(dtype))

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
