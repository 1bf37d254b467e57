"""Captures per second at 1280x1024x5 (L2, batched) and the semi-calibrated solver's time.

Run: `OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_batch.py [--quick]`
-> benchmarks/results/batch.json and batch.png. Baseline in the same run: N single calls.
"""

from __future__ import annotations

import json
import os
import pathlib
import platform
import sys

import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jaxps  # noqa: E402

OUT = pathlib.Path(__file__).resolve().parent / "results"
QUICK = "--quick" in sys.argv or os.environ.get("JAXPS_BENCH_QUICK") == "1"
# --quick (used by `python -m benchmarks --quick`): 256x320, for a smoke run, marked in the JSON.
H, W, K, N = (256, 320, 5, 2) if QUICK else (1024, 1280, 5, 4)


try:
    from benchmarks._common import timed
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import timed


def main():
    rng = np.random.default_rng(0)
    lights = jaxps.synthetic.scanner_lights(20.0)
    surface = jaxps.synthetic.face_like(H, W)
    scene = jaxps.synthetic.render_scene(surface, lights)
    base = np.asarray(scene.images)
    caps = np.stack([base * rng.uniform(0.85, 1.15, (K, 1, 1)).astype(np.float32)
                     for _ in range(N)]).astype(np.float32)
    mask = np.asarray(scene.mask)
    res = {"device": str(jax.devices()[0]), "device_count": jax.device_count(),
           "platform": platform.processor() or platform.machine(),
           "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
           "shape": [N, K, H, W], "quick": QUICK}
    _, first, run = timed(lambda: jaxps.photometric_stereo_batch(caps, lights, mask=mask, chunk=2),
                          repeats=2)
    res["batch_l2"] = {"compile_plus_first_s": first, "run_s": run, "captures_per_s": N / run}
    _, first, run = timed(lambda: jaxps.photometric_stereo_batch(caps, lights, mask=mask, chunk=2,
                                                                 vmap_size=1), repeats=2)
    res["batch_l2_lax_map"] = {"compile_plus_first_s": first, "run_s": run,
                               "captures_per_s": N / run}
    _, first, run = timed(lambda: [jaxps.photometric_stereo(c, lights, mask=mask) for c in caps],
                          repeats=2)
    res["single_calls_l2"] = {"compile_plus_first_s": first, "run_s": run,
                              "captures_per_s": N / run}
    _, first, run = timed(lambda: jaxps.photometric_stereo(caps[0], lights, mask=mask,
                                                           method="semi_calibrated"), repeats=1)
    res["semi_calibrated_one_capture"] = {"compile_plus_first_s": first, "run_s": run}
    _, first, run = timed(lambda: jaxps.intensity_estimate(caps[0], lights, mask=mask,
                                                           method="frontal"), repeats=1)
    res["frontal_estimate_one_capture"] = {"compile_plus_first_s": first, "run_s": run}
    OUT.mkdir(exist_ok=True)
    (OUT / "batch.json").write_text(json.dumps(res, indent=1))
    labels = ["batch vmap", "batch lax.map", "single calls", "semi-cal."]
    vals = [res["batch_l2"]["run_s"] / N, res["batch_l2_lax_map"]["run_s"] / N,
            res["single_calls_l2"]["run_s"] / N,
            res["semi_calibrated_one_capture"]["run_s"]]
    plt.figure(figsize=(6, 3))
    plt.bar(labels, vals)
    plt.ylabel("seconds per capture")
    plt.title(f"{W}x{H}x{K}, {res['device']}")
    plt.tight_layout()
    plt.savefig(OUT / "batch.png", dpi=100)
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
