"""Meshes of a reconstruction (`jaxps.report.to_trimesh` and the files `jaxps reconstruct`
writes), loaded back with trimesh."""

import numpy as np
import pytest

from jaxps.report import to_trimesh
from jaxps.report._mesh import write_meshes

trimesh = pytest.importorskip("trimesh")


@pytest.fixture
def recon():
    h, w = 3, 4
    height = np.arange(12, dtype=np.float32).reshape(h, w)
    mask = np.ones((h, w), bool)
    mask[0, 0] = False  # 11 vertices; 5 of the six 2x2 blocks are complete: 10 triangles
    albedo = np.zeros((h, w, 3), np.float32)
    albedo[..., 0] = np.linspace(0.1, 0.9, w)[None]  # red grows to the right
    albedo[..., 2] = 0.5
    normals = np.zeros((h, w, 3), np.float32)
    normals[..., 0], normals[..., 2] = 0.6, 0.8
    return height, mask, albedo, normals


def test_to_trimesh_vertices_faces_uvs(recon):
    height, mask, albedo, normals = recon
    mesh = to_trimesh(height, mask, albedo, normals, pixel_size=2.0)
    assert mesh.vertices.shape == (11, 3) and mesh.faces.shape == (10, 3)
    # first vertex: pixel (row 0, column 1) at x = 1 * 2, y = (3 - 1 - 0) * 2, z = height
    np.testing.assert_allclose(mesh.vertices[0], [2.0, 4.0, 1.0])
    np.testing.assert_allclose(mesh.visual.uv[0], [1.5 / 4, 1 - 0.5 / 3])
    np.testing.assert_allclose(mesh.vertex_normals, np.tile([0.6, 0.0, 0.8], (11, 1)), atol=1e-6)
    assert mesh.visual.material.image.size == (4, 3)
    # every face points toward the viewer (+z) on this slanted plane
    assert np.all(mesh.face_normals[:, 2] > 0)


def test_to_trimesh_rejects_bad_shapes(recon):
    height, mask, albedo, normals = recon
    with pytest.raises(ValueError, match="mask"):
        to_trimesh(height, mask[:2])
    with pytest.raises(ValueError, match="albedo"):
        to_trimesh(height, mask, albedo[:2])
    with pytest.raises(ValueError, match="normals"):
        to_trimesh(height, mask, normals=normals[..., :2])
    with pytest.raises(ValueError, match="mask"):
        to_trimesh(height, np.zeros_like(mask))
    for bad in (0.0, -0.5, float("inf")):  # a flat or mirrored mesh before
        with pytest.raises(ValueError, match="pixel_size must be positive and finite"):
            to_trimesh(height, mask, pixel_size=bad)


def test_written_files_load_back(recon, tmp_path):
    height, mask, albedo, normals = recon
    assert write_meshes(tmp_path, height, mask, albedo, normals) == {"vertices": 11, "faces": 10}

    obj = trimesh.load(tmp_path / "mesh.obj", process=False)
    assert obj.vertices.shape == (11, 3) and obj.faces.shape == (10, 3)
    assert obj.visual.uv.shape == (11, 2)
    np.testing.assert_allclose(obj.visual.uv[0], [1.5 / 4, 1 - 0.5 / 3], atol=1e-6)
    assert obj.visual.material.image.size == (4, 3)
    mtl = (tmp_path / "mesh.mtl").read_text()
    assert "map_Kd texture.png" in mtl and (tmp_path / "texture.png").is_file()
    assert "mtllib mesh.mtl" in (tmp_path / "mesh.obj").read_text()

    ply = trimesh.load(tmp_path / "mesh.ply", process=False)
    assert (tmp_path / "mesh.ply").read_bytes().startswith(b"ply\nformat binary_little_endian")
    assert ply.vertices.shape == (11, 3) and ply.faces.shape == (10, 3)
    colours = ply.visual.vertex_colors
    assert colours.shape == (11, 4)
    # vertex 0 is pixel (0, 1), vertex 2 pixel (0, 3): redder to the right, blue constant
    assert colours[2, 0] > colours[0, 0] and colours[0, 2] == colours[2, 2] > 0

    points = trimesh.load(tmp_path / "points.ply", process=False)
    assert len(points.vertices) == 11
    raw = points.metadata["_ply_raw"]["vertex"]["data"]
    np.testing.assert_allclose(np.stack([raw["nx"], raw["ny"], raw["nz"]], -1),
                               np.tile([0.6, 0.0, 0.8], (11, 1)), atol=1e-6)
