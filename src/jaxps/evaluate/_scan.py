"""Error maps of a reconstruction against a ground-truth scan, after ICP alignment.

The face-scanner papers judge a reconstruction against a commercial 3-D scan: the two are
aligned with ICP, then the RMS height error, the $\\ell_2$-norm error of the normals and the
angular error are reported and shown as colour maps (e.g. Hansen, Atkinson, Smith & Smith, "3D
face reconstructions from photometric stereo using near infrared and visible light", CVIU
114(8), 2010; Zafeiriou et al., "Face recognition and verification using photometric stereo:
the Photoface database and a comprehensive evaluation", IEEE TIFS 8(1), 2013).

Here the reconstruction's height map becomes a point cloud (`points_from_height`), is aligned to
the scan's point cloud (`icp`, with a global scale by default, since a height map in pixel units
meets a scan in millimetres), and each reconstructed pixel is compared with its nearest scan
point:

- height error: the signed distance from the aligned point to the scan's tangent plane at that
  scan point (positive in front of the scan), in the scan's unit;
- angular error: the angle between the reconstructed normal turned by the ICP rotation and the
  scan's normal, in degrees;
- $\\ell_2$-norm error: $\\lVert R n - n_{gt} \\rVert_2$ of the same pair (0 to 2; about the angle
  in radians for small errors).
"""

from __future__ import annotations

import os
import pathlib
import re
from typing import NamedTuple

import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from ._icp import (
    _COLLAPSED,
    ICPResult,
    _spread_ratio,
    estimate_normals,
    icp,
    points_from_height,
)

__all__ = ["SCAN_EXTENSIONS", "ScanComparison", "compare_to_scan", "l2_error", "read_scan"]

# Meshes and point clouds trimesh reads, then text and numpy point lists (`read_scan`).
_MESH_EXTENSIONS = (".ply", ".obj", ".stl", ".off", ".glb")
_TEXT_EXTENSIONS = (".xyz", ".txt", ".csv", ".asc")
# Range images of a structured-light scanner on its pixel grid (FRGC's Minolta Vivid scans).
_RANGE_EXTENSIONS = (".abs", ".abs.gz")
SCAN_EXTENSIONS: tuple[str, ...] = (*_MESH_EXTENSIONS, *_TEXT_EXTENSIONS, ".npy",
                                    *_RANGE_EXTENSIONS)


class ScanComparison(NamedTuple):
    """Per-pixel errors of a reconstruction against a scan, on the reconstruction's pixel grid.

    - `height_error`: `(H, W)` signed distance to the scan's surface (scan units), 0 off `mask`.
    - `angular_error`: `(H, W)` degrees, 0 off `mask` (all 0 when no normals were given).
    - `l2_error`: `(H, W)` $\\lVert R n - n_{gt} \\rVert_2$, 0 off `mask`.
    - `mask`: `(H, W)` bool, the pixels compared (ICP inliers inside the input mask).
    - `rms_height`: RMS of `height_error` over `mask`; `mean_abs_height`: its mean |.|.
    - `median_angular`, `mean_angular`: degrees over `mask` (NaN when no normals were given).
    - `mean_l2`: mean $\\ell_2$-norm error over `mask` (NaN when no normals were given).
    - `icp`: the `ICPResult` of the alignment.
    """

    height_error: Float[np.ndarray, "H W"]
    angular_error: Float[np.ndarray, "H W"]
    l2_error: Float[np.ndarray, "H W"]
    mask: Bool[np.ndarray, "H W"]
    rms_height: float
    mean_abs_height: float
    median_angular: float
    mean_angular: float
    mean_l2: float
    icp: ICPResult


def read_scan(
    path: str | os.PathLike,
) -> tuple[Float[np.ndarray, "M 3"], Float[np.ndarray, "M 3"] | None]:
    """Read a ground-truth scan (a mesh or a point cloud) for `compare_to_scan`.

    - A mesh (`.ply` with faces, `.obj`, `.stl`, `.off`, `.glb`), as a structured-light or
      stereo face scanner exports one: its vertices, and normals from its faces (trimesh's
      vertex normals, or the ones the file stores).
    - A point cloud (`.ply` without faces, such as `jaxps reconstruct --points` writes): its
      vertices, and `nx ny nz` where the file has them.
    - Text (`.xyz`, `.txt`, `.csv`, `.asc`): `x y z` or `x y z nx ny nz` per line, separated by
      spaces, tabs, commas or semicolons; lines starting with `#` are skipped.
    - `.npy`: an `(M, 3)` or `(M, 6)` array in the same layout.
    - A range image (`.abs`, or gzipped `.abs.gz`), as the Face Recognition Grand Challenge
      distributes its 3-D face scans (Phillips et al., "Overview of the Face Recognition Grand
      Challenge", CVPR 2005): a line "R rows", a line "C columns", a line
      "pixels (flag X Y Z):", then R x C flags, X, Y and Z values in row order; the points
      whose flag is not 0. The grid shows which way the scanner's axes run, so the points are
      turned into the camera frame (by 180 degrees about an axis) when its y runs down the
      rows (OpenCV's frame) or its x against the columns.

    Any length unit will do, since `compare_to_scan` fits a scale. The axes must be roughly
    the camera's of DESIGN.md (x right, y up, z toward the camera): ICP corrects a few degrees,
    not a mesh stored with z up.

    **Returns:** `(points (M, 3), normals (M, 3) or None)` as float64; normals are unit length
    and `None` when the file has none (or any of them is zero or not finite), in which case
    `compare_to_scan` estimates them from the points.

    **Raises:** `FileNotFoundError` for a missing file; `ValueError` naming the file for an
    extension not in `SCAN_EXTENSIONS`, a file with fewer than 3 points, non-finite
    coordinates, text rows of other than 3 or 6 numbers, or a range image whose header or
    count of values is not that of its grid.
    """
    p = pathlib.Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"scan: no such file {p}")
    ext = ".abs.gz" if p.name.lower().endswith(".abs.gz") else p.suffix.lower()
    if ext not in SCAN_EXTENSIONS:
        raise ValueError(f"scan: {p} is not a scan format jaxps reads "
                         f"({', '.join(SCAN_EXTENSIONS)})")
    if ext in _MESH_EXTENSIONS:
        points, normals = _read_mesh(p)
    elif ext in _RANGE_EXTENSIONS:
        points, normals = _read_abs(p), None
    else:
        table = np.load(p) if ext == ".npy" else _read_table(p)
        table = np.asarray(table, np.float64)
        if table.ndim != 2 or table.shape[1] not in (3, 6):
            raise ValueError(f"scan: {p} holds an array of shape {table.shape}; expected "
                             "(M, 3) x y z or (M, 6) x y z nx ny nz")
        points, normals = table[:, :3], table[:, 3:] if table.shape[1] == 6 else None
    if points.shape[0] < 3:
        raise ValueError(f"scan: {p} has {points.shape[0]} points; ICP needs at least 3")
    if not np.all(np.isfinite(points)):
        raise ValueError(f"scan: {p} has NaN/Inf coordinates")
    if normals is not None:
        length = np.linalg.norm(normals, axis=-1, keepdims=True)
        normals = normals / length if np.all(np.isfinite(length) & (length > 0)) else None
    return points, normals


def _read_mesh(path: pathlib.Path):
    import trimesh

    try:
        geometry = trimesh.load(path)
    except Exception as err:  # trimesh raises many kinds for a broken file
        raise ValueError(f"scan: cannot read {path}: {err}") from err
    if isinstance(geometry, trimesh.Scene):  # an OBJ of several groups
        geometry = geometry.to_mesh()
    points = np.asarray(geometry.vertices, np.float64)
    if isinstance(geometry, trimesh.Trimesh) and len(geometry.faces):
        return points, np.asarray(geometry.vertex_normals, np.float64)
    # A PLY point cloud's own columns: a dict of arrays (ASCII) or a record array (binary).
    vertex = geometry.metadata.get("_ply_raw", {}).get("vertex", {}).get("data", {})
    names = (vertex.dtype.names or ()) if isinstance(vertex, np.ndarray) else vertex
    if all(k in names for k in ("nx", "ny", "nz")):
        normals = np.stack([np.ravel(vertex[k]) for k in ("nx", "ny", "nz")], axis=1)
        if normals.shape == points.shape:
            return points, normals.astype(np.float64)
    return points, None


def _read_abs(path: pathlib.Path) -> np.ndarray:
    """The valid points of an FRGC range image (`read_scan`), `(M, 3)` float64."""
    import gzip

    opener = gzip.open if path.suffix.lower() == ".gz" else open
    try:
        with opener(path, "rt", encoding="utf-8-sig") as f:
            header = [f.readline().strip() for _ in range(3)]
            body = f.read()
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"scan: cannot read {path}: {err}") from err
    found = [re.fullmatch(r"(\d+)\s+" + word, line, re.IGNORECASE)
             for line, word in zip(header, ("rows", "columns"))]
    if not all(found) or not header[2].lower().startswith("pixels"):
        raise ValueError(f"scan: {path} does not start as a range image does ('R rows', "
                         f"'C columns', 'pixels (flag X Y Z):'), but with {header!r}")
    rows, cols = (int(m.group(1)) for m in found)
    try:
        values = np.array(body.split(), np.float64)
    except ValueError:
        raise ValueError(f"scan: {path} holds a value that is not a number") from None
    if values.size != 4 * rows * cols:
        raise ValueError(f"scan: {path} holds {values.size} values; {rows} rows x {cols} "
                         f"columns need {4 * rows * cols} (a flag, X, Y and Z per pixel)")
    flags, xyz = values[: rows * cols], values[rows * cols:].reshape(3, -1)
    valid = np.flatnonzero(flags != 0)
    points = xyz[:, valid].T.copy()
    # The grid says which way the scanner's axes run. The camera frame has x growing with the
    # column and y falling with the row; a frame with y down the rows (OpenCV's, z forward)
    # or x against the columns is turned by 180 degrees about the axis that agrees, which
    # keeps a right-handed frame right-handed.
    row, col = np.divmod(valid, cols)
    x_right = np.cov(points[:, 0], col)[0, 1] >= 0 if len(valid) > 1 else True
    y_up = np.cov(points[:, 1], row)[0, 1] <= 0 if len(valid) > 1 else True
    flip = np.array([not x_right, not y_up, x_right != y_up])  # two axes or none
    return np.where(flip, -points, points)


def _read_table(path: pathlib.Path) -> np.ndarray:
    rows = []
    for number, line in enumerate(path.read_text(encoding="utf-8-sig").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            rows.append([float(v) for v in re.split(r"[\s,;]+", line) if v])
        except ValueError:
            raise ValueError(f"scan: {path}, line {number}: not numbers: {line[:60]!r}") \
                from None
        if len(rows[-1]) not in (3, 6) or len(rows[-1]) != len(rows[0]):
            raise ValueError(f"scan: {path}, line {number}: {len(rows[-1])} numbers; expected "
                             "3 (x y z) or 6 (x y z nx ny nz) on every line")
    return np.array(rows, np.float64) if rows else np.zeros((0, 3))


def l2_error(
    normals_a: Float[ArrayLike, "H W 3"],
    normals_b: Float[ArrayLike, "H W 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
) -> Float[np.ndarray, "H W"]:
    """Per-pixel $\\ell_2$ norm of the difference of two unit-normal maps (0 outside `mask`).

    $\\lVert a - b \\rVert_2 = 2 \\sin(\\theta / 2)$ for unit vectors at angle $\\theta$.

    **Returns:** `(H, W)` in the floating dtype of `normals_a`.
    """
    a = np.asarray(normals_a)
    b = np.asarray(normals_b)
    if a.shape != b.shape or a.ndim != 3 or a.shape[-1] != 3:
        raise ValueError(
            f"normals_a and normals_b must both be (H, W, 3), got {a.shape} and {b.shape}")
    dtype = a.dtype if np.issubdtype(a.dtype, np.floating) else np.float32
    err = np.linalg.norm(a.astype(np.float64) - b.astype(np.float64), axis=-1)
    if mask is not None:
        if np.shape(mask) != a.shape[:2]:
            raise ValueError(f"mask must have shape {a.shape[:2]}, got {np.shape(mask)}")
        err = np.where(np.asarray(mask, bool), err, 0)
    return err.astype(dtype)


def compare_to_scan(
    height: Float[ArrayLike, "H W"],
    target: Float[ArrayLike, "M 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    normals: Float[ArrayLike, "H W 3"] | None = None,
    target_normals: Float[ArrayLike, "M 3"] | None = None,
    pixel_size: float = 1.0,
    scale: bool = True,
    **icp_options,
) -> ScanComparison:
    """Align a reconstructed height map to a scan with ICP and map the errors per pixel.

    **Arguments:**
    - `height`: `(H, W)` reconstructed height, toward the viewer (e.g. `jaxps.integrate`).
    - `target`: `(M, 3)` scan points in the camera frame, or in one whose axes are within a
      few degrees of it, in any unit (e.g. `points_from_depth`, or `read_scan` of a mesh).
    - `mask`: `(H, W)` bool, reconstructed pixels to compare (default: all finite).
    - `normals`: `(H, W, 3)` reconstructed normals for the angular and $\\ell_2$ maps (default:
      none, those maps stay 0).
    - `target_normals`: `(M, 3)` scan normals (default: `estimate_normals(target)`), e.g. a
      mesh's from `read_scan`; all are turned round if those paired with pixels face away
      from the camera on the whole (a mesh wound inside out).
    - `pixel_size`: the reconstruction's pixel size in its height unit.
    - `scale`: fit a global scale in ICP (default True).
    - `**icp_options`: passed to `icp` (default here: `init="centroid"`).

    **Returns:** a `ScanComparison` on the reconstruction's `(H, W)` grid.

    **Raises:** `ValueError` for bad shapes, or when ICP shrank the reconstruction onto a point
    of the scan (`icp`'s collapse, from a scan whose axes are not the camera's).
    """
    z = np.asarray(height)
    if z.ndim != 2:
        raise ValueError(f"height must be (H, W), got shape {z.shape}")
    dtype = z.dtype if np.issubdtype(z.dtype, np.floating) else np.float32
    src, pix = points_from_height(z, mask=mask, pixel_size=pixel_size)
    if src.shape[0] < 3:
        raise ValueError("mask leaves fewer than 3 reconstructed pixels to compare")
    tgt = np.asarray(target)
    if target_normals is None:
        tn = estimate_normals(tgt)
    else:
        tn = np.asarray(target_normals)
        if tn.shape != tgt.shape:
            raise ValueError(f"target_normals must have the shape of target {tgt.shape}, "
                             f"got {tn.shape}")
    icp_options.setdefault("init", "centroid")
    res = icp(src, tgt, scale=scale, target_normals=tn, **icp_options)
    matched = _spread_ratio(src, tgt)
    if scale and res.scale < _COLLAPSED * matched:
        raise ValueError(
            f"target: ICP shrank the reconstruction onto a point of the scan (scale "
            f"{res.scale:.3g}, where the two clouds' spreads give {matched:.3g}), "
            "so there is no alignment to compare: are the scan's axes the camera's (x right, y "
            "up, z toward the camera)? A mesh stored with z up needs turning first")

    from scipy.spatial import cKDTree

    _, idx = cKDTree(tgt).query(res.aligned.astype(np.float64))
    ref = tn[idx].astype(np.float64)
    ref /= np.maximum(np.linalg.norm(ref, axis=-1, keepdims=True), 1e-12)
    # The surface the camera sees faces it, so its normals do on the whole (the camera's axis
    # carried into the scan's frame by the ICP rotation). A mesh wound inside out has them
    # the other way round, which would read as 180-degree errors and flip the sign of the
    # height error: turn them all. (Not each on its own: at a silhouette, seen in
    # perspective or after an ICP tilt, a true normal may lean away from the axis.)
    if np.median(ref @ np.asarray(res.rotation, np.float64)[:, 2]) < 0:
        ref = -ref
    signed = np.sum((res.aligned.astype(np.float64) - tgt[idx]) * ref, axis=-1)

    h, w = z.shape
    sel = np.zeros((h, w), bool)
    r, c = pix[res.inliers, 0], pix[res.inliers, 1]
    sel[r, c] = True
    height_err = np.zeros((h, w))
    height_err[pix[:, 0], pix[:, 1]] = signed
    height_err[~sel] = 0
    ang = np.zeros((h, w))
    l2 = np.zeros((h, w))
    med = mean = mean_l2 = float("nan")
    if normals is not None:
        n = np.asarray(normals, np.float64)
        if n.shape != (h, w, 3):
            raise ValueError(f"normals must have shape {(h, w, 3)}, got {n.shape}")
        rot = np.asarray(res.rotation, np.float64)
        nr = n[pix[:, 0], pix[:, 1]] @ rot.T
        nr /= np.maximum(np.linalg.norm(nr, axis=-1, keepdims=True), 1e-12)
        cross = np.linalg.norm(np.cross(nr, ref), axis=-1)
        ang[pix[:, 0], pix[:, 1]] = np.degrees(np.arctan2(cross, np.sum(nr * ref, axis=-1)))
        l2[pix[:, 0], pix[:, 1]] = np.linalg.norm(nr - ref, axis=-1)
        ang[~sel] = 0
        l2[~sel] = 0
        med, mean, mean_l2 = (float(np.median(ang[sel])), float(np.mean(ang[sel])),
                              float(np.mean(l2[sel])))
    e = height_err[sel]
    return ScanComparison(
        height_error=height_err.astype(dtype),
        angular_error=ang.astype(dtype),
        l2_error=l2.astype(dtype),
        mask=sel,
        rms_height=float(np.sqrt(np.mean(e**2))),
        mean_abs_height=float(np.mean(np.abs(e))),
        median_angular=med,
        mean_angular=mean,
        mean_l2=mean_l2,
        icp=res,
    )
