"""Robust per-pixel solvers: accuracy under shadows/highlights, references, edge cases."""

import jax
import numpy as np
import pytest

import jaxps
from jaxps.evaluate import angular_stats
from jaxps.stability import cast_shadow_mask, perturb_lights, render_corrupted, ring_lights

ROBUST = ("barsky", "irls", "sbl")


@pytest.fixture(scope="module")
def scene8():
    # 8 lights at 45 deg: cast shadows (nose, brows) on ~29% of pixels, a specular lobe
    # (k_s = 0.6, exponent 100) and saturation, 0.5% noise.
    surf = jaxps.synthetic.face_like(64)
    return render_corrupted(surf, ring_lights(8, 45.0), specular=0.6, shininess=100.0,
                            noise=0.005, key=jax.random.key(0))


def _mean_err(res, scene):
    return angular_stats(res.normals, scene.normals, mask=scene.mask)["mean_deg"]


def test_robust_beat_l2_on_shadows_and_highlights(scene8):
    assert float(np.asarray(scene8.shadow)[:, np.asarray(scene8.mask)].any(0).mean()) > 0.1
    l2 = _mean_err(jaxps.photometric_stereo(scene8.images, scene8.lights, mask=scene8.mask),
                   scene8)
    assert l2 > 2.0  # the corruption matters for least squares
    for method in ROBUST:
        res = jaxps.photometric_stereo(scene8.images, scene8.lights, mask=scene8.mask,
                                       method=method)
        err = _mean_err(res, scene8)
        assert err < 0.6 * l2, (method, err, l2)
        assert np.all(np.isfinite(np.asarray(res.normals)))
        assert (np.asarray(res.status)[np.asarray(scene8.mask)] == 0).mean() > 0.97


def test_barsky_five_scanner_lights():
    surf = jaxps.synthetic.face_like(64)
    sc = render_corrupted(surf, ring_lights(5, 45.0), specular=0.6, shininess=100.0,
                          noise=0.005, key=jax.random.key(1))
    l2 = _mean_err(jaxps.photometric_stereo(sc.images, sc.lights, mask=sc.mask), sc)
    res = jaxps.photometric_stereo(sc.images, sc.lights, mask=sc.mask, method="barsky")
    assert _mean_err(res, sc) < 0.7 * l2
    # Dropped samples are counted: n_used = K - dropped for solved pixels.
    ok = np.asarray(res.status) == 0
    assert np.all(np.asarray(res.n_used)[ok] <= 5)
    assert np.all(np.asarray(res.info["steps"])[ok] <= 2)


def _numpy_l1(a, b, max_ite=1000, tol=1e-8):
    # IRLS for min ||Ax - b||_1 as in RobustPhotometricStereo's L1_residual_min (Ikehata 2012).
    w = np.ones(len(b))
    x_old = np.ones(3)
    for _ in range(max_ite):
        x = np.linalg.lstsq(w[:, None] * a, w * b, rcond=None)[0]
        r = b - a @ x
        if np.linalg.norm(x - x_old) < tol:
            break
        x_old = x
        w = 1.0 / np.maximum(np.sqrt(np.abs(r)), 1e-8)
    return x


def _numpy_sbl(a, b, max_ite=1000, tol=1e-8, lambda1=100.0, lambda2=1e-6):
    # Sparse Bayesian learning as in RobustPhotometricStereo's sparse_bayesian_learning.
    gamma = np.ones(len(b))
    x_old = 1000 * np.ones(3)
    for _ in range(max_ite):
        wa = a / gamma[:, None]
        x = np.linalg.solve(lambda2 * np.eye(3) + a.T @ wa, wa.T @ b)
        if np.linalg.norm(x - x_old) < tol:
            break
        x_old = x
        e = b - a @ x
        xi = np.linalg.solve(lambda1 * np.eye(3) + a.T @ wa, a.T)
        gamma = np.maximum(e * e + np.sum(a * xi.T, axis=1), 1e-8)
    return x


@pytest.mark.parametrize("method,ref", [("irls", _numpy_l1), ("sbl", _numpy_sbl)])
def test_matches_numpy_reference(scene8, method, ref):
    images = np.asarray(scene8.images)
    lights = np.asarray(scene8.lights, np.float64)
    res = jaxps.photometric_stereo(images, lights, mask=scene8.mask, method=method,
                                   rtol=1e-6, max_steps=1000)
    rng = np.random.default_rng(0)
    rows, cols = np.nonzero(np.asarray(scene8.mask) & (np.asarray(res.status) == 0))
    pick = rng.choice(len(rows), 40, replace=False)
    errs = []
    for r, c in zip(rows[pick], cols[pick]):
        i = images[:, r, c].astype(np.float64)
        x = ref(lights, i / i.mean())  # same brightness normalisation as ours
        n = x / np.linalg.norm(x)
        errs.append(np.degrees(np.arccos(np.clip(n @ np.asarray(res.normals[r, c]), -1, 1))))
    assert np.median(errs) < 0.05 and np.percentile(errs, 90) < 0.5, np.sort(errs)[-5:]


def _edge_stack():
    """(K=3..5) pixels: fine, one shadowed sample of 3, all dark, all saturated, NaN."""
    lights = ring_lights(5, 30.0)
    n = np.array([0.1, 0.2, 1.0]) / np.linalg.norm([0.1, 0.2, 1.0])
    good = 0.6 * np.maximum(lights @ n, 0)
    px = np.stack([good, good, np.zeros(5), np.ones(5), good], axis=-1)  # (K, 5 pixels)
    px[4, 4] = np.nan
    return px.reshape(5, 1, 5).astype(np.float32), lights


@pytest.mark.parametrize("method", ("l2", "l1") + ROBUST)
def test_edge_cases_have_status_and_no_nan(method):
    images, lights = _edge_stack()
    res = jaxps.photometric_stereo(images, lights, method=method)
    st = np.asarray(res.status)[0]
    assert st[0] == jaxps.Status.OK
    assert st[2] == jaxps.Status.DARK
    assert st[3] == jaxps.Status.SATURATED
    assert st[4] == jaxps.Status.OK  # 4 finite samples left
    for arr in (res.normals, res.albedo, res.residual):
        assert np.all(np.isfinite(np.asarray(arr)))
    np.testing.assert_array_equal(np.asarray(res.normals)[0, 2:4], [[0, 0, 1], [0, 0, 1]])

    # K=3 with one shadowed sample: dropped by the shadow threshold -> TOO_FEW_LIGHTS.
    im3 = images[:3].copy()
    im3[0, 0, 1] = 0.0
    res3 = jaxps.photometric_stereo(im3, lights[:3], method=method, shadow_threshold=0.01)
    assert np.asarray(res3.status)[0, 1] == jaxps.Status.TOO_FEW_LIGHTS
    assert np.asarray(res3.status)[0, 0] == jaxps.Status.OK
    assert np.all(np.isfinite(np.asarray(res3.normals)))

    if method == "l1":  # shared lights only; its DEGENERATE case is in test_l1_status_codes...
        return
    # Coplanar lights (per pixel, so they reach the kernel): DEGENERATE, finite.
    flat = np.array([[1, 0, 1], [0, 1, 1], [-1, 0, 1], [0, -1, 1]], np.float32)
    flat = flat - np.array([0, 0, 1], np.float32)  # all in the z = 0 plane
    flat[:, 2] = 0.0
    plane = np.broadcast_to(flat[:, None, None, :], (4, 1, 2, 3)).copy()
    resd = jaxps.photometric_stereo(np.full((4, 1, 2), 0.3, np.float32), plane, method=method)
    np.testing.assert_array_equal(np.asarray(resd.status), jaxps.Status.DEGENERATE)
    assert np.all(np.isfinite(np.asarray(resd.normals)))


def test_chunked_equals_unchunked(scene8, monkeypatch):
    import jax

    from jaxps.ps import _robust

    images = scene8.images[:, :40]
    mask = scene8.mask[:40]
    whole = jaxps.photometric_stereo(images, scene8.lights, mask=mask, method="irls")
    jax.clear_caches()
    monkeypatch.setattr(_robust, "_CHUNK", 500)  # 40 x 51 pixels -> 5 chunks, padded
    parts = jaxps.photometric_stereo(images, scene8.lights, mask=mask, method="irls")
    jax.clear_caches()
    # Same kernel; XLA may round differently per batch size, which can move a pixel's stop
    # by a step (changes of order rtol = 1e-4).
    np.testing.assert_array_equal(np.asarray(whole.status), np.asarray(parts.status))
    assert float(jaxps.angular_error(whole.normals, parts.normals).max()) < 0.5
    np.testing.assert_allclose(np.asarray(whole.albedo), np.asarray(parts.albedo), atol=5e-3)
    assert np.abs(np.asarray(whole.info["steps"]) - np.asarray(parts.info["steps"])).mean() < 0.5


@pytest.mark.parametrize("method", ["barsky", "irls"])
def test_blocks_equal_one_block(scene8, method, monkeypatch):
    # The solvers run in `lax.map` blocks of `_robust._BLOCK` pixels. 64 x 64 pixels in blocks
    # of 700 (6 blocks, the last padded; irls's 128-pixel loop chunks padded in each) against
    # one block: colour samples, per-pixel lights and dropped samples, as in the test below.
    from jaxps.ps import _robust

    k, h, w = scene8.images.shape
    rgb = np.stack([scene8.images, 0.7 * scene8.images], axis=-1)
    near = np.broadcast_to(np.asarray(scene8.lights)[:, None, None], (k, h, w, 3)).copy()
    near[..., 1] += np.linspace(-0.05, 0.05, h, dtype=np.float32)[:, None]
    drop = np.ones((k, h, w), bool)
    drop[1, 5::4] = False

    def solve(block):
        monkeypatch.setattr(_robust, "_BLOCK", block)
        jax.clear_caches()
        return jaxps.photometric_stereo(rgb, near, mask=scene8.mask, sample_mask=drop,
                                        method=method)

    one, blocks = solve(h * w), solve(700)
    jax.clear_caches()
    for field in ("status", "n_used"):
        np.testing.assert_array_equal(np.asarray(getattr(blocks, field)),
                                      np.asarray(getattr(one, field)))
    np.testing.assert_array_equal(np.asarray(blocks.info["steps"]), np.asarray(one.info["steps"]))
    assert (np.asarray(one.status)[np.asarray(scene8.mask)] == 0).mean() > 0.9
    assert float(jaxps.angular_error(blocks.normals, one.normals).max()) < 1e-3
    np.testing.assert_allclose(np.asarray(blocks.albedo), np.asarray(one.albedo), atol=1e-5)
    np.testing.assert_allclose(np.asarray(blocks.residual), np.asarray(one.residual), atol=1e-5)


@pytest.mark.parametrize("method", ["barsky", "irls", "sbl"])
def test_row_bands_on_threads_equal_one_call(scene8, method, monkeypatch):
    # A top-level CPU call of the loop solvers runs row bands on threads; 64 rows in 3 bands
    # of 22 (the last padded with 2 masked rows), against the same call in one program. (A
    # call traced into a caller's jit with the lights as constants is not the reference: XLA
    # folds the light products, and IRLS's stop moves by a step in some pixels.)
    from jaxps.ps import _photometric_stereo

    monkeypatch.setattr(_photometric_stereo, "cpu_cores", lambda: 3)
    bands, banded_call = [], _photometric_stereo._in_row_bands
    monkeypatch.setattr(_photometric_stereo, "_in_row_bands",
                        lambda *a: bands.append(a[-1]) or banded_call(*a))

    def both(images, lights, **kw):
        monkeypatch.setattr(_photometric_stereo, "_BAND_PIXELS", 1 << 40)
        one = jaxps.photometric_stereo(images, lights, method=method, **kw)
        monkeypatch.setattr(_photometric_stereo, "_BAND_PIXELS", 1)
        return jaxps.photometric_stereo(images, lights, method=method, **kw), one

    k, h, w = scene8.images.shape
    rgb = np.stack([scene8.images, 0.7 * scene8.images], axis=-1)
    near = np.broadcast_to(np.asarray(scene8.lights)[:, None, None], (k, h, w, 3)).copy()
    near[..., 0] += np.linspace(-0.05, 0.05, w, dtype=np.float32)
    near /= np.linalg.norm(near, axis=-1, keepdims=True)
    drop = np.ones((k, h, w), bool)
    drop[0, ::3] = False
    cases = ((scene8.images, scene8.lights, {"mask": scene8.mask}),
             (rgb, near, {"mask": scene8.mask, "sample_mask": drop}),
             (scene8.images, scene8.lights, {}))  # no mask: every pixel
    for images, lights, kw in cases:
        banded, one = both(images, lights, **kw)
        assert banded.normals.shape == one.normals.shape == (h, w, 3)
        assert banded.albedo.shape == one.albedo.shape
        assert jax.tree.structure(banded) == jax.tree.structure(one)
        np.testing.assert_array_equal(np.asarray(banded.status), np.asarray(one.status))
        np.testing.assert_array_equal(np.asarray(banded.n_used), np.asarray(one.n_used))
        np.testing.assert_array_equal(np.asarray(banded.info["steps"]),
                                      np.asarray(one.info["steps"]))
        assert float(jaxps.angular_error(banded.normals, one.normals).max()) < 1e-3
        np.testing.assert_allclose(np.asarray(banded.albedo), np.asarray(one.albedo),
                                   atol=1e-5)
        np.testing.assert_allclose(np.asarray(banded.residual), np.asarray(one.residual),
                                   atol=1e-5)
        masked = np.asarray(banded.status) == jaxps.Status.MASKED
        np.testing.assert_array_equal(masked, ~np.asarray(kw.get("mask", np.ones((h, w), bool))))
    assert bands == [3, 3, 3]
    # an option's error comes back from a band's thread; one row is one band, one program
    bad = {"max_drop": -1} if method == "barsky" else {"max_steps": 0}
    with pytest.raises(ValueError, match=next(iter(bad))):
        jaxps.photometric_stereo(scene8.images, scene8.lights, method=method, **bad)
    one_row = jaxps.photometric_stereo(scene8.images[:, :1], scene8.lights, method=method)
    assert one_row.normals.shape == (1, w, 3) and bands == [3, 3, 3, 3]


def test_step_limit_reports_not_converged(scene8):
    res = jaxps.photometric_stereo(scene8.images, scene8.lights, mask=scene8.mask,
                                   method="sbl", max_steps=2, rtol=1e-9)
    st = np.asarray(res.status)[np.asarray(scene8.mask)]
    assert np.all(st == jaxps.Status.NOT_CONVERGED)
    assert int(np.asarray(res.info["steps"]).max()) == 2


def test_colour_and_dtype(scene8):
    rgb = np.stack([scene8.images, 0.5 * scene8.images, 0.8 * scene8.images], axis=-1)
    for method in ("sbl",):  # every robust method shares the final colour solve (_finish)
        res = jaxps.photometric_stereo(rgb, scene8.lights, mask=scene8.mask, method=method)
        assert res.albedo.shape == (64, 51, 3) and res.normals.dtype == np.float32
        a = np.asarray(res.albedo)[np.asarray(res.status) == 0]
        np.testing.assert_allclose(a[:, 1] / a[:, 0], 0.5, rtol=1e-4)


def test_bad_options():
    images, lights = _edge_stack()
    with pytest.raises(ValueError, match="loss"):
        jaxps.photometric_stereo(images, lights, method="irls", loss="l3")
    with pytest.raises(ValueError, match="max_steps"):
        jaxps.photometric_stereo(images, lights, method="sbl", max_steps=0)
    with pytest.raises(ValueError, match="threshold"):
        jaxps.photometric_stereo(images, lights, method="barsky", threshold=-1)


@pytest.mark.parametrize("obj", ["cat", "owl"])
def test_psm_corrupted_against_12_light_reference(data, obj):
    # Reference: method="sbl" on all 12 real (clean) images with lights.txt. Then 30% of the
    # pixels get one random sample set to 0 (a shadow) and 30% one sample raised by 0.4 (a
    # highlight); every robust method must stay much closer to the reference than L2.
    from jaxps import load_psm

    images, mask = load_psm(data / "psm" / obj)
    images, mask = images[:, ::4, ::4], mask[::4, ::4] > 0.5
    lights = jaxps.load_lights(data / "psm" / "lights.txt")
    ref = jaxps.photometric_stereo(images, lights, mask=mask, method="sbl")
    ok = mask & (np.asarray(ref.status) == 0)
    k, h, w, _ = images.shape
    rng = np.random.default_rng(0)
    rr, cc = np.indices((h, w))
    cor = images.copy()
    js = rng.integers(0, k, (h, w))
    sel = rng.random((h, w)) < 0.3
    cor[js[sel], rr[sel], cc[sel]] = 0
    jb = (js + rng.integers(1, k, (h, w))) % k
    sel = rng.random((h, w)) < 0.3
    cor[jb[sel], rr[sel], cc[sel]] = np.minimum(cor[jb[sel], rr[sel], cc[sel]] + 0.4, 1)
    err = {m: angular_stats(jaxps.photometric_stereo(cor, lights, mask=mask, method=m).normals,
                            ref.normals, mask=ok)["mean_deg"] for m in ("l2",) + ROBUST}
    assert err["l2"] > 10
    for m in ROBUST:
        assert err[m] < 0.4 * err["l2"], err


# ---------------------------------------------------------------------------- exact L1 ("l1")
def _linprog_l1(a, b):
    """min_x ||a x - b||_1 as a linear program (scipy HiGHS): the reference optimum."""
    from scipy.optimize import linprog

    m = len(b)
    cost = np.r_[np.zeros(3), np.ones(m)]
    a_ub = np.block([[-a, -np.eye(m)], [a, -np.eye(m)]])
    res = linprog(cost, A_ub=a_ub, b_ub=np.r_[-b, b],
                  bounds=[(None, None)] * 3 + [(0, None)] * m)
    return res.fun


def test_l1_reaches_the_linear_programs_optimum_over_the_usable_samples():
    rng = np.random.default_rng(3)
    lights = np.asarray(jaxps.lights_from_angles([0, 30, -30, 10, -15, 0, 20],
                                                 [0, 5, -5, 30, -25, 45, -30]))
    images = rng.uniform(0.05, 0.9, (7, 8, 9)).astype(np.float32)
    images[1, :3] = np.nan  # dropped: not finite
    images[3, 4:] = 0.0  # dropped: below the shadow threshold
    res = jaxps.photometric_stereo(images, lights, method="l1", shadow_threshold=0.01,
                                   dark_threshold=0.0)
    assert np.all(np.asarray(res.status) == 0)
    b = np.asarray(res.normals) * np.asarray(res.albedo)[..., None]
    for r, c in np.ndindex(8, 9):
        x = images[:, r, c]
        used = np.isfinite(x) & (x >= 0.01)
        ours = np.abs(x[used] - lights[used] @ b[r, c]).sum()
        assert ours <= _linprog_l1(lights[used], x[used]) + 1e-5, (r, c)
    n_used = np.asarray(res.n_used)
    assert n_used.max() <= 7 and n_used.min() >= 3  # inliers of the fit


def test_l1_ignores_one_corrupted_sample_where_least_squares_does_not():
    # Lights in general position: with the scanner's cross, lights (-20,0), (0,0), (+20,0) lie
    # in one plane, and an error on one end of that line costs L1 the same as on the other
    # (a tie that rounding breaks either way).
    lights = jaxps.lights_from_angles([0, 30, -25, 10, -15], [0, 10, -5, 30, -25])
    s = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(48), lights)
    images = np.array(s.images)
    images[2] += 0.3  # a highlight on every pixel of one frame
    mask = np.asarray(s.mask)
    l1 = jaxps.photometric_stereo(images, s.lights, mask=mask, method="l1")
    l2 = jaxps.photometric_stereo(images, s.lights, mask=mask)
    e1 = angular_stats(l1.normals, s.normals, mask=mask)["median_deg"]
    e2 = angular_stats(l2.normals, s.normals, mask=mask)["median_deg"]
    assert e1 < 0.01 and e2 > 5, (e1, e2)  # three clean samples fit exactly
    ok = np.asarray(l1.status)[mask] == 0
    assert ok.all()
    assert np.all(np.asarray(l1.n_used)[mask] == 4)  # the corrupted sample is the outlier
    colour = jaxps.photometric_stereo(np.stack([images] * 3, -1), s.lights, mask=mask,
                                      method="l1")
    np.testing.assert_allclose(colour.normals, l1.normals, atol=1e-5)
    np.testing.assert_allclose(colour.albedo[..., 1], l1.albedo, rtol=1e-4, atol=1e-6)


def test_l1_status_codes_and_bad_input():
    lights = np.asarray(jaxps.lights_from_angles([0, 30, -30, 0], [0, 0, 0, 30]))
    images = np.full((4, 2, 3), 0.5, np.float32)
    images[3, 0] = 0.0  # the only light out of the y = 0 plane, shadowed: coplanar rest
    images[:2, 1, 1] = 0.0  # two of four shadowed: too few
    res = jaxps.photometric_stereo(images, lights, method="l1", shadow_threshold=0.01)
    st = np.asarray(res.status)
    assert np.all(st[0] == jaxps.Status.DEGENERATE)
    assert st[1, 1] == jaxps.Status.TOO_FEW_LIGHTS
    np.testing.assert_array_equal(np.asarray(res.normals)[0], [[0, 0, 1]] * 3)
    with pytest.raises(ValueError, match="K=9"):
        jaxps.photometric_stereo(np.full((9, 2, 2), 0.5, np.float32), ring_lights(9, 30.0),
                                 method="l1")
    field = np.broadcast_to(lights[:, None, None], (4, 2, 3, 3))
    with pytest.raises(ValueError, match="shared"):
        jaxps.photometric_stereo(images, field, method="l1")


def test_scene_helpers_reject_bad_arguments():
    # Each of these returned a wrong array, or failed inside jax or numpy, before.
    height = np.zeros((8, 6), np.float32)
    lights = ring_lights(5, 30.0)
    with pytest.raises(ValueError, match=r"lights must be \(K, 3\)"):
        cast_shadow_mask(height, lights[:, :2])
    with pytest.raises(ValueError, match=r"height must be \(H, W\)"):
        cast_shadow_mask(height[0], lights)
    with pytest.raises(ValueError, match="n_steps must be a positive int"):
        cast_shadow_mask(height, lights, n_steps=0)
    with pytest.raises(ValueError, match="zenith_deg must be in"):
        ring_lights(5, 95.0)
    with pytest.raises(ValueError, match="angle_deg must be finite"):
        perturb_lights(lights, float("nan"), key=0)
    with pytest.raises(ValueError, match="non-zero directions"):
        perturb_lights(np.zeros((3, 3)), 2.0, key=0)
    surface = jaxps.synthetic.face_like(8, 6)
    with pytest.raises(ValueError, match=r"lights must be \(K, 3\) or \(K, H, W, 3\)"):
        render_corrupted(surface, lights[:, :2])
    # the rotation is exactly the angle asked for, either way round
    for angle in (3.0, -3.0):
        moved = perturb_lights(lights, angle, key=1)
        cos = np.sum(moved * lights, axis=-1) / np.linalg.norm(moved, axis=-1)
        np.testing.assert_allclose(np.degrees(np.arccos(np.clip(cos, -1, 1))), 3.0, atol=1e-3)
