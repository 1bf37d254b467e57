"""Tutorial: from raw Yale B frames to a relit face (Lambertian), checked against real photos.

Five frames of subject yaleB01 under scanner-like lights (one at the camera, four at 20-25
degrees) and the ambient-only control frame go in; normals, albedo and a height map come out; the
face is then relit under every other Yale B light within 30 degrees of the camera and compared
with the real photograph taken under that light.

    python examples/tutorial_yaleb.py --out tutorial-out
"""

import argparse
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _paths import data_dir  # noqa: E402

import jaxps  # noqa: E402
from jaxps.acquisition import load_capture  # noqa: E402

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("tutorial-out"))
args = ap.parse_args()
args.out.mkdir(parents=True, exist_ok=True)

# --8<-- [start:load]
folder = data_dir() / "yaleb" / "yaleB01"
train = [(0, 0), (25, 0), (-25, 0), (0, 20), (0, -20)]  # (azimuth, elevation), degrees
frames = [folder / f"yaleB01_P00A{a:+04d}E{e:+03d}.pgm" for a, e in train]
capture = load_capture(
    frames,
    yale_names=True,  # lights from the file names: yaleB01_P00A+025E+00.pgm -> (25, 0)
    ambient=folder / "yaleB01_P00_Ambient.pgm",  # the control frame, subtracted
)
print(capture.images.shape, capture.images.dtype)  # (5, 192, 168) float32 in [0, 1]
print(np.round(capture.lights, 3))  # (5, 3) unit vectors, x right, y up, z to the camera
# --8<-- [end:load]

# --8<-- [start:solve]
result = jaxps.photometric_stereo(capture.images, capture.lights, shadow_threshold=0.01)
face = (np.asarray(result.status) == 0) & (np.asarray(result.albedo) > 0.02)
print("pixels:", jaxps.status_counts(result.status))
height = np.asarray(jaxps.integrate(result.normals, mask=face, method="lsq"))
# --8<-- [end:solve]

# --8<-- [start:relight]
# Every other light within 30 degrees of the camera is a held-out test.
tests = []
for path in sorted(folder.glob("yaleB01_P00A*.pgm")):
    az, el = jaxps.parse_yale_name(path.name)
    light = jaxps.lights_from_angles([az], [el])[0]
    if (az, el) not in train and np.degrees(np.arccos(light[2])) <= 30:
        tests.append(path)
# Loaded with the training frames, so that all are moved onto the same (frontal) frame.
everything = load_capture(frames + tests, yale_names=True,
                          ambient=folder / "yaleB01_P00_Ambient.pgm")
held_out = everything.images[len(frames):]
relit = np.asarray(jaxps.render_lambertian(result.normals, result.albedo,
                                           everything.lights[len(frames):]))

# RMSE in grey levels (0-255) over the face, per held-out light.
diff = (relit - held_out)[:, face] * 255
rmse = np.sqrt(np.mean(diff**2, axis=1))
print(f"relighting {len(tests)} held-out lights within 30 deg: RMSE {rmse.mean():.1f} grey "
      f"levels (range {rmse.min():.1f}-{rmse.max():.1f})")
# --8<-- [end:relight]

# --8<-- [start:figure]
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

show = int(np.argmax([abs(jaxps.parse_yale_name(p.name)[0]) for p in tests]))
shaded = np.asarray(jaxps.render_lambertian(
    jaxps.normals_from_height(height), np.where(face, 0.8, 0.0).astype(np.float32),
    jaxps.lights_from_angles([-30], [30])))[0]
panels = [
    ("one input frame", capture.images[0], "gray"),
    ("normals (RGB)", np.where(face[..., None], (np.asarray(result.normals) + 1) / 2, 1), None),
    ("albedo", np.asarray(result.albedo), "gray"),
    ("height, shaded", np.where(face, shaded, 1), "gray"),
    (f"relit: {tests[show].stem[-8:]}", relit[show], "gray"),
    ("real photo, same light", held_out[show], "gray"),
]
fig, axes = plt.subplots(1, len(panels), figsize=(2.2 * len(panels), 2.8))
for ax, (title, img, cmap) in zip(axes, panels):
    ax.imshow(np.clip(img, 0, 1), cmap=cmap, vmin=0, vmax=1)
    ax.set_title(title, fontsize=8)
    ax.set_axis_off()
fig.tight_layout()
fig.savefig(args.out / "tutorial_yaleb.png", dpi=110)
plt.close(fig)
# --8<-- [end:figure]
print(f"wrote {args.out / 'tutorial_yaleb.png'}")
