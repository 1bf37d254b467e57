"""FC and DCT integration with the height steps written as one stacked array, or left free.

`integrate(method="fc")` and `method="dct"` (orthographic, at the top level) first compute the
column and row height steps from the normals (`_orthographic_steps`), then the half spectrum,
in one program. `_stacked_steps_array` writes the two step planes as one `(2, H, W)` array
behind an `optimization_barrier`; left free (the form before), XLA-CPU wrote $1/|n|$ and the slope to
memory for the two planes' passes to share. This compiles both spectrum programs each way (the
form before patched in while tracing), compares the heights (the two forms, and each form's
repeated calls, which XLA-CPU's FFTs may change in the last bits), counts each
program's fusions, and times the whole integration (spectrum program, then the height
program, as `integrate` runs them) each way in the same interleaved rounds as `bench_core.py`'s
scipy baselines, at 1280x1024.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_stacked_steps.py
    -> benchmarks/results/stacked_steps.json
"""

from __future__ import annotations

import re
import sys
import types

import jax
import jax.numpy as jnp
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

H, W, ROUNDS = 1024, 1280, 25


def _free_steps(normals, mask):
    """The form before: the steps as `_orthographic_steps` returns them, stacked with no
    barrier (XLA takes each plane back out of the stack)."""
    dzdc, dzdr, ok = integ._orthographic_steps(normals, mask)
    return jnp.stack([dzdc, dzdr]), ok


def compiled(program, form, *args, **static):
    """`program` (a jitted spectrum function of `integ`) traced with the steps `form`
    (`"stacked"` or `"free"`); returns a callable of `args` and the fusion count."""
    f = program.__wrapped__  # a new function object per form: JAX caches traces per function
    fn = jax.jit(types.FunctionType(f.__code__, f.__globals__, f.__name__, f.__defaults__,
                                    f.__closure__), static_argnames=tuple(static))
    saved = integ._stacked_steps_array
    integ._stacked_steps_array = saved if form == "stacked" else _free_steps
    try:
        text = fn.lower(*args, **static).compile().as_text()
        jax.block_until_ready(fn(*args, **static))  # traced (and cached) with this form
    finally:
        integ._stacked_steps_array = saved
    return (lambda: fn(*args, **static)), len(re.findall(r"= \S+ fusion\(", text))


def main():
    lights = jaxps.synthetic.scanner_lights(20.0)
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(H, W), lights)
    normals = jax.block_until_ready(
        jaxps.photometric_stereo(jax.device_put(scene.images), lights).normals)
    mask = jax.device_put(np.ones((H, W), bool))
    pixel_size = jax.device_put(np.float32(1.0))
    p, q = _pq(np.asarray(normals))
    res = {"env": environment(), "shape": [H, W], "rounds": ROUNDS, "fusions": {},
           "max_abs_height_difference": {}}
    calls = {}
    for form in ("free", "stacked"):
        fc_spec, n_fc = compiled(integ._fc_spectrum_from_normals, form, normals, mask,
                                 pixel_size)
        dct_spec, n_dct = compiled(integ._dct_spectrum_from_normals, form, normals, mask,
                                   cam=None)
        res["fusions"][form] = {"fc_spectrum": n_fc, "dct_spectrum": n_dct}

        def fc(spec=fc_spec):
            return integ._fc_height(spec()[0], mask, None, (H, W))

        def dct(spec=dct_spec):
            g, valid = spec()
            return integ._dct_height(g, valid, None, pixel_size, None, (H, W))

        calls[f"fc_{form}"], calls[f"dct_{form}"] = fc, dct
    # The two forms against each other, and each against itself: XLA-CPU's FFTs may differ in
    # the last bits from one call to the next on a loaded machine.
    res["max_abs_repeat_difference"] = {}
    for kind in ("fc", "dct"):
        a, b = (np.asarray(calls[f"{kind}_{form}"]()) for form in ("free", "stacked"))
        res["max_abs_height_difference"][kind] = float(np.max(np.abs(a - b)))
        for form in ("free", "stacked"):
            first = np.asarray(calls[f"{kind}_{form}"]())
            res["max_abs_repeat_difference"][f"{kind}_{form}"] = max(
                float(np.max(np.abs(np.asarray(calls[f"{kind}_{form}"]()) - first)))
                for _ in range(10))
    calls["fc_scipy"] = lambda: scipy_fc(p, q)
    calls["dct_scipy"] = lambda: scipy_dct_poisson(p, -q)
    _, times = interleaved(calls, ROUNDS)
    res["median_ms"] = {k: 1e3 * float(np.median(v)) for k, v in times.items()}
    res["min_ms"] = {k: 1e3 * float(min(v)) for k, v in times.items()}
    res["ratio_to_scipy_median"] = {
        f"{kind}_{form}": res["median_ms"][f"{kind}_{form}"] / res["median_ms"][f"{kind}_scipy"]
        for kind in ("fc", "dct") for form in ("free", "stacked")}
    path = write_json("stacked_steps", res)
    print({k: v for k, v in res.items() if k != "env"}, "->", path)


if __name__ == "__main__":
    arguments(__doc__)
    main()
