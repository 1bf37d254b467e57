"""ICP on the DiLiGenT ground-truth scans: undo a known misalignment; scan error maps.

For each object, the scan's depth is back-projected twice on disjoint pixel samplings (source:
odd rows and columns, target: even rows), the source is turned by (3, -4, 5) degrees about x, y,
z through its centroid and shifted by (5, -8, 10) mm, and ICP must bring it back. Compared in the
same run: jaxps point-to-plane and point-to-point, and OpenCV's `ppf_match_3d_ICP` (point-to-plane,
Picky ICP; needs normals on both clouds, which it is given from the ground-truth normal map).

Then the reconstruction check of the papers: the ground-truth normals integrated with
`jaxps.integrate` (Frankot-Chellappa), aligned to the scan with scaled ICP, and the RMS height
error, median angular error and mean l2-norm error after alignment.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_icp.py [--quick]

writes benchmarks/results/icp.json and icp.png (and icp_error_maps_<object>.png).
"""

from __future__ import annotations

import argparse
import sys
import time

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

try:
    from benchmarks._common import RESULTS, data_dir, environment, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[1]))
    from benchmarks._common import RESULTS, data_dir, environment, write_json

import jaxps
from jaxps import evaluate as ev

OBJECTS = ("bear", "cat", "pot1", "reading")
ANGLES_DEG = (3.0, -4.0, 5.0)
SHIFT_MM = (5.0, -8.0, 10.0)


def load(obj: str):
    root = data_dir() / "diligent_gt" / obj
    depth = np.load(root / "depth_gt.npz")["depth_gt"]
    mask = (cv2.imread(str(root / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0) & np.isfinite(depth)
    k = np.loadtxt(root / "K.txt")
    raw = cv2.imread(str(root / "normal_map.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    normals = raw.astype(np.float32) / 65535 * 2 - 1
    normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-6)
    return depth, mask, k, normals


def errors(aligned, truth, rotation, r0):
    """Rotation left over (deg), centroid offset (mm) and worst point error (mm)."""
    aligned = np.asarray(aligned, np.float64)
    return {
        "rotation_error_deg": float(np.degrees(
            Rotation.from_matrix(np.asarray(rotation, np.float64) @ r0).magnitude())),
        "translation_error_mm": float(np.linalg.norm(aligned.mean(0) - truth.mean(0))),
        "max_point_error_mm": float(np.max(np.linalg.norm(aligned - truth, axis=-1))),
    }


def run_object(obj: str, step: int, repeats: int) -> dict:
    depth, mask, k, normals = load(obj)
    src_mask, tgt_mask = mask.copy(), mask.copy()
    src_mask[::step] = False
    src_mask[:, ::step] = False
    tgt_mask[1::step] = False
    src, sp = ev.points_from_depth(depth, k, mask=src_mask)
    tgt, tp = ev.points_from_depth(depth, k, mask=tgt_mask)
    truth = src.astype(np.float64)
    r0 = Rotation.from_euler("xyz", ANGLES_DEG, degrees=True).as_matrix()
    c = truth.mean(0)
    moved = ((truth - c) @ r0.T + c + np.asarray(SHIFT_MM)).astype(np.float32)
    tn = normals[tp[:, 0], tp[:, 1]]
    out = {"object": obj, "n_source": int(len(src)), "n_target": int(len(tgt)),
           "start": errors(moved, truth, np.eye(3), r0), "methods": {}}

    for method in ev.ICP_METHODS:
        times = []
        for _ in range(1 + repeats):
            t0 = time.perf_counter()
            res = ev.icp(moved, tgt, method=method, max_steps=100, target_normals=tn)
            times.append(time.perf_counter() - t0)
        out["methods"][f"jaxps {method}"] = {
            **errors(res.aligned, truth, res.rotation, r0),
            "rms_mm": res.rms, "steps": res.steps, "converged": res.converged,
            "first_call_s": times[0], "run_s": min(times[1:]),
        }

    # OpenCV (contrib surface_matching): point-to-plane ICP, 100 iterations, 4 pyramid levels.
    src_n = (normals[sp[:, 0], sp[:, 1]] @ r0.T).astype(np.float32)
    model = np.hstack([moved, src_n]).astype(np.float32)
    scene = np.hstack([tgt, tn]).astype(np.float32)
    times = []
    for _ in range(1 + repeats):
        icp_cv = cv2.ppf_match_3d_ICP(100, 1e-5, 2.5, 4)
        t0 = time.perf_counter()
        ret, residual, pose = icp_cv.registerModelToScene(model, scene)
        times.append(time.perf_counter() - t0)
    aligned = moved.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    out["methods"]["opencv ppf_match_3d_ICP"] = {
        **errors(aligned, truth, pose[:3, :3], r0),
        "residual": float(residual), "returned": int(ret),
        "first_call_s": times[0], "run_s": min(times[1:]),
    }

    # The papers' check: a reconstruction (here FC on the true normals) against the scan.
    height = np.asarray(jaxps.integrate(normals, mask=mask))
    full, fp = ev.points_from_depth(depth, k, mask=mask)
    t0 = time.perf_counter()
    comp = ev.compare_to_scan(height, full, mask=mask, normals=normals,
                              target_normals=normals[fp[:, 0], fp[:, 1]], trim=0.95)
    out["fc_reconstruction_vs_scan"] = {
        "integration": "fc", "icp": "point_to_plane, scale, trim 0.95, init centroid",
        "rms_height_mm": comp.rms_height, "mean_abs_height_mm": comp.mean_abs_height,
        "median_angular_deg": comp.median_angular, "mean_angular_deg": comp.mean_angular,
        "mean_l2": comp.mean_l2, "scale_mm_per_px": comp.icp.scale,
        "steps": comp.icp.steps, "converged": comp.icp.converged,
        "seconds": time.perf_counter() - t0,
    }
    ev.plot_error_maps(
        {"height error": comp.height_error, "angular error": comp.angular_error,
         "l2-norm error": comp.l2_error},
        mask=comp.mask, units={"height error": "mm", "angular error": "degrees"},
        signed=("height error",), path=RESULTS / f"icp_error_maps_{obj}.png")
    return out


def chart(results: list[dict], path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    markers = {"jaxps point_to_plane": "o", "jaxps point_to_point": "s",
               "opencv ppf_match_3d_ICP": "^"}
    for name, mk in markers.items():
        xs = [r["methods"][name]["run_s"] for r in results]
        ys = [max(r["methods"][name]["rotation_error_deg"], 1e-5) for r in results]
        ax.scatter(xs, ys, marker=mk, label=name, s=40)
        for r, x, y in zip(results, xs, ys):
            ax.annotate(r["object"], (x, y), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("run time per alignment (s, after the first call)")
    ax.set_ylabel("rotation left over (degrees)")
    ax.set_title(f"ICP from ({', '.join(f'{a:g}' for a in ANGLES_DEG)}) deg + "
                 f"({', '.join(f'{s:g}' for s in SHIFT_MM)}) mm, DiLiGenT")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="sparser sampling, one repeat")
    args = ap.parse_args(argv)
    step = 3 if args.quick else 2
    repeats = 1 if args.quick else 2
    if not (data_dir() / "diligent_gt").is_dir():
        print(f"skip: no DiLiGenT data at {data_dir()}")
        return {}
    results = [run_object(obj, step, repeats) for obj in OBJECTS]
    payload = {
        "benchmark": "icp",
        "command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_icp.py"
                   + (" --quick" if args.quick else ""),
        "misalignment": {"rotation_xyz_deg": ANGLES_DEG, "translation_mm": SHIFT_MM},
        "sampling": f"source rows/cols not divisible by {step}, target rows not == 1 mod {step}",
        "environment": environment(),
        "objects": results,
        # For the summary chart of `python -m benchmarks`: one point per method.
        "points": [
            {"panel": "ICP, DiLiGenT, undo (3,-4,5) deg + (5,-8,10) mm, mean of 4 objects",
             "method": name, "error_name": "rotation left (deg)",
             "error": float(np.mean([r["methods"][name]["rotation_error_deg"] for r in results])),
             "run_s": float(np.mean([r["methods"][name]["run_s"] for r in results])),
             "compile_s": float(np.mean([r["methods"][name]["first_call_s"]
                                         - r["methods"][name]["run_s"] for r in results])),
             "baseline": name.startswith("opencv")}
            for name in results[0]["methods"]
        ],
    }
    path = write_json("icp", payload)
    chart(results, RESULTS / "icp.png")
    for r in results:
        pp = r["methods"]["jaxps point_to_plane"]
        fc = r["fc_reconstruction_vs_scan"]
        print(f"{r['object']:8s} p2plane {pp['rotation_error_deg']:.4f} deg "
              f"{pp['max_point_error_mm']:.3f} mm {pp['run_s']:.3f} s | "
              f"FC vs scan RMS {fc['rms_height_mm']:.2f} mm, "
              f"median {fc['median_angular_deg']:.1f} deg")
    print(f"wrote {path}")
    return payload


if __name__ == "__main__":
    main()
