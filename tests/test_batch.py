"""Batched photometric stereo: N captures in one call equal N single calls; bad batches fail."""

import csv
import json

import jax
import numpy as np
import pytest

import jaxps
from helpers import assert_results_equal, assert_reuses_dropped_results, face_scene


def _captures(n=3, h=32):
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
    assert batch.normals.shape == (3, 32, 26, 3)
    for i in range(3):
        single = jaxps.photometric_stereo(images[i], lights, mask=masks[i], method=method)
        np.testing.assert_allclose(batch.normals[i], single.normals, atol=2e-5)
        np.testing.assert_allclose(batch.albedo[i], single.albedo, atol=2e-5)
        np.testing.assert_array_equal(batch.status[i], single.status)
        if method == "semi_calibrated":
            np.testing.assert_allclose(batch.info["intensities"][i],
                                       single.info["intensities"], atol=1e-4)


@pytest.mark.parametrize("method", ["barsky", "irls", "sbl"])
def test_loop_solver_batch_on_threads_equals_single_calls(method, monkeypatch):
    """The loop solvers' CPU batch runs captures on threads (`_captures_on_threads`), here 3
    at once; it equals single calls and the jitted `lax.map` path (`vmap_size=1`), with
    per-capture lights, masks and sample masks, colour, and `info` stacked too."""
    from jaxps.ps import _batch

    monkeypatch.setattr(_batch, "cpu_cores", lambda: 3)
    taken, on_threads = [], _batch._captures_on_threads
    monkeypatch.setattr(_batch, "_captures_on_threads",
                        lambda *a: taken.append(a[-2]) or on_threads(*a))
    scenes, images = _captures()
    images = np.stack([images, 0.8 * images], axis=-1)
    lights = np.stack([np.asarray(s.lights) for s in scenes])
    lights[1, :, 0] += 0.02
    masks = np.stack([np.asarray(s.mask) for s in scenes])
    samples = np.ones(images.shape[:4], bool)
    samples[2, 1, ::2] = False
    kw = {"mask": masks, "sample_mask": samples, "method": method}
    batch = jaxps.photometric_stereo_batch(images, lights, **kw)
    mapped = jaxps.photometric_stereo_batch(images, lights, vmap_size=1, **kw)
    assert taken == [method]
    assert batch.albedo.shape == mapped.albedo.shape == (3, 32, 26, 2)
    assert batch.info["steps"].shape == (3, 32, 26)
    for i in range(3):
        single = jaxps.photometric_stereo(images[i], lights[i], mask=masks[i],
                                          sample_mask=samples[i], method=method)
        for ref in (single, jax.tree.map(lambda a, i=i: a[i], mapped)):
            np.testing.assert_array_equal(batch.status[i], ref.status)
            np.testing.assert_array_equal(batch.info["steps"][i], ref.info["steps"])
            np.testing.assert_allclose(batch.normals[i], ref.normals, atol=1e-5)
            np.testing.assert_allclose(batch.albedo[i], ref.albedo, atol=1e-5)
            np.testing.assert_allclose(batch.residual[i], ref.residual, atol=1e-5)


@pytest.mark.parametrize("colour", [False, True])
@pytest.mark.parametrize("dtype", [np.float32, np.float16])
def test_batch_l2_equals_single_calls_with_dropped_samples(colour, dtype):
    """Every L2 output of a batch given as a list, with a shared mask, per-capture sample masks,
    a shadow threshold (dropped samples take the weighted branch), colour and float16 input,
    equals the single call."""
    scenes, images = _captures()
    if colour:
        images = images[..., None] * np.float32([1.0, 0.8, 0.6])
    images = images.astype(dtype)
    lights, mask = scenes[0].lights, np.asarray(scenes[0].mask)
    rng = np.random.default_rng(0)
    sample_mask = rng.random(images.shape[:4]) > 0.05
    opts = {"mask": mask, "sample_mask": sample_mask, "shadow_threshold": 0.05}
    batch = jaxps.photometric_stereo_batch(list(images), lights, **opts)
    assert batch.normals.dtype == dtype and batch.albedo.shape == images.shape[:1] + images.shape[2:]
    for i in range(len(images)):
        single = jaxps.photometric_stereo(images[i], lights, mask=mask,
                                          sample_mask=sample_mask[i], shadow_threshold=0.05)
        for name in ("normals", "albedo", "residual"):
            np.testing.assert_allclose(np.asarray(getattr(batch, name)[i], np.float32),
                                       np.asarray(getattr(single, name), np.float32),
                                       atol=1e-6 if dtype == np.float32 else 2e-3,
                                       err_msg=name)  # float16: lights rounded apart
        np.testing.assert_array_equal(batch.status[i], single.status)
        np.testing.assert_array_equal(batch.n_used[i], single.n_used)
    assert (np.asarray(batch.n_used) < 5).any()  # the weighted branch ran


def test_batch_l2_clean_colour_equals_single_calls():
    """Colour captures that drop no sample (the every-sample-used solve over 15 planes, one
    albedo per channel) equal single calls."""
    scenes, images = _captures()
    images = images[..., None] * np.float32([1.0, 0.8, 0.6])
    lights, mask = scenes[0].lights, np.asarray(scenes[0].mask)
    batch = jaxps.photometric_stereo_batch(images, lights, mask=mask)
    assert (np.asarray(batch.n_used)[:, mask] == 5).all()  # the clean solve, every sample used
    for i in range(len(images)):
        single = jaxps.photometric_stereo(images[i], lights, mask=mask)
        for name in ("normals", "albedo", "residual"):
            np.testing.assert_allclose(getattr(batch, name)[i], getattr(single, name),
                                       atol=1e-6, err_msg=name)
        np.testing.assert_array_equal(batch.status[i], single.status)


def test_batch_l2_per_capture_lights_equals_single_calls():
    """The one-device L2 batch with lights per capture (`(N, K, 3)`, each capture's constants
    along a leading axis) gives the single call's arrays (to float32 rounding: XLA fuses the
    two programs differently), with a capture that needs the weighted solve (a NaN sample)
    between two that do not, which sends the stack through it, from numpy and device input;
    the lax.map path (`vmap_size`) too. Without the NaN, the every-sample-used solve."""
    import jax

    scenes, images = _captures()
    lights = np.stack([np.asarray(scenes[0].lights) * s for s in (1.0, 2.0, 0.5)])
    lights[2, 0] += [0.05, -0.02, 0.0]
    images[1, 3, 5, 7] = np.nan
    mask = np.asarray(scenes[0].mask)
    for stack in (images, jax.device_put(images)):
        batch = jaxps.photometric_stereo_batch(stack, lights, mask=mask)
        for i in range(3):
            single = jaxps.photometric_stereo(images[i], lights[i], mask=mask)
            for name in ("normals", "albedo", "residual"):
                np.testing.assert_allclose(getattr(batch, name)[i], getattr(single, name),
                                           atol=1e-6, err_msg=f"{name}, capture {i}")
            np.testing.assert_array_equal(batch.status[i], single.status)
            np.testing.assert_array_equal(batch.n_used[i], single.n_used)
    assert batch.n_used[1, 5, 7] == 4 and (np.asarray(batch.n_used[0])[mask] == 5).all()
    mapped = jaxps.photometric_stereo_batch(images, lights, mask=mask, vmap_size=1)
    np.testing.assert_allclose(mapped.normals, batch.normals, atol=1e-6)
    np.testing.assert_array_equal(mapped.status, batch.status)
    images[1, 3, 5, 7] = images[0, 3, 5, 7]
    clean = jaxps.photometric_stereo_batch(images, lights, mask=mask)
    for i in range(3):
        single = jaxps.photometric_stereo(images[i], lights[i], mask=mask)
        np.testing.assert_allclose(clean.normals[i], single.normals, atol=1e-6)
        np.testing.assert_array_equal(clean.status[i], single.status)


def test_batch_l2_shared_lights_one_image_equals_single_calls(monkeypatch):
    """Captures that share their lights are solved as one image (`_l2_one_image`): one
    capture with a NaN sample sends the stack through the weighted solve, whose results equal
    the single calls (the clean ones to float32 rounding), from numpy and device input, in
    one chunk or in chunks of 2 (copied into the stacked outputs; given, or by default where
    a program may hold only two captures' pixels), fresh or into `out`."""
    from jaxps.ps import _batch

    scenes, images = _captures()
    images[1, 3, 5, 7] = np.nan
    lights, mask = scenes[0].lights, np.asarray(scenes[0].mask)
    singles = [jaxps.photometric_stereo(images[i], lights, mask=mask) for i in range(3)]
    first = jaxps.photometric_stereo_batch(images, lights, mask=mask)
    runs = {"numpy": first, "device": jaxps.photometric_stereo_batch(
                jax.device_put(images), lights, mask=mask),
            "chunks": jaxps.photometric_stereo_batch(images, lights, mask=mask, chunk=2),
            "chunks, out": jaxps.photometric_stereo_batch(
                images, lights, mask=mask, chunk=2,
                out=jaxps.photometric_stereo_batch(images, lights, mask=mask))}
    monkeypatch.setattr(_batch, "_PIXELS_PER_PROGRAM", 2 * images[0, 0].size)
    written = []
    monkeypatch.setattr(_batch, "_write_block",
                        lambda out, start, res, f=_batch._write_block: written.append(start)
                        or f(out, start, res))
    runs["default chunks"] = jaxps.photometric_stereo_batch(images, lights, mask=mask)
    assert written == [0, 2]
    for run, batch in runs.items():
        for i, single in enumerate(singles):
            for name in ("normals", "albedo", "residual"):
                np.testing.assert_allclose(getattr(batch, name)[i], getattr(single, name),
                                           atol=1e-6, err_msg=f"{run}: {name}, capture {i}")
            np.testing.assert_array_equal(batch.status[i], single.status, err_msg=run)
            np.testing.assert_array_equal(batch.n_used[i], single.n_used, err_msg=run)
    assert first.n_used[1, 5, 7] == 4 and (np.asarray(first.n_used[0])[mask] == 5).all()
    # the flag pass per capture: bit 0 (re-solve) and bit 1 (non-finite) only on capture 1
    x = jax.device_put(images)
    full = np.broadcast_to(mask, (3, *mask.shape))
    thresholds = tuple(np.float32(t) for t in _batch._sample_thresholds())
    np.testing.assert_array_equal(_batch.l2_batch_flags(x, full, None, thresholds), [0, 3, 0])


def test_batch_l2_reuses_out():
    """`out=` takes an earlier result's arrays (donated) and returns this batch's results in
    them, equal to a fresh batch; a result of the wrong shape, one already donated, or `out`
    with another method is a ValueError that names `out`."""
    scenes, images = _captures()
    lights, mask = scenes[0].lights, np.asarray(scenes[0].mask)
    first = jaxps.photometric_stereo_batch(images, lights, mask=mask)
    first_fresh = jaxps.photometric_stereo_batch(images, lights, mask=mask)
    fresh = jaxps.photometric_stereo_batch(images[::-1].copy(), lights, mask=mask)
    pointer = first.normals.unsafe_buffer_pointer()
    again = jaxps.photometric_stereo_batch(images[::-1].copy(), lights, mask=mask, out=first)
    assert again.normals.unsafe_buffer_pointer() == pointer  # written in place
    assert first.normals.is_deleted()
    for name in ("normals", "albedo", "status", "n_used", "residual"):
        np.testing.assert_array_equal(getattr(again, name), getattr(fresh, name), err_msg=name)
    with pytest.raises(ValueError, match="out.normals was already donated"):
        jaxps.photometric_stereo_batch(images, lights, mask=mask, out=first)
    with pytest.raises(ValueError, match=r"out.normals must be a JAX array \(2, 32, 26, 3\)"):
        jaxps.photometric_stereo_batch(images[:2], lights, mask=mask, out=again)
    with pytest.raises(ValueError, match="out: reusing"):
        jaxps.photometric_stereo_batch(images, lights, mask=mask, method="l1", out=again)
    with pytest.raises(ValueError, match="out must be the PSResult"):
        jaxps.photometric_stereo_batch(images, lights, mask=mask, out=tuple(again))
    # float64 input is float32 in JAX without x64: outputs and `out` follow, without a warning
    wide = jaxps.photometric_stereo_batch(images.astype(np.float64), lights, mask=mask, out=again)
    assert wide.normals.dtype == np.float32
    np.testing.assert_allclose(wide.normals, first_fresh.normals, atol=1e-6)


def test_batch_l2_writes_into_a_result_the_caller_dropped(monkeypatch):
    """An L2 batch keeps its latest two results; a later batch of the same shapes writes into
    one the caller has dropped (in one program or in chunks), never into one still held, nor
    into one of which a numpy view is left. `JAXPS_BATCH_KEEP_BYTES=0` keeps nothing, nor does
    a free-threaded interpreter; a bad value is a ValueError naming the variable."""
    from jaxps.core import _kept
    from jaxps.ps import _batch

    monkeypatch.delenv("JAXPS_BATCH_KEEP_BYTES", raising=False)
    scenes, images = _captures()
    lights, mask = scenes[0].lights, np.asarray(scenes[0].mask)
    stacks = [images * s for s in (1.0, 0.8, 0.6, 0.5, 0.4)]

    def batch(i, **kw):
        return jaxps.photometric_stereo_batch(stacks[i], lights, mask=mask, **kw)

    expected = [[np.array(a) for a in batch(i)[:5]] for i in range(len(stacks))]

    def check(res, i):
        assert_results_equal(res, expected[i], f"stack {i}")

    assert_reuses_dropped_results(batch, expected, last={"chunk": 2})  # chunks: into `third`

    with monkeypatch.context() as m:  # a free-threaded interpreter: nothing kept
        m.setattr(_kept, "_REFCOUNTS_EXACT", False)
        check(batch(4), 4)
        assert _batch._BATCH == []
    batch(4)
    assert len(_batch._BATCH) == 1
    monkeypatch.setenv("JAXPS_BATCH_KEEP_BYTES", "0")
    check(batch(4), 4)
    assert _batch._BATCH == []
    monkeypatch.setenv("JAXPS_BATCH_KEEP_BYTES", "1GB")
    with pytest.raises(ValueError, match="JAXPS_BATCH_KEEP_BYTES must be a whole number"):
        batch(4)


@pytest.mark.parametrize("colour", [False, True])
def test_batch_l2_weighted_writes_its_planes_into_kept_buffers(colour, monkeypatch):
    """A batch that drops samples solves in two programs; the first one's packed planes are
    kept and the next such batch of that shape writes into them, in one program, with `out=`
    (all five outputs in place) and in chunks of two sizes. Every result equals the same batch
    computed with nothing kept, to the bit; `JAXPS_BATCH_KEEP_BYTES=0` keeps no planes."""
    from jaxps.ps import _batch

    monkeypatch.delenv("JAXPS_BATCH_KEEP_BYTES", raising=False)
    scenes, images = _captures()
    if colour:
        images = images[..., None] * np.float32([1.0, 0.8, 0.6])
    lights, mask = scenes[0].lights, np.asarray(scenes[0].mask)
    stacks = [images * s for s in (1.0, 0.8, 0.6, 0.5)]
    shadow = float(np.percentile(images[:, :, mask], 10))

    def batch(i, **kw):
        return jaxps.photometric_stereo_batch(stacks[i], lights, mask=mask,
                                              shadow_threshold=shadow, **kw)

    monkeypatch.setenv("JAXPS_BATCH_KEEP_BYTES", "0")
    expected = [[np.array(a) for a in batch(i)[:5]] for i in range(len(stacks))]
    assert _batch._SCRATCH == []
    monkeypatch.delenv("JAXPS_BATCH_KEEP_BYTES")
    assert (expected[0][3] < 5).any() and (expected[0][3] == 5).any()  # some dropped

    def check(res, i):
        assert_results_equal(res, expected[i], f"stack {i}")

    def planes():
        return [a.unsafe_buffer_pointer() for a in _batch._SCRATCH[0][1]]

    _batch.release_batch_outputs()
    first = batch(0)
    kept = planes()
    assert len(kept) == (3 if colour else 2)  # b_x + i b_y, b_z + i misfit, colour f_0 + i f_1
    check(first, 0)
    second = batch(1)
    assert planes() == kept
    check(second, 1)
    pointers = [a.unsafe_buffer_pointer() for a in first[:5]]
    third = batch(2, out=first)  # every output in place, n_used (the first program's) too
    assert [a.unsafe_buffer_pointer() for a in third[:5]] == pointers
    assert planes() == kept
    check(third, 2)
    check(batch(3, chunk=2), 3)  # chunks of 2 and 1: planes of their own shapes, both kept

    def all_planes():
        return sorted(a.unsafe_buffer_pointer() for _, planes in _batch._SCRATCH for a in planes)

    assert len(_batch._SCRATCH) == 2
    chunked = all_planes()
    check(batch(2, chunk=2), 2)
    assert all_planes() == chunked
    check(batch(3), 3)
    monkeypatch.setenv("JAXPS_BATCH_KEEP_BYTES", "0")
    check(batch(3), 3)
    assert _batch._SCRATCH == []


def test_batch_l2_copies_unaligned_stacks_into_one_kept_buffer(monkeypatch):
    """An unaligned numpy stack is copied into aligned memory for XLA-CPU; the next batch of
    that shape copies into the same buffer, and every batch equals its single calls (no stale
    data from the stack before). `JAXPS_BATCH_KEEP_BYTES=0` keeps no buffer."""
    from jaxps.ps import _batch

    monkeypatch.delenv("JAXPS_BATCH_KEEP_BYTES", raising=False)
    scenes, images = _captures()
    lights, mask = scenes[0].lights, np.asarray(scenes[0].mask)
    raw = np.empty(images.size + 1, np.float32)  # one float in: 4 bytes off any alignment
    stack = raw[1:].reshape(images.shape) if raw[1:].ctypes.data % 64 else raw[:-1].reshape(
        images.shape)
    assert stack.ctypes.data % 64 and not stack.flags.owndata
    _batch.release_batch_outputs()
    buffers = []
    for scale in (1.0, 0.7, 0.4):
        stack[...] = images * scale
        res = jaxps.photometric_stereo_batch(stack, lights, mask=mask)
        buffers.append(_batch._STAGE[0].ctypes.data)
        for i in range(len(images)):
            single = jaxps.photometric_stereo(images[i] * scale, lights, mask=mask)
            np.testing.assert_allclose(res.albedo[i], single.albedo, rtol=1e-5, atol=1e-6)
            np.testing.assert_array_equal(res.status[i], single.status)
        np.testing.assert_array_equal(stack, images * scale)  # the input is left as it was
    assert buffers[0] == buffers[1] == buffers[2]
    monkeypatch.setenv("JAXPS_BATCH_KEEP_BYTES", "0")
    jaxps.photometric_stereo_batch(stack, lights, mask=mask)
    assert _batch._STAGE == []


@pytest.mark.parametrize("vmap_size", [None, 1])
def test_batch_chunks_and_list_input(vmap_size):
    """Chunks of 2 of a list of 3 captures equal the whole batch; with `vmap_size` the L2 batch
    takes the jitted `lax.map` path, whose chunks are solved apart and concatenated."""
    scenes, images = _captures()
    lights = np.stack([scenes[0].lights] * 3)
    whole = jaxps.photometric_stereo_batch(images, lights)
    chunked = jaxps.photometric_stereo_batch(list(images), lights, chunk=2, vmap_size=vmap_size)
    assert chunked.normals.shape == whole.normals.shape
    np.testing.assert_allclose(whole.normals, chunked.normals, atol=1e-6)
    np.testing.assert_array_equal(whole.status, chunked.status)


def test_vmap_of_l2_keeps_one_solve_and_matches_single_calls():
    # Under `jax.vmap` the traced solve's predicate is reduced over the captures, so the
    # program keeps a real `cond` (one solve runs, not both under a select), and a capture
    # that drops samples sends the batch through the weighted solve, which must still give
    # each capture its single call's result. Reverse-mode gradients go through it too.
    s = face_scene(40)
    clean = np.asarray(s.images)
    dropping = clean.copy()
    dropping[1, :12] = 1.0  # saturated samples
    stack = np.stack([clean, dropping])

    def solve(x):
        return jaxps.photometric_stereo(x, s.lights, mask=s.mask)

    batched = jax.jit(jax.vmap(solve))
    assert "conditional" in batched.lower(stack).compile().as_text()
    out = batched(stack)
    for i, x in enumerate(stack):
        single = solve(x)
        np.testing.assert_array_equal(out.status[i], single.status)
        np.testing.assert_array_equal(out.n_used[i], single.n_used)
        np.testing.assert_allclose(out.normals[i], single.normals, atol=1e-5)
        np.testing.assert_allclose(out.albedo[i], single.albedo, rtol=1e-5, atol=1e-6)
    assert (np.asarray(out.n_used[1])[np.asarray(s.mask)] < 5).any()

    def loss(x):
        return jax.jit(solve)(x).albedo.sum()

    grads = jax.grad(lambda xs: jax.vmap(loss)(xs).sum())(stack)
    for i, x in enumerate(stack):
        np.testing.assert_allclose(grads[i], jax.grad(loss)(x), rtol=1e-4, atol=1e-6)


def test_vmap_gives_a_shared_mask_one_copy_per_capture():
    # Under `jax.vmap` over the images, L2's shared mask becomes an (N, H, W) array (read by
    # the solve's loops as a per-capture plane); a mask that is itself batched, or images
    # that are not, leave it as it is.
    from jaxps.ps._l2 import _mask_per_capture

    mask = np.random.default_rng(0).random((6, 7)) > 0.5
    probes = np.zeros(3, bool)
    copies = jax.vmap(_mask_per_capture, in_axes=(None, 0))(mask, probes)
    assert copies.shape == (3, 6, 7)
    np.testing.assert_array_equal(copies, np.broadcast_to(mask, (3, 6, 7)))
    masks = np.stack([mask, ~mask, mask])
    np.testing.assert_array_equal(jax.vmap(_mask_per_capture)(masks, probes), masks)
    kept = jax.vmap(lambda p: _mask_per_capture(mask, False) & p, in_axes=0)(probes)
    np.testing.assert_array_equal(kept, np.zeros((3, 6, 7), bool))
    np.testing.assert_array_equal(_mask_per_capture(mask, False), mask)


def test_batch_rejects_different_sizes():
    _, images = _captures(2)
    with pytest.raises(ValueError, match="capture 1 has shape"):
        jaxps.photometric_stereo_batch([images[0], images[1][:, :24]],
                                       jaxps.synthetic.scanner_lights())


def test_batch_rejects_bad_lights_and_mask():
    _, images = _captures(2)
    with pytest.raises(ValueError, match="lights"):
        jaxps.photometric_stereo_batch(images, np.ones((4, 3)))
    with pytest.raises(ValueError, match="mask"):
        jaxps.photometric_stereo_batch(images, jaxps.synthetic.scanner_lights(),
                                       mask=np.ones((3, 3), bool))


def test_batch_rejects_images_on_a_0_to_255_scale():
    _, images = _captures(2)
    with pytest.raises(ValueError, match=r"images must be in \[0, 1\]"):
        jaxps.photometric_stereo_batch(np.asarray(images) * 255, jaxps.synthetic.scanner_lights())
    res = jaxps.photometric_stereo_batch(np.asarray(images) * 255,
                                         jaxps.synthetic.scanner_lights(), saturation=255)
    ref = jaxps.photometric_stereo_batch(np.asarray(images), jaxps.synthetic.scanner_lights())
    np.testing.assert_array_equal(res.status, ref.status)


@pytest.mark.parametrize("shape", [(0, 5, 8, 8), (2, 5, 0, 8)])
def test_batch_rejects_empty_stacks(shape):
    with pytest.raises(ValueError, match="at least one capture, pixel and channel"):
        jaxps.photometric_stereo_batch(np.zeros(shape, np.float32),
                                       jaxps.synthetic.scanner_lights())


def test_summary_table():
    text = jaxps.summary_table([{"capture": "a", "ok_%": 99.123}, {"capture": "bb", "ok_%": 5.0}])
    lines = text.splitlines()
    assert lines[0].split() == ["capture", "ok_%"]
    assert lines[2].split() == ["a", "99.1"]
    assert lines[3].split() == ["bb", "5"]


def test_cli_many_folders(tmp_path, capsys):
    import cv2

    from jaxps.cli import main

    scene = face_scene(48)
    lights = np.asarray(scene.lights)
    folders = []
    for name, corrupt in (("a", False), ("b", True), ("c", None)):
        folder = tmp_path / name
        folder.mkdir()
        folders.append(str(folder))
        if corrupt is None:
            continue  # an empty folder: reported as an error, not skipped
        frames = np.asarray(scene.images).copy()
        if corrupt:
            frames[2, 1::2] = 0.0  # interlace-like combing
        for i, f in enumerate(frames):
            cv2.imwrite(str(folder / f"f{i}.pgm"), np.round(f * 255).astype(np.uint8))
    light_file = tmp_path / "lights.txt"
    light_file.write_text("5\n" + "\n".join(" ".join(map(str, r)) for r in lights))
    rc = main(["reconstruct", *folders, "--lights", str(light_file), "--check-quality",
               "--out", str(tmp_path / "out")])
    out = capsys.readouterr().out
    assert rc == 1
    lines = {ln.split()[0]: ln for ln in out.splitlines() if ln[:1] in "abc"}
    assert "f2.pgm (row/interlace" in lines["b"]
    assert "no frame files" in lines["c"]
    assert (tmp_path / "out" / "a" / "normals.png").is_file()
    assert not (tmp_path / "out" / "c").exists()
    # each capture gets one capture's files, the same as a run on its folder alone (until the
    # twenty-seventh session: normals, albedo and status only, with no height or mesh)
    assert main(["reconstruct", folders[0], "--lights", str(light_file), "--out",
                 str(tmp_path / "single")]) == 0
    for name in ("albedo.png", "height.npy", "mesh.ply", "preview.png", "status.npy"):
        assert (tmp_path / "out" / "a" / name).is_file(), name
    height, alone = (np.load(tmp_path / run / "height.npy") for run in ("out/a", "single"))
    np.testing.assert_allclose(height, alone, atol=1e-5 * np.ptp(alone))
    assert np.ptp(height) > 5  # a face, 48 px high
    # the printed table is also OUT/summary.csv, one line per capture, same columns as JSON
    with open(tmp_path / "out" / "summary.csv", newline="") as f:
        table = list(csv.DictReader(f))
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())["captures"]
    assert [r["capture"] for r in table] == ["a", "b", "c"]
    assert list(table[0]) == list(summary[0])
    assert "no frame files" in table[2]["error"] and table[0]["error"] == ""
    assert float(table[0]["ok_%"]) == pytest.approx(summary[0]["ok_%"])
    # A method no capture can use is the caller's error, not a row per capture's.
    with pytest.raises(ValueError, match="method must be one of"):
        jaxps.reconstruct_many(folders, method="L2", lights=str(light_file), progress=False)
    # --shadow-threshold reaches every capture's solve (it was ignored for several folders)
    _, rows = jaxps.reconstruct_many(folders[:1], lights=str(light_file), progress=False,
                                     shadow_threshold=0.3)
    assert rows[0]["ok_pixels"] < summary[0]["ok_pixels"]
    capsys.readouterr()
    assert main(["reconstruct", *folders[:2], "--lights", str(light_file), "--report", "--out",
                 str(tmp_path / "with_report")]) == 2
    assert "--report takes one capture" in capsys.readouterr().err
    assert not (tmp_path / "with_report").exists()


def test_many_captures_drop_frames_before_the_intensities(tmp_path):
    """A capture in `reconstruct_many` is solved as `load_capture` + `photometric_stereo`
    solve it alone, also when a frame is dropped. Until the thirtieth session the many-capture
    path dropped the frame only after the intensities were estimated with it: the albedo
    differed by a common factor, and with semi-calibrated intensities the normals too."""
    import cv2

    from jaxps.acquisition import load_capture

    scene = face_scene(48)
    frames = np.asarray(scene.images).copy()
    frames[2, 1::2] = 0.0  # interlace-like combing
    for i, f in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"f{i}.pgm"), np.round(f * 255).astype(np.uint8))
    lights = np.asarray(scene.lights)
    for intensities in ("frontal", "semi_calibrated"):
        (many,), (row,) = jaxps.reconstruct_many([tmp_path], lights=lights, progress=False,
                                                 intensities=intensities)
        cap = load_capture(tmp_path, lights=lights, intensities=intensities)
        alone = jaxps.photometric_stereo(cap.images, cap.lights, mask=cap.mask,
                                         sample_mask=~cap.saturated)
        assert cap.dropped == ("f2.pgm",) and row["dropped"].startswith("f2.pgm (row/interlace")
        assert row["frames"] == 5 and [f.name for f in cap.frame_check.flagged] == ["f2.pgm"]
        ok = np.asarray(alone.status) == jaxps.Status.OK
        np.testing.assert_allclose(np.asarray(many.albedo)[ok], np.asarray(alone.albedo)[ok],
                                   atol=1e-5)
        assert float(np.max(np.asarray(jaxps.angular_error(many.normals, alone.normals))[ok])) \
            < 0.1


def test_many_captures_report_motion(tmp_path):
    """The `motion` column: the largest shift between a capture's frames, and whether it was
    undone (up to 4 px in these 96 px frames) or left. One frame moved by 2 and by 6 columns; the frame check is
    off, since it drops a frame of this face on black moved by 2 px as inconsistent."""
    import cv2

    scene = face_scene(96, noise=0.01)
    for name, shift in (("still", 0), ("moved", 2), ("far", 6)):
        (tmp_path / name).mkdir()
        for i, f in enumerate(np.asarray(scene.images)):
            f = np.roll(f, shift, axis=1) if i == 3 else f
            cv2.imwrite(str(tmp_path / name / f"f{i}.png"),
                        np.round(np.clip(f, 0, 1) * 65535).astype(np.uint16))
    _, rows = jaxps.reconstruct_many([tmp_path / n for n in ("still", "moved", "far")],
                                     lights=np.asarray(scene.lights), progress=False,
                                     check_quality=False)
    still, moved, far = (r["motion"] for r in rows)
    assert still.endswith(" px") and float(still.split()[0]) < 0.5, still
    assert moved.endswith(" px, undone") and abs(float(moved.split()[0]) - 2) < 0.2, moved
    assert far.endswith(" px, left") and abs(float(far.split()[0]) - 6) < 0.2, far
    assert "motion" in jaxps.summary_table(rows).splitlines()[0]
    _, rows = jaxps.reconstruct_many([tmp_path / "moved"], lights=np.asarray(scene.lights),
                                     progress=False, check_quality=False, register=False)
    assert rows[0]["motion"] == ""  # not measured


def test_batch_sharded_over_two_host_devices():
    """The sharded path (several devices) equals single calls; two CPU devices are forced in a
    fresh interpreter, since the device count is fixed when JAX starts."""
    import os
    import subprocess
    import sys

    from conftest import ROOT

    script = """
import sys
import numpy as np, jax, jaxps
from helpers import face_scene
assert jax.device_count() == 2, jax.devices()
sc = face_scene(32)
imgs = np.stack([np.asarray(face_scene(32, noise=0.01, seed=i).images) for i in range(3)])
b = jaxps.photometric_stereo_batch(imgs, sc.lights, mask=sc.mask)
for i in range(3):
    s = jaxps.photometric_stereo(imgs[i], sc.lights, mask=sc.mask)
    np.testing.assert_allclose(b.normals[i], s.normals, atol=2e-5)
    np.testing.assert_array_equal(b.status[i], s.status)
print("OK")
"""
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2",
           "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT / "tests")])}
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0 and "OK" in proc.stdout, proc.stdout + proc.stderr[-2000:]


def test_cli_many_folders_each_subtracts_its_own_ambient(tmp_path):
    # One folder per capture, each with its own ambient frame: `--ambient auto` subtracts each
    # folder's own, so captures under 0.05 and 0.30 of ambient light give the same normals.
    import cv2

    from jaxps.cli import main
    from jaxps.report._writers import read_normal_map

    scene = face_scene(48)
    light_file = tmp_path / "lights.txt"
    light_file.write_text("5\n" + "\n".join(" ".join(map(str, r)) for r in
                                              np.asarray(scene.lights)))
    folders = []
    for name, level in (("low", 0.05), ("high", 0.30)):
        folder = tmp_path / name
        folder.mkdir()
        folders.append(str(folder))
        for i, f in enumerate(np.asarray(scene.images)):
            cv2.imwrite(str(folder / f"f{i}.png"),
                        np.round(np.clip(f + level, 0, 1) * 65535).astype(np.uint16))
        cv2.imwrite(str(folder / "ambient.png"),
                    np.full(scene.mask.shape, round(level * 65535), np.uint16))
    argv = ["reconstruct", *folders, "--lights", str(light_file), "--intensities", "none",
            "--no-register", "--out"]
    assert main([*argv, str(tmp_path / "auto"), "--ambient", "auto"]) == 0
    assert main([*argv, str(tmp_path / "as_read")]) == 0
    mask = np.asarray(scene.mask)

    def error(run, name):
        normals = read_normal_map(tmp_path / run / name / "normals.png")
        return float(np.median(np.asarray(jaxps.angular_error(normals, scene.normals))[mask]))

    assert error("auto", "low") < 0.5 and error("auto", "high") < 0.5
    assert error("as_read", "high") > 5  # the ambient light left in bends the normals


def test_cli_many_folders_each_takes_its_own_lights(tmp_path, capsys):
    # Two rigs (lamps at 20 and 30 degrees), one folder each with its own lights.txt:
    # `--lights auto` solves each with its own; one shared file would bend the other's normals.
    import cv2

    from jaxps.cli import main
    from jaxps.report._writers import read_normal_map

    folders, scenes = [], {}
    for name, zenith in (("rig20", 20.0), ("rig30", 30.0)):
        scenes[name] = scene = face_scene(48, lights=jaxps.synthetic.scanner_lights(zenith))
        folder = tmp_path / name
        folder.mkdir()
        folders.append(str(folder))
        for i, f in enumerate(np.asarray(scene.images)):
            cv2.imwrite(str(folder / f"f{i}.png"), np.round(f * 65535).astype(np.uint16))
        np.savetxt(folder / "lights.txt", np.asarray(scene.lights))
    argv = ["reconstruct", *folders, "--intensities", "none", "--no-register", "--out"]
    assert main([*argv, str(tmp_path / "auto"), "--lights", "auto"]) == 0
    assert main([*argv, str(tmp_path / "shared"), "--lights",
                 str(tmp_path / "rig20" / "lights.txt")]) == 0

    def error(run, name):
        normals = read_normal_map(tmp_path / run / name / "normals.png")
        err = np.asarray(jaxps.angular_error(normals, scenes[name].normals))
        return float(np.median(err[np.asarray(scenes[name].mask)]))

    assert error("auto", "rig20") < 0.1 and error("auto", "rig30") < 0.1
    assert error("shared", "rig30") > 3
    # a folder without one is named in its row; the others are solved
    (tmp_path / "rig30" / "lights.txt").rename(tmp_path / "rig30" / "calibration.dat")
    capsys.readouterr()
    assert main([*argv, str(tmp_path / "missing"), "--lights", "auto"]) == 1
    assert "expected one .txt file whose name contains 'light'" in capsys.readouterr().out
