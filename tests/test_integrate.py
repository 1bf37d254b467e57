import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import face_scene

import jaxps


def periodic_surface(h=64, w=80):
    """z = 3 sin(2 pi x / W) cos(4 pi y / H) + sin(2 pi y / H): exactly periodic, band-limited."""
    x = np.arange(w)[None, :] * np.ones((h, 1))
    y = -np.arange(h)[:, None] * np.ones((1, w))  # y up: one row down is -1 in y
    ax, ay = 2 * np.pi / w, 2 * np.pi / h
    z = 3 * np.sin(ax * x) * np.cos(2 * ay * y) + np.sin(ay * y)
    p = 3 * ax * np.cos(ax * x) * np.cos(2 * ay * y)
    q = -6 * ay * np.sin(ax * x) * np.sin(2 * ay * y) + ay * np.cos(ay * y)
    n = np.stack([-p, -q, np.ones_like(p)], -1)
    return z, (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def test_fc_recovers_integrable_surface_up_to_offset():
    z, n = periodic_surface()
    rec = np.asarray(jaxps.integrate(n))
    assert rec.dtype == np.float32
    np.testing.assert_allclose(rec - rec.mean(), z - z.mean(), atol=2e-4)


def test_fc_pixel_size_scales_height():
    z, n = periodic_surface()
    a = np.asarray(jaxps.integrate(n))
    b = np.asarray(jaxps.integrate(n, pixel_size=0.5))
    np.testing.assert_allclose(b, 0.5 * a, rtol=1e-5, atol=1e-6)


def test_fc_face_and_mask_mean_zero():
    s = jaxps.synthetic.face_like(96)
    z = np.asarray(jaxps.integrate(s.normals, mask=s.mask))
    m = np.asarray(s.mask)
    truth = np.asarray(s.height)
    assert abs(z[m].mean()) < 1e-3
    err = (z - truth)[m] - (z - truth)[m].mean()
    # Non-periodic relief inside a flat (zero-gradient) surround: small but not exact.
    assert np.sqrt(np.mean(err**2)) < 0.02 * np.ptp(truth[m])


def test_normals_from_height_of_plane_and_roundtrip():
    h, w = 20, 30
    x = np.arange(w)[None, :] * np.ones((h, 1))
    y = -np.arange(h)[:, None] * np.ones((1, w))
    z = 0.3 * x - 0.2 * y  # p = 0.3, q = -0.2
    n = np.asarray(jaxps.normals_from_height(z.astype(np.float32)))
    expected = np.array([-0.3, 0.2, 1.0]) / np.linalg.norm([-0.3, 0.2, 1.0])
    np.testing.assert_allclose(n, np.broadcast_to(expected, n.shape), atol=1e-6)
    zp, n_smooth = periodic_surface(128, 128)
    back = np.asarray(jaxps.normals_from_height(zp.astype(np.float32)))
    err = np.asarray(jaxps.angular_error(back, n_smooth))[1:-1, 1:-1]
    assert err.max() < 0.2  # central differences on a smooth surface


def test_normals_from_height_masked_matches_numpy():
    """The documented rule: central differences where both neighbours are in the mask, one-sided
    where one is, slope 0 where neither is; (0, 0, 1) outside the mask."""
    rng = np.random.default_rng(4)
    h, w = 23, 31
    z = rng.normal(size=(h, w))
    mask = rng.uniform(size=(h, w)) > 0.3
    pixel_size = 0.7

    def derivative(axis):
        zt, mt = np.moveaxis(z, axis, 0), np.moveaxis(mask, axis, 0)
        d = np.zeros_like(zt)
        for i in range(zt.shape[0]):
            fwd = i + 1 < zt.shape[0] and mt[i + 1] & mt[i]
            bwd = i > 0 and mt[i - 1] & mt[i]
            up = zt[i + 1] - zt[i] if i + 1 < zt.shape[0] else 0
            down = zt[i] - zt[i - 1] if i > 0 else 0
            d[i] = np.where(fwd & bwd, (up + down) / 2, np.where(fwd, up, np.where(bwd, down, 0)))
        return np.moveaxis(d, 0, axis)

    p, q = derivative(1) / pixel_size, -derivative(0) / pixel_size
    n = np.stack([-p, -q, np.ones_like(p)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[~mask] = [0, 0, 1]
    got = np.asarray(jaxps.normals_from_height(z.astype(np.float32), mask=mask,
                                               pixel_size=pixel_size))
    np.testing.assert_allclose(got, n, rtol=0, atol=2e-6)
    assert np.any(np.abs(derivative(1))[mask] == 0)  # some pixels have no neighbour in a row


def test_nan_normals_give_finite_height():
    _, n = periodic_surface()
    n = n.copy()
    n[5, 5] = np.nan
    z = np.asarray(jaxps.integrate(n))
    assert np.all(np.isfinite(z))


def test_float64_kept():
    _, n = periodic_surface()
    with jax.enable_x64(True):
        z = jaxps.integrate(n.astype(np.float64))
        assert z.dtype == jnp.float64


@pytest.mark.parametrize(
    "normals, kwargs, match",
    [
        (np.zeros((4, 4, 2), np.float32), {}, r"\(H, W, 3\)"),
        (np.zeros((0, 4, 3), np.float32), {}, "at least one pixel"),
        (np.zeros((4, 4, 3), np.int32), {}, "floating point"),
        (np.zeros((4, 4, 3), np.float32), {"mask": np.ones((3, 4), bool)}, "mask must have"),
        (np.zeros((4, 4, 3), np.float32), {"mask": np.zeros((4, 4), bool)}, "mask is empty"),
        (np.zeros((4, 4, 3), np.float32), {"method": "nope"}, "method must be one of"),
        (np.zeros((4, 4, 3), np.float32), {"pixel_size": 0.0}, "pixel_size"),
        (np.zeros((4, 4, 3), np.float32), {"cg_preconditioner": "ilu"}, "cg_preconditioner"),
    ],
)
def test_bad_input(normals, kwargs, match):
    with pytest.raises(ValueError, match=match):
        jaxps.integrate(normals, **kwargs)


def test_normals_from_height_bad_input():
    with pytest.raises(ValueError, match="2-D height map"):
        jaxps.normals_from_height(np.zeros((3, 3, 1), np.float32))
    for size in (0.0, -1.0, float("nan")):  # were NaN normals, or x and y flipped
        with pytest.raises(ValueError, match="pixel_size must be positive and finite"):
            jaxps.normals_from_height(np.zeros((4, 4), np.float32), pixel_size=size)


def test_gradients_from_normals_checks_its_input_and_takes_none_for_every_pixel():
    _, n = periodic_surface()
    n = np.asarray(n, np.float32)
    p, q = jaxps.gradients_from_normals(n, None)  # None failed inside the jitted kernel
    nz = np.maximum(n[..., 2], 0.05)
    np.testing.assert_allclose(p, -n[..., 0] / nz, rtol=1e-6)
    np.testing.assert_allclose(q, -n[..., 1] / nz, rtol=1e-6)
    h, w = n.shape[:2]
    for bad, match in ((n[..., :2], r"normals must be \(H, W, 3\)"),  # was garbage gradients
                       (np.moveaxis(n, -1, 0), r"normals must be \(H, W, 3\)"),
                       (n.astype(np.int32), "floating point")):
        with pytest.raises(ValueError, match=match):
            jaxps.gradients_from_normals(bad, None)
    with pytest.raises(ValueError, match=rf"mask must have shape \(H, W\) = \({h}, {w}\)"):
        jaxps.gradients_from_normals(n, np.ones((w + 1, h), bool))


def test_normals_from_height_keeps_holes_local():
    """A NaN height is a pixel with no data: it gets (0, 0, 1), and its neighbours take the
    one-sided differences that an explicit mask without it gives (it used to make its four
    neighbours NaN, with or without a mask)."""
    rng = np.random.default_rng(5)
    z = rng.normal(size=(17, 19)).astype(np.float32)
    holes = np.zeros(z.shape, bool)
    holes[8, 9] = holes[0, 3] = True
    with_nan = np.where(holes, np.nan, z)
    expected = np.asarray(jaxps.normals_from_height(z, mask=~holes, pixel_size=0.5))
    for mask in (None, np.ones(z.shape, bool)):
        got = np.asarray(jaxps.normals_from_height(with_nan, mask=mask, pixel_size=0.5))
        np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(expected[holes], [[0, 0, 1], [0, 0, 1]])
    # without holes the unmasked path is the plain central difference
    np.testing.assert_allclose(np.asarray(jaxps.normals_from_height(z, pixel_size=0.5)),
                               np.asarray(jaxps.normals_from_height(z, mask=np.ones(z.shape, bool),
                                                                    pixel_size=0.5)), atol=1e-6)


K_CAMERA = np.array([[90.0, 0.0, 30.5], [0.0, 95.0, 27.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("case", ["fc", "dct", "fc-info", "dct-perspective", "fc-perspective"])
def test_fft_methods_trace_under_jit_vmap_and_grad(case):
    """"fc" and "dct" run inside `jit` and `vmap` (nothing counted or checked on the host) and
    give the heights of the eager call, whose masked mean and valid count are taken on the
    host; gradients under `jit` equal the eager ones."""
    method, _, variant = case.partition("-")
    options = {"method": method}
    if variant == "perspective":
        options["intrinsics"] = K_CAMERA
    info = variant == "info"
    face = jaxps.synthetic.face_like(56, 64)
    rng = np.random.default_rng(0)
    noisy = np.asarray(face.normals) + 0.05 * rng.standard_normal((56, 64, 3))
    normals = np.stack([face.normals, noisy]).astype(np.float32)
    normals[0, 3, :5] = np.nan  # left out of the valid count and the mean
    normals[1, 30, 30] = 0.0
    masks = np.stack([face.mask, np.ones((56, 64), bool)])
    masks[1, :, :8] = False

    def height(n, m, pixel_size=0.5):
        out = jaxps.integrate(n, mask=m, pixel_size=pixel_size, return_info=info, **options)
        return out.height if info else out

    eager = [np.asarray(height(normals[i], masks[i])) for i in range(2)]
    for z, n, m in zip(eager, normals, masks):
        assert np.isfinite(z).all()
        # mean 0 over the mask (fc), over the mask's valid normals (dct), as counted on the
        # host (eager) or in the program (traced)
        over = m if method == "fc" else m & np.isfinite(n).all(-1) & (np.abs(n).sum(-1) > 0)
        assert abs(z[over].mean()) < 1e-5 * np.abs(z).max()
    atol = 2e-5 * max(np.abs(z).max() for z in eager)  # float32 rounding of the other order
    jitted = jax.jit(height)
    for i in range(2):
        np.testing.assert_allclose(jitted(normals[i], masks[i]), eager[i], rtol=1e-5, atol=atol)
    batched = jax.vmap(height)(jnp.asarray(normals), jnp.asarray(masks))
    np.testing.assert_allclose(batched, np.stack(eager), rtol=1e-5, atol=atol)

    weights = rng.standard_normal(masks.shape[1:]).astype(np.float32)

    def loss(n, pixel_size):
        return jnp.sum(weights * height(n, masks[0], pixel_size))

    grads = jax.grad(loss, argnums=(0, 1))(normals[0], 0.5)
    grads_jit = jax.jit(jax.grad(loss, argnums=(0, 1)))(normals[0], 0.5)
    for a, b in zip(grads, grads_jit):
        assert np.isfinite(a).all()
        np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("method", ["lsq", "bilateral", "auto"])
def test_host_methods_refuse_a_trace(method):
    """The grid methods crop to the mask and check their tolerance on the host: inside `jit`
    they say so, where they would otherwise fail on a tracer."""
    s = jaxps.synthetic.face_like(24)
    with pytest.raises(ValueError, match=f"method='{method}'.*outside jit and vmap"):
        jax.jit(lambda n: jaxps.integrate(n, mask=s.mask, method=method))(s.normals)


@pytest.mark.parametrize("method", ["fc", "dct"])
def test_large_fft_methods_write_into_kept_memory(method, monkeypatch):
    """Eager `"fc"` and `"dct"` of normals over `_KEEP_FROM_BYTES` (lowered here to 0) write
    their intermediate planes into the latest call's and the height into one the caller has
    dropped, never into one still held or viewed. Every height equals the fresh-memory
    path's, to the bit (with and without a mask, with a pixel size, in float64); normals with
    no valid pixel still raise. `JAXPS_BATCH_KEEP_BYTES=0` keeps nothing; `release_batch_outputs` lets go."""
    from jaxps.core import _kept
    from jaxps.integration import _integrate

    monkeypatch.delenv("JAXPS_BATCH_KEEP_BYTES", raising=False)
    scene = face_scene(40)
    normals = [np.asarray(scene.normals) + np.float32([0.05 * i, 0, 0]) for i in range(4)]
    calls = [{"method": method, **kw}
             for kw in ({}, {"mask": scene.mask}, {"pixel_size": 0.25}, {"mask": scene.mask})]
    expected = [np.asarray(jaxps.integrate(n, **kw)) for n, kw in zip(normals, calls)]
    assert expected[0].std() > 0.1 and not np.array_equal(expected[1], expected[3])
    monkeypatch.setattr(_integrate, "_KEEP_FROM_BYTES", 0)
    jaxps.release_batch_outputs()

    def solve(i):
        return jaxps.integrate(normals[i], **calls[i])

    first = solve(0)
    pointer = first.unsafe_buffer_pointer()
    assert len(_kept._INTEGRATE_SCRATCH) == 1 and len(_kept._HEIGHTS) == 1
    second = solve(1)  # `first` is held: a fresh height
    assert second.unsafe_buffer_pointer() != pointer
    del first
    third = solve(2)  # into `first`, which nothing else holds
    assert third.unsafe_buffer_pointer() == pointer
    view = np.asarray(second)  # holds `second` through a memoryview
    pointers = {second.unsafe_buffer_pointer(), third.unsafe_buffer_pointer()}
    del second
    fourth = solve(3)
    assert fourth.unsafe_buffer_pointer() not in pointers
    np.testing.assert_array_equal(view, expected[1])
    for got, want in ((third, expected[2]), (fourth, expected[3])):
        np.testing.assert_array_equal(got, want)
    assert len(_kept._INTEGRATE_SCRATCH) == 1 and len(_kept._HEIGHTS) == 2
    with pytest.raises(ValueError, match="no finite"):
        jaxps.integrate(np.full_like(normals[0], np.nan), method=method)
    with jax.enable_x64(True):
        z = jaxps.integrate(normals[0].astype(np.float64), method=method)
        assert z.dtype == jnp.float64
        np.testing.assert_allclose(z, expected[0], atol=1e-4 * np.abs(expected[0]).max())
    jaxps.release_batch_outputs()
    assert _kept._INTEGRATE_SCRATCH == [] and _kept._HEIGHTS == []
    monkeypatch.setenv("JAXPS_BATCH_KEEP_BYTES", "0")
    np.testing.assert_array_equal(solve(3), expected[3])
    assert _kept._INTEGRATE_SCRATCH == [] and _kept._HEIGHTS == []
