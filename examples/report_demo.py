"""A run folder and its HTML report, from a small synthetic capture with known truth.

    python examples/report_demo.py --out report-out
    # then open report-out/run/report.html

The same as `jaxps demo --out DIR` followed by `jaxps report DIR --truth-normals ...
--truth-scan ...`: the truth as a normal map and as a scanned mesh in millimetres.
"""

import argparse
import pathlib

import cv2
import jax
import numpy as np

import jaxps
from jaxps.cli import reconstruct
from jaxps.report import write_report

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("report-out"))
ap.add_argument("--size", type=int, default=96)
args = ap.parse_args()
frames_dir = args.out / "frames"
frames_dir.mkdir(parents=True, exist_ok=True)

# --8<-- [start:body]
# 16-bit frames of a synthetic face, as a camera would write them.
surface = jaxps.synthetic.face_like(args.size)
lights = jaxps.synthetic.scanner_lights(20.0)
scene = jaxps.synthetic.render_scene(surface, lights, noise=0.005, key=jax.random.key(1))
paths = []
for k, img in enumerate(np.asarray(scene.images)):
    paths.append(frames_dir / f"frame_{k}.png")
    cv2.imwrite(str(paths[-1]), np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16))
np.savetxt(frames_dir / "lights.txt", lights, header=str(len(lights)), comments="")
cv2.imwrite(str(frames_dir / "mask.png"), np.asarray(scene.mask).astype(np.uint8) * 255)

# `jaxps reconstruct ... --report`, from Python.
run = args.out / "run"
reconstruct([str(p) for p in paths], str(run), lights=str(frames_dir / "lights.txt"),
            mask=str(frames_dir / "mask.png"), report=True)

# Add the ground truth: error maps appear in the report. The surface also comes as a scanner
# would hand it over, a mesh in millimetres (0.3 mm a pixel, here), compared after scaled ICP.
from jaxps.report._writers import write_normal_map  # noqa: E402

write_normal_map(args.out / "truth_normals.png", np.asarray(scene.normals))
scan = jaxps.report.to_trimesh(np.asarray(scene.height), np.asarray(scene.mask))
scan.apply_scale(0.3)
scan.export(args.out / "scan.ply")
page = write_report(run, truth_normals=args.out / "truth_normals.png",
                    truth_scan=args.out / "scan.ply")
# --8<-- [end:body]
print(f"wrote {page}")
points, scan_normals = jaxps.evaluate.read_scan(args.out / "scan.ply")
comp = jaxps.evaluate.compare_to_scan(np.load(run / "height.npy"), points,
                                      mask=np.load(run / "status.npy") == 0,
                                      target_normals=scan_normals, trim=0.95)
print(f"against the scan: RMS height error {comp.rms_height:.3f} mm, "
      f"ICP scale {comp.icp.scale:.3f} mm a pixel")
