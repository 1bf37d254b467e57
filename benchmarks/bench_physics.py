"""Parametric reflectance (diffuse term + specular lobe) against Lambert on held-out Yale B lights.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_physics.py \
        [--subjects ...] [--methods ...] [--regions ...] [--refine 0 1] [--quick]

For each subject (the "cross" training set of bench_brdf.py: lights (0,0), (+-25,0), (0,+-20),
less frames `check_frames` flags), normals and albedo by L2 photometric stereo on the training
frames, every parametric method of `jaxps.fit_brdf` fitted with each specular region size, and
every other clean light within 60 (and 30) degrees relit: RMSE in gray levels over the face mask,
raw and gain-invariant (one least-squares gain per held-out image), and each as a ratio to
Lambert's. The configuration is then chosen leave-one-subject-out: for each subject, the one
with the lowest mean gain-invariant ratio within 30 degrees on the other four, scored on it.
Writes benchmarks/results/<out>.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import pathlib
import sys
import time

import jax
import numpy as np

import jaxps

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from benchmarks._common import yale_subjects
from benchmarks.bench_brdf import OUT, cases, gain_rmse, rmse

SUBJECTS = yale_subjects()  # every yaleB* folder found (_common)
METHODS = ("ggx", "blinn_phong", "wrap_ggx", "wrap", "oren_nayar")
REGIONS = (16, 32, 0)  # 0: one specular albedo for the whole face
REFINE = (False, True)  # normals refined jointly with the lobe
KEYS = ("rmse_30", "rmse_60", "gain_30", "gain_60")


def scores(pred, obs, mask, near):
    sel60 = np.broadcast_to(mask, obs.shape)
    return {"rmse_30": rmse(pred, obs, sel60 & near[:, None, None]),
            "rmse_60": rmse(pred, obs, sel60),
            "gain_30": gain_rmse(pred, obs, mask, near), "gain_60": gain_rmse(pred, obs, mask)}


def run(subjects, methods, regions, refine):
    rows = {}
    for c in cases(subjects, ["cross"]):
        obs = c.images[c.test60]
        n, a, tr = c.ps.normals, c.ps.albedo, c.train
        lam = jaxps.fit_brdf(c.images[tr], n, a, c.lights[tr], mask=c.mask, method="lambertian")
        base = scores(np.asarray(jaxps.relight(lam, n, a, c.lights[c.test60], mask=c.mask)), obs,
                      c.mask, c.near)
        row = {"lambertian": base, "mask_pixels": int(c.mask.sum()),
               "test_lights_30": int(c.near.sum()), "test_lights_60": len(c.test60)}
        for method in methods:
            lobe = "ggx" in method or "phong" in method
            for region, joint in itertools.product(regions if lobe else regions[:1], refine):
                t = time.perf_counter()
                model = jaxps.fit_brdf(c.images[tr], n, a, c.lights[tr], mask=c.mask,
                                       method=method, region=region or None,
                                       refine_normals=joint, key=jax.random.key(0))
                fit_s = time.perf_counter() - t
                pred = np.asarray(jaxps.relight(model, n, a, c.lights[c.test60], mask=c.mask))
                s = scores(pred, obs, c.mask, c.near)
                s.update({f"{k}_ratio": s[k] / base[k] for k in KEYS})
                f = model.fit
                s.update(fit_s=fit_s, steps=f.steps, converged=f.converged,
                         train_rmse_gray=f.rmse * 255, message=f.message,
                         shape=np.asarray(model.params.shape).tolist())
                name = f"{method}/region={region}" + ("/normals" if joint else "")
                row[name] = s
                print(f"{c.subject} {name:36s} gain30 {s['gain_30_ratio']:.4f} gain60 "
                      f"{s['gain_60_ratio']:.4f} raw30 {s['rmse_30_ratio']:.4f} "
                      f"shape {np.round(s['shape'], 3).tolist()} steps {f.steps} "
                      f"fit {fit_s:.1f}s", flush=True)
        rows[c.subject] = row
    return rows


def loso(rows, key="gain_30_ratio"):
    """Leave-one-subject-out choice of the configuration: lowest mean `key` over the other
    subjects; the held-out subject's figures under that choice."""
    subjects = sorted(rows)
    configs = [n for n in rows[subjects[0]] if "/" in n]
    out = {}
    for held in subjects:
        others = [s for s in subjects if s != held]
        pick = min(configs, key=lambda n: np.mean([rows[s][n][key] for s in others]))
        out[held] = {"config": pick, **{k: rows[held][pick][f"{k}_ratio"] for k in KEYS}}
    summary = {f"mean_{k}_ratio": float(np.mean([out[s][k] for s in subjects])) for k in KEYS}
    summary["below_lambert_gain_30"] = int(sum(out[s]["gain_30"] < 1 for s in subjects))
    return {"chosen_on": key, "per_subject": out, **summary}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--subjects", nargs="+", default=SUBJECTS)
    ap.add_argument("--methods", nargs="+", default=METHODS)
    ap.add_argument("--regions", nargs="+", type=int, default=REGIONS)
    ap.add_argument("--refine", nargs="+", type=int, default=[int(r) for r in REFINE])
    ap.add_argument("--out", default="physics.json")
    ap.add_argument("--quick", action="store_true",
                    help="one subject, one configuration, written to physics_quick.json (the "
                    "stored figures are left as they are); also with JAXPS_BENCH_QUICK set")
    args = ap.parse_args()
    if args.quick or os.environ.get("JAXPS_BENCH_QUICK"):
        args.subjects, args.methods, args.regions = ["yaleB01"], ["wrap_ggx"], [32]
        args.refine, args.out = [1], "physics_quick.json"
    rows = run(args.subjects, args.methods, args.regions, [bool(r) for r in args.refine])
    result = {"rows": rows, "loso": loso(rows) if len(rows) > 1 else None}
    if result["loso"]:
        print(json.dumps(result["loso"], indent=1))
    OUT.mkdir(exist_ok=True)
    (OUT / args.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
