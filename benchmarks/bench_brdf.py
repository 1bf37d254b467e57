"""BRDF from five lights: held-out relighting error on Yale B faces, LM training and relight speed.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_brdf.py \
        [--part accuracy|speed|loop|gains|seeds|all] [--subjects ...] [--sets ...] [--methods ...]

Writes benchmarks/results/brdf.json and brdf.png (`--part loop`: brdf_loop.json, BRDF-in-the-loop
photometric stereo against a many-light reference; `--part seeds`: brdf_seeds.json, the MLP
methods' held-out error over five keys; `--part gains`: brdf_gains.json, training on
frames corrected by estimated per-frame light intensities). Accuracy: for each subject and
training set, fit normals and albedo by L2 photometric stereo on the five training frames
(ambient frame subtracted; frames that `jaxps.check_frames` flags are dropped from training and
testing, as the pipeline would: yaleB02's +25,0 and +20,-10 are interlace-combed), fit every
BRDF method on the same frames, and relight every other light within 60 (and 30) degrees of
the view axis; RMSE in gray levels (0-255) over the face
mask, raw and gain-compensated (one least-squares gain per held-out image, every method alike).
Speed: LM training on 100,000 samples, the default `wrap_ggx` fit, and relighting a 700x850
image with each (compile and run apart),
with the previous per-sample relight kernel and the pieces of the new one timed in the same run.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import time
from typing import NamedTuple

import cv2
import jax
import lineax as lx
import numpy as np
import optimistix as optx
import scipy.ndimage

import jaxps
from jaxps.reflectance._score import image_gains, rmse_gray

try:
    from benchmarks._common import clean_frames, cpu_model, interleaved
except ImportError:  # run as a script
    import sys

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import clean_frames, cpu_model, interleaved

ROOT = pathlib.Path(__file__).resolve().parents[1]
DATA = pathlib.Path(os.environ.get("JAXPS_DATA", ROOT.parent / "shared" / "data"))
OUT = ROOT / "benchmarks" / "results"

TRAIN_SETS = {
    # one light at the camera, four 20-25 degrees around it (the scanner's layout)
    "cross": [(0, 0), (0, 20), (0, -20), (25, 0), (-25, 0)],
    "alt": [(0, 0), (0, 20), (0, -20), (20, 10), (-25, 0)],
}
METHODS = {  # name -> fit_brdf keywords
    "lambertian": {"method": "lambertian"},
    "delaunay": {"method": "delaunay", "n_samples": 30_000},
    "mlp": {"method": "mlp"},
    "mlp_ratio": {"method": "mlp_ratio"},
    # the same networks trained as before frame gains existed (the paper's training)
    "mlp (no frame gains)": {"method": "mlp", "frame_gains": False},
    "mlp_ratio (no frame gains)": {"method": "mlp_ratio", "frame_gains": False},
    "mlp_plain (paper)": {"method": "mlp", "lambertian_base": False, "frame_gains": False},
    # the correction scaled by a leave-one-light-out factor (training frames only)
    "mlp_loo": {"method": "mlp", "shrink": "loo"},
    "mlp_ratio_loo": {"method": "mlp_ratio", "shrink": "loo"},
}


# Set by `--register` (bench_relight.py, relight_bound.py): every frame is moved onto the (0,0)
# frame before use. The subjects moved 0.4-3.5 px between frames (jaxps.estimate_shifts).
REGISTER = False


def load_yale(subject: str):
    """(images (K, H, W) in [0, 1] ambient-subtracted, (azimuth, elevation) list, (K,) bool of
    the frames `jaxps.check_frames` passes) of a subject. The check runs on the frames within
    60 deg of the view axis (the ones used here); farther ones are counted as passed, unused.
    With `REGISTER`, the frames within 60 deg are first moved onto the (0,0) frame (measured
    by `jaxps.estimate_shifts`, undone by `jaxps.shift_frames`; farther frames as read)."""
    folder = DATA / "yaleb" / subject
    ambient = cv2.imread(str(folder / f"{subject}_P00_Ambient.pgm"), cv2.IMREAD_UNCHANGED)
    images, angles = [], []
    for path in sorted(folder.glob(f"{subject}_P00A*.pgm")):
        ae = jaxps.parse_yale_name(path.name)
        if ae is None:
            continue
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float32)
        images.append((raw - ambient.astype(np.float32)) / 255.0)
        angles.append(ae)
    images = np.stack(images)
    if REGISTER:
        near = [i for i, (a, e) in enumerate(angles)
                if np.cos(np.radians(a)) * np.cos(np.radians(e)) >= np.cos(np.radians(60))]
        shifts = jaxps.estimate_shifts(images[near], reference=near.index(angles.index((0, 0))))
        images[near] = np.asarray(jaxps.shift_frames(images[near], -shifts))
    return images, angles, clean_frames(images, angles, subject)


def load_subject(subject: str):
    """Frames, Yale B angles, unit lights, zenith angles (deg), the frames that passed
    `check_frames`, and the many-light reference (L2 PS over every clean light within 50 deg of
    the view axis) of one subject."""
    images, angles, clean = load_yale(subject)
    lights = jaxps.lights_from_angles(*np.array(angles, float).T)
    zenith = np.degrees(np.arccos(np.clip(lights[:, 2], -1, 1)))
    near = (zenith <= 50) & clean
    return (images, angles, lights, zenith, clean,
            jaxps.photometric_stereo(images[near], lights[near]))


def split(angles, zenith, clean, set_name):
    """Training frames (the named set less the flagged ones, which the pipeline drops) and the
    test frames (every other clean light within 60 deg), as index lists."""
    named = [angles.index(a) for a in TRAIN_SETS[set_name]]
    train = [i for i in named if clean[i]]
    test60 = [i for i in range(len(angles))
              if i not in named and zenith[i] <= 60 and clean[i]]
    return train, test60


def face_mask(train_images, ps):
    """Face mask: lit in every training frame (>= 10 gray), PS status OK, albedo >= 0.3 x its
    median (drops hair, eyebrows' darkest parts and background), eroded 2 px, largest component."""
    lit = np.min(train_images, axis=0) >= 10 / 255
    ok = np.asarray(ps.status) == 0
    alb = np.asarray(ps.albedo)
    mask = lit & ok
    mask &= alb >= 0.3 * np.median(alb[mask])
    mask = scipy.ndimage.binary_erosion(mask, iterations=2)
    labels, n = scipy.ndimage.label(mask)
    if n > 1:
        sizes = scipy.ndimage.sum(mask, labels, range(1, n + 1))
        mask = labels == (1 + int(np.argmax(sizes)))
    return mask


def rmse(pred, obs, sel):
    return rmse_gray(pred, obs, sel)


def gain_rmse(pred, obs, mask, near=None):
    """RMSE after each test image gets its own least-squares scalar gain over the mask, the same
    for every method ("gain-compensated": the flash brightness of a held-out frame is unknown
    to any model). `near`: `(K,)` bool, the images to pool (default all). The figures of
    `jaxps.score_relighting`, which the held-out protocol of bench_relight.py uses."""
    pred = np.asarray(pred)
    valid = np.broadcast_to(mask, pred.shape)
    g = image_gains(pred, obs, valid)[:, None, None]
    sel = valid if near is None else valid & np.asarray(near)[:, None, None]
    return rmse_gray(pred * g, obs, sel)


def loo_gray(loo):
    """`BRDFFit.loo_rmse` in gray levels (RMSEs x 255, MSE differences x 255^2)."""
    if loo is None:
        return None
    out = {}
    for k, v in loo.items():
        if k == "skipped_folds":
            out[k] = v
            continue
        scale = 1.0 if k == "pooled_factor" else 255.0**2 if k.startswith("mse") else 255.0
        out[k] = [x * scale for x in v] if isinstance(v, list) else v * scale
    return out


class Case(NamedTuple):
    """One subject and training set, as every part of this benchmark evaluates it."""

    subject: str
    set_name: str
    images: np.ndarray  # (K, H, W), every frame of the subject
    angles: list  # (azimuth, elevation) per frame
    lights: np.ndarray  # (K, 3)
    clean: np.ndarray  # (K,) bool, passed check_frames
    ref: object  # L2 PS over the clean lights within 50 deg (the many-light reference)
    reference_lights: int
    train: list  # frame indices
    test60: list  # frame indices, clean lights within 60 deg not trained on
    near: np.ndarray  # (len(test60),) bool, within 30 deg
    ps: object  # L2 PS on the training frames
    mask: np.ndarray  # (H, W) face mask


def cases(subjects, sets):
    """A `Case` per subject and training set (the subject's frames loaded once)."""
    for subject in subjects:
        images, angles, lights, zenith, clean, ref = load_subject(subject)
        for set_name in sets:
            train, test60 = split(angles, zenith, clean, set_name)
            ps = jaxps.photometric_stereo(images[train], lights[train])
            yield Case(subject, set_name, images, angles, lights, clean, ref,
                       int(np.sum((zenith <= 50) & clean)), train, test60,
                       np.array([zenith[i] <= 30 for i in test60]), ps,
                       face_mask(images[train], ps))


def accuracy(subjects=("yaleB01", "yaleB02"), sets=("cross", "alt"), methods=None):
    methods = METHODS if methods is None else {n: METHODS[n] for n in methods}
    results = []
    for c in cases(subjects, sets):
        subject, set_name, images, angles, lights, clean = c[:6]
        train, test60, near, ps, mask = c.train, c.test60, c.near, c.ps, c.mask
        normals, albedo = ps.normals, ps.albedo
        obs = images[test60]
        row = {"subject": subject, "train_set": set_name,
               "train_lights_deg": [angles[i] for i in train],
               "flagged_frames_deg": [angles[i] for i in range(len(angles))
                                      if not clean[i]],
               "test_lights_60": len(test60), "test_lights_30": int(near.sum()),
               "mask_pixels": int(mask.sum()), "methods": {}}
        for name, kw in methods.items():
            if kw.get("shrink") and len(train) < 5:
                row["methods"][name] = {"skipped": f"shrink='loo' needs 5 frames, the "
                                                   f"set has {len(train)} clean ones"}
                print(f"{subject} {set_name} {name}: skipped ({len(train)} frames)")
                continue
            t = time.perf_counter()
            model = jaxps.fit_brdf(images[train], normals, albedo, lights[train], mask=mask,
                                   key=jax.random.key(0), **kw)
            fit_s = time.perf_counter() - t
            t = time.perf_counter()
            pred = np.asarray(jaxps.relight(model, normals, albedo, lights[test60], mask=mask))
            relight_s = time.perf_counter() - t
            flag = np.asarray(jaxps.extrapolation_mask(model, normals, lights[test60]))
            sel60 = np.broadcast_to(mask, obs.shape)
            sel30 = sel60 & near[:, None, None]
            train_pred = np.asarray(jaxps.relight(model, normals, albedo, lights[train]))
            f = model.fit
            row["methods"][name] = {
                "rmse_60": rmse(pred, obs, sel60), "rmse_30": rmse(pred, obs, sel30),
                "rmse_60_gain_oracle": gain_rmse(pred, obs, mask),
                "rmse_30_gain_oracle": gain_rmse(pred, obs, mask, near),
                "rmse_60_extrapolated": rmse(pred, obs, sel60 & flag),
                "rmse_60_inside": rmse(pred, obs, sel60 & ~flag),
                "extrapolated_fraction_60": float(flag[sel60].mean()),
                "extrapolated_fraction_30": float(flag[sel30].mean()),
                "train_mse_gray2": f.mse * 255**2, "train_rmse_gray": f.rmse * 255,
                "train_r": f.r, "steps": f.steps, "converged": f.converged,
                "n_samples": f.n_samples, "train_images_rmse": rmse(
                    train_pred, images[train], np.broadcast_to(mask, train_pred.shape)),
                "fit_s": fit_s, "relight_s": relight_s,
                "shrink": f.shrink, "loo_gray": loo_gray(f.loo_rmse),
                "frame_gains": f.frame_gains,
            }
            m = row["methods"][name]
            print(f"{subject} {set_name} {name:18s} rmse60 {m['rmse_60']:6.2f} "
                  f"rmse30 {m['rmse_30']:6.2f} gain60 {m['rmse_60_gain_oracle']:6.2f} "
                  f"gain30 {m['rmse_30_gain_oracle']:6.2f} shrink {f.shrink:.3f} "
                  f"extrap {m['extrapolated_fraction_60']:.3f} "
                  f"train mse {m['train_mse_gray2']:7.1f} R {f.r:.4f} steps {f.steps} "
                  f"fit {fit_s:5.1f}s", flush=True)
        results.append(row)
    return results


def speed(n_samples=100_000, h=700, w=850, steps=30):
    """LM training time on n_samples and relight time of an h x w image (synthetic face)."""
    surf = jaxps.synthetic.face_like(h, w)
    lights = jaxps.synthetic.scanner_lights(20.0)
    scene = jaxps.synthetic.render_scene(surf, lights)
    out = {"n_samples": n_samples, "image": [h, w], "lm_steps": steps,
           "note": f"rtol = atol = 0 so LM always runs its {steps} steps (fit_brdf's default "
                   "is 30); fit times include feature extraction and sampling"}
    # zero tolerances: LM never stops early, so the time is for exactly max_steps=30 steps
    solver = optx.LevenbergMarquardt(rtol=0.0, atol=0.0, linear_solver=lx.Normal(lx.Cholesky()))
    models = {}
    for method in ("mlp", "mlp_ratio"):
        kw = dict(mask=scene.mask, method=method, n_samples=n_samples, solver=solver,
                  max_steps=steps)
        t = time.perf_counter()
        model = jaxps.fit_brdf(scene.images, scene.normals, scene.albedo, lights,
                               key=jax.random.key(0), **kw)
        first = time.perf_counter() - t
        t = time.perf_counter()
        model = jaxps.fit_brdf(scene.images, scene.normals, scene.albedo, lights,
                               key=jax.random.key(1), **kw)
        second = time.perf_counter() - t
        out[f"train_{method}_first_s"] = first
        out[f"train_{method}_s"] = second
        out[f"train_{method}_steps"] = model.fit.steps
        models[method] = model
        print(f"train {method}: first call (compile) {first:.2f} s, second {second:.2f} s, "
              f"{model.fit.steps} steps", flush=True)
    models["lambertian"] = jaxps.fit_brdf(scene.images, scene.normals, scene.albedo, lights,
                                          mask=scene.mask, method="lambertian")
    # the default model, with its default settings (n_samples, 30 LM steps, normals refined)
    for key, name in ((0, "first_s"), (1, "s")):
        t = time.perf_counter()
        models["wrap_ggx"] = jaxps.fit_brdf(scene.images, scene.normals, scene.albedo, lights,
                                            mask=scene.mask, key=key)
        out[f"train_wrap_ggx_{name}"] = time.perf_counter() - t
    print(f"train wrap_ggx (the default): first call {out['train_wrap_ggx_first_s']:.2f} s, "
          f"second {out['train_wrap_ggx_s']:.2f} s", flush=True)
    out.update(relight_speed(models, scene.normals, scene.albedo))
    return out


def relight_speed(models, normals, albedo, rounds=15):
    """Relight one image (700x850 in `speed`) under one new light with each model, and the
    pieces of the MLP relight apart, all in one process: rounds interleave the methods so that
    the load of a shared machine hits them alike; median and min over rounds, compile (first
    call) apart."""
    import jax.numpy as jnp
    from jax.scipy.ndimage import map_coordinates

    from jaxps.core._elementwise import atan2_nonneg as _atan2_nonneg
    from jaxps.core._elementwise import tanh as _tanh
    from jaxps.reflectance._brdf import (
        _mlp,
        _mlp_elementwise,
        _predict_one,
        _relight,
        _relight_args,
        _support_weight,
    )
    from jaxps.reflectance._features import (
        _angles_elementwise,
        _sample_angles,
        pixel_coordinates,
    )

    normals, albedo = jnp.asarray(normals), jnp.asarray(albedo)
    h, w, _ = normals.shape
    light = jnp.asarray(jaxps.lights_from_angles([30.0], [10.0]), normals.dtype)
    m = models["mlp_ratio"]
    params = m.params

    @jax.jit
    def features_per_sample(n, lights):  # the previous layout: vmap of a 3-vector kernel
        n = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
        view = jnp.array([0, 0, 1], n.dtype)
        one = jax.vmap(jax.vmap(_sample_angles, (0, None, None)), (None, 0, None))
        return one(n.reshape(-1, 3), lights, view)

    @jax.jit
    def relight_per_sample(n, rho, lights):  # the previous relight: vmap of _predict_one
        ang = features_per_sample(n, lights).reshape(-1, 3)
        xy = jnp.broadcast_to(pixel_coordinates(h, w).reshape(1, -1, 2),
                              (lights.shape[0], h * w, 2)).reshape(-1, 2)
        f = jnp.concatenate([ang, xy], -1)
        r = jnp.broadcast_to(rho.reshape(1, -1), (lights.shape[0], h * w)).reshape(-1)
        return jax.vmap(lambda fs, a: _predict_one(params, fs, a, m.box_lo, m.box_hi, m.support,
                                                   m.rho_ref, m.bound, m.cell, True, True,
                                                   True))(f, r)

    ti, tr, da, _ = jax.jit(_angles_elementwise)(normals, light)
    tr = jnp.broadcast_to(tr, ti.shape)
    rows = [ti, tr, da, ti * 0.5, tr * 0.5]
    z = jnp.concatenate(rows)  # (5, P) feature-major
    zt = z.T  # (P, 5) sample-major

    def gemm(p, z):
        for wt, b in p[:-1]:
            z = jnp.tanh(wt @ z + b[:, None])
        return (p[-1][0] @ z + p[-1][1][:, None])[0]

    small_normals, small_albedo = normals[:40, :40], albedo[:40, :40]
    pixel_lights = jnp.broadcast_to(light[:, None, None, :], (1, h, w, 3)) + 0  # (1, H, W, 3)

    def render_einsum(n, a, lights):  # render_lambertian before it was written out
        eq = "kc,hwc->khw" if lights.ndim == 2 else "khwc,hwc->khw"
        return jnp.maximum(jnp.einsum(eq, lights, n), 0) * a[None]

    cases = {
        "relight_mlp": lambda: jaxps.relight(models["mlp"], normals, albedo, light),
        "relight_mlp_ratio": lambda: jaxps.relight(m, normals, albedo, light),
        # a 40x40 image: what is left is the host's work per call (checks, dispatch)
        "relight_mlp_ratio_40x40 (host time)": lambda: jaxps.relight(m, small_normals,
                                                                    small_albedo, light),
        "relight_lambertian": lambda: jaxps.relight(models["lambertian"], normals, albedo, light),
        "relight_wrap_ggx (the default)": lambda: jaxps.relight(models["wrap_ggx"], normals,
                                                                albedo, light),
        "render_lambertian": lambda: jaxps.render_lambertian(normals, albedo, light),
        "render_lambertian_per_pixel_lights": lambda: jaxps.render_lambertian(
            normals, albedo, pixel_lights),
        "render_lambertian_einsum (previous)": partial_jit(render_einsum, normals, albedo, light),
        "render_lambertian_einsum_per_pixel_lights (previous)": partial_jit(
            render_einsum, normals, albedo, pixel_lights),
        # the same kernel compiled without its 512-bit vector preference
        "relight_mlp_ratio_default_vector_width (before _WIDE_VECTORS)": lambda: _relight.plain(
            *_relight_args(m), normals, albedo, light),
        "relight_mlp_ratio_per_sample (previous kernel)": partial_jit(
            relight_per_sample, normals, albedo, light),
        "piece_features_elementwise (theta_i, theta_r, delta_alpha)": partial_jit(
            _angles_elementwise, normals, light),
        "piece_features_per_sample_vmap (previous, XLA atan2)": partial_jit(
            features_per_sample, normals, light),
        "piece_atan2_xla": partial_jit(jnp.arctan2, jnp.abs(ti), tr - 0.5),
        "piece_atan2_polynomial": partial_jit(_atan2_nonneg, jnp.abs(ti), tr - 0.5),
        "piece_tanh_xla": partial_jit(jnp.tanh, ti),
        "piece_tanh_rational (the relight kernel's)": partial_jit(_tanh, ti),
        "piece_mlp_elementwise": partial_jit(_mlp_elementwise, params, rows),
        "piece_mlp_gemm_feature_major": partial_jit(gemm, params, z),
        "piece_mlp_vmap_per_sample (previous)": partial_jit(
            jax.vmap(_mlp, (None, 0)), params, zt),
        "piece_support_gather": partial_jit(
            lambda s, a, b, c: _support_weight(s, (a, b, c), m.cell), m.support, ti, tr, da),
        "piece_support_map_coordinates_vmap (previous)": partial_jit(
            jax.vmap(lambda s, a: map_coordinates(s, list(a / m.cell - 0.5), order=1,
                                                  mode="nearest"), (None, 0)),
            m.support, jnp.stack([ti, tr, da], -1).reshape(-1, 3)),
    }
    compile_s, runs = interleaved(cases, rounds)
    out = {"relight_image": [h, w], "relight_rounds": rounds, "relight": {}}
    for name in cases:
        r = np.asarray(runs[name]) * 1e3
        out["relight"][name] = {"first_call_s": compile_s[name], "ms_median": float(np.median(r)),
                                "ms_min": float(r.min())}
        print(f"{name:58s} first {compile_s[name]:6.2f} s  median {np.median(r):7.2f} ms  "
              f"min {r.min():7.2f} ms", flush=True)
    med = {n: v["ms_median"] for n, v in out["relight"].items()}
    for name in ("relight_mlp", "relight_mlp_ratio"):
        out[f"{name}_ms_median"] = med[name]
        out[f"{name}_over_lambertian"] = med[name] / med["relight_lambertian"]
    out["relight_lambertian_ms_median"] = med["relight_lambertian"]
    out["relight_wrap_ggx_ms_median"] = med["relight_wrap_ggx (the default)"]
    out["render_lambertian_ms_median"] = med["render_lambertian"]
    out["relight_previous_kernel_over_new"] = (
        med["relight_mlp_ratio_per_sample (previous kernel)"] / med["relight_mlp_ratio"])
    return out


def partial_jit(fn, *args):
    """A zero-argument callable running `jax.jit(fn)(*args)` (compiled once)."""
    jitted = jax.jit(fn)
    return lambda: jitted(*args)


def gains(subjects=("yaleB01", "yaleB02"), set_name="cross"):
    """Per-frame light intensities of the five training frames (idea: train every method on
    gain-corrected frames and the normals they give). For each way of estimating them
    (`jaxps.intensity_estimate`: none, mean, frontal, semi_calibrated), divide the training
    frames by them, run L2 photometric stereo, and report the normals' angular error against
    L2 PS over every light within 50 deg (diagnostic only: nothing is selected with it) and the
    held-out RMSE of `lambertian`, `mlp_ratio` and (but for semi_calibrated) `mlp_ratio_loo`
    fitted on the corrected frames (the folds re-run L2 PS on the corrected frames)."""
    out = []
    for c in cases(subjects, (set_name,)):
        subject, images, lights, ref = c.subject, c.images, c.lights, c.ref
        train, test60, near, mask = c.train, c.test60, c.near, c.mask
        obs = images[test60]
        sel60 = np.broadcast_to(mask, obs.shape)
        sel30 = sel60 & near[:, None, None]
        row = {"subject": subject, "train_set": set_name,
               "reference_lights": c.reference_lights, "estimates": {}}
        for how in ("none", "mean", "frontal", "semi_calibrated"):
            e = np.asarray(jaxps.intensity_estimate(images[train], lights[train], mask=mask,
                                                    method=how), np.float64)
            frames = images[train] / e[:, None, None].astype(np.float32)
            ps = jaxps.photometric_stereo(frames, lights[train])
            st = jaxps.evaluate.angular_stats(ps.normals, ref.normals, mask=mask)
            r = {"intensities": e.tolist(), "normals_median_deg": st["median_deg"],
                 "normals_mean_deg": st["mean_deg"], "methods": {}}
            loo = how != "semi_calibrated" and len(train) >= 5  # shrink="loo" needs 5
            names = ["lambertian", "mlp_ratio"] + (["mlp_ratio_loo"] if loo else [])
            for name in names:
                model = jaxps.fit_brdf(frames, ps.normals, ps.albedo, lights[train], mask=mask,
                                       key=jax.random.key(0), **METHODS[name])
                pred = np.asarray(jaxps.relight(model, ps.normals, ps.albedo, lights[test60],
                                                mask=mask))
                r["methods"][name] = {
                    "rmse_60": rmse(pred, obs, sel60), "rmse_30": rmse(pred, obs, sel30),
                    "rmse_60_gain_oracle": gain_rmse(pred, obs, mask),
                    "rmse_30_gain_oracle": gain_rmse(pred, obs, mask, near),
                    "shrink": model.fit.shrink, "loo_gray": loo_gray(model.fit.loo_rmse)}
                m = r["methods"][name]
                print(f"{subject} {how:15s} e {np.round(e, 3)} normals median "
                      f"{st['median_deg']:5.2f} {name:10s} rmse60/30 {m['rmse_60']:6.2f} "
                      f"{m['rmse_30']:6.2f} gain {m['rmse_60_gain_oracle']:6.2f} "
                      f"{m['rmse_30_gain_oracle']:6.2f}", flush=True)
            row["estimates"][how] = r
        out.append(row)
    return out


def loop(subject="yaleB01", set_name="cross"):
    """BRDF-in-the-loop PS vs L2 PS, both from the five training frames, against L2 PS over every
    light within 50 degrees of the view axis (the many-light reference)."""
    from jaxps.reflectance._brdf_ps import brdf_photometric_stereo

    c = next(cases((subject,), (set_name,)))
    images, lights, ref, train, ps, mask = c.images, c.lights, c.ref, c.train, c.ps, c.mask
    out = {"subject": subject, "train_set": set_name, "reference_lights": c.reference_lights,
           "l2": jaxps.evaluate.angular_stats(ps.normals, ref.normals, mask=mask)}
    print("l2", out["l2"], flush=True)
    for method in ("lambertian", "mlp_ratio"):
        t = time.perf_counter()
        r = brdf_photometric_stereo(images[train], lights[train], mask=mask, method=method,
                                    iterations=2, key=jax.random.key(0), n_samples=30_000,
                                    max_steps=10, progress=jaxps.report.progress_bar())
        out[f"loop_{method}"] = jaxps.evaluate.angular_stats(r.normals, ref.normals, mask=mask)
        out[f"loop_{method}"]["status"] = jaxps.status_counts(np.asarray(r.status)[mask])
        out[f"loop_{method}"]["seconds"] = time.perf_counter() - t
        print(method, out[f"loop_{method}"], flush=True)
    return out


def seeds(subjects=("yaleB01", "yaleB02"), sets=("cross", "alt"), keys=range(5)):
    """How much of a held-out difference is the fit's randomness: the MLP methods (with and
    without frame gains) fitted with `key=jax.random.key(i)` for each i in `keys`, same frames,
    normals and mask as `accuracy`; RMSE within 60 and 30 deg per key, against Lambert."""
    names = ["mlp", "mlp_ratio", "mlp (no frame gains)", "mlp_ratio (no frame gains)"]
    out = []
    for c in cases(subjects, sets):
        subject, set_name, images, lights = c.subject, c.set_name, c.images, c.lights
        train, test60, near, ps, mask = c.train, c.test60, c.near, c.ps, c.mask
        obs = images[test60]
        sel60 = np.broadcast_to(mask, obs.shape)
        sel30 = sel60 & near[:, None, None]
        lam = jaxps.fit_brdf(images[train], ps.normals, ps.albedo, lights[train], mask=mask,
                             method="lambertian")
        pred = np.asarray(jaxps.relight(lam, ps.normals, ps.albedo, lights[test60], mask=mask))
        row = {"subject": subject, "train_set": set_name, "keys": list(keys),
               "lambertian": {"rmse_60": rmse(pred, obs, sel60),
                              "rmse_30": rmse(pred, obs, sel30)}, "methods": {}}
        for name in names:
            r60, r30 = [], []
            for i in keys:
                model = jaxps.fit_brdf(images[train], ps.normals, ps.albedo, lights[train],
                                       mask=mask, key=jax.random.key(i), **METHODS[name])
                pred = np.asarray(jaxps.relight(model, ps.normals, ps.albedo,
                                                lights[test60], mask=mask))
                r60.append(rmse(pred, obs, sel60))
                r30.append(rmse(pred, obs, sel30))
            row["methods"][name] = {
                "rmse_60": r60, "rmse_30": r30,
                "below_lambert_30": int(np.sum(np.array(r30) < row["lambertian"]["rmse_30"])),
                "below_lambert_60": int(np.sum(np.array(r60) < row["lambertian"]["rmse_60"]))}
            lam30, lam60 = row["lambertian"]["rmse_30"], row["lambertian"]["rmse_60"]
            print(f"{subject} {set_name} {name:28s} rmse30 {np.mean(r30):6.2f} "
                  f"[{min(r30):.2f}, {max(r30):.2f}] rmse60 {np.mean(r60):6.2f} "
                  f"[{min(r60):.2f}, {max(r60):.2f}] (lambert {lam30:.2f} / {lam60:.2f})",
                  flush=True)
        out.append(row)
    return out


def points(res):
    """The runner's contract (`python -m benchmarks`): one point per method and test set, held-out
    RMSE (gray levels) against the time to relight the test lights."""
    pts = []
    for row in res.get("accuracy", []):
        for name, m in row["methods"].items():
            if "skipped" in m:
                continue
            for limit in ("60", "30"):
                pts.append({"panel": f"relight {row['subject']} {row['train_set']} <={limit} deg",
                            "method": name, "run_s": m["relight_s"], "error": m[f"rmse_{limit}"],
                            "error_name": "held-out RMSE (gray)", "baseline": name == "lambertian"})
    return pts


def chart(acc, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(acc), figsize=(4 * len(acc), 3.6), sharey=True, squeeze=False)
    for ax, row in zip(axes[0], acc):
        names = [n for n, m in row["methods"].items() if "skipped" not in m]
        x = np.arange(len(names))
        ax.bar(x - 0.2, [row["methods"][n]["rmse_60"] for n in names], 0.4, label="<= 60 deg")
        ax.bar(x + 0.2, [row["methods"][n]["rmse_30"] for n in names], 0.4, label="<= 30 deg")
        ax.set_xticks(x, names, rotation=60, ha="right", fontsize=7)
        ax.set_title(f"{row['subject']} {row['train_set']}", fontsize=9)
    axes[0, 0].set_ylabel("held-out RMSE (gray levels)")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("accuracy", "speed", "loop", "gains", "seeds", "all"),
                        default="all")
    parser.add_argument("--subjects", nargs="+", default=["yaleB01", "yaleB02"])
    parser.add_argument("--sets", nargs="+", default=["cross", "alt"])
    parser.add_argument("--methods", nargs="+", default=None, choices=list(METHODS),
                        help="accuracy: refit only these methods (other methods of a stored row "
                        "are kept)")
    parser.add_argument("--quick", action="store_true",
                        help="speed only, 20,000 samples, 5 LM steps, 350x425 (kept apart under "
                        "'speed_quick'; the stored accuracy figures are left as they are)")
    args = parser.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    # the BRDF-in-the-loop and gains parts write their own files (they can run beside the others)
    path = OUT / {"loop": "brdf_loop.json", "gains": "brdf_gains.json",
                  "seeds": "brdf_seeds.json"}.get(args.part, "brdf.json")
    res = json.loads(path.read_text()) if path.exists() else {}
    res["machine"] = {"platform": platform.platform(), "cpus": os.cpu_count(),
                      "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
                      "jax": jax.__version__, "backend": jax.default_backend(), "cpu": cpu_model()}
    if args.quick or os.environ.get("JAXPS_BENCH_QUICK"):
        res["speed_quick"] = speed(n_samples=20_000, h=350, w=425, steps=5)
        args.part = "none"
    if args.part in ("accuracy", "all"):
        new = accuracy(tuple(args.subjects), tuple(args.sets), args.methods)
        old = {(r["subject"], r["train_set"]): r for r in res.get("accuracy", [])}
        for r in new:  # keep the stored methods that were not refitted
            prev = old.get((r["subject"], r["train_set"]))
            if args.methods and prev is not None:
                r["methods"] = {**prev["methods"], **r["methods"]}
        done = {(r["subject"], r["train_set"]) for r in new}
        kept = [r for r in res.get("accuracy", []) if (r["subject"], r["train_set"]) not in done]
        res["accuracy"] = sorted(kept + new, key=lambda r: (r["train_set"] != "cross",
                                                            r["train_set"], r["subject"]))
        chart(res["accuracy"], OUT / "brdf.png")
    if args.part in ("speed", "all"):
        res["speed"] = speed()
    if args.part == "gains":
        res["gains"] = gains(tuple(args.subjects))
    if args.part == "seeds":
        res["seeds"] = seeds(tuple(args.subjects), tuple(args.sets))
    if args.part == "loop":
        res["loop"] = loop()
    elif args.part not in ("gains", "seeds"):
        res["points"] = points(res)
    path.write_text(json.dumps(res, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
