"""Gradients through photometric stereo, rendering, relighting and the angular error: finite on
scenes with background, masked, saturated and NaN pixels, and equal to finite differences
(`jax.test_util.check_grads`, float64)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxps


def _scene(noise=0.01, lights=None):
    """A 14x12 face (dark background around it) with one NaN, one saturated and one masked
    pixel, in float64 numpy; noise keeps every residual away from the kink of its square root."""
    lights = jaxps.lights_from_angles([0, 30, -25, 10, -15], [0, 10, -5, 30, -25]) \
        if lights is None else lights
    s = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(14, 12), lights)
    rng = np.random.default_rng(0)
    images = np.asarray(s.images, np.float64)
    inside = images > 0
    images = np.where(inside, images + noise * rng.normal(size=images.shape), 0.0)
    images[2, 7, 6] = np.nan  # a broken sample: dropped
    images[0, 8, 5] = 1.5  # saturated, well clear of the threshold: dropped
    mask = np.ones(images.shape[1:], bool)
    mask[6, 6] = False
    return images, np.asarray(lights, np.float64), mask, np.asarray(s.mask)


def _weights(shape, seed):
    return jnp.asarray(np.random.default_rng(seed).normal(size=shape))


@pytest.mark.parametrize("method", ["l2", "l1"])
def test_photometric_stereo_gradients_match_finite_differences(method):
    with jax.enable_x64(True):
        images, lights, mask, face = _scene()
        assert (~face).sum() > 20  # background pixels (DARK) are part of the test
        h, w = mask.shape
        wn, wa, wr = _weights((h, w, 3), 1), _weights((h, w), 2), _weights((h, w), 3)

        def loss(images, lights):
            res = jaxps.photometric_stereo(images, lights, mask=mask, method=method)
            return (jnp.sum(wn * res.normals) + jnp.sum(wa * res.albedo)
                    + jnp.sum(wr * res.residual))

        res = jaxps.photometric_stereo(images, lights, mask=mask, method=method)
        codes = set(np.unique(np.asarray(res.status)).tolist())
        assert {0, int(jaxps.Status.MASKED), int(jaxps.Status.DARK)} <= codes
        g_images, g_lights = jax.grad(loss, argnums=(0, 1))(images, lights)
        assert np.isfinite(np.asarray(g_lights)).all()
        assert np.isfinite(np.asarray(g_images)).all()
        assert np.all(np.asarray(g_images)[:, ~face] == 0)  # failed pixels: zero, not NaN
        assert np.asarray(g_images)[2, 7, 6] == 0  # the NaN sample was not used
        check_grads(lambda lt: loss(images, lt), (lights,), order=1, modes=["rev"],
                    eps=1e-6)
        # The images' gradient along random directions, NaN samples held fixed.
        finite = np.nan_to_num(images)
        nan_at = np.isnan(images)

        def of_images(x):
            return loss(jnp.where(nan_at, jnp.nan, x), lights)

        check_grads(of_images, (finite,), order=1, modes=["rev"], eps=1e-6)


def test_weighted_path_and_colour_gradients_match_finite_differences():
    with jax.enable_x64(True):
        images, lights, _, _ = _scene()
        colour = np.stack([images, 0.8 * images, 0.5 * images], axis=-1)
        wa = _weights(colour.shape[1:], 4)

        def loss(x, lights):  # a shadow threshold: every pixel goes through the weighted solve
            res = jaxps.photometric_stereo(x, lights, shadow_threshold=0.02)
            return jnp.sum(wa * res.albedo) + jnp.sum(res.normals[..., 0])

        g = jax.grad(loss, argnums=(0, 1))(colour, lights)
        assert all(np.isfinite(np.asarray(a)).all() for a in g)
        check_grads(lambda lt: loss(colour, lt), (lights,), order=1, modes=["rev"], eps=1e-6)
        # Per-pixel (near) lights, the field `near_photometric_stereo` solves with.
        field = np.broadcast_to(lights[:, None, None, :], images.shape + (3,)).copy()
        field += 0.01 * np.random.default_rng(8).normal(size=field.shape)
        check_grads(lambda f: loss(colour, f), (field,), order=1, modes=["rev"], eps=1e-6)


def test_render_and_angular_error_gradients():
    with jax.enable_x64(True):
        s = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(10, 8),
                                         jaxps.synthetic.scanner_lights(20.0))
        normals = np.asarray(s.normals, np.float64)
        albedo = np.asarray(s.albedo, np.float64)
        lights = np.asarray(s.lights, np.float64)
        check_grads(lambda n, a, lt: jnp.sum(jaxps.render_lambertian(n, a, lt) ** 2),
                    (normals, albedo, lights), order=1, modes=["rev"], eps=1e-6)
        check_grads(lambda n, lt, sig: jnp.sum(jaxps.render_oren_nayar(n, albedo, lt, sig)),
                    (normals, lights, 0.3), order=1, modes=["rev"], eps=1e-6)
        # The angular error between equal maps sits at the kink of |a x b|: zero gradient, not
        # NaN; a zero normal (background) too.
        other = normals.copy()
        other[0, 0] = 0.0
        g = jax.grad(lambda a: jnp.sum(jaxps.angular_error(a, other)))(normals)
        assert np.isfinite(np.asarray(g)).all()
        rng = np.random.default_rng(5)
        tilted = normals + 0.1 * rng.normal(size=normals.shape)
        check_grads(lambda a: jnp.sum(jaxps.angular_error(a, normals)), (tilted,), order=1,
                    modes=["rev"], eps=1e-6)


def test_relight_gradients_are_finite():
    s = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(24),
                                     jaxps.synthetic.scanner_lights(20.0))
    model = jaxps.fit_brdf(s.images, s.normals, s.albedo, s.lights, mask=s.mask,
                           method="mlp_ratio", n_samples=2000, max_steps=3)
    light = jnp.asarray([[0.2, 0.1, 0.97]])

    def loss(normals, albedo, light):
        return jnp.sum(jaxps.relight(model, normals, albedo, light, mask=s.mask))

    g = jax.grad(loss, argnums=(0, 1, 2))(s.normals, s.albedo, light)
    assert all(np.isfinite(np.asarray(a)).all() for a in g)
    assert float(jnp.abs(g[2]).sum()) > 0


def test_robust_and_fitted_methods_have_finite_gradients():
    images, lights, mask, face = _scene()
    images = images.astype(np.float32)
    lights = lights.astype(np.float32)
    for method in ("barsky", "irls", "sbl", "semi_calibrated", "oren_nayar"):
        def loss(x, method=method):
            res = jaxps.photometric_stereo(x, lights, mask=mask, method=method)
            return jnp.sum(res.normals[..., 0]) + jnp.sum(res.albedo)

        g = np.asarray(jax.grad(loss)(images))
        assert np.isfinite(g).all(), method
        if method == "oren_nayar":  # its BatchedLM loop is held constant: zero, not an error
            assert np.all(g == 0)
        else:
            assert np.abs(g).sum() > 0, method
            assert np.all(g[:, ~face] == 0), method


def test_barsky_gradient_is_that_of_its_chosen_subset():
    with jax.enable_x64(True):
        images, lights, mask, _ = _scene()
        finite, nan_at = np.nan_to_num(images), np.isnan(images)
        wn = _weights(mask.shape + (3,), 6)

        def loss(x):
            res = jaxps.photometric_stereo(jnp.where(nan_at, jnp.nan, x), lights, mask=mask,
                                           method="barsky")
            return jnp.sum(wn * res.normals)

        check_grads(loss, (finite,), order=1, modes=["rev"], eps=1e-6)


def test_roughness_fit_gradients_are_finite_inside_and_at_the_bound():
    s = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(24),
                                     jaxps.synthetic.scanner_lights(20.0))
    rough = jaxps.render_oren_nayar(s.normals, s.albedo, s.lights, 0.3)

    def sigma(images, per):
        fit = jaxps.fit_roughness(images, s.normals, s.albedo, s.lights, mask=s.mask, per=per)
        return jnp.sum(jnp.asarray(fit.sigma))

    # A rough surface: an interior optimum, differentiated by optimistix's implicit adjoint.
    g = np.asarray(jax.grad(sigma)(rough, "global"))
    assert np.isfinite(g).all() and np.abs(g).sum() > 0
    # Lambertian images: the fit ends at sigma = 0, where the gradient is 0, not an error.
    g = np.asarray(jax.grad(sigma)(s.images, "global"))
    assert np.isfinite(g).all() and np.all(g == 0)
    assert np.isfinite(np.asarray(jax.grad(sigma)(rough, "pixel"))).all()
