"""Five-light normals on real faces against a semi-calibrated many-light reference (issue 17).

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_faces.py [--subjects ...]

For each shared Yale B subject (yaleB01..05, ambient frame subtracted):

- **reference**: `photometric_stereo(method="semi_calibrated")` over every light within 50 deg of
  the view axis whose frame `jaxps.check_frames` passes (yaleB02's two combed frames are left
  out);
- **half-set floor**: the same lights sorted by azimuth (then elevation), split into every other
  light, each half solved semi-calibrated; the median angle between the two halves' normals is
  how far two good many-light answers disagree on this face (non-Lambertian skin makes normals
  depend on the light set);
- **five-light candidates**: the scanner's cross lights (0,0), (+-25,0), (0,+-20), flagged frames
  dropped (yaleB02 keeps four), each per-frame intensity handling in `CANDIDATES`, then L2 PS.

The error of a candidate is the median angular error against the reference over the face
(reference albedo > 0.05 and every reference/half solve OK), written next to the subject's floor.
Candidates that learn from faces (`shape_prior`) learn leave-one-subject-out: the mean normal
field of the other subjects' references. Writes benchmarks/results/faces.json and faces.png
(error maps of one subject) and copies the figure to docs/images/faces_error_maps.png.
"""

from __future__ import annotations

import argparse
import pathlib
import shutil
import sys
import time

import jax.numpy as jnp
import numpy as np

import jaxps

try:
    from benchmarks._common import RESULTS, ROOT, data_dir, environment, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import RESULTS, ROOT, data_dir, environment, write_json

SUBJECTS = ("yaleB01", "yaleB02", "yaleB03", "yaleB04", "yaleB05")
CROSS = ((0, 0), (25, 0), (-25, 0), (0, 20), (0, -20))
MAX_ANGLE = 50.0
ALBEDO_MIN = 0.05


def load_subject(subject: str) -> dict:
    """Ambient-subtracted `(H, W)` frames in [0, 1] keyed by (azimuth, elevation)."""
    from jaxps.acquisition import read_image, subtract_ambient

    folder = data_dir() / "yaleb" / subject
    ambient = read_image(folder / f"{subject}_P00_Ambient.pgm")
    frames = {}
    for path in sorted(folder.glob(f"{subject}_P00A*.pgm")):
        angles = jaxps.parse_yale_name(path.name)
        if angles is not None:
            frames[tuple(round(a) for a in angles)] = subtract_ambient(read_image(path)[None], ambient)[0]
    return frames


def off_axis(azimuth, elevation):
    return np.degrees(np.arccos(np.cos(np.radians(azimuth)) * np.cos(np.radians(elevation))))


def lights_of(keys):
    return jaxps.lights_from_angles(*np.array(keys, np.float32).T)


def clean(frames, keys):
    """The keys whose frames `check_frames` passes, and the flagged ones with reasons."""
    stack = np.stack([frames[k] for k in keys])
    report = jaxps.check_frames(stack, names=[f"{a:+d},{e:+d}" for a, e in keys])
    kept = [k for k, keep in zip(keys, report.keep) if keep]
    return kept, {f.name: list(f.reasons) for f in report.flagged}


def semi(frames, keys):
    res = jaxps.photometric_stereo(jnp.asarray(np.stack([frames[k] for k in keys])),
                                   lights_of(keys), method="semi_calibrated")
    return res


def references(frames):
    """Reference, two half-set solves and the evaluation mask of one subject."""
    keys = sorted((k for k in frames if off_axis(*k) <= MAX_ANGLE), key=lambda k: (k[0], k[1]))
    keys, dropped = clean(frames, keys)
    ref = semi(frames, keys)
    halves = [semi(frames, keys[0::2]), semi(frames, keys[1::2])]
    ok = np.asarray(ref.status == 0) & np.asarray(ref.albedo > ALBEDO_MIN)
    for h in halves:
        ok &= np.asarray(h.status == 0)
    return keys, dropped, ref, halves, ok


def info_of(res):
    out = {}
    for key, v in res.info.items():
        v = np.asarray(v)
        out[key] = v.round(4).tolist() if v.dtype.kind == "f" else v.item() if v.ndim == 0 \
            else v.tolist()
    return out


# ---------------------------------------------------------------- five-light candidates
def _divide_and_solve(images, lights, e):
    e = jnp.asarray(e, images.dtype)
    res = jaxps.photometric_stereo(images / e[:, None, None], lights)
    return res, {"intensities": np.asarray(e).round(4).tolist()}


def cand_none(images, lights, ctx):
    return jaxps.photometric_stereo(images, lights), {}


def cand_estimate(method, **options):
    def run(images, lights, ctx):
        e = jaxps.intensity_estimate(images, lights, method=method, **options)
        return _divide_and_solve(images, lights, e)
    return run


def cand_frontal_lit(fraction):
    """`"frontal"` over the pixels lit in every frame (each sample at least `fraction` of its
    frame's 90th percentile): a pixel in attached or cast shadow under one light breaks the
    frame means' proportionality to $e_k l_k \\cdot \\bar b$, so it is left out of all of them."""
    def run(images, lights, ctx):
        im = np.asarray(images)
        top = np.percentile(im.reshape(len(im), -1), 90, axis=1)
        lit = np.all(im >= fraction * top[:, None, None], axis=0)
        e = jaxps.intensity_estimate(images, lights, method="frontal",
                                     mask=lit if lit.any() else None)
        return _divide_and_solve(images, lights, e)
    return run


def cand_semi(prior_weight):
    def run(images, lights, ctx):
        res = jaxps.photometric_stereo(images, lights, method="semi_calibrated",
                                       prior_weight=prior_weight)
        return res, info_of(res)
    return run


def _curl_ratio(images, lights, e, mask):
    """Curl energy of the L2 normals' gradient field over its variance (numpy).

    Normalised so that scaling the depth (a flattening) leaves it unchanged; dividing by the
    variance rather than the energy of the gradients also keeps a planar tilt from lowering it.
    """
    n = np.asarray(jaxps.photometric_stereo(images / e[:, None, None], lights).normals)
    nz = np.maximum(n[..., 2], 1e-3)
    p, q = -n[..., 0] / nz, -n[..., 1] / nz
    v = mask & (n[..., 2] > 0.3)
    gh, gv = (p[:, 1:] + p[:, :-1]) / 2, -(q[1:, :] + q[:-1, :]) / 2
    loop = gh[:-1, :] + gv[:, 1:] - gh[1:, :] - gv[:, :-1]
    inside = v[:-1, :-1] & v[1:, :-1] & v[:-1, 1:] & v[1:, 1:]
    return float(np.mean(loop[inside] ** 2) / (np.var(p[v]) + np.var(q[v])))


def cand_integrability(images, lights, ctx):
    """K-1 free log-intensities minimising `_curl_ratio` from the frontal start (Nelder-Mead,
    at most 150 evaluations, steps within +-0.2 of the start)."""
    import scipy.optimize

    from jaxps.acquisition import mask_from_intensity

    e0 = np.asarray(jaxps.intensity_estimate(images, lights, method="frontal"), np.float64)
    mask = mask_from_intensity(np.asarray(images))

    def intens(x):
        e = e0 * np.exp(np.concatenate([[0.0], np.clip(x, -0.2, 0.2)]))
        return jnp.asarray(e / np.exp(np.mean(np.log(e))), images.dtype)

    sol = scipy.optimize.minimize(lambda x: _curl_ratio(images, lights, intens(x), mask),
                                  np.zeros(len(e0) - 1), method="Nelder-Mead",
                                  options={"maxfev": 150, "initial_simplex": None})
    res, info = _divide_and_solve(images, lights, intens(sol.x))
    return res, {**info, "converged": bool(sol.success), "evaluations": int(sol.nfev)}


def cand_shape_prior(images, lights, ctx):
    """Leave-one-subject-out face prior: each frame's mean divided by the mean that the OTHER
    subjects' reference faces (normals, albedo; Lambert with attached shadows) give under the
    same light, geometric mean over those subjects."""
    ratios = []
    for normals, albedo in ctx["others"]:
        shade = jaxps.render_lambertian(normals, albedo, lights)
        ratios.append(np.log(np.asarray(shade, np.float64).reshape(len(lights), -1).mean(1)))
    expected = np.exp(np.mean(ratios, axis=0))
    means = np.asarray(images, np.float64).reshape(len(lights), -1).mean(1)
    e = means / expected
    return _divide_and_solve(images, lights, e / np.exp(np.mean(np.log(e))))


def cand_default_pipeline(images, lights, ctx):
    """What `load_capture(..., yale_names=True, ambient=..., check_quality=True)` and then
    `photometric_stereo` give with every other option at its default."""
    from jaxps.acquisition import load_capture

    cap = load_capture(ctx["paths"], yale_names=True, ambient=ctx["ambient"],
                       check_quality=True)
    res = jaxps.photometric_stereo(cap.images, cap.lights, mask=cap.mask,
                                   sample_mask=~cap.saturated)
    return res, {"intensities": np.round(1 / cap.gains / np.exp(np.mean(np.log(1 / cap.gains))),
                                         4).tolist(), "dropped": list(cap.dropped)}


def cand_oracle(images, lights, ctx):
    """The reference's own intensities for these lights (not available to a pipeline)."""
    return _divide_and_solve(images, lights, ctx["oracle"])


CANDIDATES = {
    "none": cand_none,
    "mean": cand_estimate("mean"),
    "frontal": cand_estimate("frontal"),
    **{f"frontal_lit{f}": cand_frontal_lit(f) for f in (0.05, 0.1, 0.2, 0.3)},
    "semi_calibrated": cand_semi(0.0),
    "semi_calibrated_prior0.1": cand_semi(0.1),
    "semi_calibrated_prior0.3": cand_semi(0.3),
    "semi_calibrated_prior1": cand_semi(1.0),
    "integrability": cand_integrability,
    "shape_prior_loo": cand_shape_prior,
    "default_load_capture": cand_default_pipeline,
    "oracle_reference_intensities": cand_oracle,
}
# The candidates a default may be chosen from (leave-one-subject-out, in `loo_choice`): the
# per-capture estimates that need nothing but the capture.
CHOOSABLE = ("none", "mean", "frontal", "frontal_lit0.05", "frontal_lit0.1", "frontal_lit0.2",
             "frontal_lit0.3", "semi_calibrated", "semi_calibrated_prior0.1",
             "semi_calibrated_prior0.3", "semi_calibrated_prior1", "integrability")


def loo_choice(subjects: dict) -> dict:
    """For each held-out subject: the `CHOOSABLE` candidate with the lowest median (over the
    other subjects) of the per-subject median error, and its error on the held-out one."""
    out = {}
    for held in subjects:
        rest = [r for s, r in subjects.items() if s != held]
        scores = {c: float(np.median([r["candidates"][c]["median_deg"] for r in rest]))
                  for c in CHOOSABLE}
        best = min(scores, key=scores.get)
        out[held] = {"chosen": best, "score_on_others_deg": scores[best],
                     "held_out_median_deg": subjects[held]["candidates"][best]["median_deg"],
                     "floor_median_deg": subjects[held]["floor"]["median_deg"]}
    return out


def run_subject(subject, frames, refs, ctx_extra):
    keys, dropped, ref, halves, ok = refs
    floor = jaxps.evaluate.angular_stats(halves[0].normals, halves[1].normals, mask=ok)
    five, five_dropped = clean(frames, list(CROSS))
    images = jnp.asarray(np.stack([frames[k] for k in five]))
    lights = lights_of(five)
    ref_e = np.asarray(ref.info["intensities"])
    oracle = np.array([ref_e[keys.index(k)] if k in keys else np.nan for k in five])
    ctx = {"oracle": oracle / np.exp(np.mean(np.log(oracle))), **ctx_extra}
    row = {
        "reference_lights": len(keys),
        "reference_dropped": dropped,
        "reference_info": info_of(ref),
        "halves_info": [info_of(h) for h in halves],
        "mask_pixels": int(ok.sum()),
        "floor": floor,
        "five_lights": [f"{a:+d},{e:+d}" for a, e in five],
        "five_dropped": five_dropped,
        "candidates": {},
    }
    maps = {}
    print(f"{subject}: {len(keys)} reference lights, floor median "
          f"{floor['median_deg']:.2f} deg, ref {row['reference_info']['steps']} steps "
          f"converged={row['reference_info']['converged']}", flush=True)
    for name, fn in CANDIDATES.items():
        res, info = fn(images, lights, ctx)
        stats = jaxps.evaluate.angular_stats(res.normals, ref.normals, mask=ok)
        row["candidates"][name] = {**stats, "floor_median_deg": floor["median_deg"], **info}
        maps[name] = np.asarray(jaxps.angular_error(res.normals, ref.normals))
        print(f"  {name:32s} median {stats['median_deg']:6.2f} (floor "
              f"{floor['median_deg']:.2f})  {info.get('intensities', '')}", flush=True)
    return row, maps, ok, np.asarray(jaxps.angular_error(halves[0].normals, halves[1].normals))


def plot(subject, maps, ok, floor_map, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [n for n in ("none", "mean", "frontal", "semi_calibrated_prior1", "integrability",
                         "shape_prior_loo", "oracle_reference_intensities") if n in maps]
    names = ["floor (half vs half)"] + shown
    fig, axes = plt.subplots(1, len(names), figsize=(2.2 * len(names), 2.9))
    for ax, name in zip(axes, names):
        err = floor_map if name.startswith("floor") else maps[name]
        shown = np.where(ok, err, np.nan)
        im = ax.imshow(shown, vmin=0, vmax=20, cmap="magma")
        ax.set_title(f"{name}\nmedian {np.median(err[ok]):.1f} deg", fontsize=7)
        ax.axis("off")
    fig.colorbar(im, ax=axes, fraction=0.02, label="angular error (deg)")
    fig.suptitle(f"{subject}: five cross lights against the 50-degree semi-calibrated reference",
                 fontsize=8)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", nargs="+", default=list(SUBJECTS))
    ap.add_argument("--figure-subject", default="yaleB01")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    data = {s: load_subject(s) for s in args.subjects}
    out = {"command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_faces.py "
                      + " ".join(sys.argv[1:] if argv is None else argv),
           "environment": environment(), "lights": [f"{a:+d},{e:+d}" for a, e in CROSS],
           "max_angle_deg": MAX_ANGLE, "subjects": {}}
    refs = {s: references(data[s]) for s in args.subjects}
    for subject in args.subjects:
        folder = data_dir() / "yaleb" / subject
        ctx = {"others": [(refs[o][2].normals, refs[o][2].albedo * refs[o][4])
                          for o in args.subjects if o != subject],
               "paths": [folder / f"{subject}_P00A{a:+04d}E{e:+03d}.pgm" for a, e in CROSS],
               "ambient": folder / f"{subject}_P00_Ambient.pgm"}
        row, maps, ok, floor_map = run_subject(subject, data[subject], refs[subject], ctx)
        out["subjects"][subject] = row
        if subject == args.figure_subject:
            plot(subject, maps, ok, floor_map, RESULTS / "faces.png")
    floors = [r["floor"]["median_deg"] for r in out["subjects"].values()]
    out["median_floor_deg"] = float(np.median(floors))
    out["median_over_subjects_deg"] = {
        name: float(np.median([r["candidates"][name]["median_deg"]
                               for r in out["subjects"].values()]))
        for name in CANDIDATES}
    out["loo"] = loo_choice(out["subjects"])
    out["loo_median_over_subjects_deg"] = float(np.median(
        [v["held_out_median_deg"] for v in out["loo"].values()]))
    print("leave-one-subject-out:", {k: (v["chosen"], round(v["held_out_median_deg"], 2))
                                     for k, v in out["loo"].items()})
    out["seconds"] = time.perf_counter() - t0
    print("median over subjects:", {k: round(v, 2) for k, v in
                                    out["median_over_subjects_deg"].items()},
          "floor", round(out["median_floor_deg"], 2))
    write_json("faces", out)
    if (RESULTS / "faces.png").exists():
        (ROOT / "docs" / "images").mkdir(exist_ok=True)
        shutil.copy(RESULTS / "faces.png", ROOT / "docs" / "images" / "faces_error_maps.png")
    return out


if __name__ == "__main__":
    main()
