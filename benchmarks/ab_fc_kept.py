"""Frankot–Chellappa (or the DCT solve) into kept memory (thirteenth session) against fresh
memory, interleaved in one process.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/ab_fc_kept.py [--rounds 12]
        [--size 4096 4096] [--method fc|dct] [--out FILE]  -> benchmarks/results/ab_fc_kept.json

`jaxps.integrate(normals, method=...)` (default `"fc"`) of a K=5 synthetic face's normals at
`--size`, as it runs now (normals over 32 MiB: the intermediate planes and the height written
into kept buffers, `_fc_kept` and `_dct_kept` in `integration/_integrate.py`) and with that
path turned off (`_KEEP_FROM_BYTES` raised out of reach: every plane in fresh memory, as
before). Both are timed alternately for `--rounds` rounds (`_common.interleaved`); the JSON
holds the best and median ms of each, the largest difference between their heights and the
minor page faults of one more call of each.
"""

from __future__ import annotations

import pathlib
import sys

import jax
import numpy as np

try:
    from benchmarks._common import arguments, environment, interleaved, page_faults, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, environment, interleaved, page_faults, write_json

import jaxps
from jaxps.integration import _integrate

KEPT = _integrate._KEEP_FROM_BYTES


def integrate(normals, method, threshold):
    _integrate._KEEP_FROM_BYTES = threshold
    try:
        return jaxps.integrate(normals, method=method)
    finally:
        _integrate._KEEP_FROM_BYTES = KEPT


def main(rounds, size, method, out):
    h, w = size
    lights = jaxps.synthetic.scanner_lights(20.0)
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(h, w), lights)
    normals = jax.block_until_ready(jaxps.photometric_stereo(scene.images, lights).normals)
    del scene
    cases = {"kept": lambda: integrate(normals, method, KEPT),
             "fresh": lambda: integrate(normals, method, 1 << 62)}
    diff = float(np.max(np.abs(np.asarray(cases["kept"]()) - np.asarray(cases["fresh"]()))))
    first, seconds = interleaved(cases, rounds)
    res = {"env": environment(), "shape": [h, w], "method": method, "rounds": rounds,
           "max_abs_difference": diff, "first_call_s": first,
           **{name: {"best_ms": 1e3 * min(s), "median_ms": 1e3 * float(np.median(s)),
                     "page_faults": page_faults(cases[name])}
              for name, s in seconds.items()}}
    print({k: v for k, v in res.items() if k != "env"}, flush=True)
    write_json(out, res)


def _options(parser):
    parser.add_argument("--rounds", type=int, default=12)
    parser.add_argument("--size", type=int, nargs=2, default=(4096, 4096),
                        metavar=("ROWS", "COLUMNS"))
    parser.add_argument("--method", choices=("fc", "dct"), default="fc")
    parser.add_argument("--out", default="ab_fc_kept", help="JSON name under results/")


if __name__ == "__main__":
    args = arguments(__doc__, configure=_options)
    main(args.rounds, tuple(args.size), args.method, args.out)
