"""A negative result, kept so that its figures can be rerun: issue 17's five-light intensities
from a face's left-right symmetry (docs/captures.md, "A face's symmetry").

The frontal estimate (`intensity_estimate(method="frontal")`) assumes the albedo-weighted
mean normal of its region is the view axis. Over a region symmetric about the face's mirror
axis, a frontal, symmetric face has a mean normal with no left-right part, whatever the
crop. So this candidate finds the axis (the mean of the five frames against its mirror image,
by `estimate_shifts`) and takes the frontal estimate over the widest band of columns symmetric
about it (`band`), or that band less 8 columns on each side. It is scored as
`bench_faces.py` scores its candidates, against the same semi-calibrated reference over the
clean lights within 50 degrees, over the same pixels. `d_reference` is the reference's own
albedo-weighted mean normal over those pixels, and `d_reference_band` the same within the
band: what the estimate would need to assume.

Run: `OPENBLAS_NUM_THREADS=1 JAXPS_DATA=../shared/data PYTHONPATH=src python
benchmarks/tried_symmetry.py` -> `benchmarks/results/tried_symmetry.json` (frames as read),
and with `--register` -> `tried_symmetry_registered.json` (every frame moved onto the (0,0)
frame first, as `bench_faces.py --register` does).
"""

from __future__ import annotations

import pathlib
import sys

import jax.numpy as jnp
import numpy as np

import jaxps

try:
    from benchmarks import bench_faces as bf
    from benchmarks._common import arguments, environment, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks import bench_faces as bf
    from benchmarks._common import arguments, environment, write_json


def mirror_axis(images) -> tuple[float, float]:
    """The column `x0` about which the mean frame best matches its mirror image, and the
    vertical shift between the two (near 0 for an upright face)."""
    from jaxps.acquisition import estimate_shifts

    mean = np.asarray(images).mean(axis=0)
    (dy, dx), = estimate_shifts(mean[None, :, ::-1], reference=mean[None])
    # The flipped frame holds the axis at W - 1 - x0, which is x0 + dx.
    return ((mean.shape[1] - 1) - dx) / 2, float(dy)


def band(shape, x0: float, margin: int = 0) -> np.ndarray:
    """Every column within the widest distance of `x0` that stays in the frame, less `margin`."""
    h, w = shape
    half = min(x0, w - 1 - x0) - margin
    return np.broadcast_to(np.abs(np.arange(w) - x0) <= half, (h, w)).copy()


def main(argv=None) -> None:
    args = arguments(__doc__, argv=argv, configure=lambda p: p.add_argument(
        "--register", action="store_true", help="move every frame onto the (0,0) frame first"))
    subjects = {}
    for subject in bf.SUBJECTS:
        frames = bf.load_subject(subject)
        if args.register:
            frames, _ = bf.register_subject(frames)
        within = sorted(k for k in frames if bf.off_axis(*k) <= bf.MAX_ANGLE)
        keys, _ = bf.clean(frames, within)
        ref = bf.semi(frames, keys)
        ok = (np.asarray(ref.status == 0) & np.asarray(ref.albedo > bf.ALBEDO_MIN)
              & bf.inner(ref.status.shape))
        five, _ = bf.clean(frames, list(bf.CROSS))
        images = jnp.asarray(np.stack([frames[k] for k in five]))
        lights = bf.lights_of(five)
        x0, dy = mirror_axis(images)
        weighted = np.asarray(ref.normals) * np.asarray(ref.albedo)[..., None]
        row = {"mirror_axis_column": round(x0, 2), "mirror_dy_px": round(dy, 3),
               "width": ok.shape[1],
               "d_reference": bf.mean_normal(weighted, ok).round(4).tolist(),
               "d_reference_band": bf.mean_normal(weighted, ok & band(ok.shape, x0))
               .round(4).tolist(), "median_deg": {}}
        for name, method, region in (("mean", "mean", None), ("frontal", "frontal", None),
                                     ("frontal_symmetric_band", "frontal",
                                      band(ok.shape, x0)),
                                     ("frontal_symmetric_band_less_8", "frontal",
                                      band(ok.shape, x0, 8))):
            e = jaxps.intensity_estimate(images, lights, method=method, mask=region)
            res, _ = bf._divide_and_solve(images, lights, e)
            inside = ok & np.asarray(res.status != jaxps.Status.MASKED)
            row["median_deg"][name] = round(jaxps.evaluate.angular_stats(
                res.normals, ref.normals, mask=inside)["median_deg"], 3)
        subjects[subject] = row
        print(subject, row, flush=True)
    names = list(row["median_deg"])
    summary = {n: float(np.median([r["median_deg"][n] for r in subjects.values()]))
               for n in names}
    print("median over subjects:", summary)
    write_json("tried_symmetry_registered" if args.register else "tried_symmetry", {
        "command": "OPENBLAS_NUM_THREADS=1 JAXPS_DATA=../shared/data PYTHONPATH=src python "
                   "benchmarks/tried_symmetry.py" + (" --register" if args.register else ""),
        "environment": environment(), "median_over_subjects_deg": summary,
        "subjects": subjects})


if __name__ == "__main__":
    main()
