import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    assert_results_equal,
    assert_reuses_dropped_results,
    face_scene,
    sphere_scene,
)

import jaxps
from jaxps import Status


def numpy_reference(images, lights, used=None):
    """Per-pixel numpy lstsq over the used samples: returns (normals, albedo) as float64."""
    k, h, w = images.shape
    flat = np.asarray(images, np.float64).reshape(k, -1)
    used = np.ones_like(flat, bool) if used is None else np.asarray(used).reshape(k, -1)
    lights = np.asarray(lights, np.float64)
    b = np.zeros((flat.shape[1], 3))
    for j in range(flat.shape[1]):
        u = used[:, j]
        if u.sum() >= 3:
            b[j] = np.linalg.lstsq(lights[u], flat[u, j], rcond=None)[0]
    rho = np.linalg.norm(b, axis=1)
    n = b / np.where(rho > 0, rho, 1)[:, None]
    return n.reshape(h, w, 3), rho.reshape(h, w)


@pytest.mark.parametrize("scene", [sphere_scene, face_scene], ids=["sphere", "face"])
def test_noise_free_recovery(scene):
    s = scene(96)
    res = jaxps.photometric_stereo(s.images, s.lights, mask=s.mask)
    ok = np.asarray(res.status == Status.OK)
    assert ok[np.asarray(s.mask)].mean() > 0.99
    err = np.asarray(jaxps.angular_error(res.normals, s.normals))[ok]
    assert np.median(err) < 0.05
    assert np.abs(np.asarray(res.albedo - s.albedo))[ok].max() < 1e-3
    assert res.normals.dtype == jnp.float32 and res.albedo.dtype == jnp.float32


def test_vmap_equals_numpy_lstsq_per_pixel():
    # Random intensities (not Lambertian) so the least-squares residual is non-zero.
    rng = np.random.default_rng(0)
    lights = jaxps.lights_from_angles([0, 30, -30, 10, -15, 0], [0, 5, -5, 30, -25, 45])
    images = rng.uniform(0.05, 0.9, (6, 8, 9)).astype(np.float32)
    images[:, :, :4] += 0.5 * np.einsum("kc,c->k", lights, [0, 0, 1])[:, None, None]
    images = np.minimum(images, 0.99).astype(np.float32)
    res = jaxps.photometric_stereo(images, lights, dark_threshold=0.0)
    n_ref, rho_ref = numpy_reference(images, lights)
    back = n_ref[..., 2] < 0
    ok = np.asarray(res.status) == Status.OK
    np.testing.assert_array_equal(ok, ~back)
    np.testing.assert_allclose(np.asarray(res.normals)[ok], n_ref[ok], atol=2e-5)
    np.testing.assert_allclose(np.asarray(res.albedo)[ok], rho_ref[ok], rtol=2e-5)
    # The residual is the RMS misfit of the Lambertian model over the used samples.
    pred = np.einsum("kc,hwc->khw", lights, n_ref) * rho_ref
    rms = np.sqrt(np.mean((images - pred) ** 2, axis=0))
    np.testing.assert_allclose(np.asarray(res.residual)[ok], rms[ok], atol=2e-5)


def test_dropped_samples_match_lstsq_on_remaining_rows():
    rng = np.random.default_rng(1)
    s = face_scene(48, lights=jaxps.lights_from_angles([0, 25, -25, 0, 0, 15, -15],
                                                       [0, 0, 0, 20, -20, 15, -15]))
    images = np.array(s.images)
    images[2, :20] = 1.0  # saturated block
    images[5, 10:30] *= 0.0  # shadowed block
    images[4][rng.uniform(size=images[4].shape) < 0.1] = np.nan
    res = jaxps.photometric_stereo(images, s.lights, mask=s.mask, shadow_threshold=1e-3)
    used = np.isfinite(images) & (images < 1.0) & (images >= 1e-3)
    n_ref, rho_ref = numpy_reference(np.nan_to_num(images), s.lights, used)
    ok = np.asarray(res.status) == Status.OK
    assert ok.sum() > 0.95 * np.asarray(s.mask).sum()
    np.testing.assert_array_equal(np.asarray(res.n_used)[ok], used.sum(0)[ok])
    np.testing.assert_allclose(np.asarray(res.normals)[ok], n_ref[ok], atol=2e-5)
    np.testing.assert_allclose(np.asarray(res.albedo)[ok], rho_ref[ok], rtol=1e-4, atol=1e-6)


def test_colour_equals_grey_when_channels_equal():
    s = face_scene(48, noise=0.01)
    grey = jaxps.photometric_stereo(s.images, s.lights, mask=s.mask)
    colour = jaxps.photometric_stereo(jnp.stack([s.images] * 3, axis=-1), s.lights, mask=s.mask)
    assert colour.albedo.shape == (*s.mask.shape, 3)
    np.testing.assert_allclose(colour.normals, grey.normals, atol=1e-6)
    for c in range(3):
        np.testing.assert_allclose(colour.albedo[..., c], grey.albedo, rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(colour.status, grey.status)


@pytest.mark.parametrize("traced", [False, True], ids=["host_packed", "traced"])
def test_colour_with_dropped_samples_equals_numpy_per_channel(traced):
    # The weighted colour solve (packed on the host, unpacked in a trace): the normal from the
    # channel mean over the used samples, each channel's albedo the least-squares scale of
    # its samples against l.n over those samples.
    s = face_scene(40)
    rng = np.random.default_rng(4)
    tint = rng.uniform(0.3, 1.0, (1, *s.mask.shape, 3)).astype(np.float32)
    images = np.asarray(s.images)[..., None] * tint
    images *= rng.uniform(0.9, 1.1, images.shape).astype(np.float32)  # channels differ
    images[1, :12] = 1.0  # saturated: every channel of these samples is dropped
    options = {"mask": np.asarray(s.mask), "shadow_threshold": 0.02, "saturation": 1.0}
    if traced:
        res = jax.jit(lambda x: jaxps.photometric_stereo(x, s.lights, **options))(images)
    else:
        res = jaxps.photometric_stereo(images, s.lights, **options)
    grey = images.mean(-1)
    used = (images < 1.0).all(-1) & (grey >= 0.02)
    n_ref, _ = numpy_reference(grey, s.lights, used)
    shading = np.einsum("kp,hwp->khw", np.asarray(s.lights, np.float64), n_ref) * used
    norm = np.maximum((shading**2).sum(0), 1e-12)[..., None]  # 0 where no sample is used
    rho_ref = np.einsum("khw,khwc->hwc", shading, images.astype(np.float64)) / norm
    ok = np.asarray(res.status) == Status.OK
    assert ok.sum() > 0.9 * np.asarray(s.mask).sum()
    np.testing.assert_array_equal(np.asarray(res.n_used)[ok], used.sum(0)[ok])
    np.testing.assert_allclose(np.asarray(res.normals)[ok], n_ref[ok], atol=2e-5)
    np.testing.assert_allclose(np.asarray(res.albedo)[ok], rho_ref[ok], rtol=1e-4, atol=1e-6)


def test_colour_albedo_scales_per_channel():
    s = face_scene(48)
    tint = jnp.array([1.0, 0.6, 0.3], jnp.float32)
    res = jaxps.photometric_stereo(s.images[..., None] * tint[None, None, None], s.lights,
                                   mask=s.mask)
    ok = np.asarray(res.status == 0)
    for c in range(3):
        np.testing.assert_allclose(np.asarray(res.albedo[..., c])[ok],
                                   float(tint[c]) * np.asarray(s.albedo)[ok], rtol=1e-4)


def test_status_codes_and_finite_outputs():
    s = face_scene(32)
    images = np.array(s.images)
    mask = np.ones(s.mask.shape, bool)
    mask[0, 0] = False
    pix = {"dark": (16, 5), "sat": (16, 10), "few": (16, 12), "nan": (16, 14), "inf": (16, 15)}
    images[:, 16, 5] = 0.0
    images[:3, 16, 10] = 1.0  # 5 lights, 3 saturated -> 2 usable
    images[:3, 16, 12] = 0.0  # 3 shadowed
    images[:3, 16, 14] = np.nan
    images[:, 16, 15] = np.inf
    res = jaxps.photometric_stereo(images, s.lights, mask=mask, shadow_threshold=0.01)
    st = np.asarray(res.status)
    assert st[0, 0] == Status.MASKED
    assert st[pix["dark"]] == Status.DARK
    assert st[pix["sat"]] == Status.SATURATED
    assert st[pix["few"]] == Status.TOO_FEW_LIGHTS
    assert st[pix["nan"]] == Status.INVALID
    assert st[pix["inf"]] == Status.INVALID
    for r, c in [(0, 0), *pix.values()]:
        np.testing.assert_array_equal(res.normals[r, c], [0, 0, 1])
        assert res.albedo[r, c] == 0
    for field in (res.normals, res.albedo, res.residual):
        assert np.all(np.isfinite(np.asarray(field)))


def test_degenerate_subset_of_lights():
    # Two of the three non-coplanar lights land in a shadow: the rest are coplanar.
    lights = jaxps.lights_from_angles([0, 30, -30, 0], [0, 0, 0, 30])
    s = face_scene(24, lights=lights)
    images = np.array(s.images)
    images[3] = 0.0  # the only light out of the y=0 plane is shadowed everywhere
    res = jaxps.photometric_stereo(images, lights, mask=s.mask, shadow_threshold=1e-4)
    st = np.asarray(res.status)[np.asarray(s.mask)]
    assert np.all(st == Status.DEGENERATE)
    assert np.all(np.isfinite(np.asarray(res.normals)))


def test_backfacing_gets_status():
    # Lights all on one side; b = rho n with n_z < 0 still gives positive intensities.
    lights = jaxps.lights_from_angles([30, 40, 50], [0, 10, -10])
    b = np.array([-1.0, 0.0, -0.2])
    images = (lights @ b).astype(np.float32)[:, None, None] * np.ones((1, 1, 2), np.float32)
    assert np.all(images > 0)
    res = jaxps.photometric_stereo(images, lights)
    np.testing.assert_array_equal(res.status, Status.BACKFACING)
    np.testing.assert_array_equal(res.normals[0, 0], [0, 0, 1])


def test_float64_in_float64_out():
    with jax.enable_x64(True):
        s = face_scene(24)
        images = np.asarray(s.images, np.float64)
        res = jaxps.photometric_stereo(images, np.asarray(s.lights, np.float64), mask=s.mask)
        assert res.normals.dtype == jnp.float64 and res.albedo.dtype == jnp.float64
        assert res.residual.dtype == jnp.float64


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16])
def test_half_precision_frames_are_solved_in_float32(dtype):
    # bfloat16 failed in the packed complex planes (a TypeError), check_frames in numpy's
    # einsum, and fit_brdf in optimistix; float16 worked for photometric stereo before.
    s = face_scene(24)
    half = jnp.asarray(s.images, dtype)
    res = jaxps.photometric_stereo(half, s.lights, mask=s.mask)
    want = jaxps.photometric_stereo(half.astype(jnp.float32), s.lights, mask=s.mask)
    assert res.normals.dtype == res.albedo.dtype == res.residual.dtype == dtype
    np.testing.assert_array_equal(res.status, want.status)
    np.testing.assert_array_equal(res.normals, want.normals.astype(dtype))
    report = jaxps.check_frames(half, mask=s.mask)
    assert report.keep.all(), report.summary()
    model = jaxps.fit_brdf(half, res.normals, res.albedo, s.lights, mask=s.mask, method="wrap")
    assert model.fit.rmse < 0.01  # Lambertian frames: the wrap model fits them


def test_per_pixel_lights_match_shared():
    s = face_scene(32)
    k, h, w = s.images.shape
    field = jnp.broadcast_to(s.lights[:, None, None, :], (k, h, w, 3))
    shared = jaxps.photometric_stereo(s.images, s.lights, mask=s.mask)
    per_pixel = jaxps.photometric_stereo(s.images, field, mask=s.mask)
    np.testing.assert_allclose(per_pixel.normals, shared.normals, atol=1e-5)
    np.testing.assert_array_equal(per_pixel.status, shared.status)


def test_switch_index_names_the_solve_the_host_would_choose():
    # `ps_l2(branch="switch")` picks its solve in the program from the same flags that
    # `branch_of` reads on the host: bit 0, some sample dropped; bit 1, some sample not finite.
    from jaxps.ps import _l2

    for flags in range(4):
        index = int(jax.jit(_l2.solve_index)(jnp.int32(flags)))
        assert _l2.SOLVES[index] == _l2.branch_of(flags)


@pytest.mark.parametrize("case", ["clean", "dropped", "dropped_finite", "nan_outside_mask",
                                  "colour_dropped", "colour", "sample_mask", "uint8_mask",
                                  "per_pixel_lights", "per_pixel_lights_dropped",
                                  "per_pixel_lights_colour_dropped"])
def test_host_chosen_branch_equals_the_traced_cond(case, monkeypatch):
    # A top-level call on the CPU runs L2's flag pass and solves in one program of its own
    # (`branch="switch"`, grey stacks), or picks the solve on the host (colour stacks,
    # per-pixel lights); a call inside a jit takes the `cond` in the caller's program. Both
    # must give the same result.
    import jaxps.ps._photometric_stereo as wrapper
    from jaxps.ps import _l2

    s = face_scene(40)
    images, options = np.array(s.images), {"mask": np.asarray(s.mask)}
    if case in ("dropped", "dropped_finite", "nan_outside_mask", "colour_dropped"):
        images[1, :12] = 1.0  # saturated
        options["shadow_threshold"] = 0.02
    if case == "dropped":
        images[3][np.random.default_rng(2).uniform(size=images[3].shape) < 0.05] = np.nan
    if case == "nan_outside_mask":  # the solve without zeroing: status codes hide the NaNs
        assert not np.asarray(s.mask).all()
        images[3][~np.asarray(s.mask)] = np.nan
    if case == "colour_dropped":
        images = images[..., None] * np.array([1.0, 0.7, 0.4], np.float32)
        images[2, 20:, :5, 1] = 1.0  # one channel saturated
    elif case == "colour":
        images = images[..., None] * np.array([1.0, 0.7, 0.4], np.float32)
    elif case == "sample_mask":
        options["sample_mask"] = np.ones(images.shape, bool)
        options["sample_mask"][2, 10:20] = False
    elif case == "uint8_mask":
        options["mask"] = np.asarray(s.mask).astype(np.uint8) * 255
    lights = s.lights
    if case.startswith("per_pixel_lights"):  # the weighted solve, packed on the host
        k, h, w = images.shape
        wobble = np.random.default_rng(3).normal(0, 0.03, (k, h, w, 3))
        lights = (2 * (np.asarray(s.lights)[:, None, None] + wobble)).astype(np.float32)
        if "colour" in case:
            images = images[..., None] * np.array([1.0, 0.7, 0.4], np.float32)
        if case.endswith("dropped"):
            images[1, :12] = 1.0
            options["shadow_threshold"] = 0.02
    branches = []
    choose = _l2.l2_branch
    monkeypatch.setattr(wrapper, "l2_branch", lambda *a: branches.append(choose(*a)) or branches[-1])
    host = jaxps.photometric_stereo(images, lights, **options)
    traced = jax.jit(lambda x: jaxps.photometric_stereo(x, lights, **options))(images)
    np.testing.assert_array_equal(host.status, traced.status)
    np.testing.assert_array_equal(host.n_used, traced.n_used)
    for a, b in zip(host[:5], traced[:5]):
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    dropping = case in ("dropped", "dropped_finite", "nan_outside_mask", "colour_dropped",
                        "sample_mask", "per_pixel_lights_dropped",
                        "per_pixel_lights_colour_dropped")
    assert (np.asarray(host.n_used)[np.asarray(s.mask)] < len(images)).any() == dropping
    # the flags read on the host: for colour stacks and per-pixel lights only
    expected = {"colour": "all_used", "colour_dropped": "weighted_finite",
                "per_pixel_lights": "all_used", "per_pixel_lights_dropped": "weighted_finite",
                "per_pixel_lights_colour_dropped": "weighted_finite"}
    assert branches == ([expected[case]] if case in expected else [])


def test_works_under_jit_and_vmap_over_captures():
    s = face_scene(24)
    batch = jnp.stack([s.images, 0.5 * s.images])

    @jax.jit
    def solve(images, lights):
        return jaxps.photometric_stereo(images, lights).normals

    out = jax.vmap(solve, in_axes=(0, None))(batch, s.lights)
    single = jaxps.photometric_stereo(s.images, s.lights).normals
    np.testing.assert_allclose(out[0], single, atol=1e-6)
    np.testing.assert_allclose(out[1], single, atol=1e-6)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(images=np.zeros((5, 4, 4), np.uint8)), "floating point"),
        (dict(images=np.zeros((5, 4), np.float32)), r"\(K, H, W\)"),
        (dict(lights=np.eye(3, dtype=np.float32)), "K=5 frames but lights have 3"),
        # frames on the last axis, as some loaders stack them: the error says which axis
        (dict(images=np.zeros((4, 6, 5), np.float32)),
         r"K=4 frames but lights have 5 rows; images look like \(H, W, K\)"),
        (dict(images=np.zeros((2, 4, 4), np.float32),
              lights=np.eye(3, dtype=np.float32)[:2]), "at least 3"),
        (dict(lights=np.zeros((5, 4, 4, 2), np.float32)), r"\(K, 3\) or \(K, H, W, 3\)"),
        (dict(lights=np.ones((5, 2), np.float32)), r"\(K, 3\) or \(K, H, W, 3\), got \(5, 2\)"),
        (dict(images=np.zeros((5, 0, 4), np.float32)), "at least one pixel"),
        (dict(mask=np.ones((3, 4), bool)), "mask must have shape"),
        (dict(sample_mask=np.ones((5, 4, 3), bool)), "sample_mask must have shape"),
        (dict(method="nope"), "method must be one of"),
        (dict(saturation=float("nan")), "saturation must be finite"),
        (dict(shadow_threshold=float("nan")), "shadow_threshold must be a number or None"),
        # an option the method does not take (a typo) names the method and what it takes,
        # not the internal solver (Python's TypeError before)
        (dict(los="l1", method="irls"), r"method='irls' got unknown option\(s\) 'los'; it "
                                        r"takes loss, "),
        (dict(max_steps=5), r"method='l2' got unknown option\(s\) 'max_steps'; it takes no"),
        (dict(branch="switch"), r"method='l2' got unknown option"),  # the wrapper's own
        # a float mask with values other than 0 and 1 counted every non-zero pixel as inside
        (dict(mask=np.full((4, 4), 0.2, np.float32)), r"mask must be bool .*e\.g\. 0\.2"),
        (dict(sample_mask=np.full((5, 4, 4), 0.7)), r"sample_mask must be bool"),
    ],
)
def test_bad_input(kwargs, match):
    args = dict(images=np.full((5, 4, 4), 0.5, np.float32), lights=jaxps.synthetic.scanner_lights())
    args.update(kwargs)
    images, lights = args.pop("images"), args.pop("lights")
    with pytest.raises(ValueError, match=match):
        jaxps.photometric_stereo(images, lights, **args)


def test_images_on_a_0_to_255_scale_are_rejected_not_failed_silently():
    """Float images on an 8- or 16-bit scale used to come back with every pixel SATURATED
    and no error; the check reads a few pixels of each frame, wherever they are held."""
    s = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(40, 36),
                                     jaxps.synthetic.scanner_lights())
    images = np.asarray(s.images)
    for scaled in (images * 255, jax.device_put(images * 65535),
                   np.stack([images * 255] * 3, -1)):  # grey, on the device, colour
        with pytest.raises(ValueError, match=r"images must be in \[0, 1\]: .*Divide 8-bit"):
            jaxps.photometric_stereo(scaled, s.lights, mask=s.mask)
    # On the images' own scale, the same solve
    own = jaxps.photometric_stereo(images * 255, s.lights, mask=s.mask, saturation=255)
    ref = jaxps.photometric_stereo(images, s.lights, mask=s.mask)
    np.testing.assert_array_equal(own.status, ref.status)
    np.testing.assert_allclose(own.normals, ref.normals, atol=1e-6)
    # [0, 1] data after a gain correction (values up to 1.3, some saturated) is solved
    bright = jaxps.photometric_stereo(images * 1.3, s.lights, mask=s.mask)
    counts = jaxps.status_counts(bright.status)
    assert counts["OK"] > 0.5 * int(np.sum(s.mask)), counts


def test_float_masks_of_0_and_1_are_taken_as_bool_masks():
    s = face_scene(24)
    ref = jaxps.photometric_stereo(s.images, s.lights, mask=s.mask)
    as_float = jaxps.photometric_stereo(s.images, s.lights, mask=np.asarray(s.mask, np.float32))
    assert_results_equal(as_float, ref)


def test_coplanar_lights_rejected_with_condition_number():
    lights = jaxps.lights_from_angles([0, 20, -20, 40], [0, 0, 0, 0])
    with pytest.raises(ValueError, match="condition number"):
        jaxps.photometric_stereo(np.ones((4, 3, 3), np.float32), lights)


def test_light_checks_are_kept_by_value_and_a_bad_set_still_raises():
    # The checked lights and host constants are kept per light set (by their bytes): a set
    # changed in place after a call is a new set, and a bad set raises every time.
    s = face_scene(24)
    lights = np.array(s.lights, np.float64)
    images = np.asarray(s.images)
    first = jaxps.photometric_stereo(images, lights)
    lights[:, 0] *= -1  # mirrored in x, in place
    mirrored = jaxps.photometric_stereo(images, lights)
    fresh = jaxps.photometric_stereo(images, np.array(lights))
    np.testing.assert_array_equal(mirrored.normals, fresh.normals)
    assert not np.array_equal(mirrored.normals, first.normals)
    coplanar = jaxps.lights_from_angles([0, 20, -20, 40], [0, 0, 0, 0])
    for _ in range(2):
        with pytest.raises(ValueError, match="condition number"):
            jaxps.photometric_stereo(np.ones((4, 3, 3), np.float32), coplanar)


def test_host_constants_match_the_traced_ones():
    # Lights known before tracing take numpy's pseudo-inverse and null basis; they must agree
    # with the differentiable jnp path (the null basis up to rotation: compare N^T N).
    from jaxps.ps._l2 import _shared_constants, host_constants

    lights = np.asarray(jaxps.lights_from_angles([0, 25, -25, 0, 0, 40], [0, 0, 0, 20, -20, 30]))
    host = host_constants(lights)
    traced = [np.asarray(a, np.float64) for a in
              jax.jit(_shared_constants)(jnp.asarray(lights, jnp.float32))]
    np.testing.assert_allclose(host[1], traced[1], atol=1e-5)
    np.testing.assert_allclose(host[2].T @ host[2], traced[2].T @ traced[2], atol=1e-5)
    np.testing.assert_allclose(host[2] @ lights, 0, atol=1e-12)
    np.testing.assert_allclose(host[3], traced[3], atol=1e-5)
    assert bool(host[4]) and bool(traced[4])
    assert not bool(host_constants(np.repeat(lights[:1], 4, axis=0))[4])


def test_reflectance_imports_scipy_only_for_the_delaunay_baseline():
    # scipy.spatial and scipy.interpolate took 0.4-0.8 s of every `jaxps relight` at import
    import subprocess
    import sys

    code = ("import sys, jaxps.reflectance, jaxps.cli._relight\n"
            "print(sorted(m for m in sys.modules if m.startswith('scipy')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert "scipy.spatial" not in out.stdout and "scipy.interpolate" not in out.stdout, out.stdout


def test_l2_on_numpy_lights_imports_no_scipy():
    # Lowering a LAPACK call (an SVD of traced lights) imports scipy.linalg: 0.12-0.15 s of
    # every command-line run. The plain L2 solve on numpy lights must not need it.
    import subprocess
    import sys

    code = ("import sys, numpy as np, jaxps\n"
            "l = np.asarray(jaxps.lights_from_angles([0, 25, -25, 0, 0], [0, 0, 0, 20, -20]))\n"
            "n = np.dstack([np.zeros((8, 8)), np.zeros((8, 8)), np.ones((8, 8))])\n"
            "img = np.clip(np.einsum('hwc,kc->khw', n, l), 0, 1).astype(np.float32)\n"
            "r = jaxps.photometric_stereo(img, l)\n"
            "assert np.allclose(np.asarray(r.normals)[..., 2], 1, atol=1e-5)\n"
            "print(sorted(m for m in sys.modules if m.startswith('scipy')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env={**__import__("os").environ, "JAXPS_CACHE_DIR": "off"})
    assert "scipy.linalg" not in out.stdout, out.stdout


@pytest.mark.parametrize("case", ["clean", "dropped"])
def test_eager_solvers_take_the_l2_branch_on_the_host(case, monkeypatch):
    # `semi_calibrated` and `oren_nayar` run outside jit and finish (or start) with an L2
    # solve: `ps_l2_eager` takes its branch on the host, like a top-level L2 call, and must
    # agree with `ps_l2`'s `cond`.
    from jaxps.ps import _l2

    s = face_scene(40)
    images = np.array(s.images)[..., None]
    if case == "dropped":
        images[1, :12] = 1.0  # saturated
        images[3][np.random.default_rng(2).uniform(size=images[3].shape) < 0.05] = np.nan
    lights = jnp.asarray(s.lights) * jnp.array([1.0, 0.8, 1.1, 1.05, 0.9])[:, None]
    thresholds = tuple(jnp.float32(t) for t in (1e-3, 1.0, 0.02))
    mask = jnp.asarray(s.mask)
    flags = []
    needs = _l2.l2_needs_weights
    monkeypatch.setattr(_l2, "l2_needs_weights", lambda *a: flags.append(needs(*a)) or flags[-1])
    host = _l2.ps_l2_eager(images, lights, mask, None, thresholds)
    traced = _l2.ps_l2(images, lights, mask, None, thresholds)
    # one read of the flags on the host: bit 0 weighted, bit 1 a NaN inside the mask
    assert [int(f) for f in flags] == [3 if case == "dropped" else 0]
    np.testing.assert_array_equal(host.status, traced.status)
    np.testing.assert_array_equal(host.n_used, traced.n_used)
    for a, b in zip(host[:5], traced[:5]):
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    # inside a trace the helper is ps_l2 itself (no flag read back)
    jax.jit(lambda x: _l2.ps_l2_eager(x, lights, mask, None, thresholds))(images)
    assert len(flags) == 1


@pytest.mark.parametrize("colour", [False, True])
def test_large_single_calls_write_into_a_result_the_caller_dropped(colour, monkeypatch):
    """A top-level L2 call whose normals exceed `_KEEP_FROM_BYTES` (lowered here to 0) keeps
    its result; a later call of the same shapes writes into one the caller has dropped, never
    into one still held or viewed, and every result equals the call with nothing kept (the
    switch program for grey stacks, the host-chosen solve for colour, dropping samples or
    not). `JAXPS_BATCH_KEEP_BYTES=0` keeps nothing; `release_batch_outputs` lets go."""
    from jaxps.core import _kept
    from jaxps.ps import _photometric_stereo

    monkeypatch.setattr(_photometric_stereo, "_KEEP_FROM_BYTES", 0)
    monkeypatch.delenv("JAXPS_BATCH_KEEP_BYTES", raising=False)
    scene = face_scene(32, noise=0.01)
    images = np.asarray(scene.images, np.float32)
    if colour:
        images = images[..., None] * np.float32([1.0, 0.8, 0.6])
    stacks = [images * s for s in (1.0, 0.8, 0.6, 0.5, 0.4)]
    shadow = float(np.percentile(images[:, np.asarray(scene.mask)], 10))

    def solve(i):  # the last stack drops samples: the weighted solve
        return jaxps.photometric_stereo(stacks[i], scene.lights, mask=scene.mask,
                                        shadow_threshold=shadow if i == 4 else None)

    monkeypatch.setenv("JAXPS_BATCH_KEEP_BYTES", "0")
    expected = [[np.array(a) for a in solve(i)[:5]] for i in range(len(stacks))]
    assert _kept._SINGLE == []
    monkeypatch.delenv("JAXPS_BATCH_KEEP_BYTES")
    assert (expected[4][3] < expected[0][3].max()).any()  # samples dropped

    assert_reuses_dropped_results(solve, expected)  # the fifth, dropping samples
    assert len(_kept._SINGLE) == 2
    jaxps.release_batch_outputs()
    assert _kept._SINGLE == []
    monkeypatch.setenv("JAXPS_BATCH_KEEP_BYTES", "0")
    assert_results_equal(solve(4), expected[4], "stack 4")
    assert _kept._SINGLE == []
