"""Samples that read 1 or more once divided by their frame's intensity (left as they are).

    OPENBLAS_NUM_THREADS=1 JAXPS_DATA=../shared/data PYTHONPATH=src python benchmarks/near_clip.py

`load_capture` divides frame k by its estimated intensity e_k (geometric mean 1), so a frame
with e_k < 1 can read above 1 where its raw sample was below the sensor's top code. The
samples clipped in the raw frame are in `Capture.saturated` (`sample_mask=~saturated`), but
`photometric_stereo`'s `saturation=1.0` drops these bright, unclipped ones too. This script
measures what that does, on captures the default pipeline reads:

- the five shared Yale B faces: the cross lights through `load_capture` with its defaults
  (frontal intensities, motion undone, flagged frames dropped), solved with `saturation=1.0`
  (what `jaxps reconstruct` does) and with the level out of reach (`1e30`: only the raw clip
  mask drops samples), each against the semi-calibrated many-light reference of
  `bench_faces.py` (frames as read);
- a rendered face that is not in the shared data: `scanner_lights(20)`, a Blinn-Phong lobe
  (strength 0.3, exponent 40), flashes of strength 1.0 / 1.1 / 0.92 / 1.05 / 0.95, exposed so
  that the dimmest flash peaks at 0.98 and the others clip, 0.5% noise, 8-bit codes, against
  its known normals.

Per capture: how many such samples and pixels there are, the median angular error at those
pixels both ways, and the face's median error both ways. Writes
benchmarks/results/near_clip.json.
"""

from __future__ import annotations

import pathlib
import sys

import numpy as np

import jaxps

try:
    from benchmarks._common import arguments, environment, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, environment, write_json

from benchmarks import bench_faces as bf

KEEP = 1e30  # a saturation level no sample reaches: only the raw clip mask drops samples


def _compare(images, lights, mask, saturated, truth, region):
    """Both solves against `truth` at the bright, unclipped pixels and over `region`."""
    bright = ((images >= 1.0) & ~saturated).any(0) & mask & region
    row = {"samples": int(((images >= 1.0) & ~saturated & bright[None]).sum()),
           "pixels": int(bright.sum()), "region_pixels": int(region.sum())}
    errors = {}
    for name, level in (("dropped", 1.0), ("kept", KEEP)):
        res = jaxps.photometric_stereo(images, lights, mask=mask, sample_mask=~saturated,
                                       saturation=level)
        err = np.array(jaxps.angular_error(res.normals, truth))
        err[np.asarray(res.status) != 0] = np.nan
        errors[name] = err[bright]
        row[name] = {"median_deg_at_those_pixels": float(np.nanmedian(err[bright]))
                     if bright.any() else None,
                     "median_deg_face": float(np.nanmedian(err[region]))}
    # per pixel: is the solve without those samples the nearer to the truth?
    row["pixels_nearer_when_dropped"] = int((errors["dropped"] < errors["kept"]).sum())
    return row


def yale(subject: str) -> dict:
    from jaxps.acquisition import load_capture

    frames = bf.load_subject(subject)
    within = sorted(k for k in frames if bf.off_axis(*k) <= bf.MAX_ANGLE)
    keys, _ = bf.clean(frames, within)
    ref = bf.semi(frames, keys)
    region = (np.asarray(ref.status == 0) & np.asarray(ref.albedo > bf.ALBEDO_MIN)
              & bf.inner(ref.status.shape))
    folder = bf.data_dir() / "yaleb" / subject
    paths = [folder / f"{subject}_P00A{a:+04d}E{e:+03d}.pgm" for a, e in bf.CROSS]
    cap = load_capture(paths, yale_names=True, ambient=folder / f"{subject}_P00_Ambient.pgm")
    row = _compare(cap.images, cap.lights, cap.mask, cap.saturated, np.asarray(ref.normals),
                   region & cap.mask)
    return {"gains": np.round(cap.gains, 4).tolist(),
            "raw_clipped_samples": int((cap.saturated & cap.mask[None]).sum()), **row}


def rendered() -> dict:
    from jaxps.stability import render_corrupted

    surface = jaxps.synthetic.face_like(192, 168)
    mask = np.asarray(surface.mask)
    lights = jaxps.synthetic.scanner_lights(20.0)
    strength = np.array([1.0, 1.1, 0.92, 1.05, 0.95], np.float32)
    scene = render_corrupted(surface, lights, specular=0.3, shininess=40.0, noise=0.005, key=0)
    lit = np.asarray(scene.images) * strength[:, None, None]
    # exposed so that the dimmest flash's brightest sample reads 0.98: the others clip
    raw = np.round(np.clip(lit * (0.98 / lit[2].max()), 0, 1) * 255) / 255
    saturated = raw >= 1.0
    e = np.asarray(jaxps.intensity_estimate(raw, lights, mask=mask, method="frontal"))
    images = (raw / e[:, None, None]).astype(np.float32)
    row = _compare(images, lights, mask, saturated, np.asarray(surface.normals), mask)
    return {"strength": strength.tolist(), "intensities": np.round(e, 4).tolist(),
            "raw_clipped_samples": int((saturated & mask[None]).sum()), **row}


def main(argv=None) -> None:
    arguments(__doc__, argv=argv)
    out = {"environment": environment(), "subjects": {}}
    for subject in bf.SUBJECTS:
        out["subjects"][subject] = row = yale(subject)
        print(subject, {k: row[k] for k in ("samples", "pixels", "dropped", "kept")}, flush=True)
    out["rendered_face"] = row = rendered()
    print("rendered", {k: row[k] for k in ("samples", "pixels", "dropped", "kept")})
    write_json("near_clip", out)


if __name__ == "__main__":
    main()
