"""Writing results: 16-bit normal maps, albedo, height, PLY meshes, a preview image.

OpenCV and trimesh are imported by the functions that use them.
"""

from __future__ import annotations

import csv
import json
import os

import numpy as np

__all__ = ["read_normal_map", "write_albedo", "write_csv", "write_json", "write_normal_map",
           "write_preview"]


def write_normal_map(path, normals: np.ndarray) -> None:
    """Write `(H, W, 3)` unit normals as a 16-bit RGB PNG, value = (n + 1) / 2 * 65535.

    The DiLiGenT convention of shared/data/README.md (x right, y up, z toward the viewer).
    """
    import cv2

    v = np.clip(np.asarray(normals, np.float32), -1, 1)  # a new array, then in place
    v += 1
    v *= np.float32(65535 / 2)
    if not cv2.imwrite(os.fspath(path), np.rint(v, out=v).astype(np.uint16)[..., ::-1]):
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


def _plain(value):
    """`value` with NumPy scalars and arrays as Python numbers and lists, tuples as lists, and
    every negative zero as 0.0 (recursively)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and value == 0.0:
        return 0.0  # -0.0 == 0.0: both become +0.0
    return value


def write_json(path, data: dict) -> None:
    """`data` as indented JSON; NumPy values become plain numbers and lists, and `-0.0` (a
    light direction's zero component, say) is written as `0.0`."""
    with open(path, "w") as f:
        json.dump(_plain(data), f, indent=2)
        f.write("\n")


def write_csv(path, rows) -> None:
    """Rows of dicts as CSV: a header from the keys of the first row, one line per row."""
    rows = [_plain(r) for r in rows]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]) if rows else [])
        writer.writeheader()
        writer.writerows(rows)


def write_preview(path, normals, albedo, height, mask, title: str = "", *,
                  max_height: int = 480) -> None:
    """A one-row PNG: normal map, albedo and the height map shaded from the upper left.

    Drawn with OpenCV rather than matplotlib (about 1 s less per `jaxps reconstruct` at 1 MP,
    most of it importing matplotlib). Panels are scaled to at most `max_height` rows (small
    frames up to twice their size, to at least half of it); pixels outside `mask` are white.
    `title` goes in a band above the panels, the panel names in one below.
    """
    import cv2

    normals, mask = np.asarray(normals, np.float32), np.asarray(mask, bool)
    h, w = mask.shape
    f = max_height / h if h > max_height else min(2.0, max(1.0, max_height / 2 / h))
    size = (max(1, round(w * f)), max(1, round(h * f)))

    def small(img):
        if f == 1:
            return img
        return cv2.resize(img, size, interpolation=cv2.INTER_AREA if f < 1 else cv2.INTER_LINEAR)

    inside = small(mask.astype(np.float32)) > 0.5
    rgb = np.clip((small(normals) + 1) / 2, 0, 1)
    alb = np.asarray(albedo, np.float32)
    top = float(np.percentile(alb[mask], 99.5)) if mask.any() else 1.0
    alb = np.clip(small(alb) / (top or 1.0), 0, 1)
    if alb.ndim == 2:
        alb = np.repeat(alb[..., None], 3, axis=-1)
    # Hillshade (Lambertian, light at azimuth 315, altitude 45 deg), as matplotlib's LightSource.
    z = np.where(mask, height, np.nanmin(np.where(mask, height, np.inf)) if mask.any() else 0)
    dz_dy, dz_dx = np.gradient(small(np.nan_to_num(np.asarray(z, np.float32))) * f)
    az, alt = np.radians(90 - 315), np.radians(45)
    shade = (-dz_dx * np.cos(az) * np.cos(alt) - dz_dy * np.sin(az) * np.cos(alt)
             + np.sin(alt)) / np.sqrt(dz_dx**2 + dz_dy**2 + 1)
    lo, hi = (float(shade[inside].min()), float(shade[inside].max())) if inside.any() else (0, 1)
    shade = np.clip((shade - lo) / ((hi - lo) or 1.0), 0, 1)
    panels = [rgb, alb, np.repeat(shade[..., None], 3, axis=-1)]
    panels = [np.where(inside[..., None], p, 1.0) for p in panels]
    gap = np.ones((size[1], 8, 3), np.float32)
    row = np.concatenate([panels[0], gap, panels[1], gap, panels[2]], axis=1)
    top, bottom = (np.ones((24, row.shape[1], 3), np.float32) for _ in range(2))
    text = {"fontFace": cv2.FONT_HERSHEY_SIMPLEX, "fontScale": 0.45, "color": (0, 0, 0),
            "thickness": 1, "lineType": cv2.LINE_AA}
    cv2.putText(top, title, (4, 17), **text)
    for i, label in enumerate(("normals (RGB = xyz)", "albedo", "height (shaded)")):
        cv2.putText(bottom, label, (4 + i * (size[0] + 8), 17), **text)
    image = np.round(np.concatenate([top, row, bottom]) * 255).astype(np.uint8)
    if not cv2.imwrite(os.fspath(path), image[..., ::-1]):
        raise OSError(f"could not write {path}")
