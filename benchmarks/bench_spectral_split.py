"""Frankot–Chellappa and the DCT solve as one program or as two split at the half spectrum.

`integrate(method="fc")` and `method="dct"` (orthographic, at the top level) run as two
programs each: the height steps and the forward transform up to the solved half spectrum, then
the inverse FFT and the masked mean. This times, at 1280x1024, both integrators built from the
same library functions as one program (what `integrate` compiled before) and as two (what it
runs now), in alternating blocks of calls so that the machine's slow spells hit both alike.
It also reads each program's thunks (fusions and FFTs) from a `jax.profiler` trace: XLA-CPU's
inverse FFT of a spectrum computed in the same program ran at about half the speed of the
same FFT on a program argument, which is what the split gains. For scale, it times scipy.fft's
`dctn` + `idctn` of one plane, the transforms of `bench_core.py`'s DCT baseline.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_spectral_split.py
    -> benchmarks/results/spectral_split.json
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import os
import statistics
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxps
from jaxps.integration import _integrate as integ

try:
    from benchmarks._common import environment, write_json
except ImportError:  # run as a script
    import pathlib

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import environment, write_json

H, W = 1024, 1280


def variants(normals, mask):
    """{integrator: {"one program": fn, "two programs": fn}}, each fn -> height."""
    pixel_size = jnp.asarray(1.0, normals.dtype)
    shape = normals.shape[:2]

    @jax.jit
    def fc_one(normals, mask, pixel_size):
        spectrum, _ = integ._fc_spectrum_from_normals(normals, mask, pixel_size)
        return integ._fc_height(spectrum, mask, None, shape)

    @jax.jit
    def dct_one(normals, mask, pixel_size):
        spectrum, valid = integ._dct_spectrum_from_normals(normals, mask, None)
        return integ._dct_height(spectrum, valid, None, pixel_size, None, shape)

    def fc_two():
        return integ._fc_height(integ._fc_spectrum_from_normals(normals, mask, pixel_size)[0], mask,
                                None, shape)

    def dct_two():
        spectrum, valid = integ._dct_spectrum_from_normals(normals, mask, None)
        return integ._dct_height(spectrum, valid, None, pixel_size, None, shape)

    return {"fc": {"one program": lambda: fc_one(normals, mask, pixel_size),
                   "two programs": fc_two},
            "dct": {"one program": lambda: dct_one(normals, mask, pixel_size),
                    "two programs": dct_two}}


def alternating(fns, repeats, block=5):
    """Median seconds of each function's calls, made in alternating blocks of `block`."""
    runs = {name: [] for name in fns}
    for fn in fns.values():
        jax.block_until_ready(fn())  # compile
    while min(len(r) for r in runs.values()) < repeats:
        for name, fn in fns.items():
            for _ in range(block):
                t0 = time.perf_counter()
                jax.block_until_ready(fn())
                runs[name].append(time.perf_counter() - t0)
    return {name: statistics.median(r) for name, r in runs.items()}


def thunks(fn, calls=10):
    """Median milliseconds of each XLA thunk (fusion, FFT, ...) of `fn`'s programs over
    `calls` traced calls, keyed `"program/thunk"`, slowest first."""
    with tempfile.TemporaryDirectory() as folder:
        jax.profiler.start_trace(folder)
        for _ in range(calls):
            jax.block_until_ready(fn())
        jax.profiler.stop_trace()
        path = glob.glob(os.path.join(folder, "**", "*.trace.json.gz"), recursive=True)[0]
        with gzip.open(path) as f:
            events = json.load(f)["traceEvents"]
    times = collections.defaultdict(list)
    for e in events:
        module = e.get("args", {}).get("hlo_module")
        if e.get("ph") == "X" and module and "hlo_op" in e["args"]:
            times[f"{module}/{e['name']}"].append(e["dur"] / 1e3)
    return dict(sorted(((k, statistics.median(t)) for k, t in times.items()),
                       key=lambda kv: -kv[1]))


def scipy_dct_pair(rhs, repeats):
    """Median seconds of scipy.fft's `dctn` + `idctn` (2 workers) of one float32 plane: the
    transforms alone of the benchmark's scipy baseline (`bench_core.py`)."""
    import scipy.fft

    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        scipy.fft.idctn(scipy.fft.dctn(rhs, norm="ortho", workers=2), norm="ortho", workers=2)
        runs.append(time.perf_counter() - t0)
    return statistics.median(runs)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=40)
    args = ap.parse_args()
    lights = jaxps.synthetic.scanner_lights(20.0)
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(H, W), lights)
    normals = jax.block_until_ready(
        jaxps.photometric_stereo(jax.device_put(scene.images), lights).normals)
    mask = jnp.ones((H, W), bool)
    rows = []
    for method, fns in variants(normals, mask).items():
        heights = [np.asarray(fn()) for fn in fns.values()]
        medians = alternating(fns, args.repeats)
        for name, fn in fns.items():
            times = thunks(fn)
            rows.append({"method": method, "program": name, "run_s": medians[name],
                         "fft_thunks_ms": sorted(t for k, t in times.items()
                                                 if k.split("/")[1].startswith("fft")),
                         "thunks_ms": times,
                         "max_abs_difference": float(np.abs(heights[0] - heights[1]).max())})
    result = {"command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python "
                         "benchmarks/bench_spectral_split.py",
              "shape": [H, W], "repeats": args.repeats, "rows": rows,
              "scipy_dctn_idctn_s": scipy_dct_pair(np.asarray(normals[..., 0]), args.repeats),
              "env": environment()}
    result["env"]["OPENBLAS_NUM_THREADS"] = os.environ.get("OPENBLAS_NUM_THREADS")
    write_json("spectral_split", result)
    for r in rows:
        print(f"{r['method']:>4} {r['program']:<13} {1e3 * r['run_s']:7.2f} ms   FFT thunks "
              f"{', '.join(f'{t:.2f}' for t in r['fft_thunks_ms'])} ms   "
              f"max |difference| {r['max_abs_difference']:.2g}")
    print(f"scipy.fft dctn + idctn alone: {1e3 * result['scipy_dctn_idctn_s']:.2f} ms")


if __name__ == "__main__":
    main()
