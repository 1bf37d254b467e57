"""First call of each photometric-stereo method in a fresh process, as a script meets it.

For every method in `jaxps.PS_METHODS`, a new Python process renders the synthetic face
(192x168, five scanner lights, frames scaled by per-frame gains 0.9-1.1 so that
`semi_calibrated` has intensities to fit) and times `photometric_stereo(...)` twice: the first
call (tracing, compiling, running) and the median of five later calls. JAX's persistent
compilation cache is not turned on (a plain `import jaxps` does not), so every first call
compiles.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_first_call.py
    -> benchmarks/results/first_call.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

H, W = 168, 192
GAINS = [1.1, 0.9, 1.0, 1.05, 0.95]


def one(method: str) -> dict:
    """In this process: the first call and the median later call of `method`."""
    import jax
    import numpy as np

    import jaxps

    lights = jaxps.synthetic.scanner_lights(20.0)
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(H, W), lights)
    images = np.asarray(scene.images) * np.asarray(GAINS, np.float32)[:, None, None]
    mask = np.asarray(scene.mask)

    def call():
        return jax.block_until_ready(
            jaxps.photometric_stereo(images, lights, mask=mask, method=method).normals)

    t0 = time.perf_counter()
    call()
    first = time.perf_counter() - t0
    runs = []
    for _ in range(5):
        t0 = time.perf_counter()
        normals = call()
        runs.append(time.perf_counter() - t0)
    error = jaxps.evaluate.angular_stats(normals, scene.normals, mask=scene.mask)["median_deg"]
    return {"method": method, "first_call_s": first, "run_s": float(np.median(runs)),
            "median_error_deg": float(error)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--one", help=argparse.SUPPRESS)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                  "first_call.json"))
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(args.one)))
        return
    import jaxps

    rows = []
    for method in jaxps.PS_METHODS:
        out = subprocess.run([sys.executable, __file__, "--one", method], capture_output=True,
                             text=True, check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        print(f"{method:>16}: first call {r['first_call_s']:5.2f} s, later calls "
              f"{1e3 * r['run_s']:7.1f} ms, median error {r['median_error_deg']:.3f} deg")
    try:
        from benchmarks._common import environment
    except ImportError:  # run as a script
        sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        from benchmarks._common import environment
    env = environment()
    env["OPENBLAS_NUM_THREADS"] = os.environ.get("OPENBLAS_NUM_THREADS")
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump({"shape": [H, W], "gains": GAINS, "rows": rows, "env": env}, f, indent=2)


if __name__ == "__main__":
    main()
