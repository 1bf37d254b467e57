"""Gradients through `jaxps.integration`: finite whatever the normals hold, and correct.

Correctness: `jax.test_util.check_grads` (reverse mode against central finite differences) in
float64 on a 12x14 face-like scene with background pixels outside the mask holding zero and
NaN normals, and zero, NaN and backfacing normals inside the mask. Finiteness: float32 on a
scene with a dark (zero-normal) and NaN background.
"""

import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxps

# CG solved to near round-off, so that finite differences see the exact solution.
EXACT = {"cg_rtol": 1e-12}
# Finite-difference step: small enough that the zero normal stays out (a normal counts once its
# squared length passes 1e-12), ample for float64.
EPS = 1e-7
K = np.array([[30.0, 0.0, 6.5], [0.0, 32.0, 5.0], [0.0, 0.0, 1.0]])


def scene(dtype=np.float64, h=12, w=14, seed=0, noise=0.05, backfacing=True):
    """Normals of a face-like relief with noise, a mask, bad normals inside and outside it."""
    s = jaxps.synthetic.face_like(h, w)
    mask = np.asarray(s.mask).copy()
    z = np.asarray(s.height, np.float64) / 3
    n = np.asarray(jaxps.normals_from_height(jnp.asarray(z)), np.float64)
    rng = np.random.default_rng(seed)
    n = n + noise * rng.standard_normal(n.shape)
    n[~mask] = 0.0  # dark background
    n[0, :3] = np.nan  # NaN background
    n[5, 7] = 0.0  # zero normal inside the mask
    n[6, 4] = np.nan  # NaN normal inside the mask
    if backfacing:
        n[4, 9] = [0.6, 0.2, -0.3]  # backfacing: n_z floored
    weights = rng.standard_normal((h, w))
    return jnp.asarray(n, dtype), jnp.asarray(mask), jnp.asarray(weights, dtype)


def loss(method, mask, weights, **options):
    def f(normals):
        return jnp.sum(weights * jaxps.integrate(normals, mask=mask, method=method, **options))
    return f


CASES = {
    "fc": {},
    "fc-info": {"return_info": True},
    "dct": {},
    "lsq": EXACT,
    # one reweighting: the weights are the constant 1/2, so this is exactly the function whose
    # gradient `bilateral` gives (its last weighted least-squares problem)
    "bilateral-1": dict(max_steps=1, **EXACT),
    "fc-perspective": {"intrinsics": K},
    "dct-perspective": {"intrinsics": K},
    "lsq-perspective": dict(intrinsics=K, **EXACT),
}


@pytest.mark.parametrize("case", CASES)
def test_integrate_gradients_match_finite_differences(case):
    method = case.split("-")[0]
    options = dict(CASES[case])
    info = options.pop("return_info", False)
    with jax.enable_x64(True):
        normals, mask, weights = scene()
        if info:
            def f(n):
                res = jaxps.integrate(n, mask=mask, method=method, return_info=True, **options)
                return jnp.sum(weights * res.height)
        else:
            f = loss(method, mask, weights, **options)
        g = jax.grad(f)(normals)
        assert bool(jnp.all(jnp.isfinite(g)))
        bad = ~jnp.all(jnp.isfinite(normals), axis=-1) | ~mask
        assert bool(jnp.all(jnp.where(bad[..., None], g, 0) == 0)), "left-out pixels: 0"
        check_grads(f, (normals,), order=1, modes=["rev"], eps=EPS, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("method", ["fc", "lsq"])
def test_integrate_gradient_in_pixel_size(method):
    with jax.enable_x64(True):
        normals, mask, weights = scene()
        opts = EXACT if method == "lsq" else {}

        def f(ps):
            return jnp.sum(weights * jaxps.integrate(normals, mask=mask, method=method,
                                                     pixel_size=ps, **opts))
        check_grads(f, (jnp.asarray(1.3),), order=1, modes=["rev"], eps=EPS)


def test_lsq_gradient_with_two_components_and_an_isolated_pixel():
    """The transpose solve projects the cotangent per connected component (Jacobi-weighted)."""
    with jax.enable_x64(True):
        normals, mask, weights = scene()
        mask = np.asarray(mask).copy()
        mask[:, 7] = False  # two halves
        mask[2, 2:5] = False
        mask[3, 2:5] = False
        mask[2, 3] = True  # an island of one pixel (no edge) is still integrated
        normals = normals.at[2, 3].set(jnp.asarray([0.1, 0.2, 0.9]))
        check_grads(loss("lsq", jnp.asarray(mask), weights, **EXACT), (normals,), order=1,
                    modes=["rev"], eps=EPS, atol=1e-5, rtol=1e-5)


def test_auto_gradient_is_that_of_the_method_it_picks():
    with jax.enable_x64(True):
        normals, mask, weights = scene(noise=0.0, backfacing=False)
        r, c = np.mgrid[:12, :14]
        full = jaxps.normals_from_height(jnp.asarray(np.sin(c / 3) * np.cos(r / 4) / 2))
        for n, m, picked in ((normals, mask, "bilateral"), (full, None, "dct")):
            info = jaxps.integrate(n, mask=m, method="auto", return_info=True, **EXACT)
            assert info.method == picked
            g = jax.grad(loss("auto", m, weights, **EXACT))(n)
            # to rounding: `method="dct"` runs as one jit, "auto" step by step
            np.testing.assert_allclose(g, jax.grad(loss(picked, m, weights, **EXACT))(n),
                                       rtol=1e-12, atol=1e-14)
        check_grads(loss("auto", None, weights), (full,), order=1, modes=["rev"], eps=EPS,
                    atol=1e-5, rtol=1e-5)


def test_full_bilateral_gradient_is_finite_and_zero_off_the_mask():
    with jax.enable_x64(True):
        normals, mask, weights = scene()
        g = jax.grad(loss("bilateral", mask, weights))(normals)
        assert bool(jnp.all(jnp.isfinite(g))) and float(jnp.abs(g).max()) > 0
        assert bool(jnp.all(jnp.where(~mask[..., None], g, 0) == 0))


@pytest.mark.parametrize("method", jaxps.INTEGRATION_METHODS)
def test_float32_gradients_finite_on_a_dark_background(method):
    s = jaxps.synthetic.face_like(40)
    n = jnp.where(s.mask[..., None], s.normals, 0)  # dark background, no mask given
    n = n.at[0, :5].set(jnp.nan).at[20, 16].set(0.0)
    w = jax.random.normal(jax.random.key(0), s.height.shape)
    for mask in (None, s.mask):
        g = jax.grad(loss(method, mask, w))(n)
        assert g.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(g)))
        assert float(jnp.abs(g).max()) > 0


def test_normals_from_height_gradients():
    with jax.enable_x64(True):
        s = jaxps.synthetic.face_like(12, 14)
        z, mask = jnp.asarray(s.height, jnp.float64) / 3, s.mask
        w = jax.random.normal(jax.random.key(1), (12, 14, 3), jnp.float64)
        for m in (None, mask):
            def f(z, m=m):
                return jnp.sum(w * jaxps.normals_from_height(z, mask=m, pixel_size=0.7))
            check_grads(f, (z,), order=1, modes=["rev"], eps=EPS)


def test_gradients_from_normals_and_integrability_map_gradients():
    with jax.enable_x64(True):
        normals, mask, weights = scene()

        def f(n):
            p, q = jaxps.gradients_from_normals(n, mask)
            return jnp.sum(weights * p) - jnp.sum(weights * q)

        def curl(n):
            return jnp.sum(weights * jaxps.integrability_map(n, mask=mask))

        for fun in (f, curl):
            g = jax.grad(fun)(normals)
            assert bool(jnp.all(jnp.isfinite(g)))
            check_grads(fun, (normals,), order=1, modes=["rev"], eps=EPS, atol=1e-5, rtol=1e-5)


def backward_cost(h=256, w=320, repeats=5, methods=("fc", "dct", "lsq", "bilateral")):
    """Not a test: the time of `jax.grad` of `sum(w * height)` over that of the forward
    `integrate`, per method, at `h`x`w` on the face-like scene (minimum of `repeats`, after a
    warm-up call). `python tests/test_gradients_integration.py` prints it (docs/integration.md).
    """
    s = jaxps.synthetic.face_like(h, w)
    wts = jax.random.normal(jax.random.key(0), (h, w))
    out = {}
    for method in methods:
        fwd = loss(method, s.mask, wts)
        bwd = jax.grad(fwd)
        times = []
        for fun in (fwd, bwd):
            jax.block_until_ready(fun(s.normals))
            best = np.inf
            for _ in range(repeats):
                t0 = time.perf_counter()
                jax.block_until_ready(fun(s.normals))
                best = min(best, time.perf_counter() - t0)
            times.append(best)
        out[method] = (times[0], times[1])
    return out


if __name__ == "__main__":
    for name, (f, b) in backward_cost().items():
        print(f"{name:10s} forward {1e3 * f:8.1f} ms  value and gradient {1e3 * b:8.1f} ms  "
              f"ratio {b / f:5.1f}")
