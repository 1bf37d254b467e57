"""The programs of a single L2 call on the CPU, each compiled on its own: compile and run time.

A top-level `photometric_stereo` call on the CPU takes L2's branch on the host: a flag pass
(`l2_needs_weights`), then only the chosen solve (`ps_l2(..., branch=...)`, inside the
wrapper's `_run`). This times, at 1280x1024 for K = 5 and 12, each of those programs with
XLA-CPU's default emitters and with the older ones (`OLDER_EMITTERS`), the solve that
`photometric_stereo` used before (the `cond` over both branches, what a traced call still
compiles), and the layout choice of the split solves: `(H, W)` planes (kept) against the
`cond` branches' flat `(H*W,)` planes reshaped to `(H, W)` at the end; also the weighted
solve's form for captures whose samples are all finite (`branch="weighted_finite"`, which
zeroes no sample; the flag pass says which form). Compile time is the
first call minus the median of the later ones, with JAX's in-memory caches cleared before each
program (and no persistent cache: this script does not turn one on).

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_l2_programs.py [--repeats 10]
    -> benchmarks/results/l2_programs.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import jax
import numpy as np

import jaxps
from jaxps.core._host import OLDER_EMITTERS
from jaxps.ps import _l2
from jaxps.ps._photometric_stereo import _run, _sample_thresholds

try:
    from benchmarks._common import RESULTS, environment, time_calls
    from benchmarks.bench_core import ring_lights
except ImportError:  # run as a script
    import pathlib

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import RESULTS, environment, time_calls
    from benchmarks.bench_core import ring_lights

H, W = 1024, 1280


def _flat_then_reshaped(weighted):
    """The chosen solve on flat planes, reshaped to `(H, W)` at the end (not kept)."""
    def solve(images, lights, mask, thresholds, shared):
        if weighted:
            out = _l2._solve_weighted(images, lights, mask, None, thresholds)
        else:
            out = _l2._solve_all_used(images, mask, None, thresholds, shared)[:-1]
        normal, albedo, status, n_used, residual = _l2._stacked(out)
        return (normal.reshape(H, W, 3), albedo.reshape(H, W), status.reshape(H, W),
                n_used.reshape(H, W), residual.reshape(H, W))
    return solve


def _rows(k, surface, repeats):
    """The timed programs for K lights: a list of JSON rows."""
    rows = []
    lights = jaxps.synthetic.scanner_lights(20.0, k=k) if k < 12 else ring_lights(k)
    lights = np.asarray(lights, np.float64)
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    scene = jaxps.synthetic.render_scene(surface, lights)
    images = jax.device_put(np.asarray(scene.images))
    mask = jax.device_put(np.asarray(scene.mask))
    shared = _l2.host_constants(lights)
    inside = np.asarray(scene.images)[:, np.asarray(scene.mask)]
    dropped = _sample_thresholds(float(np.percentile(inside, 5)))  # 5% of samples dropped
    clean = _sample_thresholds()
    th32 = tuple(np.float32(t) for t in dropped)
    l32 = np.asarray(lights, np.float32)

    def run_branch(branch, thresholds, options=None):
        fn = jax.jit(_run.__wrapped__, static_argnames=("method", "static"),
                     **({} if options is None else {"compiler_options": options}))
        static = () if branch is None else (("branch", branch),)
        return lambda: fn(images, lights, mask, None, thresholds, {"shared": shared},
                          method="l2", static=static)

    def needs(options=None):
        fn = jax.jit(_l2.l2_needs_weights.__wrapped__,
                     **({} if options is None else {"compiler_options": options}))
        return lambda: fn(images, mask, None, clean)

    def flat(weighted):
        fn = jax.jit(_flat_then_reshaped(weighted))
        return lambda: fn(images, l32, mask, th32 if weighted else clean, shared)

    programs = {
        "flag pass": needs(),
        "flag pass, older emitters": needs(OLDER_EMITTERS),
        "every sample used": run_branch("all_used", clean),
        "every sample used, older emitters": run_branch("all_used", clean, OLDER_EMITTERS),
        "every sample used, flat planes reshaped": flat(False),
        "weighted (5% dropped)": run_branch("weighted", dropped),
        "weighted (5% dropped), older emitters": run_branch("weighted", dropped,
                                                             OLDER_EMITTERS),
        "weighted (5% dropped), flat planes reshaped": flat(True),
        "weighted, every sample finite (5% dropped)": run_branch("weighted_finite", dropped),
        "weighted, every sample finite (5% dropped), older emitters": run_branch(
            "weighted_finite", dropped, OLDER_EMITTERS),
        "both branches in a cond, clean": run_branch(None, clean),
        "both branches in a cond, 5% dropped": run_branch(None, dropped),
    }
    for name, fn in programs.items():
        jax.clear_caches()  # each program traced and compiled afresh
        t = time_calls(fn, repeats)
        rows.append({"K": k, "program": name, "run_s": t["run_s_median"],
                     "compile_s": t["first_call_s"] - t["run_s_median"]})
        print(f"K={k:2d} {name:45s} run {1e3 * t['run_s_median']:7.2f} ms   compile "
              f"{t['first_call_s'] - t['run_s_median']:.3f} s", flush=True)
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    quick = os.environ.get("JAXPS_BENCH_QUICK") == "1"  # the runner's quick mode
    parser.add_argument("--repeats", type=int, default=3 if quick else 10)
    parser.add_argument("--out", default=str(RESULTS / "l2_programs.json"))
    args = parser.parse_args()
    surface = jaxps.synthetic.face_like(H, W)
    rows = [row for k in (5, 12) for row in _rows(k, surface, args.repeats)]
    res = {"command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python "
                      "benchmarks/bench_l2_programs.py", "shape": [H, W],
           "repeats": args.repeats, "env": environment(), "rows": rows}
    with open(args.out, "w") as f:
        json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
