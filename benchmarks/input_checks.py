"""The figures behind two checks of bad input, on the shared real captures.

- `lights_from_chrome(max_fraction=0.05)`: a highlight is a small spot. For each of psm's
  twelve chrome frames (linear, as `load_psm` reads them), the fraction of the sphere's pixels
  at or above 0.5 x the frame's maximum there; and the same for frames of uniform noise, what a
  lamp that did not fire leaves.
- `load_capture`'s ambient check (`acquisition/_capture.py`, `_below_ambient`): for each shared
  Yale B subject, the largest fraction of a frame's pixels darker than the true ambient frame by
  more than the check's margin, over all 64 frames and over the five cross frames; and, with
  each cross frame given as the ambient instead, that fraction in the other four's median frame
  (what the check compares with 5%).

- `load_capture`'s mask check (`_dark_in_mask`): for psm's cat and owl, the fraction of the
  mask's pixels dark in the mean frame, and of the lit pixels outside it, with the object's
  own mask, the other object's and its own inverted; the same for a rendered face (no shared
  data).

- `load_capture`'s frame check and motion step: a frame moved by 0-6 px. On a rendered face on
  black (no shared data, 96 and 192 px, noise 0.005, its mask given), the frames kept and the
  median normal error against the truth, by default (a frame flagged only as inconsistent is
  checked again once the motion is undone) and with `register=False` (the frame check alone,
  which drops it, as the default did before the thirtieth session). On the shared Yale B
  faces' five cross frames, with the (+25,0) frame moved by 3 px, the frames kept both ways.

    PYTHONPATH=src python benchmarks/input_checks.py -> benchmarks/results/input_checks.json
"""

from __future__ import annotations

import pathlib
import sys

import numpy as np

import jaxps
from jaxps import acquisition as acq
from jaxps.acquisition._capture import (
    _AMBIENT_FRACTION,
    _DARK_MASK_FRACTION,
    _below_ambient,
    _dark_in_mask,
)

try:
    from benchmarks._common import arguments, data_dir, environment, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, data_dir, environment, write_json

CROSS = ["A+000E+00", "A+025E+00", "A-025E+00", "A+000E+20", "A+000E-20"]


def chrome(data):
    images, mask = jaxps.load_psm(data / "psm" / "chrome")
    inside = mask >= 0.5 * mask.max()
    grey = images.mean(axis=-1)[:, inside]
    highlight = np.mean(grey >= 0.5 * grey.max(axis=1, keepdims=True), axis=1)
    rng = np.random.default_rng(0)
    noise = rng.uniform(0, 0.05, (8, int(inside.sum())))
    noise_fraction = np.mean(noise >= 0.5 * noise.max(axis=1, keepdims=True), axis=1)
    return {"highlight_fraction": highlight.tolist(), "noise_fraction": noise_fraction.tolist()}


def ambient(data):
    out = {}
    for folder in sorted((data / "yaleb").glob("yaleB*")):
        subject = folder.name
        amb = acq.read_image(folder / f"{subject}_P00_Ambient.pgm")
        every = np.stack([acq.read_image(p) for p in sorted(folder.glob(f"{subject}_P00A*.pgm"))])
        cross = np.stack([acq.read_image(folder / f"{subject}_P00{n}.pgm") for n in CROSS])
        out[subject] = {
            "true_ambient_all_frames_max": float(_below_ambient(every, amb)[0].max()),
            "true_ambient_cross_frames_max": float(_below_ambient(cross, amb)[0].max()),
            "cross_frame_as_ambient_median_frame": {
                n: float(np.median(_below_ambient(np.delete(cross, k, 0), cross[k])[0]))
                for k, n in enumerate(CROSS)},
        }
    return out


def masks(data):
    own = {o: jaxps.load_psm(data / "psm" / o)[1] > 0.5 for o in ("cat", "owl")}
    out = {}
    for obj, other in (("cat", "owl"), ("owl", "cat")):
        images = jaxps.load_psm(data / "psm" / obj)[0]
        out[obj] = {name: dict(zip(("dark_inside", "lit_outside"), _dark_in_mask(images, m)))
                    for name, m in (("own", own[obj]), ("other object's", own[other]),
                                    ("own, inverted", ~own[obj]))}
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(96),
                                         jaxps.synthetic.scanner_lights(20.0), noise=0.01, key=1)
    images, face = np.asarray(scene.images), np.asarray(scene.mask)
    out["rendered face"] = {name: dict(zip(("dark_inside", "lit_outside"),
                                           _dark_in_mask(images, m)))
                            for name, m in (("own", face), ("own, inverted", ~face))}
    return out


def _roll_files(folder, images, moved, shift, to_png=True):
    """Write `images` to `folder` as 16-bit PNGs, frame `moved` rolled by `shift` columns."""
    import cv2

    paths = []
    for i, f in enumerate(images):
        paths.append(str(folder / f"f{i}.png"))
        f = np.roll(f, shift, axis=1) if i == moved else f
        cv2.imwrite(paths[-1], np.round(np.clip(f, 0, 1) * 65535).astype(np.uint16))
    return paths


def moved_frame(data, shifts=(0, 1, 2, 3, 6)):
    import logging
    import tempfile

    import cv2

    logging.getLogger("jaxps").setLevel(logging.ERROR)
    out = {}
    lights = np.asarray(jaxps.synthetic.scanner_lights(20.0))
    for size in (96, 192):
        face = jaxps.synthetic.face_like(size)
        images = np.asarray(jaxps.synthetic.render_scene(face, lights, noise=0.005, key=1).images)
        rows = {}
        for shift in shifts:
            with tempfile.TemporaryDirectory() as tmp:
                paths = _roll_files(pathlib.Path(tmp), images, 1, shift)
                row = {}
                for name, register in (("default", True), ("register=False", False)):
                    cap = acq.load_capture(paths, lights=lights, mask=np.asarray(face.mask),
                                           register=register)
                    res = jaxps.photometric_stereo(cap.images, cap.lights, mask=cap.mask,
                                                   sample_mask=~cap.saturated)
                    ok = (np.asarray(res.status) == 0) & np.asarray(face.mask)
                    row[name] = {"frames": len(cap.names), "median_error_deg": float(np.median(
                        np.asarray(jaxps.angular_error(res.normals, face.normals))[ok]))}
                rows[f"{shift} px"] = row
        out[f"rendered face {size} px"] = rows
    cross = ["A+000E+00", "A+025E+00", "A-025E+00", "A+000E+20", "A+000E-20"]
    for folder in sorted((data / "yaleb").glob("yaleB*")):
        s = folder.name
        raw = [cv2.imread(str(folder / f"{s}_P00{n}.pgm"), cv2.IMREAD_UNCHANGED) for n in cross]
        row = {}
        for shift in (0, 3):
            with tempfile.TemporaryDirectory() as tmp:
                paths = []
                for n, img in zip(cross, raw):
                    paths.append(str(pathlib.Path(tmp) / f"{s}_P00{n}.pgm"))
                    cv2.imwrite(paths[-1], np.roll(img, shift, axis=1) if n == cross[1] else img)
                row[f"{shift} px"] = {}
                for name, register in (("default", True), ("register=False", False)):
                    cap = acq.load_capture(paths, yale_names=True, register=register,
                                           ambient=folder / f"{s}_P00_Ambient.pgm")
                    row[f"{shift} px"][name] = {"frames": len(cap.names),
                                                "dropped": list(cap.dropped)}
        out[s] = row
    return out


def main():
    arguments(__doc__)
    data = data_dir()
    if not (data / "psm").is_dir() or not (data / "yaleb").is_dir():
        sys.exit(f"needs the shared data (psm/ and yaleb/) under {data}")
    result = {"environment": environment(), "chrome": chrome(data), "ambient": ambient(data),
              "ambient_fraction_limit": _AMBIENT_FRACTION, "masks": masks(data),
              "dark_mask_fraction_limit": _DARK_MASK_FRACTION, "moved_frame": moved_frame(data)}
    c = result["chrome"]
    print(f"chrome: highlights cover {100 * min(c['highlight_fraction']):.2f}-"
          f"{100 * max(c['highlight_fraction']):.2f}% of the sphere; noise "
          f"{100 * min(c['noise_fraction']):.1f}-{100 * max(c['noise_fraction']):.1f}%")
    for subject, r in result["ambient"].items():
        wrong = r["cross_frame_as_ambient_median_frame"].values()
        print(f"{subject}: true ambient at most {100 * r['true_ambient_all_frames_max']:.2f}% "
              f"(all 64 frames), {100 * r['true_ambient_cross_frames_max']:.2f}% (cross); a cross "
              f"frame as the ambient {100 * min(wrong):.1f}-{100 * max(wrong):.1f}%")
    for obj, rows in result["masks"].items():
        print(f"{obj}: " + "; ".join(f"{name} mask {100 * r['dark_inside']:.1f}% dark inside, "
                                     f"{100 * r['lit_outside']:.1f}% of the lit outside"
                                     for name, r in rows.items()))
    for what, rows in result["moved_frame"].items():
        print(f"{what}, one frame moved: " + "; ".join(
            f"{shift}: " + ", ".join(f"{name} {r['frames']} frames"
                                     + (f" {r['median_error_deg']:.2f} deg"
                                        if "median_error_deg" in r else "")
                                     for name, r in row.items())
            for shift, row in rows.items()))
    print(write_json("input_checks", result))


if __name__ == "__main__":
    main()
