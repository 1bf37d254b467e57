"""A negative result, kept so that its figures can be rerun: L2 in row bands that stay in the
cache (docs/speed.md, "Tried and not kept").

At K=12 a 1 MP stack is 60 MB, more than the 32 MiB L3 cache, and the every-sample-used solve
reads it in each of its passes (status, normals, albedo, residual: `ps/_l2.py`, `_finish`),
after the flag pass has read it once. Solved in row bands of a quarter of the image, each
band's passes find its samples in the cache. The bands are fast; joining them into the
`(H, W, ...)` arrays that a `PSResult` holds is what costs. Timed here, at 1280x1024 on the
benchmark's synthetic face (`bench_core.py`'s scenes, every sample used), in interleaved
rounds (medians):

- `jaxps`: `photometric_stereo(images, lights)` (flag pass and solve in one program);
- `flags`: its flag pass alone (`l2_needs_weights`);
- `bands`: the every-sample-used solve on `--bands` row bands, one program per band (each
  slices its rows at a fixed offset), the outputs left as band arrays;
- `bands_joined`: the same, joined on the host into aligned arrays that JAX reads in place
  (`core._host.fill_on_threads`, 2 threads: what `irls` and `sbl` do with their bands);
- `bands_one_program`: one program for every band, given the first row as an argument
  (`lax.dynamic_slice`), the outputs left as band arrays;
- `bands_in_place`: one program per band writing its rows into the donated full-size outputs
  of the previous call (`.at[rows].set`, an in-place `dynamic-update-slice` on XLA-CPU).

The joined bands' outputs are checked against `jaxps`'s (`max_difference`: equal here, since
every sample is used, so both run the same kernel on each pixel).

Run: `OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/tried_l2_bands.py [--bands 4]
[--rounds 30] [--size 1024 1280] [--name tried_l2_bands]` -> `benchmarks/results/NAME.json`
(`--size 4096 4096 --bands 16 --rounds 8 --name tried_l2_bands_16mp`: the same at 16 MP, K=5
only).
"""

from __future__ import annotations

import functools
import pathlib
import sys

import jax
import numpy as np

import jaxps
from jaxps.core._host import OLDER_EMITTERS, CpuTuned, fill_on_threads
from jaxps.ps import _l2

try:
    from benchmarks._common import arguments, environment, interleaved, write_json
    from benchmarks.bench_core import H, W, ring_lights
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, environment, interleaved, write_json
    from benchmarks.bench_core import H, W, ring_lights

THRESHOLDS = (np.float32(0), np.float32(np.inf), np.float32(-np.inf))  # every sample used


def _band_solve(images, top, rows, shared):
    """The every-sample-used solve of rows `top:top + rows` (`top` static or traced)."""
    if isinstance(top, int):
        band = images[:, top:top + rows]
    else:
        band = jax.lax.dynamic_slice_in_dim(images, top, rows, axis=1)
    shared = _l2._cast_shared(shared, images.dtype)
    return _l2._stacked(_l2._solve_all_used(band, None, None, THRESHOLDS, shared, flat=False))


def _band_in_place(out, images, top, rows, shared):
    res = _band_solve(images, top, rows, shared)
    return tuple(o.at[top:top + rows].set(r) for o, r in zip(out, res))


STATIC = CpuTuned(_band_solve, OLDER_EMITTERS, static_argnums=(1, 2))
TRACED = CpuTuned(_band_solve, OLDER_EMITTERS, static_argnums=2)
IN_PLACE = CpuTuned(_band_in_place, OLDER_EMITTERS, static_argnums=(2, 3), donate_argnums=0)


def case(k, n_bands, rounds, h, w):
    lights = jaxps.synthetic.scanner_lights(20.0, k=k) if k < 12 else ring_lights(k)
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(h, w), lights)
    images = jax.device_put(scene.images)
    unit = np.asarray(lights, np.float64)
    shared = _l2.host_constants(unit / np.linalg.norm(unit, axis=1, keepdims=True))
    rows = h // n_bands
    tops = [i * rows for i in range(n_bands)]
    ours = jaxps.photometric_stereo(images, lights)
    shapes = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), tuple(ours[:5]))

    def part(top):
        return slice(top, top + rows), jax.tree.map(np.asarray, STATIC(images, top, rows, shared))

    def joined():
        return fill_on_threads(shapes, [functools.partial(part, t) for t in tops], 2)

    kept = [tuple(np.zeros(s.shape, s.dtype) for s in shapes)]

    def in_place():
        out = kept[0]
        for t in tops:
            out = IN_PLACE(out, images, t, rows, shared)
        kept[0] = out
        return out

    cases = {
        "jaxps": lambda: jaxps.photometric_stereo(images, lights),
        "flags": lambda: _l2.l2_needs_weights(images, None, None, THRESHOLDS),
        "bands": lambda: [STATIC(images, t, rows, shared) for t in tops],
        "bands_joined": joined,
        "bands_one_program": lambda: [TRACED(images, np.int32(t), rows, shared) for t in tops],
        "bands_in_place": in_place,
    }
    first, seconds = interleaved(cases, rounds)
    difference = max(float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))))
                     for a, b in zip(ours[:5], joined()))
    row = {"K": k, "bands": n_bands, "rounds": rounds,
           "median_ms": {n: 1e3 * float(np.median(s)) for n, s in seconds.items()},
           "first_call_s": first, "max_difference": difference}
    print(f"K={k}: " + ", ".join(f"{n} {v:.1f} ms" for n, v in row["median_ms"].items())
          + f"; max difference {difference:.1e}", flush=True)
    return row


def main(argv=None):
    args = arguments(__doc__, configure=lambda p: (
        p.add_argument("--bands", type=int, default=4, help="row bands (default 4)"),
        p.add_argument("--rounds", type=int, default=30, help="interleaved rounds (default 30)"),
        p.add_argument("--size", type=int, nargs=2, default=(H, W), metavar=("H", "W"),
                       help=f"image size (default {H} {W}; above 4x that, K=5 only)"),
        p.add_argument("--name", default="tried_l2_bands", help="results file name")),
        argv=argv)
    h, w = args.size
    if h % args.bands:
        raise ValueError(f"--bands must divide the image's {h} rows, got {args.bands}")
    ks = (5, 12) if h * w <= 4 * H * W else (5,)
    res = {"shape": [h, w], "cases": [case(k, args.bands, args.rounds, h, w) for k in ks],
           "env": environment()}
    write_json(args.name, res)


if __name__ == "__main__":
    main()
