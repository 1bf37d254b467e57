"""L2's every-sample-used solve with a solve of its own in each output pass, against the
same solve with every output taken from one solve (the form before), in the same rounds; and
the weighted solve's status from the sign of $b_z$ against that of $n_z$ (before).

`ps/_l2.py`'s `_finish` asks the solve for $b$ once for the status and once for each output
(normals, albedo, residual), so that XLA-CPU solves $b$ again in each output's loop instead
of writing $|b|$, $1/|b|$ and $n_z$ to memory for the other loops to read. The previous form
(`_finish_before`, patched in while it is traced) takes every output from one call. Both
are compiled the way `photometric_stereo` compiles a clean capture's solve (`_run` with
`branch="all_used"` and `OLDER_EMITTERS`), on a clean synthetic capture at 1280x1024, K = 5
and 12. The weighted solve (K = 12, 5% of the samples in the mask under a shadow threshold,
as in `bench_core.py`; `branch="weighted_finite"`, default emitters) is compiled with its
status from $b_z$ and, patched in, from $n_z$ (`backfacing_from_b=False`). The numpy
pinv-matmul + normalise of `bench_core.py` and the whole `photometric_stereo` call (flag
pass, host read, solve) run in the same interleaved rounds. Also recorded: each program's
loop fusions and compile time, and the largest difference between the two forms' outputs.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_l2_passes.py [--rounds 25]
    -> benchmarks/results/l2_passes.json
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxps
from jaxps.core._host import OLDER_EMITTERS
from jaxps.core._safe import safe_sqrt
from jaxps.core._status import Status, first_status
from jaxps.ps import _l2
from jaxps.ps._photometric_stereo import _run, _sample_thresholds

try:
    from benchmarks._common import RESULTS, environment, interleaved
    from benchmarks.bench_core import numpy_ps, ring_lights
except ImportError:  # run as a script
    import pathlib

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import RESULTS, environment, interleaved
    from benchmarks.bench_core import numpy_ps, ring_lights

H, W = 1024, 1280


def _finish_before(solve, n_used, cases, inside):
    """`_l2._finish` as it was: every output from one call of `solve`."""
    b, sq, colour_albedo = solve()
    rho_grey = safe_sqrt(b[0] ** 2 + b[1] ** 2 + b[2] ** 2)
    inv_rho = 1 / jnp.where(rho_grey > 0, rho_grey, 1)
    n = [v * inv_rho for v in b]
    rho = [rho_grey] if colour_albedo is None else colour_albedo(n)
    residual = safe_sqrt(sq / jnp.maximum(n_used, 1).astype(sq.dtype))
    status = first_status([(~inside, Status.MASKED), *cases, (~(rho_grey > 0), Status.DARK),
                           (n[2] < 0, Status.BACKFACING)])
    ok = status == Status.OK
    normal = (jnp.where(ok, n[0], 0), jnp.where(ok, n[1], 0), jnp.where(ok, n[2], 1))
    albedo = tuple(jnp.where(ok, v, 0) for v in rho)
    return normal, albedo, status, n_used, jnp.where(ok, residual, 0)


def _compiled(args, finish, branch):
    """The solve's program as `photometric_stereo` compiles it for `branch` (`"all_used"`
    with `OLDER_EMITTERS`, `"weighted_finite"` without), traced afresh with `_l2._finish`
    replaced by `finish` (None: as it is). Returns (compiled, compile s)."""
    jax.clear_caches()
    options = OLDER_EMITTERS if branch == "all_used" else {}
    fn = jax.jit(_run.__wrapped__, static_argnames=("method", "static"),
                 compiler_options=options)
    kept = _l2._finish
    if finish is not None:
        _l2._finish = finish
    try:
        t0 = time.perf_counter()
        compiled = fn.lower(*args, method="l2", static=(("branch", branch),)).compile()
        return compiled, time.perf_counter() - t0
    finally:
        _l2._finish = kept


_FINISH = _l2._finish  # as it is, before any patch


def _finish_nz(*args, **kwargs):
    """`_l2._finish` testing the sign of $n_z$ for `BACKFACING` (the weighted solve before)."""
    return _FINISH(*args, **{**kwargs, "backfacing_from_b": False})
# (label, lights K, 5% of the samples dropped, the solve's branch, the two forms)
CASES = [
    ("K=5", 5, False, "all_used", (("every output from one solve (before)", _finish_before),
                                   ("a solve per output pass", None))),
    ("K=12", 12, False, "all_used", (("every output from one solve (before)", _finish_before),
                                     ("a solve per output pass", None))),
    ("K=12, 5% dropped", 12, True, "weighted_finite", (("status from n_z (before)", _finish_nz),
                                                       ("status from b_z", None))),
]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    quick = os.environ.get("JAXPS_BENCH_QUICK") == "1"  # the runner's quick mode
    parser.add_argument("--rounds", type=int, default=3 if quick else 25)
    parser.add_argument("--out", default=str(RESULTS / "l2_passes.json"))
    ns = parser.parse_args()
    surface = jaxps.synthetic.face_like(H, W)
    cases, programs = {}, {}
    for label, k, dropped, branch, forms in CASES:
        lights = np.asarray(jaxps.synthetic.scanner_lights(20.0, k=k) if k < 12
                            else ring_lights(k), np.float64)
        lights /= np.linalg.norm(lights, axis=1, keepdims=True)
        scene = jaxps.synthetic.render_scene(surface, lights)
        images_np = np.asarray(scene.images)
        images = jax.device_put(images_np)
        mask = np.asarray(scene.mask)
        # a shadow threshold at the 5th percentile of the samples in the mask (bench_core's)
        shadow = float(np.percentile(images_np[:, mask], 5)) if dropped else None
        args = (images, lights, jax.device_put(mask) if dropped else None, None,
                _sample_thresholds(shadow), {"shared": _l2.host_constants(lights)})
        if not dropped:
            pinv = np.linalg.pinv(lights).astype(np.float32)
            cases[f"{label} numpy pinv-matmul+normalise"] = (
                lambda x=images_np, p=pinv: numpy_ps(x, p))
        outputs = {}
        for form, finish in forms:
            compiled, compile_s = _compiled(args, finish, branch)
            name = f"{label} solve, {form}"
            cases[name] = lambda c=compiled, a=args: c(*a)
            outputs[form] = [np.asarray(o) for o in cases[name]()[:5]]
            programs[name] = {"K": k, "compile_s": compile_s, "fusions": len(
                re.findall(r"= \S+ fusion\(", compiled.as_text()))}
        before, after = outputs.values()
        programs[f"{label} largest output difference"] = {
            field: float(np.max(np.abs(a.astype(np.float64) - b)))
            for field, a, b in zip(_l2.PSResult._fields, before, after)}
        options = {"mask": mask, "shadow_threshold": shadow} if dropped else {}
        cases[f"{label} photometric_stereo"] = (
            lambda x=images, lt=lights, o=options: jaxps.photometric_stereo(x, lt, **o))
    _, seconds = interleaved(cases, ns.rounds)
    rows = [{"case": name, "run_s_median": statistics.median(s), "run_s_min": min(s)}
            for name, s in seconds.items()]
    for r in rows:
        print(f"{r['case']:60s} {1e3 * r['run_s_median']:7.2f} ms", flush=True)
    for name, p in programs.items():
        print(name, p)
    result = {"shape": [H, W], "rounds": ns.rounds, "rows": rows, "programs": programs,
              "env": environment()}
    with open(ns.out, "w") as f:
        json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
