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


def aligned(array, dtype=None) -> np.ndarray:
    """`array` as a C-contiguous, 64-byte-aligned numpy array (itself when it already is one)."""
    array = np.asarray(array, dtype)
    if array.flags.c_contiguous and array.ctypes.data % ALIGNMENT == 0:
        return array
    out = aligned_empty(array.shape, array.dtype)
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


# XLA-CPU's older loop emitters, for the programs measured faster with them: the grid
# integrators (many small CG fusions; `benchmarks/bench_integration.py`) and L2's
# every-sample-used solve (`benchmarks/bench_l2_programs.py`); docs/speed.md.
OLDER_EMITTERS = {"xla_cpu_use_fusion_emitters": False}
