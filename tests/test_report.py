"""The HTML run report (`jaxps report`) and the Lambertian check plot."""

import html.parser
import json
import pathlib

import cv2
import jax
import numpy as np
import pytest

import jaxps
from jaxps import report
from jaxps.report._writers import write_normal_map
from jaxps.cli import main


class _Images(html.parser.HTMLParser):
    def __init__(self):
        super().__init__()
        self.srcs, self.h2 = [], []
        self._in_h2 = False

    def handle_starttag(self, tag, attrs):
        if tag == "img":
            self.srcs.append(dict(attrs)["src"])
        self._in_h2 = tag == "h2"

    def handle_data(self, data):
        if self._in_h2:
            self.h2.append(data)
            self._in_h2 = False


def _parse(path: pathlib.Path) -> _Images:
    p = _Images()
    p.feed(path.read_text())
    return p


def _assert_images_resolve(page: pathlib.Path, srcs):
    assert srcs
    for src in srcs:
        assert not src.startswith(("/", "file:", "http")), src  # relative links only
        img = cv2.imread(str(page.parent / src), cv2.IMREAD_UNCHANGED)
        assert img is not None, f"broken image {src}"
        assert img.shape[0] >= 32 and img.std() > 0, f"empty image {src}"


@pytest.fixture(scope="module")
def synthetic_run(tmp_path_factory):
    """A `jaxps reconstruct --report` run on a small synthetic capture with known truth."""
    root = tmp_path_factory.mktemp("run")
    surface = jaxps.synthetic.face_like(64)
    lights = jaxps.synthetic.scanner_lights(20.0)
    scene = jaxps.synthetic.render_scene(surface, lights, noise=0.003, key=jax.random.key(0))
    frames = []
    for k, img in enumerate(np.asarray(scene.images)):
        path = root / f"frame_{k}.png"
        cv2.imwrite(str(path), np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16))
        frames.append(str(path))
    np.savetxt(root / "lights.txt", lights, header=str(len(lights)), comments="")
    cv2.imwrite(str(root / "mask.png"), np.asarray(scene.mask).astype(np.uint8) * 255)
    out = root / "out"
    rc = main(["reconstruct", *frames, "--lights", str(root / "lights.txt"), "--mask",
               str(root / "mask.png"), "--out", str(out), "--report"])
    assert rc == 0
    return root, out, scene


def test_reconstruct_report_page_has_every_section(synthetic_run):
    _, out, _ = synthetic_run
    page = out / "report.html"
    parsed = _parse(page)
    _assert_images_resolve(page, parsed.srcs)
    assert {"Reconstruction", "Lambertian check", "Timings (s)"} <= set(parsed.h2)
    assert (out / "lambertian_check.png").is_file()
    assert any(src.endswith("mesh_view.png") for src in parsed.srcs)  # the textured mesh
    text = page.read_text()
    assert "photometric stereo" in text  # a timing row from summary.json


def test_lambertian_check_is_near_zero_on_lambertian_scene(synthetic_run):
    _, out, scene = synthetic_run
    check = json.loads((out / "summary.json").read_text())["lambertian_check"]
    # Rendered with Lambert's law and noise 0.003 on albedo ~0.65: I/rho scatter ~0.005.
    assert check["rms_60"] < 0.02 and check["rms_all"] < 0.02
    assert check["samples"] > 0.9 * 5 * int(np.asarray(scene.mask).sum())
    # A specular-looking boost must show up as a larger RMS.
    res = jaxps.photometric_stereo(scene.images, scene.lights, mask=scene.mask)
    shiny = np.asarray(scene.images) * 1.3
    worse = report.lambertian_check_plot(shiny, res.normals, res.albedo, scene.lights,
                                         mask=scene.mask)
    assert worse["rms_60"] > 5 * check["rms_60"]


def test_report_with_ground_truth_maps_and_numbers(synthetic_run, tmp_path):
    root, out, scene = synthetic_run
    truth = root / "truth_normals.png"
    write_normal_map(truth, np.asarray(scene.normals))
    # A near-orthographic depth scan of the same surface: f = 4000 px at 1000 units, so one
    # pixel is 0.25 units; heights scale the same way.
    mask = np.asarray(scene.mask)
    depth = np.where(mask, 1000.0 - 0.25 * np.asarray(scene.height), np.nan).astype(np.float32)
    h, w = depth.shape
    k = np.array([[4000.0, 0, (w - 1) / 2], [0, 4000.0, (h - 1) / 2], [0, 0, 1]])
    np.savez(root / "depth.npz", depth_gt=depth)
    np.savetxt(root / "K.txt", k)
    rc = main(["report", str(out), "--truth-normals", str(truth), "--truth-depth",
               str(root / "depth.npz"), "--intrinsics", str(root / "K.txt"), "--out",
               str(tmp_path / "r.html")])
    assert rc == 0
    page = tmp_path / "r.html"
    parsed = _parse(page)
    _assert_images_resolve(page, parsed.srcs)
    assert "Against ground truth" in parsed.h2
    text = page.read_text()
    ref = jaxps.evaluate.angular_stats(cv2.imread(str(out / "normals.png"), -1)[..., ::-1]
                                       .astype(np.float32) / 65535 * 2 - 1, scene.normals,
                                       mask=np.load(out / "status.npy") == 0)
    # (the page's truth went through a 16-bit PNG, hence the tolerance)
    np.testing.assert_allclose(_cell(text, "angular error median (deg)"), ref["median_deg"],
                               rtol=2e-3)
    # ICP finds the 0.25 units-per-pixel scale of the scan, and the height error is small.
    np.testing.assert_allclose(_cell(text, "ICP scale (scan units per pixel)"), 0.25, rtol=0.02)
    assert _cell(text, "RMS height error (scan units)") < 0.05


def test_report_against_a_scanned_mesh(synthetic_run, tmp_path):
    # The truth as a scanner hands it over: a mesh in millimetres (0.25 mm a pixel), turned
    # 3 degrees and moved, its faces wound inside out.
    _, out, scene = synthetic_run
    mesh = jaxps.report.to_trimesh(np.asarray(scene.height), np.asarray(scene.mask))
    mesh.apply_scale(0.25)
    turn = np.eye(4)
    turn[:3, :3] = cv2.Rodrigues(np.radians([0.0, 3.0, 0.0]))[0]
    turn[:3, 3] = [12.0, -4.0, 650.0]
    mesh.apply_transform(turn)
    mesh.invert()
    mesh.export(tmp_path / "scan.ply")
    assert main(["report", str(out), "--truth-scan", str(tmp_path / "scan.ply"), "--out",
                 str(tmp_path / "r.html")]) == 0
    page = tmp_path / "r.html"
    parsed = _parse(page)
    _assert_images_resolve(page, parsed.srcs)
    text = page.read_text()
    assert "errors against the scan scan.ply after scaled ICP" in text
    np.testing.assert_allclose(_cell(text, "ICP scale (scan units per pixel)"), 0.25, rtol=0.02)
    assert _cell(text, "RMS height error (scan units)") < 0.05
    # The run's normals turned by ICP against the mesh's, as against the truth's turned
    # into the scan's frame, within what the mesh's facets add.
    status = np.load(out / "status.npy")
    normals = cv2.imread(str(out / "normals.png"), -1)[..., ::-1].astype(np.float32) / 65535 * 2 - 1
    comp = jaxps.evaluate.compare_to_scan(np.load(out / "height.npy"), mesh.vertices,
                                          mask=status == 0, normals=normals, trim=0.95)
    truth = jaxps.evaluate.angular_stats(normals @ np.asarray(comp.icp.rotation).T,
                                         np.asarray(scene.normals) @ turn[:3, :3].T,
                                         mask=comp.mask)["median_deg"]
    assert abs(_cell(text, "median angular error after ICP (deg)") - truth) < 0.5
    with pytest.raises(SystemExit):  # one ground-truth surface at a time
        main(["report", str(out), "--truth-scan", str(tmp_path / "scan.ply"), "--truth-depth",
              str(tmp_path / "depth.npz")])
    upright = mesh.copy()  # stored with z up: refused, named by the report's argument
    quarter = np.eye(4)
    quarter[:3, :3] = cv2.Rodrigues(np.radians([90.0, 0.0, 0.0]))[0]
    upright.apply_transform(quarter)
    upright.export(tmp_path / "z_up.ply")
    with pytest.raises(ValueError, match=r"^truth_scan: ICP shrank the reconstruction"):
        report.write_report(out, truth_scan=tmp_path / "z_up.ply", out=tmp_path / "z.html")
    heightless = tmp_path / "heightless"
    heightless.mkdir()
    (heightless / "normals.png").write_bytes((out / "normals.png").read_bytes())
    with pytest.raises(ValueError, match="truth_scan: .*heightless has no height.npy"):
        report.write_report(heightless, truth_scan=tmp_path / "scan.ply")


def _cell(text: str, header: str) -> float:
    return float(text.split(f"{header}</th><td class=\"num\">")[1].split("<")[0])


def test_report_rejects_a_folder_that_is_not_a_run(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a jaxps run"):
        report.write_report(tmp_path)
    assert main(["report", str(tmp_path)]) == 2
    # a run whose summary.json was cut short: the error names the file (before: JSON's own
    # message alone)
    (tmp_path / "summary.json").write_text('{"frames": [')
    with pytest.raises(ValueError, match=r"summary.json is not valid JSON"):
        report.write_report(tmp_path)


def test_report_escapes_names(synthetic_run, tmp_path):
    _, out, _ = synthetic_run
    run = tmp_path / "run"
    run.mkdir()
    for name in ("normals.png", "albedo.png", "height.npy", "status.npy"):
        (run / name).write_bytes((out / name).read_bytes())
    summary = json.loads((out / "summary.json").read_text())
    summary["frames"] = ["<script>alert(1)</script>.png"]
    (run / "summary.json").write_text(json.dumps(summary))
    page = report.write_report(run)
    assert "<script>" not in page.read_text()
    assert "&lt;script&gt;" in page.read_text()


def test_preview_panels_show_normals_albedo_and_shading(tmp_path):
    from jaxps.report._writers import write_preview

    h, w = 600, 400
    mask = np.zeros((h, w), bool)
    mask[100:500, 50:350] = True
    normals = np.zeros((h, w, 3), np.float32)
    normals[...] = [0.6, 0.0, 0.8]
    _, xx = np.mgrid[:h, :w]
    height = -0.05 * xx.astype(np.float32)  # a plane falling to the right: one shade
    write_preview(tmp_path / "p.png", normals, np.full((h, w), 0.5, np.float32), height, mask)
    img = cv2.imread(str(tmp_path / "p.png"))[..., ::-1]
    scale = 480 / h
    ph, pw = round(h * scale), round(w * scale)
    assert img.shape == (24 + ph + 24, 3 * pw + 16, 3)
    row = img[24:24 + ph]
    cy, cx = ph // 2, pw // 2
    np.testing.assert_allclose(row[cy, cx], np.round(np.array([0.8, 0.5, 0.9]) * 255), atol=1)
    assert tuple(row[5, 5]) == (255, 255, 255)  # outside the mask
    # Albedo is scaled by its 99.5th percentile: a constant albedo is full white inside.
    assert tuple(row[cy, pw + 8 + cx]) == (255, 255, 255)
    shade = row[cy - 20:cy + 20, 2 * (pw + 8) + cx - 20:2 * (pw + 8) + cx + 20]
    assert shade.min() == shade.max()  # a plane has one shade (interior, away from the edges)


def test_write_json_has_no_negative_zero(tmp_path):
    from jaxps.report._writers import write_json

    data = {"lights": np.array([[-0.0, 0.5, 1.0]], np.float32), "x": -0.0,
            "nested": [{"y": np.float64(-0.0), "t": (np.float32(-0.0), 2)}], "n": np.int64(3)}
    write_json(tmp_path / "s.json", data)
    text = (tmp_path / "s.json").read_text()
    assert "-0.0" not in text and "-0" not in text
    back = json.loads(text)
    assert back["lights"] == [[0.0, 0.5, 1.0]] and back["n"] == 3
    assert back["nested"] == [{"y": 0.0, "t": [0.0, 2]}]
    assert np.copysign(1.0, back["x"]) == 1.0


def test_progress_bar_names_the_running_stage():
    """The commands' bar (`Stages` told to `report.progress_bar`): while a stage runs, the
    bar's line names it with its place."""
    import io

    from jaxps.core._progress import Stages
    from jaxps.report import progress_bar

    out = io.StringIO()
    with Stages(3, progress_bar(out)) as stages:
        seen = []
        for name in ("load frames", "integrate", "write outputs"):
            stages.run(name, lambda: seen.append(out.getvalue().rsplit("\r", 1)[-1]))
    for line, name in zip(seen, ("load frames (1/3)", "integrate (2/3)", "write outputs (3/3)")):
        assert line.startswith(name), line
    assert list(stages.times) == ["load frames", "integrate", "write outputs"]
