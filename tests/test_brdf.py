"""BRDF fitting and relighting: features against numpy, a synthetic non-Lambertian scene with
held-out lights, reproducibility, extrapolation flags and bad input."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxps

# --------------------------------------------------------------------------- numpy references


def features_numpy(normals, lights):
    """(K, H, W, 5) (θi, θr, Δα, x, y) by explicit per-sample loops over K and pixels."""
    h, w, _ = normals.shape
    out = np.zeros((len(lights), h, w, 5))
    v = np.array([0.0, 0.0, 1.0])
    for k, l in enumerate(np.asarray(lights, np.float64)):
        l = l / np.linalg.norm(l)
        for r in range(h):
            for c in range(w):
                n = np.asarray(normals[r, c], np.float64)
                n = n / np.linalg.norm(n)
                ti = np.arccos(np.clip(n @ l, -1, 1))
                tr = np.arccos(np.clip(n @ v, -1, 1))
                lt, vt = l - (n @ l) * n, v - (n @ v) * n
                nl, nv = np.linalg.norm(lt), np.linalg.norm(vt)
                da = 0.0 if nl < 1e-9 or nv < 1e-9 else np.arccos(
                    np.clip(lt @ vt / (nl * nv), -1, 1))
                out[k, r, c] = ti, tr, da, 2 * c / (w - 1) - 1, 1 - 2 * r / (h - 1)
    return out


def features_vectorised(normals, lights):
    """(θi, θr, Δα) as in `features_numpy`, vectorised (for rendering scenes)."""
    n = np.asarray(normals, np.float64)[None]
    l = np.asarray(lights, np.float64)[:, None, None, :]
    v = np.array([0.0, 0.0, 1.0])
    nl, nv = np.sum(n * l, -1), n[..., 2]
    lt, vt = l - nl[..., None] * n, v - nv[..., None] * n
    norm = np.linalg.norm(lt, axis=-1) * np.linalg.norm(vt, axis=-1)
    cos_da = np.where(norm > 1e-9, np.sum(lt * vt, -1) / np.maximum(norm, 1e-9), 1.0)
    ti, tr = np.arccos(np.clip(nl, -1, 1)), np.arccos(np.clip(nv, -1, 1))
    return np.stack([ti, np.broadcast_to(tr, ti.shape), np.arccos(np.clip(cos_da, -1, 1))], -1)


def render_non_lambertian(normals, albedo, lights, sigma=0.4, ks=0.2, shininess=20.0):
    """Oren–Nayar (qualitative, roughness `sigma`) plus a Blinn–Phong lobe, view (0, 0, 1)."""
    f = features_vectorised(normals, lights)
    ti, tr, da = f[..., 0], f[..., 1], f[..., 2]
    a = 1 - 0.5 * sigma**2 / (sigma**2 + 0.33)
    b = 0.45 * sigma**2 / (sigma**2 + 0.09)
    alpha, beta = np.maximum(ti, tr), np.minimum(ti, tr)
    diffuse = np.maximum(np.cos(ti), 0) * (
        a + b * np.maximum(0, np.cos(da)) * np.sin(alpha) * np.tan(beta))
    lights = np.asarray(lights, np.float64)
    half = lights + np.array([0.0, 0.0, 1.0])
    half /= np.linalg.norm(half, axis=-1, keepdims=True)
    nh = np.einsum("kc,hwc->khw", half, np.asarray(normals, np.float64))
    spec = ks * np.maximum(nh, 0) ** shininess * (np.cos(ti) > 0)
    return (np.asarray(albedo, np.float64)[None] * diffuse + spec).astype(np.float32)


@pytest.fixture(scope="module")
def scene():
    surface = jaxps.synthetic.sphere(40, max_zenith_deg=70.0)
    mask = np.asarray(surface.mask)
    x, y = np.meshgrid(np.arange(40), np.arange(40))
    albedo = np.where(mask, 0.6 + 0.2 * np.sin(x / 5.0) * np.cos(y / 7.0), 0).astype(np.float32)
    train = jaxps.synthetic.scanner_lights(20.0)
    test = jaxps.lights_from_angles([12.0, -12.0, 15.0, -8.0], [10.0, -10.0, -12.0, 14.0])
    return dict(normals=np.asarray(surface.normals), albedo=albedo, mask=mask, train=train,
                test=test, images=render_non_lambertian(surface.normals, albedo, train),
                truth=render_non_lambertian(surface.normals, albedo, test))


def rmse(a, b, mask):
    return float(np.sqrt(np.mean((np.asarray(a) - b)[:, mask] ** 2)))


# n_samples above the ~4,500 masked samples: every test fits the same shapes (one compile per
# method) and the training set is every sample.
FAST = dict(n_samples=10**6, max_steps=15)


@pytest.fixture(scope="module")
def fitted(scene):
    s = scene
    return {m: jaxps.fit_brdf(s["images"], s["normals"], s["albedo"], s["train"], mask=s["mask"],
                              method=m, key=jax.random.key(0), **FAST)
            for m in ("lambertian", "mlp_ratio", "mlp")}


# --------------------------------------------------------------------------- features


def test_features_match_numpy():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(6, 7, 3))
    n[..., 2] = np.abs(n[..., 2]) + 0.1
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[0, 0] = (0, 0, 1)  # Δα undefined: defined as 0
    lights = jaxps.lights_from_angles([0.0, 30.0, -50.0], [0.0, 20.0, -10.0])
    got = np.asarray(jaxps.brdf_features(n.astype(np.float32), lights))
    ref = features_numpy(n, lights)
    np.testing.assert_allclose(features_vectorised(n, lights), ref[..., :3], atol=1e-6)
    assert got.shape == (3, 6, 7, 5) and got.dtype == np.float32
    np.testing.assert_allclose(got, ref, atol=2e-3)  # float32 arccos/arctan2 near 0 and π
    assert jaxps.FEATURE_NAMES == ("theta_i", "theta_r", "delta_alpha", "x", "y")


def test_features_gradients_finite():
    n = jnp.array([[[0.0, 0.0, 1.0], [0.3, 0.0, 0.954]]])
    lights = jnp.array([[0.0, 0.0, 1.0]])
    g = jax.grad(lambda m: jnp.sum(jaxps.brdf_features(m, lights)))(n)
    assert np.all(np.isfinite(np.asarray(g)))


def test_atan2_polynomial_matches_numpy():
    from jaxps.core._elementwise import atan2_nonneg as _atan2_nonneg

    rng = np.random.default_rng(1)
    y = np.abs(rng.normal(size=2000)) * 10.0 ** rng.uniform(-6, 3, 2000)
    x = rng.normal(size=2000) * 10.0 ** rng.uniform(-6, 3, 2000)
    y[:4], x[:4] = [0.0, 0.0, 1.0, 1.0], [1.0, -1.0, 0.0, 1.0]  # 0, π, π/2, π/4
    got = np.asarray(_atan2_nonneg(jnp.asarray(y, jnp.float32), jnp.asarray(x, jnp.float32)))
    ref = np.arctan2(y.astype(np.float32).astype(np.float64), x.astype(np.float32))
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, ref, rtol=0, atol=4e-7)  # ~1 ulp of π
    got64 = _atan2_nonneg(jnp.asarray(y, jnp.float64), jnp.asarray(x, jnp.float64)) \
        if jax.config.jax_enable_x64 else None
    assert got64 is None or np.allclose(got64, np.arctan2(y, x), atol=1e-15)


def test_relight_tanh_matches_numpy():
    from jaxps.core._elementwise import tanh as _tanh

    x = np.concatenate([np.linspace(-12, 12, 20001), 10.0 ** np.linspace(-9, 1, 2001),
                        -(10.0 ** np.linspace(-9, 1, 2001)), [0.0]]).astype(np.float32)
    got = np.asarray(jax.jit(_tanh)(jnp.asarray(x)))
    ref = np.tanh(x.astype(np.float64))
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, ref, rtol=4e-7, atol=4e-7)
    assert np.all(np.abs(got) <= 1) and got[-1] == 0


def test_support_weight_matches_scipy_map_coordinates():
    import scipy.ndimage

    from jaxps.reflectance._brdf import _support_weight

    rng = np.random.default_rng(2)
    grid = (rng.uniform(size=(6, 4, 5)) > 0.5).astype(np.float32)
    cell = 0.3
    # angles inside, between and beyond the cells (clamped to the edge, mode="nearest")
    ang = rng.uniform(-0.5, 2.5, size=(3, 500)).astype(np.float32)
    got = np.asarray(_support_weight(jnp.asarray(grid), tuple(jnp.asarray(ang)), cell))
    ref = scipy.ndimage.map_coordinates(grid.astype(np.float64), ang / cell - 0.5, order=1,
                                        mode="nearest")
    np.testing.assert_allclose(got, ref, atol=1e-5)


def relight_numpy(model, normals, albedo, lights):
    """The model's formula (docstring of jaxps.reflectance._brdf) in float64 numpy: features by
    `features_vectorised`, the MLP as matrix products, the support by scipy's trilinear
    `map_coordinates`."""
    import scipy.ndimage

    f = features_vectorised(normals, lights)  # (K, H, W, 3)
    k, h, w, _ = f.shape
    ti, tr, da = f[..., 0], f[..., 1], f[..., 2]
    lo, hi = np.asarray(model.box_lo, np.float64), np.asarray(model.box_hi, np.float64)
    u = np.stack([ti - tr, ti + tr, da], -1)
    if model.lambertian_base:
        u = np.clip(u, lo, hi)
    z = 2 * (u - lo) / np.maximum(hi - lo, 1e-6) - 1
    x, y = np.meshgrid(2 * np.arange(w) / (w - 1) - 1, 1 - 2 * np.arange(h) / (h - 1))
    xy = np.broadcast_to(np.stack([x, y], -1), (k, h, w, 2)) * float(model.use_xy)
    a = np.concatenate([z, xy], -1)
    for i, (wt, b) in enumerate(model.params):
        a = a @ np.asarray(wt, np.float64).T + np.asarray(b, np.float64)
        a = np.tanh(a) if i < len(model.params) - 1 else a[..., 0]
    rho = np.broadcast_to(np.asarray(albedo, np.float64), (k, h, w))
    amp = rho if model.method == "mlp_ratio" else float(model.rho_ref)
    if not model.lambertian_base:
        return amp * a
    support = scipy.ndimage.map_coordinates(
        np.asarray(model.support, np.float64), [c.ravel() / model.cell - 0.5 for c in (ti, tr, da)],
        order=1, mode="nearest").reshape(k, h, w)
    return rho * np.maximum(np.cos(ti), 0) + amp * support * model.bound * np.tanh(a)


def test_relight_matches_numpy_reference(scene, fitted):
    s = scene
    plain = jaxps.fit_brdf(s["images"], s["normals"], s["albedo"], s["train"], mask=s["mask"],
                           method="mlp_ratio", lambertian_base=False, key=jax.random.key(0),
                           n_samples=10**6, max_steps=3)
    # the test lights, the training lights and two beyond them (where the support fades)
    lights = np.concatenate([s["test"], s["train"],
                             jaxps.lights_from_angles([50.0, -20.0], [0.0, -40.0])])
    for model in (fitted["mlp"], fitted["mlp_ratio"], fitted["lambertian"], plain):
        got = np.asarray(jaxps.relight(model, s["normals"], s["albedo"], lights))
        if model.method == "lambertian":
            ref = np.asarray(s["albedo"], np.float64) * np.maximum(
                np.cos(features_vectorised(s["normals"], lights)[..., 0]), 0)
        else:
            ref = relight_numpy(model, s["normals"], s["albedo"], lights)
        # float32 against float64: measured at most 1.1e-6 (albedo 0.4-0.8)
        np.testing.assert_allclose(got[:, s["mask"]], ref[:, s["mask"]], atol=5e-6)
        # inside a trace relight compiles without its vector-width option (JAX takes compiler
        # options on top-level jits only): the same kernel, the same values
        traced = jax.jit(lambda n, m=model: jaxps.relight(m, n, s["albedo"], lights))
        np.testing.assert_allclose(np.asarray(traced(s["normals"])), got, rtol=0, atol=1e-6)


# --------------------------------------------------------------------------- fitting


def test_mlp_beats_lambertian_on_held_out_lights(scene, fitted):
    s = scene
    err = {m: rmse(jaxps.relight(model, s["normals"], s["albedo"], s["test"]), s["truth"],
                   s["mask"]) for m, model in fitted.items()}
    # Oren–Nayar + specular: Lambert's law is off by ~0.05; the fitted corrections remove most
    # of it on lights between the training ones (measured ~0.01-0.02).
    assert err["lambertian"] > 0.03
    assert err["mlp_ratio"] < 0.5 * err["lambertian"], err
    assert err["mlp"] < 0.5 * err["lambertian"], err
    for model in fitted.values():
        assert 0 < model.fit.mse and -1 <= model.fit.r <= 1
        assert np.isclose(model.fit.rmse**2, model.fit.mse)
    assert fitted["mlp_ratio"].fit.r > fitted["lambertian"].fit.r
    assert 0 < fitted["mlp_ratio"].fit.steps <= FAST["max_steps"]


def test_relight_training_lights_reproduces_training_error(scene, fitted):
    s = scene
    model = fitted["mlp_ratio"]
    assert model.fit.n_samples == 5 * int(s["mask"].sum())  # every sample: same set as below
    out = jaxps.relight(model, s["normals"], s["albedo"], s["train"], mask=s["mask"])
    assert out.shape == s["images"].shape and out.dtype == jnp.float32
    # the training fit is the relight times each frame's fitted brightness factor ...
    gains = np.asarray(model.fit.frame_gains)[:, None, None]
    np.testing.assert_allclose(rmse(gains * np.asarray(out), s["images"], s["mask"]),
                               model.fit.rmse, rtol=1e-3)
    # ... and this scene's frames have none: the factors stay near 1 (they take up a little of
    # the frontal frame's specular lobe) and the relight at g = 1 is near the training error,
    # far below Lambert's
    assert np.allclose(model.fit.frame_gains, 1.0, atol=0.03), model.fit.frame_gains
    assert rmse(out, s["images"], s["mask"]) <= 1.2 * model.fit.rmse
    assert rmse(out, s["images"], s["mask"]) < 0.5 * fitted["lambertian"].fit.rmse
    # without frame gains the relight of the training lights is the training fit itself
    plain = jaxps.fit_brdf(s["images"], s["normals"], s["albedo"], s["train"], mask=s["mask"],
                           method="mlp_ratio", key=jax.random.key(0), frame_gains=False, **FAST)
    assert plain.fit.frame_gains is None
    out = jaxps.relight(plain, s["normals"], s["albedo"], s["train"], mask=s["mask"])
    np.testing.assert_allclose(rmse(out, s["images"], s["mask"]), plain.fit.rmse, rtol=1e-3)
    assert np.all(np.asarray(out)[:, ~s["mask"]] == 0)


def test_fixed_key_reproducible(scene, fitted):
    s = scene
    args = (s["images"], s["normals"], s["albedo"], s["train"])
    kw = dict(mask=s["mask"], method="mlp", **FAST)
    a = fitted["mlp"]  # key 0
    b = jaxps.fit_brdf(*args, key=jax.random.key(0), **kw)
    c = jaxps.fit_brdf(*args, key=jax.random.key(4), **kw)
    d = jaxps.fit_brdf(*args, key=4, **kw)  # an int seed means jax.random.key(seed)
    flat = [jax.flatten_util.ravel_pytree(m.params)[0] for m in (a, b, c, d)]
    np.testing.assert_array_equal(np.asarray(flat[0]), np.asarray(flat[1]))
    assert not np.array_equal(np.asarray(flat[0]), np.asarray(flat[2]))
    np.testing.assert_array_equal(np.asarray(flat[2]), np.asarray(flat[3]))


def test_delaunay_interpolates_and_falls_back_to_lambert(scene):
    s = scene
    # without the specular term I/ρ is a function of the angles alone, so samples sharing
    # angles agree and every training sample is reproduced (up to float32)
    images = render_non_lambertian(s["normals"], s["albedo"], s["train"], ks=0.0)
    model = jaxps.fit_brdf(images, s["normals"], s["albedo"], s["train"], mask=s["mask"],
                           method="delaunay", n_samples=10**6)
    out = np.asarray(jaxps.relight(model, s["normals"], s["albedo"], s["train"], mask=s["mask"]))
    inside = ~np.asarray(jaxps.extrapolation_mask(model, s["normals"], s["train"]))
    sel = inside & s["mask"][None]
    # most training samples sit in non-degenerate simplices, where they are reproduced
    assert sel.sum() > 0.5 * 5 * s["mask"].sum()
    np.testing.assert_allclose(out[sel], images[sel], atol=1e-4)
    lam = np.asarray(jaxps.render_lambertian(s["normals"], s["albedo"], s["train"]))
    np.testing.assert_allclose(out[~inside & s["mask"][None]], lam[~inside & s["mask"][None]],
                               atol=1e-5)
    far = jaxps.lights_from_angles([60.0], [0.0])
    flag = np.asarray(jaxps.extrapolation_mask(model, s["normals"], far))
    lam = np.asarray(jaxps.render_lambertian(s["normals"], s["albedo"], far))
    got = np.asarray(jaxps.relight(model, s["normals"], s["albedo"], far, mask=s["mask"]))
    sel = flag & s["mask"][None]
    assert sel.sum() > 20
    np.testing.assert_allclose(got[sel], lam[sel], atol=1e-5)


def test_mlp_degrades_to_lambert_where_flagged(scene, fitted):
    s = scene
    far = jaxps.lights_from_angles([70.0, 0.0], [0.0, -65.0])
    model = fitted["mlp_ratio"]
    flag = np.asarray(jaxps.extrapolation_mask(model, s["normals"], far)) & s["mask"][None]
    near = np.asarray(jaxps.extrapolation_mask(model, s["normals"], s["train"])) & s["mask"][None]
    assert flag.mean() > 5 * near.mean()
    got = np.asarray(jaxps.relight(model, s["normals"], s["albedo"], far))
    lam = np.asarray(jaxps.render_lambertian(s["normals"], s["albedo"], far))
    assert np.all(np.isfinite(got))
    # flagged samples get at most half the bounded correction: |I - Lambert| <= 0.5 B ρ
    bound = 0.5 * model.bound * np.broadcast_to(s["albedo"], got.shape)
    assert np.all(np.abs(got - lam)[flag] <= bound[flag] + 1e-6)


def test_frame_gains_recovered_and_not_learned_as_reflectance(scene):
    """Non-Lambertian frames whose flashes fired at known, unequal strengths, with the true
    normals and albedo: `frame_gains` recovers the strengths (up to their geometric mean), and
    the relight at unit gain beats the network trained without them, which learns the flashes
    as reflectance. (With normals from five-light PS on the same frames the normals take up
    most of the gains instead: semi-calibrated PS is near-degenerate for near-frontal lights.)"""
    s = scene
    true_gains = np.array([1.0, 1.15, 0.9, 0.85, 1.1])
    mean = np.exp(np.mean(np.log(true_gains)))
    images = s["images"] * true_gains[:, None, None].astype(np.float32)
    truth = s["truth"] * mean  # the scene as lit by the flashes' geometric mean
    kw = dict(mask=s["mask"], method="mlp_ratio", key=jax.random.key(0), **FAST)
    err = {}
    for name, extra in (("gains", {}), ("no_gains", {"frame_gains": False}),
                        ("lambertian", {"method": "lambertian"})):
        model = jaxps.fit_brdf(images, s["normals"], s["albedo"] * mean, s["train"],
                               **{**kw, **extra})
        err[name] = rmse(jaxps.relight(model, s["normals"], s["albedo"] * mean, s["test"]),
                         truth, s["mask"])
        if name == "gains":
            np.testing.assert_allclose(model.fit.frame_gains, true_gains / mean, atol=0.02)
    assert err["gains"] < 0.6 * err["no_gains"], err
    assert err["gains"] < 0.5 * err["lambertian"], err


def test_loo_shrink_keeps_real_reflectance_and_drops_frame_gains(scene):
    """`shrink="loo"` keeps the correction on a non-Lambertian scene and removes it when the
    only departure from Lambert's law is an unknown brightness per frame (Yale B's case)."""
    s = scene
    gains = np.array([1.0, 1.15, 0.9, 0.85, 1.1], np.float32)[:, None, None]
    lam_train = np.asarray(jaxps.render_lambertian(s["normals"], s["albedo"], s["train"]))
    lam_test = np.asarray(jaxps.render_lambertian(s["normals"], s["albedo"], s["test"]))
    kw = dict(mask=s["mask"], method="mlp_ratio", key=jax.random.key(0), shrink="loo", **FAST)
    results = {}
    for name, images, truth in (("brdf", s["images"], s["truth"]),
                                ("gains", lam_train * gains, lam_test)):
        ps = jaxps.photometric_stereo(images, s["train"], mask=s["mask"])
        model = jaxps.fit_brdf(images, ps.normals, ps.albedo, s["train"], **kw)
        lam = jaxps.fit_brdf(images, ps.normals, ps.albedo, s["train"], mask=s["mask"],
                             method="lambertian")
        loo = model.fit.loo_rmse
        assert loo["shrunk"] <= loo["lambertian"] + 1e-9
        assert model.bound == pytest.approx(0.5 * model.fit.shrink)
        results[name] = (model.fit.shrink,
                         rmse(jaxps.relight(model, ps.normals, ps.albedo, s["test"]), truth,
                              s["mask"]),
                         rmse(jaxps.relight(lam, ps.normals, ps.albedo, s["test"]), truth,
                              s["mask"]))
    shrink, err, err_lambert = results["brdf"]
    assert shrink > 0.5 and err < 0.8 * err_lambert, results
    shrink, err, err_lambert = results["gains"]
    assert shrink < 0.2 and err <= err_lambert * 1.01, results
    with pytest.raises(ValueError, match="shrink"):
        jaxps.fit_brdf(s["images"], s["normals"], s["albedo"], s["train"], method="delaunay",
                       shrink="loo")
    # four frames leave three per fold, which Lambert's law fits exactly: no test at all
    with pytest.raises(ValueError, match="K >= 5"):
        jaxps.fit_brdf(s["images"][:4], s["normals"], s["albedo"], s["train"][:4], **kw)


# --------------------------------------------------------------------------- BRDF in the loop


def test_brdf_in_the_loop_lambertian_matches_l2(scene):
    s = scene
    images = np.asarray(jaxps.render_lambertian(s["normals"], s["albedo"], s["train"]))
    l2 = jaxps.photometric_stereo(images, s["train"], mask=s["mask"])
    res = jaxps.brdf_photometric_stereo(images, s["train"], mask=s["mask"], method="lambertian",
                                        iterations=1, max_steps=5)
    err = np.asarray(jaxps.angular_error(res.normals, s["normals"], mask=s["mask"]))
    assert err[s["mask"]].max() < 0.1  # exact Lambertian data: stays at the truth
    np.testing.assert_allclose(np.asarray(res.albedo)[s["mask"]],
                               np.asarray(l2.albedo)[s["mask"]], atol=1e-3)
    # Exact data and the true optimum at the start: every pixel converges within 5 steps.
    assert np.all(np.asarray(res.status)[s["mask"]] == jaxps.Status.OK)
    with pytest.raises(ValueError, match="method"):
        jaxps.brdf_photometric_stereo(images, s["train"], method="delaunay")


def test_brdf_in_the_loop_with_frame_gains_moves_normals_toward_truth(scene):
    """Oren–Nayar + specular frames whose flashes fired unequally: L2 is ~19 deg off (mean);
    the loop with `mlp_ratio` re-solves each pixel against I_k / g_k with the fitted frame
    gains and ends closer to the true normals than L2 and than the same loop without frame
    gains (measured 18.6 vs 19.1 and 19.0 deg)."""
    s = scene
    gains = np.array([1.0, 1.15, 0.9, 0.85, 1.1], np.float32)[:, None, None]
    images = s["images"] * gains

    def mean_error(normals):
        return float(np.mean(np.asarray(
            jaxps.angular_error(normals, s["normals"], mask=s["mask"]))[s["mask"]]))

    l2 = mean_error(jaxps.photometric_stereo(images, s["train"], mask=s["mask"]).normals)
    kw = dict(mask=s["mask"], method="mlp_ratio", iterations=2, key=jax.random.key(0),
              n_samples=10**6, max_steps=10)
    with_gains = mean_error(jaxps.brdf_photometric_stereo(images, s["train"], **kw).normals)
    without = mean_error(jaxps.brdf_photometric_stereo(images, s["train"], frame_gains=False,
                                                       **kw).normals)
    assert with_gains < 0.985 * l2 and with_gains < 0.99 * without, (with_gains, l2, without)


# --------------------------------------------------------------------------- bad input


def test_bad_input(scene):
    s = scene
    args = (s["images"], s["normals"], s["albedo"], s["train"])
    with pytest.raises(ValueError, match="horizon"):
        jaxps.fit_brdf(*args[:3], np.concatenate([s["train"][:4], [[0.0, 0.5, -0.2]]]))
    with pytest.raises(ValueError, match="mask is empty"):
        jaxps.fit_brdf(*args, mask=np.zeros_like(s["mask"]))
    with pytest.raises(ValueError, match="normals"):
        jaxps.fit_brdf(args[0], s["normals"][:-1], *args[2:])
    with pytest.raises(ValueError, match="albedo"):
        jaxps.fit_brdf(args[0], args[1], s["albedo"][:, :-1], args[3])
    with pytest.raises(ValueError, match="lights"):
        jaxps.fit_brdf(*args[:3], s["train"][:4])
    with pytest.raises(ValueError, match="method"):
        jaxps.fit_brdf(*args, method="phong")
    with pytest.raises(ValueError, match="images"):
        jaxps.fit_brdf(s["images"][0], *args[1:])
    with pytest.raises(ValueError, match="n_samples must be at least K"):
        jaxps.fit_brdf(*args, n_samples=2)
    model = jaxps.fit_brdf(*args, method="lambertian")
    with pytest.raises(ValueError, match="horizon"):
        jaxps.relight(model, s["normals"], s["albedo"], [0.0, 0.0, -1.0])
    with pytest.raises(ValueError, match="mask"):
        jaxps.relight(model, s["normals"], s["albedo"], s["train"], mask=s["mask"][1:])


def small_face():
    """A 24 x 20 Lambertian face under the five scanner lights: images, lights, normals,
    albedo, mask (numpy)."""
    sc = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(24, 20),
                                      jaxps.synthetic.scanner_lights(20.0))
    return tuple(np.asarray(x) for x in (sc.images, sc.lights, sc.normals, sc.albedo, sc.mask))


SMALL = {"n_samples": 600, "max_steps": 3, "key": 0}


@pytest.mark.parametrize("method", ["wrap_ggx", "mlp_ratio", "mlp", "lambertian", "delaunay"])
def test_bad_normals_and_albedo_are_dropped(method):
    """A NaN normal, a zero normal and (for the MLP on intensity, whose scale is the median
    albedo) a NaN albedo leave the fit exactly as if their pixels were outside the mask."""
    im, lights, normals, albedo, mask = small_face()
    bad = [(12, 10), (8, 6), (15, 12)] if method == "mlp" else [(12, 10), (8, 6)]
    assert all(mask[p] for p in bad)
    nn, aa = normals.copy(), albedo.copy()
    nn[bad[0]], nn[bad[1]] = np.nan, 0.0
    if method == "mlp":
        aa[bad[2]] = np.nan
    out = mask.copy()
    for p in bad:
        out[p] = False
    got = jaxps.fit_brdf(im, nn, aa, lights, mask=mask, method=method, **SMALL)
    want = jaxps.fit_brdf(im, nn, aa, lights, mask=out, method=method, **SMALL)
    assert np.isfinite(got.fit.mse) and got.fit.n_samples == want.fit.n_samples
    np.testing.assert_allclose(got.fit.mse, want.fit.mse, rtol=1e-6)
    relit = np.asarray(jaxps.relight(got, normals, albedo, lights, mask=mask))
    np.testing.assert_allclose(relit, np.asarray(jaxps.relight(want, normals, albedo, lights,
                                                               mask=mask)), rtol=1e-6)
    # the parametric model keeps the given (NaN) normal where it fitted none; else all finite
    assert np.isnan(relit).sum() == (len(lights) if method == "wrap_ggx" else 0)


def test_auto_information_criterion_leaves_out_bad_normals():
    """`method="auto"` scores every model on all frames by its BIC: a NaN normal's pixel is
    left out, as if outside the mask."""
    im, lights, normals, albedo, mask = small_face()
    nn, out = normals.copy(), mask.copy()
    nn[12, 10], out[12, 10] = np.nan, False
    got, want = (jaxps.fit_brdf(im, nn, albedo, lights, mask=m, method="auto", **SMALL)
                 for m in (mask, out))
    bic = got.fit.choice["bic"]
    assert set(bic) == {"lambertian", "mlp", "mlp_ratio"}
    for name, value in want.fit.choice["bic"].items():
        np.testing.assert_allclose(bic[name], value, rtol=1e-6, err_msg=name)


def test_bad_options():
    im, lights, normals, albedo, mask = small_face()
    args = (im, normals, albedo, lights)
    for name, value in (("support_deg", 0.0), ("support_deg", -5), ("max_steps", 0),
                        ("max_steps", -1), ("bound", -1), ("bound", float("nan")),
                        ("hidden", (0,)), ("min_count", -1)):
        with pytest.raises(ValueError, match=f"{name} must be"):
            jaxps.fit_brdf(*args, mask=mask, method="mlp", **{name: value})
    with pytest.raises(ValueError, match="albedo is not > 0 at any masked pixel"):
        jaxps.fit_brdf(im, normals, np.zeros_like(albedo), lights, mask=mask)


def test_score_relighting_leaves_out_bad_pixels_and_rejects_bad_input(scene, fitted):
    """A NaN normal and a NaN albedo: scored as if outside the mask. Integer images, an empty
    mask and a scale not > 0 are refused."""
    s = scene
    lights = jaxps.lights_from_angles([12.0, -12.0, 40.0], [10.0, -10.0, 5.0])
    obs = render_non_lambertian(s["normals"], s["albedo"], lights)
    nn, aa, out = s["normals"].copy(), s["albedo"].copy(), s["mask"].copy()
    nn[20, 20], aa[15, 22] = np.nan, np.nan
    assert s["mask"][20, 20] and s["mask"][15, 22]
    out[20, 20] = out[15, 22] = False
    model = fitted["mlp"]
    got = jaxps.score_relighting(model, obs, nn, aa, lights, mask=s["mask"])
    want = jaxps.score_relighting(model, obs, nn, aa, lights, mask=out)
    assert np.isfinite(got.model["raw_60"]) and np.isfinite(got.lambertian["gain_30"])
    for key in want.model:
        np.testing.assert_allclose(got.model[key], want.model[key], rtol=1e-6, err_msg=key)
        np.testing.assert_allclose(got.lambertian[key], want.lambertian[key], rtol=1e-6)
    np.testing.assert_allclose(got.gains["model"], want.gains["model"], rtol=1e-6)
    args = (s["normals"], s["albedo"], lights)
    with pytest.raises(ValueError, match="images must be a floating"):
        jaxps.score_relighting(model, (obs * 255).astype(np.uint8), *args)
    with pytest.raises(ValueError, match="mask is empty"):
        jaxps.score_relighting(model, obs, *args, mask=np.zeros_like(s["mask"]))
    for scale in (0, -1, float("nan")):
        with pytest.raises(ValueError, match="scale must be a positive"):
            jaxps.score_relighting(model, obs, *args, scale=scale)
    with pytest.raises(ValueError, match="no usable sample"):
        jaxps.score_relighting(model, np.full_like(obs, np.nan), *args, mask=s["mask"])


# --------------------------------------------------------------------------- command line


def yale_cross_args(data, subject):
    """`jaxps relight` arguments for a Yale B subject's five "cross" frames and its ambient."""
    folder = data / "yaleb" / subject
    names = ["A+000E+00", "A+000E+20", "A+000E-20", "A+025E+00", "A-025E+00"]
    frames = [str(folder / f"{subject}_P00{n}.pgm") for n in names]
    return ["relight", *frames, "--yale-names", "--ambient",
            str(folder / f"{subject}_P00_Ambient.pgm"), "--method", "lambertian"]


def test_cli_relight_yale(data, tmp_path):
    from PIL import Image

    from jaxps.cli import main

    args = yale_cross_args(data, "yaleB01")
    out = tmp_path / "relit"
    rc = main([*args, "--light=-35,15", "--circle-frames", "4", "--out", str(out)])
    assert rc == 0
    with Image.open(out / "relit_A-035E+15.png") as im:
        img = np.asarray(im)
    assert img.shape == (192, 168) and img.dtype == np.uint8
    # azimuth -35 lights the image's right side (Yale B convention)
    assert img[:, 100:].mean() > img[:, :68].mean() + 10
    with Image.open(out / "relight.gif") as gif:
        assert gif.n_frames == 4
    # no ambient, and an AZ,EL light without its elevation: a clear error, exit code 2
    assert main([*args[:6], "--yale-names", "--light", "35", "--out", str(out)]) == 2


def test_cli_relight_measures_the_flashes_on_a_reference_target(data, tmp_path, capsys):
    """`jaxps relight --intensity-mask`: yaleB01's cross frames with a matte card painted into
    a corner under flashes of known strength; relight.json reports them and the card."""
    import json

    from helpers import yale_frames_with_card
    from jaxps.cli import main

    args = yale_cross_args(data, "yaleB01")
    strength = np.array([1.0, 0.9, 1.1, 1.05, 0.95])
    frames, ambient, _, card = yale_frames_with_card(args[1:6], args[8], strength, tmp_path)
    out = tmp_path / "relit"
    assert main(["relight", *map(str, frames), "--yale-names", "--ambient", str(ambient),
                 "--method", "lambertian", "--circle-frames", "1",
                 "--intensity-mask", str(card), "--out", str(out)]) == 0
    got = json.loads((out / "relight.json").read_text())["intensities"]
    assert got["method"] == "frontal" and got["target"]["mask"] == str(card)
    assert "relight: flash strengths measured on the card: " + " ".join(
        f"{v:.3f}" for v in got["per_frame"]) in capsys.readouterr().out
    np.testing.assert_allclose(got["per_frame"], strength / np.exp(np.mean(np.log(strength))),
                               rtol=0.01)  # an 8-bit card


def test_cli_relight_default_is_wrap_ggx_and_beats_lambert_on_a_held_out_light(data, tmp_path):
    """`jaxps relight` without --method fits wrap_ggx; its image under a held-out light
    (-35, +15) is closer to the photograph than Lambert's (bench_relight.py has the rest)."""
    import json

    from PIL import Image

    from jaxps.cli import main

    args = [a for a in yale_cross_args(data, "yaleB01") if a not in ("--method", "lambertian")]
    imgs = {}
    for name, extra in (("default", []), ("lambertian", ["--method", "lambertian"])):
        out = tmp_path / name
        assert main([*args, *extra, "--light=-35,15", "--circle-frames", "2",
                     "--out", str(out)]) == 0
        with Image.open(out / "relit_A-035E+15.png") as im:
            imgs[name] = np.asarray(im, np.float64)
        summary = json.loads((out / "relight.json").read_text())
        assert summary["method"] == ("wrap_ggx" if name == "default" else "lambertian")
    folder = data / "yaleb" / "yaleB01"
    photo = jaxps.acquisition.read_image(folder / "yaleB01_P00A-035E+15.pgm") - jaxps.acquisition.read_image(
        folder / "yaleB01_P00_Ambient.pgm")
    # PNGs are scaled for display: compare up to the best gain each, over the lit face
    sel = photo > 0.05
    err = {}
    for name, img in imgs.items():
        p, o = img[sel], photo[sel]
        g = (p @ o) / (p @ p)
        err[name] = np.sqrt(np.mean((g * p - o) ** 2))
    assert err["default"] < err["lambertian"]


def test_cli_relight_drops_combed_frame(data, tmp_path, capsys):
    """yaleB02's +25,0 frame is interlace-combed (every other band of rows dark);
    `--check-quality` drops it and fits on the other four, and the report says so. The
    command shows its stages on a bar and times each in the report."""
    import json

    from jaxps.cli import main

    out = tmp_path / "relit"
    rc = main([*yale_cross_args(data, "yaleB02"), "--circle-frames", "2", "--check-quality",
               "--out", str(out)])
    assert rc == 0
    summary = json.loads((out / "relight.json").read_text())
    assert summary["dropped_frames"] == ["yaleB02_P00A+025E+00.pgm"]
    assert summary["dropped_why"]["yaleB02_P00A+025E+00.pgm"][0].startswith("row/interlace")
    assert len(summary["frames"]) == 4
    assert list(summary["timings_s"]) == ["load", "fit", "relight_and_write"]
    err = capsys.readouterr().err
    assert "load frames (1/3)" in err and "relight and write (3/3)" in err


def test_jaxtyping_annotations_hold(scene, fitted):
    from beartype import beartype
    from jaxtyping import jaxtyped

    s = scene
    feats = jaxtyped(typechecker=beartype)(jaxps.brdf_features)(s["normals"], s["train"])
    assert feats.shape == (5, 40, 40, 5)
    out = jaxtyped(typechecker=beartype)(jaxps.relight)(
        fitted["mlp"], s["normals"], s["albedo"], s["test"], mask=s["mask"])
    flag = jaxtyped(typechecker=beartype)(jaxps.extrapolation_mask)(
        fitted["mlp"], s["normals"], s["test"])
    assert out.shape == flag.shape == (4, 40, 40) and flag.dtype == bool


# --------------------------------------------------------------------------- held-out protocol


def score_numpy(pred, lambert, obs, mask, zenith, outside):
    """`RelightScore.model` and `.lambertian` by explicit loops over the held-out images
    (gray levels; gain-invariant: each image times its least-squares factor over the mask)."""
    out = []
    for p_all in (pred, lambert):
        figs = {}
        for kind in ("raw", "gain"):
            for limit in (30, 60):
                for part in ("", "_inside", "_outside"):
                    errs = []
                    for k in range(len(obs)):
                        if zenith[k] > limit:
                            continue
                        p, o = np.asarray(p_all[k], np.float64), np.asarray(obs[k], np.float64)
                        if kind == "gain":
                            p = p * (p[mask] @ o[mask]) / (p[mask] @ p[mask])
                        sel = mask & (~outside[k] if part == "_inside" else
                                      outside[k] if part == "_outside" else True)
                        errs.append(255 * (p - o)[sel])
                    e = np.concatenate(errs)
                    figs[f"{kind}_{limit}{part}"] = np.sqrt(np.mean(e**2)) if e.size else np.nan
        out.append(figs)
    return out


def test_score_relighting_matches_numpy(scene, fitted):
    """Every figure of `score_relighting` against the loops above, on the non-Lambertian scene
    with lights within 30, within 60 and beyond 60 degrees (not scored)."""
    s = scene
    az, el = [12.0, -12.0, 40.0, -45.0, 75.0], [10.0, -10.0, 5.0, -10.0, 0.0]
    lights = jaxps.lights_from_angles(az, el)
    zenith = np.degrees(np.arccos(np.asarray(lights)[:, 2]))
    obs = render_non_lambertian(s["normals"], s["albedo"], lights)
    model = fitted["mlp"]
    score = jaxps.score_relighting(model, obs, s["normals"], s["albedo"], lights, mask=s["mask"])
    pred = np.asarray(jaxps.relight(model, s["normals"], s["albedo"], lights))
    lam = np.asarray(jaxps.render_lambertian(s["normals"], s["albedo"], lights))
    outside = np.asarray(jaxps.extrapolation_mask(model, s["normals"], lights))
    want_model, want_lam = score_numpy(pred[:4], lam[:4], obs[:4], s["mask"], zenith[:4],
                                       outside[:4])
    assert score.lights == {"30": 2, "60": 4}
    assert 0 < score.outside_fraction["30"] < score.outside_fraction["60"] < 1
    for key, want in want_model.items():
        np.testing.assert_allclose(score.model[key], want, rtol=1e-4, err_msg=key)
        np.testing.assert_allclose(score.lambertian[key], want_lam[key], rtol=1e-4, err_msg=key)
        np.testing.assert_allclose(score.ratio[key], want / want_lam[key], rtol=1e-4)
    assert np.isnan(score.gains["model"][4]) and np.isfinite(score.gains["model"][:4]).all()


def test_score_relighting_exact_model_and_unknown_flash_strength(scene):
    """A model that is the truth scores 0; test images with flash gains g_k keep the raw error
    of the numpy computation, but 0 gain-invariant error, and the gains are recovered."""
    s = scene
    lights = jaxps.lights_from_angles([12.0, -12.0, 40.0], [10.0, -10.0, 5.0])
    train = np.asarray(jaxps.render_lambertian(s["normals"], s["albedo"], s["train"]))
    model = jaxps.fit_brdf(train, s["normals"], s["albedo"], s["train"], mask=s["mask"],
                           method="lambertian")
    truth = np.asarray(jaxps.render_lambertian(s["normals"], s["albedo"], lights), np.float64)
    exact = jaxps.score_relighting(model, truth, s["normals"], s["albedo"], lights,
                                   mask=s["mask"])
    assert max(exact.model.values()) < 1e-3  # gray levels; float32 rendering
    gains = np.array([1.1, 0.85, 1.2])
    scaled = jaxps.score_relighting(model, truth * gains[:, None, None], s["normals"],
                                    s["albedo"], lights, mask=s["mask"])
    d = ((1 - gains)[:, None, None] * truth)[:, s["mask"]] * 255
    np.testing.assert_allclose(scaled.model["raw_30"], np.sqrt(np.mean(d[:2] ** 2)), rtol=1e-4)
    np.testing.assert_allclose(scaled.model["raw_60"], np.sqrt(np.mean(d**2)), rtol=1e-4)
    assert scaled.model["gain_30"] < 1e-3 and scaled.model["gain_60"] < 1e-3
    np.testing.assert_allclose(scaled.gains["model"], gains, rtol=1e-5)
    with pytest.raises(ValueError, match="within 60"):
        jaxps.score_relighting(model, truth[:1], s["normals"], s["albedo"],
                               jaxps.lights_from_angles([70.0], [0.0]), mask=s["mask"])
    with pytest.raises(ValueError, match="frames"):
        jaxps.score_relighting(model, truth[:2], s["normals"], s["albedo"], lights)


# --------------------------------------------------------------------------- method="auto"


def test_auto_choice_rule_per_region():
    """`choose_regions` on hand-made folds: the candidate beats Lambert in every fold on the
    left half of the mask and loses on the right half, so with 2 x 2 regions it is kept on the
    left only; with a margin the folds' spread cannot clear, and with one region (the gains and
    losses cancel), it is Lambert."""
    from jaxps.reflectance._auto import choose_regions, region_labels

    mask = np.zeros((8, 10), bool)
    mask[1:7, 2:10] = True
    labels = region_labels(mask, 2)
    assert labels[1, 2] == 0 and labels[1, 9] == 1 and labels[6, 2] == 2 and labels[0, 0] == -1
    rng = np.random.default_rng(0)
    left = np.zeros_like(mask)
    left[:, :6] = True
    folds = []
    for j in range(5):
        obs = rng.normal(size=mask.shape)
        lam = obs + 1.0
        better = 0.5 + 0.05 * j  # |error| 0.5-0.7 on the left, 1.5-1.7 on the right
        cand = np.where(left, obs + better, obs + 1 + better)
        folds.append((j, obs, mask.copy(), lam, {"mlp": cand}))
    name, gate, report = choose_regions(folds, mask, regions=2, margin=1.0)
    assert name == "mlp" and report["kept_cells"]["mlp"] == [0, 2]
    np.testing.assert_array_equal(gate, (left & mask).astype(float))
    assert report["gate_fraction"] == pytest.approx(0.5)
    name, gate, report = choose_regions(folds, mask, regions=1, margin=1.0)
    assert name == "lambertian" and gate is None and "no candidate" in report["reason"]
    assert choose_regions(folds[:1], mask, regions=2, margin=0.0)[0] == "lambertian"
    # the information criterion: necessary, not sufficient
    name, _, report = choose_regions(folds, mask, regions=2, margin=1.0,
                                     bics={"lambertian": 10.0, "mlp": 9.0})
    assert name == "mlp" and report["bic_rejected"] == [] and report["bic"]["mlp"] == 9.0
    name, gate, report = choose_regions(folds, mask, regions=2, margin=1.0,
                                        bics={"lambertian": 10.0, "mlp": 10.0})
    assert name == "lambertian" and gate is None and report["bic_rejected"] == ["mlp"]
    assert "not below: mlp" in report["reason"]


def test_bic_against_numpy():
    from jaxps.reflectance._auto import bic

    rng = np.random.default_rng(1)
    obs, pred = rng.normal(size=(3, 4, 5)), rng.normal(size=(3, 4, 5))
    valid = rng.random((3, 4, 5)) > 0.3
    n = valid.sum()
    rss = np.sum((pred - obs)[valid] ** 2)
    assert bic(pred, obs, valid, 7) == pytest.approx(n * np.log(rss / n) + 7 * np.log(n))


def test_auto_keeps_reflectance_and_drops_frame_gains(scene):
    """`method="auto"` with its defaults keeps a candidate on the non-Lambertian scene (better
    than Lambert on held-out lights) and returns Lambert's law when the only departure from it is a brightness
    per frame; the gate renders L + gate (M - L); K = 4 frames give Lambert's law."""
    s = scene
    gains = np.array([1.0, 1.15, 0.9, 0.85, 1.1], np.float32)[:, None, None]
    lam_train = np.asarray(jaxps.render_lambertian(s["normals"], s["albedo"], s["train"]))
    lam_test = np.asarray(jaxps.render_lambertian(s["normals"], s["albedo"], s["test"]))
    # the default settings (one region, 3 standard errors), chosen on Yale B where they give
    # Lambert's law, still keep a real departure from it
    kw = dict(mask=s["mask"], method="auto", candidates=("mlp_ratio",), key=jax.random.key(0),
              **FAST)
    ps = jaxps.photometric_stereo(s["images"], s["train"], mask=s["mask"])
    model = jaxps.fit_brdf(s["images"], ps.normals, ps.albedo, s["train"], **kw)
    choice = model.fit.choice
    assert model.method == "mlp_ratio" and choice["choice"] == "mlp_ratio", choice
    assert choice["gated_lolo_rmse"]["mlp_ratio"] < choice["lolo_rmse"]["lambertian"]
    assert model.fit.message.startswith("auto: mlp_ratio beat")
    # the network's weights (5-10-10-1) and four free frame gains; its BIC below Lambert's,
    # whose own is n ln(RSS / n) over the usable training samples
    assert model.fit.n_params == (5 * 10 + 10) + (10 * 10 + 10) + (10 + 1) + 4
    assert choice["bic"]["mlp_ratio"] < choice["bic"]["lambertian"]
    lam = np.asarray(jaxps.render_lambertian(ps.normals, ps.albedo, s["train"]), np.float64)
    obs = np.asarray(s["images"], np.float64)
    valid = s["mask"][None] & (obs < 1) & (np.asarray(ps.albedo) > 0)[None]
    n = valid.sum()
    rss = np.sum((lam - obs)[valid] ** 2)
    assert choice["bic"]["lambertian"] == pytest.approx(n * np.log(rss / n), rel=1e-5)
    # an interpolant of every training sample (one parameter each) never pays for itself
    interp = jaxps.fit_brdf(s["images"], ps.normals, ps.albedo, s["train"], mask=s["mask"],
                            method="auto", candidates=("delaunay",), **FAST)
    assert interp.fit.choice["bic_rejected"] == ["delaunay"], interp.fit.choice
    assert interp.method == "lambertian"
    # a parametric candidate gets the caller's `region` and `refine_normals`
    from jaxps.reflectance._auto import bic

    kw_p = dict(mask=s["mask"], region=None, refine_normals=False, **FAST)
    auto = jaxps.fit_brdf(s["images"], ps.normals, ps.albedo, s["train"], method="auto",
                          candidates=("wrap_ggx",), **kw_p)
    direct = jaxps.fit_brdf(s["images"], ps.normals, ps.albedo, s["train"], method="wrap_ggx",
                            **kw_p)
    pred = np.asarray(jaxps.relight(direct, ps.normals, ps.albedo, s["train"]), np.float64)
    pred *= np.asarray(direct.fit.frame_gains)[:, None, None]
    assert direct.fit.n_params == 2 + 1 + 4  # one specular albedo: region=None
    assert auto.fit.choice["bic"]["wrap_ggx"] == pytest.approx(
        bic(pred, obs, valid, direct.fit.n_params), rel=1e-6)
    score = jaxps.score_relighting(model, s["truth"], ps.normals, ps.albedo, s["test"],
                                   mask=s["mask"])
    assert score.ratio["raw_30"] < 0.9, score.ratio
    # the gate: Lambert's law where it is 0, the model where it is 1
    gate = np.zeros(s["mask"].shape, np.float32)
    gate[:20] = 1.0
    gated = jaxps.relight(dataclasses.replace(model, gate=jnp.asarray(gate)), ps.normals,
                          ps.albedo, s["test"])
    full = np.asarray(jaxps.relight(dataclasses.replace(model, gate=None), ps.normals,
                                    ps.albedo, s["test"]))
    lam = np.asarray(jaxps.render_lambertian(ps.normals, ps.albedo, s["test"]))
    np.testing.assert_allclose(gated, np.where(gate > 0, full, lam), atol=1e-6)

    ps = jaxps.photometric_stereo(lam_train * gains, s["train"], mask=s["mask"])
    flat = jaxps.fit_brdf(lam_train * gains, ps.normals, ps.albedo, s["train"], **kw)
    assert flat.method == "lambertian" and flat.gate is None, flat.fit.choice
    assert "no candidate" in flat.fit.choice["reason"]
    score = jaxps.score_relighting(flat, lam_test, ps.normals, ps.albedo, s["test"],
                                   mask=s["mask"])
    assert score.ratio["raw_30"] == pytest.approx(1.0)
    four = jaxps.fit_brdf(s["images"][:4], s["normals"], s["albedo"], s["train"][:4], **kw)
    assert four.method == "lambertian" and "at least 2" in four.fit.choice["reason"]
    with pytest.raises(ValueError, match="candidates"):
        jaxps.fit_brdf(s["images"], s["normals"], s["albedo"], s["train"], method="auto",
                       candidates=("auto",))


def test_auto_on_yale_falls_back_to_lambert(data):
    """yaleB01, the scanner's five lights: with its default settings `method="auto"` finds no
    candidate that predicts the left-out training lights by 3 standard errors better than
    Lambert's law, so it is Lambert's law, and `score_relighting` says so (ratio 1) on the
    clean held-out lights within 30 degrees; Lambert's raw error there against numpy."""
    import cv2

    folder = data / "yaleb" / "yaleB01"
    ambient = cv2.imread(str(folder / "yaleB01_P00_Ambient.pgm"), cv2.IMREAD_UNCHANGED)

    def load(names):
        return np.stack([(cv2.imread(str(folder / f"yaleB01_P00{n}.pgm"),
                                     cv2.IMREAD_UNCHANGED).astype(np.float32)
                          - ambient.astype(np.float32)) / 255 for n in names])

    train = ["A+000E+00", "A+000E+20", "A+000E-20", "A+025E+00", "A-025E+00"]
    test = ["A+005E+10", "A-010E+00", "A+010E-20", "A-020E+10", "A+015E+20"]
    angles = np.array([jaxps.parse_yale_name(f"yaleB01_P00{n}.pgm") for n in train + test])
    lights = jaxps.lights_from_angles(angles[:, 0], angles[:, 1])
    images = load(train)
    ps = jaxps.photometric_stereo(images, lights[:5])
    mask = (np.asarray(ps.status) == 0) & (np.min(images, axis=0) >= 10 / 255)
    model = jaxps.fit_brdf(images, ps.normals, ps.albedo, lights[:5], mask=mask, method="auto",
                           n_samples=5_000, max_steps=8, key=0)
    choice = model.fit.choice
    assert model.method == "lambertian" and model.gate is None, choice
    assert set(choice["lolo_rmse"]) == {"lambertian", "mlp", "mlp_ratio"}
    assert choice["folds"] == [0, 1, 2, 3, 4] and "3 standard errors" in choice["reason"]
    obs = load(test)
    score = jaxps.score_relighting(model, obs, ps.normals, ps.albedo, lights[5:], mask=mask)
    assert score.lights == {"30": 5, "60": 5}
    assert score.ratio["raw_30"] == 1.0 and score.ratio["gain_30"] == 1.0
    lam = np.asarray(ps.albedo)[None] * np.maximum(
        np.einsum("hwc,kc->khw", np.asarray(ps.normals, np.float64), lights[5:]), 0)
    want = np.sqrt(np.mean((255 * (lam - obs))[:, mask] ** 2))
    np.testing.assert_allclose(score.lambertian["raw_30"], want, rtol=1e-4)
    assert 5 < want < 40  # gray levels: a real error, not a degenerate one


# ------------------------------------------------------------------------ near lamps (per pixel)


def test_fit_brdf_per_pixel_lights_equal_shared_ones_when_broadcast(scene):
    """`(K, H, W, 3)` lights that repeat the `(K, 3)` ones at every pixel give the same fit and
    the same relit image, for a closed form, an MLP and the default parametric model (whose
    per-pixel normal refinement maps each pixel's lights)."""
    images, normals, albedo, lights, mask = (scene[k] for k in
                                             ("images", "normals", "albedo", "train", "mask"))
    lights = np.asarray(lights, np.float32)
    per_pixel = np.broadcast_to(lights[:, None, None], (*lights.shape[:1], *albedo.shape, 3))
    new = jaxps.lights_from_angles([30.0], [10.0])
    new_per_pixel = np.broadcast_to(np.asarray(new, np.float32)[:, None, None],
                                    (1, *albedo.shape, 3))
    models = {}
    for method in ("lambertian", "mlp_ratio", "wrap_ggx", "delaunay"):
        kw = dict(mask=mask, method=method, max_steps=5, n_samples=5000)
        a = models[method] = jaxps.fit_brdf(images, normals, albedo, lights, **kw)
        b = jaxps.fit_brdf(images, normals, albedo, per_pixel, **kw)
        assert (a.fit.steps, a.fit.rmse) == (b.fit.steps, b.fit.rmse), method
        want = np.asarray(jaxps.relight(a, normals, albedo, new, mask=mask))
        np.testing.assert_array_equal(
            np.asarray(jaxps.relight(b, normals, albedo, new, mask=mask)), want)
        # relight and extrapolation_mask take per-pixel lights too
        np.testing.assert_allclose(
            np.asarray(jaxps.relight(a, normals, albedo, new_per_pixel, mask=mask)), want,
            atol=1e-6, err_msg=method)
        np.testing.assert_array_equal(
            np.asarray(jaxps.extrapolation_mask(a, normals, new_per_pixel)),
            np.asarray(jaxps.extrapolation_mask(a, normals, new)))
    # the leave-one-light-out choices: the same folds, choice and correction
    for kw in (dict(method="auto", candidates=("mlp_ratio",)),
               dict(method="mlp_ratio", shrink="loo")):
        kw.update(mask=mask, max_steps=3, n_samples=3000)
        a = jaxps.fit_brdf(images, normals, albedo, lights, **kw)
        b = jaxps.fit_brdf(images, normals, albedo, per_pixel, **kw)
        assert (a.fit.message, a.fit.rmse, a.fit.shrink) == (b.fit.message, b.fit.rmse,
                                                             b.fit.shrink), kw
        np.testing.assert_allclose(np.asarray(jaxps.relight(b, normals, albedo, new)),
                                   np.asarray(jaxps.relight(a, normals, albedo, new)), atol=1e-6)
    mlp = models["mlp_ratio"]  # the jitted kernel, traced with per-pixel lights
    traced = jax.jit(lambda l: jaxps.relight(mlp, normals, albedo, l))(new_per_pixel)
    np.testing.assert_allclose(np.asarray(traced),
                               np.asarray(jaxps.relight(mlp, normals, albedo, new)), atol=1e-6)
    np.testing.assert_allclose(np.asarray(jaxps.brdf_features(normals, per_pixel)),
                               np.asarray(jaxps.brdf_features(normals, lights)), atol=1e-6)


def test_fit_brdf_with_near_lamps_recovers_the_wrap_parameter():
    """Frames of a wrap-lit face (w = 0.3) under lamps 1 m away, fall-off divided out: with
    each pixel's own light directions the fit recovers w and the relit image exactly; with
    the lamps' directions from the origin, as distant lights, it does not (not the shared
    data; true normals and albedo given)."""
    from helpers import near_face

    normals, inside, directions, _, lights = near_face()
    albedo = np.full(inside.shape, 0.6)
    wrap = 0.3
    shade = lambda cos: np.maximum((cos + wrap) / (1 + wrap), 0)
    images = albedo * shade(np.einsum("khwc,hwc->khw", directions, normals))
    new = np.asarray(jaxps.lights_from_angles([30.0], [10.0]), np.float64)
    truth = albedo * shade(normals @ new[0])
    f32 = lambda a: np.asarray(a, np.float32)
    got = {}
    for name, l in (("per_pixel", directions), ("distant", lights)):
        model = jaxps.fit_brdf(f32(images), f32(normals), f32(albedo), f32(l), mask=inside,
                               method="wrap", refine_normals=False, frame_gains=False)
        relit = np.asarray(jaxps.relight(model, f32(normals), f32(albedo), new))[0]
        got[name] = (float(model.params.shape[0]), model.fit.rmse,
                     float(np.sqrt(np.mean((relit - truth)[inside] ** 2))))
        if name == "per_pixel":  # the training frames, re-rendered under the lamps
            again = np.asarray(jaxps.relight(model, f32(normals), f32(albedo), f32(l)))
            np.testing.assert_allclose(again[:, inside], images[:, inside], atol=1e-5)
    print(got)  # (w, fit RMSE, relit RMS) each: `pytest -s -n 0 -k near_lamps_recovers`
    # measured: w 0.3000, fit RMSE 4e-8, relit RMS 4e-8 per pixel; w 0.2245, 0.0025, 0.018
    # from the origin's directions
    assert abs(got["per_pixel"][0] - wrap) < 1e-3 and got["per_pixel"][2] < 1e-4, got
    assert abs(got["distant"][0] - wrap) > 0.05 and got["distant"][2] > 0.01, got


def test_score_relighting_with_near_lamps():
    """Held-out frames of a wrap-lit face (w = 0.3) under lamps 1 m away, fall-off divided
    out, scored with each pixel's own directions: the model fitted on the other frames with
    those directions predicts them (raw error ~0, far below Lambert's), and the same lights
    broadcast from `(K, 3)` score exactly as `(K, 3)` (not the shared data)."""
    from helpers import near_face

    normals, inside, directions, _, lights = near_face()
    albedo = np.full(inside.shape, 0.6)
    shade = lambda cos: np.maximum((cos + 0.3) / 1.3, 0)
    images = albedo * shade(np.einsum("khwc,hwc->khw", directions, normals))
    f32 = lambda a: np.asarray(a, np.float32)
    train, test = [0, 1, 2, 3], [4]  # (0, -20) held out
    model = jaxps.fit_brdf(f32(images[train]), f32(normals), f32(albedo),
                           f32(directions[train]), mask=inside, method="wrap",
                           refine_normals=False, frame_gains=False)
    score = jaxps.score_relighting(model, images[test], normals, albedo, directions[test],
                                   mask=inside)
    print(score.model["raw_30"], score.lambertian["raw_30"])  # pytest -s -n 0 -k near_lamps
    # measured: 1.1e-5 gray levels, against 12.3 for Lambert's law
    assert score.model["raw_30"] < 1e-3 and score.lambertian["raw_30"] > 1.0, score.model
    assert score.lights == {"30": 1, "60": 1}
    # its light's angle is the mean direction's: a lamp 80 degrees off the axis at the centre
    # is not scored even where some pixels see it within 60 degrees
    far = directions[test].copy()
    far[..., :] = jaxps.lights_from_angles([80.0], [0.0])[0]
    far[:, :, :8] = (0.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="no held-out light within 60 degrees"):
        jaxps.score_relighting(model, images[test], normals, albedo, far, mask=inside)
    # per-pixel lights that are the same at every pixel score as distant ones
    k, (h, w) = 2, inside.shape
    same = np.broadcast_to(lights[2:4, None, None], (k, h, w, 3))
    a = jaxps.score_relighting(model, images[2:4], normals, albedo, lights[2:4], mask=inside)
    b = jaxps.score_relighting(model, images[2:4], normals, albedo, same, mask=inside)
    assert a.model == b.model and a.lambertian == b.lambertian and a.lights == b.lights


def test_score_relighting_takes_one_light_as_a_3_vector():
    """One held-out frame with its light as a `(3,)` vector (the code before indexed the
    caller's `(3,)` array with a `(1,)` mask and raised an IndexError): a flat Lambertian
    patch scores 0 under its own light (not the shared data)."""
    h = w = 24
    normals = np.zeros((h, w, 3), np.float32)
    normals[..., 2] = 1
    albedo = np.full((h, w), 0.5, np.float32)
    lights = jaxps.lights_from_angles([0, 25, -25, 0, 0], [0, 0, 0, 20, -20])
    images = np.asarray(jaxps.render_lambertian(normals, albedo, lights), np.float32)
    model = jaxps.fit_brdf(images, normals, albedo, lights, method="lambertian")
    score = jaxps.score_relighting(model, images[3:4], normals, albedo, np.asarray(lights)[3])
    assert score.lights == {"30": 1, "60": 1}
    assert score.model["raw_30"] < 1e-4 and score.lambertian["raw_30"] < 1e-4


def test_fit_brdf_per_pixel_lights_bad_input(scene):
    images, normals, albedo, lights, mask = (scene[k] for k in
                                             ("images", "normals", "albedo", "train", "mask"))
    k, (h, w) = len(lights), albedo.shape
    per_pixel = np.broadcast_to(np.asarray(lights, np.float32)[:, None, None], (k, h, w, 3))
    with pytest.raises(ValueError, match=r"per-pixel lights must be \(K, H, W, 3\)"):
        jaxps.fit_brdf(images, normals, albedo, per_pixel[:, :-1], mask=mask)
    below = per_pixel.copy()
    below[2, 0, 0] = (0.5, 0.0, -0.1)
    with pytest.raises(ValueError, match=r"lights \[2\] are at or below the horizon"):
        jaxps.fit_brdf(images, normals, albedo, below, mask=mask)
    nan = per_pixel.copy()
    nan[1, 3, 3, 0] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        jaxps.fit_brdf(images, normals, albedo, nan, mask=mask)
    with pytest.raises(ValueError, match=r"lights must be \(K, 3\) or \(K, H, W, 3\)"):
        jaxps.brdf_features(normals, per_pixel[:, :, :-1])


def test_cli_relight_with_near_light_positions(tmp_path):
    """`jaxps relight --light-positions --pixel-size`: a Lambertian face lit by lamps 1 m away
    (16-bit PNGs) relit under a distant (30, 10) light. With the lamps' positions the relit
    image matches the truth to the 8-bit PNG's rounding; with their directions from the origin
    as `--lights` it does not (not the shared data)."""
    import json

    import cv2
    from helpers import near_face_files

    from jaxps.cli import main

    px = 2.0
    normals, inside, _, _, _ = near_face_files(tmp_path, px)
    new = np.asarray(jaxps.lights_from_angles([30.0], [10.0]), np.float64)[0]
    truth = 0.6 * np.maximum(normals @ new, 0)
    base = ["relight", str(tmp_path / "face"), "--mask", str(tmp_path / "mask.png"),
            "--no-register", "--light=30,10", "--circle-frames", "1"]
    near = ["--light-positions", str(tmp_path / "positions.txt"), "--pixel-size", str(px)]
    rms = {}
    for name, extra in (("distant", ["--lights", str(tmp_path / "lights.txt"), "--method",
                                     "lambertian"]),
                        ("near", [*near, "--method", "lambertian"]),
                        ("near_default", near)):
        assert main([*base, *extra, "--out", str(tmp_path / name)]) == 0
        summary = json.loads((tmp_path / name / "relight.json").read_text())
        relit = cv2.imread(str(tmp_path / name / "relit_A+030E+10.png"), cv2.IMREAD_UNCHANGED)
        got = relit / 255.0 * summary["png_scale"]
        rms[name] = float(np.sqrt(np.mean((got - truth)[inside] ** 2)))
        if name != "distant":
            assert summary["near_lights"]["converged"], summary["near_lights"]
    print(rms)  # `pytest -s -n 0 -k cli_relight_with_near`
    # measured: 0.030 from the origin's directions, 0.0010 with the lamps (lambertian) and
    # 0.0008 (the default wrap_ggx); one 8-bit step is about 0.0024 here
    assert rms["near"] < 0.003 and rms["near_default"] < 0.003 and rms["distant"] > 0.015, rms


def test_cli_relight_near_lamps_with_face_crop(tmp_path, monkeypatch):
    """`jaxps relight --crop-face` with near lamps: the relit image is of the crop, the lamps
    stay measured from the frame's centre (`"centre_px"`), and the crop relights the face as
    the whole frame does. The face sits off the camera axis in a larger frame; the face
    detector is replaced by its box (not the shared data)."""
    import json

    import cv2
    from helpers import off_centre_face_files

    from jaxps.acquisition import _capture
    from jaxps.cli import main

    px = 2.0
    normals, full_mask, (h0, w0), (top, left, h, w) = off_centre_face_files(tmp_path, px)
    monkeypatch.setattr(_capture, "detect_face", lambda image: (top, left, h, w))
    new = np.asarray(jaxps.lights_from_angles([30.0], [10.0]), np.float64)[0]
    truth = np.zeros((h0, w0))
    truth[top:top + h, left:left + w] = 0.6 * np.maximum(normals @ new, 0)
    rms = {}
    # "none": the rendered flashes are equal, so no strength estimate is needed
    for name, extra in (("crop", ["--crop-face"]), ("whole", []),
                        ("crop_none", ["--crop-face", "--intensities", "none"])):
        assert main(["relight", str(tmp_path / "face"), "--mask", str(tmp_path / "mask.png"),
                     "--no-register", *extra, "--light-positions",
                     str(tmp_path / "positions.txt"), "--pixel-size", str(px), "--light=30,10",
                     "--method", "lambertian", "--circle-frames", "1", "--out",
                     str(tmp_path / name)]) == 0
        summary = json.loads((tmp_path / name / "relight.json").read_text())
        relit = cv2.imread(str(tmp_path / name / "relit_A+030E+10.png"), cv2.IMREAD_UNCHANGED)
        t, l, ch, cw = summary["crop"] or (0, 0, h0, w0)
        assert relit.shape == (ch, cw)
        if name != "whole":
            assert (ch, cw) != (h0, w0) and t <= top and l <= left
            np.testing.assert_allclose(summary["near_lights"]["centre_px"],
                                       [(h0 - 1) / 2 - t, (w0 - 1) / 2 - l])
        err = relit / 255.0 * summary["png_scale"] - truth[t:t + ch, l:l + cw]
        rms[name] = float(np.sqrt(np.mean(err[full_mask[t:t + ch, l:l + cw]] ** 2)))
    print(rms)  # `pytest -s -n 0 -k relight_near_lamps_with_face_crop`
    # measured: 0.0030 (crop), 0.0030 (whole), 0.0007 (crop, --intensities none): what the
    # default frontal strengths leave on this off-axis face (0.63 deg in the normals,
    # tests/test_cli.py's face-crop test)
    assert rms["crop"] < 0.005 and abs(rms["crop"] - rms["whole"]) < 0.001, rms
    assert rms["crop_none"] < 0.0015, rms
