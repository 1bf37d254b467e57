"""ICP alignment and scan error maps (jaxps.evaluate)."""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaxps
from jaxps import evaluate as ev
from jaxps.evaluate._icp import _step_point_to_point


def _misalign(points, angles_deg, shift, scale=1.0):
    """Rotate about the centroid, scale and shift: returns moved points and the true inverse."""
    r0 = Rotation.from_euler("xyz", angles_deg, degrees=True).as_matrix()
    c = points.mean(axis=0)
    moved = scale * (points.astype(np.float64) - c) @ r0.T + c + np.asarray(shift)
    return moved.astype(points.dtype), r0


def _rotation_error_deg(r_est, r0):
    return float(np.degrees(Rotation.from_matrix(np.asarray(r_est, np.float64) @ r0).magnitude()))


@pytest.fixture(scope="module")
def face_points():
    surf = jaxps.synthetic.face_like(64)
    pts, _ = ev.points_from_height(np.asarray(surf.height), mask=np.asarray(surf.mask))
    return pts


def test_umeyama_step_matches_numpy_svd():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(200, 3)).astype(np.float32)
    r0 = Rotation.from_euler("xyz", [20, -10, 35], degrees=True).as_matrix()
    q = (1.7 * p.astype(np.float64) @ r0.T + [1.0, -2.0, 0.5]).astype(np.float32)
    w = np.ones(200, np.float32)
    s, r, t = _step_point_to_point(p, q, w, with_scale=True)
    # numpy reference (Umeyama 1991, eqs. 38-42)
    mp, mq = p.mean(0), q.mean(0)
    u, sv, vt = np.linalg.svd((q - mq).T @ (p - mp) / len(p))
    d = np.diag([1, 1, np.sign(np.linalg.det(u) * np.linalg.det(vt))])
    r_ref = u @ d @ vt
    s_ref = np.trace(np.diag(sv) @ d) / np.mean(np.sum((p - mp) ** 2, -1))
    np.testing.assert_allclose(np.asarray(r), r_ref, atol=1e-5)
    np.testing.assert_allclose(float(s), s_ref, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(r), r0, atol=1e-5)
    np.testing.assert_allclose(float(s), 1.7, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(t), mq - s_ref * r_ref @ mp, atol=1e-4)


def test_point_to_plane_undoes_rigid_misalignment_on_synthetic_face(face_points):
    src, r0 = _misalign(face_points, [3.0, -4.0, 5.0], [2.0, -3.0, 4.0])
    res = ev.icp(src, face_points, method="point_to_plane", max_steps=100)
    assert res.converged and res.steps < 100
    assert _rotation_error_deg(res.rotation, r0) < 0.01
    np.testing.assert_allclose(res.aligned, face_points, atol=0.01)
    assert res.rms < 0.01
    assert res.scale == 1.0


def test_point_to_point_reduces_misalignment_on_synthetic_face(face_points):
    # Point-to-point ICP on a regular pixel grid locks onto a nearby grid match (measured:
    # 2.2 deg from three different starts); it must still remove most of the misalignment.
    src, r0 = _misalign(face_points, [3.0, -4.0, 5.0], [2.0, -3.0, 4.0])
    start = np.sqrt(np.mean(np.sum((src - face_points) ** 2, axis=-1)))
    res = ev.icp(src, face_points, method="point_to_point", max_steps=200)
    end = np.sqrt(np.mean(np.sum((res.aligned - face_points) ** 2, axis=-1)))
    assert res.converged
    assert end < start / 4
    assert _rotation_error_deg(res.rotation, r0) < 3.0


def test_icp_recovers_scale(face_points):
    src, r0 = _misalign(face_points, [2.0, 3.0, -2.0], [1.0, 1.0, -2.0], scale=0.4)
    res = ev.icp(src, face_points, scale=True, init="centroid", max_steps=100, tol=1e-7)
    assert res.converged
    np.testing.assert_allclose(res.scale, 1 / 0.4, rtol=1e-3)
    assert _rotation_error_deg(res.rotation, r0) < 0.05
    np.testing.assert_allclose(res.aligned, face_points, atol=0.05)


def test_icp_step_limit_reports_not_converged(face_points):
    src, _ = _misalign(face_points, [3.0, -4.0, 5.0], [2.0, -3.0, 4.0])
    res = ev.icp(src, face_points, method="point_to_point", max_steps=1)
    assert res.steps == 1 and not res.converged
    assert np.all(np.isfinite(res.aligned))


def test_trimmed_icp_ignores_outliers(face_points):
    src, r0 = _misalign(face_points, [2.0, 2.0, 4.0], [1.0, 2.0, 0.0])
    rng = np.random.default_rng(1)
    junk = (src[: len(src) // 10] + rng.normal(0, 30, (len(src) // 10, 3))).astype(src.dtype)
    noisy = np.concatenate([src, junk])
    plain = ev.icp(noisy, face_points, max_steps=100)
    trimmed = ev.icp(noisy, face_points, max_steps=100, trim=0.85)
    assert _rotation_error_deg(trimmed.rotation, r0) < 0.05
    assert _rotation_error_deg(plain.rotation, r0) > _rotation_error_deg(trimmed.rotation, r0)
    assert trimmed.inliers[: len(src)].mean() > 0.9


def test_icp_keeps_dtype_and_transform_points(face_points):
    src, _ = _misalign(face_points.astype(np.float64), [1.0, 0.0, 2.0], [0.5, 0.0, 0.0])
    res = ev.icp(src, face_points, max_steps=30)
    assert res.aligned.dtype == np.float64 and res.rotation.dtype == np.float64
    np.testing.assert_allclose(ev.transform_points(src, res), res.aligned, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(res.rotation), 1.0, atol=1e-6)


def test_icp_rejects_bad_input(face_points):
    with pytest.raises(ValueError, match="source"):
        ev.icp(face_points[:, :2], face_points)
    with pytest.raises(ValueError, match="method"):
        ev.icp(face_points, face_points, method="nope")
    with pytest.raises(ValueError, match="trim"):
        ev.icp(face_points, face_points, trim=0)
    with pytest.raises(ValueError, match="max_steps"):
        ev.icp(face_points, face_points, max_steps=0)
    bad = face_points.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="target"):
        ev.icp(face_points, bad)
    line = np.zeros((20, 3))
    line[:, 0] = np.arange(20.0)
    for source, target in ((line, face_points), (face_points, np.ones((20, 3)))):
        with pytest.raises(ValueError, match="lie on one line"):  # scipy's error from NaNs
            ev.icp(source, target)
    for neighbours in (0, 2, 4.5):  # silently taken as 3 (or 4) before
        with pytest.raises(ValueError, match="neighbours must be an int >= 3"):
            ev.estimate_normals(face_points, neighbours=neighbours)


def test_points_from_depth_back_projects_like_pinhole():
    k = np.array([[100.0, 0, 3.0], [0, 200.0, 2.0], [0, 0, 1]])
    depth = np.full((4, 6), np.nan, np.float32)
    depth[1, 5] = 50.0
    pts, pix = ev.points_from_depth(depth, k)
    assert pix.tolist() == [[1, 5]]
    np.testing.assert_allclose(pts[0], [(5 - 3) * 50 / 100, -(1 - 2) * 50 / 200, -50], rtol=1e-6)
    with pytest.raises(ValueError, match="intrinsics"):
        ev.points_from_depth(depth, np.eye(2))


def test_l2_error_is_chord_of_angular_error():
    surf = jaxps.synthetic.sphere(32)
    n = np.asarray(surf.normals)
    r = Rotation.from_euler("y", 7, degrees=True).as_matrix().astype(np.float32)
    m = n @ r.T
    l2 = ev.l2_error(n, m, mask=np.asarray(surf.mask))
    ang = np.asarray(ev.angular_error(n, m, mask=np.asarray(surf.mask)))
    np.testing.assert_allclose(l2, 2 * np.sin(np.radians(ang) / 2), atol=1e-5)
    assert l2.dtype == np.float32


def _load_gt(data, obj, step):
    root = data / "diligent_gt" / obj
    depth = np.load(root / "depth_gt.npz")["depth_gt"]
    mask = (cv2.imread(str(root / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0) & np.isfinite(depth)
    k = np.loadtxt(root / "K.txt")
    raw = cv2.imread(str(root / "normal_map.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    assert raw.dtype == np.uint16
    normals = raw.astype(np.float32) / 65535 * 2 - 1
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    # Disjoint samplings of the same scan, as two scanners would give.
    src_mask, tgt_mask = mask.copy(), mask.copy()
    src_mask[:, ::step] = False
    src_mask[::step] = False
    tgt_mask[1::step] = False
    return depth, mask, k, normals, src_mask, tgt_mask


@pytest.mark.parametrize("obj", ["bear", "cat", "pot1", "reading"])
def test_icp_undoes_known_misalignment_on_diligent(data, obj):
    depth, _, k, _, src_mask, tgt_mask = _load_gt(data, obj, step=3)
    src, _ = ev.points_from_depth(depth, k, mask=src_mask)
    tgt, _ = ev.points_from_depth(depth, k, mask=tgt_mask)
    moved, r0 = _misalign(src, [3.0, -4.0, 5.0], [5.0, -8.0, 10.0])  # mm
    res = ev.icp(moved, tgt, method="point_to_plane", max_steps=50)
    assert _rotation_error_deg(res.rotation, r0) < 0.1
    assert np.max(np.linalg.norm(res.aligned.astype(np.float64) - src, axis=-1)) < 0.2  # mm


def test_compare_to_scan_on_diligent_depth(data, tmp_path):
    # The scan's own depth, seen orthographically in "pixels": ICP must find the pixel size
    # (~0.4 mm) and leave only the perspective/orthographic difference.
    depth, mask, k, normals, src_mask, tgt_mask = _load_gt(data, "bear", step=2)
    tgt, pix = ev.points_from_depth(depth, k, mask=tgt_mask)
    pixel_mm = float(np.median(depth[mask])) / k[0, 0]
    height = np.where(src_mask, -depth / pixel_mm, 0).astype(np.float32)  # pixel units
    comp = ev.compare_to_scan(height, tgt, mask=src_mask, normals=normals,
                              target_normals=normals[pix[:, 0], pix[:, 1]], trim=0.98)
    np.testing.assert_allclose(comp.icp.scale, pixel_mm, rtol=0.03)
    assert comp.rms_height < 0.5  # mm
    assert comp.median_angular < 2.0
    assert comp.mask.sum() > 0.95 * src_mask.sum()
    assert not np.any(comp.mask & ~src_mask)
    assert np.all(np.isfinite(comp.height_error))
    out = tmp_path / "err.png"
    ev.plot_error_maps({"height": comp.height_error, "angle": comp.angular_error},
                       mask=comp.mask, signed=("height",), units={"height": "mm"}, path=out)
    img = cv2.imread(str(out))
    assert img is not None and img.shape[0] > 100 and img.std() > 10


def test_jaxtyping_annotations_hold(face_points, tmp_path):
    from beartype import beartype
    from jaxtyping import jaxtyped

    surf = jaxps.synthetic.face_like(32)
    height, mask = np.asarray(surf.height), np.asarray(surf.mask)
    checked = {f.__name__: jaxtyped(typechecker=beartype)(f) for f in (
        ev.points_from_height, ev.points_from_depth, ev.icp, ev.estimate_normals,
        ev.l2_error, ev.compare_to_scan, ev.transform_points, ev.read_scan)}
    pts, pix = checked["points_from_height"](height, mask=mask)
    k = np.array([[100.0, 0, 16], [0, 100.0, 16], [0, 0, 1]])
    checked["points_from_depth"](np.where(mask, 50.0 - height, np.nan), k, mask=mask)
    res = checked["icp"](pts + np.float32(0.5), pts, max_steps=5)
    checked["transform_points"](pts, res)
    checked["estimate_normals"](pts)
    checked["l2_error"](np.asarray(surf.normals), np.asarray(surf.normals), mask=mask)
    comp = checked["compare_to_scan"](height, pts, mask=mask, normals=np.asarray(surf.normals),
                                      scale=False, max_steps=5)
    assert comp.rms_height < 1e-3
    jaxps.report.to_trimesh(height, mask).export(tmp_path / "scan.ply")
    points, normals = checked["read_scan"](tmp_path / "scan.ply")
    assert points.shape == normals.shape


def test_plot_error_maps_names_maps_of_another_shape():
    a = np.zeros((6, 5))
    with pytest.raises(ValueError, match=r"maps must share one \(H, W\) shape"):
        ev.plot_error_maps({"a": a, "b": a[:-1]})  # drawn side by side, silently, before
    with pytest.raises(ValueError, match=r"mask must have the maps' shape \(6, 5\)"):
        ev.plot_error_maps({"a": a}, mask=np.ones((5, 5), bool))  # numpy's broadcast error
    with pytest.raises(ValueError, match=r"map 'a' must be \(H, W\)"):
        ev.plot_error_maps({"a": a[0]})


@pytest.fixture(scope="module")
def face_scan():
    """A synthetic face, its truth, and the same surface as a mesh in another unit and pose:
    0.6 units per pixel, turned 4 degrees about y and moved, as a scanner would hand it over."""
    surf = jaxps.synthetic.face_like(64)
    height, mask = np.asarray(surf.height), np.asarray(surf.mask)
    mesh = jaxps.report.to_trimesh(height, mask)
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("y", 4, degrees=True).as_matrix()
    turn[:3, 3] = [5.0, -3.0, 400.0]
    mesh.apply_scale(0.6)
    mesh.apply_transform(turn)
    return height, mask, np.asarray(surf.normals), mesh


@pytest.mark.parametrize("name", ["face.ply", "face.obj", "face.stl", "face.off",
                                  "inside_out.ply", "points.xyz", "points_normals.csv",
                                  "points.npy"])
def test_read_scan_compares_a_mesh_in_its_own_unit_and_pose(face_scan, tmp_path, name):
    height, mask, normals, mesh = face_scan
    path = tmp_path / name
    if name.startswith("face"):
        mesh.export(path)
    elif name == "inside_out.ply":  # faces wound the other way: normals point into the head
        flipped = mesh.copy()
        flipped.invert()
        flipped.export(path)
    elif name == "points.xyz":
        np.savetxt(path, mesh.vertices, header="x y z")
    elif name == "points_normals.csv":
        np.savetxt(path, np.c_[mesh.vertices, mesh.vertex_normals], delimiter=",")
    else:
        np.save(path, mesh.vertices)
    points, scan_normals = ev.read_scan(path)
    assert points.shape == mesh.vertices.shape and points.dtype == np.float64
    np.testing.assert_allclose(np.sort(points, axis=0), np.sort(mesh.vertices, axis=0),
                               atol=1e-4)  # STL and PLY store float32
    assert (scan_normals is None) == (name in ("points.xyz", "points.npy"))
    comp = ev.compare_to_scan(height, points, mask=mask, normals=normals,
                              target_normals=scan_normals, trim=0.95)
    np.testing.assert_allclose(comp.icp.scale, 0.6, rtol=1e-3)
    assert comp.rms_height < 1e-3  # scan units
    # The mesh's own normals are closer to the truth than normals estimated from its points,
    # also when its faces are wound inside out: they are turned round, where they would read
    # as 180 degrees off.
    assert comp.median_angular < (0.5 if scan_normals is not None else 1.2)
    assert comp.median_angular > 0.05  # a faceted mesh is not the smooth truth


def _write_abs(path, xyz, flags, rows=1):
    """An FRGC range image: `rows` rows of the pixels, each a flag and X Y Z."""
    import gzip

    lines = [f"{rows} rows", f"{len(flags) // rows} columns", "pixels (flag X Y Z):",
             " ".join(str(int(f)) for f in flags)]
    lines += [" ".join(f"{v:.6f}" for v in xyz[:, i]) for i in range(3)]
    text = "\n".join(lines) + "\n"
    if path.suffix == ".gz":
        with gzip.open(path, "wt") as f:
            f.write(text)
    else:
        path.write_text(text)


@pytest.mark.parametrize(("name", "axes"), [
    ("camera_frame.abs", (1, 1, 1)),  # x right, y up, z toward the camera
    ("y_down.abs.gz", (1, -1, -1)),  # OpenCV's: y down the rows, z forward; gzipped
    ("x_left.abs", (-1, 1, -1)),
    ("both.abs", (-1, -1, 1)),
])
def test_read_scan_turns_a_range_image_into_the_camera_frame(face_scan, tmp_path, name, axes):
    # An FRGC-style range image of the synthetic face, 0.25 mm a pixel at 1000 mm, its pixels
    # outside the face flagged 0, written in a scanner frame whose axes run other ways: read
    # back, it is the camera-frame scan, whatever the scanner's axes.
    height, mask, normals, _ = face_scan
    h, w = height.shape
    k = np.array([[4000.0, 0, (w - 1) / 2], [0, 4000.0, (h - 1) / 2], [0, 0, 1]])
    points, pixels = ev.points_from_depth(np.where(mask, 1000.0 - 0.25 * height, np.nan), k)
    index = pixels[:, 0] * w + pixels[:, 1]
    grid = np.full((h * w, 3), -999999.0)
    grid[index] = points * np.array(axes)
    _write_abs(tmp_path / name, grid, np.isin(np.arange(h * w), index), rows=h)
    read, scan_normals = ev.read_scan(tmp_path / name)
    assert scan_normals is None
    np.testing.assert_allclose(read, points, atol=1e-4)  # the file holds 6 decimals
    comp = ev.compare_to_scan(height, read, mask=mask, normals=normals, trim=0.95)
    np.testing.assert_allclose(comp.icp.scale, 0.25, rtol=0.01)
    assert comp.rms_height < 0.01  # mm


_BAD_SCANS = [  # file name, contents (None: no file), error, message
    ("missing.ply", None, FileNotFoundError, "no such file"),
    ("scan.vtk", "# vtk DataFile\n", ValueError, r"scan.vtk is not a scan format.*\.ply"),
    ("four.txt", "0 0 0 1\n1 0 0 1\n0 1 0 1\n", ValueError,
     r"four.txt, line 1: 4 numbers; expected 3"),
    ("ragged.txt", "0 0 0\n1 0 0 0 0 1\n0 1 0\n", ValueError, r"ragged.txt, line 2: 6 numbers"),
    ("words.csv", "x,y,z\n0,0,0\n", ValueError, r"words.csv, line 1: not numbers: 'x,y,z'"),
    ("two.xyz", "0 0 0\n1 0 0\n", ValueError, "two.xyz has 2 points; ICP needs at least 3"),
    ("nan.npy", np.array([[0, 0, 0], [1, 0, np.nan], [0, 1, 0.0]]), ValueError,
     "nan.npy has NaN/Inf coordinates"),
    ("flat.npy", np.zeros((5, 4)), ValueError, r"shape \(5, 4\); expected \(M, 3\)"),
    ("broken.ply", b"ply\nformat binary_little_endian 1.0\nelement", ValueError,
     "cannot read .*broken.ply"),
    ("headless.abs", "1 0 0 1\n", ValueError, r"does not start as a range image does"),
    ("short.abs", "2 rows\n2 columns\npixels (flag X Y Z):\n1 1 1 1\n0 1 0 1\n",
     ValueError, r"short.abs holds 8 values; 2 rows x 2 columns need 16"),
]


@pytest.mark.parametrize(("name", "contents", "error", "message"), _BAD_SCANS,
                         ids=[row[0] for row in _BAD_SCANS])
def test_read_scan_names_what_it_cannot_read(tmp_path, name, contents, error, message):
    path = tmp_path / name
    if isinstance(contents, str):
        path.write_text(contents)
    elif isinstance(contents, bytes):
        path.write_bytes(contents)
    elif contents is not None:
        np.save(path, contents)
    with pytest.raises(error, match=message):
        ev.read_scan(path)


def test_compare_to_a_whole_head_scan():
    # A closed scan (an ellipsoidal head of 160 x 220 x 180 mm, back and all, turned 3 degrees
    # and moved) against a height map of its front (1 mm a pixel): ICP starts from the
    # centroids, deep inside the head, and still finds the front.
    trimesh = pytest.importorskip("trimesh")
    a, b, c = 80.0, 110.0, 90.0
    y, x = np.mgrid[69.5:-70:-1, -49.5:50:1]
    inside = 1 - (x / a) ** 2 - (y / b) ** 2
    height = (c * np.sqrt(np.clip(inside, 0, None))).astype(np.float32)
    normals = np.stack([x / a**2, y / b**2, height / c**2], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    head = trimesh.creation.icosphere(subdivisions=5)
    head.apply_scale([a, b, c])
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("x", 3, degrees=True).as_matrix()
    turn[:3, 3] = [4.0, -7.0, 300.0]
    head.apply_transform(turn)
    for face in (inside > 0.2, inside > 0.7):
        comp = ev.compare_to_scan(height, head.vertices, mask=face, normals=normals,
                                  target_normals=head.vertex_normals, trim=0.95)
        assert comp.icp.converged
        np.testing.assert_allclose(comp.icp.scale, 1.0, rtol=1e-3)
        assert comp.rms_height < 0.02  # mm; the mesh's facets are about 3 mm across
        assert comp.median_angular < 1.0


def test_read_scan_reads_what_jaxps_reconstruct_writes(face_scan, tmp_path):
    # mesh.ply (faces, vertex colours) and points.ply (a cloud with the run's normals) of a
    # run read back as its points, so that one run can be compared with another.
    from jaxps.report._mesh import write_meshes

    height, mask, normals, _ = face_scan
    write_meshes(tmp_path, height, mask, np.full(mask.shape, 0.5), normals, obj=False)
    mesh_points, mesh_normals = ev.read_scan(tmp_path / "mesh.ply")
    cloud_points, cloud_normals = ev.read_scan(tmp_path / "points.ply")
    assert mesh_points.shape == cloud_points.shape == (mask.sum(), 3)
    np.testing.assert_allclose(np.sort(mesh_points, axis=0), np.sort(cloud_points, axis=0),
                               atol=1e-4)
    np.testing.assert_allclose(cloud_normals, normals[mask], atol=1e-5)  # row-major order
    assert np.median(np.sum(mesh_normals * normals[mask], axis=-1)) > 0.999


@pytest.mark.parametrize("turn", [("x", 90), ("y", 180), ("z", 90)])
def test_compare_to_scan_names_a_scan_whose_axes_are_turned(face_scan, turn):
    # A scan stored with other axes (z up, say): scaled ICP shrinks the reconstruction onto a
    # point of it, which it then "fits" to round-off. Before, that came back with a scale near
    # 0 (negative, or "converged") and height errors near 0, or stopped in SciPy's "'x' must
    # be finite"; now ICP stops there and the comparison says what is wrong.
    height, mask, normals, mesh = face_scan
    scan = mesh.vertices @ Rotation.from_euler(*turn, degrees=True).as_matrix().T
    with pytest.raises(ValueError, match=r"shrank the reconstruction onto a point.*z up"):
        ev.compare_to_scan(height, scan, mask=mask, normals=normals, trim=0.95)
    points, _ = ev.points_from_height(height, mask=mask)
    res = ev.icp(points, scan, scale=True, init="centroid", trim=0.95)
    assert not res.converged and 0 < res.scale < 0.01 * 0.6
    # Turned by less, the same scan is found: ICP's basin is wide enough for a tilted scanner.
    tilted = mesh.vertices @ Rotation.from_euler("x", 30, degrees=True).as_matrix().T
    comp = ev.compare_to_scan(height, tilted, mask=mask, normals=normals, trim=0.95)
    assert comp.icp.converged and comp.rms_height < 1e-3
