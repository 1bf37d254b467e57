"""Row bands on threads (docs/robust.md): which solvers gain from them, on `bench_robust.py`'s
1280x1024, K=5 scene, in one process. Per method, median of 7 calls after a first one:

- `one program`: the whole image as one call (bands switched off);
- `library`: `photometric_stereo` as it is (row bands on threads for the solvers in
  `_BANDED_SOLVERS`, one per core);
- `halves on threads`: the image cut into two halves of rows, each a call (bands off) on a
  thread of its own, joined by nothing (what banding could give a method at best on 2 cores);
- `2x bands`: twice as many bands as cores, each on a thread of its own (for the banded
  solvers).

Then batches of the banded solvers (8 captures of 192x168, 4 of 512x640, each frame scaled by
its own gain): `photometric_stereo_batch` as it is (captures on threads), the jitted `lax.map`
path it took before (`vmap_size=1`), and one `photometric_stereo` call per capture.

Rounds interleave the variants, so a busy machine hits them alike.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/robust_bands.py
"""

from __future__ import annotations

import statistics
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np

try:
    from benchmarks._common import arguments, environment, interleaved, write_json
except ImportError:  # run as a script
    import pathlib

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, environment, interleaved, write_json


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
            if name == "2x bands":
                ps.cpu_cores = lambda: 2 * cores
                try:
                    return call(images, mask, method)
                finally:
                    ps.cpu_cores = cpu_cores
            ps._BAND_PIXELS = 1 << 40  # bands off
            try:
                if name == "one program":
                    return call(images, mask, method)
                halves = ((images[:, :h // 2], mask[:h // 2]), (images[:, h // 2:], mask[h // 2:]))
                return list(pool.map(lambda a: call(*a, method), halves))
            finally:
                ps._BAND_PIXELS = banded_pixels

        return run

    names = ["one program", "library", "halves on threads"]
    cases = {(m, n): variant(m, n) for m in methods
             for n in names + (["2x bands"] if m in ps._BANDED_SOLVERS else [])}
    _, times = interleaved(cases, rounds)
    out = {"environment": environment(), "image": [h, w], "lights": 5, "cores": cores,
           "rounds": rounds, "band_pixels": banded_pixels, "seconds_median": {}}
    for (m, n), ts in times.items():
        out["seconds_median"].setdefault(m, {})[n] = statistics.median(ts)
        print(f"{m:7s} {n:18s} {statistics.median(ts):.4f} s  (min {min(ts):.4f})", flush=True)
    out["batch_seconds_median"] = batches(rounds)
    print("written", write_json("robust_bands", out))


def batches(rounds):
    import jax

    import jaxps
    from jaxps.ps._photometric_stereo import _BANDED_SOLVERS
    from jaxps.stability import render_corrupted, ring_lights

    out = {}
    for n, h, w in ((8, 192, 168), (4, 512, 640)):
        sc = render_corrupted(jaxps.synthetic.face_like(h, w), ring_lights(5, 45.0),
                              specular=0.6, shininess=100.0, noise=0.005, key=jax.random.key(0))
        gains = np.random.default_rng(0).uniform(0.85, 1.15, (n, 5, 1, 1)).astype(np.float32)
        images = np.asarray(sc.images)[None] * gains
        lights, mask = np.asarray(sc.lights), np.asarray(sc.mask)
        for method in sorted(_BANDED_SOLVERS):
            def batch(m=method, im=images, lt=lights, mk=mask, **kw):
                return jaxps.photometric_stereo_batch(im, lt, mask=mk, method=m, **kw)

            def singles(m=method, im=images, lt=lights, mk=mask):
                return [jaxps.photometric_stereo(c, lt, mask=mk, method=m) for c in im]

            cases = {"batch": batch, "batch lax.map (vmap_size=1)": lambda: batch(vmap_size=1),
                     "single calls": singles}
            _, times = interleaved(cases, rounds)
            key = f"{method} {n}x{h}x{w}"
            out[key] = {c: statistics.median(ts) for c, ts in times.items()}
            print(key, "  ".join(f"{c} {v:.4f} s" for c, v in out[key].items()), flush=True)
    return out


if __name__ == "__main__":
    arguments(__doc__)
    main()
