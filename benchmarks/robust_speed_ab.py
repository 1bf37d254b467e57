"""Time the robust solvers of whichever jaxps is on `PYTHONPATH`, for A/B runs of two versions.

The 1280x1024, K=5 scene of `bench_robust.py`. Each method is called once to compile, then 7
times; the median and minimum are printed with the mean / median error against the truth.
`--save F` also writes `irls`'s per-pixel step counts, status and normals to `F` (.npz), and
`--compare A B` prints how two such files differ; `--size H W` and `--chunk N` change the
scene's size and the pixels per `lax.map` chunk of the iterative solvers, and `--block N` the
pixels per block of the whole solve. Run the versions alternately, e.g. with a worktree of
the older commit:

    git worktree add /tmp/old <commit>
    for i in 1 2; do
      OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/robust_speed_ab.py --save /tmp/new.npz
      OPENBLAS_NUM_THREADS=1 PYTHONPATH=/tmp/old/src python benchmarks/robust_speed_ab.py --save /tmp/old.npz
    done
    python benchmarks/robust_speed_ab.py --compare /tmp/new.npz /tmp/old.npz
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def run(methods, save, size=(1024, 1280), chunk=None, block=None):
    import jax

    import jaxps
    from jaxps.evaluate import angular_stats
    from jaxps.stability import render_corrupted, ring_lights

    print(jaxps.__file__, "chunk", chunk or "default", "block", block or "default", "size", size)
    from jaxps.ps import _robust

    if chunk:
        _robust._CHUNK = chunk
    if block:
        _robust._BLOCK = block
    surf = jaxps.synthetic.face_like(*size)
    scene = render_corrupted(surf, ring_lights(5, 45.0), specular=0.6, shininess=100.0,
                             noise=0.005, key=jax.random.key(0))
    images, lights, mask = (np.asarray(a) for a in (scene.images, scene.lights, scene.mask))
    for method in methods:
        def call(method=method):
            return jax.block_until_ready(
                jaxps.photometric_stereo(images, lights, mask=mask, method=method))
        res = call()
        times = []
        for _ in range(7):
            t = time.perf_counter()
            call()
            times.append(time.perf_counter() - t)
        st = angular_stats(res.normals, scene.normals, mask=mask)
        print(f"{method:<7} median {statistics.median(times):.4f} s  min {min(times):.4f} s  "
              f"error {st['mean_deg']:.4f} / {st['median_deg']:.4f} deg", flush=True)
        if save and method == "irls":
            np.savez(save, steps=np.asarray(res.info["steps"]), status=np.asarray(res.status),
                     normals=np.asarray(res.normals))


def compare(a, b):
    a, b = np.load(a), np.load(b)
    print("pixels whose steps differ:", int((a["steps"] != b["steps"]).sum()))
    print("pixels whose status differs:", int((a["status"] != b["status"]).sum()))
    print("largest normal component difference:", float(np.abs(a["normals"] - b["normals"]).max()))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--methods", nargs="+", default=["barsky", "irls", "sbl"])
    ap.add_argument("--save", help="write irls's steps, status and normals here (.npz)")
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"))
    ap.add_argument("--size", nargs=2, type=int, default=(1024, 1280), metavar=("H", "W"))
    ap.add_argument("--chunk", type=int, help="pixels per lax.map chunk of the loops "
                    "(patches `_robust._CHUNK`)")
    ap.add_argument("--block", type=int, help="pixels per block of the whole solve, in "
                    "versions that solve in blocks (patches `_robust._BLOCK`)")
    args = ap.parse_args()
    if args.compare:
        compare(*args.compare)
    else:
        run(args.methods, args.save, tuple(args.size), args.chunk, args.block)


if __name__ == "__main__":
    main()
