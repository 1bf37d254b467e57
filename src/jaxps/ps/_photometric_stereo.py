"""The public photometric-stereo entry point: validates input, then dispatches on `method`.

Every solver has the signature
`solver(images, lights, mask, sample_mask, thresholds, **options) -> PSResult` with `images`
`(K, H, W, C)` (C=1 for grey), `lights` `(K, 3)` unit vectors or `(K, H, W, 3)`, `mask` `(H, W)`
bool, `sample_mask` `(K, H, W)` bool and `thresholds` = (dark, saturation, shadow) scalars.
"""

from __future__ import annotations

import functools
import importlib
import inspect

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from ..core._host import (
    OLDER_EMITTERS,
    CpuTuned,
    cpu_cores,
    cpu_top_level,
    fill_on_threads,
    to_device,
)
from ..core._kept import _SINGLE, KEEP_FROM_BYTES, keep, keep_bytes, result_specs, spare_outputs
from ..core._store import active as store_active
from ..core._store import call as stored_call
from ..lights._directions import frame_count_error, validate_lights
from ._l2 import PSResult, host_constants, l2_branch, working_dtype

__all__ = ["PS_METHODS", "photometric_stereo"]

# method -> (module of this package, solver). Modules load on first use, so the iterative
# solvers' optimistix and equinox are not imported by a plain L2 run.
_SOLVERS = {
    "l2": ("_l2", "ps_l2"),
    "l1": ("_l1", "ps_l1"),
    "barsky": ("_robust", "ps_barsky"),
    "irls": ("_robust", "ps_irls"),
    "sbl": ("_robust", "ps_sbl"),
    "semi_calibrated": ("_semicalibrated", "ps_semi_calibrated"),
    "oren_nayar": ("_oren_nayar", "ps_oren_nayar"),
}
PS_METHODS: tuple[str, ...] = tuple(_SOLVERS)
# Solvers that check their options on concrete values (and jit their own cores) are called
# outside the wrapper's jit.
_EAGER_SOLVERS = frozenset({"semi_calibrated", "oren_nayar"})
# Solvers that run XLA `while_loop`s over the image (their per-pixel loops, or `lax.map` over
# blocks of pixels), which XLA-CPU runs on one thread. A top-level CPU call solves them in row
# bands of at least `_BAND_PIXELS` pixels, one band per core, each band a call of its own on a
# thread of its own: pixels are independent, so the results are those of one call
# (docs/robust.md, "Row bands on threads").
_BANDED_SOLVERS = frozenset({"barsky", "irls", "sbl"})
_BAND_PIXELS = 1 << 14


def _sample_thresholds(shadow_threshold: float | None = None, saturation: float = 1.0,
                      dark_threshold: float = 1e-3) -> tuple[float, float, float]:
    """`(dark, saturation, shadow)` as the L2 kernels take them (see `photometric_stereo`)."""
    for name, value in (("saturation", saturation), ("dark_threshold", dark_threshold)):
        if not np.isfinite(value):
            raise ValueError(f"{name} must be finite, got {value}")
    # NaN compares false with every sample: every sample would be dropped, every pixel failed
    if shadow_threshold is not None and np.isnan(shadow_threshold):
        raise ValueError("shadow_threshold must be a number or None (keep every sample), got nan")
    if shadow_threshold is not None and shadow_threshold >= saturation:
        # a sample is usable only below saturation and at or above the shadow threshold
        raise ValueError(f"shadow_threshold ({shadow_threshold:g}) must be below saturation "
                         f"({saturation:g}): every sample would be dropped")
    return dark_threshold, saturation, -np.inf if shadow_threshold is None else shadow_threshold


def _host_values(images) -> np.ndarray | None:
    """`images` as a numpy array read in place, or None where that would wait or copy: a
    traced array, one still being computed or copied, or one on another device."""
    if isinstance(images, np.ndarray):
        return images
    if (isinstance(images, jax.core.Tracer) or not images.is_fully_addressable
            or not images.is_ready() or any(d.platform != "cpu" for d in images.devices())):
        return None
    return np.asarray(images)


def _check_scale(images, saturation: float, pixel_axis: int = 1) -> None:
    """Raise for images on a 0..255 or 0..65535 scale: every sample of them is at or above the
    default `saturation` of 1, so without this every pixel would come back `SATURATED`, with
    normal (0, 0, 1) and albedo 0, and no word. `pixel_axis`: the H axis (then W).

    Reads at most 16 x 16 pixels of every frame in place on the host (microseconds); arrays
    that are not on the host yet are not checked (`_host_values`), so no call waits for it.
    Data in [0, 1] never trips it, even after a gain correction: it needs a quarter of the
    samples read at or above `saturation` and one above twice it.
    """
    values = _host_values(images)
    if values is None or not saturation > 0:
        return
    h, w = values.shape[pixel_axis:pixel_axis + 2]
    rows, cols = (np.arange(16) * (n - 1) // 15 if n > 16 else np.arange(n) for n in (h, w))
    probe = values[(slice(None),) * pixel_axis + (rows[:, None], cols[None, :])]
    top = probe.max(initial=-np.inf)
    if not (top > 2 * saturation or np.isnan(top)):  # the usual case, decided in one pass
        return
    probe = probe[np.isfinite(probe)]
    if probe.size and probe.max() > 2 * saturation and np.mean(probe >= saturation) >= 0.25:
        raise ValueError(
            f"images must be in [0, 1]: {np.mean(probe >= saturation):.0%} of the samples "
            f"checked are at or above saturation={saturation:g} (largest {probe.max():g}), "
            "and every such sample would be dropped as saturated. Divide 8-bit data by 255 "
            "and 16-bit data by 65535, or give saturation on the images' own scale (e.g. 255)"
        )


@functools.cache
def _solver_options(method: str) -> tuple[str, ...]:
    """The keyword-only options of `method`'s solver (L2's `shared` and `branch` are the
    wrapper's own, not options)."""
    module, name = _SOLVERS[method]
    solver = getattr(importlib.import_module(f"{__package__}.{module}"), name)
    return tuple(p.name for p in inspect.signature(solver).parameters.values()
                 if p.kind is inspect.Parameter.KEYWORD_ONLY)


def _check_options(method: str, options: dict) -> None:
    # Before: an unknown option reached the solver and Python's TypeError named the
    # internal function (`ps_irls() got an unexpected keyword argument ...`).
    allowed = _solver_options(method)
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        takes = f"takes {', '.join(allowed)}" if allowed else "takes no options"
        raise ValueError(
            f"method={method!r} got unknown option(s) {', '.join(map(repr, unknown))}; it "
            f"{takes} (see jaxps.photometric_stereo's docs for each method)"
        )


def _check_binary(name: str, m) -> None:
    """A floating mask must hold only 0 and 1: anything else would count as inside (`!= 0`),
    so an anti-aliased or probability mask of 0.2 would be solved as if it were 1. Bool and
    integer masks, and traced ones, are taken as they are."""
    if m is None or isinstance(m, jax.core.Tracer):
        return
    if not jnp.issubdtype(m.dtype if hasattr(m, "dtype") else np.asarray(m).dtype,
                          jnp.floating):
        return
    values = np.asarray(m)
    if not np.all((values == 0) | (values == 1)):
        raise ValueError(f"{name} must be bool (or floating 0/1), got values other than 0 and 1 "
                         f"(e.g. {float(values[(values != 0) & (values != 1)].flat[0]):g}); "
                         f"threshold it, e.g. {name} > 0.5")


def _check_images(images) -> tuple[jax.Array | np.ndarray, bool]:
    # Host arrays stay on the host: the jitted solve takes them as arguments (in place when
    # 64-byte aligned, as `load_capture` returns them), where `jnp.asarray` would copy the
    # stack and, in a fresh process, compile a conversion for its shape.
    if not isinstance(images, jax.Array):
        images = np.asarray(images)
    if not jnp.issubdtype(images.dtype, jnp.floating):
        raise ValueError(
            f"images must be floating point in [0, 1] (got dtype {images.dtype}); divide 8-bit "
            "data by 255 and 16-bit data by 65535, or load with jaxps.acquisition.load_capture"
        )
    if images.ndim not in (3, 4):
        raise ValueError(
            f"images must be (K, H, W) grey or (K, H, W, C) colour, got shape {images.shape}"
        )
    if 0 in images.shape:
        raise ValueError(f"images must have at least one pixel and channel, got shape "
                         f"{images.shape}")
    return images, images.ndim == 3


def photometric_stereo(
    images: Float[ArrayLike, "K H W *C"],
    lights: Float[ArrayLike, "K 3"] | Float[ArrayLike, "K H W 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    method: str = "l2",
    sample_mask: Bool[ArrayLike, "K H W"] | None = None,
    shadow_threshold: float | None = None,
    saturation: float = 1.0,
    dark_threshold: float = 1e-3,
    **options,
) -> PSResult:
    """Per-pixel albedo and unit normal from K >= 3 images under known distant lights.

    Least squares under Lambert's law (Woodham 1980), solved independently per pixel: a
    one-pixel kernel lifted with `jax.vmap`, jitted. Samples that are NaN/Inf, at or above
    `saturation` (any channel), below `shadow_threshold` (grey mean) or false in `sample_mask`
    are left out of that pixel's solve; a pixel left with fewer than 3 usable samples, or whose
    usable lights do not span 3-D, gets a non-zero `status` and the finite defaults
    normal (0, 0, 1), albedo 0. Colour stacks share one normal (from the channel-mean solve)
    and get per-channel albedo.

    **Arguments:**
    - `images`: `(K, H, W)` grey or `(K, H, W, C)` colour, floating point, linear, in [0, 1].
    - `lights`: `(K, 3)` directions toward the lights (normalised here), or `(K, H, W, 3)` per
      pixel for near lights.
    - `mask`: `(H, W)` bool (or floating 0/1), pixels to solve (default: all).
    - `method`: one of `jaxps.PS_METHODS`.
    - `sample_mask`: `(K, H, W)` bool, samples allowed into the solve (e.g. not saturated in
      the raw frame before ambient subtraction).
    - `shadow_threshold`: drop samples whose intensity is below this (default: keep all);
      below `saturation`.
    - `saturation`: samples at or above this are treated as saturated and dropped.
    - `dark_threshold`: a pixel whose brightest finite sample is at or below this is `DARK`.
    - `**options`: passed to the chosen solver (e.g. step limits of iterative methods).

    **Returns:** a `PSResult` (normals `(H, W, 3)`, albedo `(H, W)` or `(H, W, C)`, status,
    n_used, residual), in the floating dtype of `images` (float16 and bfloat16 frames are
    solved in float32).

    For `"l2"` on a grey stack with shared lights, a call on the CPU outside any
    `jit`/`grad`/`vmap` runs a program of its own that holds the flag pass (does any pixel
    drop a sample? is any sample non-finite?) and the three solves, and runs the one the
    flags call for. On a colour stack, with per-pixel lights, or with the store of compiled
    programs on (`jaxps.cli.enable_compilation_cache`, as `jaxps` commands have it) it first
    waits for one read of its flags and then compiles (or loads) and runs only the solve it
    needs (per-pixel lights always take the weighted solve). Inside a trace the choice is a
    `lax.cond` in the caller's program (docs/photometric_stereo.md, "How it is built").
    Such a call whose normals take more than 32 MiB (about 2.8 MP in float32) keeps its result,
    and a later call of the same shapes writes into one of the two latest once nothing else
    refers to it (not even a numpy view), instead of into fresh memory, which costs a page
    fault per 4 KiB; `$JAXPS_BATCH_KEEP_BYTES` bounds what is kept (default 1 GiB, `0`
    keeps none) and `jaxps.release_batch_outputs()` lets go of it.
    For `"irls"`, `"sbl"` and `"barsky"`, such a call on a multi-core CPU solves bands of rows
    on threads of their own (one per core, at least 16384 pixels each) and returns once all
    are done; the results are those of one call.

    **Raises:** `ValueError` for a wrong shape, dtype or method, an option the chosen
    `method` does not take, a floating mask with values other than 0 and 1, or a bad light
    set (see `validate_lights`).
    """
    if method not in PS_METHODS:
        raise ValueError(f"method must be one of {PS_METHODS}, got {method!r}")
    if options:
        _check_options(method, options)
    images, grey = _check_images(images)
    k, h, w = images.shape[:3]

    lights_shape = np.shape(lights)
    shared = None  # host constants of numpy lights
    if len(lights_shape) == 2:
        if lights_shape[1] != 3:
            raise ValueError(f"lights must be (K, 3) or (K, H, W, 3), got {lights_shape}")
        if isinstance(lights, jax.core.Tracer):
            lights = lights / jnp.linalg.norm(lights, axis=-1, keepdims=True)
        else:
            lights, shared = _checked_lights(np.asarray(lights, np.float64).tobytes(),
                                             lights_shape[0])
    elif lights_shape != (k, h, w, 3):
        raise ValueError(
            f"lights must be (K, 3) or (K, H, W, 3) = {(k, h, w, 3)} to match images "
            f"{tuple(images.shape[:3])}, got {lights_shape}"
        )
    if lights_shape[0] != k:
        raise frame_count_error(images.shape, lights_shape[0])
    if k < 3:
        raise ValueError(f"photometric stereo needs at least 3 images, got K={k}")
    if mask is not None and np.shape(mask) != (h, w):
        raise ValueError(f"mask must have shape (H, W) = {(h, w)}, got {np.shape(mask)}")
    if sample_mask is not None and np.shape(sample_mask) != (k, h, w):
        raise ValueError(
            f"sample_mask must have shape (K, H, W) = {(k, h, w)}, got {np.shape(sample_mask)}"
        )
    for name, m in (("mask", mask), ("sample_mask", sample_mask)):
        _check_binary(name, m)
    thresholds = _sample_thresholds(shadow_threshold, saturation, dark_threshold)
    _check_scale(images, saturation)

    # Arrays in `options` are traced; everything else (step limits, loss names, solver
    # objects) is static. Unhashable options fall back to running the wrapper eagerly.
    dynamic = {k: v for k, v in options.items() if isinstance(v, (jax.Array, np.ndarray))}
    branch = None
    if method == "l2" and shared is not None:
        dynamic["shared"] = shared  # no LAPACK call in the jitted solve
    per_pixel = len(lights_shape) == 4
    if (method == "l2" and ("shared" in dynamic or per_pixel)
            and cpu_top_level(images, lights, mask, sample_mask)):
        # Grey stacks with shared lights: the flag pass and the three solves in one program
        # with XLA-CPU's older emitters (`ps_l2(branch="switch")`). A flag program, its read
        # on the host and a program of the chosen solve alone took 1.10-1.45x as long at
        # 1 MP (`benchmarks/bench_l2_switch.py`), but compile and load only what runs. So
        # colour stacks, no faster in one program, per-pixel lights (always the weighted
        # solve; the flags say whether it must zero samples) and processes that load their
        # programs from the store (a `jaxps` command: the switch's executable made a warm
        # `jaxps reconstruct`'s photometric-stereo stage 0.06-0.09 s against 0.02-0.04 s,
        # `benchmarks/bench_cli.py`) take the solve on the host. The stacks go to the device
        # once.
        images = to_device(images)
        mask, sample_mask = (None if m is None else to_device(m, bool)
                             for m in (mask, sample_mask))
        if per_pixel or images.ndim == 4 or store_active():
            branch = l2_branch(images, mask, sample_mask, thresholds)
        else:
            branch = "switch"
        if per_pixel:
            lights = to_device(lights)
            branch = "weighted" if branch == "weighted" else "weighted_finite"
        options = {**options, "branch": branch}
    static = tuple(sorted((k, v) for k, v in options.items() if k not in dynamic))
    try:
        hash(static)
        run = _run.__wrapped__ if method in _EAGER_SOLVERS else _run
    except TypeError:
        run = _run.__wrapped__
    if run is not _run:
        images = to_device(images)  # the eager solvers take device arrays
    elif (branch is not None and not store_active()
          and h * w * 3 * images.dtype.itemsize > _KEEP_FROM_BYTES):  # a top-level L2 call
        return _into_kept_result(branch, images, lights, mask, sample_mask, thresholds,
                                 dynamic, method=method, static=static)
    elif branch in ("switch", "all_used"):
        run = _run_older_emitters
    elif method in _BANDED_SOLVERS and not dynamic:
        bands = min(cpu_cores(), h * w // _BAND_PIXELS, h)
        if bands > 1 and cpu_top_level(images, lights, mask, sample_mask):
            return _in_row_bands(images, lights, mask, sample_mask, thresholds, method,
                                 static, bands)
    return stored_call(run, images, lights, mask, sample_mask, thresholds, dynamic,
                       method=method, static=static)


def _in_row_bands(images, lights, mask, sample_mask, thresholds, method, static, n):
    """`_run` on `n` bands of rows, each on its own thread, joined into one `PSResult`
    (`core._host.fill_on_threads`).

    Every band has the same height (the last one padded with masked rows), so one program
    is compiled for all of them. Bands are numpy views of host arrays (CPU arrays are read in
    place), which `_run` takes as arguments.
    """
    h, w = images.shape[1:3]
    rows = -(-h // n)
    images, lights = np.asarray(images), np.asarray(lights)
    mask = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    sample_mask = None if sample_mask is None else np.asarray(sample_mask, bool)

    def span(i):
        return i * rows, min((i + 1) * rows, h)

    def args(i):
        top, bottom = span(i)
        pad = rows - (bottom - top)

        def cut(a, axis, **kw):
            a = a[(slice(None),) * axis + (slice(top, bottom),)]
            if pad:  # the last band: masked rows below the image
                widths = [(0, 0)] * a.ndim
                widths[axis] = (0, pad)
                a = np.pad(a, widths, **kw)
            return a

        return (cut(images, 1), lights if lights.ndim == 2 else cut(lights, 1, mode="edge"),
                cut(mask, 0), None if sample_mask is None else cut(sample_mask, 1))

    def solve(x, lt, m, samples):
        return _run(x, lt, m, samples, thresholds, {}, method=method, static=static)

    def band(i):
        top, bottom = span(i)
        return slice(top, bottom), jax.tree.map(lambda a: np.asarray(a)[:bottom - top],
                                                solve(*args(i)))

    shapes = jax.tree.map(lambda s: jax.ShapeDtypeStruct((h, *s.shape[1:]), s.dtype),
                          jax.eval_shape(solve, *args(0)))
    return fill_on_threads(shapes, [functools.partial(band, i) for i in range(n)], n)


# A scanner's calls share one light set: its checks and the host constants (three small
# SVDs, most of the wrapper's own time per call) are kept for the last few sets, by their
# bytes. The arrays are shared between calls, so they are made read-only.
@functools.lru_cache(maxsize=16)
def _checked_lights(data: bytes, k: int) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """`(K, 3)` float64 lights given as their bytes, checked (`validate_lights`, which raises
    for a bad set: nothing is kept then) and unit-normalised, and their `host_constants`."""
    lights = np.frombuffer(data, np.float64).reshape(k, 3)
    validate_lights(lights)  # the checks; it returns float32, so normalise here
    lights = lights / np.linalg.norm(lights, axis=-1, keepdims=True)
    constants = host_constants(lights)
    for a in (lights, *constants):
        a.setflags(write=False)
    return lights, constants


@functools.partial(jax.jit, static_argnames=("method", "static"))
def _run(images, lights, mask, sample_mask, thresholds, dynamic, *, method, static):
    """Casts, default masks and the grey channel axis, inside one jit with the solver.

    Done here rather than eagerly so that no full-size temporary (an expanded or sliced copy
    of the stack, an all-true mask) is written to memory where XLA can fuse it away. L2 gets
    no all-true mask at all: as an operand of its `switch` one was written on every call.
    """
    out_dtype = images.dtype
    dtype = working_dtype(images.dtype)
    grey = images.ndim == 3
    images = images.astype(dtype)
    # L2 takes grey stacks as they are: a channel axis added here is fused into each pass of
    # a solve compiled on its own (the host-chosen branch), 3x slower weighted at K=12
    if grey and method != "l2":
        images = images[..., None]
    k, h, w = images.shape[:3]
    # L2 takes None: one `True` in its kernels, where an all-true plane built here was
    # written to memory as an operand of its `switch` (a page fault per 4 KiB of it)
    if mask is not None:
        mask = jnp.asarray(mask, bool)
    elif method != "l2":
        mask = jnp.ones((h, w), bool)
    if sample_mask is not None:
        sample_mask = jnp.asarray(sample_mask, bool)
    elif method != "l2":  # L2 takes None (no mask planes to read, or to copy into its `cond`)
        sample_mask = jnp.ones((k, h, w), bool)
    thresholds = tuple(jnp.asarray(t, dtype) for t in thresholds)
    module, name = _SOLVERS[method]
    solver = getattr(importlib.import_module(f"{__package__}.{module}"), name)
    res = solver(images, jnp.asarray(lights, dtype), mask, sample_mask, thresholds,
                 **dict(static), **dynamic)
    albedo = res.albedo[..., 0] if grey and method != "l2" else res.albedo
    return PSResult(
        res.normals.astype(out_dtype),
        albedo.astype(out_dtype),
        res.status,
        res.n_used,
        res.residual.astype(out_dtype),
        res.info,
    )


# L2's flag pass and solves (`branch="switch"`), or its every-sample-used solve alone, as a
# top-level CPU program, with XLA-CPU's older emitters. Compiled on its own, the
# every-sample-used solve took 7.2-8.3 against 10.3-10.8 ms with them at 1 MP, K=5 (three runs
# of `benchmarks/bench_l2_programs.py`); the switch 0.71-0.98x its time with the default
# ones on grey stacks, every sample used or 5% dropped (`benchmarks/bench_l2_switch.py`).
_run_older_emitters = CpuTuned(_run.__wrapped__, OLDER_EMITTERS,
                               static_argnames=("method", "static"))


def _run_into(out, *args, **kwargs):
    del out  # donated: XLA writes each output into its buffer (`keep_unused` keeps it)
    return _run.__wrapped__(*args, **kwargs)


_run_older_emitters_into = CpuTuned(_run_into, OLDER_EMITTERS, static_argnames=("method", "static"),
                                    donate_argnums=0, keep_unused=True)
_run_into_out = jax.jit(_run_into, static_argnames=("method", "static"), donate_argnums=0,
                        keep_unused=True)
# A top-level L2 call whose normals take more bytes than this writes into a kept result
# (`_into_kept_result`): the first write to each 4 KiB page of fresh memory is a page fault.
_KEEP_FROM_BYTES = KEEP_FROM_BYTES


def _into_kept_result(branch, images, lights, mask, sample_mask, thresholds, dynamic, **static):
    """A top-level L2 call on the CPU whose solve `branch` was chosen (arguments as `_run`
    takes them), written into the buffers of one of the two latest such results of the same
    shapes once its caller has let go of it (`_kept.spare_outputs`), else into fresh memory;
    the result is kept in turn, within `$JAXPS_BATCH_KEEP_BYTES`. At 4096x4096, K=5 a call
    took 5.7-6.2 against 10.0-10.1 ns a pixel with nothing kept (`benchmarks/bench_core.py`;
    docs/speed.md, "Why the time per pixel grows")."""
    specs = result_specs((), images.shape[1:], images.dtype)
    budget = keep_bytes()
    out = spare_outputs(_SINGLE, specs) if budget else None
    args = (images, lights, mask, sample_mask, thresholds, dynamic)
    if branch in ("switch", "all_used"):  # as `photometric_stereo` runs them
        run, run_into = _run_older_emitters, _run_older_emitters_into
    else:
        run, run_into = _run, _run_into_out
    res = run(*args, **static) if out is None else run_into(out, *args, **static)
    keep(_SINGLE, specs, res[:5], budget)
    return res
