"""Parametric reflectance from a few lights: a diffuse term and a specular lobe that follows the
light, fitted by variable projection.

Per pixel $p$ and training frame $k$ the model is

$$ I_{pk} = g_k \\left( \\rho_{d,p}\\, D(n_p, l_k; \\theta) + \\rho_{s,r(p)}\\, S(n_p, l_k; \\theta)
\\right), \\qquad v = (0, 0, 1), $$

with one diffuse albedo $\\rho_d$ per pixel, one specular albedo $\\rho_s$ per *region* $r(p)$
(square blocks of `region` pixels: five samples per pixel overfit two free albedos, issue 16),
shared shape parameters $\\theta$ and, optionally, one brightness factor $g_k$ per frame
($\\prod_k g_k = 1$; `relight` renders at $g = 1$).

Diffuse terms $D$ (the method's first part):
- Lambert: $\\max(0, \\cos\\theta_i)$.
- `wrap`: wrap lighting $\\max(0, (\\cos\\theta_i + w) / (1 + w))$, a cheap stand-in for the
  subsurface scattering that softens the terminator on skin (Green, "Real-time approximations to
  subsurface scattering", GPU Gems 2004; Jimenez et al., "Separable subsurface scattering", 2015),
  with one shared $w \\in (0, 1)$.
- `oren_nayar`: Oren & Nayar (SIGGRAPH 1994), qualitative model, one shared $\\sigma \\in (0, 1)$
  rad (`jaxps.shading`'s implementation).

Specular lobes $S$ (the method's second part), evaluated at the half vector
$h = (l + v) / \\lVert l + v \\rVert$ so that the highlight moves with the light:
- `ggx`: the microfacet model $D_{GGX}(n \\cdot h; \\alpha)\\, G\\, F(l \\cdot h) /
  (4 F_0 \\cos\\theta_r)$, so that $\\rho_s$ is the lobe's strength at normal incidence:
  Torrance & Sparrow (1967)'s form with the GGX distribution and its Smith shadowing
  $G = G_1(\\cos\\theta_i) G_1(\\cos\\theta_r)$ (Walter et al., EGSR 2007), Schlick's Fresnel
  (Schlick 1994) with $F_0 = 0.028$ (skin's index of refraction, 1.4), one shared roughness
  $\\alpha \\in (0.05, 1)$.
- `blinn_phong`: $\\frac{e + 2}{8 \\pi} (n \\cdot h)^e$ where $\\cos\\theta_i > 0$ (Blinn 1977,
  normalised), one shared exponent $e \\in (1, 500)$.

Fit: the albedos enter linearly, so for given $\\theta$ and $g$ they are solved in closed form
(per region, $\\rho_s$ from the residuals with $\\rho_d$ projected out; then $\\rho_d$ per pixel;
both clipped at 0), and Levenberg–Marquardt (optimistix) moves only the few shared parameters,
bounded through sigmoids (variable projection: Golub & Pereyra 1973). After the solver stops the
albedos are solved once more on every masked pixel, not only the `n_samples // K` sampled ones.

Joint normals (`refine_normals=True`): L2 photometric stereo bends the normals towards the
highlight, so the lobe finds little left to explain (issue 16). Each pixel's normal is then
re-solved with the lobe and the shared parameters fixed (damped Gauss–Newton in two tangent
coordinates, the diffuse albedo projected out), and the shared parameters re-fitted: two rounds.

`wrap_ggx_residual`: `wrap_ggx` plus $g_k\\, B \\rho_d \\tanh m(\\tilde u)$, a 3-8-1 tanh
network $m$ over Rusinkiewicz (1998)'s half/difference angles $u = (\\theta_h, \\theta_d,
\\phi_d)$ clamped to their training range ($B$ = `RESIDUAL_BOUND`), fitted by LM after the
parametric part with the gains fixed (the issue's "MLP that learns only the residual").
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree

from ..core._host import NO_YNN, CpuTuned
from ..core._reduce import sum0
from ..core._store import call as stored_call
from ..shading._oren_nayar import SIGMA_MAX, _shading

__all__ = ["PARAMETRIC_METHODS"]

# method -> (diffuse term, specular lobe)
PARAMETRIC_METHODS = {
    "wrap": ("wrap", None),
    "oren_nayar": ("oren_nayar", None),
    "ggx": ("lambert", "ggx"),
    "blinn_phong": ("lambert", "blinn_phong"),
    "wrap_ggx": ("wrap", "ggx"),
    "oren_nayar_ggx": ("oren_nayar", "ggx"),
    "wrap_ggx_residual": ("wrap", "ggx"),  # + a residual MLP over (θh, θd, φd)
}
RESIDUAL_HIDDEN = 8  # hidden units of the residual MLP (3-8-1)
RESIDUAL_BOUND = 0.25  # |correction| <= RESIDUAL_BOUND x the pixel's diffuse albedo
REGION_PX = 32  # side of the specular albedo's square regions (see docs/brdf.md)
F0_SKIN = 0.028  # Schlick's F0 for an index of refraction of 1.4
# Bounds of the shared parameters (sigmoid reparametrisation) and their starting values.
_BOUNDS = {"ggx": (0.05, 1.0), "blinn_phong": (1.0, 500.0), "wrap": (0.0, 1.0),
           "oren_nayar": (0.0, SIGMA_MAX)}
_START = {"ggx": 0.3, "blinn_phong": 20.0, "wrap": 0.2, "oren_nayar": 0.3}


class ParametricParams(NamedTuple):
    """The fitted parameters of a parametric method (`BRDFModel.params`).

    - `shape`: `(2,)` the diffuse term's parameter ($w$ or $\\sigma$; 0 for Lambert) and the
      lobe's ($\\alpha$ or $e$; 0 without a lobe).
    - `diffuse_ratio`: `(H, W)` $\\rho_d / \\rho$, the fitted diffuse albedo over the albedo the
      model was fitted with (1 outside the mask), so `relight` takes the same albedo map.
    - `specular`: `(H, W)` $\\rho_s$ in the images' units (the pixel's region's value; 0
      outside the mask).
    - `normals`: `(H, W, 3)` the jointly refined normals (`refine_normals=True`; `relight`
      renders with them instead of its `normals` argument), else None.
    - `residual`, `box`: the residual MLP's `((W1, b1), (W2, b2))` and the `(2, 3)` training
      range of (θh, θd, φd) its inputs are clamped to (`"wrap_ggx_residual"`), else None.
    """

    shape: jax.Array
    diffuse_ratio: jax.Array
    specular: jax.Array
    normals: jax.Array | None = None
    residual: tuple | None = None
    box: jax.Array | None = None


def _to_bounded(t, name):
    lo, hi = _BOUNDS[name]
    return lo + (hi - lo) * jax.nn.sigmoid(t)


def _from_bounded(x, name):
    lo, hi = _BOUNDS[name]
    u = (x - lo) / (hi - lo)
    return math.log(u / (1 - u))


def _col(a, j):
    """Component `j` of `(K, 3)` distant lights as `(K, 1)`, of `(K, P, 3)` per-pixel ones as
    `(K, P)`: either broadcasts against `(1, P)` planes of the normals."""
    return a[:, j][:, None] if a.ndim == 2 else a[..., j]


def _view(lights):
    """The view direction (0, 0, 1), shaped to add to `lights` (`(..., 3)`)."""
    return jnp.asarray([0, 0, 1], lights.dtype).reshape((1,) * (lights.ndim - 1) + (3,))


def _terms(diffuse, specular, shape, normals, lights):
    """Diffuse and specular shading `(K, P)` for `(P, 3)` normals, `(K, 3)` distant or
    `(K, P, 3)` per-pixel lights and the bounded `shape` (2,)."""
    col = _col
    nx, ny, nz = (normals[:, j][None] for j in range(3))  # (1, P)
    cos_i = col(lights, 0) * nx + col(lights, 1) * ny + col(lights, 2) * nz
    cos_r = jnp.clip(nz, 1e-4, 1)
    if diffuse == "lambert":
        d = jnp.maximum(cos_i, 0)
    elif diffuse == "wrap":
        d = jnp.maximum((cos_i + shape[0]) / (1 + shape[0]), 0)
    else:
        d = _shading(cos_i, cos_r, col(lights, 2) - cos_i * cos_r, shape[0] ** 2)
    if specular is None:
        return d, jnp.zeros_like(d)
    half = lights + _view(lights)
    half = half / jnp.linalg.norm(half, axis=-1, keepdims=True)
    cos_h = jnp.clip(col(half, 0) * nx + col(half, 1) * ny + col(half, 2) * nz, 0, 1)
    lit = cos_i > 0
    if specular == "blinn_phong":
        e = shape[1]
        s = (e + 2) / (8 * math.pi) * jnp.exp(e * jnp.log(jnp.maximum(cos_h, 1e-12)))
        return d, jnp.where(lit, s, 0)
    a2 = shape[1] ** 2
    ndf = a2 / (math.pi * (cos_h**2 * (a2 - 1) + 1) ** 2)

    def g1(c):
        return 2 * c / (c + jnp.sqrt(a2 + (1 - a2) * c**2))

    ci = jnp.clip(cos_i, 1e-4, 1)
    cos_d = sum(col(lights, j) * col(half, j) for j in range(3))  # l.h, (K, 1) or (K, P)
    fresnel = 1 + (1 / F0_SKIN - 1) * (1 - cos_d) ** 5  # Schlick's F / F0
    s = ndf * g1(ci) * g1(cos_r) * fresnel / (4 * cos_r)
    return d, jnp.where(lit, s, 0)


def _albedos(d, s, y, w, region, n_regions):
    """Closed-form albedos for `(K, P)` shading `d`, `s`, data `y` and 0/1 weights `w`:
    `(n_regions,)` specular (with the per-pixel diffuse albedo projected out) and `(P,)`
    diffuse, both clipped at 0."""
    tiny = jnp.asarray(1e-12, d.dtype)
    dd = jnp.maximum(jnp.sum(w * d * d, 0), tiny)
    proj = lambda x: x - d * (jnp.sum(w * d * x, 0) / dd)[None]
    s_perp, y_perp = proj(s), proj(y)
    num = jax.ops.segment_sum(jnp.sum(w * s_perp * y_perp, 0), region, n_regions)
    den = jax.ops.segment_sum(jnp.sum(w * s_perp * s_perp, 0), region, n_regions)
    rho_s = jnp.maximum(num / jnp.maximum(den, tiny), 0)
    rho_d = jnp.maximum(jnp.sum(w * d * (y - rho_s[region][None] * s), 0) / dd, 0)
    return rho_s, rho_d


def _unpack(p, diffuse, specular, k, fit_gains):
    dtype = p.dtype
    shape = jnp.stack([
        _to_bounded(p[0], diffuse) if diffuse != "lambert" else jnp.zeros((), dtype),
        _to_bounded(p[1], specular) if specular is not None else jnp.zeros((), dtype)])
    gains = jnp.exp(p[2:] - jnp.mean(p[2:])) if fit_gains else jnp.ones((k,), dtype)
    return shape, gains


def _predict(p, data, diffuse, specular, n_regions, fit_gains):
    """`(K, P)` prediction and the albedos for flat parameters `p`."""
    normals, lights, y, w, region = data
    shape, gains = _unpack(p, diffuse, specular, lights.shape[0], fit_gains)
    d, s = _terms(diffuse, specular, shape, normals, lights)
    d, s = gains[:, None] * d, gains[:, None] * s
    rho_s, rho_d = _albedos(d, s, y, w, region, n_regions)
    return rho_d[None] * d + rho_s[region][None] * s, rho_s, rho_d, shape, gains


def fit(images, normals, albedo, lights, mask, usable, *, method, key, n_samples, solver,
         max_steps, frame_gains, region, refine_normals=False, rounds=2):
    """Fit `method` (a key of `PARAMETRIC_METHODS`). `usable`: `(K, H, W)` bool, samples that
    may be fitted (the others, NaN or not, are never read; a pixel with none keeps its
    normal). Returns `(ParametricParams, gains (K,), steps, converged, the solver's
    message, prediction, target, n_params)`, prediction and target over the usable samples of
    every masked pixel; steps are summed over the rounds, converged and the message are the
    last round's. `n_params`: free parameters beyond a normal and an albedo per pixel (which
    Lambert's law has too): the shape parameters, one specular albedo per region with a
    fitted pixel, K - 1 frame gains, the residual network's weights."""
    if region is not None and int(region) < 1:
        raise ValueError(f"region must be a positive number of pixels or None, got {region}")
    diffuse, specular = PARAMETRIC_METHODS[method]
    k, h, w = images.shape
    dtype = images.dtype
    size = int(region) if region is not None else max(h, w)
    cols = -(-w // size)
    n_regions = cols * -(-h // size)
    yy, xx = np.mgrid[:h, :w]
    region_map = (yy // size) * cols + xx // size
    # Samples are gathered and results scattered on the host: each eager jnp op traced and
    # lowered a small program of its own in every new process. Unusable samples read as 0: a
    # NaN under weight 0 would still make its residual, and its pixel's albedos, NaN.
    usable = np.asarray(usable)
    images = np.where(usable, np.asarray(images), np.zeros((), dtype))
    normals = np.asarray(normals).reshape(-1, 3)
    pix = np.flatnonzero(np.asarray(mask).reshape(-1) & usable.any(0).reshape(-1))

    lights = np.asarray(lights)
    per_pixel = lights.ndim == 4  # (K, H, W, 3) near lamps: each pixel's own directions

    def data_of(sel):
        return (normals[sel], lights.reshape(k, -1, 3)[:, sel] if per_pixel else lights,
                images.reshape(k, -1)[:, sel],
                usable.reshape(k, -1)[:, sel].astype(dtype),
                region_map.reshape(-1)[sel].astype(np.int32))

    train = pix
    if pix.size * k > n_samples:
        pick = np.asarray(jax.random.choice(key, pix.size, (max(n_samples // k, 1),),
                                            replace=False))
        train = np.sort(pix[pick])
    p0 = np.concatenate([
        np.asarray([_from_bounded(_START[diffuse], diffuse) if diffuse != "lambert" else 0.0,
                    _from_bounded(_START[specular], specular) if specular else 0.0], dtype),
        np.zeros((k,), dtype)])
    static = dict(zip(_STATIC_NAMES, (diffuse, specular, n_regions, bool(frame_gains))))

    def solve(p):
        """One Levenberg-Marquardt fit from `p`: the value, the result, the step count."""
        if solver is None:  # the default: a program of arrays and names, kept by the store
            value, code, steps = stored_call(_solve_default, p, data_of(train), **static,
                                             max_steps=int(max_steps))
            return value, jax.tree.unflatten(_RESULT_TREE, code), steps
        sol = _solve(p, data_of(train), solver, *static.values(), int(max_steps))
        return sol.value, sol.result, sol.stats["num_steps"]

    value, result, steps = solve(p0)
    steps = int(steps)
    for _ in range(rounds if refine_normals else 0):
        normals = normals.copy()
        normals[pix] = np.asarray(stored_call(_refine_jit, value, data_of(pix), **static))
        value, result, more = solve(value)
        steps += int(more)
    pred, rho_s, rho_d, shape, gains = stored_call(_predict_jit, value, data_of(pix), **static)
    alb = np.asarray(albedo).reshape(-1)[pix]
    ratio = np.ones((h * w,), dtype)
    ratio[pix] = np.where(alb > 0, np.asarray(rho_d) / np.where(alb > 0, alb, 1), 1)
    spec = np.zeros((h * w,), dtype)
    spec[pix] = np.asarray(rho_s)[region_map.reshape(-1)[pix]]
    params = ParametricParams(shape, *jax.device_put((ratio.reshape(h, w), spec.reshape(h, w))),
                              jax.device_put(normals.reshape(h, w, 3)) if refine_normals else None)
    sel = usable.reshape(k, -1)[:, pix]
    target = images.reshape(k, -1)[:, pix]
    ok = bool(result == optx.RESULTS.successful)
    message = "converged" if ok else str(result).split("<", 1)[-1].rstrip(">")
    if method.endswith("_residual"):
        data = data_of(train)
        base, _, rho_d_train, _, _ = stored_call(_predict_jit, value, data, **static)
        u = _half_diff(data[0], data[1])
        box = jnp.stack([jnp.min(u, axis=(0, 1)), jnp.max(u, axis=(0, 1))])
        mlp = _init_residual(key, dtype)
        flat, unravel = ravel_pytree(mlp)
        amp = RESIDUAL_BOUND * gains[:, None] * rho_d_train[None]
        res = _solve_residual(flat, (_scaled(u, box), base, amp, data[2], data[3]),
                              _DEFAULT_SOLVER if solver is None else solver, int(max_steps))
        steps += int(res.stats["num_steps"])
        ok = ok and bool(res.result == optx.RESULTS.successful)
        message += "; residual MLP: " + ("converged" if res.result == optx.RESULTS.successful
                                         else str(res.result).split("<", 1)[-1].rstrip(">"))
        params = params._replace(residual=unravel(res.value), box=box)
        u_all = _half_diff(normals.reshape(-1, 3)[pix], data_of(pix)[1])
        amp_all = RESIDUAL_BOUND * gains[:, None] * rho_d[None]
        pred = pred + amp_all * jnp.tanh(_mlp(params.residual, _scaled(u_all, box)))
    lobe_params = 0 if specular is None else 1 + np.unique(region_map.reshape(-1)[pix]).size
    n_params = ((diffuse != "lambert") + lobe_params + (k - 1) * bool(frame_gains)
                + (0 if params.residual is None else ravel_pytree(params.residual)[0].size))
    return params, gains, steps, ok, message, np.asarray(pred)[sel], target[sel], int(n_params)


def _half_diff(normals, lights):
    """Rusinkiewicz (1998)'s half/difference angles (θh, θd, φd) `(K, P, 3)` for `(P, 3)`
    normals and `(K, 3)` distant or `(K, P, 3)` per-pixel lights, view (0, 0, 1): θh between n
    and h, θd between l and h, φd the azimuth of l about h from the plane of n and h
    (isotropic, in [0, π])."""
    l = lights[:, None] if lights.ndim == 2 else lights  # (K, 1, 3) or (K, P, 3)
    hv = l + _view(l)
    hv = hv / jnp.linalg.norm(hv, axis=-1, keepdims=True)
    n = normals[None]  # (1, P, 3)
    cos_h = jnp.sum(n * hv, -1)  # (K, P)
    cos_d = jnp.sum(l * hv, -1)  # (K, 1) or (K, P)
    n_perp = n - cos_h[..., None] * hv
    l_perp = l - cos_d[..., None] * hv
    dot = jnp.sum(n_perp * l_perp, -1)
    cross = jnp.linalg.norm(jnp.cross(n_perp, jnp.broadcast_to(l_perp, n_perp.shape)), axis=-1)
    phi = jnp.arctan2(cross, dot)
    theta_h = jnp.arccos(jnp.clip(cos_h, -1, 1))
    theta_d = jnp.broadcast_to(jnp.arccos(jnp.clip(cos_d, -1, 1)), theta_h.shape)
    return jnp.stack([theta_h, theta_d, phi], -1)


def _scaled(u, box):
    """`u` clamped to the training box and mapped to [-1, 1] per coordinate."""
    lo, hi = (b.reshape((1,) * (u.ndim - 1) + (3,)) for b in box)
    return 2 * (jnp.clip(u, lo, hi) - lo) / jnp.maximum(hi - lo, 1e-6) - 1


def _init_residual(key, dtype):
    w1 = jax.random.normal(key, (RESIDUAL_HIDDEN, 3), dtype) / math.sqrt(3)
    w2 = 1e-2 * jax.random.normal(jax.random.fold_in(key, 1), (1, RESIDUAL_HIDDEN), dtype)
    return ((w1, jnp.zeros((RESIDUAL_HIDDEN,), dtype)), (w2, jnp.zeros((1,), dtype)))


def _mlp(params, z):
    """`(..., 3)` scaled inputs -> `(...)` outputs of the 3-H-1 tanh network."""
    (w1, b1), (w2, b2) = params
    lead = (1,) * (z.ndim - 1)
    hidden = jnp.tanh(z @ w1.T + b1.reshape(*lead, -1))
    return (hidden @ w2.T + b2.reshape(*lead, 1))[..., 0]


@eqx.filter_jit
def _solve_residual(flat, data, solver, max_steps):
    z, base, amp, y, w = data
    unravel = ravel_pytree(_init_residual(jax.random.key(0), flat.dtype))[1]

    def residuals(p, _):
        return (w * (base + amp * jnp.tanh(_mlp(unravel(p), z)) - y)).reshape(-1)

    return optx.least_squares(residuals, solver, flat, max_steps=max_steps, throw=False)


def _refine(p, data, diffuse, specular, n_regions, fit_gains, steps=8):
    """Per-pixel normals re-solved with the shared parameters `p` and the regions' specular
    albedos fixed (the diffuse albedo projected out): damped Gauss–Newton on
    $n = (n_0 + a e_x + b e_y) / \\lVert\\cdot\\rVert$, a step kept only where it lowers the
    pixel's squared error. Returns `(P, 3)` unit normals."""
    normals, lights, y, w, region = data
    rho_s = _predict(p, data, diffuse, specular, n_regions, fit_gains)[1][region]
    shape, gains = _unpack(p, diffuse, specular, lights.shape[0], fit_gains)

    def normal(n0, ab):
        n = n0 + jnp.stack([ab[0], ab[1], jnp.zeros((), ab.dtype)])
        return n / jnp.linalg.norm(n)

    def resid(ab, n0, yp, wp, rs, lp):
        d, s = _terms(diffuse, specular, shape, normal(n0, ab)[None], lp)
        d, s = (gains[:, None] * d)[:, 0], (gains[:, None] * s)[:, 0]
        rd = jnp.maximum(jnp.sum(wp * d * (yp - rs * s)) / jnp.maximum(jnp.sum(wp * d * d),
                                                                      1e-12), 0)
        return wp * (yp - rd * d - rs * s)

    def one(n0, yp, wp, rs, lp):
        def step(_, state):  # a loop, not unrolled: 8 unrolled steps took 2.3 s to compile
            ab, lam = state
            r = resid(ab, n0, yp, wp, rs, lp)
            jac = jax.jacfwd(resid)(ab, n0, yp, wp, rs, lp)
            a = jac.T @ jac
            a = a + lam * jnp.diag(jnp.diag(a)) + 1e-9 * jnp.eye(2, dtype=a.dtype)
            # the 2x2 system by cofactors: a batched LU and two triangular solves took 37 of
            # this function's 87 ms at 30,000 pixels (scratch)
            grad = jac.T @ r
            delta = -jnp.stack([a[1, 1] * grad[0] - a[0, 1] * grad[1],
                                a[0, 0] * grad[1] - a[1, 0] * grad[0]]) / (
                a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0])
            delta = delta * jnp.minimum(1, 0.2 / jnp.maximum(jnp.linalg.norm(delta), 1e-12))
            better = jnp.sum(resid(ab + delta, n0, yp, wp, rs, lp) ** 2) < jnp.sum(r**2)
            return jnp.where(better, ab + delta, ab), jnp.where(better, lam * 0.3, lam * 10)

        start = (jnp.zeros((2,), n0.dtype), jnp.asarray(1e-3, n0.dtype))
        return normal(n0, jax.lax.fori_loop(0, steps, step, start)[0])

    # per-pixel lights (K, P, 3) are mapped with their pixel, distant ones (K, 3) shared
    return jax.vmap(one, in_axes=(0, 1, 1, 0, None if lights.ndim == 2 else 1))(
        normals, y, w, rho_s, lights)


_STATIC_NAMES = ("diffuse", "specular", "n_regions", "fit_gains")
_refine_jit = jax.jit(_refine, static_argnames=_STATIC_NAMES)


def _predict_and_jacobian(p, data, diffuse, specular, n_regions, fit_gains):
    """`_predict`'s `(K, P)` prediction and its `(len(p), K, P)` Jacobian with respect to the
    flat parameters `p`, the closed-form albedos differentiated by hand (variable projection:
    Golub & Pereyra 1973, the full derivative, not Kaufman's approximation).

    `jax.jacfwd` of `_predict` took 24-30 ms at 100,000 samples, 30-40x a prediction:
    XLA-CPU recomputed the shading's derivatives inside each of the albedos' sums. Here each
    parameter moves only a few things. A shape parameter moves the `(K, P)` shading
    ($\\dot d$, $\\dot s$ from one `jax.jvp` of `_terms`), and a frame gain $g_k$ moves frame
    $k$ alone, so its per-pixel sums are that frame's terms, with no sum at all. Equal to
    `jax.jacfwd`'s within float32 rounding (`tests/test_parametric.py`)."""
    normals, lights, y, w, region = data
    k = lights.shape[0]

    def unpack(q):
        return _unpack(q, diffuse, specular, k, fit_gains)

    def terms(shape):
        return _terms(diffuse, specular, shape, normals, lights)

    shape, gains = unpack(p)
    # each parameter's pull on the two shape values and the K gains: (n, 2), (n, K)
    shape_dot, gains_dot = jax.vmap(lambda t: jax.jvp(unpack, (p,), (t,))[1])(
        jnp.eye(p.shape[0], dtype=p.dtype))
    (d0, s0), (dd0, ds0) = jax.jvp(terms, (shape,), (jnp.asarray([1, 0], p.dtype),))
    _, (dd1, ds1) = jax.jvp(terms, (shape,), (jnp.asarray([0, 1], p.dtype),))
    g = gains[:, None]
    d, s = g * d0, g * s0

    def dot(a, b):  # the frames' weighted inner product, per pixel: (1, P)
        # unrolled (`sum0`): XLA-CPU's reduction over the short frame axis was the slowest
        # part of this Jacobian (3.7 against 6.6 ms, scratch)
        return sum0(w * a * b)[None]

    # the forward solve, as `_albedos` (per-pixel terms (1, P), per-region (1, R))
    tiny = jnp.asarray(1e-12, d.dtype)
    a_raw = dot(d, d)
    a = jnp.maximum(a_raw, tiny)
    d_s = dot(d, s)
    cs, cy = d_s / a, dot(d, y) / a
    s_perp, y_perp = s - d * cs, y - d * cy
    seg = jax.vmap(lambda x: jax.ops.segment_sum(x, region, n_regions))
    num = seg(dot(s_perp, y_perp))
    den_raw = seg(dot(s_perp, s_perp))
    den = jnp.maximum(den_raw, tiny)
    ratio = num / den
    rs = jnp.maximum(ratio, 0)[:, region]
    rho_d_raw = dot(d, y - rs * s) / a
    rho_d = jnp.maximum(rho_d_raw, 0)
    pred = rho_d * d + rs * s
    d_yp, d_sp = dot(d, y_perp), dot(d, s_perp)

    def albedo_dots(a_dot, ds_dot, dy_dot, st_yp, dt_yp, dt_sp, st_sp):
        """The albedos' tangents along m directions from the directions' `(m, P)` sums
        <dt, d>, <dt, s> + <d, st>, <dt, y>, <st, y_perp>, <dt, y_perp>, <dt, s_perp> and
        <st, s_perp> (dt, st: the direction's change of d and s), as `jax.jvp` of `_albedos`
        gives them (where a `maximum` clips, its branch's derivative)."""
        a_dot = jnp.where(a_raw > tiny, 2 * a_dot, 0)
        cs_dot = (ds_dot - cs * a_dot) / a
        cy_dot = (dy_dot - cy * a_dot) / a
        num_dot = seg(st_yp - cs * dt_yp - cs_dot * d_yp - cy * dt_sp - cy_dot * d_sp)
        den_dot = jnp.where(den_raw > tiny, seg(2 * (st_sp - cs * dt_sp - cs_dot * d_sp)), 0)
        rs_dot = jnp.where(ratio > 0, (num_dot - ratio * den_dot) / den, 0)[:, region]
        rho_d_dot = jnp.where(rho_d_raw > 0,
                              (dy_dot - rs * ds_dot - rs_dot * d_s - rho_d_raw * a_dot) / a, 0)
        return rho_d_dot, rs_dot

    # along the two shape values: (K, P) changes of d and s, one direction at a time (stacked,
    # XLA-CPU laid the segment sums' input out transposed: 4.9 against 8.2 ms a step, scratch)
    dt, st = (g * dd0, g * dd1), (g * ds0, g * ds1)
    shape_dots = [albedo_dots(dot(dti, d), dot(dti, s) + dot(sti, d), dot(dti, y),
                              dot(sti, y_perp), dot(dti, y_perp), dot(dti, s_perp),
                              dot(sti, s_perp))
                  for dti, sti in zip(dt, st)]
    # along the K gains: gain j scales frame j's d0 and s0 alone, so the sums along gain j
    # are frame j's terms, and those along all K gains are the (K, P) terms themselves
    wd0, ws0 = w * d0, w * s0
    gain_dots = albedo_dots(wd0 * d, 2 * g * wd0 * s0, wd0 * y, ws0 * y_perp, wd0 * y_perp,
                            wd0 * s_perp, ws0 * s_perp)
    # along each parameter: the tangents are linear in the 2 + K directions'
    basis = jnp.concatenate([shape_dot, gains_dot], 1)  # (n, 2 + K)
    rho_d_dot, rs_dot = (basis @ jnp.concatenate([*shapes, gains])
                         for shapes, gains in zip(zip(*shape_dots), gain_dots))

    def change(x, x0):  # (n, K, P) change of d (or s) from its shape directions x and x0
        return (shape_dot[:, 0, None, None] * x[0][None] + shape_dot[:, 1, None, None] * x[1][None]
                + gains_dot[:, :, None] * x0[None])

    # every term broadcast explicitly (the tests make rank promotion an error)
    jac = (rho_d_dot[:, None] * d[None] + rho_d[None] * change(dt, d0)
           + rs_dot[:, None] * s[None] + rs[None] * change(st, s0))
    return pred, jac


@functools.partial(jax.custom_jvp, nondiff_argnums=(2, 3, 4, 5))
def _weighted_residuals(p, data, diffuse, specular, n_regions, fit_gains):
    """The fit's `(K P,)` residuals, with `_predict_and_jacobian`'s Jacobian as its JVP."""
    y, w = data[2], data[3]
    return (w * (_predict(p, data, diffuse, specular, n_regions, fit_gains)[0] - y)).reshape(-1)


@functools.partial(_weighted_residuals.defjvp, symbolic_zeros=True)
def _weighted_residuals_jvp(diffuse, specular, n_regions, fit_gains, primals, tangents):
    p, data = primals
    p_dot, data_dot = tangents
    if not all(isinstance(t, jax.custom_derivatives.SymbolicZero)
               for t in jax.tree.leaves(data_dot)):
        raise NotImplementedError("the fit's residuals are differentiated only with respect to "
                                  "its parameters, not its data")
    y, w = data[2], data[3]
    pred, jac = _predict_and_jacobian(p, data, diffuse, specular, n_regions, fit_gains)
    residuals = (w * (pred - y)).reshape(-1)
    if isinstance(p_dot, jax.custom_derivatives.SymbolicZero):
        return residuals, jnp.zeros_like(residuals)
    return residuals, sum0(p_dot[:, None, None] * (w[None] * jac)).reshape(-1)


def _least_squares(p0, data, solver, diffuse, specular, n_regions, fit_gains, max_steps):
    def residuals(p, data):
        return _weighted_residuals(p, data, diffuse, specular, n_regions, fit_gains)

    return optx.least_squares(residuals, solver, p0, args=data, max_steps=max_steps, throw=False)


# QR (optimistix's default), not Cholesky of the normal equations: the centred log-gains and
# an unused shape parameter leave J rank-deficient, and float32 Cholesky then failed.
_DEFAULT_SOLVER = optx.LevenbergMarquardt(rtol=1e-4, atol=1e-6)


def _solve_default(p0, data, diffuse, specular, n_regions, fit_gains, max_steps):
    """`_least_squares` with `_DEFAULT_SOLVER`: every argument an array or a name, so that the
    store of compiled programs keeps it (a warm `jaxps relight` then traces no fit), and only
    the parts of the solution that `fit` reads."""
    sol = _least_squares(p0, data, _DEFAULT_SOLVER, diffuse, specular, n_regions, fit_gains,
                         max_steps)
    # the result as its int32 code: an equinox enumeration item does not survive the pickled
    # tree of a stored executable (`fit` rebuilds it with `_RESULT_TREE`)
    return sol.value, jax.tree.leaves(sol.result), sol.stats["num_steps"]


_RESULT_TREE = jax.tree.structure(optx.RESULTS.successful)


# Without YNNPACK fusions (`core._host.NO_YNN`): each LM step's sums over the K frames ran
# faster in XLA's own loops (`benchmarks/bench_ynn.py`).
_solve = CpuTuned(_least_squares, NO_YNN, jit=eqx.filter_jit)
_solve_default = CpuTuned(_solve_default, NO_YNN,
                          static_argnames=(*_STATIC_NAMES, "max_steps"))
_predict_jit = jax.jit(_predict, static_argnames=_STATIC_NAMES)


@functools.partial(jax.jit, static_argnames="method")
def render(method, params, normals, albedo, lights):
    """`(K, H, W)` images of a fitted parametric `method` at unit frame gains, under `(K, 3)`
    distant or `(K, H, W, 3)` per-pixel lights."""
    diffuse, specular = PARAMETRIC_METHODS[method]
    h, w, _ = normals.shape
    dtype = normals.dtype
    if lights.ndim == 4:
        lights = lights.reshape(lights.shape[0], h * w, 3)
    if params.normals is not None:
        normals = params.normals.astype(dtype)
    d, s = _terms(diffuse, specular, params.shape.astype(dtype), normals.reshape(-1, 3), lights)
    rho_d = (albedo * params.diffuse_ratio.astype(dtype)).reshape(1, -1)
    out = rho_d * d + params.specular.astype(dtype).reshape(1, -1) * s
    if params.residual is not None:
        z = _scaled(_half_diff(normals.reshape(-1, 3), lights), params.box.astype(dtype))
        out = out + RESIDUAL_BOUND * rho_d * jnp.tanh(_mlp(params.residual, z))
    return out.reshape(-1, h, w)
