"""Which photometric-stereo method for five scanner frames of a real face (issue 17's faces).

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/faces_methods.py [--register]

`bench_faces.py` compares ways to handle each flash's strength, always with L2 PS. This script
keeps the library's default capture handling and varies the solver instead. For each shared
Yale B subject, the five cross frames (0,0), (+-25,0), (0,+-20) are loaded the way `jaxps
reconstruct` loads them (`load_capture(..., yale_names=True, ambient=...)` with every other
option at its default: frontal intensities, motion undone, flagged frames dropped, saturated
samples left out), then solved by every method in `METHODS` with its default options. Each
normal map is scored against the same semi-calibrated many-light reference and half-set floor
as `bench_faces.py` (`--register`: the registered protocol, `faces_methods_registered.json`;
otherwise frames as read, `faces_methods.json`).

The rule for a default, fixed before any figure of this script was seen: leave one subject
out, pick the method with the lowest median (over the other four subjects) of the
per-subject median error, and score it on the held-out subject. A method replaces `"l2"` as
the command line's default only if every fold picks it and no held-out subject is worse with
it than with `"l2"`, in both protocols.

`--synthetic` checks the same methods away from the shared data instead: `face_like` (256x224)
under `scanner_lights` at 20 and 25 degrees, rendered by `jaxps.stability.render_corrupted` with
cast shadows, a Blinn-Phong lobe of strength 0, 0.3 or 0.6 (exponent 40), 0.5% noise and
clipping at 1 (clipped samples left out), scored against the true normals
(`faces_methods_synthetic.json`).
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np

import jaxps

try:
    from benchmarks._common import block, data_dir, environment, write_json
    from benchmarks.bench_faces import (
        SUBJECTS,
        load_subject,
        loo_choice,
        references,
        register_subject,
    )
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import block, data_dir, environment, write_json
    from benchmarks.bench_faces import (
        SUBJECTS,
        load_subject,
        loo_choice,
        references,
        register_subject,
    )

CROSS = ((0, 0), (25, 0), (-25, 0), (0, 20), (0, -20))
METHODS = ("l2", "barsky", "l1", "irls", "sbl", "oren_nayar")


def solve_all(cap, repeats=3):
    """Every method on one capture: `{method: (PSResult, seconds after compile)}`."""
    out = {}
    for method in METHODS:
        def run(method=method):
            return jaxps.photometric_stereo(cap.images, cap.lights, mask=cap.mask,
                                            sample_mask=~cap.saturated, method=method)
        res = block(run())
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            block(run())
            times.append(time.perf_counter() - t)
        out[method] = res, float(np.median(times))
    return out


def synthetic() -> dict:
    """`--synthetic`: every method on rendered five-light faces with known normals."""
    from jaxps.stability import render_corrupted

    surface = jaxps.synthetic.face_like(256, 224)
    mask = np.asarray(surface.mask)
    rows = []
    for zenith in (20.0, 25.0):
        lights = jaxps.synthetic.scanner_lights(zenith)
        for specular in (0.0, 0.3, 0.6):
            scene = render_corrupted(surface, lights, specular=specular, shininess=40.0,
                                     noise=0.005, key=0)
            row = {"zenith_deg": zenith, "specular": specular,
                   "shadowed_fraction": float(np.asarray(scene.shadow)[:, mask].mean()),
                   "clipped_fraction": float((np.asarray(scene.images)[:, mask] >= 1).mean()),
                   "methods": {}}
            for method in METHODS:
                res = jaxps.photometric_stereo(scene.images, lights, mask=mask,
                                               sample_mask=np.asarray(scene.images) < 1,
                                               method=method)
                row["methods"][method] = jaxps.evaluate.angular_stats(
                    res.normals, surface.normals, mask=mask)
            print(f"zenith {zenith:.0f}, specular {specular}: " + ", ".join(
                f"{m} {v['median_deg']:.2f} / {v['mean_deg']:.2f}"
                for m, v in row["methods"].items()), flush=True)
            rows.append(row)
    return {"scenes": rows}


def loo(subjects: dict) -> dict:
    """Leave-one-subject-out choice of the method (see the module's docstring):
    `bench_faces.loo_choice` over the methods, with each held-out subject's L2 figure."""
    view = {s: {"candidates": r["methods"], "floor": {"median_deg": r["floor_median_deg"]}}
            for s, r in subjects.items()}
    return {s: {**v, "l2_median_deg": subjects[s]["methods"]["l2"]["median_deg"]}
            for s, v in loo_choice(view, METHODS).items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", nargs="+", default=list(SUBJECTS))
    ap.add_argument("--register", action="store_true",
                    help="reference and halves from frames moved onto the (0,0) frame")
    ap.add_argument("--synthetic", action="store_true",
                    help="rendered faces with known normals instead of the shared subjects")
    args = ap.parse_args(argv)
    from jaxps.acquisition import load_capture

    t0 = time.perf_counter()
    command = ("OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/faces_methods.py "
               + " ".join(sys.argv[1:] if argv is None else argv))
    if args.synthetic:
        out = {"command": command, "environment": environment(), "methods": list(METHODS),
               **synthetic(), "seconds": time.perf_counter() - t0}
        write_json("faces_methods_synthetic", out)
        return out
    name = "faces_methods_registered" if args.register else "faces_methods"
    out = {"command": command, "environment": environment(), "registered": bool(args.register),
           "methods": list(METHODS), "subjects": {}}
    for subject in args.subjects:
        frames = load_subject(subject)
        if args.register:
            frames = register_subject(frames)[0]
        keys, _, ref, _, ok, floor, _, _ = references(frames)
        folder = data_dir() / "yaleb" / subject
        cap = load_capture([folder / f"{subject}_P00A{a:+04d}E{e:+03d}.pgm" for a, e in CROSS],
                           yale_names=True, ambient=folder / f"{subject}_P00_Ambient.pgm")
        row = {"reference_lights": len(keys), "floor_median_deg": floor["median_deg"],
               "five_lights_kept": len(cap.lights), "methods": {}}
        for method, (res, seconds) in solve_all(cap).items():
            inside = ok & np.asarray(res.status != jaxps.Status.MASKED)
            stats = jaxps.evaluate.angular_stats(res.normals, ref.normals, mask=inside)
            row["methods"][method] = {**stats, "seconds": seconds,
                                      "failed_fraction": float(np.mean(
                                          np.asarray(res.status)[inside] != 0))}
            print(f"{subject} {method:10s} median {stats['median_deg']:6.2f}  mean "
                  f"{stats['mean_deg']:6.2f}  (floor {floor['median_deg']:.2f})  "
                  f"{seconds * 1e3:7.1f} ms", flush=True)
        out["subjects"][subject] = row
    subjects = out["subjects"]
    out["median_over_subjects_deg"] = {
        m: float(np.median([r["methods"][m]["median_deg"] for r in subjects.values()]))
        for m in METHODS}
    out["median_floor_deg"] = float(np.median([r["floor_median_deg"] for r in subjects.values()]))
    out["worse_than_l2"] = {m: [s for s, r in subjects.items()
                                if r["methods"][m]["median_deg"] > r["methods"]["l2"]["median_deg"]]
                            for m in METHODS}
    out["loo"] = loo(subjects)
    out["loo_median_over_subjects_deg"] = float(np.median(
        [v["held_out_median_deg"] for v in out["loo"].values()]))
    out["seconds"] = time.perf_counter() - t0
    print("median over subjects:", {k: round(v, 2) for k, v in
                                    out["median_over_subjects_deg"].items()},
          "floor", round(out["median_floor_deg"], 2))
    print("leave-one-subject-out:", {k: (v["chosen"], round(v["held_out_median_deg"], 2))
                                     for k, v in out["loo"].items()})
    write_json(name, out)
    return out


if __name__ == "__main__":
    main()
