"""Semi-calibrated PS: recovers per-frame intensities and normals on synthetic scenes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxps
from helpers import face_scene

E_TRUE = np.array([1.0, 0.82, 1.12, 1.06, 0.93], np.float32)


def _scaled(h=48, noise=0.0):
    scene = face_scene(h, noise=noise)
    return scene, np.asarray(scene.images) * E_TRUE[:, None, None]


def test_recovers_intensities_and_normals():
    scene, images = _scaled()
    res = jaxps.photometric_stereo(images, scene.lights, mask=scene.mask,
                                   method="semi_calibrated")
    expected = E_TRUE / np.exp(np.mean(np.log(E_TRUE)))  # geometric mean 1
    assert bool(res.info["converged"])
    np.testing.assert_allclose(res.info["intensities"], expected, rtol=1e-4)
    stats = jaxps.evaluate.angular_stats(res.normals, scene.normals, mask=scene.mask)
    assert stats["median_deg"] < 0.01
    plain = jaxps.photometric_stereo(images, scene.lights, mask=scene.mask)
    assert jaxps.evaluate.angular_stats(plain.normals, scene.normals,
                                        mask=scene.mask)["median_deg"] > 5
    assert res.normals.dtype == images.dtype
    assert np.all(np.isfinite(res.normals))


def test_intensity_estimates_mean_and_frontal():
    scene, images = _scaled()
    mean = np.asarray(images)[:, np.asarray(scene.mask)].mean(axis=1)
    got = jaxps.intensity_estimate(images, scene.lights, mask=scene.mask, method="mean")
    np.testing.assert_allclose(got, mean / np.exp(np.mean(np.log(mean))), rtol=1e-5)
    frontal = jaxps.intensity_estimate(images, scene.lights, mask=scene.mask, method="frontal")
    lz = np.asarray(scene.lights)[:, 2]
    ref = mean / lz
    np.testing.assert_allclose(frontal, ref / np.exp(np.mean(np.log(ref))), rtol=1e-5)
    np.testing.assert_array_equal(
        jaxps.intensity_estimate(images, scene.lights, method="none"), np.ones(5))


def test_intensity_estimates_skip_non_finite_pixels_and_reject_bad_lights():
    scene, images = _scaled()
    mask = np.asarray(scene.mask)
    bad = images.copy()
    bad[1, 20, 20] = np.nan  # inside the mask, one frame
    bad[3, 21, 22] = np.inf
    assert mask[20, 20] and mask[21, 22]
    keep = mask.copy()
    keep[20, 20] = keep[21, 22] = False  # the pixels finite in every frame
    for method in ("mean", "frontal"):
        np.testing.assert_allclose(
            jaxps.intensity_estimate(bad, scene.lights, mask=mask, method=method),
            jaxps.intensity_estimate(images, scene.lights, mask=keep, method=method), rtol=1e-6)
    flipped = np.asarray(scene.lights).copy()
    flipped[1, 2] = -0.3  # a light toward the back: l_z < 0
    with pytest.raises(ValueError, match=r"l_z, which must be > 0.*light\(s\) \[1\]"):
        jaxps.intensity_estimate(images, flipped, mask=mask, method="frontal")
    zero = np.asarray(scene.lights).copy()
    zero[4] = 0
    with pytest.raises(ValueError, match=r"lights \[4\] are zero vectors"):
        jaxps.intensity_estimate(images, zero, mask=mask, method="frontal")
    for method in ("mean", "frontal", "semi_calibrated"):
        with pytest.raises(ValueError, match="mask is empty"):
            jaxps.intensity_estimate(images, scene.lights, mask=np.zeros_like(mask),
                                     method=method)


def test_frontal_over_a_reference_target_of_known_normal():
    """A flat matte target turned 20 degrees, under flashes of known strength: "frontal" over
    it with its normal gives the strengths exactly; taken as facing the camera, it does not."""
    lights = np.asarray(jaxps.synthetic.scanner_lights(20.0), np.float64)
    d = np.array([0.0, np.sin(np.radians(20.0)), np.cos(np.radians(20.0))])
    shade = 0.5 * E_TRUE * (lights @ d)
    images = np.broadcast_to(shade[:, None, None], (5, 6, 7)).astype(np.float32)
    expected = E_TRUE / np.exp(np.mean(np.log(E_TRUE)))
    got = jaxps.intensity_estimate(images, lights, method="frontal", normal=d)
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    np.testing.assert_allclose(  # the default normal is the view axis
        jaxps.intensity_estimate(images, lights, method="frontal", normal=[0, 0, 2]),
        jaxps.intensity_estimate(images, lights, method="frontal"), rtol=1e-6)
    assumed = np.asarray(jaxps.intensity_estimate(images, lights, method="frontal"))
    assert np.max(np.abs(assumed / expected - 1)) > 0.05
    with pytest.raises(ValueError, match="normal is the mean normal of the 'frontal'"):
        jaxps.intensity_estimate(images, lights, method="mean", normal=d)
    for bad in ([0, 0], [0, 0, 0], [np.nan, 0, 1]):
        with pytest.raises(ValueError, match=r"normal must be a finite, non-zero \(3,\)"):
            jaxps.intensity_estimate(images, lights, method="frontal", normal=bad)
    with pytest.raises(ValueError, match=r"faces away from light\(s\) \[(\d, )*\d\]"):
        jaxps.intensity_estimate(images, lights, method="frontal", normal=[1, 0, 0])


def test_known_intensities_match_scaled_lights():
    scene, images = _scaled()
    res = jaxps.photometric_stereo(images, scene.lights, mask=scene.mask,
                                   method="semi_calibrated", intensities=E_TRUE)
    stats = jaxps.evaluate.angular_stats(res.normals, scene.normals, mask=scene.mask)
    assert stats["median_deg"] < 1e-3


def test_step_limit_keeps_the_best_usable_answer():
    scene, images = _scaled()
    res = jaxps.photometric_stereo(images, scene.lights, mask=scene.mask,
                                   method="semi_calibrated", max_steps=4)
    assert not bool(res.info["converged"]) and not bool(res.info["fallback"])
    assert int(res.info["steps"]) == 4
    start, used = np.asarray(res.info["objective"])
    assert used < 0.9 * start  # the steps lowered the objective: their intensities are kept
    status = np.asarray(res.status)[np.asarray(scene.mask)]
    assert np.all(status == jaxps.Status.OK)  # the capture is not discarded
    front = jaxps.photometric_stereo(images, scene.lights, mask=scene.mask, method="l2")
    one = jaxps.evaluate.angular_stats(res.normals, scene.normals, mask=scene.mask)
    plain = jaxps.evaluate.angular_stats(front.normals, scene.normals, mask=scene.mask)
    assert one["median_deg"] < plain["median_deg"]


def _many_lights():
    """25 lights on a 20-degree grid of azimuth and elevation, all within 50 deg of the view
    axis, like Yale B's well-posed set."""
    az, el = np.meshgrid([-40.0, -20.0, 0.0, 20.0, 40.0], [-30.0, -15.0, 0.0, 15.0, 30.0])
    return jaxps.lights_from_angles(az.ravel().astype(np.float32), el.ravel().astype(np.float32))


def test_many_light_fit_converges_with_noise():
    """Well posed (25 lights), noisy float32 images: the fit stops by its rule, well inside
    the step limit, at the true intensities (the old 1e-6 rule ran to its limit on a real
    29-light face)."""
    lights = _many_lights()
    k = len(lights)
    scene = face_scene(64, lights=lights)
    e_true = np.exp(np.random.default_rng(0).normal(0, 0.1, k)).astype(np.float32)
    images = np.asarray(scene.images)
    noisy = images * e_true[:, None, None] + np.random.default_rng(1).normal(
        0, 0.005, images.shape).astype(np.float32)
    noisy = np.clip(noisy, 0, 1)
    res = jaxps.photometric_stereo(noisy, lights, mask=scene.mask, method="semi_calibrated",
                                   shadow_threshold=0.02)
    assert bool(res.info["converged"]) and int(res.info["steps"]) < 50
    expected = e_true / np.exp(np.mean(np.log(e_true)))
    np.testing.assert_allclose(res.info["intensities"], expected, rtol=0.01)
    stats = jaxps.evaluate.angular_stats(res.normals, scene.normals, mask=scene.mask)
    assert stats["median_deg"] < 1.0


def test_bad_input():
    scene, images = _scaled()
    with pytest.raises(ValueError, match="K >= 4"):
        jaxps.photometric_stereo(images[[0, 1, 3]], np.asarray(scene.lights)[[0, 1, 3]],
                                 method="semi_calibrated")
    with pytest.raises(ValueError, match="max_steps"):
        jaxps.photometric_stereo(images, scene.lights, method="semi_calibrated", max_steps=0)
    with pytest.raises(ValueError, match="intensities"):
        jaxps.photometric_stereo(images, scene.lights, method="semi_calibrated",
                                 intensities=np.ones(4))
    with pytest.raises(ValueError, match="method"):
        jaxps.intensity_estimate(images, scene.lights, method="nope")


def test_flash_visibility_is_zero_where_a_change_of_intensities_keeps_the_data_lambertian():
    flash_visibility = jaxps.flash_visibility

    def lights(az, el):
        return np.asarray(jaxps.lights_from_angles(np.array(az, float), np.array(el, float)),
                          np.float64)

    cross = lights([0, 25, -25, 0, 0], [0, 0, 0, 20, -20])
    four = lights([0, -25, 0, 0], [0, 0, 20, -20])  # the cross less one light
    assert flash_visibility(cross) == pytest.approx(0.2648, abs=1e-4)  # docs/captures.md
    assert flash_visibility(four) < 1e-6
    assert flash_visibility(3.0 * cross) == pytest.approx(flash_visibility(cross))  # unit lights
    zero = cross.copy()
    zero[1] = 0  # numpy's LinAlgError from the SVD of NaNs before
    with pytest.raises(ValueError, match=r"finite, non-zero directions; rows \[1\]"):
        flash_visibility(zero)
    res = jaxps.photometric_stereo(face_scene(24).images, cross, method="semi_calibrated")
    assert float(res.info["visibility"]) == pytest.approx(flash_visibility(cross), abs=1e-6)

    # Scaling the four frames along the invisible direction leaves exact Lambertian data
    # exactly Lambertian (zero L2 residual, other normals); along the most visible one it does not.
    null = np.linalg.svd(four, full_matrices=True)[0][:, 3:].T
    jac = (null[:, :, None] * four[None]).transpose(0, 2, 1).reshape(-1, 4)
    vt = np.linalg.svd(jac)[2]
    invisible = vt[2] - vt[2].mean()  # the null space also holds the common scale
    rng = np.random.default_rng(0)
    n = rng.normal(size=(16, 16, 3)) * [0.2, 0.2, 0] + [0, 0, 1]
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    images = 0.5 * np.einsum("kc,hwc->khw", four, n).astype(np.float32)  # lit, unsaturated
    residual = {}
    for name, d in (("invisible", invisible), ("visible", vt[0])):
        scaled = images * (1 + 0.2 * d / np.abs(d).max())[:, None, None].astype(np.float32)
        out = jaxps.photometric_stereo(scaled, four)
        assert np.all(np.asarray(out.status) == 0)
        residual[name] = float(np.median(out.residual))
    assert residual["invisible"] < 1e-5 and residual["visible"] > 1e-3, residual


def test_flash_visibility_has_a_gradient_for_designing_a_light_layout():
    # A full SVD's null-space basis has no derivative in JAX (NotImplementedError before); the
    # projector onto that space gives the same value and one. Generic lights, so that the
    # smallest singular value is simple and the derivative exists.
    rng = np.random.default_rng(3)
    for k in (4, 5, 8):
        lights = rng.normal(size=(k, 3))
        lights[:, 2] = np.abs(lights[:, 2]) + 1
        grad = np.asarray(jax.grad(jaxps.flash_visibility)(jnp.asarray(lights, jnp.float32)))
        eps, fd = 1e-4, np.zeros_like(lights)
        for i in range(k):
            for j in range(3):
                step = np.zeros_like(lights)
                step[i, j] = eps
                fd[i, j] = (jaxps.flash_visibility(lights + step)
                            - jaxps.flash_visibility(lights - step)) / (2 * eps)
        np.testing.assert_allclose(grad, fd, atol=2e-5 * np.abs(fd).max(), err_msg=f"K={k}")
        assert float(jax.jit(jaxps.flash_visibility)(jnp.asarray(lights, jnp.float32))) == \
            pytest.approx(jaxps.flash_visibility(lights), rel=1e-5)
