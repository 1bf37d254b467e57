"""The public API's conventions (dm_pix `api_test.py` in spirit)."""

import inspect

import numpy as np
import pytest
from beartype import beartype
from jaxtyping import jaxtyped

import jaxps

PUBLIC_FUNCTIONS = [getattr(jaxps, n) for n in jaxps.__all__
                    if inspect.isfunction(getattr(jaxps, n))]


def test_all_names_exist_and_are_documented():
    assert jaxps.__version__
    for name in jaxps.__all__:
        obj = getattr(jaxps, name)
        if isinstance(obj, tuple):
            continue  # PS_METHODS, INTEGRATION_METHODS
        assert inspect.getdoc(obj), f"jaxps.{name} has no docstring"


def test_design_names_present():
    for name in ("lights_from_angles", "photometric_stereo", "integrate", "angular_error",
                 "render_lambertian", "PS_METHODS", "INTEGRATION_METHODS", "evaluate"):
        assert hasattr(jaxps, name)
    assert "l2" in jaxps.PS_METHODS and "fc" in jaxps.INTEGRATION_METHODS


@pytest.mark.parametrize("fn", PUBLIC_FUNCTIONS, ids=lambda f: f.__name__)
def test_options_are_keyword_only(fn):
    params = list(inspect.signature(fn).parameters.values())
    for p in params:
        if p.default is not inspect.Parameter.empty and p.kind is p.POSITIONAL_OR_KEYWORD:
            # Optional arguments come after `*`, except in helpers whose only inputs are options.
            assert all(q.default is not inspect.Parameter.empty for q in params), (
                f"{fn.__name__}: option {p.name!r} should be keyword-only")


def test_jaxtyping_annotations_hold_on_valid_input():
    s = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(32),
                                     jaxps.synthetic.scanner_lights())
    checked = {f.__name__: jaxtyped(typechecker=beartype)(f) for f in (
        jaxps.photometric_stereo, jaxps.integrate, jaxps.normals_from_height,
        jaxps.angular_error, jaxps.render_lambertian, jaxps.lights_from_angles)}
    res = checked["photometric_stereo"](s.images, s.lights, mask=s.mask)
    z = checked["integrate"](res.normals, mask=s.mask)
    n = checked["normals_from_height"](z)
    checked["angular_error"](n, res.normals, mask=s.mask)
    checked["render_lambertian"](res.normals, res.albedo, s.lights)
    checked["lights_from_angles"](np.array([0.0, 10.0, 20.0]), np.array([0.0, 5.0, -5.0]))
    colour = checked["photometric_stereo"](np.stack([np.asarray(s.images)] * 3, -1), s.lights)
    assert colour.albedo.shape == (32, 26, 3)


def test_status_codes_have_messages():
    for code in jaxps.Status:
        assert code.message
    assert jaxps.Status.OK == 0
    assert jaxps.status_counts(np.array([[0, 0], [1, 3]])) == {"OK": 2, "MASKED": 1, "DARK": 1}


def test_status_counts_takes_a_result_and_rejects_what_is_not_status_codes():
    s = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(16),
                                     jaxps.synthetic.scanner_lights())
    res = jaxps.photometric_stereo(s.images, s.lights, mask=s.mask)
    counts = jaxps.status_counts(res)  # numpy's "inhomogeneous shape" error before
    assert counts == jaxps.status_counts(res.status)
    assert counts["MASKED"] == int(np.sum(~np.asarray(s.mask)))
    with pytest.raises(ValueError, match="integer array of Status codes .* dtype float32"):
        jaxps.status_counts(res.albedo)
    with pytest.raises(ValueError, match=r"codes that are not a Status: \[42\]"):
        jaxps.status_counts(np.array([0, 42]))
