"""Batched photometric stereo: N captures in one call equal N single calls; bad batches fail."""

import numpy as np
import pytest

import jaxps
from helpers import face_scene


def _captures(n=3, h=48):
    scenes = [face_scene(h, noise=0.01, seed=i) for i in range(n)]
    gains = np.array([[1.0, 0.9, 1.1, 1.05, 0.95], [1.0, 1.0, 1.0, 1.0, 1.0],
                      [0.9, 1.1, 1.0, 0.95, 1.05]], np.float32)[:n]
    images = np.stack([np.asarray(s.images) * g[:, None, None] for s, g in zip(scenes, gains)])
    return scenes, images.astype(np.float32)


@pytest.mark.parametrize("method", ["l2", "semi_calibrated"])
def test_batch_equals_single_calls(method):
    scenes, images = _captures()
    lights = scenes[0].lights
    masks = np.stack([np.asarray(s.mask) for s in scenes])
    batch = jaxps.photometric_stereo_batch(images, lights, mask=masks, method=method)
    assert batch.normals.shape == (3, 48, 38, 3)
    for i in range(3):
        single = jaxps.photometric_stereo(images[i], lights, mask=masks[i], method=method)
        np.testing.assert_allclose(batch.normals[i], single.normals, atol=2e-5)
        np.testing.assert_allclose(batch.albedo[i], single.albedo, atol=2e-5)
        np.testing.assert_array_equal(batch.status[i], single.status)
        if method == "semi_calibrated":
            np.testing.assert_allclose(batch.info["intensities"][i],
                                       single.info["intensities"], atol=1e-4)


def test_batch_chunks_and_list_input():
    scenes, images = _captures()
    lights = np.stack([scenes[0].lights] * 3)
    whole = jaxps.photometric_stereo_batch(images, lights)
    chunked = jaxps.photometric_stereo_batch(list(images), lights, chunk=2)
    np.testing.assert_allclose(whole.normals, chunked.normals, atol=1e-6)


def test_batch_rejects_different_sizes():
    _, images = _captures(2)
    with pytest.raises(ValueError, match="capture 1 has shape"):
        jaxps.photometric_stereo_batch([images[0], images[1][:, :40]],
                                       jaxps.synthetic.scanner_lights())


def test_batch_rejects_bad_lights_and_mask():
    _, images = _captures(2)
    with pytest.raises(ValueError, match="lights"):
        jaxps.photometric_stereo_batch(images, np.ones((4, 3)))
    with pytest.raises(ValueError, match="mask"):
        jaxps.photometric_stereo_batch(images, jaxps.synthetic.scanner_lights(),
                                       mask=np.ones((3, 3), bool))


def test_summary_table():
    text = jaxps.summary_table([{"capture": "a", "ok_%": 99.123}, {"capture": "bb", "ok_%": 5.0}])
    lines = text.splitlines()
    assert lines[0].split() == ["capture", "ok_%"]
    assert lines[2].split() == ["a", "99.1"]
    assert lines[3].split() == ["bb", "5"]
