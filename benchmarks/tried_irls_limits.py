"""What holds `photometric_stereo(method="irls")` at 1280x1024 back (docs/speed.md, "Robust L1
at 1 MP"). On `bench_robust.py`'s scene, in one process:

- the whole call with the step limit at 1 and at its default (the fixed cost against the loop);
- the final weighted solve and outputs alone (`_planes` + `_finish_planes` + `_outputs`), and
  the number of XLA thunks (fusions) it runs, from a `jax.profiler` trace;
- the steps the `lax.map` chunks of 8192 pixels run (each until its slowest pixel converges)
  against the mean steps of an object pixel;
- the whole call with other chunk sizes (`_robust._CHUNK`, patched);
- two independent `fori_loop`s in one program against one (does XLA-CPU run them at once?).

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/tried_irls_limits.py
"""

from __future__ import annotations

import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxps
from jaxps.ps import _robust
from jaxps.stability import render_corrupted, ring_lights

try:
    from benchmarks.bench_spectral_split import thunks
except ImportError:  # run as a script
    import pathlib

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks.bench_spectral_split import thunks


def median_ms(fn, calls=7):
    jax.block_until_ready(fn())
    times = []
    for _ in range(calls):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times)


def main():
    h, w = 1024, 1280
    scene = render_corrupted(jaxps.synthetic.face_like(h, w), ring_lights(5, 45.0),
                             specular=0.6, shininess=100.0, noise=0.005, key=jax.random.key(0))
    images, lights, mask = (np.asarray(a) for a in (scene.images, scene.lights, scene.mask))

    def irls(**kw):
        return lambda: jaxps.photometric_stereo(images, lights, mask=mask, method="irls", **kw)

    for steps in (1, 200):
        print(f"irls, max_steps={steps}: {median_ms(irls(max_steps=steps)):.1f} ms")

    im, lt, m = jnp.asarray(images)[..., None], jnp.asarray(lights), jnp.asarray(mask)
    allowed = jnp.ones(im.shape[:3], bool)
    thr = (jnp.float32(0), jnp.float32(1), jnp.float32(0))

    @jax.jit
    def finish(im, lt, m, allowed, thr):
        x, grey, finite, unsat, used, lts = _robust._planes(im, lt, m, allowed, thr)
        out = _robust._finish_planes(x, grey, finite, unsat, used,
                                     [u.astype(im.dtype) for u in used], lts, thr[0],
                                     jnp.float32(0.05), jnp.array(True))
        return _robust._outputs(*out, jnp.zeros(h * w, jnp.int32), m, im.dtype)

    args = (im, lt, m, allowed, thr)
    print(f"final solve and outputs alone: {median_ms(lambda: finish(*args)):.1f} ms, "
          f"{len(thunks(lambda: finish(*args)))} thunks")

    steps = np.asarray(irls()().info["steps"]).reshape(-1)
    chunk = _robust._CHUNK
    padded = np.pad(steps, (0, -len(steps) % chunk)).reshape(-1, chunk)
    print(f"steps per chunk of {chunk} (mean of each chunk's slowest pixel): "
          f"{padded.max(1).mean():.1f}; per object pixel: {steps[mask.reshape(-1)].mean():.1f}")

    for size in (128, 2048, 8192):
        _robust._CHUNK = size
        jax.clear_caches()
        print(f"irls, chunks of {size}: {median_ms(irls()):.1f} ms")
    _robust._CHUNK = chunk

    def loop(x):
        return jax.lax.fori_loop(0, 200, lambda i, x: jnp.sin(x) * 1.0001 + 0.1, x)

    x = jnp.ones(1 << 14, jnp.float32)
    one, two = jax.jit(loop), jax.jit(lambda a, b: (loop(a), loop(b)))
    print(f"one fori_loop {median_ms(lambda: one(x)):.2f} ms, two independent ones in one "
          f"program {median_ms(lambda: two(x, x + 1)):.2f} ms")


if __name__ == "__main__":
    import argparse

    argparse.ArgumentParser(description=__doc__).parse_args()  # --help before any work
    main()
