"""A reconstruction as a trimesh mesh, and the mesh files `jaxps reconstruct` writes.

trimesh (not meshio) because meshio has no materials or texture coordinates: trimesh writes an
OBJ with its MTL and texture PNG, binary PLY with per-vertex colours and normals, and loads all
of them back. It is imported by the functions here only, so `import jaxps` stays light.
"""

from __future__ import annotations

import os

import numpy as np

from ..core._host import positive_scalar

__all__ = ["to_trimesh", "write_meshes", "write_ply"]


def _grid_mesh(height, mask, pixel_size):
    """Vertices `(V, 3)` (x right, y up, z = height), triangles `(F, 3)` and the `(V,)` rows and
    columns of the pixels they come from; each 2x2 block of valid pixels gives two triangles
    wound toward the viewer."""
    if not positive_scalar(pixel_size):
        raise ValueError(f"pixel_size must be positive and finite, got {pixel_size}")
    h, w = height.shape
    index = np.full((h, w), -1, np.int64)
    index[mask] = np.arange(mask.sum())
    rows, cols = np.nonzero(mask)
    verts = np.stack([cols * pixel_size, (h - 1 - rows) * pixel_size, height[mask]], axis=1)
    a, b = index[:-1, :-1], index[:-1, 1:]  # top-left, top-right
    c, d = index[1:, :-1], index[1:, 1:]  # bottom-left, bottom-right
    quads = (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)
    faces = np.concatenate([np.stack([a[quads], c[quads], b[quads]], 1),
                            np.stack([b[quads], c[quads], d[quads]], 1)])
    return verts.astype(np.float32), faces, rows, cols


def _albedo_rgb8(albedo, mask, *, inside_only=False):
    """`(H, W)` or `(H, W, 3)` linear albedo as `(H, W, 3)` uint8 sRGB (or, with `inside_only`,
    `(V, 3)` for the pixels of `mask` in row-major order), scaled so that the 99.5th percentile
    inside `mask` maps to 0.95 (as `albedo.png`). Grey albedo is encoded once, then repeated."""
    a = np.asarray(albedo, np.float32)
    grey = a.ndim == 2
    inside = a[mask]
    top = float(np.percentile(inside[inside > 0], 99.5)) if np.any(inside > 0) else 1.0
    a = inside if inside_only else a
    a = np.clip(np.nan_to_num(a) * np.float32(0.95 / top if top > 0 else 1.0), 0, 1)
    srgb = np.where(a <= 0.0031308, 12.92 * a, 1.055 * a ** np.float32(1 / 2.4) - 0.055)
    rgb = np.round(srgb * 255).astype(np.uint8)
    return np.repeat(rgb[..., None], 3, axis=-1) if grey else rgb


def to_trimesh(height, mask, albedo=None, normals=None, *, pixel_size: float = 1.0):
    """A reconstruction as a `trimesh.Trimesh`, one vertex per valid pixel.

    **Arguments:**
    - `height`: `(H, W)` height in pixels (z toward the viewer); non-finite pixels are left out.
    - `mask`: `(H, W)` bool, the pixels to mesh.
    - `albedo`: `(H, W)` grey or `(H, W, 3)` colour, linear; when given, the mesh is textured
      with it (`mesh.visual` is `TextureVisuals`, image `(H, W, 3)` uint8 sRGB, scaled so the
      99.5th percentile is 0.95) and the UV of the vertex of pixel (row r, column c) is
      `((c + 0.5) / W, 1 - (r + 0.5) / H)`. `mesh.visual.to_color()` gives vertex colours.
    - `normals`: `(H, W, 3)` unit normals (x right, y up, z to the viewer), stored as vertex
      normals; default: trimesh computes them from the faces.
    - `pixel_size`: x and y units per pixel.

    **Returns:** `trimesh.Trimesh` with vertices `(V, 3)` at `(c, H - 1 - r, height)` times
    `pixel_size` (z unscaled) and faces `(F, 3)`: two triangles per 2x2 block of valid pixels.
    """
    import trimesh

    height = np.asarray(height, np.float64)
    if height.ndim != 2:
        raise ValueError(f"height must be (H, W), got shape {height.shape}")
    mask = np.asarray(mask, bool)
    if mask.shape != height.shape:
        raise ValueError(f"mask must have the shape of height {height.shape}, got {mask.shape}")
    mask = mask & np.isfinite(height)
    if not mask.any():
        raise ValueError("mask has no pixel with a finite height: nothing to mesh")
    verts, faces, rows, cols = _grid_mesh(height, mask, pixel_size)
    h, w = height.shape
    kwargs = {}
    if normals is not None:
        normals = np.asarray(normals, np.float64)
        if normals.shape != (h, w, 3):
            raise ValueError(f"normals must be {(h, w, 3)}, got shape {normals.shape}")
        kwargs["vertex_normals"] = normals[mask]
    if albedo is not None:
        albedo = np.asarray(albedo)
        if albedo.shape[:2] != (h, w) or albedo.ndim not in (2, 3):
            raise ValueError(f"albedo must be (H, W) or (H, W, 3) with (H, W) = {(h, w)}, "
                             f"got shape {albedo.shape}")
        from PIL import Image

        image = Image.fromarray(_albedo_rgb8(albedo, mask))
        uv = np.stack([(cols + 0.5) / w, 1 - (rows + 0.5) / h], axis=1)
        material = trimesh.visual.material.SimpleMaterial(
            image=image, name="texture", diffuse=(255, 255, 255, 255),
            ambient=(255, 255, 255, 255), specular=(0, 0, 0, 255))
        kwargs["visual"] = trimesh.visual.TextureVisuals(uv=uv, material=material)
    return trimesh.Trimesh(verts, faces, process=False, **kwargs)


def write_ply(path, height: np.ndarray, mask: np.ndarray, *, albedo: np.ndarray | None = None,
              pixel_size: float = 1.0) -> int:
    """Write the masked height map as a binary PLY triangle mesh; returns the face count.

    Vertices are (x, y, z) in the camera frame (x right, y up, pixel units times
    `pixel_size`), one per valid pixel; each 2x2 block of valid pixels gives two triangles,
    wound toward the viewer (the mesh of `to_trimesh`). With `albedo` (`(H, W)` or
    `(H, W, 3)`), each vertex carries its pixel's colour (8-bit sRGB, scaled as `albedo.png`).

    Written with numpy rather than trimesh (which `write_meshes` uses for the OBJ and the point
    cloud): for a 1280x1024 face trimesh took 0.6-1.2 s, this takes a small fraction of it, and
    `jaxps reconstruct` writes it on every run. Loads in trimesh, MeshLab and Blender.
    """
    mask = np.asarray(mask, bool) & np.isfinite(height)
    verts, faces, _, _ = _grid_mesh(np.asarray(height), mask, pixel_size)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if albedo is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertex = np.empty(len(verts), dtype=fields)
    vertex["x"], vertex["y"], vertex["z"] = verts.T
    if albedo is not None:  # vertices are the mask's pixels in row-major order
        rgb = _albedo_rgb8(albedo, mask, inside_only=True)
        vertex["red"], vertex["green"], vertex["blue"] = rgb.T
    face = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face["n"], face["v"] = 3, faces
    props = "".join(f"property {'float' if t == '<f4' else 'uchar'} {n}\n" for n, t in fields)
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vertex)}\n{props}"
              f"element face {len(face)}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(vertex.tobytes())
        f.write(face.tobytes())
    return len(face)


def write_meshes(out, height, mask, albedo, normals, *, pixel_size: float = 1.0,
                 obj: bool = True, points: bool = True) -> dict:
    """Write the mesh files of a run into the folder `out`:

    - `mesh.ply`: binary PLY with per-vertex colours from the albedo;
    - with `obj`: `mesh.obj` with `mesh.mtl` and the albedo texture `texture.png` (UVs from
      pixel positions). A text format: at 1280x1024 it takes trimesh about 7 s and 200 MB, so
      `jaxps reconstruct` writes it only when asked (`--obj`);
    - with `points`: `points.ply`, a binary PLY point cloud, one point per valid pixel with its
      normal.

    Arguments as `to_trimesh`. **Returns:** `{"vertices": V, "faces": F}`.
    """
    mask = np.asarray(mask, bool) & np.isfinite(np.asarray(height))
    faces = write_ply(os.path.join(out, "mesh.ply"), height, mask, albedo=albedo,
                      pixel_size=pixel_size)
    if obj or points:
        import trimesh

        mesh = to_trimesh(height, mask, albedo, normals, pixel_size=pixel_size)
    if obj:
        mesh.export(os.path.join(out, "mesh.obj"), mtl_name="mesh.mtl")
    if points:
        cloud = trimesh.Trimesh(mesh.vertices, np.zeros((0, 3), np.int64), process=False,
                                vertex_normals=mesh.vertex_normals)
        with open(os.path.join(out, "points.ply"), "wb") as f:
            f.write(trimesh.exchange.ply.export_ply(cloud, encoding="binary",
                                                    vertex_normal=True))
    return {"vertices": int(mask.sum()), "faces": faces}
