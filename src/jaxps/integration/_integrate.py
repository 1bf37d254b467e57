"""Normal integration: from a normal map to a height map, and back.

Gradients follow DESIGN.md: $p = \\partial z/\\partial x = -n_x/n_z$ and
$q = \\partial z/\\partial y = -n_y/n_z$ with y up, so one row down is $-1$ in y:
$\\partial z/\\partial \\mathrm{col} = p$ and $\\partial z/\\partial \\mathrm{row} = -q$.

Methods (see `docs/integration.md` for measured accuracy and speed):
- `"fc"`: Frankot–Chellappa, FFT on the whole image (periodic borders).
- `"dct"`: Poisson with Neumann borders on the whole image, by DCT (Simchony et al. 1990).
- `"lsq"`: masked least squares on the mask only (Quéau et al. 2018), jitted matrix-free CG.
- `"bilateral"`: discontinuity-aware bilateral normal integration (Cao et al. 2022).
- `"auto"`: picks one of these from the mask and the curl of the normal field.

Perspective (`intrinsics=K`): with $d$ the depth along the optical axis, the unknown becomes
$\\eta = -f_x \\log d$ and the equations keep their orthographic form with $n_z$ replaced by
$m = n_z - n_x (c - c_x)/f_x + n_y (r - c_y)/f_y$ (Durou & Courteille's log-depth
change of variables, in the form used by Cao et al. 2022, derived here for the camera frame of
DESIGN.md with K in the usual pixel convention: column c, row r).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ..core._host import (
    OLDER_EMITTERS,
    CpuTuned,
    cpu_top_level,
    has_value,
    positive_scalar,
    to_device,
)
from ..core._kept import (
    _HEIGHTS,
    _INTEGRATE_SCRATCH,
    KEEP_FROM_BYTES,
    keep,
    keep_bytes,
    spare_outputs,
)
from ..core._safe import safe_sqrt
from ..core._store import active as store_active
from ..core._store import call as stored_call
from ._grid import PRECONDITIONERS, bilateral, lsq_midpoint
from ._poisson import (
    _edge_div_of_means,
    _neumann_from_spectrum,
    _neumann_spectrum,
    _neumann_spectrum_parts,
    dct_poisson,
)

# The public names are listed (and re-exported) in `jaxps.integration`.

INTEGRATION_METHODS: tuple[str, ...] = ("fc", "dct", "lsq", "bilateral", "auto")

# n_z is floored here before dividing, so a grazing normal gives a gradient of at most ~20.
_MIN_NZ = 0.05
# Crop sides are padded up to `_bucket`'s ladder, so objects of similar size share one
# compilation; no side is padded to less than this.
_BUCKET = 32
# `"auto"`: a pixel whose |curl| exceeds _CURL_PIXEL (height units per pixel loop) is
# non-integrable; more than _CURL_FRACTION of them in the mask picks "bilateral".
_CURL_PIXEL = 0.05
_CURL_FRACTION = 0.01
# Default CG tolerances (relative residual). "lsq" is one linear solve: 1e-4 makes it the exact
# least-squares answer to ~0.5% MADE on DiLiGenT (1e-3 is 4% off on pot1). "bilateral" keeps
# Cao et al.'s 1e-3: its published accuracy depends on these inexact solves (see docs).
_LSQ_RTOL = 1e-4
_BILATERAL_RTOL = 1e-3
_NO_VALID_NORMAL = "normals has no finite, non-zero normal inside mask"
# Eager "fc" and "dct" of normals over this many bytes write into kept memory (`_fc_kept`).
_KEEP_FROM_BYTES = KEEP_FROM_BYTES


class IntegrationResult(NamedTuple):
    """What `integrate(..., return_info=True)` returns.

    - `height`: `(H, W)` height, as `integrate` returns it.
    - `method`: the method that ran (for `"auto"`, the one it picked).
    - `reason`: why `"auto"` picked it (or `"requested"`).
    - `steps`: reweighting steps (`"bilateral"`), 1 for one linear solve, 0 for FFT/DCT.
    - `solver_steps`: conjugate-gradient steps in all (0 for FFT/DCT).
    - `converged`: whether every iteration met its tolerance within its step limit.
    - `residual`: `(H, W)` RMS over a pixel's in-mask edges of (height step − the step the
      normals ask for), in pixel units of the solved variable; 0 outside the mask.
    - `valid`: `(H, W)` bool, the pixels that were integrated (mask and finite normals).
    """

    height: Array
    method: str
    reason: str
    steps: int
    solver_steps: int
    converged: bool
    residual: Array
    valid: Array


def _host_count(mask) -> int:
    """The true pixels of a bool mask, counted on the host (a CPU array is read in place).
    Counted in a program, the bools were first written to memory as an int32 plane."""
    return int(np.count_nonzero(np.asarray(mask)))


def _check_normals(normals, mask):
    """`normals` as a device array, `mask` as one (None stays None: every pixel, with no
    all-true plane to build and read), and the number of pixels in the mask (None for a
    traced mask, which has no value to count yet)."""
    normals = to_device(normals)
    if normals.ndim != 3 or normals.shape[-1] != 3:
        raise ValueError(f"normals must be (H, W, 3), got shape {normals.shape}")
    if not jnp.issubdtype(normals.dtype, jnp.floating):
        raise ValueError(f"normals must be floating point, got {normals.dtype}")
    h, w, _ = normals.shape
    if h == 0 or w == 0:
        raise ValueError(f"normals must have at least one pixel, got shape {normals.shape}")
    # Host-side checks on host arrays: no small jitted op to compile in a fresh process.
    if mask is None:
        return normals, None, h * w
    if np.shape(mask) != (h, w):
        raise ValueError(f"mask must have shape (H, W) = {(h, w)}, got {np.shape(mask)}")
    if not has_value(mask):
        return normals, jnp.asarray(mask, bool), None
    count = _host_count(mask)
    if not count:
        raise ValueError("mask is empty: no pixel to integrate")
    return normals, to_device(mask, bool), count


def _check_intrinsics(intrinsics):
    if intrinsics is None:
        return None
    k = np.asarray(intrinsics, np.float64)
    if k.shape != (3, 3) or not np.all(np.isfinite(k)):
        raise ValueError(f"intrinsics must be a finite 3x3 matrix K, got shape {k.shape}")
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        raise ValueError(f"intrinsics must have positive focal lengths, got {k[0, 0]}, {k[1, 1]}")
    return tuple(float(v) for v in (k[0, 0], k[1, 1], k[0, 2], k[1, 2]))


def gradients_from_normals(
    normals: Float[ArrayLike, "H W 3"], mask: Bool[ArrayLike, "H W"] | None
) -> tuple[Float[Array, "H W"], Float[Array, "H W"]]:
    """Surface gradients `(p, q)` = (dz/dx, dz/dy), y up, of `(H, W, 3)` normals: `(H, W)`
    each, 0 outside `mask` (`(H, W)` bool, or None for every pixel) and for NaN normals.

    $n_z$ is floored at 0.05. Gradients with respect to `normals` are finite (0 for the pixels
    left out): NaN normals are replaced before dividing, not after.
    """
    if not hasattr(normals, "dtype"):
        normals = np.asarray(normals)
    if normals.ndim != 3 or normals.shape[-1] != 3:
        raise ValueError(f"normals must be (H, W, 3), got shape {normals.shape}")
    if not jnp.issubdtype(normals.dtype, jnp.floating):
        raise ValueError(f"normals must be floating point, got {normals.dtype}")
    if mask is not None and np.shape(mask) != normals.shape[:2]:
        raise ValueError(f"mask must have shape (H, W) = {normals.shape[:2]}, got "
                         f"{np.shape(mask)}")
    return _gradients_from_normals(normals, None if mask is None else jnp.asarray(mask, bool))


@jax.jit
def _gradients_from_normals(normals, mask):
    ok = jnp.all(jnp.isfinite(normals), axis=-1)
    ok = ok if mask is None else mask & ok
    n = jnp.where(ok[..., None], normals, 0)  # no NaN in the branch `where` leaves out
    nx, ny, nz = n[..., 0], n[..., 1], jnp.maximum(n[..., 2], _MIN_NZ)
    p = jnp.where(ok, -nx / nz, 0)
    q = jnp.where(ok, -ny / nz, 0)
    return p, q


@jax.jit
def _unit_normals(normals, mask):
    """Unit normals, `(0, 0, 1)` where non-finite or of zero length; and the valid mask
    (`mask`, None for every pixel, and a finite non-zero normal)."""
    finite = jnp.all(jnp.isfinite(normals), axis=-1)
    n = jnp.where(finite[..., None], normals, 0)
    sq = jnp.sum(n * n, axis=-1, keepdims=True)
    ok = finite & (sq[..., 0] > 1e-12) & jnp.isfinite(sq[..., 0])
    one = jnp.ones((), n.dtype)
    # sqrt of the guarded square: the length's gradient at a zero normal would be 0/0
    n = jnp.where(ok[..., None], n / jnp.sqrt(jnp.where(ok[..., None], sq, one)), 0)
    n = n.at[..., 2].set(jnp.where(ok, n[..., 2], one))
    return n, ok if mask is None else mask & ok


def _slope_coefficients(n, cam):
    """`(m_u, m_v)`: the factor multiplying the height step per column / per row."""
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
    if cam is None:
        return nz, nz
    fx, fy, cx, cy = cam
    h, w = nz.shape
    dt = n.dtype
    u = (jnp.arange(w, dtype=dt) - jnp.asarray(cx, dt))[None, :]
    v = (jnp.arange(h, dtype=dt) - jnp.asarray(cy, dt))[:, None]
    m = nz - nx * u / jnp.asarray(fx, dt) + ny * v / jnp.asarray(fy, dt)
    return m, m * jnp.asarray(fy / fx, dt)


def _height_steps(n, valid, cam):
    """Per-pixel height steps per column and per row (0 where not valid); slopes floored."""
    mu, mv = _slope_coefficients(n, cam)
    floor = jnp.asarray(_MIN_NZ, n.dtype)
    gc = jnp.where(valid, -n[..., 0] / jnp.maximum(mu, floor), 0)
    gr = jnp.where(valid, n[..., 1] / jnp.maximum(mv, floor), 0)
    return gc, gr


def _mid_edges(gc, gr, valid):
    eh = valid[:, 1:] & valid[:, :-1]
    ev = valid[1:, :] & valid[:-1, :]
    gh = jnp.where(eh, (gc[:, 1:] + gc[:, :-1]) / 2, 0)
    gv = jnp.where(ev, (gr[1:, :] + gr[:-1, :]) / 2, 0)
    return gh, gv, eh, ev


@jax.jit
def _curl(gc, gr, valid):
    gh, gv, eh, ev = _mid_edges(gc, gr, valid)
    # circulation around each 2x2 loop: right on top, down on the right, back left, back up
    loop = gh[:-1, :] + gv[:, 1:] - gh[1:, :] - gv[:, :-1]
    inside = eh[:-1, :] & eh[1:, :] & ev[:, :-1] & ev[:, 1:]
    c = jnp.where(inside, jnp.abs(loop), 0)
    z = jnp.zeros((), c.dtype)
    pads = [((0, 1), (0, 1)), ((1, 0), (0, 1)), ((0, 1), (1, 0)), ((1, 0), (1, 0))]
    return jnp.max(jnp.stack([jnp.pad(c, p, constant_values=z) for p in pads]), axis=0)


@jax.jit
def _residual_map(z, gc, gr, valid):
    gh, gv, eh, ev = _mid_edges(gc, gr, valid)
    rh = jnp.where(eh, z[:, 1:] - z[:, :-1] - gh, 0) ** 2
    rv = jnp.where(ev, z[1:, :] - z[:-1, :] - gv, 0) ** 2
    zero = jnp.zeros((), z.dtype)
    dt = z.dtype

    def spread(a, b):  # sum of edge values onto both end pixels
        return (jnp.pad(a, ((0, 0), (1, 0)), constant_values=zero)
                + jnp.pad(a, ((0, 0), (0, 1)), constant_values=zero)
                + jnp.pad(b, ((1, 0), (0, 0)), constant_values=zero)
                + jnp.pad(b, ((0, 1), (0, 0)), constant_values=zero))

    total = spread(rh, rv) / jnp.maximum(spread(eh.astype(dt), ev.astype(dt)), jnp.ones((), dt))
    return safe_sqrt(total)  # finite gradient where the residual is 0


def integrability_map(
    normals: Float[ArrayLike, "H W 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    intrinsics: Float[ArrayLike, "3 3"] | None = None,
) -> Float[Array, "H W"]:
    """The curl of the gradient field: how far a normal map is from being integrable.

    For every 2x2 loop of pixels inside `mask`, the sum of the height steps the normals ask for
    around the loop (edge steps are the mean of the two end pixels' gradients) would be 0 for
    a continuous surface; each pixel gets the largest $|\\text{circulation}|$ of the loops it
    belongs to. Large values mark depth discontinuities, occluding boundaries and noisy normals.

    **Arguments:**
    - `normals`: `(H, W, 3)` normals (normalised here; NaN or zero ones are left out).
    - `mask`: `(H, W)` bool, valid pixels (default: all).
    - `intrinsics`: optional `(3, 3)` camera matrix K: the curl of the log-depth field instead.

    **Returns:** `(H, W)` non-negative curl in height units per pixel (0 outside the mask and
    for pixels with no full loop inside it), in the dtype of `normals`.
    """
    normals, mask, _ = _check_normals(normals, mask)
    cam = _check_intrinsics(intrinsics)
    n, valid = _unit_normals(normals, mask)
    gc, gr = _height_steps(n, valid, cam)
    return _curl(gc, gr, valid)


def _fc_spectrum(dzdc, dzdr, scale):
    """Frankot–Chellappa's height spectrum (half plane) from the column and row steps, times
    `scale`."""
    return _fc_solve(jnp.fft.rfft2(dzdc), jnp.fft.rfft2(dzdr), scale, dzdc.shape)


def _fc_solve(fc, fr, scale, shape):
    """Frankot–Chellappa's height spectrum from the half spectra `fc`, `fr` of the column and
    row steps of an image of `shape`, times `scale`. Both spectra, the scale and the -1j are
    one pass over the half spectrum (no full-size temporaries)."""
    h, w = shape
    dt = fc.real.dtype
    wc = 2 * jnp.pi * jnp.fft.rfftfreq(w).astype(dt)[None, :]
    wr = 2 * jnp.pi * jnp.fft.fftfreq(h).astype(dt)[:, None]
    d = wc * wc + wr * wr
    factor = jnp.where(d > 0, jnp.asarray(scale, dt) / jnp.where(d > 0, d, 1), 0)  # DC -> 0
    re = wc * fc.real + wr * fr.real
    im = wc * fc.imag + wr * fr.imag
    return jax.lax.complex(im * factor, -re * factor)


# Frankot–Chellappa and the DCT solve run as two programs each at the top level, split at the
# half spectrum: XLA-CPU ran the inverse FFT at half speed on a spectrum computed in the same
# program (see `_poisson.py`, above `_poisson_spectrum`).
def _fc_height_of(g, mask, count, shape):
    """Frankot–Chellappa's height from `_fc_spectrum`'s half spectrum, mean 0 over `mask`, which
    holds `count` pixels (`_host_count`)."""
    z = jnp.fft.irfft2(g, s=shape).astype(g.real.dtype)
    # Over every pixel (no mask) the spectrum's zero DC term is the mean 0 already: no pass.
    return z if mask is None else z - _mean_over(z, mask, count)


_fc_height = jax.jit(_fc_height_of, static_argnames="shape")


@functools.partial(jax.jit, static_argnames="shape", donate_argnums=0, keep_unused=True)
def _fc_height_into(out, g, mask, count, shape):
    """`_fc_height` written into `out`, the donated buffer of a height its caller has let go
    of (`_fc_kept`)."""
    return _fc_height_of(g, mask, count, shape)


_fc_spectrum_jit = jax.jit(_fc_spectrum)


def _frankot_chellappa(dzdc, dzdr, mask, count, scale=1.0):
    """Least-squares periodic height from its column and row steps, mean 0 over `mask` (of
    `count` pixels), times `scale` (Frankot & Chellappa, IEEE TPAMI 10(4), 1988)."""
    return _fc_height(_fc_spectrum_jit(dzdc, dzdr, scale), mask, count, dzdc.shape)


def _bucket(n: int) -> int:
    """`n` rounded up to 32, 64, ..., 256, 320, 384, 448, 512, 640, ...: a multiple of 32 and of
    a quarter of the power of two below `n`. A side grows by less than a quarter, a face box
    that changes by tens of pixels keeps its size (one compile of the multigrid solve), and
    the multigrid halves the side evenly. With 32-px steps, a session of 24 faces compiled 10
    crop sizes, against 5 (`benchmarks/bench_lsq_buckets.py`)."""
    step = max(_BUCKET, 1 << max(0, (n - 1).bit_length() - 3))
    return -(-n // step) * step


def _crop(valid):
    """Bounding box of `valid`, its sides grown to `_bucket` sizes (within the image if
    possible)."""
    rows, cols = np.nonzero(np.asarray(valid))
    box = []
    for lo, hi, size in ((rows.min(), rows.max() + 1, valid.shape[0]),
                         (cols.min(), cols.max() + 1, valid.shape[1])):
        want = min(_bucket(int(hi - lo)), size)
        lo = max(0, min(lo, size - want))
        box.append(slice(int(lo), int(lo + want)))
    return tuple(box)


def _lsq_fast(normals, mask, pixel_size, **solver):
    """`integrate(method="lsq")` without intrinsics or info, as `jaxps reconstruct` calls it:
    two programs of the store (`core._store`), so that a new process loads them instead of
    tracing the multigrid solve and a dozen eager steps (a warm command's integration at 1 MP:
    0.31-0.35 against 0.88 s, docs/integration.md "On real faces").
    The crop's size is static (`_bucket`'s, as in the general path) and its corner a program
    argument, so captures of one size share a program."""
    valid = stored_call(_valid_normals, normals, mask)
    if not bool(np.any(np.asarray(valid))):
        raise ValueError(_NO_VALID_NORMAL)
    box = _crop(valid)
    corner = to_device(np.array([box[0].start, box[1].start], np.int32))
    return stored_call(_lsq_height, normals, mask, corner,
                       to_device(pixel_size, normals.dtype),
                       size=(box[0].stop - box[0].start, box[1].stop - box[1].start), **solver)


@jax.jit
def _valid_normals(normals, mask):
    return _unit_normals.__wrapped__(normals, mask)[1]


def _lsq_height_of(normals, mask, corner, pixel_size, *, size, rtol, max_steps, preconditioner):
    """The general path's `"lsq"` steps in one program, on the crop of `size` at `corner`."""
    n, valid = _unit_normals.__wrapped__(normals, mask)
    gc, gr = _height_steps(n, valid, None)
    gc, gr, v = (jax.lax.dynamic_slice(a, (corner[0], corner[1]), size) for a in (gc, gr, valid))
    out = lsq_midpoint(gc, gr, v, rtol=rtol, max_steps=max_steps, preconditioner=preconditioner)
    eta = jax.lax.dynamic_update_slice(jnp.zeros(valid.shape, normals.dtype), out.z,
                                       (corner[0], corner[1]))
    return _to_height(eta, valid, None, pixel_size, everywhere=False)


# With XLA-CPU's older loop emitters, as `lsq_midpoint` is compiled at the top level (inside
# this program it is traced, so it would take the default ones): it compiled in 1.10-1.46
# against 1.71-2.44 s at crops of 320x224 to 640x512 px, with warm calls no slower
# (`benchmarks/bench_lsq_buckets.py --emitters --repeats 9`), and `jaxps reconstruct`'s
# first 1 MP run integrated in 2.16 and 1.95 s against 3.28 and 2.94 s (`bench_cli.py`).
_lsq_height = CpuTuned(_lsq_height_of, OLDER_EMITTERS,
                       static_argnames=("size", "rtol", "max_steps", "preconditioner"))


def _mean_over(z, valid, count=None):
    """The mean of `z` over `valid` (None: every pixel), which holds `count` pixels (counted
    here if None)."""
    if valid is None:
        return jnp.mean(z)
    count = jnp.sum(valid) if count is None else jnp.asarray(count)
    return jnp.sum(jnp.where(valid, z, 0)) / jnp.maximum(count, 1).astype(z.dtype)


def _to_height(eta, valid, cam, pixel_size, everywhere, count=None):
    """Solved variable -> height toward the viewer, mean 0 over `valid` (of `count` pixels,
    counted here if None)."""
    dt = eta.dtype
    eta = eta - _mean_over(eta, valid, count)
    if cam is not None:
        fx = jnp.asarray(cam[0], dt)
        limit = jnp.asarray(50, dt)
        depth = fx * jnp.exp(jnp.clip(-eta / fx, -limit, limit))
        eta = -(depth - _mean_over(depth, valid, count))
    if not everywhere:
        eta = jnp.where(valid, eta, 0)
    return (eta * jnp.asarray(pixel_size, dt)).astype(dt)


def _orthographic_steps(normals, mask, guard=True):
    """Height steps per column and per row of unit normals (0 where not valid), and the valid
    mask: `_unit_normals` + `_height_steps` without intrinsics, written on the three normal
    planes so that XLA fuses the slopes into one pass (a reduction over the length-3 axis or
    `.at[].set` would each cost a pass over the image).

    `guard`: zero non-finite normals before any arithmetic, so that the branches `where`
    leaves out carry no NaN into the gradient. The values are the same either way (a
    non-finite component makes the squared length non-finite, so the pixel is not valid);
    `_stacked_steps_array` computes them unguarded and differentiates the guarded form."""
    nx, ny, nz = normals[..., 0], normals[..., 1], normals[..., 2]
    if guard:
        finite = jnp.isfinite(nx) & jnp.isfinite(ny) & jnp.isfinite(nz)
        nx, ny, nz = (jnp.where(finite, a, 0) for a in (nx, ny, nz))
    sq = nx * nx + ny * ny + nz * nz
    ok = jnp.isfinite(sq) & (sq > 1e-12)
    ok = ok if mask is None else mask & ok
    inv = jax.lax.rsqrt(jnp.where(ok, sq, 1))
    slope = 1 / jnp.maximum(nz * inv, _MIN_NZ)
    return jnp.where(ok, -nx * inv * slope, 0), jnp.where(ok, ny * inv * slope, 0), ok


def _stacked_steps(normals, mask, guard):
    dzdc, dzdr, ok = _orthographic_steps(normals, mask, guard)
    return jax.lax.optimization_barrier(jnp.stack([dzdc, dzdr])), ok


@jax.custom_jvp
def _stacked_steps_array(normals, mask):
    """`_orthographic_steps` with the two step planes written as one `(2, H, W)` array behind
    an `optimization_barrier`, and the valid mask. Left free, XLA-CPU wrote $1/|n|$ and the
    slope to memory for the two planes' passes to share; this way one pass computes both steps
    from the normals: at 1 MP the median FC took 4-26% less time and DCT 15-34% less, with
    the same heights (five runs of `benchmarks/bench_stacked_steps.py`).

    Computed without the finiteness guard, whose zeroed planes XLA-CPU wrote to memory: the
    spectrum programs of FC and DCT compile to 10 and 7 loop fusions instead of 12 and 9
    (`benchmarks/ab_integrate.py`). Differentiated through the guarded form, so gradients
    stay finite on non-finite normals."""
    return _stacked_steps(normals, mask, guard=False)


@_stacked_steps_array.defjvp
def _stacked_steps_array_jvp(primals, tangents):
    normals, mask = primals
    return jax.jvp(lambda n: _stacked_steps(n, mask, guard=True), (normals,), (tangents[0],))


def _fc_first(normals, mask, pixel_size):
    """`integrate(method="fc")` without intrinsics, up to the height's spectrum (`_fc_height`
    finishes it): `((steps, fc, fr), spectrum, any_valid)`, with its intermediate planes (the
    `(2, H, W)` steps and their two half spectra) and whether any normal was valid."""
    steps, ok = _stacked_steps_array(normals, mask)
    fc, fr = jnp.fft.rfft2(steps[0]), jnp.fft.rfft2(steps[1])
    return (steps, fc, fr), _fc_solve(fc, fr, pixel_size, ok.shape), jnp.any(ok)


@jax.jit
def _fc_spectrum_from_normals(normals, mask, pixel_size):
    """`_fc_first` without its intermediate planes: `(spectrum, any_valid)`."""
    return _fc_first(normals, mask, pixel_size)[1:]


@functools.partial(jax.jit, donate_argnums=0, keep_unused=True)
def _fc_spectrum_into(scratch, normals, mask, pixel_size):
    """`_fc_spectrum_from_normals` writing into the donated `scratch` of an earlier call
    (`_fc_kept`): `(steps, fc, fr, spectrum), any_valid`. Inside one program the intermediate
    planes are temporaries, fresh memory on every call; here they are outputs."""
    planes, spectrum, any_valid = _fc_first(normals, mask, pixel_size)
    return (*planes, spectrum), any_valid


def _fc_kept(normals, mask, count, pixel_size):
    """`integrate(method="fc")` of normals over `_KEEP_FROM_BYTES` at the top level on the CPU,
    without intrinsics: `(height, any_valid)`.

    Frankot–Chellappa's intermediate planes (its steps, their half spectra and the height's
    spectrum, 20 bytes a pixel) are written into those of the latest such call of the same
    shapes, and the height into one of the latest two heights once its caller has let go of it
    (`core._kept.spare_outputs`); both are kept in turn, within `$JAXPS_BATCH_KEEP_BYTES`. In
    fresh memory, which glibc maps afresh for blocks this large on every call, each first write
    to a 4 KiB page is a page fault (docs/speed.md, "Why the time per pixel grows"). At
    4096x4096 the median call took 224 against 299 ms, with 32,783 against 118,808 page
    faults (`benchmarks/ab_fc_kept.py`)."""
    shape, dtype = normals.shape[:2], normals.dtype
    half, cdt = (shape[0], shape[1] // 2 + 1), np.result_type(dtype, np.complex64)
    specs = (((2, *shape), dtype), (half, cdt), (half, cdt), (half, cdt))
    scratch, any_valid = _into_scratch("fc", specs, _fc_spectrum_into, normals, mask,
                                       pixel_size)
    height = _into_kept_height(_fc_height_into, dtype, scratch[-1], mask, count, shape=shape)
    return height, any_valid


def _dct_kept(normals, mask, pixel_size):
    """`integrate(method="dct")` as `_fc_kept` runs `"fc"`: its steps, reordered divergence,
    that plane's half spectrum and the solve's (24 bytes a pixel) written into the latest such
    call's, the height into a dropped one. `(height, count)`, `count` the valid normals (0:
    none, and no height)."""
    shape, dtype = normals.shape[:2], normals.dtype
    half, cdt = (shape[0], shape[1] // 2 + 1), np.result_type(dtype, np.complex64)
    specs = (((2, *shape), dtype), (shape, dtype), (half, cdt), (half, cdt))
    scratch, valid = _into_scratch("dct", specs, _dct_spectrum_into, normals, mask)
    count = _host_count(valid)
    if count == 0:
        return None, 0
    full = count == valid.size  # then no mean to take (`_dct_height`)
    height = _into_kept_height(_dct_height_into, dtype, scratch[-1], None if full else valid,
                               to_device(count, dtype), pixel_size, shape=shape)
    return height, count


def _into_scratch(name, specs, program, *args):
    """`program(scratch, *args)`, `scratch` the donated planes of the latest call of `name`
    with these `(shape, dtype)` `specs` (zeros the first time, so that one program serves):
    `(planes, *rest)`; the planes are kept for the next call."""
    budget = keep_bytes()
    key = (name, specs)
    scratch = spare_outputs(_INTEGRATE_SCRATCH, key) if budget else None
    if scratch is None:
        scratch = tuple(jnp.zeros(shape, dtype) for shape, dtype in specs)
    scratch, *rest = program(scratch, *args)
    keep(_INTEGRATE_SCRATCH, key, scratch, budget)
    return (scratch, *rest)


def _into_kept_height(program, dtype, *args, shape):
    """`program(out, *args, shape=shape)`, `out` one of the latest two `(shape, dtype)` heights
    that its caller has let go of (zeros if none); the height is kept in turn."""
    budget = keep_bytes()
    key = (shape, np.dtype(dtype))
    out = spare_outputs(_HEIGHTS, key) if budget else None
    height = program(jnp.zeros(shape, dtype) if out is None else out[0], *args, shape=shape)
    keep(_HEIGHTS, key, (height,), budget)
    return height


@functools.partial(jax.jit, static_argnames="cam")
def _dct_spectrum_from_normals(normals, mask, cam):
    """`integrate(method="dct")` in two programs: this one, up to the solve's half spectrum
    (and the valid mask), then `_dct_height`."""
    if cam is None:
        return _dct_first(normals, mask)[1:]
    n, valid = _unit_normals(normals, mask)
    gc, gr = _height_steps(n, valid, cam)
    return _neumann_spectrum(_edge_div_of_means(gc, gr)), valid


def _dct_first(normals, mask):
    """`_dct_spectrum_from_normals` without intrinsics, with its intermediate planes:
    `((steps, reordered divergence, its half spectrum), spectrum, valid)`."""
    steps, valid = _stacked_steps_array(normals, mask)
    planes, spectrum = _neumann_spectrum_parts(_edge_div_of_means(steps[0], steps[1]))
    return (steps, *planes), spectrum, valid


@functools.partial(jax.jit, donate_argnums=0, keep_unused=True)
def _dct_spectrum_into(scratch, normals, mask):
    """`_dct_spectrum_from_normals` without intrinsics, writing into the donated `scratch` of
    an earlier call (`_dct_kept`): `(steps, reordered divergence, its half spectrum,
    spectrum), valid`."""
    planes, spectrum, valid = _dct_first(normals, mask)
    return (*planes, spectrum), valid


@functools.partial(jax.jit, static_argnames="shape", donate_argnums=0, keep_unused=True)
def _dct_height_into(out, g, valid, count, pixel_size, shape):
    """`_dct_height` without intrinsics, written into `out`, the donated buffer of a height its
    caller has let go of (`_dct_kept`)."""
    return _dct_height.__wrapped__(g, valid, count, pixel_size, None, shape)


@functools.partial(jax.jit, static_argnames=("cam", "shape"))
def _dct_height(g, valid, count, pixel_size, cam, shape):
    """`_dct_spectrum_from_normals`'s spectrum and valid mask (of `count` pixels, counted here
    if None) to the height. `valid` None: every pixel is valid, and without intrinsics the
    solve's zero DC term is the mean 0 already (no pass over the image for it)."""
    eta = _neumann_from_spectrum(g, shape).astype(g.real.dtype)
    if valid is None and cam is None:
        return (eta * jnp.asarray(pixel_size, eta.dtype)).astype(eta.dtype)
    return _to_height(eta, valid, cam, pixel_size, True, count)


def _auto_choice(n, valid, cam):
    full = bool(jnp.all(valid))
    gc, gr = _height_steps(n, valid, cam)
    curl = _curl(gc, gr, valid)
    frac = float(jnp.sum(curl > _CURL_PIXEL)) / max(int(jnp.sum(valid)), 1)
    if frac > _CURL_FRACTION:
        return "bilateral", (
            f"{100 * frac:.1f}% of the pixels have |curl| > {_CURL_PIXEL} (limit "
            f"{100 * _CURL_FRACTION:g}%): discontinuities, so the discontinuity-aware method")
    if full:
        return "dct", (
            f"full rectangle and integrable ({100 * frac:.2f}% of pixels with |curl| > "
            f"{_CURL_PIXEL}): the DCT Poisson solve is exact least squares there, with "
            "Neumann borders (FC would assume a periodic surface)")
    return "lsq", (
        f"irregular mask or holes, integrable ({100 * frac:.2f}% of pixels with |curl| > "
        f"{_CURL_PIXEL}): masked least squares")


def integrate(
    normals: Float[ArrayLike, "H W 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    method: str = "fc",
    pixel_size: float = 1.0,
    intrinsics: Float[ArrayLike, "3 3"] | None = None,
    k: float = 2.0,
    max_steps: int = 150,
    tol: float = 1e-4,
    cg_rtol: float | None = None,
    cg_max_steps: int = 5000,
    cg_preconditioner: str = "multigrid",
    return_info: bool = False,
) -> Float[Array, "H W"] | IntegrationResult:
    """Integrate a normal map into a height map (orthographic camera unless `intrinsics`).

    `"fc"`: Frankot & Chellappa, "A method for enforcing integrability in shape from shading
    algorithms", IEEE TPAMI 10(4), 1988 — the least-squares integrable surface in the Fourier
    basis, $\\hat z = -i(\\omega_x \\hat p + \\omega_y \\hat q) / (\\omega_x^2 + \\omega_y^2)$,
    computed with a real FFT. Borders: the gradient field is treated as periodic over the
    whole image (no padding). Mask: gradients outside `mask` (and of NaN normals) are set to 0,
    so the surface is flat there and the mask's outline can bend the result; `n_z` is floored
    at 0.05 so grazing normals cannot blow up. The height's mean over `mask` is 0.

    `"dct"`: Poisson integration with Neumann borders by a DCT (Simchony, Chellappa & Shao,
    IEEE TPAMI 12(5), 1990): the same set-up as `"fc"` (whole image, zero gradients outside
    `mask`), but exact least squares for a non-periodic rectangle. Cost of an FFT.

    `"lsq"`: masked least squares (Quéau, Durou & Aujol, "Normal integration: a survey", JMIV
    2018): $\\min_z \\sum_{(i,j)} (z_j - z_i - (g_i + g_j)/2)^2$ over neighbouring pixel pairs
    both inside `mask`, so the outline is a free (Neumann) border and holes cost nothing.
    Solved by preconditioned conjugate gradients on a 5-point stencil, jitted (see `_grid.py`
    for why not `scipy.sparse`); stops at `cg_rtol` (default 1e-4) or `cg_max_steps`.

    `"bilateral"`: bilateral normal integration (Cao et al., "Bilateral Normal Integration",
    ECCV 2022): iteratively reweighted least squares over one-sided differences with sigmoid
    weights of sharpness `k`, so the height may jump where the normals' one-sided steps
    disagree. Stops when the energy's relative change is below `tol` or after `max_steps`
    reweightings, each solved by warm-started CG as above. Use it for objects with depth
    discontinuities or self-occlusions; on DiLiGenT it is 3-20x more accurate than `"lsq"`.

    `"auto"`: the cheapest adequate method, from the curl of the normal field
    (`integrability_map`): more than 1% of the pixels with |curl| > 0.05 -> `"bilateral"`;
    else a full rectangle -> `"dct"`; else `"lsq"`. `return_info=True` says which and why.

    Perspective: give `intrinsics` (the 3x3 K, e.g. DiLiGenT's `K.txt`) to integrate the log
    depth instead (see the module docstring). Shape is then known up to a global scale; the
    height returned is `-(d - mean d)` with the depth $d$ scaled so its geometric mean over the
    mask is $f_x$ pixels, i.e. in pixel units at the object's distance (times `pixel_size`).

    Bad normals: NaN, infinite or zero normals inside `mask` are left out (flat for
    `"fc"`/`"dct"`, holes for `"lsq"`/`"bilateral"`); normals need not be unit length; slopes
    use $n_z$ floored at 0.05 (backfacing or grazing normals give a slope of at most ~20; for
    `"bilateral"` they get a weight ~$n_z^2$). The height is always finite.

    Gradients (reverse mode) with respect to `normals` and `pixel_size` are finite for every
    method, 0 for the normals left out; the CG solves are differentiated by the implicit
    function theorem, `"bilateral"` with the weights of its last solve held fixed (see
    "Gradients" in `docs/integration.md`).

    Inside `jax.jit` and `jax.vmap`, `"fc"` and `"dct"` are traced into the caller's program
    (e.g. `jax.vmap(jaxps.integrate)` over a stack of normal maps), the same heights to
    float32 rounding; nothing is checked on the values there, so normals with no valid pixel
    give a height of 0 instead of an error. `"lsq"`, `"bilateral"` and `"auto"` crop to the
    mask and test their tolerances on the host, so they raise a `ValueError` inside `jit` or
    `vmap` (`jax.grad` outside them is fine).

    **Arguments:**
    - `normals`: `(H, W, 3)` normals, n_z >= 0.
    - `mask`: `(H, W)` bool, valid pixels (default: all).
    - `method`: one of `jaxps.INTEGRATION_METHODS`.
    - `pixel_size`: the size of a pixel in the height's unit (default 1: pixel units).
    - `intrinsics`: optional `(3, 3)` camera matrix for perspective integration.
    - `k`: sharpness of the bilateral weights (Cao et al. use 2).
    - `max_steps`, `tol`: reweighting limit and relative energy tolerance (`"bilateral"`).
    - `cg_rtol`, `cg_max_steps`: conjugate-gradient relative tolerance and step limit per solve
      (default tolerance: 1e-4 for `"lsq"`, Cao et al.'s 1e-3 for `"bilateral"`).
    - `cg_preconditioner`: `"multigrid"` (a geometric multigrid V-cycle, Braess 1995; 5-25x
      fewer CG steps) or `"jacobi"` (diagonal, as Cao et al.'s code: their figures to the
      digit, 2-6x slower; see `docs/integration.md`).
    - `return_info`: return an `IntegrationResult` instead of the height alone.

    **Returns:** `(H, W)` height in the dtype of `normals` (normals narrower than float32 are
    solved in float32), z toward the viewer, mean 0 over the mask; `"fc"` and `"dct"` define
    it everywhere, `"lsq"` and `"bilateral"` give 0 outside the mask. With
    `return_info=True`, an `IntegrationResult`.
    """
    if method not in INTEGRATION_METHODS:
        raise ValueError(f"method must be one of {INTEGRATION_METHODS}, got {method!r}")
    if not positive_scalar(pixel_size):  # not checked inside jit or vmap
        raise ValueError(f"pixel_size must be positive and finite, got {pixel_size}")
    if not (np.isfinite(k) and k > 0):
        raise ValueError(f"k must be positive, got {k}")
    if cg_preconditioner not in PRECONDITIONERS:
        raise ValueError(f"cg_preconditioner must be one of {PRECONDITIONERS}, "
                         f"got {cg_preconditioner!r}")
    for name, value in (("max_steps", max_steps), ("cg_max_steps", cg_max_steps)):
        if int(value) < 1:
            raise ValueError(f"{name} must be at least 1, got {value}")
    for name, value in (("tol", tol), ("cg_rtol", 1e-3 if cg_rtol is None else cg_rtol)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be positive, got {value}")
    normals, mask, count = _check_normals(normals, mask)
    if jnp.finfo(normals.dtype).bits < 32:
        # XLA's FFTs take float32 or float64 only: solve in float32, answer in the input's dtype
        out = integrate(normals.astype(jnp.float32), mask=mask, method=method,
                        pixel_size=pixel_size, intrinsics=intrinsics, k=k, max_steps=max_steps,
                        tol=tol, cg_rtol=cg_rtol, cg_max_steps=cg_max_steps,
                        cg_preconditioner=cg_preconditioner, return_info=return_info)
        if return_info:
            return out._replace(height=out.height.astype(normals.dtype),
                                residual=out.residual.astype(normals.dtype))
        return out.astype(normals.dtype)
    dtype = normals.dtype
    cam = _check_intrinsics(intrinsics)
    # Inside `jit` or `vmap` the normals (or the mask, or pixel_size) have no value yet:
    # nothing can be counted, cropped or checked on the host, so only the FFT methods are
    # traced.
    traced = count is None or not has_value(normals) or not has_value(pixel_size)
    if traced and method not in ("fc", "dct"):
        raise ValueError(
            f"method={method!r} crops to the mask and checks its tolerance on the host, so it "
            "runs outside jit and vmap (jax.grad is fine); inside them use 'fc' or 'dct'")
    if method in ("fc", "dct") and not return_info and (cam is None or method == "dct"):
        # The common cases in two jits each (split at the spectrum, see `_fc_height`): no
        # full-size temporaries between the steps.
        pixel_size = to_device(pixel_size, dtype)
        shape = normals.shape[:2]
        # Traced (inside a caller's program) the counts are taken there and nothing is checked.
        # Large eager calls write into kept memory (`_fc_kept`, `_dct_kept`).
        kept = (not traced and not store_active() and cpu_top_level(normals, mask)
                and normals.size * normals.dtype.itemsize > _KEEP_FROM_BYTES)
        if method == "fc":
            count = None if count is None else to_device(count, dtype)
            if kept:
                height, any_valid = _fc_kept(normals, mask, count, pixel_size)
            else:
                spectrum, any_valid = stored_call(_fc_spectrum_from_normals, normals, mask,
                                                  pixel_size)
                height = stored_call(_fc_height, spectrum, mask, count, shape=shape)
            if not traced and not bool(any_valid):
                raise ValueError(_NO_VALID_NORMAL)
            return height
        if cam is None and kept:
            height, count = _dct_kept(normals, mask, pixel_size)
            if count == 0:
                raise ValueError(_NO_VALID_NORMAL)
            return height
        spectrum, valid = stored_call(_dct_spectrum_from_normals, normals, mask, cam=cam)
        count = None if traced else _host_count(valid)  # before the height's program takes it
        if count == 0:
            raise ValueError(_NO_VALID_NORMAL)
        if cam is None and count == valid.size:
            valid = None  # every pixel: no mean to take (`_dct_height`)
        return stored_call(_dct_height, spectrum, valid,
                           None if count is None else to_device(count, dtype), pixel_size,
                           cam=cam, shape=shape)
    if mask is None:  # the general path reads a mask plane
        mask = to_device(np.ones(normals.shape[:2], bool))
    if method == "lsq" and cam is None and not return_info:
        return _lsq_fast(normals, mask, pixel_size, rtol=_LSQ_RTOL if cg_rtol is None else cg_rtol,
                         max_steps=int(cg_max_steps), preconditioner=cg_preconditioner)
    n, valid = _unit_normals(normals, mask)
    if not traced and not bool(jnp.any(valid)):
        raise ValueError(_NO_VALID_NORMAL)

    reason = "requested"
    if method == "auto":
        method, reason = _auto_choice(n, valid, cam)

    gc, gr = _height_steps(n, valid, cam)
    steps, solver_steps, converged = 0, 0, True
    if method == "fc":
        if cam is None:  # the seeds' behaviour, on normalised normals
            p, q = _gradients_from_normals(n, mask)
        else:
            p, q = gc, -gr
        eta = _frankot_chellappa(p, -q, mask, count)
    elif method == "dct":
        eta = dct_poisson(gc, gr)
    else:
        box = _crop(valid)
        v = valid[box]
        if method == "lsq":
            rtol = _LSQ_RTOL if cg_rtol is None else cg_rtol
            out = lsq_midpoint(gc[box], gr[box], v, rtol=rtol, max_steps=int(cg_max_steps),
                               preconditioner=cg_preconditioner)
        else:
            mu, mv = _slope_coefficients(n, cam)
            zero = jnp.zeros((), dtype)
            mu = jnp.where(valid, jnp.maximum(mu, zero), 0)[box]
            mv = jnp.where(valid, jnp.maximum(mv, zero), 0)[box]
            bu = jnp.where(valid, -n[..., 0], 0)[box]
            bv = jnp.where(valid, n[..., 1], 0)[box]
            rtol = _BILATERAL_RTOL if cg_rtol is None else cg_rtol
            out = bilateral(mu, mv, bu, bv, v, k=k, tol=tol, cg_rtol=rtol,
                            max_steps=int(max_steps), cg_max_steps=int(cg_max_steps),
                            preconditioner=cg_preconditioner)
        eta = jnp.zeros(valid.shape, dtype).at[box].set(out.z)
        steps, solver_steps = int(out.steps), int(out.cg_steps)
        converged = bool(out.converged)
    everywhere = method in ("fc", "dct")
    height = _to_height(eta.astype(dtype), mask if method == "fc" else valid, cam,
                        pixel_size, everywhere)
    if not return_info:
        return height
    residual = _residual_map(jnp.where(valid, eta, 0).astype(dtype), gc, gr, valid)
    return IntegrationResult(height, method, reason, steps, solver_steps, converged,
                             residual.astype(dtype), valid)


def normals_from_height(
    z: Float[ArrayLike, "H W"],
    *,
    pixel_size: float = 1.0,
    mask: Bool[ArrayLike, "H W"] | None = None,
) -> Float[Array, "H W 3"]:
    """Unit normals of a height map, from central differences (one-sided at the borders).

    With `mask`, differences never reach outside it: a pixel whose neighbour on one side is
    outside uses the one-sided difference to the other side, and a pixel with neither
    neighbour along an axis gets slope 0 there; normals outside the mask are `(0, 0, 1)`.
    Non-finite heights (NaN for "no data") count as outside the mask, with or without one, so
    they do not spread to their neighbours.

    **Arguments:**
    - `z`: `(H, W)` height, toward the viewer, in the unit of `pixel_size`.
    - `pixel_size`: the size of a pixel in the height's unit.
    - `mask`: optional `(H, W)` bool, the pixels where `z` is meaningful.

    **Returns:** `(H, W, 3)` unit normals $(-p, -q, 1)/\\sqrt{1+p^2+q^2}$ in the dtype of `z`.
    """
    z = jnp.asarray(z)
    if z.ndim != 2 or min(z.shape) < 2:
        raise ValueError(f"z must be a 2-D height map of at least 2x2, got shape {z.shape}")
    if not jnp.issubdtype(z.dtype, jnp.floating):
        z = z.astype(jnp.float32)
    if not positive_scalar(pixel_size):
        raise ValueError(f"pixel_size must be positive and finite, got {pixel_size}")
    if mask is None:
        return _normals_from_height(z, jnp.asarray(pixel_size, z.dtype))
    if np.shape(mask) != z.shape:
        raise ValueError(f"mask must have shape {z.shape}, got {np.shape(mask)}")
    return _normals_from_height_masked(z, jnp.asarray(mask, bool),
                                       jnp.asarray(pixel_size, z.dtype))


@jax.jit
def _normals_from_height(z, pixel_size):
    def everywhere():
        dzdr, dzdc = jnp.gradient(z)
        return _unit_normals_from_slopes(dzdc / pixel_size, -dzdr / pixel_size, None)

    # the rare height map with holes: the masked differences, around them only
    finite = jnp.isfinite(z)
    return jax.lax.cond(jnp.all(finite), everywhere,
                        lambda: _normals_from_height_masked.__wrapped__(z, finite, pixel_size))


def _unit_normals_from_slopes(p, q, mask):
    """`(H, W, 3)` $(-p, -q, 1)/\\sqrt{1+p^2+q^2}$, `(0, 0, 1)` outside `mask` (if given).
    Written on the planes (one reciprocal length, then one stack): a norm over the length-3
    axis and a division by it each cost XLA-CPU a pass over the image
    (`benchmarks/bench_evaluate.py`)."""
    inv = 1 / jnp.sqrt(1 + p * p + q * q)
    n = (-p * inv, -q * inv, inv)
    if mask is not None:
        n = (jnp.where(mask, n[0], 0), jnp.where(mask, n[1], 0), jnp.where(mask, n[2], 1))
    return jnp.stack(n, axis=-1)


def _masked_derivative(z, mask, axis):
    """Central difference along `axis` (0: rows, 1: columns) where both neighbours are in
    `mask`, one-sided where one is, 0 where neither is. Padded along `axis` in place (a
    `moveaxis` of the columns was a transpose, a pass over memory of its own)."""
    def step(a):  # a[i + 1] - a[i] along `axis`, shape one shorter
        lo = jax.lax.slice_in_dim(a, 0, a.shape[axis] - 1, axis=axis)
        hi = jax.lax.slice_in_dim(a, 1, a.shape[axis], axis=axis)
        return hi - lo if a.dtype != jnp.bool_ else hi & lo

    def pad(a, before):
        widths = [(0, 0), (0, 0)]
        widths[axis] = (1, 0) if before else (0, 1)
        return jnp.pad(a, widths)

    dz, dm = step(z), step(mask)
    fwd, has_fwd = pad(dz, False), pad(dm, False)
    bwd, has_bwd = pad(dz, True), pad(dm, True)
    both = has_fwd & has_bwd
    return jnp.where(both, (fwd + bwd) / 2, jnp.where(has_fwd, fwd, jnp.where(has_bwd, bwd, 0)))


@jax.jit
def _normals_from_height_masked(z, mask, pixel_size):
    mask = mask & jnp.isfinite(z)
    p = _masked_derivative(z, mask, 1) / pixel_size
    q = -_masked_derivative(z, mask, 0) / pixel_size
    return _unit_normals_from_slopes(p, q, mask)
