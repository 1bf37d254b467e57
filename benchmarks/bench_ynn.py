"""Programs with and without YNNPACK fusions (`core._host.NO_YNN`), in the same process.

This JAX's XLA-CPU hands reductions, together with the elementwise work that feeds them, to
YNNPACK ("ynn" fusions). For the LM fits, whose every step sums over each pixel's K
samples, XLA's own loops ran faster. jaxps compiles those programs with
`compiler_options={"xla_cpu_experimental_ynn_fusion_type": ""}` (no YNNPACK fusion) through
`core._host.CpuTuned`. This script times each program both ways, in alternating rounds
(median over rounds, first calls apart), and checks that the results agree:

- `photometric_stereo` with `irls`, `barsky`, `sbl` and `l1`, left on the default (`irls`,
  `barsky` and `sbl` were compiled without YNNPACK until their kernels moved to planes,
  `ynn_before_irls_planes.json`), on `bench_robust.py`'s 1280x1024 scene (five lights on a
  45-degree cone, cast shadows, a Blinn-Phong lobe, 0.5% noise), with the median angular
  error of each;
- `photometric_stereo(method="semi_calibrated")` at 1280x1024 and 192x168 on a Lambertian
  rendering under the same lights with frames scaled by gains 0.9-1.1, whose LM fit of the
  intensities is tuned (the largest relative error of the fitted intensities);
- `fit_brdf` with its defaults (`wrap_ggx`) on the 192x168 scene, the size of `jaxps
  relight`'s benchmark, whose LM solves are tuned.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_ynn.py [--rounds 5]
    -> benchmarks/results/ynn.json
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import time

import jax
import numpy as np

import jaxps
from jaxps.stability import render_corrupted, ring_lights

try:
    from benchmarks._common import environment, write_json
except ImportError:  # run as a script
    import pathlib

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import environment, write_json

GAINS = np.asarray([1.1, 0.9, 1.0, 1.05, 0.95], np.float32)


@contextlib.contextmanager
def default_fusions(on: bool):
    """While `on`, every program below runs as XLA-CPU compiles it by default (the plain jit
    of each `CpuTuned`); else every one without YNNPACK, the robust solvers included (which
    jaxps leaves on the default since their kernels work on planes: the rows show why)."""
    from jaxps.core._host import NO_YNN, CpuTuned
    from jaxps.ps import _photometric_stereo, _semicalibrated
    from jaxps.reflectance import _parametric

    saved = (_photometric_stereo._run, _semicalibrated._fit_intensities, _parametric._solve)
    if on:
        _semicalibrated._fit_intensities = saved[1].plain
        _parametric._solve = saved[2].plain
    else:
        _photometric_stereo._run = _NO_YNN_RUN.setdefault(
            "run", CpuTuned(saved[0].__wrapped__, NO_YNN, static_argnames=("method", "static")))
    try:
        yield
    finally:
        (_photometric_stereo._run, _semicalibrated._fit_intensities,
         _parametric._solve) = saved


_NO_YNN_RUN: dict = {}  # one tuned `_run` for the whole run (its compiled programs kept)


def angular_median(normals, truth, mask) -> float:
    cos = np.clip(np.sum(np.asarray(normals) * np.asarray(truth), -1), -1, 1)
    return float(np.median(np.degrees(np.arccos(cos))[np.asarray(mask)]))


def cases():
    """(name, shape, call, summary): `call()` runs the work and returns what `summary` turns
    into the figures compared between the two compilations."""
    out = []
    for h, w in ((1024, 1280), (192, 168)):
        # bench_robust.py's scene: cast shadows, a Blinn-Phong lobe, 0.5% noise
        scene = render_corrupted(jaxps.synthetic.face_like(h, w), ring_lights(5, 45.0),
                                 specular=0.6, shininess=100.0, noise=0.005,
                                 key=jax.random.key(0))
        lights = np.asarray(scene.lights)
        images = jax.device_put(scene.images)
        mask, truth = np.asarray(scene.mask), np.asarray(scene.normals)

        def ps_summary(res, truth=truth, mask=mask):
            return {"median_error_deg": angular_median(res.normals, truth, mask)}

        for method in ("irls", "barsky", "sbl", "l1") if h > 200 else ():
            out.append((f"photometric_stereo {method}", (h, w),
                        lambda m=method, im=images, lt=lights, mk=mask: jaxps.photometric_stereo(
                            im, lt, mask=mk, method=m), ps_summary))
        # semi-calibrated on a Lambertian rendering with known per-frame gains
        lambert = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(h, w), lights)
        scaled = jax.device_put(np.asarray(lambert.images) * GAINS[:, None, None])
        out.append(("photometric_stereo semi_calibrated", (h, w),
                    lambda im=scaled, lt=lights, mk=mask: jaxps.photometric_stereo(
                        im, lt, mask=mk, method="semi_calibrated"),
                    lambda res: {"steps": int(res.info["steps"]),
                                 "intensity_error": float(np.max(np.abs(
                                     np.asarray(res.info["intensities"]) / GAINS
                                     * np.exp(np.mean(np.log(GAINS))) - 1)))}))
        if h < 200:
            res = jaxps.photometric_stereo(images, lights, mask=mask)
            out.append(("fit_brdf wrap_ggx (defaults)", (h, w),
                        lambda r=res, mk=mask, im=images, lt=lights: jaxps.fit_brdf(
                            im, r.normals, r.albedo, lt, mask=mk, key=jax.random.key(0)),
                        lambda m: {"steps": int(m.fit.steps),
                                   "shape": np.round(np.asarray(m.params.shape), 5).tolist(),
                                   "rmse": float(m.fit.rmse)}))
    return out


def run(rounds: int) -> dict:
    rows = []
    for name, shape, call, summary in cases():
        first, times, results = {}, {"default": [], "no_ynn": []}, {}
        for variant in ("default", "no_ynn"):
            with default_fusions(variant == "default"):
                t0 = time.perf_counter()
                results[variant] = summary(jax.block_until_ready(call()))
                first[variant] = time.perf_counter() - t0
        for _ in range(rounds):
            for variant in ("default", "no_ynn"):
                with default_fusions(variant == "default"):
                    t0 = time.perf_counter()
                    jax.block_until_ready(call())
                    times[variant].append(time.perf_counter() - t0)
        med = {v: statistics.median(t) for v, t in times.items()}
        row = {"work": name, "shape": list(shape), "default_s": med["default"],
               "no_ynn_s": med["no_ynn"], "ratio": med["no_ynn"] / med["default"],
               "first_call_s": first, "default": results["default"],
               "no_ynn": results["no_ynn"]}
        rows.append(row)
        print(f"{name:<38} {shape[0]:>4}x{shape[1]:<4} default {1e3 * med['default']:8.1f} ms"
              f"   no YNNPACK {1e3 * med['no_ynn']:8.1f} ms   ratio {row['ratio']:.2f}",
              flush=True)
    return {"command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_ynn.py",
            "rounds": rounds, "rows": rows, "env": environment()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--out", default="ynn", help="results/<OUT>.json")
    args = ap.parse_args(argv)
    path = write_json(args.out, run(args.rounds))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
