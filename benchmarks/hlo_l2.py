"""Passes over memory in the compiled L2 programs: loop fusions and copies in XLA's HLO.

Counts, for a 1280x1024 grey capture with K=5 shared lights, the fusions and copies of the
single-call program (`photometric_stereo`) and of the batch's three programs: its flag pass
(`l2_needs_weights`), its solve (`l2_solve`, every sample used or weighted; grey `(K, H, W)`
input as the batch passes it, and with a channel axis added first) and its in-place write
(`l2_write`), and the two traced as one program (`l2_into`, which the batch takes for light
captures): each `dynamic-update-slice` then fuses into the pass that computes its values. For
each, how many fusions XLA-CPU splits across threads (`outer_dimension_partitions`).

Run: `PYTHONPATH=src python benchmarks/hlo_l2.py` -> `benchmarks/results/hlo_l2.json`.
"""

from __future__ import annotations

import json
import pathlib
import re

import jax
import jax.numpy as jnp
import numpy as np

import jaxps
from jaxps.ps._l2 import host_constants, l2_into, l2_needs_weights, l2_solve, l2_write

OUT = pathlib.Path(__file__).resolve().parent / "results" / "hlo_l2.json"
N, K, H, W = 8, 5, 1024, 1280


def counts(text: str) -> dict:
    """Fusion and copy instructions in a compiled module (all computations)."""
    return {"fusions": len(re.findall(r"= \S+ fusion\(", text)),
            "copies": len(re.findall(r"= \S+ copy\(", text)),
            "partitioned_fusions": text.count("outer_dimension_partitions")}


def main():
    lights = np.asarray(jaxps.synthetic.scanner_lights(20.0), np.float64)
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    images = jax.ShapeDtypeStruct((K, H, W), jnp.float32)
    mask = jax.ShapeDtypeStruct((H, W), jnp.bool_)
    thresholds = tuple(jax.ShapeDtypeStruct((), jnp.float32) for _ in range(3))
    shared = host_constants(lights)
    lt = jax.ShapeDtypeStruct((K, 3), jnp.float32)
    out = (jax.ShapeDtypeStruct((N, H, W, 3), jnp.float32),
           jax.ShapeDtypeStruct((N, H, W), jnp.float32),
           jax.ShapeDtypeStruct((N, H, W), jnp.int32), jax.ShapeDtypeStruct((N, H, W), jnp.int32),
           jax.ShapeDtypeStruct((N, H, W), jnp.float32))
    flat = (jax.ShapeDtypeStruct((H * W, 3), jnp.float32),
            *(jax.ShapeDtypeStruct((H * W,), d)
              for d in (jnp.float32, jnp.int32, jnp.int32, jnp.float32)))
    single = jax.jit(lambda x: jaxps.photometric_stereo(x, lights))

    def solve(x, weighted):
        return l2_solve.lower(x, lt, mask, None, thresholds, shared, weighted=weighted,
                              dtype=np.float32).compile().as_text()

    def one_program(weighted):
        return l2_into.lower(out, 0, images, lt, mask, None, thresholds, shared,
                             weighted=weighted, dtype=np.float32).compile().as_text()
    res = {
        "shape": [K, H, W], "batch": N,
        "photometric_stereo": counts(single.lower(images).compile().as_text()),
        "l2_solve": counts(solve(images, weighted=False)),
        "l2_solve_weighted": counts(solve(images, weighted=True)),
        # The grey frames given a channel axis inside the program (as `_run` does for
        # `ps_l2`), then solved as `(K, H, W, 1)`.
        "l2_solve_channel_axis_added": counts(jax.jit(
            lambda x, li, m, t, s: l2_solve(x[..., None], li, m, None, t, s, weighted=False,
                                            dtype=np.float32)
        ).lower(images, lt, mask, thresholds, shared).compile().as_text()),
        "l2_write": counts(l2_write.lower(out, 0, flat).compile().as_text()),
        "l2_into": counts(one_program(weighted=False)),
        "l2_into_weighted": counts(one_program(weighted=True)),
        "l2_needs_weights": counts(l2_needs_weights.lower(images, mask, None, thresholds,
                                                          shared).compile().as_text()),
    }
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text(json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
