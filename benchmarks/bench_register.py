"""Motion between frames: how far the shared captures moved, and what measuring it costs.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_register.py

- **Measured motion** (`jaxps.estimate_shifts` against the frame lit closest to the view axis):
  every Yale B frame within 50 degrees of the view axis (the faces moved), and the 12 frames of
  each psm object and of `jaxps demo`'s rendered face at 1280x1024 (still scenes: what the
  estimate reads as motion where there is none, which sets `load_capture`'s `MIN_SHIFT`).
- **Integrability without a reference**: the normalised curl of the five-light normals
  (`bench_faces._curl_ratio`: the cross lights, frontal intensities, L2 PS) with the frames as
  read and registered (`load_capture`'s default): normals from frames that do not line up mix
  neighbouring points of the face and integrate worse. No reference, so no shared registration
  error can flatter the registered figure.
- **Speed**: `estimate_shifts` on five frames of a rendered face at 192x168 and 1280x1024
  (median of 5 calls), against scikit-image's `phase_cross_correlation` (upsample 100, phase
  normalisation) on the same windowed crops; `shift_frames` (moving the five frames back)
  against `scipy.ndimage.shift` (cubic spline, edges repeated), which it replaced.

Writes benchmarks/results/register.json.
"""

from __future__ import annotations

import pathlib
import statistics
import sys
import time

import numpy as np

import jaxps

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from benchmarks._common import arguments, data_dir, environment, write_json, yale_subjects

SUBJECTS = yale_subjects()  # every yaleB* folder found (_common)


def _median_s(fn, repeats=5):
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def yale_motion():
    from jaxps.acquisition import load_capture

    out = {}
    for subject in SUBJECTS:
        folder = data_dir() / "yaleb" / subject
        paths = [p for p in sorted(folder.glob(f"{subject}_P00A*.pgm"))
                 if np.cos(np.radians(jaxps.parse_yale_name(p.name)[0]))
                 * np.cos(np.radians(jaxps.parse_yale_name(p.name)[1])) >= np.cos(np.radians(50))]
        cap = load_capture(paths, yale_names=True, ambient=folder / f"{subject}_P00_Ambient.pgm",
                           intensities="none")
        size = np.hypot(*np.asarray(cap.shifts).T)
        out[subject] = {"frames": len(paths), "max_px": float(np.abs(cap.shifts).max()),
                        "median_px": float(np.median(size[size > 0])),
                        "registered": cap.registered}
    return out


def five_light_curl():
    import jax.numpy as jnp

    from benchmarks import bench_faces as bf
    from jaxps.acquisition import mask_from_intensity

    out = {}
    for subject in SUBJECTS:
        raw = bf.load_subject(subject)
        row = {}
        for name, frames in (("as_read", raw), ("registered", bf.register_subject(raw)[0])):
            five, _ = bf.clean(frames, list(bf.CROSS))
            images = jnp.asarray(np.stack([frames[k] for k in five]))
            lights = bf.lights_of(five)
            e = np.asarray(jaxps.intensity_estimate(images, lights, method="frontal"))
            mask = mask_from_intensity(np.asarray(images)) & bf.inner(images.shape[1:])
            row[name] = bf._curl_ratio(images, lights, e, mask)
        out[subject] = row
    return out


def still_motion():
    import subprocess
    import tempfile

    from jaxps.acquisition import load_capture

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "jaxps", "demo", "--size", "1024", "--width", "1280",
                        "--out", tmp], check=True, capture_output=True)
        frames = pathlib.Path(tmp) / "frames"
        cap = load_capture(sorted(frames.glob("frame_*.png")), lights=frames / "lights.txt",
                           ambient=frames / "ambient.png", mask=frames / "mask.png")
        out["jaxps demo 1280x1024"] = {"frames": len(cap.names),
                                       "max_px": float(np.abs(cap.shifts).max()),
                                       "registered": cap.registered}
    for obj in ("cat", "owl"):
        folder = data_dir() / "psm" / obj
        cap = load_capture(folder, lights=data_dir() / "psm" / "lights.txt",
                           mask=folder / f"{obj}.mask.png", intensities="none")
        out[obj] = {"frames": len(cap.names), "max_px": float(np.abs(cap.shifts).max()),
                    "registered": cap.registered}
    return out


def speed():
    from scipy import ndimage
    from skimage.registration import phase_cross_correlation

    from jaxps.acquisition._register import _box, _prepare, _window

    shifts = np.array([[0.0, 0.0], [1.3, -0.7], [-2.4, 0.35], [0.6, 2.8], [-1.55, -1.9]])
    out = {}
    for h, w in ((192, 168), (1024, 1280)):
        scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(h, w),
                                             jaxps.synthetic.scanner_lights(20.0))
        moved = np.stack([np.fft.ifft2(ndimage.fourier_shift(np.fft.fft2(im), s)).real
                          for im, s in zip(np.asarray(scene.images), shifts)]).astype(np.float32)
        mask = np.asarray(scene.mask)
        ours = jaxps.estimate_shifts(moved, mask=mask)
        box = _box(mask, pad=4)
        win = _window(box[1] - box[0], box[3] - box[2])

        def skimage_shifts():
            ref = _prepare(moved[0], box, win, 1).astype(np.float64)
            return np.array([-phase_cross_correlation(
                ref, _prepare(f, box, win, 1).astype(np.float64), upsample_factor=100,
                normalization="phase")[0] for f in moved])

        theirs = skimage_shifts()

        def scipy_shift(frames, by):  # what shift_frames replaced (and no longer imports)
            return np.stack([ndimage.shift(f, s, order=3, mode="nearest")
                             for f, s in zip(frames, by)])

        out[f"{h}x{w}"] = {
            "estimate_shifts_s": _median_s(lambda: jaxps.estimate_shifts(moved, mask=mask)),
            "skimage_s": _median_s(skimage_shifts, repeats=3),
            "shift_frames_s": _median_s(lambda: jaxps.shift_frames(moved, -ours), repeats=3),
            "scipy_ndimage_shift_s": _median_s(lambda: scipy_shift(moved, -ours), repeats=3),
            "shift_frames_max_difference_from_scipy": float(np.abs(
                np.asarray(jaxps.shift_frames(moved, -ours)) - scipy_shift(moved, -ours)).max()),
            "max_error_px": float(np.abs(ours - shifts).max()),
            "skimage_max_error_px": float(np.abs(theirs - shifts).max()),
        }
    return out


def main():
    res = {"command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_register.py",
           "environment": environment()}
    res["yaleb_within_50deg"] = yale_motion()
    res["still_scenes"] = still_motion()
    res["five_light_curl_ratio"] = five_light_curl()
    res["speed_five_frames"] = speed()
    for key in ("yaleb_within_50deg", "still_scenes", "five_light_curl_ratio", "speed_five_frames"):
        for name, row in res[key].items():
            print(key, name, {k: round(v, 3) if isinstance(v, float) else v
                              for k, v in row.items()}, flush=True)
    write_json("register", res)


if __name__ == "__main__":
    arguments(__doc__)
    main()
