"""`check_lights`: a lights file mirrored, or turned by 180 degrees, is told from the frames.

Synthetic scenes (a rendered face, a tilted plane) need no data; the shared Yale B faces test
the figures quoted in the docstring and docs/robust.md."""

import json
import logging

import cv2
import numpy as np
import pytest

import jaxps
from jaxps import acquisition as acq
from jaxps import synthetic
from jaxps.cli import main

FIVE = ["A+000E+00", "A+025E+00", "A-025E+00", "A+000E+20", "A+000E-20"]
# Wrong lights files, from the right one (the scanner's five: centre, then two pairs).
MIRRORED = {"y negated": lambda l: l * [1, -1, 1], "x negated": lambda l: l * [-1, 1, 1],
            "left and right swapped": lambda l: l[[0, 2, 1, 3, 4]]}
TURNED = lambda l: l[[0, 2, 1, 4, 3]]  # opposite lamps swapped: 180 degrees


@pytest.fixture(scope="module")
def face():
    lights = np.asarray(synthetic.scanner_lights(20.0), np.float64)
    surface = synthetic.face_like(160)
    scene = synthetic.render_scene(surface, lights, noise=0.01, key=3)
    return np.asarray(scene.images), lights, np.asarray(surface.mask)


def test_a_rendered_face_with_its_lights_is_integrable_and_bulges(face):
    images, lights, mask = face
    c = jaxps.check_lights(images, lights, mask=mask)
    assert c.curl < 0.15 and c.convexity < -0.4  # integrable; bulging toward the camera
    assert not c.flagged and c.unchecked == "" and c.loops > 1000
    assert "curl 0.0" in c.summary() and "mirrored" not in c.summary()


@pytest.mark.parametrize("wrong", list(MIRRORED))
def test_mirrored_lights_give_two_minus_the_curl(face, wrong):
    images, lights, mask = face
    right = jaxps.check_lights(images, lights, mask=mask)
    c = jaxps.check_lights(images, MIRRORED[wrong](lights), mask=mask)
    # (p, q) -> (-p, q) or (p, -q): every loop's curl is the other derivative's sum
    assert c.curl == pytest.approx(2 - right.curl, abs=1e-6) and c.loops == right.loops
    assert c.mirrored and not c.hollow
    assert "mirrored" in c.summary() and "y UP" in c.summary()


def test_lights_turned_by_180_degrees_give_a_hollow_face(face):
    images, lights, mask = face
    right = jaxps.check_lights(images, lights, mask=mask)
    c = jaxps.check_lights(images, TURNED(lights), mask=mask)
    assert c.curl == pytest.approx(right.curl, abs=1e-6)  # (-p, -q) is integrable too
    assert c.convexity == pytest.approx(-right.convexity, abs=1e-6)
    assert c.hollow and not c.mirrored and "turned by 180 degrees" in c.summary()


def test_a_plane_is_neither_mirrored_nor_hollow():
    lights = np.asarray(synthetic.scanner_lights(20.0), np.float64)
    n = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    images = (lights @ n)[:, None, None] * np.ones((5, 120, 120))
    images = images + 0.01 * np.random.default_rng(0).standard_normal(images.shape)
    for given in (lights, lights * [1, -1, 1]):
        c = jaxps.check_lights(images, given)
        assert 0.8 < c.curl < 1.2 and abs(c.convexity) < 0.05 and not c.flagged


def test_no_verdict_for_wide_lights_or_too_few_pixels(face):
    images, lights, mask = face
    wide = lights.copy()
    wide[1] = [np.sin(np.radians(60)), 0, np.cos(np.radians(60))]
    c = jaxps.check_lights(images, wide, mask=mask)
    assert np.isnan(c.curl) and not c.flagged and "60 degrees" in c.unchecked
    assert "not checked" in c.summary()
    assert np.isfinite(jaxps.check_lights(images, wide, mask=mask, max_zenith_deg=61).curl)
    tiny = np.zeros_like(mask)
    tiny[70:74, 60:64] = True
    c = jaxps.check_lights(images, lights, mask=tiny)
    assert np.isnan(c.curl) and "need 50" in c.unchecked


def test_bad_input_names_the_argument(face):
    images, lights, mask = face
    with pytest.raises(ValueError, match="lights: 4 lights for 5 frames"):
        jaxps.check_lights(images, lights[:4], mask=mask)
    with pytest.raises(ValueError, match="mask must have shape"):
        jaxps.check_lights(images, lights, mask=mask[1:])
    with pytest.raises(ValueError, match="images must be"):
        jaxps.check_lights(images[0], lights, mask=mask)
    with pytest.raises(ValueError, match="max_zenith_deg"):
        jaxps.check_lights(images, lights, mask=mask, max_zenith_deg=0)


def test_colour_frames_are_checked_on_their_grey(face):
    images, lights, mask = face
    colour = images[..., None] * np.array([0.9, 1.0, 0.7], np.float32)
    grey = jaxps.check_lights(colour.mean(axis=-1), lights, mask=mask)
    got = jaxps.check_lights(colour, lights, mask=mask)
    assert got.curl == pytest.approx(grey.curl, abs=1e-6)


def test_yale_faces_right_and_wrong_lights(data, caplog):
    """The shared faces' five scanner frames, as `jaxps reconstruct --yale-names --ambient`
    loads them: the lights as given pass, every mirrored file is flagged (and logged), a turn
    by 180 degrees gives a hollow face (benchmarks/light_check.py: curl 0.36-0.45 as given,
    1.55-1.64 mirrored; convexity -0.15 to -0.21 as given)."""
    for folder in sorted((data / "yaleb").glob("yaleB*")):
        s = folder.name
        files = [folder / f"{s}_P00{n}.pgm" for n in FIVE]
        cap = acq.load_capture(files, yale_names=True, ambient=folder / f"{s}_P00_Ambient.pgm",
                               check_quality=False)
        right = cap.light_check
        assert right is not None and not right.flagged, s
        assert 0.3 < right.curl < 0.5 and right.convexity < -0.1, s
        for name, wrong in MIRRORED.items():
            caplog.clear()
            with caplog.at_level(logging.WARNING, logger="jaxps"):
                got = acq.load_capture(files, lights=wrong(cap.lights), ambient=folder /
                                       f"{s}_P00_Ambient.pgm", check_quality=False)
            assert got.light_check.mirrored, (s, name)
            assert "is the lights file mirrored?" in caplog.text, (s, name)
        turned = jaxps.check_lights(cap.images, TURNED(cap.lights), mask=cap.mask)
        assert turned.hollow and turned.convexity > 0.1, s


def test_reconstruct_reports_the_check_and_warns(tmp_path, caplog):
    """`jaxps reconstruct` with a lights file whose y points down the image rows."""
    lights = np.asarray(synthetic.scanner_lights(20.0), np.float64)
    images = np.asarray(synthetic.render_scene(synthetic.face_like(96), lights, noise=0.005,
                                               key=1).images)
    paths = []
    for k, img in enumerate(images):
        paths.append(str(tmp_path / f"f{k}.png"))
        cv2.imwrite(paths[-1], np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16))
    outputs = {}
    for name, given in (("right", lights), ("y down", lights * [1, -1, 1])):
        jaxps.save_lights(tmp_path / f"{name}.txt", given)
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="jaxps"):
            assert main(["reconstruct", *paths, "--lights", str(tmp_path / f"{name}.txt"),
                         "--out", str(tmp_path / name)]) == 0
        outputs[name] = (json.loads((tmp_path / name / "summary.json").read_text()),
                         caplog.text)
    right, log = outputs["right"]
    assert right["light_check"]["mirrored"] is False and right["light_check"]["curl"] < 0.2
    assert "mirrored" not in log
    wrong, log = outputs["y down"]
    assert wrong["light_check"]["mirrored"] is True
    assert wrong["light_check"]["curl"] == pytest.approx(2 - right["light_check"]["curl"],
                                                         abs=1e-3)
    assert "is the lights file mirrored?" in log and "mirrored" in wrong["light_check"]["summary"]


def test_many_captures_get_a_lights_column(tmp_path):
    """`reconstruct_many`: the same lights for two folders, the second one's frames lit by
    the lights mirrored in y."""
    lights = np.asarray(synthetic.scanner_lights(20.0), np.float64)
    for name, lit_by in (("right", lights), ("mirrored", lights * [1, -1, 1])):
        folder = tmp_path / name
        folder.mkdir()
        images = np.asarray(synthetic.render_scene(synthetic.face_like(96), lit_by).images)
        for k, img in enumerate(images):
            cv2.imwrite(str(folder / f"f{k}.png"),
                        np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16))
    _, rows = jaxps.reconstruct_many([tmp_path / "right", tmp_path / "mirrored"],
                                     lights=lights, progress=False)
    assert [r["lights"] for r in rows] == ["ok", "mirrored?"]
    assert "lights" in jaxps.summary_table(rows).splitlines()[0]
