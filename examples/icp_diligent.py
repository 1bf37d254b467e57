"""ICP against a ground-truth scan: undo a known misalignment, then map a reconstruction's errors.

Uses the DiLiGenT "bear" ground truth (depth in mm, intrinsics, normal map).

    python examples/icp_diligent.py --out icp-out
"""

import argparse
import pathlib
import sys

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _paths import data_dir  # noqa: E402

import jaxps  # noqa: E402
from jaxps import evaluate  # noqa: E402

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("icp-out"))
ap.add_argument("--object", default="bear", choices=["bear", "cat", "pot1", "reading"])
args = ap.parse_args()
args.out.mkdir(parents=True, exist_ok=True)

# --8<-- [start:load]
root = data_dir() / "diligent_gt" / args.object
depth = np.load(root / "depth_gt.npz")["depth_gt"]  # (512, 612) mm, NaN off the object
mask = (cv2.imread(str(root / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0) & np.isfinite(depth)
K = np.loadtxt(root / "K.txt")  # 3x3 intrinsics, f ~ 3770 px
raw = cv2.imread(str(root / "normal_map.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]  # 16-bit RGB
normals = raw.astype(np.float32) / 65535 * 2 - 1

scan, pix = evaluate.points_from_depth(depth, K, mask=mask)  # (N, 3) mm, camera frame
scan_normals = normals[pix[:, 0], pix[:, 1]]
# --8<-- [end:load]

# --8<-- [start:misalign]
# Odd rows, turned by (3, -4, 5) degrees about their centroid and moved (5, -8, 10) mm, against
# the even rows: two samplings of one surface, as two scanners would give.
odd = pix[:, 0] % 2 == 1
truth, target, target_normals = scan[odd], scan[~odd], scan_normals[~odd]
R0 = Rotation.from_euler("xyz", [3, -4, 5], degrees=True).as_matrix()
c = truth.mean(axis=0)
moved = ((truth - c) @ R0.T + c + [5.0, -8.0, 10.0]).astype(np.float32)

fit = evaluate.icp(moved, target, method="point_to_plane", target_normals=target_normals)
left = np.degrees(Rotation.from_matrix(fit.rotation.astype(np.float64) @ R0).magnitude())
worst = np.linalg.norm(fit.aligned - truth, axis=-1).max()
print(f"ICP: {fit.steps} steps, converged={fit.converged}, rotation left {left:.4f} deg, "
      f"worst point {worst:.4f} mm")
# --8<-- [end:misalign]

# --8<-- [start:compare]
# A reconstruction in pixel units (here: the true normals integrated with Frankot-Chellappa)
# against the scan in mm: scaled ICP, then per-pixel error maps.
height = np.asarray(jaxps.integrate(normals, mask=mask))
comp = evaluate.compare_to_scan(height, scan, mask=mask, normals=normals,
                                target_normals=scan_normals, trim=0.95)
print(f"FC height vs scan: RMS {comp.rms_height:.2f} mm, median angular error "
      f"{comp.median_angular:.1f} deg, scale {comp.icp.scale:.3f} mm/px")
evaluate.plot_error_maps(
    {"height error": comp.height_error, "angular error": comp.angular_error},
    mask=comp.mask, signed=("height error",),
    units={"height error": "mm", "angular error": "degrees"},
    path=args.out / f"icp_{args.object}.png")
# --8<-- [end:compare]
print(f"wrote {args.out / f'icp_{args.object}.png'}")
