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

`--yale` (`reference_target_yale.json`; with `--register`, `reference_target_yale_registered
.json`): the shared Yale B faces with an emulated target. A 12x12 corner of each of the five
cross frames (hair or background there) is overwritten with a matte target facing the camera
that carries the flash strengths of the subject's own many-light reference (its fitted
intensities: what a real target would have measured if the reference is right), the ambient
frame's corner with 0, and the files are written out again. Then `jaxps reconstruct FRAMES
--yale-names --ambient A` (issue 17's command line) runs with and without `--intensity-mask`,
and the normals are scored as `bench_faces.py` scores them (the same reference, mask and
half-set floor; the target's corner left out). This checks the whole command on real frames
(quality checks, registration and the crop with a still target in view), not the target's
physics, which the synthetic part checks.

`--near` (`reference_target_near.json`): the synthetic face and target under near lights. The
scanner's five lamps stand 1000 or 2000 mm from the face's mean depth, along the cross's
directions; 1 mm pixels; the target 100 mm behind the face's mean depth, facing the camera;
Lambertian, 0.5% noise, the same flashes. The target is lit from other distances than the
face, by a factor per lamp. A flat board at the face's mean depth, imaged once under other
flashes with the target in view, gives `acquisition.target_ratios`, which put it right.
Estimates: frontal over the face (the default), the target, the target times the ratios, and
the true flashes. The face is solved as the command line solves it (distant lights, L2) and
with the lamps' positions known (`near_photometric_stereo`); median angular error over the
face, then the median over the seeds, and the largest error of the flash strengths.
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import jax.numpy as jnp
import numpy as np

import jaxps

try:
    from benchmarks import bench_faces as faces
    from benchmarks._common import RESULTS, ROOT, environment, write_json
    from benchmarks.bench_light_layout import tilted_face
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks import bench_faces as faces
    from benchmarks._common import RESULTS, ROOT, environment, write_json
    from benchmarks.bench_light_layout import tilted_face

H, W = 256, 224
TARGET = (slice(4, 28), slice(4, 28))  # rows, columns: a corner outside the face's mask
TARGET_ALBEDO = 0.5


def turned(degrees):
    """The unit normal (0, 0, 1) turned up by `degrees` (about the camera's x axis)."""
    t = np.radians(degrees)
    return np.array([0.0, np.sin(t), np.cos(t)])


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


YALE_TARGET = (slice(2, 14), slice(2, 14))


def yale_subject(subject, register, folder):
    """Issue 17's command line on one subject's five cross frames with an emulated target,
    with and without `--intensity-mask`, against `bench_faces`'s reference."""
    import cv2

    from jaxps.cli import reconstruct
    from jaxps.report._writers import read_normal_map

    raw = faces.load_subject(subject)
    data = faces.register_subject(raw)[0] if register else raw
    keys, _, ref, _, ok, floor, _, _ = faces.references(data)
    ref_e = np.asarray(ref.info["intensities"], np.float64)
    src = faces.data_dir() / "yaleb" / subject
    target = np.zeros(raw[(0, 0)].shape, bool)
    target[YALE_TARGET] = True
    paths = []
    for az, el in faces.CROSS:
        name = f"{subject}_P00A{az:+04d}E{el:+03d}.pgm"
        frame = cv2.imread(str(src / name), cv2.IMREAD_UNCHANGED)
        light = np.asarray(faces.lights_of([(az, el)]), np.float64)[0]
        # a frame the reference left out (yaleB02's combed one) is dropped by the checks too
        e = ref_e[keys.index((az, el))] if (az, el) in keys else 1.0
        frame[target] = np.uint8(np.clip(np.round(255 * TARGET_ALBEDO * e * light[2]), 0, 255))
        paths.append(folder / name)
        cv2.imwrite(str(paths[-1]), frame)
    ambient = cv2.imread(str(src / f"{subject}_P00_Ambient.pgm"), cv2.IMREAD_UNCHANGED)
    ambient[target] = 0
    ambient_path = folder / f"{subject}_P00_Ambient.pgm"
    cv2.imwrite(str(ambient_path), ambient)
    row = {"floor_median_deg": floor["median_deg"], "reference_intensities": {
        f"{a:+d},{e:+d}": float(ref_e[keys.index((a, e))]) for a, e in faces.CROSS
        if (a, e) in keys}}
    maps = {}
    for name, options in (("command line (frontal over the face)", {}),
                          ("command line, --intensity-mask", {"intensity_mask": target})):
        out = folder / name.replace(" ", "_").replace(",", "").replace("(", "").replace(")", "")
        summary = reconstruct([str(p) for p in paths], str(out), yale_names=True,
                              ambient=str(ambient_path), **options)
        normals = read_normal_map(out / "normals.png")
        status = np.load(out / "status.npy")
        inside = ok & ~target & (status != jaxps.Status.MASKED)
        stats = jaxps.evaluate.angular_stats(normals, ref.normals, mask=inside)
        maps[name] = np.where(inside, np.asarray(jaxps.angular_error(normals, ref.normals)),
                              np.nan)
        row[name] = {"median_deg": stats["median_deg"], "mean_deg": stats["mean_deg"],
                     "intensities": summary["intensities"]["per_frame"],
                     "dropped": summary["dropped_frames"], "motion": summary["motion"]}
    # the card's strengths against the reference's, over the frames the checks kept
    kept = [k for k in faces.CROSS if k in keys]
    want = np.array([ref_e[keys.index(k)] for k in kept])
    got = np.array(row["command line, --intensity-mask"]["intensities"])
    row["card_intensity_error_largest"] = float(np.max(np.abs(
        got / (want / np.exp(np.mean(np.log(want)))) - 1)))
    print(subject, {k: round(v["median_deg"], 2) for k, v in row.items() if isinstance(v, dict)
                    and "median_deg" in v}, "floor", round(floor["median_deg"], 2), flush=True)
    return row, maps


def plot(subject, maps, path, registered):
    """The error maps of `subject`: the command line without and with the card."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(maps), figsize=(2.8 * len(maps) + 0.8, 3.3))
    for ax, (name, err) in zip(axes, maps.items()):
        im = ax.imshow(err, vmin=0, vmax=20, cmap="magma")
        label = name.replace("command line (frontal over the face)", "jaxps reconstruct")
        label = label.replace("command line, ", "with ")
        ax.set_title(f"{label}\nmedian {np.nanmedian(err):.2f} deg", fontsize=8)
        ax.axis("off")
    fig.colorbar(im, ax=axes, fraction=0.03, label="angular error (deg)")
    fig.suptitle(f"{subject}, five cross frames and an emulated card:\nerror against the "
                 f"50-degree reference{', registered' * registered}", fontsize=8, y=1.08)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def yale(register, figure_subject="yaleB03") -> dict:
    import shutil
    import tempfile

    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for subject in faces.SUBJECTS:
            folder = pathlib.Path(tmp) / subject
            folder.mkdir()
            rows[subject], maps = yale_subject(subject, register, folder)
            if subject == figure_subject:
                name = "reference_target_yale" + "_registered" * register
                plot(subject, maps, RESULTS / f"{name}.png", register)
                shutil.copy(RESULTS / f"{name}.png", ROOT / "docs" / "images" / f"{name}.png")
    names = [k for k, v in next(iter(rows.values())).items() if isinstance(v, dict)
             and "median_deg" in v]
    return {"subjects": rows, "median_over_subjects_deg": {
        n: float(np.median([r[n]["median_deg"] for r in rows.values()])) for n in names},
        "median_floor_deg": float(np.median([r["floor_median_deg"] for r in rows.values()]))}


NEAR_DEPTH = -100.0  # mm, the target behind the face's mean depth


def near_capture(seed, lights, distance, board=None):
    """`(images, face, target, true strengths, positions)` of the near-light scanner: a face
    (tilted as in `capture`), or with `board` (a mask) a flat board there at depth 0 (`face`
    is then None)."""
    rng = np.random.default_rng(seed)
    if board is None:
        surface = tilted_face(H, W, rng.uniform(-0.08, 0.08, 2))
        region = np.asarray(surface.mask)
        normals = np.asarray(surface.normals, np.float64)
        depth = np.asarray(surface.height, np.float64)  # 1 mm pixels: pixels are mm
        depth = depth - depth[region].mean()
    else:
        surface, region = None, board
        normals = np.broadcast_to([0.0, 0.0, 1.0], (H, W, 3))
        depth = np.zeros((H, W))
    target = np.zeros((H, W), bool)
    target[TARGET] = True
    points = np.asarray(jaxps.surface_points(jnp.asarray(depth, jnp.float32)), np.float64)
    points[target, 2] = NEAR_DEPTH
    normals = np.where(target[..., None], [0.0, 0.0, 1.0], normals)
    positions = distance * lights
    directions, falloff = (np.asarray(a, np.float64) for a in
                           jaxps.near_light_field(positions, jnp.asarray(points, jnp.float32)))
    albedo = np.where(target, TARGET_ALBEDO, np.where(region, 0.6, 0.0))
    strength = np.exp(rng.normal(0, 0.1, len(lights)))
    images = (np.maximum(np.einsum("khwc,hwc->khw", directions, normals), 0) * falloff * albedo
              * strength[:, None, None])
    images = images + 0.005 * rng.standard_normal(images.shape)
    images = np.clip(np.where(region | target, images, 0), 0, 1).astype(np.float32)
    return images, surface, target, strength / np.exp(np.mean(np.log(strength))), positions


def near(seeds, lights) -> dict:
    from jaxps.acquisition import target_ratios

    board = np.zeros((H, W), bool)
    board[32:224, 24:200] = True  # the face's place
    rows = {}
    for distance in (1000.0, 2000.0):
        errors, near_errors, strength_errors = {}, {}, {}
        for seed in seeds:
            images, face, target, strength, positions = near_capture(seed, lights, distance)
            board_images = near_capture(1000 + seed, lights, distance, board=board)[0]
            ratios = target_ratios(board_images, lights, target, board)
            mask = np.asarray(face.mask)
            est = lambda **kw: np.asarray(jaxps.intensity_estimate(
                images, lights, method="frontal", **kw), np.float64)
            on_target = est(mask=target)
            for name, e in {"frontal (face, the default)": est(mask=mask),
                            "target": on_target, "target x ratios": on_target * ratios,
                            "oracle": strength}.items():
                e = e / np.exp(np.mean(np.log(e)))
                frames = jnp.asarray(np.clip(images / e[:, None, None], 0, 1), jnp.float32)
                far = jaxps.photometric_stereo(frames, lights, mask=mask)
                # normals only, scored as they were measured: with FC's steps
                close = jaxps.near_photometric_stereo(frames, positions, mask=mask,
                                                     integration="fc").ps
                for store, res in ((errors, far), (near_errors, close)):
                    store.setdefault(name, []).append(jaxps.evaluate.angular_stats(
                        res.normals, face.normals, mask=mask)["median_deg"])
                strength_errors.setdefault(name, []).append(
                    float(np.max(np.abs(e / strength - 1))))
        key = f"lamps at {distance:g} mm"
        rows[key] = {name: {
            "distant_ps_median_over_seeds_deg": float(np.median(errors[name])),
            "near_ps_median_over_seeds_deg": float(np.median(near_errors[name])),
            "largest_intensity_error_median": float(np.median(strength_errors[name])),
            "distant_ps_per_seed_deg": np.round(errors[name], 4).tolist(),
            "near_ps_per_seed_deg": np.round(near_errors[name], 4).tolist()}
            for name in errors}
        print(key, {n: (round(r["distant_ps_median_over_seeds_deg"], 2),
                        round(r["near_ps_median_over_seeds_deg"], 2),
                        round(r["largest_intensity_error_median"], 4))
                    for n, r in rows[key].items()}, flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--yale", action="store_true",
                    help="the shared Yale B faces with an emulated target (see above)")
    ap.add_argument("--register", action="store_true",
                    help="with --yale: the reference from registered frames")
    ap.add_argument("--near", action="store_true",
                    help="the synthetic face under near lights, with the target's ratios")
    args = ap.parse_args(argv)
    command = ("OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_reference_target.py "
               + " ".join(sys.argv[1:] if argv is None else argv))
    if args.yale:
        out = {"command": command, "environment": environment(), "registered": args.register,
               "target": {"rows": [YALE_TARGET[0].start, YALE_TARGET[0].stop],
                          "columns": [YALE_TARGET[1].start, YALE_TARGET[1].stop],
                          "albedo": TARGET_ALBEDO}, **yale(args.register)}
        print("median over subjects:", {k: round(v, 2) for k, v in
                                        out["median_over_subjects_deg"].items()},
              "floor", round(out["median_floor_deg"], 2))
        write_json("reference_target_yale" + "_registered" * args.register, out)
        return out
    lights = np.asarray(faces.lights_of(list(faces.CROSS)), np.float64)
    if args.near:
        out = {"command": command, "environment": environment(), "image": [H, W],
               "pixel_mm": 1.0, "target_depth_mm": NEAR_DEPTH, "seeds": args.seeds,
               "rows": near(range(args.seeds), lights.astype(np.float32))}
        write_json("reference_target_near", out)
        return out
    out = {"command": command,
           "environment": environment(), "image": [H, W], "seeds": args.seeds,
           "lights": [f"{a:+d},{e:+d}" for a, e in faces.CROSS],
           "target": {"rows": [TARGET[0].start, TARGET[0].stop],
                      "columns": [TARGET[1].start, TARGET[1].stop], "albedo": TARGET_ALBEDO},
           "rows": run(range(args.seeds), lights)}
    write_json("reference_target", out)
    return out


if __name__ == "__main__":
    main()
