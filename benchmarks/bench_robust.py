"""Speed and accuracy of the robust PS solvers at 1280x1024, K=5, against RobustPhotometricStereo.

Writes benchmarks/results/robust.json and robust.png (`--out NAME`: NAME.json, NAME.png). Run:
    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_robust.py
Baseline: RobustPhotometricStereo (Ikehata et al. 2012, github.com/yasumat/RobustPhotometricStereo)
`rpsnumerics.L1_residual_min` / `sparse_bayesian_learning`, imported from the folder in $RPS_PATH
(not part of this repository; GPL). Without it, a numpy reimplementation of the same per-pixel
IRLS / SBL loops (below) is timed instead, and the JSON says so. Its per-pixel loop is timed on a
random subset of object pixels and scaled to the whole object. Scene: `face_like` 1024x1280,
5 lights on a 45-degree cone (one on the axis), cast shadows, Blinn-Phong lobe (k_s 0.6,
exponent 100), 0.5% noise.
"""

import argparse
import importlib
import json
import os
import pathlib
import sys
import time

import jax
import numpy as np

import jaxps
from jaxps.evaluate import angular_stats
from jaxps.stability import render_corrupted, ring_lights

try:
    from benchmarks._common import cpu_model
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import cpu_model

OUT = pathlib.Path(__file__).resolve().parent / "results"


def numpy_l1(a, b, max_ite=1000, tol=1.0e-8):
    """Same algorithm as rpsnumerics.L1_residual_min (IRLS, W = 1/sqrt|r|)."""
    w = np.ones(len(b))
    x_old = np.ones(a.shape[1])
    x = x_old
    for _ in range(max_ite):
        x = np.linalg.lstsq(w[:, None] * a, w * b, rcond=None)[0]
        r = b - a @ x
        if np.linalg.norm(x - x_old) < tol:
            return x
        x_old = x
        w = 1.0 / np.maximum(np.sqrt(np.abs(r)), 1e-8)
    return x


def numpy_sbl(a, b, max_ite=1000, tol=1.0e-8):
    """Same algorithm as rpsnumerics.sparse_bayesian_learning."""
    gamma = np.ones(len(b))
    x_old = 1000 * np.ones(a.shape[1])
    x = x_old
    for _ in range(max_ite):
        wa = a / gamma[:, None]
        x = np.linalg.solve(1e-6 * np.eye(3) + a.T @ wa, wa.T @ b)
        if np.linalg.norm(x - x_old) < tol:
            break
        x_old = x
        e = b - a @ x
        xi = np.linalg.solve(np.eye(3) + a.T @ wa, a.T)
        gamma = np.maximum(e * e + np.sum(a * xi.T, axis=1), 1e-8)
    return x


def baseline():
    path = os.environ.get("RPS_PATH", "/work/scratch7/rps")
    if os.path.isfile(os.path.join(path, "rpsnumerics.py")):
        sys.path.insert(0, path)
        mod = importlib.import_module("rpsnumerics")

        def l1(a, b):
            return mod.L1_residual_min(a, b[:, None]).ravel()

        def sbl(a, b):
            return mod.sparse_bayesian_learning(a, b[:, None]).ravel()

        return "RobustPhotometricStereo rpsnumerics (original code, " + path + ")", l1, sbl
    return "numpy reimplementation of RobustPhotometricStereo's loops", numpy_l1, numpy_sbl


def time_ours(images, lights, mask, method, repeats, **opt):
    t = time.perf_counter()
    res = jaxps.photometric_stereo(images, lights, mask=mask, method=method, **opt)
    jax.block_until_ready(res)
    first = time.perf_counter() - t
    runs = []
    for _ in range(repeats):
        t = time.perf_counter()
        res = jaxps.photometric_stereo(images, lights, mask=mask, method=method, **opt)
        jax.block_until_ready(res)
        runs.append(time.perf_counter() - t)
    return res, first, runs


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--h", type=int, default=1024)
    ap.add_argument("--w", type=int, default=1280)
    ap.add_argument("--subset", type=int, default=1500)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="320x256, 200 baseline pixels")
    ap.add_argument("--out", default="robust",
                    help="name of the JSON and PNG in benchmarks/results (default robust)")
    args = ap.parse_args()
    if args.quick:
        args.h, args.w, args.subset, args.repeats = 256, 320, 200, 1
    surf = jaxps.synthetic.face_like(args.h, args.w)
    scene = render_corrupted(surf, ring_lights(5, 45.0), specular=0.6, shininess=100.0,
                             noise=0.005, key=jax.random.key(0))
    images = np.asarray(scene.images)
    lights = np.asarray(scene.lights)
    mask = np.asarray(scene.mask)
    truth = np.asarray(scene.normals)
    n_obj = int(mask.sum())
    rng = np.random.default_rng(0)
    rows, cols = np.nonzero(mask)
    pick = rng.choice(len(rows), args.subset, replace=False)
    sub = np.zeros_like(mask)
    sub[rows[pick], cols[pick]] = True

    doc = {"machine": {"OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
                       "jax": jax.__version__, "device": str(jax.devices()[0]),
                       "cpus": os.cpu_count(), "cpu": cpu_model()},
           "shape": [5, args.h, args.w], "object_pixels": n_obj,
           "scene": {"shadowed": float(np.asarray(scene.shadow)[:, mask].mean()),
                     "saturated": float((images[:, mask] >= 1).mean()),
                     "specular": float((np.asarray(scene.specular)[:, mask] > 0.02).mean())},
           "ours": {}, "baseline": {}}
    configs = [("l2", {}), ("l1", {}), ("barsky", {}), ("irls", {}),
               ("irls-huber", {"loss": "huber"}), ("sbl", {})]
    for name, opt in configs:
        method = name.split("-")[0]
        res, first, runs = time_ours(images, lights, mask, method, args.repeats, **opt)
        st = angular_stats(res.normals, truth, mask=mask)
        sst = angular_stats(res.normals, truth, mask=sub)
        doc["ours"][name] = {
            "first_call_s": first, "run_s": float(np.median(runs)), "runs_s": runs,
            "compile_s_est": first - float(np.median(runs)),
            "error_all": st, "error_subset": sst,
            "status": jaxps.status_counts(np.asarray(res.status)[mask]),
            "max_steps_taken": None if res.info is None else int(np.asarray(
                res.info["steps"]).max()),
            "_normals": np.asarray(res.normals),
        }
        print(name, f"first {first:.2f}s run {np.median(runs):.3f}s",
              f"mean {st['mean_deg']:.2f} median {st['median_deg']:.2f}", flush=True)

    label, l1, sbl = baseline()
    doc["baseline"]["source"] = label
    for name, fn, n in (("L1", l1, args.subset), ("SBL", sbl, args.subset // 3)):
        normals = np.zeros((n, 3))
        t = time.perf_counter()
        for j in range(n):
            x = fn(lights.astype(np.float64), images[:, rows[pick[j]], cols[pick[j]]]
                   .astype(np.float64))
            normals[j] = x / max(np.linalg.norm(x), 1e-12)
        dt = time.perf_counter() - t
        ref = truth[rows[pick[:n]], cols[pick[:n]]]
        err = np.degrees(np.arccos(np.clip(np.sum(normals * ref, axis=-1), -1, 1)))
        per_px = dt / n
        same = {}  # ours on exactly the pixels the baseline solved
        for ours_name in doc["ours"]:
            e = doc["ours"][ours_name]["_normals"][rows[pick[:n]], cols[pick[:n]]]
            e = np.degrees(np.arccos(np.clip(np.sum(e * ref, axis=-1), -1, 1)))
            same[ours_name] = {"median_deg": float(np.median(e)), "mean_deg": float(np.mean(e))}
        doc["baseline"][name] = {"pixels_timed": n, "seconds_timed": dt,
                                 "ms_per_pixel": 1e3 * per_px,
                                 "scaled_object_s": per_px * n_obj,
                                 "scaled_full_frame_s": per_px * args.h * args.w,
                                 "error_subset": {"median_deg": float(np.median(err)),
                                                  "mean_deg": float(np.mean(err))},
                                 "ours_on_same_pixels": same}
        print(name, f"{1e3 * per_px:.3f} ms/pixel -> {per_px * n_obj:.1f} s for the object",
              f"mean {np.mean(err):.2f}", flush=True)
    for rec in doc["ours"].values():
        del rec["_normals"]
    for ours, base in (("l1", "L1"), ("irls", "L1"), ("sbl", "SBL"), ("barsky", "L1")):
        doc["ours"][ours]["speedup_vs_" + base] = (doc["baseline"][base]["scaled_object_s"]
                                                   / doc["ours"][ours]["run_s"])
    panel = f"robust PS {args.w}x{args.h} K=5 (shadows+highlights)"
    doc["points"] = [
        {"panel": panel, "method": k, "run_s": v["run_s"], "compile_s": v["compile_s_est"],
         "error": v["error_all"]["mean_deg"], "error_name": "mean angular error (deg)",
         "baseline": False} for k, v in doc["ours"].items()] + [
        {"panel": panel, "method": "RobustPhotometricStereo " + b,
         "run_s": doc["baseline"][b]["scaled_object_s"],
         "error": doc["baseline"][b]["error_subset"]["mean_deg"],
         "error_name": "mean angular error (deg)", "baseline": True} for b in ("L1", "SBL")]
    OUT.mkdir(exist_ok=True)
    (OUT / f"{args.out}.json").write_text(json.dumps(doc, indent=1))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    names = list(doc["ours"]) + ["RPS " + b for b in ("L1", "SBL")]
    times = [doc["ours"][k]["run_s"] for k in doc["ours"]] + [
        doc["baseline"][b]["scaled_object_s"] for b in ("L1", "SBL")]
    errs = [doc["baseline"]["SBL"]["ours_on_same_pixels"][k]["mean_deg"] for k in doc["ours"]] + [
        doc["baseline"][b]["error_subset"]["mean_deg"] for b in ("L1", "SBL")]
    a1.barh(names, times)
    a1.set_xscale("log")
    a1.set_xlabel(f"seconds for {n_obj} object pixels, K=5 (RPS scaled from a subset)")
    a2.barh(names, errs)
    a2.set_xlabel("mean angular error on the pixels RPS SBL solved (deg; RPS L1 on its own subset)")
    fig.suptitle(f"robust PS {args.w}x{args.h}, K=5, {doc['machine']['device']}, "
                 f"OPENBLAS_NUM_THREADS={doc['machine']['OPENBLAS_NUM_THREADS']}")
    fig.tight_layout()
    fig.savefig(OUT / f"{args.out}.png", dpi=110)


if __name__ == "__main__":
    main()
