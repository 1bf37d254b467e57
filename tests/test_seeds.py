"""Every public function that takes a PRNG `key` also takes an int seed, and the seed means
`jax.random.key(seed)`: the same numbers as passing that key."""

import importlib
import inspect

import jax
import numpy as np
import pytest

import jaxps
from jaxps.core._random import as_key
from jaxps.stability import perturb_lights, render_corrupted, ring_lights, sweep
from jaxps.synthetic import face_like, render_scene, sphere

# Every public callable with a `key` parameter; the test below fails when one is added without
# being covered here.
COVERED = {"fit_brdf", "brdf_photometric_stereo", "render_scene", "render_corrupted",
           "perturb_lights", "sweep"}


def _public_callables():
    mods = [jaxps] + [importlib.import_module(f"jaxps.{m}") for m in
                      ("acquisition", "evaluate", "synthetic", "stability", "report", "core",
                       "lights", "ps", "integration", "shading", "reflectance")]
    for mod in mods:
        for name in mod.__all__:
            obj = getattr(mod, name)
            if callable(obj) and not inspect.isclass(obj):
                yield name, obj


def test_every_public_key_function_is_covered():
    with_key = {n for n, f in _public_callables() if "key" in inspect.signature(f).parameters}
    assert with_key == COVERED


def test_as_key():
    want = jax.random.key_data(jax.random.key(7))
    for seed in (7, np.int64(7)):
        np.testing.assert_array_equal(jax.random.key_data(as_key(seed)), want)
    assert as_key(None) is None
    np.testing.assert_array_equal(jax.random.key_data(as_key(None, default=7)), want)
    k = jax.random.key(3)
    assert as_key(k) is k
    for bad in (True, 1.5, "0"):
        with pytest.raises(TypeError, match="key"):
            as_key(bad)


def test_render_scene_and_render_corrupted_seed():
    surf = sphere(16)
    lights = ring_lights(4, 30.0)
    a = render_scene(surf, lights, noise=0.05, key=3).images
    b = render_scene(surf, lights, noise=0.05, key=jax.random.key(3)).images
    c = render_scene(surf, lights, noise=0.05, key=4).images
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.array_equal(np.asarray(a), np.asarray(c))
    kw = {"shadows": False, "noise": 0.05}
    a = render_corrupted(surf, lights, key=3, **kw).images
    b = render_corrupted(surf, lights, key=jax.random.key(3), **kw).images
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_perturb_lights_seed():
    lights = ring_lights(5, 30.0)
    a = perturb_lights(lights, 5.0, key=2)
    np.testing.assert_array_equal(a, perturb_lights(lights, 5.0, key=jax.random.key(2)))
    assert not np.array_equal(a, perturb_lights(lights, 5.0, key=1))


def test_sweep_seed():
    kw = {"values": (2.0,), "methods": ("l2",), "h": 24}
    a = sweep("light_error_deg", key=5, **kw)
    b = sweep("light_error_deg", key=jax.random.key(5), **kw)
    assert a == b
    assert a != sweep("light_error_deg", key=6, **kw)


def test_brdf_photometric_stereo_seed():
    surf = face_like(20)
    lights = ring_lights(6, 35.0, centre=True)
    images = render_scene(surf, lights).images
    kw = {"mask": np.asarray(surf.mask), "method": "mlp", "iterations": 1, "max_steps": 3,
          "n_samples": 500, "hidden": (4,)}
    a = jaxps.brdf_photometric_stereo(images, lights, key=1, **kw)
    b = jaxps.brdf_photometric_stereo(images, lights, key=jax.random.key(1), **kw)
    np.testing.assert_array_equal(np.asarray(a.normals), np.asarray(b.normals))
    pa, pb = (jax.flatten_util.ravel_pytree(r.info["models"][0].params)[0] for r in (a, b))
    np.testing.assert_array_equal(np.asarray(pa), np.asarray(pb))
