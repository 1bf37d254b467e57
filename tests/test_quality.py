"""Frame quality checks on synthetic corruptions, and on the real Yale B frames."""

import re

import cv2
import numpy as np
import pytest

import jaxps
from helpers import face_scene


def _frames():
    scene = face_scene(64, noise=0.005, seed=3)
    return scene, np.clip(np.asarray(scene.images) + 0.05, 0, 1).astype(np.float32)


def test_clean_capture_passes():
    scene, frames = _frames()
    report = jaxps.check_frames(frames, mask=scene.mask)
    assert report.keep.all(), report.summary()
    with pytest.raises(TypeError, match="thresholds must be a QualityThresholds"):
        jaxps.check_frames(frames, thresholds=None)  # an AttributeError before


@pytest.mark.parametrize("kind, frame, words", [
    ("interlace", 1, "interlace"),
    ("rows", 2, "corrupt rows|row/interlace"),
    ("saturated", 3, "saturated"),
    ("dark", 4, "dark"),
    ("truncated", 1, "truncated"),
    ("blank", 3, r"blank: every pixel 0 \("),
    ("other_scene", 2, "inconsistent"),
])
def test_corruption_is_flagged(kind, frame, words):
    scene, frames = _frames()
    f = frames[frame]
    if kind == "interlace":
        f[1::2] = np.roll(f[1::2], 3, axis=1) * 0.7
    elif kind == "rows":
        f[[20, 33]] = 1.0
    elif kind == "saturated":
        frames[frame] = np.clip(f * 4, 0, 1)
    elif kind == "dark":
        frames[frame] = f * 0.01
    elif kind == "truncated":
        f[-20:] = 0.0
    elif kind == "blank":  # e.g. the ambient frame given as a frame too: zero once subtracted
        f[:] = 0.0
    elif kind == "other_scene":
        frames[frame] = np.asarray(jax_random_frame(f.shape))
    report = jaxps.check_frames(frames, mask=None if kind in ("truncated", "blank") else scene.mask,
                                names=[f"f{i}.png" for i in range(5)])
    assert [c.index for c in report.flagged] == [frame], report.summary()
    assert re.search(words, report.summary())
    assert f"f{frame}.png" in report.summary()
    if kind == "blank":  # not taken for a short read
        assert "truncated" not in report.summary(), report.summary()
    kept_frames, kept_lights, kept = jaxps.drop_flagged(frames, scene.lights, report)
    assert list(kept) == [i for i in range(5) if i != frame]
    assert kept_frames.shape[0] == 4 and kept_lights.shape == (4, 3)


def jax_random_frame(shape):
    rng = np.random.default_rng(0)
    return rng.uniform(0.1, 0.9, shape).astype(np.float32)


def test_every_frame_flagged_raises_with_reasons():
    scene, frames = _frames()
    frames = frames * 0.001
    report = jaxps.check_frames(frames, mask=scene.mask)
    assert not report.keep.any()
    with pytest.raises(ValueError, match=r"only 0 of 5 frames passed(.|\n)*dark"):
        jaxps.drop_flagged(frames, scene.lights, report)


def test_thresholds_out_of_range_are_named():
    scene, frames = _frames()
    for kwargs in ({"comb": -1.0}, {"dark_fraction": 1.5}, {"row_z": float("nan")}):
        name = next(iter(kwargs))
        with pytest.raises(ValueError, match=rf"thresholds must be(.|\n)*{name}="):
            jaxps.check_frames(frames, thresholds=jaxps.QualityThresholds(**kwargs))


def test_check_file_truncated_pgm(tmp_path):
    img = (np.arange(40 * 30) % 256).astype(np.uint8).reshape(40, 30)
    path = tmp_path / "a.pgm"
    cv2.imwrite(str(path), img)
    assert jaxps.check_file(path) is None
    data = path.read_bytes()
    path.write_bytes(data[:-100])
    assert "truncated" in jaxps.check_file(path)
    assert jaxps.check_file(tmp_path / "missing.pgm") == "missing file"


def test_yaleb_interlaced_frames_flagged(data):
    folder = data / "yaleb" / "yaleB02"
    names = ["yaleB02_P00A+000E+00.pgm", "yaleB02_P00A+020E-10.pgm", "yaleB02_P00A+025E+00.pgm",
             "yaleB02_P00A-020E-10.pgm", "yaleB02_P00A+000E+20.pgm"]
    frames = np.stack([cv2.imread(str(folder / n), cv2.IMREAD_UNCHANGED) for n in names])
    report = jaxps.check_frames(frames.astype(np.float32) / 255, names=names)
    assert [c.name for c in report.flagged] == names[1:3]
    assert all("interlace" in c.reasons[0] for c in report.flagged)


def test_load_capture_check_quality_drops_and_logs(data, caplog):
    from jaxps.acquisition import load_capture

    folder = data / "yaleb" / "yaleB02"
    names = ["yaleB02_P00A+000E+00.pgm", "yaleB02_P00A+020E+10.pgm", "yaleB02_P00A-020E+10.pgm",
             "yaleB02_P00A+020E-10.pgm", "yaleB02_P00A-020E-10.pgm"]
    with caplog.at_level("WARNING", logger="jaxps"):
        cap = load_capture([folder / n for n in names], yale_names=True,
                           ambient=folder / "yaleB02_P00_Ambient.pgm", check_quality=True)
    assert cap.names == tuple(n for n in names if n != "yaleB02_P00A+020E-10.pgm")
    assert cap.images.shape[0] == 4 and cap.lights.shape == (4, 3)
    assert "yaleB02_P00A+020E-10.pgm: row/interlace" in caplog.text


def _on_black_canvas():
    """The test frames `(K, h, w)` in the middle of an exactly black `(K, 3h, 3w)` canvas."""
    _, frames = _frames()
    k, h, w = frames.shape
    canvas = np.zeros((k, 3 * h, 3 * w), np.float32)
    canvas[:, h:2 * h, w:2 * w] = frames
    return canvas, frames


def test_dark_surround_is_not_a_dark_frame():
    # An object on black filling under 20% of the frame (checked without a mask): more than
    # `dark_fraction` of every frame is below `dark_level`, but only a frame that is dark for
    # this capture (its mean under `dark_relative` times the median frame mean) is flagged.
    canvas, _ = _on_black_canvas()
    report = jaxps.check_frames(canvas)
    assert all(m > 0.8 for m in (c.measures["dark_fraction"] for c in report.frames))
    assert not any("dark" in r for c in report.frames for r in c.reasons), report.summary()
    canvas[3] *= 0.05
    report = jaxps.check_frames(canvas)
    assert [c.index for c in report.flagged if any("dark" in r for r in c.reasons)] == [3]


def test_blank_border_every_frame_shares_is_not_truncation():
    # A render on an exactly black canvas: every frame ends in h constant rows (how a short
    # read is padded too). Only a frame with more of them than the capture's median frame, by
    # `max(min_truncated_rows, truncated_fraction * H)`, is a short read.
    canvas, frames = _on_black_canvas()
    k, h, w = frames.shape
    report = jaxps.check_frames(canvas)
    assert [c.measures["truncated_rows"] for c in report.frames] == [h] * k
    assert report.keep.all(), report.summary()
    cut = 10  # > max(8, 0.05 * 3h = 9.6)
    canvas[2, 2 * h - cut:2 * h] = 0.0
    report = jaxps.check_frames(canvas)
    assert [c.index for c in report.flagged] == [2], report.summary()
    assert f"last {h + cut} rows constant" in report.summary()
    canvas[2, 2 * h - cut, w:2 * w] = frames[2, -cut]  # one row fewer: below the threshold
    report = jaxps.check_frames(canvas)
    assert report.frames[2].measures["truncated_rows"] == h + cut - 1
    assert not any("truncated" in r for c in report.frames for r in c.reasons), report.summary()
