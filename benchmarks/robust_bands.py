"""Row bands on threads (docs/robust.md): which solvers gain from them, on `bench_robust.py`'s
1280x1024, K=5 scene, in one process. Per method, median of 7 calls after a first one:

- `one program`: the whole image as one call (bands switched off);
- `library`: `photometric_stereo` as it is (row bands on threads for `irls` and `sbl`);
- `halves on threads`: the image cut into two halves of rows, each a call (bands off) on a
  thread of its own, joined by nothing (what banding could give a method at best on 2 cores);
- `2x bands`: twice as many bands as cores (for `irls` and `sbl`).

Rounds interleave the variants, so a busy machine hits them alike.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/robust_bands.py
"""

from __future__ import annotations

import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

try:
    from benchmarks._common import environment, write_json
except ImportError:  # run as a script
    import pathlib

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import environment, write_json


def main(methods=("l2", "l1", "barsky", "irls", "sbl"), rounds=7):
    import jax

    import jaxps
    from jaxps.core._host import cpu_cores
    from jaxps.ps import _photometric_stereo as ps
    from jaxps.stability import render_corrupted, ring_lights

    h, w = 1024, 1280
    scene = render_corrupted(jaxps.synthetic.face_like(h, w), ring_lights(5, 45.0),
                             specular=0.6, shininess=100.0, noise=0.005, key=jax.random.key(0))
    images, lights, mask = (np.asarray(a) for a in (scene.images, scene.lights, scene.mask))
    cores = cpu_cores()
    pool = ThreadPoolExecutor(2)
    banded_pixels = ps._BAND_PIXELS

    def call(im, m, method):
        return jax.block_until_ready(jaxps.photometric_stereo(im, lights, mask=m, method=method))

    def variant(method, name):
        def run():
            if name == "library":
                return call(images, mask, method)
            ps._BAND_PIXELS = 1 << 40  # bands off
            try:
                if name == "one program":
                    return call(images, mask, method)
                halves = ((images[:, :h // 2], mask[:h // 2]), (images[:, h // 2:], mask[h // 2:]))
                return list(pool.map(lambda a: call(*a, method), halves))
            finally:
                ps._BAND_PIXELS = banded_pixels

        if name == "2x bands":
            def run():  # noqa: F811
                ps.cpu_cores = lambda: 2 * cores
                try:
                    return call(images, mask, method)
                finally:
                    ps.cpu_cores = cpu_cores
        return run

    names = ["one program", "library", "halves on threads"]
    cases = {(m, n): variant(m, n) for m in methods
             for n in names + (["2x bands"] if m in ps._BANDED_SOLVERS else [])}
    for fn in cases.values():
        fn()  # compile
    times = {c: [] for c in cases}
    for _ in range(rounds):
        for c, fn in cases.items():
            t = time.perf_counter()
            fn()
            times[c].append(time.perf_counter() - t)
    out = {"environment": environment(), "image": [h, w], "lights": 5, "cores": cores,
           "rounds": rounds, "band_pixels": banded_pixels, "seconds_median": {}}
    for (m, n), ts in times.items():
        out["seconds_median"].setdefault(m, {})[n] = statistics.median(ts)
        print(f"{m:7s} {n:18s} {statistics.median(ts):.4f} s  (min {min(ts):.4f})", flush=True)
    print("written", write_json("robust_bands", out))


if __name__ == "__main__":
    main()
