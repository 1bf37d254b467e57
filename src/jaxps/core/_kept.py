"""Memory that large calls keep for reuse: L2 results and heights (a later call of the same
shapes writes into the buffers of one the caller has let go of, instead of into fresh memory),
a batch's aligned copy of its stack, and the intermediate planes of the weighted batch solve
and of the FFT integrators (Frankot–Chellappa and the DCT solve).

XLA-CPU allocates each call's outputs with `malloc`. glibc serves a block larger than its
mmap threshold (which rises to at most 32 MiB) with a fresh `mmap` and unmaps it on `free`,
so every call writing such outputs maps and zeroes new pages, a page fault per 4 KiB
(docs/speed.md, "Why the time per pixel grows"). Keeping the latest results and donating a
dropped one, as `out=` does, removes that.

A result is reused only when nothing outside these lists refers to any of its arrays:
`sys.getrefcount` against the count for an object only a list holds. A numpy view of an
array (`np.asarray`) holds it through a memoryview, so it counts as held. A free-threaded
interpreter counts references lazily: there nothing is kept (`keep_bytes` gives 0).
"""

from __future__ import annotations

import os
import sys
import threading

import numpy as np

__all__ = [
    "KEEP_FROM_BYTES", "keep", "keep_bytes", "release_batch_outputs", "result_specs",
    "spare_outputs",
]

# Entries `(key, arrays)`, newest first (`keep`, `spare_outputs`). Results, keyed by their
# `result_specs`: of L2 batches (`photometric_stereo_batch`), and of single calls whose normals
# alone exceed glibc's largest mmap threshold (`photometric_stereo`). Two entries each: in
# `res = photometric_stereo(...)` in a loop, `res` still holds the previous result while the
# next call runs, so the one before it is the one free.
_BATCH: list[tuple] = []
_SINGLE: list[tuple] = []
_ENTRIES = 2
# The aligned copy of the latest unaligned numpy stack of a batch (`_batch._staged`).
_STAGE: list[np.ndarray] = []
# The weighted batch solve's packed planes of the latest two chunks that took it
# (`l2_batch_solve`'s `scratch`), keyed by the `(shape, dtype)` of the chunk's stack, since a
# batch's last chunk may be smaller than the others: never returned to a caller.
_SCRATCH: list[tuple] = []
# Heights of `integrate(method="fc" | "dct")` calls whose normals exceed glibc's largest mmap
# threshold, keyed by `(shape, dtype)`, and the intermediate planes of the latest two such calls
# (never returned to a caller), keyed by the method and the planes' `(shape, dtype)`s.
_HEIGHTS: list[tuple] = []
_INTEGRATE_SCRATCH: list[tuple] = []
_LOCK = threading.Lock()
# A single call whose normals take more bytes than this writes into kept memory: glibc maps
# blocks above its mmap threshold, which rises to 32 MiB at most, afresh on every call.
KEEP_FROM_BYTES = 32 << 20
_KEEP_DEFAULT = 1 << 30


def keep_bytes() -> int:
    """Bytes kept for reuse, for each list on its own: `$JAXPS_BATCH_KEEP_BYTES`, default
    1 GiB; 0 on a free-threaded interpreter."""
    value = os.environ.get("JAXPS_BATCH_KEEP_BYTES", "")
    try:
        budget = _KEEP_DEFAULT if value == "" else max(int(value), 0)
    except ValueError:
        raise ValueError("JAXPS_BATCH_KEEP_BYTES must be a whole number of bytes (0 keeps "
                         f"none), got {value!r}") from None
    return budget if _REFCOUNTS_EXACT else 0


def refcounts(arrays) -> list[int]:
    """`sys.getrefcount` of each item of a tuple or list (indexed, so that no loop variable
    adds a reference of its own)."""
    return [sys.getrefcount(arrays[i]) for i in range(len(arrays))]


# What `refcounts` gives for an object that only its tuple (or list) holds (measured, not
# assumed: interpreters differ in the references a call keeps).
ONLY_HELD_HERE = refcounts((object(),))[0]
_REFCOUNTS_EXACT = getattr(sys, "_is_gil_enabled", lambda: True)()


def result_specs(lead: tuple, shape: tuple, dtype) -> tuple:
    """`(shape, dtype)` of the five arrays of an L2 result (a `PSResult`'s), with leading axes
    `lead` (`()` for one capture, `(N,)` for a batch); `shape` is one capture's `(H, W[, C])`
    and `dtype` that of its normals, albedo and residual."""
    h, w = shape[:2]
    dtype, i32 = np.dtype(dtype), np.dtype(np.int32)
    return (((*lead, h, w, 3), dtype), ((*lead, *shape), dtype), ((*lead, h, w), i32),
            ((*lead, h, w), i32), ((*lead, h, w), dtype))


def spare_outputs(kept: list, key) -> tuple | None:
    """The arrays of an entry of `kept` with `key` (for results, their `result_specs`), taken
    out of it, when nothing outside it refers to any of them any more (so donating them
    cannot change anything the caller sees); else None. Should a buffer still have an outside
    reference, XLA declines its donation and writes a fresh one."""
    with _LOCK:
        for i, (k, arrays) in enumerate(kept):
            if k != key or any(a.is_deleted() for a in arrays):  # deleted: donated (`out=`)
                continue
            if max(refcounts(arrays)) <= ONLY_HELD_HERE:
                return kept.pop(i)[1]
    return None


def keep(kept: list, key, arrays, budget: int) -> None:
    """Put `arrays` first in `kept` under `key`; `kept` holds at most two entries within
    `budget` bytes (`keep_bytes()`; with 0, nothing is kept and what was is let go)."""
    with _LOCK:
        kept.insert(0, (key, tuple(arrays)))
        out, total = [], 0
        for entry in kept[:_ENTRIES]:
            size = sum(a.nbytes for a in entry[1])
            if total + size <= budget and not any(a.is_deleted() for a in entry[1]):
                out.append(entry)
                total += size
        kept[:] = out


def release_batch_outputs() -> None:
    """Let go of the results that `photometric_stereo_batch`, `photometric_stereo` and
    `integrate` keep for reuse.

    An L2 batch on one device keeps its latest two results, and so does a top-level L2 call on
    the CPU whose normals exceed 32 MiB (about 2.8 MP): the next calls of the same shapes write
    into their buffers once the caller has dropped them, instead of into fresh memory, which
    costs a page fault per 4 KiB (docs/speed.md, "Many captures"). A result the caller still
    holds is never written to. A batch also keeps the aligned copy of the latest unaligned
    numpy stack and the weighted solve's intermediate planes of the latest batch that dropped
    samples. `integrate(method="fc" | "dct")` keeps its latest two heights and its
    intermediate planes in the same way when its normals exceed 32 MiB. Each of these is
    bounded by `$JAXPS_BATCH_KEEP_BYTES` (default 1 GiB; `0` keeps none). This frees what is
    kept, e.g. at the end of a stream of large captures."""
    with _LOCK:
        for kept in (_BATCH, _SINGLE, _STAGE, _SCRATCH, _HEIGHTS, _INTEGRATE_SCRATCH):
            kept.clear()
