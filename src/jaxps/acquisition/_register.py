"""Motion between the frames of a capture: measure it, and register the frames when it is small.

A walk-through scanner fires its lights a few milliseconds apart; a subject who moves between
frames smears every normal. `estimate_shifts` measures each frame's translation against a
reference frame by phase correlation (Kuglin & Hines 1975) on the face region, refined to
sub-pixel accuracy by the upsampled-DFT search of Guizar-Sicairos, Thurman & Fienup, "Efficient
subpixel image registration algorithms", Opt. Lett. 33(2), 2008, with phase normalisation
(whitened spectra), which keeps the albedo detail and discards most of the low-frequency shading
that differs between lights. The search is scikit-image's `phase_cross_correlation` rewritten
as one jitted JAX function over all frames: the reference spectrum is computed once, the
upsampled search runs in two stages (1/10 px, then 1/`upsample`), FFT sizes are trimmed to
2-3-5-smooth lengths, and the spectra are float32 (a few 1/100 px from scikit-image's float64 on
Yale B frames; a test checks it). Written with JAX rather than `scipy.fft`, whose import alone
took 0.32 s of every command-line run. Shifts are applied by cubic-spline interpolation.

Tried and dropped: correlating each frame with a rendering of the current Lambertian fit under its
own light (to remove the shading difference) made synthetic shifts worse (0.02 px -> 0.1 px)."""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
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

    **Returns:** frames of the same shape and dtype.
    """
    arr = np.asarray(frames)
    shifts = np.asarray(shifts, np.float64)
    if arr.ndim not in (3, 4) or shifts.shape != (arr.shape[0], 2):
        raise ValueError(f"frames (K, H, W[, C]) and shifts (K, 2) expected, got {arr.shape} "
                         f"and {shifts.shape}")
    if not np.all(np.isfinite(shifts)):
        raise ValueError("shifts must be finite")
    from scipy import ndimage  # SciPy and scikit-image load when first used

    out = np.empty_like(arr)
    for i, s in enumerate(shifts):
        full = (s[0], s[1]) + (0.0,) * (arr.ndim - 3)
        out[i] = ndimage.shift(arr[i], full, order=3, mode="nearest")
    return jnp.asarray(out)


WORK_PIXELS = 2**21  # larger correlation boxes are block-averaged down to about this size


def _window(h, w):
    return np.outer(np.hanning(h), np.hanning(w)).astype(np.float32)


def _prepare(img, box, win, factor):
    """The box of `img`, block-averaged by `factor`, mean removed, Hann-windowed (float32)."""
    y0, y1, x0, x1 = box
    crop = np.asarray(img[y0:y1, x0:x1], np.float32)
    hh, ww = win.shape
    crop = crop[:hh * factor, :ww * factor].reshape(hh, factor, ww, factor).mean(axis=(1, 3))
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


def _dft_rows(n, size, upsample, offset):
    """`(size, n)` rows $e^{2\\pi i (j - o) f_m}$, $f_m$ = `np.fft.fftfreq(n, upsample)`, $o$ the
    integer `offset`: the exponent is reduced modulo a whole turn in int32 first, so float32
    keeps it exact where $(j - o) f_m$ runs to 1e5 turns."""
    m = jnp.arange(n, dtype=jnp.int32)
    m = jnp.where(m < (n + 1) // 2, m, m - n)
    turns = (jnp.arange(size, dtype=jnp.int32)[:, None] - offset) * m[None, :] % (n * upsample)
    return jnp.exp(1j * ((2 * np.pi / (n * upsample)) * turns.astype(jnp.float32))
                   .astype(jnp.complex64))


def _refine(cross, peak, upsample, span):
    """The peak of $|\\mathcal{F}^{-1}$ `cross`$|$ on a grid `upsample` times finer, within
    `span` pixels of `peak`: the matrix-product DFT of Guizar-Sicairos et al. (2008), as in
    scikit-image's `_upsampled_dft`."""
    h, w = cross.shape
    size = int(np.ceil(upsample * span))
    centre = size // 2
    offset = centre - jnp.round(peak * upsample).astype(jnp.int32)
    fine = jnp.abs(_dft_rows(h, size, upsample, offset[0]) @ cross
                   @ _dft_rows(w, size, upsample, offset[1]).T)
    at = jnp.stack(jnp.unravel_index(jnp.argmax(fine), fine.shape)) - centre
    return jnp.round(peak * upsample) / upsample + at / upsample


@functools.partial(jax.jit, static_argnames=("upsample", "phase"))
def _search(refs, frames, upsample, phase):
    """(dy, dx) `(K, 2)` that move each prepared frame onto its prepared reference (scikit-image's
    sign): the integer peak of the (whitened) cross-correlation, then the upsampled search in
    two stages (1/10 pixel over 1.5 pixels, then 1/`upsample` over 0.15): the same peak as one
    search at 1/`upsample` over 1.5 pixels, with 100x fewer samples."""
    cross = jnp.fft.fft2(refs) * jnp.conj(jnp.fft.fft2(frames))
    if phase:
        cross = cross / jnp.maximum(jnp.abs(cross), jnp.finfo(jnp.float32).eps).astype(cross.dtype)
    shape = jnp.asarray(frames.shape[1:])

    def one(cross):
        corr = jnp.abs(jnp.fft.ifft2(cross))
        peak = jnp.stack(jnp.unravel_index(jnp.argmax(corr), corr.shape))
        peak = jnp.where(peak > shape // 2, peak - shape, peak).astype(jnp.float32)
        span = 1.5
        for up in sorted({min(upsample, 10), upsample}):
            if up > 1:
                peak, span = _refine(cross, peak, up, span), 1.5 / up
        return peak

    return jax.vmap(one)(cross)


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
    - `upsample`: sub-pixel resolution is 1/`upsample` pixel.

    **Returns:** `(K, 2)` float64 (dy, dx): frame k's content sits at reference position plus
    (dy, dx).
    """
    grey = np.asarray(frames, np.float64)
    if grey.ndim == 4:
        grey = grey.mean(axis=-1)
    if grey.ndim != 3:
        raise ValueError(f"frames must be (K, H, W[, C]), got {np.shape(frames)}")
    k, h, w = grey.shape
    sel = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    if sel.shape != (h, w) or not sel.any():
        raise ValueError(f"mask must be a non-empty (H, W) = {(h, w)} array")
    box = _box(sel, pad=4)
    if isinstance(reference, (int, np.integer)):
        if not 0 <= reference < k:
            raise ValueError(f"reference must index a frame in [0, {k}), got {reference}")
        refs = np.broadcast_to(grey[reference], grey.shape)
    else:
        refs = np.asarray(reference, np.float64)
        if refs.shape != grey.shape:
            raise ValueError(f"reference images must have shape {grey.shape}, got {refs.shape}")
    # Large boxes are block-averaged to about WORK_PIXELS: the motion worth undoing is pixels,
    # and the correlation of a 1 MP face needs no more detail than that. Sides are trimmed to
    # fast FFT lengths.
    factor = max(1, round(np.sqrt((box[1] - box[0]) * (box[3] - box[2]) / WORK_PIXELS)))
    win = _window(*(_fast_len((box[j + 1] - box[j]) // factor) for j in (0, 2)))
    frames_p = np.stack([_prepare(g, box, win, factor) for g in grey])
    if isinstance(reference, (int, np.integer)):
        refs_p = frames_p[reference][None]  # one spectrum, broadcast against every frame
    else:
        refs_p = np.stack([_prepare(r, box, win, factor) for r in refs])
    shifts = -factor * np.asarray(_search(refs_p, frames_p, int(upsample),
                                          normalization == "phase"), np.float64)
    blank = ~(np.any(frames_p, axis=(1, 2)) & np.any(refs_p, axis=(1, 2)))
    shifts[blank] = 0.0  # nothing to correlate
    return shifts


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
    - `frames`: `(K, H, W)` or `(K, H, W, C)` floating point.
    - `mask`: `(H, W)` face region (default: whole frame).
    - `reference`: the frame that stays put.
    - `max_shift`: larger motion is reported but not corrected (`registered=False`): a subject
      who moved that far has probably also turned, which a translation cannot undo.
    - `upsample`: sub-pixel resolution 1/`upsample`.

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
