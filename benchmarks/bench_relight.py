"""Held-out relighting on the Yale B faces (every `yaleB*` folder of the data: the five shared
ones here): every model against Lambert's law, and `fit_brdf(method="auto")`'s settings chosen
leave-one-subject-out.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_relight.py \
        [--subjects yaleB01 ...] [--models lambertian mlp ...] [--candidates mlp ...] \
        [--n-samples 20000] [--max-steps 15] [--register]

Writes benchmarks/results/relight.json, relight.png and docs/images/relight_<subject>.png.
Protocol (`jaxps.score_relighting`): per subject, train on the scanner's five lights "cross"
(0,0), (+-25,0), (0,+-20) less the frames `jaxps.check_frames` flags (yaleB02 loses +25,0),
normals and albedo by L2 photometric stereo on those frames, face mask as in bench_brdf.py;
every other clean light within 60 degrees is held out. A model name is a `fit_brdf` method
(any of `jaxps.BRDF_METHODS`, including ones added later) or a variant of bench_brdf.py's
METHODS (e.g. `mlp_loo`); every fit uses `--n-samples` and `--max-steps`. `--register`: every
frame within 60 degrees is first moved onto the (0,0) frame (the subjects moved 0.4-3.5 px
between frames; `bench_brdf.load_yale`), training and held-out frames alike.

`auto`: the model `fit_brdf(method="auto", candidates=--candidates)` with the library's
defaults. Besides, the leave-one-light-out folds (`lolo_folds`, the candidates fitted on four
of the five training frames) are computed once per subject; every setting of (regions, margin) in the grid
below is scored on the held-out lights; for each subject, the setting with the smallest worst
raw RMSE / Lambert within 30 deg over the *other four* subjects (then the smallest mean) is
applied to it ("auto (LOSO)"); ties go to the larger margin, then the fewer regions. The
same rule over all five gives the library's default.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxps
from jaxps.reflectance._auto import choose_regions, lolo_folds

try:
    from benchmarks import bench_brdf
    from benchmarks._common import yale_subjects
    from benchmarks.bench_brdf import METHODS, cases
except ImportError:  # run as a script
    import sys

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks import bench_brdf
    from benchmarks._common import yale_subjects
    from benchmarks.bench_brdf import METHODS, cases

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
IMAGES = ROOT / "docs" / "images"
SUBJECTS = yale_subjects()  # every yaleB* folder found (_common)
REGIONS = (1, 2, 4, 8)
MARGINS = (0.0, 1.0, 2.0, 3.0)
PICTURE_LIGHT = (-20, 10)  # one held-out light within 30 deg, shown in the pictures


def options_of(name, n_samples, max_steps):
    kw = dict(METHODS.get(name, {"method": name}))
    return {**kw, "n_samples": n_samples, "max_steps": max_steps, "key": jax.random.key(0)}


def score_dict(s: jaxps.RelightScore):
    return {"model": s.model, "lambertian": s.lambertian, "ratio": s.ratio, "lights": s.lights,
            "outside_fraction": s.outside_fraction,
            "gains": {k: [None if np.isnan(x) else float(x) for x in v]
                      for k, v in s.gains.items()}}


def subject_run(c, models, candidates, n_samples, max_steps):
    """Scores of every model, and of every auto setting, for one `bench_brdf.Case`."""
    images, lights, train, test = c.images, c.lights, c.train, c.test60
    normals, albedo, mask = c.ps.normals, c.ps.albedo, c.mask
    args = (images[train], normals, albedo, lights[train])
    row = {"subject": c.subject, "train_lights_deg": [c.angles[i] for i in train],
           "flagged_frames_deg": [c.angles[i] for i in range(len(c.angles)) if not c.clean[i]],
           "test_lights_60": len(test), "test_lights_30": int(c.near.sum()),
           "mask_pixels": int(mask.sum()), "models": {}}
    fitted, preds = {}, {}  # preds: (H, W) relit under PICTURE_LIGHT
    pic = lights[[c.angles.index(PICTURE_LIGHT)]]
    for name in dict.fromkeys(["lambertian", *models, *candidates]):
        # "auto": fit_brdf's own defaults (regions, margin) among the benchmark's candidates
        extra = {"candidates": tuple(candidates)} if name == "auto" else {}
        t = time.perf_counter()
        try:
            fitted[name] = jaxps.fit_brdf(*args, mask=mask,
                                          **options_of(name, n_samples, max_steps), **extra)
        except ValueError as exc:  # e.g. shrink="loo" with the four frames of yaleB02
            row["models"][name] = {"skipped": str(exc)}
            print(f"{c.subject} {name:12s} skipped: {exc}", flush=True)
            continue
        fit_s = time.perf_counter() - t
        s = jaxps.score_relighting(fitted[name], images[test], normals, albedo, lights[test],
                                   mask=mask)
        preds[name] = np.asarray(jaxps.relight(fitted[name], normals, albedo, pic))[0]
        row["models"][name] = {**score_dict(s), "fit_s": fit_s, "shrink": fitted[name].fit.shrink,
                               "choice": fitted[name].fit.choice}
        print(f"{c.subject} {name:12s} raw30 {s.model['raw_30']:6.2f} "
              f"({s.ratio['raw_30']:.4f}x) gain30 {s.model['gain_30']:6.2f} "
              f"({s.ratio['gain_30']:.4f}x) raw60 {s.ratio['raw_60']:.4f}x "
              f"gain60 {s.ratio['gain_60']:.4f}x fit {fit_s:5.1f}s", flush=True)
    if "auto" not in models:
        return row, preds
    t = time.perf_counter()
    opts = options_of("mlp", n_samples, max_steps)
    opts.pop("method")
    opts.update(ps_method="l2", saturation=1.0)
    folds = [] if len(train) < 5 else lolo_folds(  # as fit_brdf(method="auto") does
        jaxps.fit_brdf, jaxps.relight, images[train], lights[train], mask, candidates,
        ps_method="l2", saturation=1.0, options=opts)
    row["auto_folds_s"] = time.perf_counter() - t
    row["auto"] = {}
    for regions in REGIONS:
        for margin in MARGINS:
            name, gate, report = choose_regions(folds, mask, regions=regions, margin=margin)
            model = fitted[name] if gate is None else dataclasses.replace(
                fitted[name], gate=jnp.asarray(gate, jnp.float32))
            s = jaxps.score_relighting(model, images[test], normals, albedo, lights[test],
                                       mask=mask)
            row["auto"][f"{regions}x{margin:g}"] = {
                "regions": regions, "margin": margin, "choice": name,
                "gate_fraction": report.get("gate_fraction", 0.0),
                "lolo_rmse_gray": {k: v * 255 for k, v in report.get("lolo_rmse", {}).items()},
                **score_dict(s)}
            print(f"{c.subject} auto {regions}x{margin:g}: {name} gate "
                  f"{report.get('gate_fraction', 0.0):.2f} raw30 {s.ratio['raw_30']:.4f}x "
                  f"gain30 {s.ratio['gain_30']:.4f}x", flush=True)
            preds[f"auto {regions}x{margin:g}"] = np.asarray(
                jaxps.relight(model, normals, albedo, pic))[0]
    return row, preds


def pick(rows, subjects, ties="conservative"):
    """The auto setting with the smallest worst raw RMSE / Lambert within 30 deg over
    `subjects`, then the smallest mean. `ties="conservative"`: then the largest margin, then
    the fewest regions (the model closest to Lambert's law among equals); `"first"`: the first
    in REGIONS x MARGINS order (the rule of the first run, which gave yaleB04 margin 0)."""
    def key(setting):
        a = rows[0]["auto"][setting]
        r = [row["auto"][setting]["ratio"]["raw_30"] for row in rows if row["subject"] in subjects]
        tail = (-a["margin"], a["regions"]) if ties == "conservative" else ()
        return (max(r), float(np.mean(r)), *tail)
    return min(rows[0]["auto"], key=key)


def loso(rows, ties="conservative"):
    """Leave-one-subject-out: each subject scored with the setting picked on the others."""
    out = {}
    for row in rows:
        others = [r["subject"] for r in rows if r is not row]
        setting = pick(rows, others, ties)
        a = row["auto"][setting]
        out[row["subject"]] = {"setting": setting, "picked_on": others, "choice": a["choice"],
                               "gate_fraction": a["gate_fraction"], "ratio": a["ratio"],
                               "model": a["model"]}
    return out


def pictures(c, preds, path):
    """The real held-out photograph under PICTURE_LIGHT, each model's relit image and its
    error (relit - real, gray levels, one colour scale), raw and after the image's
    least-squares gain (the gain-invariant error: the flash strength taken out)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    real = c.images[c.angles.index(PICTURE_LIGHT)] * 255
    names = list(preds)
    fig, axes = plt.subplots(3, len(names) + 1, figsize=(1.9 * (len(names) + 1), 6.9))
    box = np.argwhere(c.mask)
    (r0, c0), (r1, c1) = box.min(0), box.max(0) + 1
    crop = (slice(r0, r1), slice(c0, c1))
    axes[0, 0].imshow(real[crop], cmap="gray", vmin=0, vmax=255)
    axes[0, 0].set_title(f"real, light {PICTURE_LIGHT}", fontsize=8)
    axes[1, 0].text(0.5, 0.5, "relit - real\n(raw)", ha="center", va="center", fontsize=9)
    axes[2, 0].text(0.5, 0.5, "relit x best gain\n- real", ha="center", va="center",
                    fontsize=9)
    for j, name in enumerate(names, start=1):
        p = preds[name] * 255
        gain = float(p[c.mask] @ real[c.mask] / (p[c.mask] @ p[c.mask]))
        axes[0, j].imshow(np.where(c.mask, p, 0)[crop], cmap="gray", vmin=0, vmax=255)
        axes[0, j].set_title(name, fontsize=8)
        for row, q, label in ((1, p, "raw"), (2, gain * p, f"gain {gain:.2f}")):
            err = np.where(c.mask, q - real, np.nan)
            im = axes[row, j].imshow(err[crop], cmap="RdBu_r", vmin=-40, vmax=40)
            axes[row, j].set_title(f"{label}: RMSE {np.sqrt(np.nanmean(err**2)):.1f}",
                                   fontsize=7)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in axes[1:, 0]:
        ax.axis("off")
    fig.colorbar(im, ax=axes[1:, :].ravel().tolist(), fraction=0.02, label="gray")
    fig.suptitle(f"{c.subject}: held-out light {PICTURE_LIGHT} (azimuth, elevation deg)",
                 fontsize=9)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def chart(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), sharey=True)
    names = [n for n in rows[0]["models"] if n != "lambertian"]
    series = [*names, "auto (LOSO)"] if "auto_loso" in rows[0] else names
    nan = {"ratio": {"raw_30": np.nan, "gain_30": np.nan}}
    x = np.arange(len(rows))
    width = 0.8 / len(series)
    for ax, kind in zip(axes, ("raw_30", "gain_30")):
        for j, name in enumerate(series):
            vals = [r["auto_loso"]["ratio"][kind] if name == "auto (LOSO)"
                    else r["models"].get(name, nan).get("ratio", nan["ratio"])[kind]
                    for r in rows]
            ax.bar(x + (j - (len(series) - 1) / 2) * width, vals, width, label=name)
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_xticks(x, [r["subject"] for r in rows])
        ax.set_title(f"held-out RMSE / Lambert, {'raw' if kind == 'raw_30' else 'gain-invariant'}"
                     ", lights <= 30 deg", fontsize=9)
        ax.set_ylim(0.9, None)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--subjects", nargs="+", default=list(SUBJECTS))
    parser.add_argument("--models", nargs="+",
                        default=["lambertian", "mlp", "mlp_ratio", "delaunay", "mlp_loo", "auto"],
                        help="fit_brdf method names (jaxps.BRDF_METHODS) or bench_brdf variants")
    parser.add_argument("--candidates", nargs="+", default=["mlp", "mlp_ratio"],
                        help="the methods auto chooses among (default: fit_brdf's, with "
                        "BRDF_METHODS as of issue 16)")
    parser.add_argument("--out", default=str(OUT / "relight.json"), help="the JSON to write")
    parser.add_argument("--n-samples", type=int, default=20_000)
    parser.add_argument("--max-steps", type=int, default=15)
    parser.add_argument("--no-pictures", action="store_true")
    parser.add_argument("--register", action="store_true",
                        help="move every frame onto the (0,0) frame first")
    parser.add_argument("--quick", action="store_true",
                        help="yaleB01, lambertian and mlp, 3,000 samples, 3 LM steps, no pictures:"
                        " stored under 'quick' in relight.json, the other figures kept")
    args = parser.parse_args()
    quick = args.quick or bool(os.environ.get("JAXPS_BENCH_QUICK"))
    if quick:
        args.subjects, args.models, args.candidates = ["yaleB01"], ["lambertian", "mlp"], []
        args.n_samples, args.max_steps, args.no_pictures = 3_000, 3, True
    unknown = [m for m in [*args.models, *args.candidates]
               if m not in jaxps.BRDF_METHODS and m not in METHODS]
    if unknown:
        parser.error(f"unknown models {unknown}: use jaxps.BRDF_METHODS or {list(METHODS)}")
    OUT.mkdir(parents=True, exist_ok=True)
    bench_brdf.REGISTER = args.register
    t0 = time.perf_counter()
    rows, shown = [], []
    for c in cases(tuple(args.subjects), ("cross",)):
        row, preds = subject_run(c, args.models, args.candidates, args.n_samples, args.max_steps)
        rows.append(row)
        shown.append((c, preds))
    res = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                       "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
                       "jax": jax.__version__},
           "settings": {"train_set": "cross", "n_samples": args.n_samples,
                        "max_steps": args.max_steps, "key": 0, "models": args.models,
                        "candidates": args.candidates, "regions_grid": list(REGIONS),
                        "margin_grid": list(MARGINS), "picture_light": list(PICTURE_LIGHT),
                        "registered": args.register},
           "subjects": rows}
    if "auto" in args.models and len(rows) > 1:
        res["auto_loso"] = loso(rows)
        res["auto_loso_ties_first"] = loso(rows, ties="first")
        res["auto_pick_all"] = pick(rows, [r["subject"] for r in rows])
        for row in rows:
            row["auto_loso"] = res["auto_loso"][row["subject"]]
            print(f"{row['subject']} auto (LOSO) setting {row['auto_loso']['setting']} "
                  f"choice {row['auto_loso']['choice']} raw30 "
                  f"{row['auto_loso']['ratio']['raw_30']:.4f}x gain30 "
                  f"{row['auto_loso']['ratio']['gain_30']:.4f}x", flush=True)
        print(f"setting picked on all subjects: {res['auto_pick_all']}")
    for c, preds in [] if args.no_pictures else shown:
        row = next(r for r in rows if r["subject"] == c.subject)
        pics = {n: preds[n] for n in args.models if n in preds}
        pictures(c, pics, IMAGES / f"relight_{c.subject}.png")
    res["seconds"] = seconds = time.perf_counter() - t0
    path = pathlib.Path(args.out)
    if quick:  # a smoke run: keep the stored figures
        res = {**(json.loads(path.read_text()) if path.exists() else {}), "quick": res}
    else:
        chart(rows, path.with_suffix(".png"))
    path.write_text(json.dumps(res, indent=1))
    print(f"wrote {path} ({seconds:.0f} s)")


if __name__ == "__main__":
    main()
