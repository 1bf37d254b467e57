"""A negative result, kept so that its figures can be rerun: the weighted L2 residual in closed
form (docs/speed_history.md, "Not there yet", dropped samples).

The weighted solve (`ps/_l2.py`, `_pixel_weighted`) recomputes each used sample's misfit
$g_k - l_k \\cdot b$ once $b$ is known. The closed form $\\sum_k w_k g_k^2 - b^T r$ (with
$r = \\sum_k w_k g_k l_k$, already built for the solve) needs no second look at the samples,
but in float32 the difference of two nearly equal sums cancels. This script times both on the
benchmark's K=12 capture with 5% of samples dropped (a shadow threshold at the 5th percentile)
and reports how far the closed-form residual is from the exact one.

Run: `OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/tried_weighted_residual.py`
-> `benchmarks/results/tried_weighted_residual.json`.
"""

from __future__ import annotations

import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxps
from jaxps.core._linalg import REL_DET_MIN, solve3
from jaxps.core._status import Status
from jaxps.ps import _l2

try:
    from benchmarks._common import arguments, environment, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, environment, write_json


def pixel_weighted_closed_form(x, usable, inside, lights, thresholds, all_finite=False):
    """`_l2._pixel_weighted` (grey) with the residual from the normal equations."""
    g, w, cases, n_used, a, r, _ = _l2._weighted_system(x, usable, lights, thresholds,
                                                        all_finite)
    b, rel_det = solve3(a, r)
    b = [b[p] for p in range(3)]
    sq = jnp.maximum(sum(wk * gk * gk for wk, gk in zip(w, g))
                     - sum(b[p] * r[p] for p in range(3)), 0)
    cases.append((rel_det < REL_DET_MIN, Status.DEGENERATE))
    return _l2._finish(lambda: (b, sq, None), n_used, cases, inside, backfacing_from_b=True)


def main(repeats=15):
    h, w = 1024, 1280
    t = np.linspace(0, 2 * np.pi, 11, endpoint=False)
    lights = np.asarray(jaxps.lights_from_angles(np.r_[0, 30 * np.cos(t)],
                                                 np.r_[0, 30 * np.sin(t)]), np.float32)
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(h, w), jnp.asarray(lights))
    images, mask = jax.device_put(scene.images), jnp.asarray(scene.mask)
    threshold = float(np.percentile(np.asarray(scene.images)[:, np.asarray(scene.mask)], 5))
    thresholds = (jnp.float32(0), jnp.float32(np.inf), jnp.float32(threshold))
    lt = jnp.asarray(lights)

    def solver(kernel):
        # `_solve_weighted` looks `_pixel_weighted` up when traced: each jit gets its kernel
        _l2._pixel_weighted = kernel
        f = jax.jit(lambda im: _l2._stacked(_l2._solve_weighted(im, lt, mask, None, thresholds)))
        jax.block_until_ready(f(images))
        return f

    exact_kernel = _l2._pixel_weighted
    try:
        fns = {"exact": solver(exact_kernel),
               "closed_form": solver(pixel_weighted_closed_form)}
    finally:
        _l2._pixel_weighted = exact_kernel
    out = {name: f(images) for name, f in fns.items()}
    times = {name: [] for name in fns}
    for _ in range(3):  # interleaved rounds
        for name, f in fns.items():
            for _ in range(repeats // 3):
                t0 = time.perf_counter()
                jax.block_until_ready(f(images))
                times[name].append(time.perf_counter() - t0)
    ok = np.asarray(out["exact"][2]) == Status.OK
    exact, closed = (np.asarray(out[n][4])[ok] for n in ("exact", "closed_form"))
    res = {"shape": [12, h, w], "dropped_fraction": 0.05,
           "median_s": {n: float(np.median(v)) for n, v in times.items()},
           "exact_residual_max": float(exact.max()),
           "closed_form_residual_max": float(closed.max()),
           "residual_max_abs_difference": float(np.abs(closed - exact).max()),
           "normals_max_abs_difference": float(np.abs(np.asarray(out["exact"][0])
                                                      - np.asarray(out["closed_form"][0])).max()),
           "env": environment()}
    print(res)
    write_json("tried_weighted_residual", res)


if __name__ == "__main__":
    arguments(__doc__)
    main()
