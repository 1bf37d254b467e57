import cv2
import numpy as np
import pytest

import jaxps
from helpers import mask_png, near_target_capture, target_capture
from jaxps import acquisition as acq


def test_16bit_png_keeps_16_bits(tmp_path):
    ramp = (np.arange(64 * 64, dtype=np.uint32) * 16).reshape(64, 64).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "f.png"), ramp)
    img = acq.read_image(tmp_path / "f.png")
    assert img.dtype == np.float32
    np.testing.assert_array_equal(np.round(img * 65535).astype(np.uint16), ramp)
    assert len(np.unique(img)) == 4096  # more levels than 8 bits could hold


def test_16bit_colour_png_rgb_order(tmp_path):
    rgb = np.zeros((4, 5, 3), np.uint16)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 60000, 30000, 1000
    cv2.imwrite(str(tmp_path / "c.png"), rgb[..., ::-1])
    img = acq.read_image(tmp_path / "c.png")
    np.testing.assert_allclose(img[0, 0], np.array([60000, 30000, 1000]) / 65535, rtol=1e-6)


def test_shared_16bit_normal_map(data):
    n = acq.read_image(data / "diligent_gt" / "bear" / "normal_map.png")
    assert n.shape[-1] == 3
    assert len(np.unique(n[..., 2])) > 256
    m = acq.read_mask(data / "diligent_gt" / "bear" / "mask.png", n.shape[:2])
    v = n[m] * 2 - 1
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1, atol=2e-3)
    assert np.median(v[:, 2]) > 0.5  # z toward the viewer


def test_pgm_maxval_of_a_12_bit_camera_reads_as_one(tmp_path):
    codes = np.array([[0, 1000, 4095], [2048, 4095, 7]], np.uint16)
    binary = tmp_path / "f0.pgm"  # 16-bit big-endian samples, maxval 4095
    binary.write_bytes(b"P5\n# a camera's comment\n3 2\n4095\n" + codes.astype(">u2").tobytes())
    text = tmp_path / "f1.pgm"
    text.write_text("P2\n3 2 4095\n" + " ".join(map(str, codes.ravel())) + "\n")
    for path in (binary, text):
        np.testing.assert_allclose(acq.read_image(path), codes / 4095, rtol=1e-6)
    # Before, 4095 / 65535 = 0.0625: the frames 16x too dark and nothing saturated.
    stack, saturated = acq.load_stack([binary, text])
    np.testing.assert_allclose(stack, np.stack([codes / 4095] * 2), rtol=1e-6)
    np.testing.assert_array_equal(saturated, np.stack([codes == 4095] * 2))


def test_bits_reads_a_12_bit_camera_in_16_bit_pngs(tmp_path, caplog):
    rng = np.random.default_rng(0)
    codes = rng.integers(100, 3000, size=(3, 20, 16)).astype(np.uint16)
    codes[:, :3, :4] = 4095  # a saturated highlight of a 12-bit camera
    paths = []
    for i, c in enumerate(codes):
        paths.append(tmp_path / f"f{i}.png")
        cv2.imwrite(str(paths[-1]), c)
    cv2.imwrite(str(tmp_path / "ambient.png"), np.full((20, 16), 40, np.uint16))
    with caplog.at_level("WARNING", logger="jaxps"):
        stack, saturated = acq.load_stack(paths)  # read as 16-bit: 16x too dark, unsaturated
    assert not saturated.any() and stack.max() == pytest.approx(4095 / 65535)
    assert "top out at code 4095, the largest of a 12-bit camera" in caplog.text
    assert "bits=12 (--bits 12)" in caplog.text
    caplog.clear()
    pgm = tmp_path / "f.pgm"  # a PGM whose header keeps the 16-bit maxval: the same warning
    pgm.write_bytes(b"P5\n16 20\n65535\n" + codes[0].astype(">u2").tobytes())
    with caplog.at_level("WARNING", logger="jaxps"):
        acq.load_stack([pgm])
    assert "top out at code 4095" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="jaxps"):
        stack, saturated = acq.load_stack(paths, bits=12)
    assert caplog.text == ""
    np.testing.assert_allclose(stack, codes / 4095, rtol=1e-6)
    np.testing.assert_array_equal(saturated, codes == 4095)
    # load_capture reads the ambient frame at the same depth
    cap = acq.load_capture(paths, lights=np.eye(3) + 0.5, ambient=tmp_path / "ambient.png",
                           bits=12, intensities="none", register=False, check_quality=False)
    np.testing.assert_allclose(cap.images, np.clip((codes - 40.0) / 4095, 0, None), atol=1e-6)
    with pytest.raises(ValueError, match=r"codes up to 4095, above the 1023 of bits=10"):
        acq.load_stack(paths, bits=10)
    for bad in (0, 17, 12.0):
        with pytest.raises(ValueError, match="bits must be an int from 1 to 16"):
            acq.read_image(paths[0], bits=bad)


def test_grey_png_with_alpha_reads_as_grey(tmp_path):
    from PIL import Image

    grey = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    Image.fromarray(np.dstack([grey, np.full_like(grey, 255)]), "LA").save(tmp_path / "la.png")
    got = acq.read_image(tmp_path / "la.png", linearize="none")
    # (3, 4, 3) colour before: OpenCV returns four channels for grey + alpha
    np.testing.assert_allclose(got, grey / 255, rtol=1e-6)


def test_8bit_srgb_png_decoded_tiff_and_pgm_linear(tmp_path):
    v = np.full((3, 3), 128, np.uint8)
    for name in ("g.png", "g.pgm", "g.tif", "g.bmp"):
        cv2.imwrite(str(tmp_path / name), v)
    srgb = ((128 / 255 + 0.055) / 1.055) ** 2.4
    assert acq.read_image(tmp_path / "g.png")[0, 0] == pytest.approx(srgb, rel=1e-5)
    assert acq.read_image(tmp_path / "g.pgm")[0, 0] == pytest.approx(128 / 255, rel=1e-6)
    assert acq.read_image(tmp_path / "g.tif")[0, 0] == pytest.approx(128 / 255, rel=1e-6)
    assert acq.read_image(tmp_path / "g.bmp")[0, 0] == pytest.approx(128 / 255, rel=1e-6)
    assert acq.read_image(tmp_path / "g.png", linearize="none")[0, 0] == pytest.approx(128 / 255)
    t16 = np.full((2, 2), 40000, np.uint16)
    cv2.imwrite(str(tmp_path / "t.tif"), t16)
    assert acq.read_image(tmp_path / "t.tif")[0, 0] == pytest.approx(40000 / 65535, rel=1e-6)


def test_read_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.png"):
        acq.read_image(tmp_path / "missing.png")
    (tmp_path / "broken.png").write_bytes(b"not an image at all")
    with pytest.raises(ValueError, match="broken.png"):
        acq.read_image(tmp_path / "broken.png")
    with pytest.raises(ValueError, match="linearize"):
        acq.read_image(tmp_path / "broken.png", linearize="gamma")
    # float frames in a camera's own units (here up to 2492.7) would read as saturated nearly
    # everywhere, and the frame check would call them corrupt: the file is named instead
    cv2.imwrite(str(tmp_path / "hdr.tif"), np.linspace(0, 2492.7, 12, dtype=np.float32)
                .reshape(3, 4))
    with pytest.raises(ValueError, match=r"hdr.tif holds floating-point values up to 2492.7"):
        acq.read_image(tmp_path / "hdr.tif")
    cv2.imwrite(str(tmp_path / "unit.tif"), np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4))
    assert acq.read_image(tmp_path / "unit.tif").max() == 1.0


def test_list_frames_natural_order_and_skips(tmp_path):
    for name in ("x.10.png", "x.2.png", "x.mask.png", "x_Ambient.pgm", "notes.txt", "x.1.png",
                 "x.3.bmp"):
        (tmp_path / name).write_bytes(b"")
    names = [p.rsplit("/", 1)[-1] for p in acq.list_frames(tmp_path)]
    assert names == ["x.1.png", "x.2.png", "x.3.bmp", "x.10.png"]
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="no frame files"):
        acq.list_frames(empty)
    with pytest.raises(FileNotFoundError, match="not found"):
        acq.list_frames(tmp_path / "nope")


def test_mismatched_frame_sizes_name_the_file(tmp_path):
    cv2.imwrite(str(tmp_path / "a.pgm"), np.zeros((4, 4), np.uint8))
    cv2.imwrite(str(tmp_path / "b.pgm"), np.zeros((4, 5), np.uint8))
    with pytest.raises(ValueError, match=r"b\.pgm has shape \(4, 5\)"):
        acq.load_stack([tmp_path / "a.pgm", tmp_path / "b.pgm"])
    # one frame re-exported at another depth, or as a PNG (decoded from sRGB): not one scale
    cv2.imwrite(str(tmp_path / "c.pgm"), np.zeros((4, 4), np.uint16))
    with pytest.raises(ValueError, match=r"c\.pgm holds 16-bit codes, but .*a\.pgm holds "
                                         r"8-bit codes: all frames of a capture must share"):
        acq.load_stack([tmp_path / "a.pgm", tmp_path / "c.pgm"])
    cv2.imwrite(str(tmp_path / "d.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError, match=r"d\.png holds 8-bit codes decoded from sRGB"):
        acq.load_stack([tmp_path / "a.pgm", tmp_path / "d.png"])
    assert acq.load_stack([tmp_path / "a.pgm", tmp_path / "d.png"], linearize="none")[0].shape \
        == (2, 4, 4)


def test_load_capture_names_what_is_missing(tmp_path):
    paths = []
    for k in range(3):
        paths.append(tmp_path / f"f{k}.pgm")
        cv2.imwrite(str(paths[-1]), np.full((3, 3), 100, np.uint8))
    with pytest.raises(ValueError, match=r"at least 3 frames, got 2 \(f0.pgm, f1.pgm\)"):
        acq.load_capture(paths[:2], lights=np.eye(3)[:2])
    with pytest.raises(FileNotFoundError, match="ambient frame not found: .*amb.pgm"):
        acq.load_capture(paths, lights=np.eye(3), ambient=tmp_path / "amb.pgm")
    with pytest.raises(FileNotFoundError, match="mask not found: .*m.png"):
        acq.load_capture(paths, lights=np.eye(3), mask=str(tmp_path / "m.png"))


def test_ambient_subtraction_clips_and_saturation_from_raw(tmp_path):
    frames = [np.full((3, 3), v, np.uint8) for v in (10, 100, 255)]
    paths = []
    for k, f in enumerate(frames):
        paths.append(tmp_path / f"f{k}.pgm")
        cv2.imwrite(str(paths[-1]), f)
    cv2.imwrite(str(tmp_path / "amb.pgm"), np.full((3, 3), 50, np.uint8))
    cap = acq.load_capture(paths, lights=np.eye(3), ambient=tmp_path / "amb.pgm",
                           intensities="none")
    np.testing.assert_allclose(cap.images[:, 0, 0], [0, 50 / 255, 205 / 255], rtol=1e-6)
    np.testing.assert_array_equal(cap.saturated[:, 0, 0], [False, False, True])
    assert cap.intensity_method == "none" and np.all(cap.gains == 1)
    # 64-byte aligned, so that XLA-CPU takes the stack as a jit argument without a copy
    assert cap.images.ctypes.data % 64 == 0 and cap.images.flags.c_contiguous
    # The default estimate cannot use a black frame: it falls back to "none", says so in the
    # capture and on the "jaxps" logger, and still loads.
    cap = acq.load_capture(paths, lights=np.eye(3), ambient=tmp_path / "amb.pgm")
    assert cap.intensity_method == "none" and np.all(cap.gains == 1)


def test_folder_ambient_auto_and_unused_ambient_named(tmp_path, caplog):
    # A scanner writes one folder per capture, its ambient frame inside: ambient="auto" takes
    # that file, and a folder's ambient frame left unused is named on the "jaxps" logger.
    rng = np.random.default_rng(0)
    for k in range(3):
        cv2.imwrite(str(tmp_path / f"f{k}.pgm"), rng.integers(60, 250, (6, 5), dtype=np.uint8))
    cv2.imwrite(str(tmp_path / "Ambient.pgm"), rng.integers(1, 50, (6, 5), dtype=np.uint8))
    kw = {"lights": np.eye(3), "intensities": "none", "check_quality": False, "register": False}
    given = acq.load_capture(tmp_path, ambient=tmp_path / "Ambient.pgm", **kw)
    auto = acq.load_capture(tmp_path, ambient="auto", **kw)
    np.testing.assert_array_equal(auto.images, given.images)
    with caplog.at_level("WARNING", logger="jaxps"):
        plain = acq.load_capture(tmp_path, **kw)
    assert "Ambient.pgm" in caplog.text and "not subtracted" in caplog.text
    assert np.all(plain.images > given.images)
    with pytest.raises(ValueError, match="a folder of frames"):
        acq.load_capture(sorted(tmp_path.glob("f*.pgm")), ambient="auto", **kw)
    cv2.imwrite(str(tmp_path / "ambient_2.pgm"), np.zeros((6, 5), np.uint8))
    with pytest.raises(ValueError, match="expected one frame .*Ambient.pgm.*ambient_2.pgm"):
        acq.load_capture(tmp_path, ambient="auto", **kw)


def test_multi_page_tiff_stands_for_its_pages(tmp_path):
    # A high-speed camera may write a capture as one multi-page TIFF: its pages are the frames
    # (named page by page), and "stack.tif[5]" names one page, here the ambient frame. The
    # same frames as separate files load the same.
    from helpers import face_scene

    scene = face_scene(48)
    ambient = np.full(scene.mask.shape, 0.1, np.float32)
    pages = [np.round(np.clip(f + ambient, 0, 1) * 65535).astype(np.uint16)
             for f in np.asarray(scene.images)] + [np.round(ambient * 65535).astype(np.uint16)]
    stack = tmp_path / "stack.tif"
    assert cv2.imwritemulti(str(stack), pages)
    for i, page in enumerate(pages):
        cv2.imwrite(str(tmp_path / f"f{i}.tif"), page)
    kw = {"lights": np.asarray(scene.lights), "intensities": "none", "register": False}
    cap = acq.load_capture([f"{stack}[{i}]" for i in range(5)], ambient=f"{stack}[5]", **kw)
    files = acq.load_capture([tmp_path / f"f{i}.tif" for i in range(5)],
                             ambient=tmp_path / "f5.tif", **kw)
    np.testing.assert_array_equal(cap.images, files.images)
    assert cap.names == tuple(f"stack.tif[{i}]" for i in range(5))
    # the whole file, alone or in a folder, is its six pages
    (tmp_path / "stack").mkdir()
    stack.rename(tmp_path / "stack" / "stack.tif")
    stack = tmp_path / "stack" / "stack.tif"
    assert acq.list_frames(tmp_path / "stack") == [f"{stack}[{i}]" for i in range(6)]
    six = acq.load_capture(stack, lights=np.vstack([scene.lights, [[0, 0, 1]]]),
                           check_quality=False, intensities="none", register=False)
    assert len(six.names) == 6 and six.names[5] == "stack.tif[5]"
    with pytest.raises(ValueError, match=r"stack.tif\[6\]: .*stack.tif has 6 page"):
        acq.read_image(f"{stack}[6]")
    with pytest.raises(FileNotFoundError, match="ambient frame not found: .*nope.tif"):
        acq.load_capture(stack, lights=np.eye(3), ambient=tmp_path / "nope.tif[1]")


def test_an_ambient_frame_in_another_encoding_is_named(tmp_path):
    # 16-bit frames (linear) and an 8-bit PNG ambient frame (decoded from sRGB): not one scale
    rng = np.random.default_rng(0)
    paths = []
    for k in range(3):
        paths.append(tmp_path / f"f{k}.png")
        cv2.imwrite(str(paths[-1]), rng.integers(20000, 60000, (6, 5), dtype=np.uint16))
    cv2.imwrite(str(tmp_path / "amb.png"), np.full((6, 5), 20, np.uint8))
    kw = {"lights": np.eye(3), "intensities": "none", "check_quality": False, "register": False}
    with pytest.raises(ValueError, match=r"amb.png is decoded from sRGB .* but the frames "
                                         r"\(f0.png\) are read as linear"):
        acq.load_capture(paths, ambient=tmp_path / "amb.png", **kw)
    cap = acq.load_capture(paths, ambient=tmp_path / "amb.png", linearize="none", **kw)
    raw = cv2.imread(str(paths[0]), cv2.IMREAD_UNCHANGED) / 65535
    np.testing.assert_allclose(cap.images[0], raw - 20 / 255, atol=1e-6)


def test_folder_lights_auto(tmp_path):
    # lights="auto" takes the folder's own lights file, as ambient="auto" its ambient frame.
    rng = np.random.default_rng(0)
    for k in range(3):
        cv2.imwrite(str(tmp_path / f"f{k}.pgm"), rng.integers(60, 250, (6, 5), dtype=np.uint8))
    lights = np.array([[0, 0, 1], [0.6, 0, 0.8], [0, 0.6, 0.8]])
    np.savetxt(tmp_path / "Lights.txt", lights)
    kw = {"intensities": "none", "check_quality": False, "register": False}
    auto = acq.load_capture(tmp_path, lights="auto", **kw)
    np.testing.assert_allclose(auto.lights, lights, atol=1e-6)
    with pytest.raises(ValueError, match="lights='auto' takes the lights file from a folder"):
        acq.load_capture(sorted(tmp_path.glob("f*.pgm")), lights="auto", **kw)
    (tmp_path / "lights_old.txt").write_text("0 0 1\n")
    with pytest.raises(ValueError, match=r"expected one \.txt file .*Lights.txt.*lights_old"):
        acq.load_capture(tmp_path, lights="auto", **kw)
    with pytest.raises(FileNotFoundError, match="lights file not found: .*nope.txt"):
        acq.load_capture(tmp_path, lights=tmp_path / "nope.txt", **kw)


def test_load_capture_divides_out_frame_intensities(tmp_path):
    """Frames of a sphere cap (mean normal on the view axis, no shadows) under flashes of known
    strength: the default ("frontal") recovers them, "none" keeps the frames as read, and the
    capture reports what was used."""
    from helpers import sphere_scene

    scene = sphere_scene(48)
    strength = np.array([1.0, 0.8, 1.1, 1.05, 0.9])
    frames = np.asarray(scene.images) * strength[:, None, None] * 0.8
    paths = []
    for k, f in enumerate(frames):
        paths.append(tmp_path / f"f{k}.png")
        cv2.imwrite(str(paths[-1]), np.round(np.clip(f, 0, 1) * 65535).astype(np.uint16))
    lights = np.asarray(scene.lights)
    plain = acq.load_capture(paths, lights=lights, intensities="none", linearize="none")
    cap = acq.load_capture(paths, lights=lights, linearize="none")
    assert cap.intensity_method == "frontal"
    # The estimate scales with each flash (what the scene alone gives, times the strength).
    alone = np.asarray(jaxps.intensity_estimate(scene.images, lights, method="frontal"))
    e = strength * alone / np.exp(np.mean(np.log(strength * alone)))
    np.testing.assert_allclose(cap.intensities, e, rtol=2e-3)
    np.testing.assert_allclose(cap.gains, 1 / cap.intensities, rtol=1e-6)
    np.testing.assert_allclose(cap.images * cap.intensities[:, None, None], plain.images,
                               rtol=1e-5, atol=1e-7)
    truth = scene.normals
    err = {name: jaxps.evaluate.angular_stats(
        jaxps.photometric_stereo(c.images, c.lights, mask=scene.mask).normals, truth,
        mask=scene.mask)["median_deg"] for name, c in (("plain", plain), ("default", cap))}
    assert err["plain"] > 4 and err["default"] < 0.6 * err["plain"]
    with pytest.raises(ValueError, match="intensities"):
        acq.load_capture(paths, lights=lights, intensities="median")


def test_load_capture_measures_the_flashes_on_a_reference_target(tmp_path):
    """The subject is turned, so "frontal" over it (the default) misreads the flashes; over a
    target facing the camera (`intensity_mask`) they are measured, and the subject's normal
    comes out right."""
    strength = np.array([1.0, 0.8, 1.1, 1.05, 0.9])
    paths, lights, face, target, subject = target_capture(tmp_path, strength)
    kw = dict(lights=lights, mask=face, linearize="none", register=False, check_quality=False)
    default = acq.load_capture(paths, **kw)
    cap = acq.load_capture(paths, intensity_mask=target, **kw)
    expected = strength / np.exp(np.mean(np.log(strength)))
    np.testing.assert_allclose(cap.intensities, expected, rtol=1e-3)
    assert cap.intensity_method == "frontal"
    assert np.max(np.abs(default.intensities / expected - 1)) > 0.02
    np.testing.assert_allclose(  # the same from a mask file, with the target's normal given
        acq.load_capture(paths, intensity_mask=mask_png(tmp_path, target),
                         intensity_normal=[0, 0, 1], **kw).intensities, cap.intensities,
        rtol=1e-6)

    # A target pixel clipped in one frame is left out of every frame's mean.
    clipped = target_capture(tmp_path / "clipped", strength, clip=(1, 0, 0))[0]
    np.testing.assert_allclose(acq.load_capture(clipped, intensity_mask=target, **kw).intensities,
                               cap.intensities, rtol=1e-6)
    blown = target_capture(tmp_path / "blown", strength, clip=(2, slice(None), slice(None)))[0]
    with pytest.raises(ValueError, match="every pixel of the reference target is saturated"):
        acq.load_capture(blown, intensity_mask=target, **kw)

    def error(c):
        n = np.asarray(jaxps.photometric_stereo(c.images, c.lights, mask=face).normals)[face]
        return np.degrees(np.arccos(np.clip(n @ subject, -1, 1))).max()

    assert error(cap) < 0.05 and error(default) > 1.0


def test_reference_target_errors_name_the_argument(tmp_path):
    strength = np.ones(5)
    paths, lights, face, target, _ = target_capture(tmp_path, strength)
    kw = dict(lights=lights, mask=face, linearize="none", register=False, check_quality=False)
    with pytest.raises(ValueError, match="intensity_mask: .* not intensities='semi_calibrated'"):
        acq.load_capture(paths, intensity_mask=target, intensities="semi_calibrated", **kw)
    with pytest.raises(ValueError, match="intensity_normal .* needs intensity_mask"):
        acq.load_capture(paths, intensity_normal=[0, 0, 1], **kw)
    with pytest.raises(ValueError, match="intensity_mask is empty"):
        acq.load_capture(paths, intensity_mask=np.zeros_like(target), **kw)
    with pytest.raises(ValueError, match=r"intensity_mask has shape \(3, 3\)"):
        acq.load_capture(paths, intensity_mask=np.ones((3, 3), bool), **kw)
    with pytest.raises(FileNotFoundError, match="intensity mask not found"):
        acq.load_capture(paths, intensity_mask=tmp_path / "none.png", **kw)
    black = np.zeros_like(target)
    black[-3:, :3] = True  # off the subject and the target: 0 in every frame
    with pytest.raises(ValueError, match="intensity_mask: the reference target's intensities"):
        acq.load_capture(paths, intensity_mask=black, **kw)
    with pytest.raises(ValueError, match="intensity_mask: .*faces away from light"):
        acq.load_capture(paths, intensity_mask=target, intensity_normal=[1, 0, 0], **kw)


def test_target_ratios_carry_the_target_to_the_subject_under_near_lights(tmp_path):
    """Lamps a metre away light a target in the frame's corner, 100 mm behind the subject,
    from other distances than the subject: its flash strengths come out 10% off (measured).
    A board at the subject's place, imaged once with other flashes, gives the ratios that put
    them right, to the 1% that the near lights' spread over the subject leaves."""
    board_paths, lights, board, target = near_target_capture(
        tmp_path / "board", [1.08, 0.97, 1.0, 0.92, 1.04], board=True)
    images, saturated = acq.load_stack(board_paths)
    ratios = acq.target_ratios(images, lights, target, board, saturated=saturated)
    assert ratios.shape == (5,) and ratios.dtype == np.float32
    assert abs(np.exp(np.mean(np.log(ratios))) - 1) < 1e-6
    # Other flashes for the board, the same ratios: they are the lamps', not the shot's.
    other = near_target_capture(tmp_path / "board2", [0.9, 1.1, 1.0, 1.0, 0.95], board=True)[0]
    np.testing.assert_allclose(acq.target_ratios(acq.load_stack(other)[0], lights, target,
                                                 board), ratios, rtol=1e-4)

    strength = np.array([1.0, 0.9, 1.1, 1.05, 0.95])
    paths, lights, subject, target = near_target_capture(tmp_path / "face", strength)
    truth = strength / np.exp(np.mean(np.log(strength)))  # the flashes at the subject's place
    kw = dict(lights=lights, mask=subject, intensity_mask=target, register=False)
    plain = acq.load_capture(paths, **kw)
    fixed = acq.load_capture(paths, intensity_ratios=ratios, **kw)
    assert np.max(np.abs(plain.intensities / truth - 1)) > 0.05  # measured 0.10
    assert np.max(np.abs(fixed.intensities / truth - 1)) < 0.015  # measured 0.0085
    ratio_file = tmp_path / "ratios.txt"
    # with the byte-order mark and CRLF line ends of a file saved by Windows Notepad
    ratio_file.write_text("\ufeff# per light\n" + "".join(f"{r:.9f}  # f{k}.png\n"
                                                           for k, r in enumerate(ratios)),
                          encoding="utf-8", newline="\r\n")
    np.testing.assert_allclose(acq.load_capture(paths, intensity_ratios=ratio_file,
                                                **kw).intensities, fixed.intensities,
                               rtol=1e-6)

    # A frame the checks drop takes its ratio with it: the others keep theirs.
    black = list(paths)
    black[2] = tmp_path / "black.png"
    import cv2

    cv2.imwrite(str(black[2]), np.zeros((48, 64), np.uint16))
    four = acq.load_capture(black, intensity_ratios=ratios, **kw)
    assert four.dropped == ("black.png",)
    keep = [0, 1, 3, 4]
    truth4 = strength[keep] / np.exp(np.mean(np.log(strength[keep])))
    assert np.max(np.abs(four.intensities / truth4 - 1)) < 0.015


def test_target_ratio_errors_name_the_argument(tmp_path):
    paths, lights, subject, target = near_target_capture(tmp_path, np.ones(5))
    kw = dict(lights=lights, mask=subject, register=False)
    with pytest.raises(ValueError, match="intensity_ratios .* need intensity_mask"):
        acq.load_capture(paths, intensity_ratios=np.ones(5), **kw)
    with pytest.raises(ValueError, match=r"intensity_ratios: 5 frames need 5 ratios"):
        acq.load_capture(paths, intensity_mask=target, intensity_ratios=np.ones(4), **kw)
    with pytest.raises(ValueError, match="finite and positive"):
        acq.load_capture(paths, intensity_mask=target, intensity_ratios=[1, 1, 0, 1, 1], **kw)
    (tmp_path / "bad.txt").write_text("1\n1\nx\n1\n1\n")
    with pytest.raises(ValueError, match=r"intensity_ratios \(.*bad.txt\): not a list"):
        acq.load_capture(paths, intensity_mask=target, intensity_ratios=tmp_path / "bad.txt",
                         **kw)
    with pytest.raises(FileNotFoundError, match="intensity ratios not found"):
        acq.load_capture(paths, intensity_mask=target, intensity_ratios=tmp_path / "no.txt",
                         **kw)
    images = acq.load_stack(paths)[0]
    with pytest.raises(ValueError, match="subject: no pixel"):
        acq.target_ratios(images, lights, target, np.zeros_like(subject))
    with pytest.raises(ValueError, match=r"target has shape \(3, 3\)"):
        acq.target_ratios(images, lights, np.ones((3, 3), bool), subject)
    with pytest.raises(ValueError, match="target: .*faces away"):
        acq.target_ratios(images, lights, target, subject, target_normal=[1, 0, 0])


def test_equalize_mean():
    rng = np.random.default_rng(0)
    base = rng.uniform(0.2, 0.8, (8, 8)).astype(np.float32)
    stack = np.stack([base * g for g in (0.8, 1.0, 1.2)])
    eq, gains = acq.equalize_mean(stack)
    np.testing.assert_allclose(gains, [1 / 0.8, 1.0, 1 / 1.2], rtol=1e-5)
    np.testing.assert_allclose(eq[0], eq[2], rtol=1e-5)
    with pytest.raises(ValueError, match="zero mean"):
        acq.equalize_mean(np.stack([base, 0 * base, base]))


def test_yale_capture_with_names_face_and_mask(data):
    folder = data / "yaleb" / "yaleB01"
    names = ["A+000E+00", "A+025E+00", "A-025E+00", "A+000E+20", "A+000E-20"]
    paths = [folder / f"yaleB01_P00{n}.pgm" for n in names]
    cap = acq.load_capture(paths, yale_names=True, ambient=folder / "yaleB01_P00_Ambient.pgm",
                           crop_face=True, mask="auto")
    np.testing.assert_allclose(cap.lights, jaxps.lights_from_angles([0, 25, -25, 0, 0],
                                                                    [0, 0, 0, 20, -20]))
    t, l, h, w = cap.crop
    # The cropped Yale B frames are nearly all face: the box must cover most of the frame.
    assert h * w > 0.6 * 192 * 168 and cap.images.shape[1:] == (h, w)
    assert 0.6 < cap.mask.mean() <= 1.0


def test_a_lit_frame_given_as_the_ambient_is_an_error(data):
    """An ambient-only frame is darker than the lit frames but for noise; a lit frame given in
    its place (a wrong file name) is brighter than them over much of the face, and subtracting
    it would leave each frame the difference of two lights, solved as if it were one."""
    from jaxps.acquisition._capture import _AMBIENT_FRACTION, _below_ambient

    names = ["A+000E+00", "A+025E+00", "A-025E+00", "A+000E+20", "A+000E-20"]
    right, wrong = [], []
    for subject in ("yaleB01", "yaleB02", "yaleB03", "yaleB04", "yaleB05"):
        folder = data / "yaleb" / subject
        ambient = acq.read_image(folder / f"{subject}_P00_Ambient.pgm")
        every = np.stack([acq.read_image(p) for p in sorted(folder.glob(f"{subject}_P00A*.pgm"))])
        right.append(_below_ambient(every, ambient)[0].max())
        cross = np.stack([acq.read_image(folder / f"{subject}_P00{n}.pgm") for n in names])
        right.append(_below_ambient(cross, ambient)[0].max())
        for k in range(5):
            wrong.append(np.median(_below_ambient(np.delete(cross, k, 0), cross[k])[0]))
    # Measured: at most 0.25% of any frame's pixels with the true ambient frame (all 64 frames
    # of a subject, or its five cross frames); 14-58% of the median frame's with a cross frame.
    assert max(right) < 0.003 < _AMBIENT_FRACTION < 0.13 < min(wrong)
    folder = data / "yaleb" / "yaleB03"
    paths = [folder / f"yaleB03_P00{n}.pgm" for n in names]
    with pytest.raises(ValueError, match=r"ambient frame .*A\+000E\+20.pgm is brighter.*lit frame"):
        acq.load_capture(paths, yale_names=True, ambient=paths[3])


def test_a_lit_frame_given_as_the_ambient_is_an_error_on_a_synthetic_face(tmp_path):
    """Away from the shared data: a rendered face under five scanner lights over room light,
    with sensor noise; its true ambient frame passes, a lit frame in its place does not."""
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(96),
                                         jaxps.synthetic.scanner_lights(20.0))
    rng = np.random.default_rng(1)
    room = 0.05 + 0.02 * rng.uniform(size=scene.images.shape[1:])
    paths = []
    for k, img in enumerate(scene.images):
        noisy = img + room + rng.normal(0, 0.004, img.shape)
        paths.append(tmp_path / f"f{k}.png")
        cv2.imwrite(str(paths[-1]), np.round(np.clip(noisy, 0, 1) * 65535).astype(np.uint16))
    ambient = room + rng.normal(0, 0.004, room.shape)
    cv2.imwrite(str(tmp_path / "ambient.png"),
                np.round(np.clip(ambient, 0, 1) * 65535).astype(np.uint16))
    kw = {"lights": scene.lights, "intensities": "none", "register": False}
    cap = acq.load_capture(paths, ambient=tmp_path / "ambient.png", **kw)
    assert cap.images.shape == scene.images.shape
    for k in range(5):
        with pytest.raises(ValueError, match=f"ambient frame .*f{k}.png is brighter"):
            acq.load_capture(paths, ambient=paths[k], **kw)


def test_an_inverted_mask_is_named_in_a_warning(tmp_path, data, caplog):
    """A mask whose object is black (or another capture's): most of its pixels are dark.
    psm's masks: 5.4-7.6% dark in the mean frame as given, 100% inverted, 26-45% swapped
    (below the warning's 50%); a rendered face (no shared data): 0% and 100%
    (`benchmarks/input_checks.py`)."""
    import logging

    from jaxps.acquisition._capture import _dark_in_mask

    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(96),
                                         jaxps.synthetic.scanner_lights(20.0))
    paths = []
    for k, img in enumerate(np.asarray(scene.images)):
        paths.append(tmp_path / f"f{k}.png")
        cv2.imwrite(str(paths[-1]), np.round(img * 65535).astype(np.uint16))
    face = np.asarray(scene.mask)
    caplog.set_level(logging.WARNING, logger="jaxps")
    acq.load_capture(paths, lights=scene.lights, mask=face)
    assert "mask" not in caplog.text
    # Inside the inverted mask every frame is black: the frame check then stops the load, and
    # its error, like the warning before it, names the mask first (the thirtieth session;
    # before, the error said only "only 0 of 5 frames passed").
    with pytest.raises(ValueError, match="only 0 of 5 frames passed") as err:
        acq.load_capture(paths, lights=scene.lights, mask=~face)
    assert str(err.value).startswith("mask: 100% of the mask's pixels are dark")
    assert "100% of the mask's pixels are dark" in caplog.text
    assert "is the mask inverted" in caplog.text
    masks = {o: jaxps.load_psm(data / "psm" / o)[1] > 0.5 for o in ("cat", "owl")}
    for obj, other in (("cat", "owl"), ("owl", "cat")):
        images = jaxps.load_psm(data / "psm" / obj)[0]
        right, inverted = _dark_in_mask(images, masks[obj]), _dark_in_mask(images, ~masks[obj])
        assert right[0] < 0.1 and right[1] < 0.01, obj
        assert inverted[0] > 0.99 and inverted[1] > 0.99, obj
        assert 0.2 < _dark_in_mask(images, masks[other])[0] < 0.5, obj


def test_face_detection_on_padded_tight_crop(data):
    img = acq.read_image(data / "yaleb" / "yaleB02" / "yaleB02_P00A+000E+00.pgm")
    box = acq.detect_face(img)
    assert box is not None
    t, l, h, w = box
    # The box contains the image centre (the nose), not a cheek off to one side.
    assert t < 96 < t + h and l < 84 < l + w
    assert acq.detect_face(np.zeros((100, 100), np.float32)) is None
    # A few dead (NaN) pixels leave the face where it was; before, they made the whole
    # stretched image NaN and the cascade found nothing.
    dead = img.copy()
    dead[::37, ::41] = np.nan
    got = acq.detect_face(dead)
    assert got is not None and np.abs(np.subtract(got, box)).max() <= 3, (got, box)


def test_face_detection_and_crop_reject_bad_arguments():
    img = np.zeros((60, 50), np.float32)
    for kwargs, match in (({"pad": -0.1}, "pad must be"), ({"min_size": 0}, "min_size must"),
                          ({"min_size": 2.5}, "min_size must")):
        with pytest.raises(ValueError, match=match):
            acq.detect_face(img, **kwargs)
    with pytest.raises(ValueError, match=r"image must be a non-empty \(H, W\)"):
        acq.detect_face(img[0])  # OpenCV's own error before
    stack = np.arange(2 * 6 * 5, dtype=np.float32).reshape(2, 6, 5)
    np.testing.assert_array_equal(acq.crop(stack, (1, 2, 3, 2), axis=1), stack[:, 1:4, 2:4])
    np.testing.assert_array_equal(acq.crop(stack[0], (0, 0, 6, 5)), stack[0])
    # A box over an edge, or with no pixels, raises instead of returning a smaller crop.
    for box in ((4, 0, 3, 5), (0, -1, 2, 2), (1, 1, 0, 2), (1, 1, -2, 2)):
        with pytest.raises(ValueError, match="does not lie inside the image's 6 x 5 pixels"):
            acq.crop(stack, box, axis=1)
    with pytest.raises(ValueError, match="two image axes"):
        acq.crop(stack, (0, 0, 1, 1), axis=2)
    with pytest.raises(ValueError, match="threshold must be a number, 'otsu' or None"):
        acq.mask_from_intensity(stack, threshold="auto")
    with pytest.raises(ValueError, match="threshold must be finite"):
        acq.mask_from_intensity(stack, threshold=float("nan"))


def test_psm_capture_colour_linear_with_mask(data):
    folder = data / "psm" / "cat"
    cap = acq.load_capture(folder, lights=data / "psm" / "lights.txt",
                           mask=folder / "cat.mask.png", intensities="none")
    assert cap.images.shape == (12, 340, 512, 3)
    assert cap.names[:3] == ("cat.0.png", "cat.1.png", "cat.2.png")
    assert cap.names[-1] == "cat.11.png"
    raw = cv2.imread(str(folder / "cat.0.png"))[..., ::-1] / 255
    np.testing.assert_allclose(cap.images[0], np.where(raw <= 0.04045, raw / 12.92,
                                                       ((raw + 0.055) / 1.055) ** 2.4), atol=1e-5)


def test_capture_errors(tmp_path, data):
    folder = data / "yaleb" / "yaleB01"
    with pytest.raises(ValueError, match="Yale B light"):
        acq.load_capture([folder / "yaleB01_P00_Ambient.pgm"] * 3, yale_names=True)
    with pytest.raises(ValueError, match=r"3 frames but 12 lights in .*psm.lights\.txt"):
        acq.load_capture(sorted(folder.glob("*A+0*.pgm"))[:3], lights=data / "psm" / "lights.txt")
    cv2.imwrite(str(tmp_path / "m.png"), np.ones((5, 5), np.uint8))
    with pytest.raises(ValueError, match="m.png has shape"):
        acq.load_capture(sorted(folder.glob("*A+0*.pgm"))[:3], mask=tmp_path / "m.png")
    with pytest.raises(ValueError, match="empty list"):
        acq.load_capture([])
    # a bad option is named before any file is read (these files do not exist)
    with pytest.raises(ValueError, match="intensities must be one of"):
        acq.load_capture([tmp_path / "missing.png"] * 3, intensities="median")


def test_srgb_decoding_matches_colour_science():
    import colour

    from jaxps.acquisition._files import srgb_to_linear

    v = np.linspace(0, 1, 1001, dtype=np.float32)
    np.testing.assert_allclose(srgb_to_linear(v), colour.cctf_decoding(v, function="sRGB"),
                               rtol=1e-6, atol=1e-7)
    # and its inverse, which `jaxps relight` writes sRGB frames' relit images with
    from jaxps.acquisition._files import linear_to_srgb

    np.testing.assert_allclose(linear_to_srgb(v), colour.cctf_encoding(v, function="sRGB"),
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(v)), v, atol=1e-6)


def test_bucket_box_grows_about_the_centre_within_the_image():
    # 100x90 at (50, 60) in 480x640 -> 128x128, centred: 14 rows and 19 columns added before.
    assert acq.bucket_box((50, 60, 100, 90), (480, 640)) == (36, 41, 128, 128)
    # At the top-left edge the grown box is shifted inward; past the image it is the image.
    assert acq.bucket_box((0, 3, 100, 90), (480, 640)) == (0, 0, 128, 128)
    assert acq.bucket_box((5, 600, 140, 30), (150, 640)) == (0, 576, 150, 64)
    # Already a multiple, or multiple=1: unchanged.
    assert acq.bucket_box((7, 9, 128, 64), (480, 640)) == (7, 9, 128, 64)
    assert acq.bucket_box((7, 9, 101, 77), (480, 640), multiple=1) == (7, 9, 101, 77)
    with pytest.raises(ValueError, match="multiple"):
        acq.bucket_box((0, 0, 10, 10), (20, 20), multiple=0)


def test_face_crops_of_different_sizes_share_one_shape(data):
    """Yale B subjects' face boxes differ; grown to multiples of 64 they share shapes."""
    folder = data / "yaleb"
    shapes, raw = set(), set()
    for subject in ("yaleB01", "yaleB02", "yaleB03"):
        img = acq.read_image(folder / subject / f"{subject}_P00A+000E+00.pgm")
        box = acq.detect_face(img)
        raw.add(box[2:])
        t, l, h, w = acq.bucket_box(box, img.shape)
        assert t <= box[0] and l <= box[1] and t + h >= box[0] + box[2] and l + w >= box[1] + box[3]
        shapes.add((h, w))
    assert len(shapes) < len(raw)
