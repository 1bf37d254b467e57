"""L2's weighted solve, packed into two complex planes against the kernel before, interleaved.

The weighted solve (some samples dropped) of a host-chosen L2 branch computes $b$, the misfit
and the status codes with `_l2._pixel_weighted_packed`: two complex outputs carry four values
out of one loop over the image each, inside a `cond` that XLA cannot see through, and
`_l2._unpack_weighted` writes the five results from them. The kernel before
(`_pixel_weighted`, `packed=False`) wrote each output from a loop of its own, and each of
those loops solved the pixel's system again from all K samples.

Both programs solve the same 1280x1024 synthetic face with 5% of the samples in the mask
below a shadow threshold (grey, every sample finite: `all_finite`, as the flag pass finds),
for K = 4, 5, 8 and 12. They are timed in alternating order in one process, so that the
shared machine's slow spells fall on both; medians and minima of `--rounds` calls each. Also
recorded: the largest difference between their results (status and n_used must be equal) and
the loop fusions each program compiles to, counting those that read the whole stack of
samples (a `cond`'s two identical branches are both compiled, so the packed program's count
includes each of its fusions twice).

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_weighted_packed.py
    -> benchmarks/results/weighted_packed.json

`--per-pixel`: per-pixel `(K, H, W, 3)` lights instead (near lights: the scanner's five, each
perturbed per pixel and scaled by 2, so that the solve normalises them), every sample used,
K=5. Three programs, interleaved: the unpacked solve with the lights normalised as an array
first (the code before), the same normalised in the kernel (`_l2._unit_lights`), and the
packed solve with them normalised in the kernel (what a top-level call runs now).
-> benchmarks/results/weighted_packed_per_pixel.json
"""

from __future__ import annotations

import argparse
import functools
import re
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxps
from jaxps.ps import _l2

try:
    from benchmarks._common import environment, write_json
    from benchmarks.bench_core import ring_lights
except ImportError:  # run as a script
    import pathlib

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import environment, write_json
    from benchmarks.bench_core import ring_lights

H, W = 1024, 1280


@functools.partial(jax.jit, static_argnames=("packed",))
def _solve(images, lights, mask, thresholds, packed):
    return _l2._stacked(_l2._solve_weighted(images, lights, mask, None, thresholds, flat=False,
                                            all_finite=True, packed=packed))


def _fusions(text: str, k: int) -> dict:
    stack = f"f32[{k},{H},{W}]"
    heads = [line for line in text.splitlines() if line.startswith("%fused_computation")]
    return {"fusions": len(re.findall(r"= \S+ fusion\(", text)),
            "fusions_reading_the_stack": sum(stack in line.split("->")[0] for line in heads)}


def _row(k, surface, rounds):
    lights = jaxps.synthetic.scanner_lights(20.0, k=k) if k <= 5 else ring_lights(k)
    scene = jaxps.synthetic.render_scene(surface, lights)
    images, mask = jax.device_put(scene.images), jax.device_put(scene.mask)
    inside = np.asarray(scene.images)[:, np.asarray(scene.mask)]
    shadow = float(np.percentile(inside, 5))
    thresholds = tuple(jnp.float32(t) for t in (0.0, np.inf, shadow))
    lights = jnp.asarray(lights, jnp.float32)
    args = (images, lights, mask, thresholds)
    variants = {"before": False, "packed": True}
    out = {name: jax.block_until_ready(_solve(*args, packed=p)) for name, p in variants.items()}
    times = {name: [] for name in variants}
    for r in range(rounds):
        for name, p in (variants.items() if r % 2 else reversed(variants.items())):
            t = time.perf_counter()
            jax.block_until_ready(_solve(*args, packed=p))
            times[name].append(time.perf_counter() - t)
    before, packed = out["before"], out["packed"]
    row = {"K": k, "dropped_fraction": float(np.mean(inside < shadow)),
           "status_equal": bool(np.array_equal(before[2], packed[2])),
           "n_used_equal": bool(np.array_equal(before[3], packed[3])),
           "max_abs_diff": {name: float(np.max(np.abs(np.asarray(a, np.float64)
                                                      - np.asarray(b, np.float64))))
                            for name, a, b in zip(("normals", "albedo", "residual"),
                                                  (before[0], before[1], before[4]),
                                                  (packed[0], packed[1], packed[4]))}}
    for name, p in variants.items():
        row[name] = {"run_s_median": float(np.median(times[name])),
                     "run_s_min": float(np.min(times[name])),
                     **_fusions(_solve.lower(*args, packed=p).compile().as_text(), k)}
    row["median_ratio"] = row["packed"]["run_s_median"] / row["before"]["run_s_median"]
    print(f"K={k:2d}: before {1e3 * row['before']['run_s_median']:6.2f} ms "
          f"(min {1e3 * row['before']['run_s_min']:6.2f}), packed "
          f"{1e3 * row['packed']['run_s_median']:6.2f} ms "
          f"(min {1e3 * row['packed']['run_s_min']:6.2f}), ratio {row['median_ratio']:.3f}",
          flush=True)
    return row


@functools.partial(jax.jit, static_argnames=("variant",))
def _solve_per_pixel(images, lights, mask, thresholds, variant):
    if variant == "array-normalised, unpacked (before)":
        lights = lights / jnp.linalg.norm(lights, axis=-1, keepdims=True)
        lt = [[lights[i, ..., p] for p in range(3)] for i in range(lights.shape[0])]
        kernel = functools.partial(_l2._pixel_weighted, all_finite=True)
        return _l2._stacked(_l2._lift(kernel, (0, None, 0, 0, None), False)(
            *_l2._planes(images, None, mask, False), lt, thresholds))
    return _l2._stacked(_l2._solve_weighted(images, lights, mask, None, thresholds,
                                            flat=False, all_finite=True,
                                            packed=variant.endswith("packed")))


def _per_pixel(surface, rounds):
    k = 5
    lights = np.asarray(jaxps.synthetic.scanner_lights(20.0, k=k))
    scene = jaxps.synthetic.render_scene(surface, lights)
    images, mask = jax.device_put(scene.images), jax.device_put(scene.mask)
    rng = np.random.default_rng(0)
    near = 2 * (lights[:, None, None, :] + 0.05 * rng.standard_normal((k, H, W, 3)))
    near = jnp.asarray(near, jnp.float32)
    thresholds = tuple(jnp.float32(t) for t in (0.0, np.inf, -np.inf))
    variants = ["array-normalised, unpacked (before)", "kernel-normalised, unpacked",
                "kernel-normalised, packed"]
    args = (images, near, mask, thresholds)
    out = {v: jax.block_until_ready(_solve_per_pixel(*args, variant=v)) for v in variants}
    times = {v: [] for v in variants}
    for r in range(rounds):
        for v in (variants if r % 2 else variants[::-1]):
            t = time.perf_counter()
            jax.block_until_ready(_solve_per_pixel(*args, variant=v))
            times[v].append(time.perf_counter() - t)
    before = out[variants[0]]
    rows = []
    for v in variants:
        rows.append({"variant": v, "run_s_median": float(np.median(times[v])),
                     "run_s_min": float(np.min(times[v])),
                     "status_equal": bool(np.array_equal(before[2], out[v][2])),
                     "max_abs_diff_normals": float(np.max(np.abs(
                         np.asarray(before[0], np.float64) - np.asarray(out[v][0])))),
                     "median_ratio": float(np.median(times[v]) / np.median(times[variants[0]]))})
        print(f"{v:38s} {1e3 * rows[-1]['run_s_median']:7.2f} ms "
              f"(min {1e3 * rows[-1]['run_s_min']:7.2f}), ratio {rows[-1]['median_ratio']:.3f}",
              flush=True)
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=60)
    parser.add_argument("--quick", action="store_true", help="6 rounds (the runner's mode)")
    parser.add_argument("--per-pixel", action="store_true",
                        help="per-pixel lights, K=5, every sample used")
    args = parser.parse_args()
    if args.quick:
        args.rounds = 6
    surface = jaxps.synthetic.face_like(H, W)
    if args.per_pixel:
        write_json("weighted_packed_per_pixel", {
            "command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python "
                       "benchmarks/bench_weighted_packed.py --per-pixel",
            "shape": [H, W], "K": 5, "rounds": args.rounds, "env": environment(),
            "rows": _per_pixel(surface, args.rounds)})
        return
    rows = [_row(k, surface, args.rounds) for k in (4, 5, 8, 12)]
    write_json("weighted_packed", {
        "command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python "
                   "benchmarks/bench_weighted_packed.py",
        "shape": [H, W], "rounds": args.rounds, "env": environment(), "rows": rows})


if __name__ == "__main__":
    main()
