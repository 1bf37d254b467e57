"""The Oren–Nayar rough-diffuse reflectance model, its renderer, and roughness fitting.

Oren and Nayar, "Generalization of Lambert's reflectance model", SIGGRAPH 1994. A surface of
V-cavity facets whose slopes are Gaussian with standard deviation $\\sigma$ (radians). With the
albedo $\\rho$ and the irradiance normalised so that Lambert's law reads $I = \\rho \\cos\\theta_i$,
the radiance is $I = \\rho\\, f(\\theta_i, \\theta_r, \\Delta\\phi; \\sigma)$ with

- **qualitative** form (the paper's eq. 30, the one used in practice and the default here):
  $f = \\cos\\theta_i\\,(A + B \\max(0, \\cos\\Delta\\phi) \\sin\\alpha \\tan\\beta)$,
  $A = 1 - 0.5\\,\\sigma^2 / (\\sigma^2 + 0.33)$, $B = 0.45\\,\\sigma^2 / (\\sigma^2 + 0.09)$;
- **full** form (the paper's direct-illumination term $L_1$, eqs. 27-29; the inter-reflection
  term $L_2$, which grows with $\\rho^2$ and so depends on the unknown camera gain, is left out):
  $f = \\cos\\theta_i\\,(C_1 + \\cos\\Delta\\phi\\, C_2 \\tan\\beta
  + (1 - |\\cos\\Delta\\phi|)\\, C_3 \\tan\\tfrac{\\alpha+\\beta}{2})$,

where $\\alpha = \\max(\\theta_i, \\theta_r)$, $\\beta = \\min(\\theta_i, \\theta_r)$ and
$\\Delta\\phi$ is the azimuth between the light and view directions in the tangent plane.
$\\sigma = 0$ gives Lambert's law exactly; $f = 0$ for $\\theta_i \\ge 90°$ (attached shadow).

The view direction is the camera axis $v = (0, 0, 1)$ (orthographic camera, DESIGN.md). In
vector form, with $c_i = n \\cdot l$, $c_r = n \\cdot v$ and
$P = \\cos\\Delta\\phi \\sin\\theta_i \\sin\\theta_r = l \\cdot v - c_i c_r$, the qualitative
term is $\\max(0,\\cos\\Delta\\phi)\\sin\\alpha\\tan\\beta =
\\max(0, P) / \\max(c_i, c_r)$: smooth in the normal, with no `arccos`,
which is how the fitting code evaluates it.

Fitting works in $s = \\sigma^2$: $\\partial f / \\partial \\sigma = 0$ at $\\sigma = 0$, so a
Lambertian start would be a stationary point in $\\sigma$ but is not one in $s$. The fitted $s$
is projected onto $[0, \\sigma_{max}^2]$; a value that lands on a bound is reported `AT_BOUND`.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ..core._batched_lm import BatchedLM, solve_pixels
from ..core._host import has_value
from ..core._reduce import sum0
from ..core._safe import safe_sqrt
from ..core._status import Status, first_status

__all__ = [
    "OREN_NAYAR_FORMS",
    "RoughnessFit",
    "fit_roughness",
    "oren_nayar",
    "render_oren_nayar",
]

OREN_NAYAR_FORMS = ("qualitative", "full")
# Roughness bound (radians) used when none is given: facet slopes of 1 rad sd is far beyond skin.
SIGMA_MAX = 1.0
# Below this s = sigma^2 the model is not evaluated (s / (s + 0.09) would blow up at -0.09).
_S_FLOOR = -0.03


def _coefficients(s, form):
    """Oren–Nayar coefficients from $s = \\sigma^2$ (any sign above `_S_FLOOR`)."""
    s = jnp.maximum(s, _S_FLOOR)
    a = 1 - 0.5 * s / (s + 0.33)
    b = 0.45 * s / (s + 0.09)
    if form == "qualitative":
        return a, b, None
    c3 = 0.125 * s / (s + 0.09)
    return a, b, c3


def _shading(cos_i, cos_r, p, s, form="qualitative"):
    """$f = I / \\rho$ from $c_i = n \\cdot l$, $c_r = n \\cdot v$, $P = l \\cdot v - c_i c_r$
    and $s = \\sigma^2$.

    Elementwise and broadcastable; zero where $c_i \\le 0$. Safe (finite value and gradient)
    at normal incidence, grazing angles and $\\sigma = 0$.
    """
    dtype = cos_i.dtype
    tiny = jnp.asarray(1e-6, dtype)
    lit = cos_i > 0
    ci = jnp.where(lit, cos_i, 1)
    cr = jnp.clip(cos_r, tiny, 1)
    a, b, c3 = _coefficients(s, form)
    if form == "qualitative":
        f = ci * (a + b * jnp.maximum(p, 0) / jnp.maximum(jnp.maximum(ci, cr), tiny))
    else:
        ci = jnp.clip(ci, tiny, 1)
        si = jnp.sqrt(jnp.maximum(1 - ci**2, tiny**2))
        sr = jnp.sqrt(jnp.maximum(1 - cr**2, tiny**2))
        theta_i = jnp.arctan2(si, ci)
        theta_r = jnp.arctan2(sr, cr)
        alpha = jnp.maximum(theta_i, theta_r)
        beta = jnp.minimum(theta_i, theta_r)
        cos_dphi = jnp.clip(p / (si * sr), -1, 1)
        # tan(beta) with beta = min angle: the larger cosine.
        c_beta = jnp.maximum(ci, cr)
        tan_beta = jnp.sqrt(jnp.maximum(1 - c_beta**2, 0) + tiny**2) / c_beta
        two_beta_pi = 2 * beta / jnp.pi
        c2 = jnp.where(cos_dphi >= 0, b * jnp.sin(alpha), b * (jnp.sin(alpha) - two_beta_pi**3))
        c3 = c3 * (4 * alpha * beta / jnp.pi**2) ** 2
        tan_half = jnp.tan(jnp.minimum((alpha + beta) / 2, jnp.asarray(1.5, dtype)))
        f = ci * (a + cos_dphi * c2 * tan_beta + (1 - jnp.abs(cos_dphi)) * c3 * tan_half)
    return jnp.where(lit, f, 0).astype(dtype)


def _check_form(form):
    if form not in OREN_NAYAR_FORMS:
        raise ValueError(f"form must be one of {OREN_NAYAR_FORMS}, got {form!r}")


def oren_nayar(
    theta_i: Float[ArrayLike, "*N"],
    theta_r: Float[ArrayLike, "*N"],
    delta_phi: Float[ArrayLike, "*N"],
    sigma: Float[ArrayLike, "*N"],
    *,
    form: str = "qualitative",
) -> Float[Array, "*N"]:
    """Oren–Nayar reflectance $I / \\rho$ as a pure function of the angles and the roughness.

    Oren & Nayar, SIGGRAPH 1994 (see the module docstring for both forms). Normalised so that
    $\\sigma = 0$ gives $\\cos\\theta_i$ (Lambert) and $\\theta_i \\ge \\pi/2$ gives 0.

    **Arguments:**
    - `theta_i`: angle between normal and light (radians).
    - `theta_r`: angle between normal and view direction (radians).
    - `delta_phi`: azimuth difference between light and view about the normal (radians).
    - `sigma`: facet-slope roughness (radians, >= 0).
    - `form`: `"qualitative"` (eq. 30, default) or `"full"` (direct term $L_1$).

    All arguments broadcast together. **Returns:** $f$ in the floating dtype of `theta_i`
    (float32 for integer input).
    """
    _check_form(form)
    theta_i = jnp.asarray(theta_i)
    dtype = theta_i.dtype if jnp.issubdtype(theta_i.dtype, jnp.floating) else jnp.float32
    theta_i = theta_i.astype(dtype)
    theta_r = jnp.asarray(theta_r, dtype)
    delta_phi = jnp.asarray(delta_phi, dtype)
    sigma = jnp.asarray(sigma, dtype)
    try:
        jnp.broadcast_shapes(theta_i.shape, theta_r.shape, delta_phi.shape, sigma.shape)
    except ValueError:
        raise ValueError(f"theta_i, theta_r, delta_phi and sigma must broadcast together, got "
                         f"shapes {theta_i.shape}, {theta_r.shape}, {delta_phi.shape} and "
                         f"{sigma.shape}") from None
    # Checked where it has a value: inside `jit` or `vmap` the caller keeps sigma >= 0.
    if has_value(sigma) and bool(jnp.any(sigma < 0)):
        raise ValueError("sigma must be >= 0 (radians)")
    ci, cr = jnp.cos(theta_i), jnp.cos(theta_r)
    p = jnp.cos(delta_phi) * jnp.sin(theta_i) * jnp.sin(theta_r)
    return _shading(ci, cr, p, sigma**2, form)


def _geometry(normals, lights):
    """$c_i$ `(K, ...)`, $c_r$ `(...)`, $P$ `(K, ...)` for normals `(..., 3)`, lights `(K, 3)`."""
    # Written out: an einsum over the 3-axis is slow on XLA-CPU (see `core/_reduce.py`).
    col = lambda j: lights[:, j].reshape((-1,) + (1,) * (normals.ndim - 1))  # noqa: E731
    cos_i = col(0) * normals[None, ..., 0] + col(1) * normals[None, ..., 1] + (
        col(2) * normals[None, ..., 2])
    cos_r = normals[..., 2]
    return cos_i, cos_r, col(2) - cos_i * cos_r[None]


def render_oren_nayar(
    normals: Float[ArrayLike, "H W 3"],
    albedo: Float[ArrayLike, "H W"],
    lights: Float[ArrayLike, "K 3"],
    sigma: Float[ArrayLike, ""] | Float[ArrayLike, "H W"],
    *,
    form: str = "qualitative",
) -> Float[Array, "K H W"]:
    """Render $I_k = \\rho\\, f(n, l_k, v; \\sigma)$ with $v = (0, 0, 1)$ (no cast shadows).

    **Arguments:**
    - `normals`: `(H, W, 3)` unit normals; `albedo`: `(H, W)`.
    - `lights`: `(K, 3)` unit directions toward the lights.
    - `sigma`: roughness in radians, a scalar or `(H, W)`.
    - `form`: `"qualitative"` or `"full"`.

    **Returns:** `(K, H, W)` images in the dtype of `normals`.
    """
    _check_form(form)
    normals = jnp.asarray(normals)
    if normals.ndim != 3 or normals.shape[-1] != 3:
        raise ValueError(f"normals must be (H, W, 3), got {normals.shape}")
    dtype = normals.dtype
    albedo = jnp.asarray(albedo, dtype)
    if albedo.shape != normals.shape[:2]:
        raise ValueError(f"albedo must be (H, W) = {normals.shape[:2]}, got {albedo.shape}")
    if np.ndim(lights) != 2 or np.shape(lights)[-1] != 3:
        raise ValueError(f"lights must be (K, 3), got {np.shape(lights)}")
    if not isinstance(lights, jax.core.Tracer):
        # the model's angles take unit vectors: a longer one would act as no brightness,
        # only as wrong angles
        length = np.linalg.norm(np.asarray(lights, np.float64), axis=-1)
        if not np.all(np.abs(length - 1) <= 1e-3):
            raise ValueError(f"lights must be finite unit directions; their lengths are "
                             f"{np.round(length, 4).tolist()} (normalise them)")
    lights = jnp.asarray(lights, dtype)
    sigma = jnp.asarray(sigma, dtype)
    if sigma.shape not in ((), normals.shape[:2]):
        raise ValueError(f"sigma must be a scalar or (H, W), got shape {sigma.shape}")
    if not isinstance(sigma, jax.core.Tracer) and not bool(
            jnp.all((sigma >= 0) & (sigma <= np.pi / 2))):
        raise ValueError(f"sigma (roughness, radians) must lie in [0, pi/2] everywhere, got "
                         f"{float(jnp.min(sigma)):g}..{float(jnp.max(sigma)):g} (degrees?)")
    return _render(normals, albedo, lights, sigma, form)


@functools.partial(jax.jit, static_argnames="form")
def _render(normals, albedo, lights, sigma, form):
    cos_i, cos_r, p = _geometry(normals, lights)
    s = jnp.broadcast_to(sigma**2, albedo.shape)
    return albedo[None] * _shading(cos_i, cos_r[None], p, s[None], form)


# ---------------------------------------------------------------------------------------------
# Roughness fitting


class RoughnessFit(NamedTuple):
    """Result of `fit_roughness`.

    - `sigma`: roughness in radians: a scalar (`per="global"`), `(R,)` per label
      (`per="region"`) or `(H, W)` (`per="pixel"`).
    - `status`: int32 `jaxps.Status` codes, same shape as `sigma` (0 = ok; `AT_BOUND` when the
      fit ended on 0 or `sigma_max`, `TOO_FEW_LIGHTS` when too few lit samples,
      `NOT_CONVERGED` at the step limit, `MASKED` outside the mask for per-pixel fits).
    - `steps`: int32 solver steps, same shape.
    - `rms`: RMS residual $I - \\rho f$ of the fitted model over the samples used (same shape).
    - `rms_lambertian`: the same with $\\sigma = 0$ (the albedo refitted alike), for comparison.
    - `n_samples`: int32 samples used.
    - `albedo`: the albedo the fit used, `(H, W)` (refitted per pixel when `refit_albedo`).
    """

    sigma: Float[Array, "*S"]
    status: Int[Array, "*S"]
    steps: Int[Array, "*S"]
    rms: Float[Array, "*S"]
    rms_lambertian: Float[Array, "*S"]
    n_samples: Int[Array, "*S"]
    albedo: Float[Array, "H W"]


def default_solver(dtype=jnp.float32) -> optx.LevenbergMarquardt:
    """The least-squares solver used when none is given: Levenberg–Marquardt with tolerances
    suited to `dtype`."""
    if jnp.dtype(dtype) == jnp.float64:
        return optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10)
    # Tighter than this, float32 rounding in the summed loss keeps the test from ever passing.
    return optx.LevenbergMarquardt(rtol=1e-4, atol=1e-6)


def _albedo(i, w, f):
    """Closed-form albedo $\\rho = \\sum w I f / \\sum w f^2$ (variable projection), 0 where no
    sample; `i`, `w`, `f` share a leading sample axis `K`."""
    num, den = sum0(w * i * f), sum0(w * f * f)
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1), 0)


def _basis(cos_i, cos_r, p, form):
    """Per-sample geometry the model needs, precomputed once for fixed normals.

    Qualitative: $f = A c + B g$ with $c = \\max(c_i, 0)$ and $g = c\\,\\max(P, 0)/\\max(c_i, c_r)$,
    linear in $(A, B)$. Full: the raw $(c_i, c_r, P)$. All leaves `(K, N)` or `(1, N)`.
    """
    if form == "qualitative":
        tiny = jnp.asarray(1e-6, cos_i.dtype)
        lit = cos_i > 0
        c = jnp.where(lit, cos_i, 0)
        g = c * jnp.maximum(p, 0) / jnp.maximum(jnp.maximum(cos_i, cos_r), tiny)
        return c, jnp.where(lit, g, 0)
    return cos_i, cos_r, p


def _model(s, geo, form):
    """$f$ from the precomputed `_basis` and $s = \\sigma^2$ (broadcast against the leaves)."""
    if form == "qualitative":
        a, b, _ = _coefficients(s, form)
        c, g = geo
        return a * c + b * g
    cos_i, cos_r, p = geo
    return _shading(cos_i, cos_r, p, s, form)


def _residuals(s, data, form, refit):
    """Weighted residuals $w (I - \\rho f)$; `data` = (i, w, geo, rho), `(K, N)` and `(N,)`."""
    i, w, geo, rho_given = data
    f = _model(s.astype(i.dtype), geo, form)
    rho = _albedo(i, w, f) if refit else rho_given
    return w * (i - rho[None] * f)


def _s_from_ratio(t):
    """Invert $t = B(s) / A(s)$ of the qualitative model for $s \\ge 0$ ($t \\in [0, 0.9)$).

    $(0.45 - 0.5t)s^2 + (0.1485 - 0.375t)s - 0.0297t = 0$, positive root.
    """
    t = jnp.clip(t, 0, 0.899)
    a = 0.45 - 0.5 * t
    b = 0.1485 - 0.375 * t
    c = -0.0297 * t
    return (-b + jnp.sqrt(b * b - 4 * a * c)) / (2 * a)


def _ratio(s):
    """$t = B(s) / A(s)$ of the qualitative model (increasing in $s \\ge 0$, from 0 to 0.9)."""
    a, b, _ = _coefficients(s, "qualitative")
    return b / a


def _sums(data):
    """Per-pixel weighted sums $S_{cc}, S_{cg}, S_{gg}, S_{ci}, S_{gi}, S_{ii}$ (qualitative)."""
    i, w, (c, g), _ = data
    return tuple(sum0(w * x * y) for x, y in ((c, c), (c, g), (g, g), (c, i), (g, i), (i, i)))


def _explained(sums, t):
    """$F(t) = (S_{ci} + t S_{gi})^2 / (S_{cc} + 2t S_{cg} + t^2 S_{gg})$: the part of
    $\\sum I^2$ that $f \\propto c + t g$ explains with the best albedo (see `_exact_pixels`)."""
    scc, scg, sgg, sci, sgi = sums[:5]
    num = sci + t * sgi
    den = scc + 2 * t * scg + t * t * sgg
    return jnp.where(den > 0, num * num / jnp.where(den > 0, den, 1), 0)


def _exact_pixels(data, s_max):
    """Per-pixel $s$ of the qualitative model with the albedo free, exactly, in closed form.

    With $f = A(s)\\,(c + t g)$ and $t = B/A$, the albedo absorbs $A$: after eliminating it the
    cost is $\\sum I^2 - F(t)$ with $F(t) = (S_{ci} + t S_{gi})^2 / (S_{cc} + 2t S_{cg} +
    t^2 S_{gg})$ (the $S$ are weighted sums over the pixel's samples). $F$ has two stationary
    points on the real line: its zero $t = -S_{ci}/S_{gi}$ and its maximum $t^*$, the ratio of the
    unconstrained 2x2 linear fit $I \\approx \\rho' c + u g$. So over the box
    $[0, t(s_{max})]$ the optimum is $t^*$ if inside, else the better end, and $s$ follows from
    $t$ by `_s_from_ratio`. No iteration: the same minimum a converged
    Levenberg–Marquardt finds (tested), for every pixel at once.
    """
    i = data[0]
    scc, scg, sgg, sci, sgi, _ = _sums(data)
    det = scc * sgg - scg * scg
    ok = det > 1e-9 * jnp.maximum(scc * sgg, jnp.finfo(i.dtype).tiny)
    det = jnp.where(ok, det, 1)
    rho_a = (sgg * sci - scg * sgi) / det
    u = (scc * sgi - scg * sci) / det
    t_max = _ratio(s_max)
    t_star = jnp.where(ok & (rho_a > 0), jnp.clip(u / jnp.where(rho_a > 0, rho_a, 1), 0, t_max),
                       0)

    sums = (scc, scg, sgg, sci, sgi)
    f0, f_star, f_max = (_explained(sums, t) for t in (jnp.zeros_like(t_star), t_star, t_max))
    # Ties go to the smaller roughness (Lambert when sigma is not identifiable).
    t = jnp.where(f_star > f0, t_star, 0)
    t = jnp.where(f_max > jnp.maximum(f0, f_star), t_max, t)
    s = jnp.where(t >= t_max, s_max, _s_from_ratio(t))
    return jnp.clip(s, 0, s_max)


def _sum_residuals(s, sums):
    """One residual per pixel whose square is that pixel's cost at $s$, albedo eliminated.

    $\\sum_k (I_k - \\rho f_k)^2 = S_{ii} - F(t)$ with $t = B(s)/A(s)$ (see `_exact_pixels`),
    so a global or regional fit needs six sums per pixel, not every sample: the solver's
    Jacobian has N rows instead of K N. A constant $10^{-6} S_{ii}$ is added under the root
    (it moves no minimum) to keep the root's derivative finite at a perfect fit.
    """
    sii = sums[5]
    fit = _explained(sums, _ratio(s.astype(sii.dtype)))
    used = sii > 0  # pixels with no sample (outside the mask) add nothing, gradient included
    cost = jnp.where(used, jnp.maximum(sii - fit, 0) + 1e-6 * sii, 1)
    return jnp.where(used, jnp.sqrt(cost), 0)


def _solve_one(data, s0, s_max, form, refit, solver, max_steps, min_samples, reduced=False):
    """Fit one $s = \\sigma^2$ to the samples in `data` (weights zero for unused samples).

    `reduced`: solve on per-pixel sums (`_sum_residuals`), for global and regional fits with
    the qualitative form and a refitted albedo. Not for a single pixel: there the one residual
    $\\sqrt{\\text{cost}}$ makes Gauss–Newton a root finder for a cost that is not zero at
    its minimum.
    """
    i, w = data[0], data[1]
    dtype = i.dtype
    n = jnp.sum(w > 0)

    if reduced:  # the same cost from six sums per pixel instead of every sample
        fn, args = _sum_residuals, _sums(data)
    else:
        fn, args = (lambda s, a: _residuals(s, a, form, refit)), data
    sol = optx.least_squares(fn, solver, jnp.asarray(s0, dtype), args=args,
                             max_steps=max_steps, throw=False)
    s = sol.value
    s_proj = jnp.clip(s, 0, s_max)
    at_bound = (s <= 0) | (s >= s_max)
    converged = sol.result == optx.RESULTS.successful
    r = _residuals(s_proj, data, form, refit)
    r0 = _residuals(jnp.zeros((), dtype), data, form, refit)
    denom = jnp.maximum(n, 1).astype(dtype)
    rms = safe_sqrt(jnp.sum(r**2) / denom)
    rms0 = safe_sqrt(jnp.sum(r0**2) / denom)
    status = first_status([(n < min_samples, Status.TOO_FEW_LIGHTS),
                           (~converged, Status.NOT_CONVERGED), (at_bound, Status.AT_BOUND)])
    sigma = jnp.where(n < min_samples, 0, safe_sqrt(s_proj))  # finite gradient at s = 0
    sigma = jnp.where(jnp.isfinite(sigma), sigma, 0).astype(dtype)
    steps = sol.stats["num_steps"].astype(jnp.int32)
    rms = jnp.where(jnp.isfinite(rms), rms, 0).astype(dtype)
    return sigma, status, steps, rms, rms0.astype(dtype), n.astype(jnp.int32)


def _fit_pixels(data, s0, s_max, form, refit, solver, max_steps, min_samples):
    """Per-pixel fits, all pixels at once: closed form (`solver=None` for the qualitative form
    with the albedo refitted) or `BatchedLM`; the same problem as `_solve_one`, one per pixel."""
    i, w, geo, rho_given = data
    dtype = i.dtype
    n_px = i.shape[1]

    def fn(y, a):
        return _residuals(y[:, 0][None], a, form, refit)

    if solver is None:
        s = _exact_pixels(data, s_max)
        done = jnp.ones((n_px,), bool)
        steps = jnp.zeros((n_px,), jnp.int32)
    else:
        # BatchedLM is a while_loop, which reverse mode cannot differentiate: its roughness is
        # a constant to `jax.grad` (the closed form above is differentiated as usual).
        data = jax.lax.stop_gradient(data)
        y0 = jnp.full((n_px,), s0, dtype)
        if form == "qualitative" and refit:
            y0 = _exact_pixels(data, s_max).astype(dtype)

        def resid(y, a):
            return _residuals(y[0], a, form, refit)

        geo = tuple(jnp.broadcast_to(x, i.shape) for x in geo)
        (s,), done, steps = solve_pixels(resid, (y0,), (i, w, geo, rho_given),
                                         jnp.ones((n_px,), bool), solver, max_steps=max_steps,
                                         lower=(0,), upper=(s_max,))
    n = sum0(w > 0)
    s_proj = jnp.clip(s, 0, s_max)
    at_bound = (s <= 0) | (s >= s_max)
    r = fn(s_proj[:, None], data)
    r0 = fn(jnp.zeros((n_px, 1), dtype), data)
    denom = jnp.maximum(n, 1).astype(dtype)
    rms = safe_sqrt(sum0(r**2) / denom)
    rms0 = safe_sqrt(sum0(r0**2) / denom)
    status = first_status([(n < min_samples, Status.TOO_FEW_LIGHTS),
                           (~done, Status.NOT_CONVERGED), (at_bound, Status.AT_BOUND)])
    sigma = jnp.where(n < min_samples, 0, safe_sqrt(s_proj)).astype(dtype)
    return sigma, status, steps, rms.astype(dtype), rms0.astype(dtype), n.astype(jnp.int32)


@eqx.filter_jit
def _fit(images, normals, albedo, lights, mask, sample_mask, labels, s0, s_max, cos_min,
         saturation, solver, *, form, per, refit, max_steps, min_samples, n_labels):
    k, h, wd = images.shape
    dtype = images.dtype
    cos_i, cos_r, p = _geometry(normals, lights)
    ok = (jnp.isfinite(images) & (images < saturation) & sample_mask & mask[None]
          & (cos_i > cos_min))
    rho_given = albedo
    if not refit:  # the given albedo is used: its non-finite pixels are dropped
        ok = ok & jnp.isfinite(albedo)[None]
        rho_given = jnp.where(jnp.isfinite(albedo), albedo, 0)
    w = ok.astype(dtype)
    i = jnp.where(ok, images, 0)
    flat = lambda x: x.reshape(k, h * wd)  # noqa: E731
    geo = _basis(flat(cos_i), cos_r.reshape(1, -1), flat(p), form)
    data = (flat(i), flat(w), geo, rho_given.reshape(-1))
    args = (s0, s_max, form, refit, solver, max_steps, min_samples)

    reduced = form == "qualitative" and refit
    if per == "global":
        out = _solve_one(data, *args, reduced=reduced)
    elif per == "region":
        lab = labels.reshape(-1)

        def region(r):
            sel = (lab == r).astype(dtype)
            d = (data[0], data[1] * sel[None], data[2], data[3])
            return _solve_one(d, *args, reduced=reduced)

        out = jax.vmap(region)(jnp.arange(n_labels))
    elif solver is None or isinstance(solver, BatchedLM):  # per pixel, image-wide kernels
        out = _fit_pixels(data, *args)
    else:  # per pixel: one optimistix solve per pixel, lifted with vmap
        def pixel(i_, w_, geo_, rho_):
            geo_ = tuple(x[:, None] for x in geo_)
            return _solve_one((i_[:, None], w_[:, None], geo_, rho_[None]), *args)

        out = jax.vmap(pixel, in_axes=(1, 1, 1, 0))(*data)
    if per == "pixel":
        m = mask.reshape(-1)
        sigma, status, steps, rms, rms0, n = out
        status = jnp.where(m, status, Status.MASKED).astype(jnp.int32)
        out = tuple(jnp.where(m, x, 0).astype(x.dtype) for x in (sigma,)) + (status,) + tuple(
            jnp.where(m, x, 0).astype(x.dtype) for x in (steps, rms, rms0, n))
        out = tuple(x.reshape(h, wd) for x in out)

    # The albedo the fit used (per pixel, at the fitted sigma).
    sig = out[0] if per != "region" else jnp.where(
        labels >= 0, out[0][jnp.clip(labels, 0, n_labels - 1)], 0)
    sig = jnp.broadcast_to(sig, (h, wd))
    f = _shading(cos_i, cos_r[None], p, (sig**2)[None], form)
    rho = _albedo(i, w, f) if refit else albedo
    rho = jnp.where(mask, rho, 0).astype(dtype)
    return RoughnessFit(*out, rho)


def _check_stack(images, normals, albedo, lights, mask):
    """Validate and convert the common (images, normals, albedo, lights, mask) arguments."""
    images = jnp.asarray(images)
    if not jnp.issubdtype(images.dtype, jnp.floating):
        raise ValueError(f"images must be floating point in [0, 1], got dtype {images.dtype}")
    if images.ndim != 3:
        raise ValueError(f"images must be grey (K, H, W), got shape {images.shape}")
    k, h, w = images.shape
    dtype = images.dtype
    normals = jnp.asarray(normals, dtype)
    if normals.shape != (h, w, 3):
        raise ValueError(f"normals must be (H, W, 3) = {(h, w, 3)}, got {normals.shape}")
    albedo = jnp.asarray(albedo, dtype)
    if albedo.shape != (h, w):
        raise ValueError(f"albedo must be (H, W) = {(h, w)}, got {albedo.shape}")
    lights = np.asarray(lights, np.float64)
    if lights.shape != (k, 3):
        raise ValueError(f"lights must be (K, 3) = {(k, 3)} to match images, got {lights.shape}")
    norms = np.linalg.norm(lights, axis=1)
    if not np.all(np.isfinite(lights)) or np.any(norms < 1e-8):
        raise ValueError("lights must be finite, non-zero vectors")
    lights = jnp.asarray(lights / norms[:, None], dtype)
    if mask is None:
        mask = jnp.ones((h, w), bool)
    elif np.shape(mask) != (h, w):
        raise ValueError(f"mask must have shape (H, W) = {(h, w)}, got {np.shape(mask)}")
    mask = jnp.asarray(mask, bool)
    return images, normals, albedo, lights, mask


def fit_roughness(
    images: Float[ArrayLike, "K H W"],
    normals: Float[ArrayLike, "H W 3"],
    albedo: Float[ArrayLike, "H W"],
    lights: Float[ArrayLike, "K 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    per: str = "global",
    labels: Int[ArrayLike, "H W"] | None = None,
    form: str = "qualitative",
    refit_albedo: bool = True,
    sample_mask: Bool[ArrayLike, "K H W"] | None = None,
    saturation: float = 1.0,
    max_theta_deg: float = 89.0,
    sigma_max: float = SIGMA_MAX,
    sigma0: float = 0.1,
    min_samples: int | None = None,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 64,
) -> RoughnessFit:
    """Fit the Oren–Nayar roughness $\\sigma$ to images with known normals (Oren & Nayar 1994).

    Minimises $\\sum w_{k} (I_{k} - \\rho\\, f(n, l_k, v; \\sigma))^2$ over the usable lit samples
    with an optimistix least-squares solver (default `optx.LevenbergMarquardt`), in
    $s = \\sigma^2$ (see the module docstring), then projects $\\sigma$ onto `[0, sigma_max]`.
    With `refit_albedo` (default) each pixel's albedo is eliminated in closed form for every
    trial $\\sigma$ (variable projection: $\\rho = \\sum I f / \\sum f^2$), so an albedo biased by
    a Lambertian solve does not bias $\\sigma$; otherwise the given albedo is used as is.

    - `per="global"`: one $\\sigma$ for every pixel in `mask`.
    - `per="region"`: one $\\sigma$ per label $0 \\dots R-1$ of the integer map `labels`
      (negative labels are ignored); the R problems are solved under `vmap`.
    - `per="pixel"`: one $\\sigma$ per pixel. For the qualitative form with the albedo refitted
      (the defaults) this has a closed-form exact solution (see `_exact_pixels`: the cost is a
      ratio of quadratics in $B/A$), computed for all pixels at once with `steps` 0; otherwise,
      or when a solver is passed, a batched one-parameter solve per pixel (`jaxps.BatchedLM`,
      image-wide, or any optimistix solver under `vmap`).

    **Arguments:**
    - `images`: `(K, H, W)` grey, linear, floating point.
    - `normals`: `(H, W, 3)` unit normals (e.g. from `photometric_stereo`).
    - `albedo`: `(H, W)` (used as is when `refit_albedo=False`; pixels where it is
      non-finite are then left out of the fit).
    - `lights`: `(K, 3)` directions toward the lights (normalised here).
    - `mask`: `(H, W)` bool pixels to use (default: all).
    - `per`, `labels`: see above.
    - `form`: `"qualitative"` or `"full"` Oren–Nayar.
    - `refit_albedo`: eliminate the albedo per pixel (default) or keep `albedo`.
    - `sample_mask`: `(K, H, W)` bool samples allowed (e.g. not in cast shadow).
    - `saturation`: samples at or above this are dropped.
    - `max_theta_deg`: samples with $\\theta_i$ above this (attached shadow) are dropped.
    - `sigma_max`: upper bound of $\\sigma$ (radians).
    - `sigma0`: starting $\\sigma$.
    - `min_samples`: fewer usable samples than this gives `TOO_FEW_LIGHTS` (default 2 per
      pixel fit, with albedo refitted; else 1; 2 per global/region fit).
    - `solver`: an `optx.AbstractLeastSquaresSolver` object (default `LevenbergMarquardt`), or
      for `per="pixel"` a `jaxps.BatchedLM` (default where there is no closed form);
      `max_steps`: its step limit.

    **Returns:** a `RoughnessFit` (`sigma`, `status`, `steps`, `rms`, `rms_lambertian`,
    `n_samples`, `albedo`), floats in the dtype of `images`.

    **Raises:** `ValueError` naming the argument for wrong shapes, dtypes, `per`, `form` or
    bounds.
    """
    images, normals, albedo, lights, mask = _check_stack(images, normals, albedo, lights, mask)
    k, h, w = images.shape
    dtype = images.dtype
    _check_form(form)
    if per not in ("global", "region", "pixel"):
        raise ValueError(f"per must be 'global', 'region' or 'pixel', got {per!r}")
    if not (0 < sigma_max <= np.pi / 2):
        raise ValueError(f"sigma_max must be in (0, pi/2] radians, got {sigma_max}")
    if not (0 <= sigma0 < sigma_max):
        raise ValueError(f"sigma0 must be in [0, sigma_max), got {sigma0}")
    if not (0 < max_theta_deg <= 90):
        raise ValueError(f"max_theta_deg must be in (0, 90], got {max_theta_deg}")
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    n_labels = 0
    if per == "region":
        if labels is None:
            raise ValueError("per='region' needs labels= (an (H, W) integer map)")
        labels_np = np.asarray(labels)
        if labels_np.shape != (h, w) or not np.issubdtype(labels_np.dtype, np.integer):
            raise ValueError(f"labels must be an (H, W) = {(h, w)} integer map, got "
                             f"{labels_np.shape} {labels_np.dtype}")
        n_labels = int(labels_np.max()) + 1 if labels_np.size else 0
        if n_labels < 1:
            raise ValueError("labels has no region (every label is negative)")
        labels = jnp.asarray(labels_np, jnp.int32)
    else:
        labels = jnp.zeros((h, w), jnp.int32)
    if sample_mask is None:
        sample_mask = jnp.ones((k, h, w), bool)
    elif np.shape(sample_mask) != (k, h, w):
        raise ValueError(f"sample_mask must be (K, H, W) = {(k, h, w)}, got "
                         f"{np.shape(sample_mask)}")
    if min_samples is None:
        min_samples = (2 if refit_albedo else 1) if per == "pixel" else 2
    if solver is None and not (per == "pixel" and form == "qualitative" and refit_albedo):
        solver = BatchedLM() if per == "pixel" else default_solver(dtype)
    elif isinstance(solver, BatchedLM) and per != "pixel":
        raise ValueError("solver=BatchedLM() is for per='pixel'; pass an optimistix solver")
    as_dtype = lambda v: jnp.asarray(v, dtype)  # noqa: E731
    return _fit(images, normals, albedo, lights, mask, jnp.asarray(sample_mask, bool), labels,
                as_dtype(sigma0**2), as_dtype(sigma_max**2),
                as_dtype(np.cos(np.radians(max_theta_deg))), as_dtype(saturation), solver,
                form=form, per=per, refit=refit_albedo, max_steps=int(max_steps),
                min_samples=int(min_samples), n_labels=n_labels)
