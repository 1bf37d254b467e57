"""Motion between the frames of a capture: measure it, and register the frames when it is small.

A walk-through scanner fires its lights a few milliseconds apart; a subject who moves between
frames smears every normal. `estimate_shifts` measures each frame's translation against a
reference frame by phase correlation (Kuglin & Hines 1975) on the face region, refined to
sub-pixel accuracy by the upsampled-DFT search of Guizar-Sicairos, Thurman & Fienup, "Efficient
subpixel image registration algorithms", Opt. Lett. 33(2), 2008, with phase normalisation
(whitened spectra), which keeps the albedo detail and discards most of the low-frequency shading
that differs between lights. The search is scikit-image's `phase_cross_correlation` rewritten
for speed: the reference spectrum is computed once, the upsampled search runs in two stages
(1/10 px, then 1/`upsample`), and FFT sizes are trimmed to 2-3-5-smooth lengths. It uses
`numpy.fft`, which needs no import beyond numpy: `import scipy.fft` alone took 0.32 s of every
command-line run, and a jitted JAX version paid tracing and lowering in every new process.
Shifts are applied by cubic-spline interpolation (`scipy.ndimage.shift`'s, written out in numpy).

Tried and dropped: correlating each frame with a rendering of the current Lambertian fit under its
own light (to remove the shading difference) made synthetic shifts worse (0.02 px -> 0.1 px)."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

__all__ = ["Registration", "estimate_shifts", "register_frames", "shift_frames"]


class Registration(NamedTuple):
    """Result of `register_frames`.

    - `frames`: `(K, H, W[, C])` frames moved onto the reference (unchanged if not registered).
    - `shifts`: `(K, 2)` measured (dy, dx) in pixels of each frame relative to the reference
      (a frame content moved down/right has positive dy/dx); the reference row is 0.
    - `registered`: whether the frames were moved (all shifts within `max_shift`).
    """

    frames: Float[Array, "K H W *C"]
    shifts: np.ndarray
    registered: bool


def shift_frames(
    frames: Float[ArrayLike, "K H W *C"], shifts: Float[ArrayLike, "K 2"]
) -> Float[Array, "K H W *C"]:
    """Move each frame by `(dy, dx)` pixels: cubic-spline interpolation, edges repeated.

    **Arguments:**
    - `frames`: `(K, H, W)` or `(K, H, W, C)`.
    - `shifts`: `(K, 2)` finite (dy, dx) per frame, each smaller than the frame
      (`|dy| < H`, `|dx| < W`); positive moves the content down/right.

    Non-finite pixels stay local: every output pixel whose spline samples include one is NaN,
    the rest are interpolated as if the pixel held the mean of its finite neighbours (a frame
    with zero shift is returned as is).

    **Returns:** frames of the same shape and dtype.
    """
    arr = np.asarray(frames)
    shifts = np.asarray(shifts, np.float64)
    if arr.ndim not in (3, 4) or shifts.shape != (arr.shape[0], 2):
        raise ValueError(f"frames (K, H, W[, C]) and shifts (K, 2) expected, got {arr.shape} "
                         f"and {shifts.shape}")
    if not np.all(np.isfinite(shifts)):
        raise ValueError("shifts must be finite")
    too_far = np.any(np.abs(shifts) >= arr.shape[1:3], axis=1)
    if too_far.any():
        k = int(np.argmax(too_far))
        raise ValueError(f"shifts must be smaller than the frame (H, W) = {arr.shape[1:3]}, "
                         f"got {shifts[k].tolist()} for frame {k}")
    return jnp.asarray(_shift(arr, shifts))


def _shift(arr, shifts, order=3):
    """`shift_frames` on numpy: each `(H, W[, C])` frame of `arr` moved by its `(dy, dx)`.

    Spline interpolation of `order` 3 (images) or 1 (masks) with the edge repeated outside:
    `scipy.ndimage.shift(frame, (dy, dx), order=order, mode="nearest")` written out (the same
    12-sample edge padding before the prefilter, so equal to float32 rounding; more for shifts
    over 10 px, whose samples would fall outside it), because importing `scipy.ndimage` took
    0.45 s of every command-line run that moved its frames. Non-finite pixels: see
    `shift_frames`.
    """
    out = np.empty_like(arr)
    floating = np.issubdtype(arr.dtype, np.floating)
    for i, (dy, dx) in enumerate(shifts):
        if dy == 0 and dx == 0:
            out[i] = arr[i]
            continue
        p = max(SPLINE_PAD, int(np.ceil(max(abs(dy), abs(dx)))) + 2)
        pad = [(p, p)] * 2 + [(0, 0)] * (arr.ndim - 3)
        frame = np.asarray(arr[i], np.float64)
        bad = None
        if floating and not np.isfinite(frame.sum()):  # the sum: all finite, tested cheaply
            # The prefilter would spread a NaN over the whole frame: fill it in first.
            bad = ~np.isfinite(frame)
            frame = _fill(frame, bad)
        c = np.pad(frame, pad, mode="edge")
        if order == 3:
            c = _spline_coefficients(_spline_coefficients(c, 0), 1)
        moved = _move(_move(c, dy, 0, order, p), dx, 1, order, p)
        if bad is not None:
            # Output pixels whose interpolation taps hold a filled pixel are unknown. Along an
            # axis with an integer shift the spline reproduces its samples: one tap only.
            b = np.pad(bad.astype(np.float64), pad, mode="edge")
            b = _move(_move(b, dy, 0, order if dy % 1 else 1, p), dx, 1,
                      order if dx % 1 else 1, p)
            moved[b > 0] = np.nan
        if np.issubdtype(arr.dtype, np.integer):  # rounded and clipped, as scipy does
            info = np.iinfo(arr.dtype)
            moved = np.clip(np.rint(moved), info.min, info.max)
        out[i] = moved
    return out


def _fill(frame, bad):
    """`frame` (H, W[, C]) with each `bad` pixel set to the mean of the good ones among its
    3 x 3 neighbours, or to the frame's (channel's) good mean where it has none."""
    h, w = frame.shape[:2]
    pad = [(1, 1)] * 2 + [(0, 0)] * (frame.ndim - 2)
    good = np.pad(~bad, pad).astype(np.float64)
    vals = np.pad(np.where(bad, 0.0, frame), pad)
    near = lambda a: sum(a[i:i + h, j:j + w] for i in range(3) for j in range(3))
    total, count = near(vals), near(good)
    mean = vals.sum(axis=(0, 1)) / np.maximum(good.sum(axis=(0, 1)), 1)
    return np.where(bad, np.where(count > 0, total / np.maximum(count, 1), mean), frame)


SPLINE_PAD = 12  # edge samples scipy.ndimage pads before its prefilter (mode "nearest")
_POLE = np.sqrt(3.0) - 2.0  # the cubic B-spline prefilter's pole


def _spline_coefficients(x, axis):
    """Cubic B-spline coefficients of `x` along `axis`: the causal and anticausal recursions of
    Unser, "Splines: a perfect fit for signal and image processing", IEEE SPM 16(6), 1999,
    mirror boundary (as scipy.ndimage; after the edge padding it barely matters)."""
    x = np.moveaxis(x, axis, 0).copy()
    n, z = x.shape[0], _POLE
    m = min(n, 30)  # the causal start's mirror sum, truncated where |z|^m < 1e-17
    x[0] = np.tensordot(z ** np.arange(m), x[:m], 1)
    for k in range(1, n):
        x[k] += z * x[k - 1]
    x[n - 1] = z / (z * z - 1) * (x[n - 1] + z * x[n - 2])
    for k in range(n - 2, -1, -1):
        x[k] = z * (x[k + 1] - x[k])
    return np.moveaxis(6.0 * x, 0, axis)


def _move(c, s, axis, order, pad=SPLINE_PAD):
    """Samples `c` (padded by `pad` along `axis`) at `y - s` for each output `y`: the
    order-3 B-spline of coefficients `c`, or linear interpolation of samples `c` (order 1)."""
    start = int(np.floor(-s))
    f = -s - start
    if order == 1:
        taps = ((start, 1 - f), (start + 1, f))
    else:
        g = 1 - f
        taps = ((start - 1, g**3 / 6), (start, 2 / 3 - f * f + f**3 / 2),
                (start + 1, 2 / 3 - g * g + g**3 / 2), (start + 2, f**3 / 6))
    n = c.shape[axis] - 2 * pad
    out = 0.0
    for offset, weight in taps:
        if weight != 0:
            index = [slice(None)] * c.ndim
            index[axis] = slice(pad + offset, pad + offset + n)
            out = out + weight * c[tuple(index)]
    return out


WORK_PIXELS = 2**21  # larger correlation boxes are block-averaged down to about this size


def _window(h, w):
    return np.outer(np.hanning(h), np.hanning(w)).astype(np.float32)


def _prepare(img, box, win, factor):
    """The box of `img`, block-averaged by `factor`, mean removed, Hann-windowed (float32).
    Non-finite pixels are filled in from their finite neighbours (`_fill`): one NaN would
    make the whole spectrum NaN."""
    y0, _, x0, _ = box
    hh, ww = win.shape
    crop = np.asarray(img[y0:y0 + hh * factor, x0:x0 + ww * factor], np.float32)
    if not np.isfinite(crop.sum()):  # the sum: all finite, tested cheaply
        crop = _fill(crop, ~np.isfinite(crop)).astype(np.float32)
    if factor > 1:  # strided sums: numpy's mean over a reshaped block axis was 4x slower
        crop = sum(crop[i::factor, j::factor] for i in range(factor) for j in range(factor))
    crop = crop - crop[win > 0].mean()
    return crop * win


def _box(mask, pad):
    ys, xs = np.nonzero(mask)
    h, w = mask.shape
    return (max(ys.min() - pad, 0), min(ys.max() + pad + 1, h),
            max(xs.min() - pad, 0), min(xs.max() + pad + 1, w))


def _fast_len(n):
    """The largest length <= n whose prime factors are 2, 3 and 5 (FFTs of it are fastest)."""
    while True:
        m = n
        for p in (2, 3, 5):
            while m % p == 0:
                m //= p
        if m == 1:
            return n
        n -= 1


def _upsampled_dft(spec, size, upsample, offsets):
    """`size` x `size` samples of the inverse DFT of `spec` on a grid `upsample` times finer,
    starting at `offsets` (fine-grid units): the matrix-product DFT of Guizar-Sicairos et al.
    (2008), as in scikit-image's `_upsampled_dft` (two small matrix products instead of a
    zero-padded FFT)."""
    rows, cols = (np.exp(2j * np.pi * np.outer(np.arange(size) - offsets[a],
                                               np.fft.fftfreq(spec.shape[a], upsample)))
                  .astype(np.complex64) for a in (0, 1))
    return rows @ spec @ cols.T


def _phase_shift(ref_spec, img_spec, upsample, normalization):
    """(dy, dx) that moves `img` onto `ref` (scikit-image's sign), from their spectra: the
    integer peak of the (whitened) cross-correlation, then the upsampled-DFT search around it,
    in two stages (1/10 pixel over 1.5 pixels, then 1/`upsample` over 0.15): the same peak as
    one search at 1/`upsample` over 1.5 pixels, with 100x fewer samples."""
    cross = ref_spec * np.conj(img_spec)
    if normalization == "phase":
        cross = cross / np.maximum(np.abs(cross), np.finfo(np.float32).eps)
    corr = np.abs(np.fft.ifft2(cross))
    shape = np.array(corr.shape)
    peak = np.array(np.unravel_index(np.argmax(corr), corr.shape), np.float64)
    wrap = peak > shape // 2
    peak[wrap] -= shape[wrap]
    span = 1.5
    for up in sorted({min(upsample, 10), upsample}):
        if up <= 1:
            continue
        peak = np.round(peak * up) / up
        size = int(np.ceil(up * span))
        centre = np.fix(size / 2.0)
        fine = np.abs(_upsampled_dft(cross, size, up, centre - peak * up))
        peak = peak + (np.array(np.unravel_index(np.argmax(fine), fine.shape)) - centre) / up
        span = 1.5 / up
    return peak


NORMALIZATIONS = ("phase", None)  # as scikit-image's phase_cross_correlation


def estimate_shifts(
    frames: Float[ArrayLike, "K H W *C"],
    *,
    reference: int | Float[ArrayLike, "K H W"] = 0,
    mask: Bool[ArrayLike, "H W"] | None = None,
    upsample: int = 100,
    normalization: str | None = "phase",
) -> np.ndarray:
    """Translation of each frame against a reference by windowed sub-pixel phase correlation.

    **Arguments:**
    - `frames`: `(K, H, W)` or `(K, H, W, C)` (the channel mean is used).
    - `reference`: index of the reference frame, or `(K, H, W)` per-frame reference images
      (e.g. renderings under each frame's own light).
    - `mask`: `(H, W)` region to correlate (the face); its bounding box plus a margin is
      windowed with a Hann window. Default: the whole frame.
    - `upsample`: sub-pixel resolution is 1/`upsample` pixel (a positive integer).
    - `normalization`: `"phase"` whitens the cross-power spectrum (phase correlation); `None`
      correlates the plain spectra.

    Non-finite pixels (in `frames` or `reference`) are left out of the correlation: each is
    replaced by the mean of its finite 3 x 3 neighbours (the frame's finite mean where it has
    none), which adds no edge for the whitened spectrum to lock onto.

    **Returns:** `(K, 2)` float64 (dy, dx): frame k's content sits at reference position plus
    (dy, dx).
    """
    from threadpoolctl import threadpool_limits

    if isinstance(upsample, bool) or not isinstance(upsample, (int, np.integer)) \
            or upsample < 1:
        raise ValueError(f"upsample must be a positive integer, got {upsample!r}")
    if normalization not in NORMALIZATIONS:
        raise ValueError(f"normalization must be one of {NORMALIZATIONS}, got {normalization!r}")
    grey = np.asarray(frames, np.float32)
    if grey.ndim == 4:
        grey = grey.mean(axis=-1)
    if grey.ndim != 3:
        raise ValueError(f"frames must be (K, H, W[, C]), got {np.shape(frames)}")
    k, h, w = grey.shape
    sel = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    if sel.shape != (h, w) or not sel.any():
        raise ValueError(f"mask must be a non-empty (H, W) = {(h, w)} array")
    box = _box(sel, pad=4)
    shared = isinstance(reference, (int, np.integer))
    if shared:
        if not 0 <= reference < k:
            raise ValueError(f"reference must index a frame in [0, {k}), got {reference}")
        refs = np.broadcast_to(grey[reference], grey.shape)
    else:
        refs = np.asarray(reference, np.float32)
        if refs.shape != grey.shape:
            raise ValueError(f"reference images must have shape {grey.shape}, got {refs.shape}")
    # Boxes over WORK_PIXELS are block-averaged down to about that size: the motion worth undoing
    # is pixels, and a 16 MP face needs no more detail than 2 MP to show it. Sides are trimmed to
    # fast FFT lengths; the FFTs take complex input (numpy's real-input fft2 was 2-7x slower).
    factor = max(1, round(np.sqrt((box[1] - box[0]) * (box[3] - box[2]) / WORK_PIXELS)))
    win = _window(*(_fast_len((box[j + 1] - box[j]) // factor) for j in (0, 2)))
    # numpy's unscaled FFTs (norm="backward" forward, "forward" inverse) ran 2-3x slower than
    # its scaled ones (numpy 2.4, complex64: 9.7 against 4.4 ms at 900x750, 22.8 against 8.7 ms
    # at 1024x1280; `benchmarks/bench_io.py`), so the transform scales by 1/n and the window
    # by n: the same spectrum, to rounding.
    win_n = win * np.float32(win.size)
    spectrum = lambda img: np.fft.fft2(_prepare(img, box, win_n, factor).astype(np.complex64),
                                       norm="forward")
    ref_spec = spectrum(refs[0]) if shared else None

    def shift(i):
        a = ref_spec if shared else spectrum(refs[i])
        b = spectrum(grey[i])
        if not (np.any(a) and np.any(b)):
            return np.zeros(2)
        return -factor * _phase_shift(a, b, upsample, normalization)

    # Frames on a thread each: numpy's FFTs release the GIL. The search's small matrix products
    # run on one BLAS thread: a multi-threaded BLAS on a busy machine made five 192x168 frames
    # take 0.16 s instead of 0.01 s.
    with threadpool_limits(1, user_api="blas"), \
            ThreadPoolExecutor(min(k, os.cpu_count() or 1)) as pool:
        return np.array(list(pool.map(shift, range(k))), np.float64).reshape(k, 2)


def register_frames(
    frames: Float[ArrayLike, "K H W *C"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    reference: int = 0,
    max_shift: float = 4.0,
    upsample: int = 100,
) -> Registration:
    """Measure inter-frame motion and, when every shift is within `max_shift` pixels, undo it.

    **Arguments:**
    - `frames`: `(K, H, W)` or `(K, H, W, C)` floating point. Non-finite pixels take no part in
      the measurement and, when the frames are moved, make the few output pixels that
      interpolate them NaN (see `shift_frames`).
    - `mask`: `(H, W)` face region (default: whole frame).
    - `reference`: the frame that stays put.
    - `max_shift`: larger motion is reported but not corrected (`registered=False`): a subject
      who moved that far has probably also turned, which a translation cannot undo.
    - `upsample`: sub-pixel resolution 1/`upsample` (a positive integer).

    **Returns:** a `Registration`.
    """
    frames = jnp.asarray(frames)
    if not jnp.issubdtype(frames.dtype, jnp.floating):
        raise ValueError(f"frames must be floating point, got {frames.dtype}")
    if not (np.isfinite(max_shift) and max_shift >= 0):
        raise ValueError(f"max_shift must be finite and >= 0, got {max_shift!r}")
    shifts = estimate_shifts(frames, reference=reference, mask=mask, upsample=upsample)
    ok = bool(np.max(np.abs(shifts)) <= max_shift)
    out = shift_frames(frames, -shifts) if ok else frames
    return Registration(out, shifts, ok)
