"""Many captures at once: stacked `(N, ...)` outputs, solved as one image, on threads, or mapped.

A scanner at a gate produces thousands of captures a day. `photometric_stereo_batch` solves N
captures of the same size into `(N, ...)` outputs. On one device the L2 solve treats the stack
as one image of N times the pixels (`_l2_one_image`). On one CPU the loop solvers (`irls`,
`sbl`, `barsky`) run captures on threads (`_captures_on_threads`). Other methods map the
single-capture solver over the capture axis in one jitted call with `jax.lax.map` (in
sequence, or in `jax.vmap` groups of `vmap_size`), and when several devices are present the
capture axis is split across them with `jax.sharding` (a 1-D mesh named `"captures"`). The
results equal N separate `photometric_stereo` calls.
`jaxps.reconstruct_many` (`cli/_reconstruct.py`) runs capture folders through loading, quality
checks and the solve with one progress bar and a summary table.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from ..core._host import (
    ALIGNMENT,
    aligned,
    aligned_empty,
    cpu_cores,
    cpu_top_level,
    fill_on_threads,
)
from ..lights._directions import validate_lights
from ..core._kept import (
    _BATCH,
    _LOCK,
    _SCRATCH,
    _STAGE,
    ONLY_HELD_HERE,
    keep,
    keep_bytes,
    refcounts,
    release_batch_outputs,
    result_specs,
    spare_outputs,
)
from . import _robust
from ._l2 import (
    PSResult,
    branch_of,
    host_constants,
    l2_batch_flags,
    l2_batch_solve,
    working_dtype,
)
from ._photometric_stereo import (
    _BANDED_SOLVERS,
    PS_METHODS,
    _check_scale,
    _sample_thresholds,
    photometric_stereo,
)

__all__ = ["photometric_stereo_batch", "release_batch_outputs"]

_CACHE: dict = {}
# Pixels of the L2 batch solved in one program when `chunk` is not given: 16 captures of
# 1 MP. One program holds its chunk's outputs and the weighted solve's temporaries, which
# grow with it: 64 captures of 1 MP with 5% of the samples dropped peaked at 6.77 GB in one
# program, 5.56 GB in these default chunks (4 of 16) and 4.98 GB in chunks of 8
# (`benchmarks/bench_batch.py --peak-rss 64 CHUNK --dropped`, CHUNK 64, None, 8).
_PIXELS_PER_PROGRAM = 1 << 24
# Options of the L2 solve that `_l2_one_image` handles; any other goes the general way.
_L2_OPTIONS = frozenset({"shadow_threshold", "saturation", "dark_threshold"})

def _staged(images, threads, budget):
    """An unaligned host stack copied into 64-byte-aligned memory (XLA-CPU reads that in
    place), on `threads` threads: into the buffer of the previous such copy when it has the
    same shape and dtype, else into fresh memory, which the kernel maps and zeroes first (at
    8 x 1 MP x 5 on 2 threads, 17.7 ms into a kept buffer against 56.3 ms into fresh memory,
    medians of 5 interleaved calls, `benchmarks/bench_batch.py --copy`).
    Returns `(aligned stack, buffer to give back to `_unstage` once every program that reads
    it has finished, or None)`."""
    images = np.asarray(images)
    if images.flags.c_contiguous and images.ctypes.data % ALIGNMENT == 0:
        return images, None
    buffer = None
    if budget >= images.nbytes:
        with _LOCK:
            if (_STAGE and _STAGE[0].shape == images.shape and _STAGE[0].dtype == images.dtype
                    and max(refcounts(_STAGE)) <= ONLY_HELD_HERE):
                buffer = _STAGE.pop()
        if buffer is None:
            buffer = aligned_empty(images.shape, images.dtype)
    else:  # not to be kept: let go of what was
        with _LOCK:
            _STAGE.clear()
    copy = aligned(images, threads=threads, out=buffer)
    return copy, buffer


def _unstage(buffer, budget):
    """Keep `buffer` (from `_staged`) for the next copy, within `budget` bytes."""
    with _LOCK:
        _STAGE[:] = [buffer] if buffer.nbytes <= budget else []


def _stack_captures(images):
    """`(N, K, H, W[, C])` captures as one array: numpy stays numpy (each chunk is moved to the
    device on its own, so the whole stack is not copied first), JAX arrays stay JAX arrays."""
    if isinstance(images, (list, tuple)):
        if not images:
            raise ValueError("images: empty list of captures")
        shapes = [np.shape(c) for c in images]
        for i, s in enumerate(shapes):
            if s != shapes[0]:
                raise ValueError(
                    f"images: capture {i} has shape {s} but capture 0 has {shapes[0]}; a batch "
                    "needs captures of one size (crop or resize them, or solve them separately)")
        on_device = any(isinstance(c, jax.Array) for c in images)
        if on_device:
            images = jnp.stack([jnp.asarray(c) for c in images])
        else:
            images = [np.asarray(c) for c in images]
            images = np.stack(images, out=aligned_empty((len(images), *shapes[0]),
                                                       np.result_type(*[c.dtype for c in images])))
    elif not isinstance(images, jax.Array):
        images = np.asarray(images)
    if images.ndim not in (4, 5):
        raise ValueError(
            f"images must be (N, K, H, W) or (N, K, H, W, C), got shape {images.shape}")
    if 0 in images.shape:
        raise ValueError(f"images must hold at least one capture, pixel and channel, got shape "
                         f"{images.shape}")
    return images


def _batched_fn(method, options, shared_lights, shared_mask, vmap_size):
    key = (method, shared_lights, shared_mask, vmap_size, tuple(sorted(options.items())))
    try:
        hash(key)
    except TypeError:
        key = None
    if key is not None and key in _CACHE:
        return _CACHE[key]

    def single(images, lights, mask, sample_mask):
        return photometric_stereo(images, lights, mask=mask, sample_mask=sample_mask,
                                  method=method, **options)

    # Shared lights / mask stay unbatched (closed over), so per-light work is done once.
    def batched(images, lights, mask, sample_mask):
        def one(xs):
            img, lt, msk, smask = xs
            return single(img, lights if shared_lights else lt,
                          mask if shared_mask else msk, smask)

        xs = (images, None if shared_lights else lights, None if shared_mask else mask,
              sample_mask)
        if vmap_size == "all":
            return jax.vmap(one)(xs)
        # `vmap_size=None`: one capture after another, so each keeps the single-call kernel
        # (its `lax.cond` stays a branch; under `vmap` both sides would run).
        return jax.lax.map(one, xs, batch_size=vmap_size)

    fn = jax.jit(batched)
    if key is not None:
        _CACHE[key] = fn
    return fn


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _l2_outputs(n, shape, dtype):
    """Zeroed `(N, ...)` outputs of an L2 batch (`result_specs`)."""
    return tuple(jnp.zeros(s, d) for s, d in result_specs((n,), shape, dtype))


def _check_out(out, n, shape, dtype):
    """`out`'s five arrays, checked against the `(N, H, W[, C])` batch they are to hold."""
    if not isinstance(out, PSResult):
        raise ValueError(f"out must be the PSResult of an earlier batch, got {type(out).__name__}")
    arrays = tuple(out[:5])
    for name, a, (e_shape, e_dtype) in zip(PSResult._fields, arrays,
                                           result_specs((n,), shape, dtype)):
        if not isinstance(a, jax.Array) or a.shape != e_shape or a.dtype != e_dtype:
            got = f"{getattr(a, 'shape', None)} {getattr(a, 'dtype', type(a).__name__)}"
            raise ValueError(f"out.{name} must be a JAX array {e_shape} {np.dtype(e_dtype)} to "
                             f"hold this batch, got {got}")
        if a.is_deleted():
            raise ValueError(f"out.{name} was already donated (passed as out= before)")
    return arrays


def _l2_one_image(images, lights, mask, sample_mask, shared_lights, shared_mask, options,
                  chunk, out=None):
    """The L2 batch on one device: each chunk (by default at most `_PIXELS_PER_PROGRAM`
    pixels) solved as one image of N times the pixels. One flag pass over the chunk comes
    back to the host (`l2_batch_flags`), then one program writes all five `(N, ...)` outputs,
    each in one pass on all threads (`l2_batch_solve`), into `out`'s buffers when given.
    Chunks of a longer batch are copied into the stacked outputs (`_write_block`). Solved
    capture by capture, a clean capture's program wrote each output through a
    `dynamic-update-slice` that XLA-CPU ran on one thread, and any other capture's was copied
    in after its solve (docs/speed.md, "Many captures")."""
    n, h, w = images.shape[0], images.shape[2], images.shape[3]
    dtype = jax.dtypes.canonicalize_dtype(images.dtype)  # float64 is float32 without x64
    solve_dtype = working_dtype(dtype)
    thresholds = tuple(jnp.asarray(t, solve_dtype) for t in _sample_thresholds(**options))
    lights = np.asarray(lights, np.float64)
    lights = lights / np.linalg.norm(lights, axis=-1, keepdims=True)
    # the pseudo-inverse etc. on the host: once, or per capture with a leading N axis
    consts = (host_constants(lights) if shared_lights else
              tuple(np.stack(c) for c in zip(*map(host_constants, lights))))
    if chunk is None:  # as many programs as `_PIXELS_PER_PROGRAM` needs, of one size
        programs = -(-n * h * w // _PIXELS_PER_PROGRAM)
        chunk = -(-n // programs)
    step = min(chunk, n)
    # XLA-CPU reads a 64-byte-aligned host array in place; anything else `device_put` copies,
    # on one thread: align such stacks on every core first (`aligned`). Other devices copy.
    threads = cpu_cores() if jax.default_backend() == "cpu" else 0

    def to_device(a):
        return jax.device_put(aligned(a, threads=threads) if threads else a)

    budget = keep_bytes()  # bytes kept for the next batch (read once per call)
    staging = None  # the aligned copy of a whole unaligned numpy stack, kept for the next

    def solve(sl, into=None):
        nonlocal staging

        def part(a, per_capture=True):
            return a if not per_capture or sl.stop - sl.start == n else a[sl]

        x = part(images)
        if isinstance(x, jax.Array):
            pass
        elif threads and sl.stop - sl.start == n:
            x, staging = _staged(x, threads, budget)
            x = jax.device_put(x)
        else:
            x = to_device(x)
        if shared_mask:  # one plane per capture: see `l2_batch_solve`
            msk = aligned_empty((sl.stop - sl.start, h, w), bool)
            msk[...] = mask
        else:
            msk = part(mask)
        msk = to_device(msk)
        smask = None if sample_mask is None else to_device(part(sample_mask))
        lt = jax.device_put(part(lights, not shared_lights).astype(solve_dtype))
        cst = jax.device_put(tuple(part(c, not shared_lights) for c in consts))
        flags = np.asarray(l2_batch_flags(x, msk, smask, thresholds))
        key = (x.shape, x.dtype)  # of the weighted solve's packed planes
        res, planes = l2_batch_solve(x, lt, msk, smask, thresholds, cst, dtype=dtype, out=into,
                                     branch=branch_of(int(np.bitwise_or.reduce(flags))),
                                     scratch=spare_outputs(_SCRATCH, key) if budget else None)
        if planes is not None:
            keep(_SCRATCH, key, planes, budget)
        return res

    fresh = out is None
    specs = result_specs((n,), tuple(images.shape[2:]), dtype)
    if fresh and budget > 0:  # an earlier batch's buffers, if its caller dropped them
        out = spare_outputs(_BATCH, specs)
    if step >= n:
        result = PSResult(*solve(slice(0, n), out))
    else:
        if out is None:
            out = _l2_outputs(n, tuple(images.shape[2:]), dtype)
        for start in range(0, n, step):
            out = _write_block(out, start, solve(slice(start, min(start + step, n))))
        result = PSResult(*out)
    if fresh:
        keep(_BATCH, specs, result[:5], budget)
    if staging is not None:  # the solve reads it: wait for it, then the next copy may reuse it
        jax.block_until_ready(result)
        _unstage(staging, budget)
    return result


@functools.partial(jax.jit, donate_argnums=0)
def _write_block(out, start, results):
    """A chunk's `(M, ...)` results written into the stacked outputs `out` from capture
    `start` on, in place (`out` is donated)."""
    return tuple(jax.lax.dynamic_update_slice_in_dim(o, r, start, 0)
                 for o, r in zip(out, results))


def _captures_on_threads(images, lights, mask, sample_mask, shared_lights, shared_mask,
                         method, options):
    """A batch of a loop solver (`barsky`, `irls`, `sbl`) on the CPU: each capture a top-level
    `photometric_stereo` call (which solves large captures in row bands on threads), on one
    thread per core, each result written into stacked host outputs as it arrives
    (`core._host.fill_on_threads`). Under `lax.map` the captures' `while_loop`s ran one after
    another on one thread."""
    n = images.shape[0]

    def args(i):
        return (images[i], lights if shared_lights else lights[i],
                mask if shared_mask else mask[i], None if sample_mask is None else sample_mask[i])

    def solve(x, lt, msk, smask):
        return photometric_stereo(x, lt, mask=msk, sample_mask=smask, method=method, **options)

    shapes = jax.tree.map(lambda s: jax.ShapeDtypeStruct((n, *s.shape), s.dtype),
                          jax.eval_shape(solve, *args(0)))
    parts = [lambda i=i: (i, solve(*args(i))) for i in range(n)]
    # `barsky` on a capture of one block runs no loop, and XLA-CPU spreads it over the cores
    # itself: captures at once would contend, so they run one after another
    one_block = method == "barsky" and images.shape[2] * images.shape[3] <= _robust._BLOCK
    return fill_on_threads(shapes, parts, 1 if one_block else min(cpu_cores(), n))


def photometric_stereo_batch(
    images: Float[ArrayLike, "N K H W *C"] | Sequence[Float[ArrayLike, "K H W *C"]],
    lights: Float[ArrayLike, "K 3"] | Float[ArrayLike, "N K 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | Bool[ArrayLike, "N H W"] | None = None,
    sample_mask: Bool[ArrayLike, "N K H W"] | None = None,
    method: str = "l2",
    chunk: int | None = None,
    vmap_size: int | None = None,
    out: PSResult | None = None,
    **options,
) -> PSResult:
    """Photometric stereo on N captures of one size at once, into `(N, ...)` outputs.

    **Arguments:**
    - `images`: `(N, K, H, W)` or `(N, K, H, W, C)`, or a list of N `(K, H, W[, C])` captures
      (all the same shape).
    - `lights`: `(K, 3)` shared by every capture, or `(N, K, 3)`.
    - `mask`: `(H, W)` shared or `(N, H, W)`; default all pixels.
    - `sample_mask`: `(N, K, H, W)` bool; default all samples.
    - `method`: one of `jaxps.PS_METHODS` (solver options as in `photometric_stereo`).
    - `chunk`: solve at most this many captures per call (bounds host/device memory). Default:
      all, except for `method="l2"` on one device, where chunks of equal size hold at most
      2^24 pixels each (16 captures of 1 MP).
    - `vmap_size`: captures vectorised together with `jax.vmap` inside one call; the groups run
      one after another (`jax.lax.map(..., batch_size=vmap_size)`). `None` (default) is the
      fastest on a CPU, where under `vmap` the L2 solver's branch on "some sample dropped" (a
      `lax.cond`) evaluates both sides. With `method="l2"` on one device, the captures are
      then solved as one image of N times the pixels: each chunk in one program, and one
      capture that drops a sample sends its chunk through the weighted solve, as one pixel
      does a single image. With `method="irls"`, `"sbl"` or `"barsky"` on one CPU, each
      capture is a call of its own, one per core at a time (`"barsky"` captures of at most
      32768 pixels one after another), whose results are written into stacked outputs
      (XLA-CPU runs their `while_loop`s on one thread). Other methods run the captures one
      after another. See docs/speed.md for the measured ratios.
    - `out`: the `PSResult` of an earlier batch of the same shape and dtype, whose arrays are
      overwritten with this batch's results and returned (they are donated: the old result is
      unusable afterwards). Only for `method="l2"` on one device. Fresh `(N, ...)` outputs are
      large enough that the allocator maps new pages for every batch, and the first write to
      each 4 KiB page costs a page fault (at 8 x 1 MP, `out=` took 22-41% less time than fresh
      outputs in three runs of `benchmarks/bench_batch.py`). Without `out`, such a batch
      keeps its latest two results and writes into one of them once the caller has dropped it
      (no reference left, numpy views included; a result still held is never written), so a
      loop `res = photometric_stereo_batch(...)` gets this without `out`. What is kept is
      bounded by `$JAXPS_BATCH_KEEP_BYTES` (default 1 GiB, `0` keeps nothing; nothing is
      kept on a free-threaded Python) and let go by `jaxps.ps.release_batch_outputs()`. A
      numpy stack that is not 64-byte aligned (as `np.stack` makes them) is copied into
      aligned memory, which XLA-CPU reads in place:
      into the previous such copy's buffer when it fits, and such a call waits for its
      results before it returns, so that the buffer is free for the next.

    With several devices the whole chunk is vmapped and its capture axis padded to a multiple
    of the device count and sharded across them (a 1-D mesh `"captures"`).

    **Returns:** a `PSResult` whose arrays have a leading N axis (`info` entries too).

    **Raises:** `ValueError` for captures of different sizes (naming the capture), or shapes of
    `lights`/`mask` that do not match, or an `out` that does not match the batch or cannot be
    used here.
    """
    if method not in PS_METHODS:
        raise ValueError(f"method must be one of {PS_METHODS}, got {method!r}")
    images = _stack_captures(images)
    if not np.issubdtype(images.dtype, np.floating):
        raise ValueError(f"images must be floating point in [0, 1], got {images.dtype}")
    _check_scale(images, options.get("saturation", 1.0), pixel_axis=2)
    n, k, h, w = images.shape[:4]
    lights = np.asarray(lights, np.float32)
    shared_lights = lights.shape == (k, 3)
    if shared_lights:
        lights = validate_lights(lights)
    elif lights.shape == (n, k, 3):
        lights = np.stack([validate_lights(lt) for lt in lights])
    else:
        raise ValueError(f"lights must be ({k}, 3) or ({n}, {k}, 3), got {lights.shape}")
    if mask is None:  # one all-true mask for every capture
        mask = np.ones((h, w), bool)
    mask = np.asarray(mask, bool)
    shared_mask = mask.shape == (h, w)
    if not shared_mask and mask.shape != (n, h, w):
        raise ValueError(f"mask must be ({h}, {w}) or ({n}, {h}, {w}), got {mask.shape}")
    if sample_mask is not None:
        sample_mask = np.asarray(sample_mask, bool)
        if sample_mask.shape != (n, k, h, w):
            raise ValueError(f"sample_mask must be {(n, k, h, w)}, got {sample_mask.shape}")
    if chunk is not None and not (isinstance(chunk, int) and chunk >= 1):
        raise ValueError(f"chunk must be a positive int, got {chunk!r}")

    if vmap_size is not None and not (isinstance(vmap_size, int) and vmap_size >= 1):
        raise ValueError(f"vmap_size must be a positive int or None, got {vmap_size!r}")
    if (method == "l2" and vmap_size is None and len(jax.devices()) == 1
            and set(options) <= _L2_OPTIONS and not isinstance(images, jax.core.Tracer)):
        if out is not None:
            out = _check_out(out, n, images.shape[2:],
                             jax.dtypes.canonicalize_dtype(images.dtype))
        return _l2_one_image(images, lights, mask, sample_mask, shared_lights, shared_mask,
                             options, chunk, out)
    if out is not None:
        raise ValueError("out: reusing a result is supported for method='l2' on one device "
                         "with vmap_size=None only")
    if (method in _BANDED_SOLVERS and vmap_size is None and len(jax.devices()) == 1
            and cpu_top_level(images, lights, mask, sample_mask)):
        return _captures_on_threads(images, lights, mask, sample_mask, shared_lights,
                                    shared_mask, method, options)
    fn = _batched_fn(method, options, shared_lights, shared_mask,
                     "all" if len(jax.devices()) > 1 else vmap_size)
    devices = jax.devices()
    step = n if chunk is None else chunk
    parts = []
    for start in range(0, n, step):
        sl = slice(start, min(start + step, n))
        part = images if (start == 0 and step >= n) else images[sl]
        args = [jax.device_put(part),  # in place when 64-byte aligned (core/_host.py)
                jnp.asarray(lights if shared_lights else lights[sl], images.dtype),
                jnp.asarray(mask if shared_mask else mask[sl]),
                None if sample_mask is None else jnp.asarray(sample_mask[sl])]
        batched = [True, not shared_lights, not shared_mask, sample_mask is not None]
        m = args[0].shape[0]
        if len(devices) > 1:
            pad = (-m) % len(devices)
            mesh = jax.sharding.Mesh(np.array(devices), ("captures",))
            split = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("captures"))
            whole = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
            args = [a if a is None else jax.device_put(
                        jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]) if pad else a,
                        split) if b else jax.device_put(a, whole)
                    for a, b in zip(args, batched)]
        out = fn(*args)
        if len(devices) > 1:  # drop the padding (a slice is a copy: only when padded)
            out = jax.tree_util.tree_map(lambda x: x[:m], out)
        parts.append(out)
    if len(parts) == 1:
        return parts[0]
    return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *parts)
