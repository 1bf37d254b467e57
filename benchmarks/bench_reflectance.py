"""Reflectance analysis on Yale B (Table-1-shaped check, roughness, held-out relighting) and speed.

Run: `OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_reflectance.py [--size 1024]`
Writes benchmarks/results/reflectance.json and reflectance.png (Fig.-7-like panels).

Real data: ../shared/data/yaleb (or $JAXPS_DATA/yaleb). Every frame has the ambient frame
subtracted (clipped at 0) and is scaled to [0, 1]. Face mask (there is no mask file): pixels
whose ambient-subtracted value exceeds 8/255 in at least 90% of the frames lit within 50 degrees
of the view axis, and whose mean over those frames is at least 10% of its 99th percentile.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import pathlib
import platform

import cv2
import jax
import jax.numpy as jnp
import numpy as np

import jaxps

try:
    from benchmarks._common import clean_frames, time_calls
except ImportError:  # run as a script
    import sys

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import clean_frames, time_calls

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
TRAIN = [(0, 0), (25, 0), (-25, 0), (0, 20), (0, -20)]


def data_dir() -> pathlib.Path:
    return pathlib.Path(os.environ.get("JAXPS_DATA", ROOT.parent / "shared" / "data"))


def load_yale(subject_dir):
    """(images (K, H, W) float32 ambient-subtracted, angles (K, 2) degrees, lights (K, 3)) of
    the frames that pass `jaxps.check_frames` (`clean_frames`: yaleB02 loses two combed ones)."""
    files = sorted(glob.glob(os.path.join(subject_dir, "*.pgm")))
    amb_file = [f for f in files if f.endswith("_Ambient.pgm")][0]
    amb = cv2.imread(amb_file, cv2.IMREAD_UNCHANGED).astype(np.float32) / 255
    ims, angs = [], []
    for f in files:
        ae = jaxps.parse_yale_name(f)
        if ae is None:
            continue
        im = cv2.imread(f, cv2.IMREAD_UNCHANGED)
        if im is None:
            continue
        ims.append(np.clip(im.astype(np.float32) / 255 - amb, 0, 1))
        angs.append(ae)
    angs = np.asarray(angs, np.float32)
    ims = np.stack(ims)
    clean = clean_frames(ims, angs, os.path.basename(os.path.normpath(subject_dir)))
    ims, angs = ims[clean], angs[clean]
    return ims, angs, jaxps.lights_from_angles(angs[:, 0], angs[:, 1])


def face_mask(images, zenith_deg):
    near = images[zenith_deg <= 50]
    lit = (near > 8 / 255).mean(0) >= 0.9
    mean = near.mean(0)
    return lit & (mean >= 0.1 * np.percentile(mean, 99))


def subject_figures(subject_dir):
    images, angs, lights = load_yale(subject_dir)
    zen = np.degrees(np.arccos(np.clip(lights[:, 2], -1, 1)))
    mask = face_mask(images, zen)
    near = zen <= 50
    ref = jaxps.photometric_stereo(images[near], lights[near], mask=mask)
    ok = mask & (np.asarray(ref.status) == 0)
    rows = {}
    checks = {}
    for name, sel in (("lights<=50", near), ("all lights", np.ones_like(near))):
        chk = jaxps.lambertian_check(images[sel], ref.normals, ref.albedo, lights[sel], mask=ok)
        rows[name] = {"rms_60": chk.rms_60, "sd_60": chk.sd_60, "rms_all": chk.rms_all,
                      "sd_all": chk.sd_all, "rms_samples_60": chk.rms_samples_60,
                      "rms_samples_all": chk.rms_samples_all, "samples": chk.n_samples}
        checks[name] = chk
    # Global roughness on the within-50 set, with the reference normals fixed (albedo refitted).
    fit = jaxps.fit_roughness(images[near], ref.normals, ref.albedo, lights[near], mask=ok)
    fit_pix = jaxps.fit_roughness(images[near], ref.normals, ref.albedo, lights[near], mask=ok,
                                  per="pixel")
    sp = np.asarray(fit_pix.sigma)[ok]
    on_ref = jaxps.photometric_stereo(images[near], lights[near], mask=mask,
                                      method="oren_nayar", sigma="global")
    sig_joint = float(np.max(np.asarray(on_ref.info["sigma"])[ok]))
    # Lambertian check again with the Oren-Nayar curve for the jointly fitted sigma.
    checks["frames"] = int(len(images))
    checks["on"] = jaxps.lambertian_check(images[near], ref.normals, ref.albedo, lights[near],
                                          mask=ok, sigma=max(sig_joint, 0.2))

    # The scanner's five lights; one that check_frames flagged (yaleB02's +25,0) is replaced
    # by the nearest clean light (+20,+10): compare_models needs five training lights.
    train = np.zeros(len(angs), bool)
    for a, e in TRAIN:
        light = jaxps.lights_from_angles([a], [e])[0]
        order = np.argsort(-(lights @ light))
        train[next(i for i in order if not train[i])] = True
    assert train.sum() == 5
    within60 = zen <= 60
    keep = train | within60
    # Regions: 3x3 grid over the face's bounding box (forehead/eyes/cheeks/mouth/chin bands).
    ys, xs = np.nonzero(ok)
    labels = np.full(ok.shape, -1, np.int32)
    gy = np.clip((np.arange(ok.shape[0])[:, None] - ys.min()) * 3 // (np.ptp(ys) + 1), 0, 2)
    gx = np.clip((np.arange(ok.shape[1])[None, :] - xs.min()) * 3 // (np.ptp(xs) + 1), 0, 2)
    labels = np.where(ok, gy * 3 + gx, -1).astype(np.int32)
    mc = jaxps.compare_models(images[keep], lights[keep], train=train[keep], mask=ok,
                              labels=labels)
    within30 = keep & ((zen <= 30) | train)
    mc30 = jaxps.compare_models(images[within30], lights[within30], train=train[within30],
                                mask=ok)
    return {
        "frames": int(len(images)), "frames_within_50": int(near.sum()),
        "train_lights_deg": angs[train].tolist(),
        "frames_test_within_60": int((within60 & ~train).sum()),
        "mask_pixels": int(mask.sum()), "ref_ps_ok_pixels": int(ok.sum()),
        "table1": rows,
        "sigma_global_fixed_normals": float(fit.sigma), "sigma_global_status":
            jaxps.Status(int(fit.status)).name, "sigma_global_steps": int(fit.steps),
        "rms_fit_lambertian": float(fit.rms_lambertian) * 255,
        "rms_fit_oren_nayar": float(fit.rms) * 255,
        "sigma_pixel_median": float(np.median(sp)),
        "sigma_pixel_p10_p90": [float(v) for v in np.percentile(sp, [10, 90])],
        "sigma_pixel_status": jaxps.status_counts(np.asarray(fit_pix.status)[ok]),
        "sigma_global_joint_on_ps": sig_joint,
        "joint_on_ps_status": jaxps.status_counts(np.asarray(on_ref.status)[ok]),
        "heldout_within60": {"rmse_gray": mc.rmse, "bic": mc.bic, "sigma": mc.sigma,
                             "sigma_status": jaxps.Status(mc.sigma_status).name,
                             "choice": mc.choice, "test_samples": mc.test_samples,
                             "region_sigma": [float(v) for v in mc.region_sigma],
                             "region_rmse_lambertian_on": mc.region_rmse.tolist(),
                             "region_choice": mc.region_choice},
        "heldout_within30": {"rmse_gray": mc30.rmse, "sigma": mc30.sigma, "choice": mc30.choice,
                             "test_samples": mc30.test_samples},
    }, checks


def synthetic_accuracy():
    """Angular error of L2 vs Oren–Nayar PS on face_like(80) rendered with known sigma."""
    surf = jaxps.synthetic.face_like(80)
    m = surf.mask
    x, y = np.meshgrid(np.arange(m.shape[1]), np.arange(m.shape[0]))
    albedo = jnp.where(m, 0.6 + 0.2 * np.sin(x / 7.0) * np.cos(y / 9.0), 0).astype(jnp.float32)
    sets = {"scanner5_20deg": jaxps.synthetic.scanner_lights(20.0),
            "eight_lights": jaxps.lights_from_angles([0, 30, -30, 0, 0, 45, -45, 20],
                                                     [0, 0, 0, 30, -30, 20, -20, -40])}
    rows = []
    for name, lights in sets.items():
        for sigma in (0.1, 0.2, 0.3, 0.4):
            images = jaxps.render_oren_nayar(surf.normals, albedo, lights, sigma)
            images = jnp.clip(images + 0.005 * jax.random.normal(jax.random.key(1), images.shape),
                              0, 1)
            row = {"lights": name, "sigma_true": sigma, "noise": 0.005}
            l2 = jaxps.photometric_stereo(images, lights, mask=m)
            row["l2_mean_deg"] = jaxps.evaluate.angular_stats(l2.normals, surf.normals,
                                                              mask=m)["mean_deg"]
            fit = jaxps.fit_roughness(images, surf.normals, albedo, lights, mask=m)
            row["sigma_global_true_normals"] = float(fit.sigma)
            fit_l2 = jaxps.fit_roughness(images, l2.normals, l2.albedo, lights, mask=m)
            row["sigma_global_l2_normals"] = float(fit_l2.sigma)
            for mode in ("pixel", "global"):
                r = jaxps.photometric_stereo(images, lights, mask=m, method="oren_nayar",
                                             sigma=mode)
                ok = m & (np.asarray(r.status) == 0)
                row[f"on_{mode}_mean_deg"] = jaxps.evaluate.angular_stats(
                    r.normals, surf.normals, mask=ok)["mean_deg"]
                row[f"on_{mode}_sigma_median"] = float(np.median(np.asarray(r.info["sigma"])[ok]))
                row[f"on_{mode}_ok_fraction"] = float(ok.sum() / m.sum())
            rows.append(row)
            print(row)
    return rows


def _time(fn, repeats=1):
    out = time_calls(fn, repeats)
    print(out, flush=True)
    return out


def xla_reduction(k=5, n=1 << 20):
    """Why the solvers unroll sums over the lights: `jnp.sum(x * y, axis=0)` over a short
    leading axis against `jaxps.core._reduce.sum0` (K - 1 adds), both jitted, best of 20."""
    from jaxps.core._reduce import sum0

    x = jax.random.uniform(jax.random.key(0), (k, n))
    y = jax.random.uniform(jax.random.key(1), (k, n))
    out = {"shape": [k, n]}
    for name, fn in (("jnp_sum_axis0", lambda a, b: jnp.sum(a * b, axis=0)),
                     ("sum0_unrolled", lambda a, b: sum0(a * b))):
        f = jax.jit(fn)
        out[name + "_ms"] = 1e3 * time_calls(lambda: f(x, y), 20)["run_s_min"]
    print(out, flush=True)
    return out


def speed(size):
    surf = jaxps.synthetic.sphere(size, max_zenith_deg=75)
    lights = jaxps.synthetic.scanner_lights(20.0)
    albedo = jnp.where(surf.mask, 0.7, 0.0).astype(jnp.float32)
    images = jaxps.render_oren_nayar(surf.normals, albedo, lights, 0.3)
    images = jnp.clip(images + 0.005 * jax.random.normal(jax.random.key(0), images.shape), 0, 1)
    m = surf.mask
    out = {"size": [size, size], "pixels_in_mask": int(m.sum()), "lights": 5}
    out["l2_ps"] = _time(lambda: jaxps.photometric_stereo(images, lights, mask=m).normals, repeats=3)
    out["sigma_per_pixel"] = _time(lambda: jaxps.fit_roughness(
        images, surf.normals, albedo, lights, mask=m, per="pixel").sigma, repeats=3)
    out["sigma_global"] = _time(lambda: jaxps.fit_roughness(
        images, surf.normals, albedo, lights, mask=m).sigma, repeats=3)
    out["oren_nayar_ps_pixel"] = _time(lambda: jaxps.photometric_stereo(
        images, lights, mask=m, method="oren_nayar").normals, repeats=3)
    r = jaxps.photometric_stereo(images, lights, mask=m, method="oren_nayar")
    out["oren_nayar_ps_pixel"]["max_steps_used"] = int(r.info["steps"].max())
    out["oren_nayar_ps_pixel"]["status"] = jaxps.status_counts(np.asarray(r.status)[m])
    out["oren_nayar_ps_fixed_sigma"] = _time(lambda: jaxps.photometric_stereo(
        images, lights, mask=m, method="oren_nayar", sigma=0.3).normals, repeats=3)
    out["oren_nayar_ps_global_sigma"] = _time(lambda: jaxps.photometric_stereo(
        images, lights, mask=m, method="oren_nayar", sigma="global").normals, repeats=3)
    # The same per-pixel sigma fit through optimistix under vmap, on a small crop (slow path).
    c = 64
    win = slice(size // 2 - c // 2, size // 2 + c // 2)
    crop, ncrop, acrop = images[:, win, win], surf.normals[win, win], albedo[win, win]
    import optimistix as optx

    lm = optx.LevenbergMarquardt(rtol=1e-4, atol=1e-6)
    t_optx = _time(lambda: jaxps.fit_roughness(crop, ncrop, acrop, lights, per="pixel",
                                               solver=lm).sigma, repeats=1)
    t_exact = _time(lambda: jaxps.fit_roughness(crop, ncrop, acrop, lights,
                                                per="pixel").sigma, repeats=1)
    t_batched = _time(lambda: jaxps.fit_roughness(crop, ncrop, acrop, lights, per="pixel",
                                                  solver=jaxps.BatchedLM()).sigma, repeats=1)
    out["per_pixel_64x64_optimistix_vmap_vs_batched"] = {"optimistix": t_optx,
                                                         "batched_lm": t_batched,
                                                         "closed_form": t_exact}
    # The same fits on the whole image with the per-pixel LM (the path taken for the full
    # form or a given albedo), for comparison with the closed form above.
    out["sigma_per_pixel_batched_lm"] = _time(lambda: jaxps.fit_roughness(
        images, surf.normals, albedo, lights, mask=m, per="pixel",
        solver=jaxps.BatchedLM()).sigma, repeats=3)
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--skip-speed", action="store_true",
                    help="keep the stored speed section of reflectance.json, do not rerun it")
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    result = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                          "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
                          "load_avg_at_start": os.getloadavg(), "jax": jax.__version__,
                          "backend": jax.default_backend()}}
    yale = data_dir() / "yaleb"
    checks = {}
    if yale.is_dir():
        result["yaleb"] = {}
        for subject in ("yaleB01", "yaleB02"):
            result["yaleb"][subject], checks[subject] = subject_figures(yale / subject)
            print(subject, json.dumps(result["yaleb"][subject]["table1"], indent=1))
    result["synthetic"] = synthetic_accuracy()
    stored = OUT / "reflectance.json"
    if args.skip_speed and stored.exists():
        old = json.loads(stored.read_text())
        if "speed" in old:
            result["speed"] = old["speed"]
            result["speed_machine"] = old.get("speed_machine", old.get("machine"))
    if not args.skip_speed:
        result["speed"] = speed(args.size)
        result["speed"]["xla_reduction"] = xla_reduction()
        print(json.dumps(result["speed"], indent=1))
    result["machine"]["load_avg_at_end"] = os.getloadavg()
    with open(OUT / "reflectance.json", "w") as f:
        json.dump(result, f, indent=1)
    if checks:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 2 * len(checks), figsize=(5 * 2 * len(checks), 3.8))
        for j, (subject, ch) in enumerate(checks.items()):
            jaxps.plot_lambertian_check(ch["on"], ax=axes[2 * j],
                                        title=f"{subject}, lights <= 50 deg: RMS "
                                        f"{ch['on'].rms_60:.3f} / {ch['on'].rms_all:.3f}")
            jaxps.plot_lambertian_check(ch["all lights"], ax=axes[2 * j + 1],
                                        title=f"{subject}, all {ch['frames']} "
                                        "lights: RMS "
                                        f"{ch['all lights'].rms_60:.3f} / "
                                        f"{ch['all lights'].rms_all:.3f}")
        fig.tight_layout()
        fig.savefig(OUT / "reflectance.png", dpi=110)
    print("wrote", OUT / "reflectance.json")


if __name__ == "__main__":
    main()
