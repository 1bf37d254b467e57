"""Integration methods beyond FC: dct, lsq, bilateral, perspective, auto; height error measures."""

import cv2
import jax
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as sla

import jaxps
from jaxps.evaluate import fit_scale_offset, height_error_map, height_stats, made

SOLVERS = ("dct", "lsq", "bilateral")


def rms_after_offset(z, ref, mask):
    d = np.asarray(z, np.float64)[mask] - np.asarray(ref, np.float64)[mask]
    return float(np.sqrt(np.mean((d - d.mean()) ** 2)))


def mid_lsq_reference(normals, mask):
    """scipy reference for the masked least squares of `"lsq"`: sparse normal equations."""
    n = np.asarray(normals, np.float64)
    h, w = mask.shape
    gc = -n[..., 0] / np.maximum(n[..., 2], 0.05)
    gr = n[..., 1] / np.maximum(n[..., 2], 0.05)
    idx = -np.ones((h, w), int)
    idx[mask] = np.arange(mask.sum())
    eh, ev = mask[:, 1:] & mask[:, :-1], mask[1:] & mask[:-1]
    i = np.r_[idx[:, :-1][eh], idx[:-1][ev]]
    j = np.r_[idx[:, 1:][eh], idx[1:][ev]]
    g = np.r_[(gc[:, 1:] + gc[:, :-1])[eh] / 2, (gr[1:] + gr[:-1])[ev] / 2]
    rows = np.arange(len(i))
    d = sp.csr_matrix((np.r_[np.ones(len(i)), -np.ones(len(i))], (np.r_[rows, rows], np.r_[j, i])),
                      shape=(len(i), int(mask.sum())))
    lap = (d.T @ d + 1e-9 * sp.eye(d.shape[1])).tocsc()
    z = sla.spsolve(lap, d.T @ g)
    out = np.zeros((h, w))
    out[mask] = z - z.mean()
    return out


@pytest.fixture(scope="module")
def face():
    return jaxps.synthetic.face_like(48)


# --- exact gradients -----------------------------------------------------------------------

def test_dct_equals_lsq_on_the_full_rectangle(face):
    # both are the exact least-squares solution of the same equations on a rectangle
    z_dct = np.asarray(jaxps.integrate(face.normals, method="dct"))
    z_lsq = np.asarray(jaxps.integrate(face.normals, method="lsq", cg_rtol=1e-6))
    ref = mid_lsq_reference(face.normals, np.ones(face.mask.shape, bool))
    assert np.max(np.abs(z_dct - ref)) < 2e-3 * np.ptp(ref)
    assert np.max(np.abs(z_lsq - ref)) < 2e-3 * np.ptp(ref)


@pytest.mark.parametrize("shape", [(1, 5), (2, 2), (7, 9), (8, 10), (6, 5), (5, 6), (34, 40)])
def test_dct_poisson_equals_scipy_dctn(shape):
    # The one-pass spectral solve (Makhoul's 2-D DCT composed with its inverse) against
    # scipy.fft.dctn / idctn in float64, for odd and even sides (two reorderings).
    import scipy.fft

    from jaxps.integration._poisson import dct_poisson

    rng = np.random.default_rng(sum(shape))
    gc, gr = rng.standard_normal((2, *shape))
    h, w = shape
    gh, gv = (gc[:, 1:] + gc[:, :-1]) / 2, (gr[1:] + gr[:-1]) / 2
    rhs = np.zeros(shape)
    rhs[:, 1:] += gh
    rhs[:, :-1] -= gh
    rhs[1:] += gv
    rhs[:-1] -= gv
    lam = (4 * np.sin(np.pi * np.arange(h)[:, None] / (2 * h)) ** 2
           + 4 * np.sin(np.pi * np.arange(w)[None, :] / (2 * w)) ** 2)
    c = scipy.fft.dctn(rhs, norm="ortho")
    c[lam > 0] /= lam[lam > 0]
    c[lam == 0] = 0
    ref = scipy.fft.idctn(c, norm="ortho")
    z = np.asarray(dct_poisson(gc.astype(np.float32), gr.astype(np.float32)), np.float64)
    assert abs(z.mean()) < 1e-6
    np.testing.assert_allclose(z, ref, atol=2e-6 * max(1, np.abs(ref).max()))


def test_dct_beats_fc_on_a_non_periodic_rectangle():
    # why "auto" picks "dct", not "fc", for a full rectangle: a ramp is not periodic
    y, x = np.mgrid[0:40, 0:48].astype(np.float64)
    z = 0.2 * x + 0.001 * (x - 10) ** 2 + 0.0125 * (y - 5) ** 2  # y here is the row index
    n = np.stack([-(0.2 + 0.002 * (x - 10)), 0.025 * (y - 5), np.ones_like(z)], -1)
    n = (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)
    full = np.ones(z.shape, bool)
    err = {m: rms_after_offset(jaxps.integrate(n, method=m), z, full) for m in ("fc", "dct")}
    assert err["dct"] < 1e-3 < 1.0 < err["fc"]


def test_lsq_matches_scipy_reference_on_a_mask(face):
    mask = np.asarray(face.mask)
    z = np.asarray(jaxps.integrate(face.normals, mask=mask, method="lsq", cg_rtol=1e-6))
    ref = mid_lsq_reference(face.normals, mask)
    assert np.max(np.abs(z - ref)[mask]) < 2e-3 * np.ptp(ref[mask])
    assert np.all(z[~mask] == 0)


def test_multigrid_and_jacobi_cg_agree_with_holes_and_two_components(face):
    """Same heights, per-component offsets included (both keep each component's Jacobi-weighted
    mean), with far fewer CG steps for the multigrid V-cycle."""
    mask = np.asarray(face.mask).copy()
    mask[:, 19] = False  # two components
    mask[20:24, 10:14] = False  # a hole
    mask[1, 1] = True  # a pixel with no edge
    out = {p: jaxps.integrate(face.normals, mask=mask, method="lsq", cg_rtol=1e-6,
                              cg_preconditioner=p, return_info=True)
           for p in ("multigrid", "jacobi")}
    zm, zj = (np.asarray(out[p].height, np.float64) for p in ("multigrid", "jacobi"))
    assert np.max(np.abs(zm - zj)[mask]) < 1e-4 * np.ptp(zj[mask])
    assert out["multigrid"].solver_steps * 5 < out["jacobi"].solver_steps
    assert out["multigrid"].converged and out["jacobi"].converged


def test_lsq_in_two_stored_programs_equals_the_general_path(face):
    """`integrate(method="lsq")` without info runs as two programs (`_lsq_fast`, the crop's
    corner an argument); with `return_info` it takes the general path: the same heights, on
    a mask with two components, a hole and a lone pixel, and crops at two corners."""
    mask = np.asarray(face.mask).copy()
    mask[:, 19] = False
    mask[20:24, 10:14] = False
    mask[1, 1] = True
    for m in (mask, np.pad(mask, ((40, 0), (0, 36)))):
        normals = np.pad(np.asarray(face.normals), ((m.shape[0] - mask.shape[0], 0),
                                                    (0, m.shape[1] - mask.shape[1]), (0, 0)))
        fast = np.asarray(jaxps.integrate(normals, mask=m, method="lsq"))
        general = jaxps.integrate(normals, mask=m, method="lsq", return_info=True)
        assert general.converged
        assert np.max(np.abs(fast - np.asarray(general.height))) < 1e-5 * np.ptp(fast[m])
        assert np.all(fast[~m] == 0)


def test_lsq_crop_sides_come_from_a_ladder_that_face_boxes_share():
    """`"lsq"` compiles once per crop size, so its sides follow a ladder (`_bucket`): 32-px
    steps to 256, then four sizes per octave. Every side fits, grows by less than a quarter
    (past 256) and is a multiple of 32; a face box whose side wanders over 513-640 px keeps
    one size, where 32-px steps gave it four (`bench_lsq_buckets.py`)."""
    from jaxps.integration._integrate import _bucket, _crop

    n = np.arange(1, 5000)
    b = np.array([_bucket(int(k)) for k in n])
    assert np.all(b >= n) and np.all(b % 32 == 0) and np.all(np.diff(b) >= 0)
    assert np.all(b[n > 256] < 1.25 * n[n > 256])
    assert [_bucket(k) for k in (1, 33, 200, 256, 257, 500, 513, 700, 1000, 1025)] == \
        [32, 64, 224, 256, 320, 512, 640, 768, 1024, 1280]
    assert len(set(b[(n > 256) & (n <= 4096)])) == 16  # 320 ... 4096, four per octave
    assert {_bucket(k) for k in range(513, 641)} == {640}
    # in an image: the box grows about the pixels within the frame, or takes the whole side
    valid = np.zeros((700, 900), bool)
    valid[100:613, 880:900] = True
    rows, cols = _crop(valid)
    assert (rows.stop - rows.start, cols.stop - cols.start) == (640, 32)
    assert rows.start <= 100 and rows.stop >= 613 and cols.stop == 900
    valid[:, :] = True
    assert _crop(valid) == (slice(0, 700), slice(0, 900))


@pytest.mark.parametrize("method", SOLVERS)
def test_exact_gradients_recover_the_surface(face, method):
    mask = np.asarray(face.mask)
    z = np.asarray(jaxps.integrate(face.normals, mask=mask, method=method))
    err = rms_after_offset(z, face.height, mask)
    ptp = float(np.ptp(np.asarray(face.height)[mask]))
    # dct sees zero gradients outside the mask (the FC set-up), so the outline bends it
    assert err < (0.05 if method == "dct" else 0.01) * ptp
    assert z.dtype == np.float32 and np.all(np.isfinite(z))


def test_masked_methods_beat_fc_on_an_irregular_mask():
    cap = jaxps.synthetic.sphere(48, max_zenith_deg=60.0)  # a disc mask, steep near its edge
    mask = np.asarray(cap.mask)
    errs = {m: rms_after_offset(jaxps.integrate(cap.normals, mask=mask, method=m),
                                cap.height, mask) for m in ("fc", "lsq")}
    assert errs["lsq"] < 0.2 * errs["fc"]


def test_holes_cost_nothing_for_masked_methods(face):
    mask = np.asarray(face.mask).copy()
    mask[20:26, 10:30] = False  # a slot across the face
    mask[34:38, 18:22] = False
    for method in ("lsq", "bilateral"):
        z = np.asarray(jaxps.integrate(face.normals, mask=mask, method=method))
        assert rms_after_offset(z, face.height, mask) < 0.01 * np.ptp(np.asarray(face.height))
        assert np.all(z[~mask] == 0)


# --- noise --------------------------------------------------------------------------------

@pytest.mark.parametrize("method", SOLVERS)
def test_noisy_gradients_stay_close(face, method):
    mask = np.asarray(face.mask)
    noise = np.asarray(jax.random.normal(jax.random.key(0), face.normals.shape)) * 0.03
    noisy = np.asarray(face.normals) + noise.astype(np.float32)
    z = np.asarray(jaxps.integrate(noisy, mask=mask, method=method))
    err = rms_after_offset(z, face.height, mask)
    assert err < 0.06 * np.ptp(np.asarray(face.height)[mask])


# --- a depth discontinuity ----------------------------------------------------------------

def sheared_step(h=40, w=48, radius=8.0):
    """Top half a plane rising to the right whose lower edge rolls off like the rim of an
    object (steep normals there, as at a real occluding contour); bottom half flat. The jump
    between them grows along the edge, so the gradient field has curl there."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    top = y < h // 2
    dy = np.clip(y - (h // 2 - 0.5 - radius), 0, None)
    rim = np.sqrt(np.maximum(radius**2 - dy**2, 0)) - radius
    z = np.where(top, 0.3 * x + 12.0 + rim, 0.0)
    dz_drow = np.where(top, -dy / np.sqrt(np.maximum(radius**2 - dy**2, 1e-3)), 0)
    n = np.stack([np.where(top, -0.3, 0.0), dz_drow, np.ones_like(z)], -1)
    n = (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)
    return z.astype(np.float32), n, top


def test_bilateral_keeps_the_jump_that_lsq_smears():
    z_true, n, top = sheared_step()
    # per-piece error: a jump's size cannot come from normals, but each side's shape can
    errs = {}
    for method in ("lsq", "bilateral"):
        z = np.asarray(jaxps.integrate(n, method=method))
        inner = np.ones(top.shape, bool)
        inner[18:22] = False
        errs[method] = max(rms_after_offset(z, z_true, top & inner),
                           rms_after_offset(z, z_true, ~top & inner))
    assert errs["bilateral"] < 0.1 and errs["lsq"] > 10 * errs["bilateral"]


def test_curl_marks_the_discontinuity():
    _, n, top = sheared_step()
    curl = np.asarray(jaxps.integrability_map(n))
    assert curl.shape == top.shape
    assert np.all(curl[19:21] > 0.1)
    assert np.all(curl[:18] < 1e-5) and np.all(curl[22:] < 1e-5)


def test_curl_against_numpy_loop_circulation(face):
    noise = np.asarray(jax.random.normal(jax.random.key(1), face.normals.shape)) * 0.05
    n = np.asarray(face.normals) + noise.astype(np.float32)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    curl = np.asarray(jaxps.integrability_map(n), np.float64)
    gc = -n[..., 0] / np.maximum(n[..., 2], 0.05)
    gr = n[..., 1] / np.maximum(n[..., 2], 0.05)
    gh, gv = (gc[:, 1:] + gc[:, :-1]) / 2, (gr[1:] + gr[:-1]) / 2
    loop = np.abs(gh[:-1] + gv[:, 1:] - gh[1:] - gv[:, :-1])
    ref = np.zeros(curl.shape)
    for dr in (0, 1):
        for dc in (0, 1):
            sl = (slice(dr, dr + loop.shape[0]), slice(dc, dc + loop.shape[1]))
            ref[sl] = np.maximum(ref[sl], loop)
    np.testing.assert_allclose(curl, ref, atol=1e-4, rtol=1e-3)


# --- perspective --------------------------------------------------------------------------

def perspective_plane(h=48, w=48, f=60.0):
    """A tilted plane seen by a wide-angle camera: depth d = c / (n_cv . ray)."""
    n = np.array([0.35, 0.25, 1.0])
    n /= np.linalg.norm(n)
    r, c = np.mgrid[0:h, 0:w].astype(np.float64)
    ray = np.stack([(c - w / 2) / f, (r - h / 2) / f, np.ones_like(r)], -1)
    n_cv = np.array([n[0], -n[1], -n[2]])  # OpenCV frame: y down, z away
    depth = -100.0 / (ray @ n_cv)
    k = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    normals = np.broadcast_to(n.astype(np.float32), (h, w, 3)).copy()
    return normals, depth, k


@pytest.mark.parametrize("method", ("dct", "lsq", "bilateral"))
def test_perspective_recovers_the_depth_orthographic_cannot(method):
    normals, depth, k = perspective_plane()
    persp = jaxps.integrate(normals, method=method, intrinsics=k)
    ortho = jaxps.integrate(normals, method=method)
    e_p, e_o = made(persp, depth), made(ortho, depth)
    assert e_p < 0.01 * np.ptp(depth) and e_p < 0.1 * e_o
    assert fit_scale_offset(persp, depth)[0] < 0  # height toward the viewer vs depth away


# --- auto ---------------------------------------------------------------------------------

def smooth_bump(h=40, w=48):
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    g = 8.0 * np.exp(-((x - w / 2) ** 2 + (y - h / 2) ** 2) / (2 * 10.0**2))
    p = -(x - w / 2) / 10.0**2 * g
    q = (y - h / 2) / 10.0**2 * g  # dz/dy with y up = -dz/drow
    n = np.stack([-p, -q, np.ones_like(g)], -1)
    disc = (x - w / 2) ** 2 + (y - h / 2) ** 2 < 15**2
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32), disc


def test_auto_picks_by_mask_and_curl():
    n_bump, disc = smooth_bump()
    full = jaxps.integrate(n_bump, method="auto", return_info=True)
    masked = jaxps.integrate(n_bump, mask=disc, method="auto", return_info=True)
    _, n, _ = sheared_step()
    jump = jaxps.integrate(n, method="auto", return_info=True)
    assert (full.method, masked.method, jump.method) == ("dct", "lsq", "bilateral")
    assert "curl" in jump.reason and "mask" in masked.reason
    np.testing.assert_allclose(
        np.asarray(jump.height), np.asarray(jaxps.integrate(n, method="bilateral")), atol=1e-5)


def test_info_reports_iterations_and_residual(face):
    _, n, top = sheared_step()
    info = jaxps.integrate(n, method="bilateral", return_info=True)
    assert info.converged and 1 < info.steps < 150 and info.solver_steps > info.steps
    cut = jaxps.integrate(n, method="bilateral", max_steps=2, return_info=True)
    assert cut.steps == 2 and not cut.converged
    lsq = jaxps.integrate(n, method="lsq", return_info=True)
    # lsq spreads the non-integrable part over the image; bilateral concentrates it at the jump
    r_lsq, r_bil = np.asarray(lsq.residual), np.asarray(info.residual)
    assert np.median(r_bil) < 0.1 * np.median(r_lsq)
    ok = jaxps.integrate(face.normals, method="dct", return_info=True)
    assert ok.steps == 0 and ok.converged and ok.reason == "requested"


# --- re-derived normals --------------------------------------------------------------------

def test_normals_from_height_with_mask_are_exact_on_a_plane():
    y, x = np.mgrid[0:20, 0:24].astype(np.float32)
    z = 0.4 * x + 0.2 * (19 - y)  # dz/dx = 0.4, dz/dy = 0.2 (y up, rows go down)
    mask = (x - 12) ** 2 + (y - 10) ** 2 < 64
    n = np.asarray(jaxps.normals_from_height(np.where(mask, z, 0), mask=mask))
    want = np.array([-0.4, -0.2, 1.0]) / np.linalg.norm([-0.4, -0.2, 1.0])
    np.testing.assert_allclose(n[mask], np.broadcast_to(want, n[mask].shape), atol=1e-5)
    np.testing.assert_array_equal(n[~mask], np.broadcast_to([0, 0, 1], n[~mask].shape))


def test_integration_denoises_normals(face):
    mask = np.asarray(face.mask)
    noise = np.asarray(jax.random.normal(jax.random.key(2), face.normals.shape)) * 0.05
    noisy = np.asarray(face.normals) + noise.astype(np.float32)
    noisy /= np.linalg.norm(noisy, axis=-1, keepdims=True)
    z = jaxps.integrate(noisy, mask=mask, method="lsq")
    again = jaxps.normals_from_height(z, mask=mask)
    before = jaxps.evaluate.angular_stats(noisy, face.normals, mask=mask)["mean_deg"]
    after = jaxps.evaluate.angular_stats(again, face.normals, mask=mask)["mean_deg"]
    assert after < 0.8 * before


# --- bad input ----------------------------------------------------------------------------

def test_bad_input_raises_naming_the_argument(face):
    n = face.normals
    with pytest.raises(ValueError, match="mask"):
        jaxps.integrate(n, mask=np.ones((3, 3), bool), method="lsq")
    with pytest.raises(ValueError, match="mask"):
        jaxps.integrate(n, mask=np.zeros(face.mask.shape, bool), method="bilateral")
    with pytest.raises(ValueError, match="method"):
        jaxps.integrate(n, method="poisson")
    with pytest.raises(ValueError, match="intrinsics"):
        jaxps.integrate(n, method="lsq", intrinsics=np.eye(2))
    with pytest.raises(ValueError, match="normals"):
        jaxps.integrate(np.full(n.shape, np.nan, np.float32), method="lsq")
    for name, value in (("k", -1.0), ("max_steps", 0), ("tol", 0.0), ("cg_rtol", np.nan)):
        with pytest.raises(ValueError, match=name):
            jaxps.integrate(n, method="bilateral", **{name: value})


@pytest.mark.parametrize("method", ("fc", "dct", "lsq", "bilateral", "auto"))
def test_nan_backfacing_and_non_unit_normals_give_finite_heights(face, method):
    n = np.asarray(face.normals).copy()
    mask = np.asarray(face.mask)
    n[24, 10:20] = np.nan
    n[30, 15:20] = [0.3, 0.1, -0.5]  # backfacing
    n[10, 20] = 0.0
    scaled = n * 3.0
    info = jaxps.integrate(scaled, mask=mask, method=method, return_info=True)
    z = np.asarray(info.height)
    assert np.all(np.isfinite(z))
    assert not np.any(np.asarray(info.valid)[24, 10:20]) and not np.asarray(info.valid)[10, 20]
    clean = mask.copy()
    clean[22:33, 8:22] = False
    clean[10, 20] = False
    ref = np.asarray(jaxps.integrate(n, mask=mask, method=method))
    np.testing.assert_allclose(z[clean], ref[clean], atol=1e-3 * np.ptp(ref[clean]))
    assert rms_after_offset(z, face.height, clean) < 0.1 * np.ptp(np.asarray(face.height)[mask])


# --- evaluate -----------------------------------------------------------------------------

def test_height_measures_against_numpy():
    rng = np.random.default_rng(0)
    z = rng.standard_normal((12, 10))
    ref = -2.5 * z + 7.0 + 0.1 * rng.standard_normal(z.shape)
    mask = rng.random(z.shape) > 0.3
    a = np.stack([z[mask], np.ones(mask.sum())], 1)
    coef = np.linalg.lstsq(a, ref[mask], rcond=None)[0]
    resid = a @ coef - ref[mask]
    s, t = fit_scale_offset(z, ref, mask=mask)
    np.testing.assert_allclose([s, t], coef, rtol=1e-10)
    stats = height_stats(z, ref, mask=mask)
    np.testing.assert_allclose(stats["made"], np.mean(np.abs(resid)), rtol=1e-10)
    np.testing.assert_allclose(stats["rms"], np.sqrt(np.mean(resid**2)), rtol=1e-10)
    assert made(z, ref, mask=mask) == stats["made"]
    err = height_error_map(z, ref, mask=mask)
    assert np.all(np.isnan(err[~mask]))
    np.testing.assert_allclose(err[mask], resid, atol=1e-12)
    off = height_stats(z, z + 3.0, align="offset")
    assert off["made"] < 1e-12 and abs(off["offset"] - 3.0) < 1e-12
    with pytest.raises(ValueError, match="reference"):
        made(z, ref[:5])
    with pytest.raises(ValueError, match="align"):
        height_stats(z, ref, align="icp")


# --- real ground truth: DiLiGenT --------------------------------------------------------------

# From `python benchmarks/bench_integration.py` (benchmarks/results/integration.json), MADE in mm
# after a least-squares scale+offset fit over the mask. "jacobi": the Jacobi-preconditioned CG
# of Cao et al.'s code, whose figures it reproduces.
DILIGENT_MADE = {
    "bear": {"fc": 2.731, "dct": 2.308, "lsq": 0.267, "bilateral persp": 0.184,
            "bilateral persp jacobi": 0.172},
    "cat": {"fc": 5.020, "dct": 4.421, "lsq": 1.793, "bilateral persp": 0.101,
           "bilateral persp jacobi": 0.094},
    "pot1": {"fc": 2.013, "dct": 2.014, "lsq": 1.525, "bilateral persp": 0.627,
            "bilateral persp jacobi": 0.666},
    "reading": {"fc": 5.500, "dct": 5.317, "lsq": 2.671, "bilateral persp": 0.292,
               "bilateral persp jacobi": 0.302},
}


def load_diligent(root, name):
    d = root / "diligent_gt" / name
    raw = cv2.imread(str(d / "normal_map.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and np.any(raw % 256)  # 16 bits kept
    normals = raw[..., ::-1].astype(np.float32) / 65535 * 2 - 1
    mask = cv2.imread(str(d / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    depth = np.load(d / "depth_gt.npz")["depth_gt"]
    return normals, mask, depth, np.loadtxt(d / "K.txt")


@pytest.mark.parametrize("name", sorted(DILIGENT_MADE))
def test_diligent_made_matches_the_benchmark(data, name):
    normals, mask, depth, k = load_diligent(data, name)
    norm = np.linalg.norm(normals[mask], axis=-1)
    assert np.median(np.abs(norm - 1)) < 1e-3  # RGB order and scaling right
    assert np.median(normals[mask][:, 2]) > 0.5  # z toward the viewer
    for label, want in DILIGENT_MADE[name].items():
        method, *rest = label.split()
        z = jaxps.integrate(normals, mask=mask, method=method,
                            intrinsics=k if "persp" in rest else None,
                            cg_preconditioner="jacobi" if "jacobi" in rest else "multigrid")
        got = made(z, depth, mask=mask)
        assert abs(got - want) < 0.03 * want + 0.005, (label, got, want)


@pytest.mark.parametrize("method", ("dct", "lsq", "bilateral"))
def test_float64_kept(method):
    _, n, _ = sheared_step(16, 20, radius=4.0)
    with jax.enable_x64(True):
        z64 = jaxps.integrate(n.astype(np.float64), method=method)
        assert z64.dtype == np.float64 and np.all(np.isfinite(np.asarray(z64)))
    z32 = jaxps.integrate(n, method=method)
    assert z32.dtype == np.float32
    np.testing.assert_allclose(np.asarray(z64), np.asarray(z32), atol=0.05)


@pytest.mark.parametrize("method", jaxps.INTEGRATION_METHODS)
def test_float16_normals_integrate_in_float32(method, face):
    # float16 normals (what photometric_stereo returns for float16 frames): XLA's FFTs take
    # only float32/float64, so integrate solves in float32 and answers in float16.
    n16 = np.asarray(face.normals, np.float16)
    mask = np.asarray(face.mask)
    z16 = jaxps.integrate(n16, mask=mask, method=method)
    z32 = jaxps.integrate(n16.astype(np.float32), mask=mask, method=method)
    assert z16.dtype == np.float16
    np.testing.assert_allclose(np.asarray(z16, np.float32), np.asarray(z32, np.float16),
                               rtol=0, atol=1e-6)
    info = jaxps.integrate(n16, mask=mask, method=method, return_info=True)
    assert info.height.dtype == info.residual.dtype == np.float16
