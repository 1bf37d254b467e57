"""Host arrays that XLA-CPU reads in place.

A numpy array passed to a jitted function on the CPU is used without a copy when its data
start on a 64-byte boundary; numpy's own allocations are only 16-byte aligned, and then every
call copies the whole array first (about 10 ms for five 1280x1024 float32 frames on this
project's machine, `benchmarks/bench_batch.py`). Stacks that jaxps builds on the host are
therefore allocated here.
"""

from __future__ import annotations

import numpy as np

ALIGNMENT = 64


def aligned_empty(shape, dtype) -> np.ndarray:
    """An uninitialised C-contiguous array whose data start on a 64-byte boundary."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    buf = np.empty(nbytes + ALIGNMENT, np.uint8)
    start = (-buf.ctypes.data) % ALIGNMENT
    return buf[start:start + nbytes].view(dtype).reshape(shape)


def aligned(array, dtype=None, threads: int = 1, out=None) -> np.ndarray:
    """`array` as a C-contiguous, 64-byte-aligned numpy array (itself when it already is one).

    `threads` > 1 copies slices of the leading axis on that many threads: the first write to
    fresh memory is a page fault per 4 KiB, and threads take them at once. A 1 MP x 5 x 8
    float32 stack took 35 ms on 2 threads against 62 ms on one and 145 ms for
    `jax.device_put`'s own copy (`benchmarks/bench_batch.py --copy`). `out`: an aligned
    array of the same shape and dtype to copy into, instead of fresh memory."""
    array = np.asarray(array, dtype)
    if array.flags.c_contiguous and array.ctypes.data % ALIGNMENT == 0:
        return array
    if out is None:
        out = aligned_empty(array.shape, array.dtype)
    if threads > 1 and array.ndim and len(array) > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(min(threads, len(array))) as pool:
            list(pool.map(lambda i: np.copyto(out[i], array[i]), range(len(array))))
    else:
        out[...] = array
    return out


def to_device(array, dtype=None):
    """`array` as a JAX array: JAX arrays (and tracers) as they are, anything else through
    `jax.device_put`. `jnp.asarray` on a numpy array is a jitted conversion in this JAX: in a
    fresh process it compiles once per shape (about 10-20 ms each on the command line) and it
    always copies, where `device_put` of a 64-byte-aligned array does not."""
    import jax

    if isinstance(array, jax.Array):
        return array if dtype is None else array.astype(dtype)
    return jax.device_put(np.asarray(array, dtype))


def cpu_cores() -> int:
    """The CPU cores this process may run on (its affinity mask where the OS has one, which
    `os.cpu_count` ignores: a container limited to 2 cores of a 64-core host sees 64)."""
    import os

    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def fill_on_threads(shapes, parts, threads: int):
    """Aligned host arrays of the pytree `shapes` (`jax.ShapeDtypeStruct` leaves), filled on
    `threads` threads and returned as JAX arrays that read them in place.

    `parts`: callables, each returning `(index, tree)` whose leaves are written at `[index]`
    of the matching arrays, by the thread that computed them. For work XLA-CPU runs on one
    thread (a `while_loop`), split into independent calls: the calls run at once, and the
    joined result is written by several threads instead of a jitted concatenate on one.
    """
    from concurrent.futures import ThreadPoolExecutor

    import jax

    leaves, tree = jax.tree.flatten(shapes)
    outs = [aligned_empty(s.shape, s.dtype) for s in leaves]

    def run(part):
        index, result = part()
        for out, a in zip(outs, jax.tree.leaves(result)):
            out[index] = np.asarray(a)

    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(run, parts))
    return jax.tree.unflatten(tree, [jax.device_put(o) for o in outs])


def has_value(array) -> bool:
    """Whether `array` holds a value now: anything but a tracer, or a tracer with a concrete
    value (`jax.grad`'s outside `jit`); False inside `jit` and `vmap`, where host-side checks
    and counts cannot run."""
    import jax

    if not isinstance(array, jax.core.Tracer):
        return True
    concrete = getattr(array, "to_concrete_value", None)
    return concrete is not None and concrete() is not None


def positive_scalar(value) -> bool:
    """Whether `value` is a finite scalar > 0, as argument checks ask of `pixel_size`; True
    where it has no value to test (inside `jit` or `vmap`, `has_value`). Tested with numpy
    where it can be: a `jnp` test inside a caller's `jit` is traced, even of a constant."""
    import jax
    import jax.numpy as jnp

    if np.ndim(value) != 0:
        return False
    if not has_value(value):
        return True
    if isinstance(value, jax.core.Tracer):  # `jax.grad`'s, outside `jit`: it has a value
        return bool(jnp.isfinite(value) & (value > 0))
    return bool(np.isfinite(value) and value > 0)


def cpu_top_level(*trees) -> bool:
    """Whether a jitted call with these arguments runs as its own program on the CPU: no
    argument is a tracer (JAX accepts `compiler_options` on top-level jits only; inside a
    user's `jit`/`grad` the call is traced into the caller's program) and the default backend
    is the CPU (the options below are XLA-CPU's). Callers then pick a jit compiled with
    XLA-CPU options."""
    import jax

    if jax.default_backend() != "cpu":
        return False
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(trees))


# XLA-CPU compile options, each for the programs measured faster with it (docs/speed.md):
# - the older loop emitters: the grid integrators (many small CG fusions;
#   `benchmarks/bench_integration.py`) and L2's every-sample-used solve
#   (`benchmarks/bench_l2_programs.py`);
# - no YNNPACK fusions (an empty list of fusion kinds): this JAX hands reductions, with the
#   elementwise work that feeds them, to YNNPACK, which ran the iterative solvers' sums over
#   the K samples slower than XLA's own loops (`benchmarks/bench_ynn.py`).
OLDER_EMITTERS = {"xla_cpu_use_fusion_emitters": False}
NO_YNN = {"xla_cpu_experimental_ynn_fusion_type": ""}


class CpuTuned:
    """`fun` jitted twice: plain, and with XLA-CPU `options` (`compiler_options`).

    A call takes the tuned program when it is a top-level call on the CPU (`cpu_top_level`:
    JAX takes compiler options on top-level jits only), else the plain one, which inside a
    trace is inlined into the caller's program as usual. The options are experimental flags:
    an XLA that does not know one (an older or newer JAX) rejects it when the tuned program
    is first compiled, before anything has run, and from then on every call takes the plain
    program (as every call does with a JAX whose `jit` takes no `compiler_options`). `jit`:
    `jax.jit` or `equinox.filter_jit`; `kwargs` go to both jits.
    """

    def __init__(self, fun, options, jit=None, **kwargs):
        import functools

        import jax

        jit = jax.jit if jit is None else jit
        self.plain = jit(fun, **kwargs)
        try:
            self.tuned = jit(fun, compiler_options=options, **kwargs)
        except TypeError:  # a JAX whose jit takes no compiler options
            self.tuned = None
        self.options = options
        self.known = self.tuned is not None  # False once this XLA has rejected an option
        functools.update_wrapper(self, fun)

    def __call__(self, *args, **kwargs):
        if self.known and cpu_top_level(args, kwargs):
            try:
                return self.tuned(*args, **kwargs)
            except Exception as error:  # XLA's error type differs between JAX versions
                if "compile option" not in str(error):
                    raise
                self.known = False
        return self.plain(*args, **kwargs)
