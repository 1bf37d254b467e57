"""`core._host.CpuTuned`: programs compiled with XLA-CPU options, and their fallbacks."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxps
from jaxps.core._host import NO_YNN, OLDER_EMITTERS, CpuTuned


def _sum_of_squares(x):
    return jnp.sum(x * x, axis=0)  # a reduction over a small leading axis (a YNNPACK fusion)


def _fusion_kinds(jitted, *args):
    return jitted.lower(*args).compile().as_text()


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="XLA-CPU options")
def test_tuned_program_is_compiled_with_the_options():
    x = jnp.asarray(np.random.default_rng(0).normal(size=(5, 4096)), jnp.float32)
    tuned = CpuTuned(_sum_of_squares, NO_YNN)
    np.testing.assert_allclose(tuned(x), np.sum(np.asarray(x) ** 2, 0), rtol=1e-5)
    if not tuned.known:
        pytest.skip(f"this JAX {jax.__version__} has no option {NO_YNN}")
    # this JAX fuses the reduction into YNNPACK by default, and the tuned program does not
    plain_text = _fusion_kinds(tuned.plain, x)
    tuned_text = _fusion_kinds(tuned.tuned, x)
    if "__ynn_fusion" not in plain_text:
        pytest.skip("this XLA makes no YNNPACK fusion here")
    assert "__ynn_fusion" not in tuned_text


def test_unknown_option_falls_back_to_the_plain_program():
    x = jnp.arange(12.0).reshape(3, 4)
    tuned = CpuTuned(_sum_of_squares, {"xla_no_such_option_in_any_jax": True})
    np.testing.assert_allclose(tuned(x), np.sum(np.asarray(x) ** 2, 0))
    assert not tuned.known  # rejected once, at compile time; plain from then on
    np.testing.assert_allclose(tuned(2 * x), 4 * np.sum(np.asarray(x) ** 2, 0))


def test_other_errors_are_not_swallowed():
    def bad(x):
        raise ValueError("x must be positive")

    tuned = CpuTuned(bad, OLDER_EMITTERS)
    with pytest.raises(ValueError, match="positive"):
        tuned(jnp.ones(3))
    assert tuned.known


def test_inside_a_trace_the_plain_program_is_inlined():
    # compiler options are refused on a nested jit; the tuned wrapper must not be taken there
    tuned = CpuTuned(_sum_of_squares, NO_YNN, jit=eqx.filter_jit)
    x = jnp.arange(12.0).reshape(3, 4)
    out = jax.jit(lambda y: tuned(y) + 1)(x)
    np.testing.assert_allclose(out, np.sum(np.asarray(x) ** 2, 0) + 1)
    grad = jax.grad(lambda y: tuned(y).sum())(x)
    np.testing.assert_allclose(grad, 2 * np.asarray(x))


@pytest.mark.parametrize("method", ["irls", "barsky", "sbl"])
def test_robust_solvers_match_inside_and_outside_a_trace(method):
    """The tuned top-level program and the plain one traced inside `jit` agree (the options
    change how XLA loops, not what the solver computes)."""
    lights = jaxps.synthetic.scanner_lights(20.0)
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(48, 40), lights)
    top = jaxps.photometric_stereo(scene.images, lights, mask=scene.mask, method=method)
    traced = jax.jit(lambda im: jaxps.photometric_stereo(im, lights, mask=scene.mask,
                                                         method=method))(scene.images)
    np.testing.assert_array_equal(np.asarray(top.status), np.asarray(traced.status))
    ok = np.asarray(top.status) == 0
    cos = np.clip(np.sum(np.asarray(top.normals) * np.asarray(traced.normals), -1), -1, 1)
    assert np.degrees(np.arccos(cos[ok])).max() < 0.05
    truth = np.sum(np.asarray(top.normals) * np.asarray(scene.normals), -1)[ok]
    assert np.degrees(np.arccos(np.clip(truth, -1, 1))).max() < 1.0
