"""Which five lights can self-calibrate their flashes: three layouts on the shared Yale B faces.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_light_layout.py [--register]

Five frames with unknown flash strengths $e_k$ leave $K-1$ free intensities. A change
$e_k \\to e_k (1 + \\delta_k)$ is invisible to the data where $\\mathrm{diag}(\\delta) L$ stays in
the column space of the lights $L$ (the data stay exactly Lambertian, with other normals). For
lights close to the view axis, $\\delta_k$ linear in the light's offset $(l_{k,x}, l_{k,y})$
nearly does that: to first order it adds a plane to the face's height (a tilt), which no
per-pixel residual and no integrability test sees. `visibility` is the singular values of the
map $\\delta \\mapsto N\\,\\mathrm{diag}(\\delta)\\,L$ ($N$ spanning the null space of $L^T$):
the smallest non-zero one says how strongly the weakest intensity change shows in the
residuals that `method="semi_calibrated"` fits.

Layouts, five frames each (a frame `check_frames` flags is dropped, as `load_capture` does):

- `scanner_cross`: the face scanner's (0,0), (+-25,0), (0,+-20) (issue 17's lights);
- `x_35`: (0,0) and four on the diagonals, (+-35,+15), (+-35,-20);
- `wide_cross`: (0,0), (+-50,0), (0,+45), (0,-35).

Each layout is scored against semi-calibrated PS over every clean light within 50 degrees
except the layout's own (so no frame is in both), by the median angular error over the face
(as `bench_faces.py`: reference albedo > 0.05, 4 px from the edge), for mean equalisation,
frontal intensities (the library's default) and semi-calibrated PS with `prior_weight` 0 and 1.
With `--register` every frame is first moved onto the (0,0) frame (`bench_faces.py`'s
registered protocol). Writes benchmarks/results/light_layout.json (or
light_layout_registered.json).

`--synthetic` checks the same away from Yale B: `jaxps.synthetic.face_like` (256x224) turned
by a random slope of up to 0.08 on each axis (about 4.6 degrees; a shear, which is the change
five near-frontal frames cannot see), rendered under each layout with cast shadows, a
Blinn-Phong lobe ($k_s$ 0 or 0.3), 0.5% noise and random flash strengths (log-normal, 10%),
seeds 0-4; median error against the known normals over the mask, then the median over the
seeds -> light_layout_synthetic.json.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

import jax.numpy as jnp
import numpy as np

import jaxps
from jaxps.ps._visibility import visibility_spectrum

try:
    from benchmarks import bench_faces as faces
    from benchmarks._common import environment, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks import bench_faces as faces
    from benchmarks._common import environment, write_json

LAYOUTS = {
    "scanner_cross": [(0, 0), (25, 0), (-25, 0), (0, 20), (0, -20)],
    "x_35": [(0, 0), (35, 15), (-35, 15), (35, -20), (-35, -20)],
    "wide_cross": [(0, 0), (50, 0), (-50, 0), (0, 45), (0, -35)],
}
ESTIMATES = {
    "mean": faces.cand_estimate("mean"),
    "frontal": faces.cand_estimate("frontal"),
    "semi_calibrated": faces.cand_semi(0.0),
    "semi_calibrated_prior1": faces.cand_semi(1.0),
}


def visibility(keys) -> list[float]:
    """`visibility_spectrum` (every singular value behind `jaxps.flash_visibility`, largest
    first) of the unit lights of `keys`; the last is 0 (a common scale changes nothing)."""
    return visibility_spectrum(faces.lights_of(keys)).round(4).tolist()


def score_subject(frames: dict) -> dict:
    within = sorted(k for k in frames if faces.off_axis(*k) <= faces.MAX_ANGLE)
    keys, _ = faces.clean(frames, within)
    out = {}
    for name, layout in LAYOUTS.items():
        five, dropped = faces.clean(frames, layout)
        ref_keys = [k for k in keys if k not in layout]
        ref = faces.semi(frames, ref_keys)
        ok = (np.asarray(ref.status == 0) & np.asarray(ref.albedo > faces.ALBEDO_MIN)
              & faces.inner(ref.status.shape))
        images = jnp.asarray(np.stack([frames[k] for k in five]))
        row = {"frames": len(five), "dropped": dropped, "reference_lights": len(ref_keys)}
        for est, fn in ESTIMATES.items():
            res, info = fn(images, faces.lights_of(five), {})
            inside = ok & np.asarray(res.status != jaxps.Status.MASKED)
            row[est] = {"median_deg": jaxps.evaluate.angular_stats(
                res.normals, ref.normals, mask=inside)["median_deg"], **info}
        out[name] = row
    return out


def tilted_face(h, w, slope):
    """`face_like(h, w)` with the plane `slope[0] x + slope[1] y` (pixels) added to its height."""
    face = jaxps.synthetic.face_like(h, w)
    n = np.asarray(face.normals, np.float64)
    grad = np.stack([-n[..., 0] / n[..., 2] + slope[0], -n[..., 1] / n[..., 2] + slope[1],
                     -np.ones(n.shape[:2])], -1)
    normals = -grad / np.linalg.norm(grad, axis=-1, keepdims=True)
    x = np.arange(w) - (w - 1) / 2
    y = (h - 1) / 2 - np.arange(h)
    height = np.asarray(face.height) + slope[0] * x[None] + slope[1] * y[:, None]
    return face._replace(height=jnp.asarray(height, jnp.float32),
                         normals=jnp.asarray(normals, jnp.float32))


def synthetic(seeds=range(5)) -> dict:
    """`--synthetic` (see the module docstring)."""
    from jaxps.stability import render_corrupted

    rows = {}
    for name, layout in LAYOUTS.items():
        lights = np.asarray(faces.lights_of(layout))
        for specular in (0.0, 0.3):
            errors = {"frontal": [], "semi_calibrated": []}
            for seed in seeds:
                rng = np.random.default_rng(seed)
                face = tilted_face(256, 224, rng.uniform(-0.08, 0.08, 2))
                scene = render_corrupted(face, lights, specular=specular, noise=0.005, key=seed)
                gains = np.exp(rng.normal(0, 0.1, len(layout))).astype(np.float32)
                images = jnp.asarray(np.clip(np.asarray(scene.images) * gains[:, None, None],
                                             0, 1))
                mask = np.asarray(face.mask)
                for est, errs in errors.items():
                    res, _ = ESTIMATES[est](images, lights, {})
                    errs.append(jaxps.evaluate.angular_stats(
                        res.normals, face.normals, mask=mask)["median_deg"])
            rows[f"{name}, specular {specular}"] = {
                est: {"median_over_seeds_deg": float(np.median(v)), "per_seed_deg": v}
                for est, v in errors.items()}
            print(name, specular, {e: round(float(np.median(v)), 2)
                                   for e, v in errors.items()}, flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--register", action="store_true",
                    help="move every frame onto the (0,0) frame first")
    ap.add_argument("--synthetic", action="store_true",
                    help="tilted synthetic faces with known normals instead of Yale B")
    args = ap.parse_args(argv)
    if args.synthetic:
        t0 = time.perf_counter()
        out = {"command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python "
                          "benchmarks/bench_light_layout.py --synthetic",
               "environment": environment(),
               "layouts": {n: [f"{a:+d},{e:+d}" for a, e in lay] for n, lay in LAYOUTS.items()},
               "scenes": synthetic()}
        out["seconds"] = time.perf_counter() - t0
        print("wrote", write_json("light_layout_synthetic", out))
        return
    if not (faces.data_dir() / "yaleb").is_dir():
        sys.exit(f"no Yale B captures under {faces.data_dir()}: set JAXPS_DATA")
    t0 = time.perf_counter()
    subjects = {}
    for subject in faces.SUBJECTS:
        frames = faces.load_subject(subject)
        if args.register:
            frames, _ = faces.register_subject(frames)
        subjects[subject] = score_subject(frames)
        print(subject, {lay: {e: round(r[e]["median_deg"], 2) for e in ESTIMATES}
                        for lay, r in subjects[subject].items()}, flush=True)
    medians = {lay: {e: float(np.median([subjects[s][lay][e]["median_deg"] for s in subjects]))
                     for e in ESTIMATES} for lay in LAYOUTS}
    out = {"command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python "
                      f"benchmarks/bench_light_layout.py{' --register' if args.register else ''}",
           "environment": environment(), "registered": args.register,
           "layouts": {n: [f"{a:+d},{e:+d}" for a, e in lay] for n, lay in LAYOUTS.items()},
           "visibility": {n: visibility(lay) for n, lay in LAYOUTS.items()},
           "subjects": subjects, "median_over_subjects_deg": medians,
           "seconds": time.perf_counter() - t0}
    for lay, row in medians.items():
        print(f"{lay:14s} visibility {out['visibility'][lay]}  median over subjects "
              + ", ".join(f"{e} {v:.2f}" for e, v in row.items()))
    print("wrote", write_json("light_layout_registered" if args.register else "light_layout", out))


if __name__ == "__main__":
    main()
