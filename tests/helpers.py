"""Shared test helpers: synthetic scenes and a dtype-aware tolerance."""

import numpy as np

import jaxps


def tol(dtype) -> float:
    return {np.dtype(np.float32): 1e-4, np.dtype(np.float64): 1e-9}[np.dtype(dtype)]


def face_scene(h=96, lights=None, noise=0.0, seed=0):
    import jax

    surface = jaxps.synthetic.face_like(h)
    lights = jaxps.synthetic.scanner_lights(20.0) if lights is None else lights
    return jaxps.synthetic.render_scene(surface, lights, noise=noise,
                                        key=jax.random.key(seed) if noise else None)


def sphere_scene(h=96, lights=None):
    surface = jaxps.synthetic.sphere(h, max_zenith_deg=60.0)
    lights = jaxps.synthetic.scanner_lights(20.0) if lights is None else lights
    return jaxps.synthetic.render_scene(surface, lights)


def assert_results_equal(res, want, label=""):
    """The five arrays of a `PSResult` equal `want`'s, to the bit."""
    for name, got, expected in zip(jaxps.PSResult._fields, res[:5], want):
        np.testing.assert_array_equal(got, expected, err_msg=f"{label}: {name}")


def assert_reuses_dropped_results(solve, expected, last=None):
    """The reuse of kept results (`core/_kept.py`), for `solve(i, **kw)` of five stacks with
    `expected` arrays: a result still held is never written, one dropped is (its normals'
    buffer is reused), and the buffer of which a numpy view is left is not; every result
    equals `expected`. `last`: keyword arguments of the fifth call. Returns the fourth and
    fifth."""
    jaxps.release_batch_outputs()
    first = solve(0)
    pointer = first.normals.unsafe_buffer_pointer()
    second = solve(1)  # `first` is held: fresh buffers
    assert second.normals.unsafe_buffer_pointer() != pointer
    del first
    third = solve(2)  # into the buffers of `first`, which nothing else holds
    assert third.normals.unsafe_buffer_pointer() == pointer
    assert_results_equal(second, expected[1], "stack 1")
    assert_results_equal(third, expected[2], "stack 2")
    view = np.asarray(second.albedo)  # holds `second.albedo` (through a memoryview)
    viewed, held = second.albedo.unsafe_buffer_pointer(), third.normals.unsafe_buffer_pointer()
    del second
    fourth = solve(3)
    # Neither the viewed buffer nor the held result is written. Where `second`'s other buffers
    # went is not checked: one CI run (of 7710569) found `fourth.normals` at the address that
    # `second.normals` had, with the view intact. Why was not found (not reproduced in
    # isolation or in three files run together); XLA declines to donate a buffer a view holds.
    assert fourth.albedo.unsafe_buffer_pointer() != viewed
    assert fourth.normals.unsafe_buffer_pointer() != held
    np.testing.assert_array_equal(view, expected[1][1])
    pointer = third.normals.unsafe_buffer_pointer()
    del third
    fifth = solve(4, **(last or {}))  # into the dropped `third`
    assert fifth.normals.unsafe_buffer_pointer() == pointer
    assert_results_equal(fourth, expected[3], "stack 3")
    assert_results_equal(fifth, expected[4], "stack 4")
    return fourth, fifth


def target_capture(tmp_path, strength, clip=None):
    """16-bit frames of a flat subject turned 10 degrees (albedo 0.7) and, in a corner, a flat
    matte target facing the camera (albedo 0.5), under flashes of `strength`; their paths,
    the lights, the subject's mask, the target's mask and the subject's normal. `clip`:
    (frame, row, column) of the target set to full scale (saturated) in that frame."""
    import cv2

    tmp_path.mkdir(parents=True, exist_ok=True)
    lights = np.asarray(jaxps.synthetic.scanner_lights(20.0), np.float64)
    turn = np.radians(10.0)
    subject = np.array([np.sin(turn), 0.0, np.cos(turn)])
    face, target = np.zeros((24, 32), bool), np.zeros((24, 32), bool)
    face[6:, 10:] = True
    target[:5, :6] = True
    frames = np.zeros((5, 24, 32))
    frames[:, face] = (0.7 * lights @ subject)[:, None]
    frames[:, target] = 0.5 * lights[:, 2:]
    frames = frames * strength[:, None, None]
    if clip is not None:
        frame, rows, cols = clip
        frames[frame, :5, :6][rows, cols] = 1.0
    paths = []
    for k, f in enumerate(frames):
        paths.append(tmp_path / f"f{k}.png")
        cv2.imwrite(str(paths[-1]), np.round(np.clip(f, 0, 1) * 65535).astype(np.uint16))
    return paths, lights, face, target, subject


def near_target_capture(folder, strength, board=False, distance=1000.0, pixel_mm=4.0):
    """16-bit frames of a scanner whose five lamps stand `distance` mm from the subject's
    place, along `scanner_lights(20)`: a flat subject turned 10 degrees (albedo 0.7; with
    `board`, a board facing the camera instead) around the origin, and a matte target facing
    the camera (albedo 0.5) in the top-left corner, 100 mm behind, lit by flashes of
    `strength`. Near lights (`jaxps.near_light_field`, 1 at the origin) light the two from
    different distances. Returns the paths, the lights, the subject's (or board's) mask and
    the target's mask."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    lights = np.asarray(jaxps.synthetic.scanner_lights(20.0), np.float64)
    h, w = 48, 64
    subject, target = np.zeros((h, w), bool), np.zeros((h, w), bool)
    subject[12:40, 18:50] = True
    target[:8, :10] = True
    turn = 0.0 if board else np.radians(10.0)
    normal = np.array([np.sin(turn), 0.0, np.cos(turn)])
    points = np.asarray(jaxps.surface_points(np.zeros((h, w), np.float32), pixel_size=pixel_mm),
                        np.float64)
    points[..., 2] = np.where(target, -100.0, -np.tan(turn) * points[..., 0])
    directions, falloff = (np.asarray(a, np.float64) for a in jaxps.near_light_field(
        distance * lights, points))
    normals = np.where(target[..., None], [0.0, 0.0, 1.0], normal)
    albedo = np.where(target, 0.5, np.where(subject, 0.7, 0.0))
    frames = (np.maximum(np.einsum("khwc,hwc->khw", directions, normals), 0) * falloff
              * albedo * np.asarray(strength, np.float64)[:, None, None])
    paths = []
    for k, f in enumerate(frames):
        paths.append(folder / f"f{k}.png")
        cv2.imwrite(str(paths[-1]), np.round(np.clip(f, 0, 1) * 65535).astype(np.uint16))
    return paths, lights, subject, target


def mask_png(tmp_path, mask):
    """`mask` written as `tmp_path/target_mask.png` (255 inside); its path."""
    import cv2

    path = tmp_path / "target_mask.png"
    cv2.imwrite(str(path), mask.astype(np.uint8) * 255)
    return path


def yale_frames_with_card(frames, ambient, strengths, out):
    """Yale B `frames` (paths) copied to `out` with a matte card (albedo 0.5, facing the camera)
    painted into their 12x12 top-left corner under flashes of `strengths`, and `ambient` with
    that corner 0. Returns the new frame paths, the new ambient path, the card's mask and the
    path of that mask written as a PNG."""
    import pathlib

    import cv2

    card = np.zeros((192, 168), bool)
    card[2:14, 2:14] = True
    paths = []
    for path, e in zip(frames, strengths):
        frame = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        lz = jaxps.lights_from_angles(*jaxps.parse_yale_name(path))[0, 2]
        frame[card] = np.uint8(round(255 * 0.5 * e * float(lz)))
        paths.append(out / pathlib.Path(path).name)
        cv2.imwrite(str(paths[-1]), frame)
    dark = cv2.imread(str(ambient), cv2.IMREAD_UNCHANGED)
    dark[card] = 0
    ambient_path = out / pathlib.Path(ambient).name
    cv2.imwrite(str(ambient_path), dark)
    mask_path = out / "card.png"
    cv2.imwrite(str(mask_path), card.astype(np.uint8) * 255)
    return paths, ambient_path, card, mask_path


def near_face(px=2.0, h=96):
    """The synthetic face (its mean depth at z = 0) under five lamps 1000 mm away, in the
    directions of `scanner_lights(20)` from the origin: `(normals, mask, directions, falloff,
    lights)`, the lamps' per-pixel unit directions `(K, H, W, 3)` and fall-off `(K, H, W)`
    (numpy float64) and their directions from the origin `(K, 3)`."""
    import jax.numpy as jnp

    face = jaxps.synthetic.face_like(h)
    inside = np.asarray(face.mask)
    depth = np.asarray(face.height, np.float64) * px
    points = jaxps.surface_points(jnp.asarray(depth - depth[inside].mean(), jnp.float32),
                                  pixel_size=px)
    lights = np.asarray(jaxps.synthetic.scanner_lights(20.0), np.float64)
    directions, falloff = (np.asarray(a, np.float64)
                           for a in jaxps.near_light_field(1000.0 * lights, points))
    return np.asarray(face.normals, np.float64), inside, directions, falloff, lights


def near_face_files(folder, px=2.0):
    """`near_face` as a Lambertian capture (albedo 0.6) in `folder`: 16-bit PNG frames in
    `face/`, `mask.png`, `positions.txt` (the lamps in mm, with a comment and a count line)
    and `lights.txt` (their directions from the origin). Returns `near_face`'s tuple."""
    import cv2

    normals, inside, directions, falloff, lights = face = near_face(px)
    frames = np.maximum(np.einsum("khwc,hwc->khw", directions, normals), 0) * falloff * 0.6
    (folder / "face").mkdir()
    for k, frame in enumerate(frames * inside):
        cv2.imwrite(str(folder / "face" / f"f{k}.png"),
                    np.round(np.clip(frame, 0, 1) * 65535).astype(np.uint16))
    cv2.imwrite(str(folder / "mask.png"), inside.astype(np.uint8) * 255)
    (folder / "positions.txt").write_text(
        "# lamps, mm\n5\n" + "".join(f"{x} {y} {z}\n" for x, y, z in 1000.0 * lights))
    jaxps.save_lights(folder / "lights.txt", lights)
    return face


def off_centre_face_files(folder, px=2.0):
    """A Lambertian face (albedo 0.6) off the camera axis in a larger frame, under five lamps
    1000 mm away (`scanner_lights(20)` directions from the frame's centre): the 96-pixel face's
    box has its top-left corner at (60, 150) in a 192 x 256 frame, so its centre sits 60
    columns right of and 12 rows below the frame's. Writes 16-bit PNG frames in `face/`,
    `mask.png` (the whole frame's) and `positions.txt` (mm). Returns `(normals of the face,
    the frame's mask, (H0, W0), (top, left, h, w) of the face's box)`."""
    import cv2
    import jax.numpy as jnp

    face = jaxps.synthetic.face_like(96)
    inside = np.asarray(face.mask)
    normals = np.asarray(face.normals, np.float64)
    depth = np.asarray(face.height, np.float64) * px
    depth = depth - depth[inside].mean()
    (h0, w0), (top, left), (h, w) = (192, 256), (60, 150), inside.shape
    rows, cols = np.mgrid[top:top + h, left:left + w]
    points = np.stack([(cols - (w0 - 1) / 2) * px, ((h0 - 1) / 2 - rows) * px, depth], -1)
    positions = 1000.0 * np.asarray(jaxps.synthetic.scanner_lights(20.0), np.float64)
    directions, falloff = (np.asarray(a, np.float64) for a in
                           jaxps.near_light_field(positions, jnp.asarray(points, jnp.float32)))
    frames = np.zeros((len(positions), h0, w0))
    frames[:, top:top + h, left:left + w] = (
        np.maximum(np.einsum("khwc,hwc->khw", directions, normals), 0) * falloff * 0.6 * inside)
    (folder / "face").mkdir()
    for k, frame in enumerate(frames):
        cv2.imwrite(str(folder / "face" / f"f{k}.png"),
                    np.round(np.clip(frame, 0, 1) * 65535).astype(np.uint16))
    full_mask = np.zeros((h0, w0), bool)
    full_mask[top:top + h, left:left + w] = inside
    cv2.imwrite(str(folder / "mask.png"), full_mask.astype(np.uint8) * 255)
    (folder / "positions.txt").write_text("".join(f"{x} {y} {z}\n" for x, y, z in positions))
    return normals, full_mask, (h0, w0), (top, left, h, w)
