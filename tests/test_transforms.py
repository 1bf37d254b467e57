"""The public array functions inside a caller's `jax.jit` and `jax.vmap`: the same values as
eager calls.

Each function checks its arguments on the host where they have a value, and leaves the check to
the caller inside a trace. Four of the cases below raised inside a trace until the
twenty-fifth session: `oren_nayar` (its `sigma >= 0` test), `near_light_field` (its positions'
tests), and `surface_points` and `integrate` given a traced `pixel_size`.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import face_scene

import jaxps

SCENE = face_scene(24)
NORMALS, ALBEDO, LIGHTS = SCENE.normals, SCENE.albedo, SCENE.lights
HEIGHT, MASK = SCENE.height, SCENE.mask
POSITIONS = jnp.asarray(np.asarray(LIGHTS) * 400.0, jnp.float32)  # lamps 400 px away
ANGLES = jnp.linspace(0.1, 1.2, 7, dtype=jnp.float32)


def _tilted(normals, t):
    """Unit normals tipped by `t` along x: a second, different input of the same kind."""
    n = normals + jnp.asarray([[[t, 0.0, 0.0]]], normals.dtype)
    return n / jnp.linalg.norm(n, axis=-1, keepdims=True)


# name: (function of one argument, that argument, a second valid value of it)
CASES = {
    "oren_nayar, sigma": (
        lambda s: jaxps.oren_nayar(ANGLES, ANGLES[::-1], ANGLES, s),
        jnp.float32(0.2), jnp.float32(0.4)),
    "render_oren_nayar, sigma": (
        lambda s: jaxps.render_oren_nayar(NORMALS, ALBEDO, LIGHTS, s),
        jnp.float32(0.2), jnp.float32(0.4)),
    "render_lambertian, lights": (
        lambda l: jaxps.render_lambertian(NORMALS, ALBEDO, l), LIGHTS, LIGHTS[::-1]),
    "angular_error, normals": (
        lambda n: jaxps.angular_error(n, NORMALS, mask=MASK), _tilted(NORMALS, 0.1),
        _tilted(NORMALS, -0.2)),
    "normals_from_height, height": (
        lambda z: jaxps.normals_from_height(z, pixel_size=0.5), HEIGHT, 0.5 * HEIGHT),
    "normals_from_height, pixel_size": (
        lambda p: jaxps.normals_from_height(HEIGHT, pixel_size=p), jnp.float32(0.5),
        jnp.float32(2.0)),
    "surface_points, height": (
        lambda z: jaxps.surface_points(z, pixel_size=2.0), HEIGHT, 0.5 * HEIGHT),
    "surface_points, pixel_size": (
        lambda p: jaxps.surface_points(HEIGHT, pixel_size=p), jnp.float32(0.5),
        jnp.float32(2.0)),
    "near_light_field, positions": (
        lambda p: jaxps.near_light_field(p, jaxps.surface_points(HEIGHT)), POSITIONS,
        1.5 * POSITIONS),
    "integrate fc, normals": (
        lambda n: jaxps.integrate(n, mask=MASK), NORMALS, _tilted(NORMALS, 0.1)),
    "integrate dct, normals": (
        lambda n: jaxps.integrate(n, mask=MASK, method="dct"), NORMALS, _tilted(NORMALS, 0.1)),
    "integrate fc, pixel_size": (
        lambda p: jaxps.integrate(NORMALS, mask=MASK, pixel_size=p), jnp.float32(0.5),
        jnp.float32(2.0)),
    "photometric_stereo l2, images": (
        lambda i: jaxps.photometric_stereo(i, LIGHTS, mask=MASK)[:3], SCENE.images,
        0.5 * SCENE.images),
}


def _assert_close(got, want, label):
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=2e-5, atol=2e-5,
                                   err_msg=label)


@pytest.mark.parametrize("name", sorted(CASES))
def test_inside_jit_and_vmap_equals_eager_calls(name):
    f, x, y = CASES[name]
    want_x, want_y = f(x), f(y)
    _assert_close(jax.jit(f)(x), want_x, f"{name}: jit")
    both = jax.vmap(f)(jnp.stack([x, y]))
    _assert_close(jax.tree.map(lambda a: a[0], both), want_x, f"{name}: vmap, first")
    _assert_close(jax.tree.map(lambda a: a[1], both), want_y, f"{name}: vmap, second")


def test_eager_calls_still_check_what_a_trace_cannot():
    with pytest.raises(ValueError, match="sigma must be >= 0"):
        jaxps.oren_nayar(ANGLES, ANGLES, ANGLES, -0.1)
    with pytest.raises(ValueError, match="must broadcast together"):
        jaxps.oren_nayar(ANGLES, ANGLES[:3], ANGLES, 0.1)
    with pytest.raises(ValueError, match="positions contain NaN"):
        jaxps.near_light_field(POSITIONS.at[0, 0].set(jnp.nan), jaxps.surface_points(HEIGHT))
    for bad in (0.0, -1.0, float("nan"), jnp.float32(-2.0), np.ones(2)):
        with pytest.raises(ValueError, match="pixel_size must be positive and finite"):
            jaxps.surface_points(HEIGHT, pixel_size=bad)
        with pytest.raises(ValueError, match="pixel_size must be positive and finite"):
            jaxps.integrate(NORMALS, pixel_size=bad)


@pytest.mark.parametrize("method", ["fc", "dct"])
def test_gradient_in_pixel_size_inside_jit(method):
    # The height scales with pixel_size, so d/dp sum(h(p)^2) = 2 sum(h(p)^2) / p.
    def loss(p):
        return jnp.sum(jaxps.integrate(NORMALS, mask=MASK, method=method, pixel_size=p) ** 2)

    p = jnp.float32(0.5)
    want = 2 * float(loss(p)) / 0.5
    assert float(jax.jit(jax.grad(loss))(p)) == pytest.approx(want, rel=1e-4)
    assert float(jax.grad(loss)(p)) == pytest.approx(want, rel=1e-4)


def test_constant_arguments_inside_jit():
    # A constant sigma, positions or pixel_size inside a caller's jit is a tracer of JAX's
    # too: the first three raised on 73ea9ec.
    calls = {
        "oren_nayar": (lambda t: jaxps.oren_nayar(t, t, t, 0.2), ANGLES),
        "near_light_field": (lambda z: jaxps.near_light_field(
            np.asarray(POSITIONS), jaxps.surface_points(z)), HEIGHT),
        "surface_points": (lambda z: jaxps.surface_points(z, pixel_size=jnp.float32(0.5)),
                           HEIGHT),
        "integrate": (lambda n: jaxps.integrate(n, pixel_size=jnp.float32(0.5)), NORMALS),
        "normals_from_height": (lambda z: jaxps.normals_from_height(
            z, pixel_size=jnp.float32(0.5)), HEIGHT),
    }
    for name, (f, x) in calls.items():
        _assert_close(jax.jit(f)(x), f(x), name)
