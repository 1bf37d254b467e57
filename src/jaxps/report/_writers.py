"""Writing results: 16-bit normal maps, albedo, height, PLY meshes, a preview figure.

OpenCV and matplotlib are imported by the functions that use them.
"""

from __future__ import annotations

import json
import os

import numpy as np

__all__ = ["read_normal_map", "write_albedo", "write_json", "write_normal_map", "write_ply",
           "write_preview"]


def write_normal_map(path, normals: np.ndarray) -> None:
    """Write `(H, W, 3)` unit normals as a 16-bit RGB PNG, value = (n + 1) / 2 * 65535.

    The DiLiGenT convention of shared/data/README.md (x right, y up, z toward the viewer).
    """
    import cv2

    v = np.round((np.clip(np.asarray(normals, np.float64), -1, 1) + 1) / 2 * 65535)
    if not cv2.imwrite(os.fspath(path), v.astype(np.uint16)[..., ::-1]):
        raise OSError(f"could not write {path}")


def read_normal_map(path) -> np.ndarray:
    """Read a 16-bit normal-map PNG back to `(H, W, 3)` float32 normals (inverse of the writer)."""
    import cv2

    raw = cv2.imread(os.fspath(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.dtype != np.uint16 or raw.ndim != 3:
        raise ValueError(f"{path} is not a 16-bit RGB normal map")
    return (raw[..., ::-1].astype(np.float32) / 65535 * 2 - 1).astype(np.float32)


def write_albedo(path, albedo: np.ndarray) -> float:
    """Write albedo as a 16-bit PNG scaled so its 99.5th percentile maps to 0.95 of full range.

    Returns the scale (stored value / 65535 = albedo * scale), which callers record.
    """
    import cv2

    a = np.asarray(albedo, np.float64)
    top = float(np.percentile(a[a > 0], 99.5)) if np.any(a > 0) else 1.0
    scale = 0.95 / top if top > 0 else 1.0
    v = np.round(np.clip(a * scale, 0, 1) * 65535).astype(np.uint16)
    if v.ndim == 3:
        v = v[..., ::-1]
    if not cv2.imwrite(os.fspath(path), v):
        raise OSError(f"could not write {path}")
    return scale


def write_ply(path, height: np.ndarray, mask: np.ndarray, *, pixel_size: float = 1.0) -> int:
    """Write the masked height map as a binary PLY triangle mesh; returns the face count.

    Vertices are (x, y, z) in the camera frame (x right, y up, pixel units times
    `pixel_size`); each 2x2 block of valid pixels gives two triangles, wound toward the viewer.
    """
    h, w = height.shape
    mask = np.asarray(mask, bool) & np.isfinite(height)
    index = np.full((h, w), -1, np.int64)
    index[mask] = np.arange(mask.sum())
    rows, cols = np.nonzero(mask)
    verts = np.stack([cols * pixel_size, (h - 1 - rows) * pixel_size, height[mask]], axis=1)

    a, b = index[:-1, :-1], index[:-1, 1:]  # top-left, top-right
    c, d = index[1:, :-1], index[1:, 1:]  # bottom-left, bottom-right
    quads = (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)
    faces = np.concatenate([np.stack([a[quads], c[quads], b[quads]], 1),
                            np.stack([b[quads], c[quads], d[quads]], 1)])
    vertex = np.empty(len(verts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    vertex["x"], vertex["y"], vertex["z"] = verts.T
    face = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face["n"], face["v"] = 3, faces
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertex)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(face)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(vertex.tobytes())
        f.write(face.tobytes())
    return len(face)


def write_json(path, data: dict) -> None:
    with open(path, "w") as f:
        json.dump(data, f, indent=2)
        f.write("\n")


def write_preview(path, normals, albedo, height, mask, title: str = "") -> None:
    """A one-row figure: normal map, albedo and the height map shaded from the upper left."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    normals, mask = np.asarray(normals), np.asarray(mask, bool)
    ls = matplotlib.colors.LightSource(azdeg=315, altdeg=45)
    z = np.where(mask, height, np.nan)
    shaded = ls.hillshade(np.nan_to_num(z, nan=float(np.nanmin(z)) if mask.any() else 0.0))
    fig, axes = plt.subplots(1, 3, figsize=(12, 4.4), constrained_layout=True)
    axes[0].imshow(np.where(mask[..., None], (normals + 1) / 2, 1).clip(0, 1))
    axes[0].set_title("normals (RGB = xyz)")
    alb = np.asarray(albedo)
    top = np.percentile(alb[mask], 99.5) if mask.any() else 1
    axes[1].imshow(np.clip(alb / (top or 1), 0, 1), cmap="gray" if alb.ndim == 2 else None)
    axes[1].set_title("albedo")
    axes[2].imshow(np.where(mask, shaded, 1), cmap="gray")
    axes[2].set_title("height (shaded)")
    for ax in axes:
        ax.set_axis_off()
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=100)
    plt.close(fig)
