"""A top-level L2 call on the CPU: one program with the flag pass and all three solves, against
a flag program read on the host and then the chosen solve's program.

`photometric_stereo(method="l2")` with shared lights, called outside any trace on the CPU, now
compiles `ps_l2(branch="switch")`: the flag pass and the three solves of `_l2.SOLVES` in one
program with XLA-CPU's older emitters, where `lax.switch` runs the one that the flags call for.
Before, it ran the flag program (`l2_branch`), read its flag on the host, and then ran a
program that held only the chosen solve (the every-sample-used one with the older emitters,
a weighted one with the default emitters). This times both ways, interleaved, on the
synthetic face at 1280x1024 for K = 5 and 12, grey with every sample used and with 5% of
the samples in the mask under a shadow threshold, and colour with every sample used. It
checks that status and `n_used` are equal and records the largest normal difference, and
the compile time of each (its first call after `jax.clear_caches()`, minus the median run).
For grey frames with every sample used it also times `photometric_stereo` itself on aligned
numpy frames, with its kept light checks and host constants and with them cleared before
every call (`photometric_stereo_kept_ms`, `photometric_stereo_cleared_ms`).

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_l2_switch.py [--rounds 20]
    [--name l2_switch] -> benchmarks/results/NAME.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import jax
import numpy as np

import jaxps
from jaxps.core._host import aligned, to_device
from jaxps.ps import _l2
from jaxps.ps._photometric_stereo import (
    _checked_lights,
    _run,
    _run_older_emitters,
    _sample_thresholds,
)

try:
    from benchmarks._common import block, environment, interleaved, write_json
    from benchmarks.bench_core import ring_lights
except ImportError:  # run as a script
    import pathlib

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import block, environment, interleaved, write_json
    from benchmarks.bench_core import ring_lights

H, W = 1024, 1280


def ways(images, lights, mask, thresholds):
    """`{"host-chosen": fn, "switch": fn, "switch, default emitters": fn}`: the ways of a
    top-level call, each returning the `PSResult` (the arguments as `photometric_stereo`
    passes them to `_run`); the last is the switch compiled with the default emitters."""
    dynamic = {"shared": _l2.host_constants(lights)}

    def host_chosen():
        branch = _l2.l2_branch(images, mask, None, thresholds)
        run = _run_older_emitters if branch == "all_used" else _run
        return run(images, lights, mask, None, thresholds, dynamic, method="l2",
                   static=(("branch", branch),))

    def switch(run=_run_older_emitters):
        return run(images, lights, mask, None, thresholds, dynamic, method="l2",
                   static=(("branch", "switch"),))

    return {"host-chosen": host_chosen, "switch": switch,
            "switch, default emitters": lambda: switch(_run)}


def wrapper_ms(frames, lights, rounds):
    """`photometric_stereo(frames, lights)` as a user calls it (aligned numpy frames), with
    its kept light checks and host constants, and with them cleared before every call."""
    def cleared():
        _checked_lights.cache_clear()
        return jaxps.photometric_stereo(frames, lights)

    _, seconds = interleaved({"kept": lambda: jaxps.photometric_stereo(frames, lights),
                              "cleared": cleared}, rounds)
    return {f"photometric_stereo_{w}_ms": 1e3 * statistics.median(s)
            for w, s in seconds.items()}


def compile_s(fn, run_s):
    jax.clear_caches()
    t0 = time.perf_counter()
    block(fn())
    return time.perf_counter() - t0 - run_s


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--name", default="l2_switch", help="results/NAME.json")
    args = parser.parse_args(argv)
    surface = jaxps.synthetic.face_like(H, W)
    rows = []
    for k in (5, 12):
        lights = np.asarray(ring_lights(k) if k >= 8 else jaxps.synthetic.scanner_lights(20.0, k=k),
                            np.float64)
        lights /= np.linalg.norm(lights, axis=1, keepdims=True)
        scene = jaxps.synthetic.render_scene(surface, lights)
        grey = aligned(np.asarray(scene.images, np.float32))
        mask = to_device(aligned(np.asarray(scene.mask)), bool)
        colour = to_device(aligned(np.stack([grey, 0.8 * grey, 0.6 * grey], -1)))
        shadow = float(np.percentile(grey[:, np.asarray(scene.mask)], 5))
        frames, grey = grey, to_device(grey)
        cases = {"grey, every sample used": (grey, _sample_thresholds()),
                 "grey, 5% of samples dropped": (grey, _sample_thresholds(shadow)),
                 "colour, every sample used": (colour, _sample_thresholds())}
        for case, (images, thresholds) in cases.items():
            fns = ways(images, lights, mask, thresholds)
            _, seconds = interleaved(fns, args.rounds)
            a, b = fns["switch"](), fns["host-chosen"]()
            same = all(np.array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)))
                       for f in ("status", "n_used"))
            run = {w: statistics.median(s) for w, s in seconds.items()}
            row = {"K": k, "case": case,
                   "switch_ms": 1e3 * run["switch"], "host_chosen_ms": 1e3 * run["host-chosen"],
                   "switch_over_host_chosen": run["switch"] / run["host-chosen"],
                   "switch_default_emitters_ms": 1e3 * run["switch, default emitters"],
                   "switch_compile_s": compile_s(fns["switch"], run["switch"]),
                   "host_chosen_compile_s": compile_s(fns["host-chosen"], run["host-chosen"]),
                   "status_and_n_used_equal": same,
                   "max_normal_difference": float(np.abs(np.asarray(a.normals)
                                                         - np.asarray(b.normals)).max())}
            if case == "grey, every sample used":  # the whole call, with numpy frames
                row.update(wrapper_ms(frames, lights, args.rounds))
            rows.append(row)
            print(f"K={k:2d} {case:28s} switch {row['switch_ms']:6.2f} ms  host-chosen "
                  f"{row['host_chosen_ms']:6.2f} ms  {row['switch_over_host_chosen']:.3f}x  default "
                  f"emitters {row['switch_default_emitters_ms']:6.2f} ms  "
                  f"compile {row['switch_compile_s']:.2f} / {row['host_chosen_compile_s']:.2f} s"
                  f"  equal {same}  normals {row['max_normal_difference']:.1e}"
                  + (f"  photometric_stereo {row['photometric_stereo_kept_ms']:.2f} ms, "
                     f"cleared {row['photometric_stereo_cleared_ms']:.2f} ms"
                     if "photometric_stereo_kept_ms" in row else ""), flush=True)
    path = write_json(args.name, {
        "command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_l2_switch.py "
                   + " ".join(sys.argv[1:] if argv is None else argv),
        "environment": environment(), "rounds": args.rounds, "shape": [H, W], "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
