"""Motion between frames: synthetic sub-pixel shifts are measured and undone."""

import numpy as np
import pytest
from scipy import ndimage

import jaxps
from helpers import face_scene

SHIFTS = np.array([[0.0, 0.0], [1.3, -0.7], [-2.4, 0.35], [0.6, 2.8], [-1.55, -1.9]])


def _fourier_shift(img, s):
    return np.fft.ifft2(ndimage.fourier_shift(np.fft.fft2(img), s)).real


def test_subpixel_shifts_recovered_and_ps_restored():
    scene = face_scene(96)
    images = np.asarray(scene.images)
    moved = np.stack([_fourier_shift(im, s) for im, s in zip(images, SHIFTS)]).astype(np.float32)
    reg = jaxps.register_frames(moved, mask=scene.mask)
    assert reg.registered
    assert np.max(np.abs(reg.shifts - SHIFTS)) < 0.1
    inner = ndimage.binary_erosion(np.asarray(scene.mask), iterations=4)
    still = jaxps.photometric_stereo(images, scene.lights, mask=scene.mask)
    fixed = jaxps.photometric_stereo(reg.frames, scene.lights, mask=scene.mask)
    unfixed = jaxps.photometric_stereo(moved, scene.lights, mask=scene.mask)
    err = jaxps.evaluate.angular_stats(fixed.normals, still.normals, mask=inner)
    assert err["median_deg"] < 0.5
    assert jaxps.evaluate.angular_stats(unfixed.normals, still.normals,
                                        mask=inner)["median_deg"] > 3


def test_large_motion_reported_not_corrected():
    scene = face_scene(64)
    images = np.asarray(scene.images)
    moved = images.copy()
    moved[2] = _fourier_shift(images[2], (6.0, 0.0))
    reg = jaxps.register_frames(moved, mask=scene.mask, max_shift=3.0)
    assert not reg.registered
    assert abs(reg.shifts[2, 0] - 6.0) < 0.2
    np.testing.assert_array_equal(np.asarray(reg.frames), moved)


def test_shift_frames_roundtrip_and_errors():
    rng = np.random.default_rng(1)
    frames = ndimage.gaussian_filter(rng.random((2, 32, 32)), 2).astype(np.float32)
    out = jaxps.shift_frames(jaxps.shift_frames(frames, [[1, 2], [0, -1]]), [[-1, -2], [0, 1]])
    np.testing.assert_allclose(np.asarray(out)[:, 4:-4, 4:-4], frames[:, 4:-4, 4:-4], atol=1e-5)
    with pytest.raises(ValueError, match="shifts"):
        jaxps.shift_frames(frames, [[1, 2]])
    with pytest.raises(ValueError, match="reference"):
        jaxps.estimate_shifts(frames, reference=5)
