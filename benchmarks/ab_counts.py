"""Counts on the host and no all-true planes: the twelfth session's changes against the code
before them, interleaved in one process.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/ab_counts.py [--rounds 60]
        [--size 1024 1280] [--out FILE]  -> benchmarks/results/ab_counts.json

At `--size` (default 1280x1024), K=5, every sample used:

- `ps_l2`: a single L2 call's one program (`ps_l2(branch="switch")`, compiled with
  `OLDER_EMITTERS` as `photometric_stereo` compiles it) with `mask=None`, against the same
  program given the all-true mask that `photometric_stereo` used to build inside it (then an
  operand of its `switch`, written to memory on every call);
- `fc`: `jaxps.integrate(normals)` (no mask: no all-true plane, and the mean a plain one)
  against its two programs as `integrate` ran them before (`before_fc`: an all-true mask
  built and put on the device, the count taken in the second program);
- `dct`: `jaxps.integrate(normals, method="dct")` (valid normals counted on the host) against
  its two programs as they ran before (`before_dct`: the same all-true mask, the count and
  the any-valid test in the second program).

Each pair is timed alternately for `--rounds` rounds (the order swapped every round); the
JSON holds the best and median ms of each, the largest difference between their outputs and
the minor page faults of one more call of each.
"""

from __future__ import annotations

import functools
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

try:
    from benchmarks._common import arguments, environment, page_faults, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, environment, page_faults, write_json

import jaxps
from jaxps.core._host import OLDER_EMITTERS, to_device
from jaxps.integration import _integrate as integ
from jaxps.integration._poisson import _neumann_from_spectrum
from jaxps.ps import _l2
from jaxps.ps._photometric_stereo import _sample_thresholds


@functools.partial(jax.jit, static_argnames=("cam", "shape"))
def before_dct_height(g, valid, pixel_size, cam, shape):
    """`_dct_height` before: the valid normals counted, and tested, in the program."""
    eta = _neumann_from_spectrum(g, shape).astype(g.real.dtype)
    return integ._to_height(eta, valid, cam, pixel_size, True), jnp.any(valid)


def before_dct(normals):
    mask = to_device(np.ones(normals.shape[:2], bool))  # as `integrate` built it
    pixel_size = to_device(1.0, normals.dtype)
    spectrum, valid = integ._dct_spectrum_from_normals(normals, mask, cam=None)
    height, any_valid = before_dct_height(spectrum, valid, pixel_size, cam=None,
                                          shape=normals.shape[:2])
    if not bool(any_valid):
        raise ValueError("no valid normal")
    return height


def before_fc(normals):
    mask = to_device(np.ones(normals.shape[:2], bool))  # as `integrate` built it
    pixel_size = to_device(1.0, normals.dtype)
    spectrum, any_valid = integ._fc_spectrum_from_normals(normals, mask, pixel_size)
    height = integ._fc_height(spectrum, mask, None, shape=normals.shape[:2])  # counted there
    if not bool(any_valid):
        raise ValueError("no valid normal")
    return height


def _interleaved(fns, rounds):
    times = {k: [] for k in fns}
    for r in range(rounds):
        for k in (list(fns) if r % 2 else list(fns)[::-1]):
            t0 = time.perf_counter()
            jax.block_until_ready(fns[k]())
            times[k].append(time.perf_counter() - t0)
    return {k: {"best_ms": 1e3 * min(v), "median_ms": 1e3 * float(np.median(v))}
            for k, v in times.items()}


def main(rounds, size, out):
    h, w = size
    lights = jaxps.synthetic.scanner_lights(20.0)
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(h, w), lights)
    images = jax.device_put(scene.images)
    unit = np.asarray(lights, np.float64)
    unit = unit / np.linalg.norm(unit, axis=1, keepdims=True)
    thresholds = tuple(jnp.float32(t) for t in _sample_thresholds())
    shared = _l2._cast_shared(tuple(jnp.asarray(c) for c in _l2.host_constants(unit)),
                              jnp.float32)
    args = (images, jnp.asarray(unit, jnp.float32), thresholds, shared)

    def switch(mask_in_program):
        def solve(x, lt, th, sh):
            mask = jnp.ones(x.shape[1:3], bool) if mask_in_program else None
            return _l2.ps_l2(x, lt, mask, None, th, sh, branch="switch")
        return jax.jit(solve).lower(*args).compile(compiler_options=OLDER_EMITTERS)

    normals = jax.block_until_ready(jaxps.photometric_stereo(images, lights).normals)
    after_ps, before_ps = switch(False), switch(True)
    pairs = {
        "ps_l2": {"after": lambda: after_ps(*args), "before": lambda: before_ps(*args)},
        "fc": {"after": lambda: jaxps.integrate(normals),
               "before": lambda: before_fc(normals)},
        "dct": {"after": lambda: jaxps.integrate(normals, method="dct"),
                "before": lambda: before_dct(normals)},
    }
    res = {"env": environment(), "shape": [5, h, w], "rounds": rounds}
    for name, fns in pairs.items():
        a, b = (jax.tree.leaves(f()) for f in fns.values())
        diff = max(float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64))))
                   for x, y in zip(a, b))
        del a, b
        res[name] = {"max_abs_difference": diff, **_interleaved(fns, rounds),
                     "page_faults": {k: page_faults(f) for k, f in fns.items()}}
        print(name, res[name], flush=True)
    write_json(out, res)


def _options(parser):
    parser.add_argument("--rounds", type=int, default=60)
    parser.add_argument("--size", type=int, nargs=2, default=(1024, 1280),
                        metavar=("ROWS", "COLUMNS"))
    parser.add_argument("--out", default="ab_counts", help="JSON name under results/")


if __name__ == "__main__":
    args = arguments(__doc__, configure=_options)
    main(args.rounds, tuple(args.size), args.out)
