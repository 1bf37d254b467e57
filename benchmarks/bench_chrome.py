"""Mirror-sphere light calibration: how close `lights_from_chrome` comes to known lights.

Synthetic mirror spheres (not the shared data): a sphere of radius 20, 41 or 120 px at a
sub-pixel centre, lit by the scanner cross of `jaxps.synthetic.scanner_lights(20)` with each
light moved by up to 3 degrees in azimuth and elevation (a new draw per seed). Each frame is
the reflection of a lamp, $\\exp((r \\cdot l - 1)/s)$ with $r$ the mirrored view and $s$ = 0.02
(a broad lamp) or 0.005 (a small one), over a floor of 0.05, with 0.5% noise; "saturated"
multiplies by 4 and clips at 1, so the highlight is a plateau, as a flash's is. Figure: the
largest angular error of the five lights of a capture, median (and worst) over 8 seeds.

Estimators of the highlight's centre, all on the largest connected blob at or above
`level` x the frame's brightest value $m$ on the sphere:
- `level-subtracted`: the centroid with weights $I - \\text{level}\\, m$ (what
  `jaxps.lights_from_chrome` does, default level 0.5);
- `intensity-weighted`: the centroid with weights $I$ (the estimator before, at its default
  level 0.9, rebuilt here).

With the shared data (`$JAXPS_DATA` or ../shared/data): the angle between each estimator's
lights from psm/chrome and the distributed psm/lights.txt, whose truth is not known either.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_chrome.py
        -> benchmarks/results/chrome.json
"""

from __future__ import annotations

import pathlib
import sys

import numpy as np

import jaxps

try:
    from benchmarks._common import arguments, data_dir, environment, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, data_dir, environment, write_json

RADII = (20.3, 41.2, 120.3)
SHARPNESS = (0.02, 0.005)
ESTIMATORS = {  # name: (weights, level)
    "level-subtracted, level 0.5 (the default)": ("subtracted", 0.5),
    "level-subtracted, level 0.9": ("subtracted", 0.9),
    "intensity-weighted, level 0.5": ("intensity", 0.5),
    "intensity-weighted, level 0.9 (before)": ("intensity", 0.9),
}


def render(lights, radius, sharpness, saturated, rng):
    """`(K, H, W)` frames of a mirror sphere and its `(H, W)` mask."""
    h, w = int(3 * radius), int(4 * radius)
    centre = (1.4 * radius + 0.3, 2 * radius + 0.7)
    rows, cols = np.indices((h, w), dtype=np.float64)
    x, y = (cols - centre[1]) / radius, -(rows - centre[0]) / radius
    rr = x * x + y * y
    inside = rr < 1
    n = np.stack([x, y, np.sqrt(np.maximum(1 - rr, 0))], axis=-1)
    mirrored = 2 * n[..., 2:3] * n - np.array([0.0, 0.0, 1.0])
    frames = np.stack([np.exp((mirrored @ light - 1) / sharpness) + 0.05 for light in lights])
    frames = frames + rng.normal(0, 0.005, frames.shape)
    if saturated:
        frames = 4 * frames
    return np.where(inside, np.clip(frames, 0, 1), 0), inside.astype(np.float32)


def calibrate(images, mask, weights, level):
    """`(K, 3)` lights with the named estimator."""
    if weights == "subtracted":
        return jaxps.lights_from_chrome(images, mask, level=level).lights
    import scipy.ndimage as ndi

    (r0, c0), radius = jaxps.sphere_from_mask(mask)
    inside = mask >= 0.5 * mask.max()
    lights = []
    for img in np.asarray(images, np.float64):
        img = img.mean(axis=-1) if img.ndim == 3 else img  # colour: the channels' mean
        vals = np.where(inside, img, 0.0)
        labels, count = ndi.label(vals >= level * vals.max())
        sizes = ndi.sum_labels(vals, labels, index=np.arange(1, count + 1))
        blob = labels == 1 + int(np.argmax(sizes))
        row, col = ndi.center_of_mass(np.where(blob, vals, 0.0))
        x, y = (col - c0) / radius, -(row - r0) / radius
        n = np.array([x, y, np.sqrt(max(1 - x * x - y * y, 0.0))])
        lights.append(2 * n[2] * n - np.array([0.0, 0.0, 1.0]))
    return np.asarray(lights)


def angles(a, b):
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1, 1)))


def synthetic(seeds):
    design = jaxps.synthetic.scanner_lights(20.0)
    azimuth, elevation = jaxps.angles_from_lights(design)
    rows = []
    for radius in RADII:
        for sharpness in SHARPNESS:
            for saturated in (False, True):
                worst = {name: [] for name in ESTIMATORS}
                for seed in range(seeds):
                    rng = np.random.default_rng(seed)
                    truth = jaxps.lights_from_angles(azimuth + rng.uniform(-3, 3, 5),
                                                     elevation + rng.uniform(-3, 3, 5))
                    images, mask = render(truth, radius, sharpness, saturated, rng)
                    for name, (weights, level) in ESTIMATORS.items():
                        worst[name].append(float(angles(calibrate(images, mask, weights, level),
                                                        truth).max()))
                row = {"radius_px": radius, "sharpness": sharpness, "saturated": saturated}
                for name, errors in worst.items():
                    row[name] = {"median_deg": float(np.median(errors)),
                                 "worst_deg": float(np.max(errors)), "per_seed_deg": errors}
                rows.append(row)
                print(f"r {radius:5.1f} px, s {sharpness}, saturated {saturated!s:5}: " + ", ".join(
                    f"{name.split(' (')[0]} {row[name]['median_deg']:.3f}" for name in ESTIMATORS),
                    flush=True)
    return rows


def psm():
    folder = data_dir() / "psm"
    if not (folder / "chrome").is_dir():
        print(f"psm: no {folder / 'chrome'}, skipped")
        return None
    images, mask = jaxps.load_psm(folder / "chrome")
    reference = jaxps.load_lights(folder / "lights.txt")
    out = {}
    for name, (weights, level) in ESTIMATORS.items():
        angle = angles(calibrate(images, mask, weights, level), reference)
        out[name] = {"angle_deg": angle.tolist(), "mean_deg": float(angle.mean()),
                     "max_deg": float(angle.max())}
        print(f"psm/chrome against lights.txt, {name}: mean {angle.mean():.2f}, largest "
              f"{angle.max():.2f} deg", flush=True)
    return out


def main(argv=None):
    seeds = 2 if arguments(__doc__, quick=True, argv=argv).quick else 8
    result = {"environment": environment(), "seeds": seeds, "synthetic": synthetic(seeds),
              "psm_against_lights_txt": psm()}
    print(write_json("chrome", result))


if __name__ == "__main__":
    main()
