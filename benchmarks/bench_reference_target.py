"""Flash strengths measured on a reference target in view, against the estimates from the face.

Five near-frontal frames cannot tell a brighter flash from a tilted face (issue 17; docs/
captures.md, "Which lights can self-calibrate"): "frontal" assumes the face looks at the
camera, and on the shared Yale B faces its error follows the face's pose. A flat, matte target
fixed to the scanner and seen in every frame breaks the tie: over it
$\\bar i_k = e_k \\rho\\, l_k \\cdot d$ with its normal $d$ known, so "frontal" over the target
(`intensity_estimate(..., mask=target, normal=d)`, `load_capture(intensity_mask=...,
intensity_normal=...)`) measures the flash strengths with no assumption about the face.

Synthetic captures with known normals (there is no such target in the shared data): the face
of `jaxps.synthetic.face_like` (256x224) tilted by a plane of slope up to 0.08 on each axis
(up to 4.6 degrees), rendered with cast shadows, 0.5% noise and a Blinn-Phong lobe of
strength 0 or 0.3 (`jaxps.stability.render_corrupted`), under the scanner cross of the shared
faces ((0,0), (+-25,0), (0,+-20)); a 24x24 matte target of albedo 0.5 in a corner of the
frame, facing the camera or turned 20 degrees; each frame scaled by a flash strength
$e^{N(0, 0.1^2)}$. Median angular error over the face mask against the known normals, then
the median over ten seeds, for: no correction, mean equalisation, frontal over the face (the
default), frontal over the target with its normal given, the same with that normal 1 and 3
degrees off, and the true strengths (oracle).

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_reference_target.py
        -> benchmarks/results/reference_target.json
"""

from __future__ import annotations

import argparse
import sys

import jax.numpy as jnp
import numpy as np

import jaxps

try:
    from benchmarks import bench_faces as faces
    from benchmarks._common import environment, write_json
    from benchmarks.bench_light_layout import tilted_face
except ImportError:  # run as a script
    import pathlib

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks import bench_faces as faces
    from benchmarks._common import environment, write_json
    from benchmarks.bench_light_layout import tilted_face

H, W = 256, 224
TARGET = (slice(4, 28), slice(4, 28))  # rows, columns: a corner outside the face's mask
TARGET_ALBEDO = 0.5


def turned(degrees, about="x"):
    """The unit normal (0, 0, 1) turned by `degrees` about the camera's x (up) or y axis."""
    t = np.radians(degrees)
    return np.array([0.0, np.sin(t), np.cos(t)]) if about == "x" else \
        np.array([np.sin(t), 0.0, np.cos(t)])


def capture(seed, lights, specular, target_normal, noise=0.005):
    """One synthetic capture: `(images (K, H, W), face, target mask, true strengths)`."""
    from jaxps.stability import render_corrupted

    rng = np.random.default_rng(seed)
    face = tilted_face(H, W, rng.uniform(-0.08, 0.08, 2))
    scene = render_corrupted(face, lights, specular=specular, noise=noise, key=seed)
    images = np.array(scene.images, np.float64)
    target = np.zeros((H, W), bool)
    target[TARGET] = True
    assert not np.any(target & np.asarray(face.mask)), "the target must lie off the face"
    shade = TARGET_ALBEDO * np.maximum(np.asarray(lights, np.float64) @ target_normal, 0)
    images[:, target] = shade[:, None] + noise * rng.standard_normal((len(lights),
                                                                      int(target.sum())))
    strength = np.exp(rng.normal(0, 0.1, len(lights)))
    images = np.clip(images * strength[:, None, None], 0, 1).astype(np.float32)
    return images, face, target, strength / np.exp(np.mean(np.log(strength)))


def estimates(images, lights, face_mask, target, target_normal, strength):
    """Each estimate's `(K,)` intensities (geometric mean 1)."""
    est = lambda **kw: np.asarray(jaxps.intensity_estimate(images, lights, **kw), np.float64)
    axis = np.cross(target_normal, [1.0, 0.0, 0.0])  # across the normal: a left-right turn
    axis /= np.linalg.norm(axis)

    def off(deg):  # the target's normal turned by `deg` about `axis` (a misstated normal)
        t = np.radians(deg)
        return target_normal * np.cos(t) + np.cross(axis, target_normal) * np.sin(t)

    return {
        "none": np.ones(len(lights)),
        "mean": est(mask=face_mask, method="mean"),
        "frontal (face, the default)": est(mask=face_mask, method="frontal"),
        "target": est(mask=target, method="frontal", normal=target_normal),
        **{f"target, its normal {d} degree{'s' * (d > 1)} off": est(
            mask=target, method="frontal", normal=off(d)) for d in (1, 3)},
        "oracle": strength,
    }


def run(seeds, lights) -> dict:
    rows = {}
    for target_deg in (0.0, 20.0):
        normal = turned(target_deg)
        for specular in (0.0, 0.3):
            errors, intensity_errors = {}, {}
            for seed in seeds:
                images, face, target, strength = capture(seed, lights, specular, normal)
                mask = np.asarray(face.mask)
                for name, e in estimates(images, lights, mask, target, normal, strength).items():
                    res = jaxps.photometric_stereo(jnp.asarray(images / e[:, None, None],
                                                               jnp.float32), lights, mask=mask)
                    errors.setdefault(name, []).append(jaxps.evaluate.angular_stats(
                        res.normals, face.normals, mask=mask)["median_deg"])
                    intensity_errors.setdefault(name, []).append(
                        float(np.max(np.abs(e / strength - 1))))
            key = f"target turned {target_deg:g} deg, specular {specular:g}"
            rows[key] = {name: {"median_over_seeds_deg": float(np.median(v)),
                                "per_seed_deg": np.round(v, 4).tolist(),
                                "largest_intensity_error_median": float(np.median(
                                    intensity_errors[name]))}
                         for name, v in errors.items()}
            print(key, {n: round(r["median_over_seeds_deg"], 2) for n, r in rows[key].items()},
                  flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    args = ap.parse_args(argv)
    lights = np.asarray(faces.lights_of(list(faces.CROSS)), np.float64)
    out = {"command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python "
                      "benchmarks/bench_reference_target.py "
                      + " ".join(sys.argv[1:] if argv is None else argv),
           "environment": environment(), "image": [H, W], "seeds": args.seeds,
           "lights": [f"{a:+d},{e:+d}" for a, e in faces.CROSS],
           "target": {"rows": [TARGET[0].start, TARGET[0].stop],
                      "columns": [TARGET[1].start, TARGET[1].stop], "albedo": TARGET_ALBEDO},
           "rows": run(range(args.seeds), lights)}
    write_json("reference_target", out)
    return out


if __name__ == "__main__":
    main()
