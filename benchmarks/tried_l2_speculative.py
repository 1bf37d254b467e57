"""Tried and not kept: L2's every-sample-used solve with no flag pass before it, checked after.

A top-level L2 call on a grey stack runs `ps_l2(branch="switch")`: a flag pass reads the whole
stack (does any pixel in the mask drop a sample? is any sample non-finite?), then `lax.switch`
runs the solve the flags call for. The speculative program here skips that pass when it can:

1. a probe reads every 8th row for dropped samples; if it finds one, the flag pass and the
   weighted solve run as in the switch;
2. else the every-sample-used solve runs, and its residual's loop, which reads every sample
   anyway, sets the residual to -1 where the pixel drops a sample (`_pixel_flags`); in the
   status's loop instead, XLA-CPU wrote |b| and 1/|b| to memory (6 loop fusions, not 4);
3. on the host, a negative residual (one read of a scalar: the minimum) means the probe
   missed a pixel, and the call runs the switch program after all.

The results equal the switch's (the tests of the trial compared them with the traced `cond`,
a patch on and between probed rows). This times both programs, compiled alike (XLA-CPU's
older emitters), interleaved, with numpy's pinv-matmul + normalise and the bare XLA kernel of
`bench_core.py`, at 1280x1024 with the face mask, K = 5 and 12:

- every sample used (the speculation holds);
- 5% of the samples in the mask under a shadow threshold (the probe sees them);
- one 4x4 px saturated patch in one frame, between probed rows (the probe misses it: the
  call runs twice);
- 30 such patches at random places.

Why it was not kept: it saves at most the flag pass, and a miss costs a second solve. With
`--real` it also reports, for the shared captures as `load_capture` gives them (psm objects
with their masks, Yale B's five cross lights with the ambient frame; saturated samples left
out as the README's quick start does), how many pixels in the mask drop a sample and whether
the probe's rows hold one of them.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/tried_l2_speculative.py
    [--rounds 30] [--name tried_l2_speculative] -> benchmarks/results/NAME.json
"""

from __future__ import annotations

import argparse
import statistics
import sys

import jax
import jax.numpy as jnp
import numpy as np

import jaxps
from jaxps.core._host import OLDER_EMITTERS, CpuTuned, aligned, to_device
from jaxps.ps import _l2
from jaxps.ps._photometric_stereo import _sample_thresholds

try:
    from benchmarks._common import data_dir, environment, interleaved, write_json
    from benchmarks.bench_core import bare_l2, numpy_ps, ring_lights
except ImportError:  # run as a script
    import pathlib

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import data_dir, environment, interleaved, write_json
    from benchmarks.bench_core import bare_l2, numpy_ps, ring_lights

H, W = 1024, 1280
PROBE_STRIDE = 8


def _pixel_all_used_marked(x, usable, inside, shared, thresholds):
    """`_l2._pixel_all_used`, the residual -1 where `_l2._pixel_flags` says the pixel drops a
    sample."""
    *out, residual = _l2._pixel_all_used(x, usable, inside, shared, thresholds)
    needs = (_l2._pixel_flags(x, usable, inside, thresholds) & 1) == 1
    return *out, jnp.where(needs, jnp.asarray(-1, residual.dtype), residual)


def _speculative(images, lights, mask, sample_mask, thresholds, shared):
    """The speculative program: `(normals, albedo, status, n_used, residual), recheck`."""
    rows = (images[:, ::PROBE_STRIDE], None if mask is None else mask[::PROBE_STRIDE],
            None if sample_mask is None else sample_mask[:, ::PROBE_STRIDE])
    probe = _l2._max_flags(_l2._flags(*rows, thresholds, flat=False))

    def clean(im, lt, m, sm, th):
        axis = None if sm is None else 0
        return _l2._stacked(_l2._lift(_pixel_all_used_marked, (0, axis, _l2._axis(m), None, None),
                                      False)(*_l2._planes(im, sm, m, False), shared, th))

    def weighted(*a):
        flags = _l2._max_flags(_l2._flags(a[0], a[2], a[3], a[4], flat=False))
        return jax.lax.cond(
            (flags >> 1) & 1 == 1,
            lambda *b: _l2._stacked(_l2._solve_weighted(*b, flat=False, packed=True)),
            lambda *b: _l2._stacked(_l2._solve_weighted(*b, flat=False, all_finite=True,
                                                        packed=True)),
            *a)

    out = jax.lax.cond(probe & 1 == 1, weighted, clean,
                       images, lights, mask, sample_mask, thresholds)
    return out, jnp.min(out[4]) < 0  # the weighted residuals are never negative


def _switch(images, lights, mask, sample_mask, thresholds, shared):
    return _l2.ps_l2(images, lights, mask, sample_mask, thresholds, shared, branch="switch")[:5]


speculative_program = CpuTuned(_speculative, OLDER_EMITTERS)
switch_program = CpuTuned(_switch, OLDER_EMITTERS)


def patches(images, mask, n, rng, between=True):
    """`images` with `n` saturated 4x4 patches in frame 1, inside `mask`, each starting 2 rows
    after a probed row (`between`) so that the probe does not read it."""
    out = np.array(images)
    rows, cols = np.nonzero(mask[:-8, :-4])
    for i in rng.choice(len(rows), n, replace=False):
        r = (rows[i] // PROBE_STRIDE) * PROBE_STRIDE + 2 if between else rows[i]
        out[1, r:r + 4, cols[i]:cols[i] + 4] = 1.0
    return aligned(out)


def ways(images, lights, mask, thresholds):
    """`{"speculative": fn, "switch": fn}` on the same arguments; `fn()` returns the five
    arrays of the result, and `twice` says whether the speculative call ran the switch."""
    shared = tuple(jnp.asarray(a, jnp.float32) if a.dtype != bool else jnp.asarray(a)
                   for a in _l2.host_constants(lights))
    args = (to_device(images), jnp.asarray(lights, jnp.float32), mask, None,
            tuple(jnp.asarray(t, jnp.float32) for t in thresholds), shared)
    twice = []

    def speculative():
        out, recheck = speculative_program(*args)
        if bool(recheck):  # a pixel off the probed rows drops a sample
            del out
            twice.append(True)
            return switch_program(*args)
        return out

    return {"speculative": speculative, "switch": lambda: switch_program(*args)}, twice


def real_captures():
    """`{capture: {"pixels_dropping", "rows", "probe_sees_one"}}` for the shared captures
    (`_common.data_dir()`), as the speculative program's probe would find them."""
    from jaxps import acquisition

    root, out = data_dir(), {}
    caps = {obj: {"path": root / "psm" / obj, "lights": root / "psm" / "lights.txt",
                  "mask": root / "psm" / obj / f"{obj}.mask.png"} for obj in ("cat", "owl")}
    cross = [("+000", "+00"), ("+025", "+00"), ("-025", "+00"), ("+000", "+20"), ("+000", "-20")]
    for s in range(1, 6):
        d = root / "yaleb" / f"yaleB0{s}"
        caps[d.name] = {"path": [d / f"{d.name}_P00A{a}E{e}.pgm" for a, e in cross],
                        "yale_names": True, "ambient": d / f"{d.name}_P00_Ambient.pgm"}
    for name, kw in caps.items():
        cap = acquisition.load_capture(kw.pop("path"), **kw)
        grey = np.asarray(cap.images, np.float32)
        grey = grey.mean(-1) if grey.ndim == 4 else grey
        thresholds = tuple(jnp.asarray(t, jnp.float32) for t in _sample_thresholds())
        flags = np.asarray(_l2._flags(jnp.asarray(grey), jnp.asarray(cap.mask),
                                      jnp.asarray(~cap.saturated), thresholds, flat=False))
        rows = np.unique(np.nonzero(flags & 1)[0])
        out[name] = {"pixels_dropping": int((flags & 1).sum()), "rows": rows.tolist(),
                     "probe_sees_one": bool((rows % PROBE_STRIDE == 0).any())}
        print(f"{name}: {out[name]['pixels_dropping']} pixels drop a sample, on {len(rows)} rows;"
              f" the probe sees one: {out[name]['probe_sees_one']}", flush=True)
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--name", default="tried_l2_speculative", help="results/NAME.json")
    parser.add_argument("--real", action="store_true",
                        help="only the shared captures' dropped samples (no timing)")
    args = parser.parse_args(argv)
    command = ("PYTHONPATH=src python benchmarks/tried_l2_speculative.py "
               + " ".join(sys.argv[1:] if argv is None else argv))
    if args.real:
        path = write_json(args.name, {"command": command, "probe_stride": PROBE_STRIDE,
                                      "captures": real_captures()})
        print(f"wrote {path}")
        return
    surface = jaxps.synthetic.face_like(H, W)
    rng = np.random.default_rng(0)
    rows = []
    for k in (5, 12):
        lights = np.asarray(ring_lights(k) if k >= 8 else jaxps.synthetic.scanner_lights(20.0, k=k),
                            np.float64)
        lights /= np.linalg.norm(lights, axis=1, keepdims=True)
        scene = jaxps.synthetic.render_scene(surface, lights)
        grey = aligned(np.asarray(scene.images, np.float32))
        face = np.asarray(scene.mask)
        mask = to_device(aligned(face), bool)
        shadow = float(np.percentile(grey[:, face], 5))
        pinv = np.linalg.pinv(lights).astype(np.float32)
        bare, dev = bare_l2(lights), to_device(grey)
        clean = _sample_thresholds()
        cases = {"every sample used": (grey, clean),
                 "5% of samples dropped": (grey, _sample_thresholds(shadow)),
                 "one patch between probed rows": (patches(grey, face, 1, rng), clean),
                 "30 patches": (patches(grey, face, 30, rng, between=False), clean)}
        for case, (images, thresholds) in cases.items():
            fns, twice = ways(images, lights, mask, thresholds)
            _, seconds = interleaved({**fns, "numpy": lambda g=grey, p=pinv: numpy_ps(g, p),
                                      "bare": lambda f=bare, x=dev: f(x)}, args.rounds)
            a, b = fns["speculative"](), fns["switch"]()
            same = all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(a[2:4], b[2:4]))
            ms = {w: 1e3 * statistics.median(s) for w, s in seconds.items()}
            row = {"K": k, "case": case, **{f"{w}_ms": v for w, v in ms.items()},
                   "speculative_over_switch": ms["speculative"] / ms["switch"],
                   "ran_twice": bool(twice),
                   "pixels_dropping": int((np.asarray(b[3])[face] < k).sum()),
                   "status_and_n_used_equal": same,
                   "max_normal_difference": float(jnp.abs(a[0] - b[0]).max())}
            rows.append(row)
            print(f"K={k:2d} {case:30s} speculative {ms['speculative']:6.2f} ms  switch "
                  f"{ms['switch']:6.2f} ms  {row['speculative_over_switch']:.3f}x  numpy "
                  f"{ms['numpy']:6.2f}  bare {ms['bare']:6.2f}  twice {row['ran_twice']}  "
                  f"equal {same}  normals {row['max_normal_difference']:.1e}", flush=True)
    path = write_json(args.name, {
        "command": "OPENBLAS_NUM_THREADS=1 " + command, "environment": environment(),
        "rounds": args.rounds, "shape": [H, W], "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
