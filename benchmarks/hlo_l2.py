"""Passes over memory in the compiled L2 programs: loop fusions and copies in XLA's HLO.

Counts, for 1280x1024 grey captures with K=5 lights, the fusions and copies of the
single-call program (`photometric_stereo`) and its flag pass (`l2_needs_weights`), and of
the batch's programs for 8 captures solved as one image: its flag pass (`l2_batch_flags`) and
its solve (`l2_batch_solve`: every sample used, with XLA-CPU's older emitters as the batch
compiles it, or weighted, in two programs whose counts are given apart and summed; lights
shared or per capture; into fresh outputs or into `out`'s donated buffers and kept planes), and the every-sample-used solve given one `(H, W)` mask broadcast inside the
program instead of one plane per capture. For each, how many fusions XLA-CPU splits across
threads (`outer_dimension_partitions`), and for the `out` programs how many outputs alias a
donated input (`aliased_outputs`).

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
from jaxps.ps import _l2

OUT = pathlib.Path(__file__).resolve().parent / "results" / "hlo_l2.json"
N, K, H, W = 8, 5, 1024, 1280


def counts(text: str) -> dict:
    """Fusion and copy instructions in a compiled module (all computations)."""
    header = text.split("\n", 1)[0]  # HloModule ..., input_output_alias={ {0}: (0, {}, ...
    return {"fusions": len(re.findall(r"= \S+ fusion\(", text)),
            "copies": len(re.findall(r"= \S+ copy\(", text)),
            "partitioned_fusions": text.count("outer_dimension_partitions"),
            "aliased_outputs": len(re.findall(r"\{\d+\}: \(\d+, \{\}, (may|must)-alias\)",
                                              header))}


def compiled(program, *args, **kwargs) -> dict:
    return counts(program.lower(*args, **kwargs).compile().as_text())


def main():
    f32 = jnp.float32
    lights = np.asarray(jaxps.synthetic.scanner_lights(20.0), np.float64)
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    images = jax.ShapeDtypeStruct((K, H, W), f32)
    mask = jax.ShapeDtypeStruct((H, W), jnp.bool_)
    thresholds = tuple(jax.ShapeDtypeStruct((), f32) for _ in range(3))
    shared = _l2.host_constants(lights)
    stack = jax.ShapeDtypeStruct((N, K, H, W), f32)
    masks = jax.ShapeDtypeStruct((N, H, W), jnp.bool_)
    lt = jax.ShapeDtypeStruct((K, 3), f32)
    per_capture = (jax.ShapeDtypeStruct((N, K, 3), f32),
                   tuple(np.stack([c] * N) for c in shared))
    out = (jax.ShapeDtypeStruct((N, H, W, 3), f32), jax.ShapeDtypeStruct((N, H, W), f32),
           jax.ShapeDtypeStruct((N, H, W), jnp.int32), jax.ShapeDtypeStruct((N, H, W), jnp.int32),
           jax.ShapeDtypeStruct((N, H, W), f32))
    kw = {"dtype": np.dtype(np.float32)}

    def tuned(program):
        return getattr(program, "tuned", None) or program  # the CPU's compile options

    def batch(branch, into=False, lights_and_consts=(lt, shared)):
        li, consts = lights_and_consts
        args = (stack, li, masks, None, thresholds)
        if branch == "all_used":
            program = tuned(_l2._BATCH_PROGRAMS[into])
            return compiled(program, *((out,) if into else ()), *args, consts, **kw)
        # two programs: the packed planes (into kept ones), then the outputs (into `out`)
        planes_program, unpack_program = map(tuned, _l2._BATCH_WEIGHTED)
        planes = jax.eval_shape(planes_program, (None, None), *args, branch=branch)
        scratch = (planes[:-1], planes[-1]) if into else (None, None)
        into_out = (out[0], out[1], out[2], out[4]) if into else None
        first = compiled(planes_program, scratch, *args, branch=branch)
        second = compiled(unpack_program, into_out, planes, channels=1, **kw)
        return {"planes": first, "outputs": second,
                **{name: first[name] + second[name] for name in first}}

    broadcast_mask = jax.jit(
        lambda x, m, t, s: _l2._batch_solve(x, lt, jnp.broadcast_to(m, (N, H, W)), None, t, s,
                                            kw["dtype"]),
        compiler_options=_l2.OLDER_EMITTERS)
    res = {
        "shape": [K, H, W], "batch": N,
        "photometric_stereo": compiled(jax.jit(lambda x: jaxps.photometric_stereo(x, lights)),
                                       images),
        "l2_needs_weights": compiled(_l2.l2_needs_weights, images, mask, None, thresholds),
        "l2_batch_flags": compiled(_l2.l2_batch_flags, stack, masks, None, thresholds),
        "l2_batch_solve": batch("all_used"),
        "l2_batch_solve_weighted": batch("weighted"),
        "l2_batch_solve_weighted_finite": batch("weighted_finite"),
        "l2_batch_solve_into_out": batch("all_used", into=True),
        "l2_batch_solve_weighted_into_out": batch("weighted_finite", into=True),
        "l2_batch_solve_lights_per_capture": batch("all_used", lights_and_consts=per_capture),
        "l2_batch_solve_weighted_lights_per_capture": batch("weighted_finite",
                                                            lights_and_consts=per_capture),
        # One `(H, W)` mask broadcast to the stack inside the program (not kept)
        "l2_batch_solve_one_mask_broadcast": compiled(broadcast_mask, stack, mask, thresholds,
                                                      shared),
    }
    OUT.parent.mkdir(exist_ok=True)
    OUT.write_text(json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    import argparse

    argparse.ArgumentParser(description=__doc__).parse_args()  # --help before any work
    main()
