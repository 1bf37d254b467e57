"""`integrate(method="fc" | "dct")` at 1280x1024 (or `--size`), timed against scipy in interleaved rounds,
for A/B runs of two versions of jaxps (run it once with each on `PYTHONPATH`).

The same calls as `bench_core.py`'s FC and DCT rows (normals from L2 PS of the synthetic face,
scipy's baselines from the same gradients), and the same with the scene's face mask, whose
height takes its mean over the mask. Also the number of loop fusions in the steps-to-spectrum
program of each method, read from the compiled HLO. `--save F` writes the heights to F
(`.npz`); `--compare A B` prints the largest difference between two such files.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/ab_integrate.py --out NAME
    -> benchmarks/results/NAME.json
"""

from __future__ import annotations

import re
import sys

import jax
import numpy as np

import jaxps
from jaxps.integration import _integrate as integ

try:
    from benchmarks._common import arguments, environment, interleaved, write_json
    from benchmarks.bench_core import _pq, scipy_dct_poisson, scipy_fc
except ImportError:  # run as a script
    import pathlib

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, environment, interleaved, write_json
    from benchmarks.bench_core import _pq, scipy_dct_poisson, scipy_fc

def _configure(parser):
    parser.add_argument("--out", default="ab_integrate", help="results/NAME.json")
    parser.add_argument("--rounds", type=int, default=40)
    parser.add_argument("--size", nargs=2, type=int, default=(1024, 1280),
                        metavar=("ROWS", "COLUMNS"))
    parser.add_argument("--save", help="write the heights to this .npz")
    parser.add_argument("--compare", nargs=2, metavar=("A", "B"),
                        help="largest height difference between two --save files, then stop")


def _fusions(program, *args, **static):
    text = program.lower(*args, **static).compile().as_text()
    return len(re.findall(r"= \S+ fusion\(", text.split("ENTRY")[1]))


def main():
    args = arguments(__doc__, configure=_configure)
    if args.compare:
        a, b = (np.load(f) for f in args.compare)
        print({k: float(np.max(np.abs(a[k] - b[k]))) for k in a.files})
        return
    h, w = args.size
    lights = jaxps.synthetic.scanner_lights(20.0)
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(h, w), lights)
    images = jax.device_put(scene.images)
    normals = jax.block_until_ready(jaxps.photometric_stereo(images, lights).normals)
    mask = np.asarray(scene.mask)
    p, q = _pq(np.asarray(normals))
    cases = {
        "fc": lambda: jaxps.integrate(normals),
        "dct": lambda: jaxps.integrate(normals, method="dct"),
        "fc_mask": lambda: jaxps.integrate(normals, mask=mask),
        "dct_mask": lambda: jaxps.integrate(normals, mask=mask, method="dct"),
        "ps_fc": lambda: jaxps.integrate(jaxps.photometric_stereo(images, lights).normals),
        "scipy_fc": lambda: scipy_fc(p, q),
        "scipy_dct": lambda: scipy_dct_poisson(p, -q),
    }
    first, seconds = interleaved(cases, args.rounds)
    med = {k: 1e3 * float(np.median(v)) for k, v in seconds.items()}
    res = {
        "env": environment(), "shape": [h, w], "rounds": args.rounds,
        "jaxps": jaxps.__file__,
        "fusions": {
            "fc_spectrum": _fusions(integ._fc_spectrum_from_normals, normals, None,
                                    np.float32(1)),
            "dct_spectrum": _fusions(integ._dct_spectrum_from_normals, normals, None, cam=None),
        },
        "median_ms": med,
        "min_ms": {k: 1e3 * float(min(v)) for k, v in seconds.items()},
        "first_call_s": first,
        "fc_over_scipy": med["fc"] / med["scipy_fc"],
        "dct_over_scipy": med["dct"] / med["scipy_dct"],
    }
    if args.save:
        np.savez(args.save, **{k: np.asarray(cases[k]()) for k in
                               ("fc", "dct", "fc_mask", "dct_mask")})
    path = write_json(args.out, res)
    print({k: v for k, v in res.items() if k not in ("env", "first_call_s")}, "->", path)


if __name__ == "__main__":
    main()
