"""The parametric fit (`fit_brdf(method="wrap_ggx")`, the default) in this tree against the
same fit at an earlier revision, interleaved, on the shared Yale B subjects.

Loads `src/jaxps/reflectance/_parametric.py` as it was at `--before` (`git show`) next to the
current one, in one process (the old module imports the current tree's other modules), and
points `fit_brdf` at each in turn. Per subject (bench_brdf.py's protocol: the five "cross"
lights less the frames `check_frames` flags, L2 normals and albedo, its face mask, key 0,
`fit_brdf`'s defaults) it records the fit's seconds in `--rounds` interleaved rounds after a
first call of each (which compiles), its LM steps, whether it converged, the shape parameters,
the training RMSE, and the gain-invariant relighting error within 30 degrees over Lambert's
(`score_relighting` on every other clean light within 60 degrees, as bench_relight.py).

Also, on the first subject: the LM Jacobian alone at 100,000 samples (20,000 pixels, as the
fit draws them), `jax.jacfwd` of the prediction against `_predict_and_jacobian` (medians of
interleaved calls, both compiled as the solver is) and their largest difference.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/ab_parametric.py --before REV \
        [--subjects ...] [--rounds 3] [--name NAME]
    -> benchmarks/results/NAME.json (default ab_parametric.json)
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import tempfile

import jax
import jax.numpy as jnp
import numpy as np

import jaxps
from jaxps.core._host import NO_YNN
from jaxps.reflectance import _brdf, _parametric

try:
    from benchmarks._common import environment, interleaved, module_at, write_json, yale_subjects
    from benchmarks.bench_brdf import cases
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import environment, interleaved, module_at, write_json, yale_subjects
    from benchmarks.bench_brdf import cases

SUBJECTS = yale_subjects()  # every yaleB* folder found (_common)


def fit_with(module, c):
    """`fit_brdf`'s default fit of case `c`, with `module` as its parametric code."""
    _brdf._parametric = module
    try:
        return jaxps.fit_brdf(c.images[c.train], c.ps.normals, c.ps.albedo, c.lights[c.train],
                              mask=c.mask, key=jax.random.key(0))
    finally:
        _brdf._parametric = _parametric


def jacobian_rows(c, rounds):
    """jacfwd against the hand-written Jacobian on case `c`'s first 20,000 masked pixels."""
    k = len(c.train)
    images = np.asarray(c.images[c.train], np.float32)
    pix = np.flatnonzero(np.asarray(c.mask).reshape(-1))[:20_000]
    h, w = c.mask.shape
    size = _parametric.REGION_PX
    cols = -(-w // size)
    region = ((np.arange(h * w) // w) // size * cols + np.arange(h * w) % w // size)[pix]
    data = jax.device_put((np.asarray(c.ps.normals, np.float32).reshape(-1, 3)[pix],
                           np.asarray(c.lights[c.train], np.float32),
                           np.nan_to_num(images.reshape(k, -1)[:, pix]),
                           np.isfinite(images.reshape(k, -1)[:, pix]).astype(np.float32),
                           region.astype(np.int32)))
    static = {"diffuse": "wrap", "specular": "ggx", "n_regions": cols * -(-h // size),
              "fit_gains": True}
    p = jnp.asarray([-1.0, -0.5, 0.01, -0.02, 0.0, 0.03, -0.01][:2 + k], jnp.float32)

    def jacfwd(p, data):
        return jnp.moveaxis(jax.jacfwd(lambda q: _parametric._predict(q, data, **static)[0])(p),
                            -1, 0)

    def hand(p, data):
        return _parametric._predict_and_jacobian(p, data, **static)[1]

    compiled = {name: jax.jit(fn).lower(p, data).compile(NO_YNN)
                for name, fn in (("jacfwd", jacfwd), ("hand_written", hand))}
    _, seconds = interleaved({name: (lambda f=f: f(p, data)) for name, f in compiled.items()},
                             rounds)
    diff = float(jnp.max(jnp.abs(compiled["jacfwd"](p, data) - compiled["hand_written"](p, data))))
    scale = float(jnp.max(jnp.abs(compiled["jacfwd"](p, data))))
    return {"subject": c.subject, "samples": int(k * pix.size),
            **{f"{name}_ms": 1e3 * statistics.median(s) for name, s in seconds.items()},
            "max_difference": diff, "max_entry": scale}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", required=True, help="git revision to compare with")
    ap.add_argument("--subjects", nargs="+", default=list(SUBJECTS))
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--jacobian-rounds", type=int, default=20)
    ap.add_argument("--name", default="ab_parametric")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        before = module_at(args.before, "src/jaxps/reflectance/_parametric.py",
                           pathlib.Path(folder))
        rows, jac = [], None
        for c in cases(args.subjects, ["cross"]):
            if jac is None:
                jac = jacobian_rows(c, args.jacobian_rounds)
                print(f"{c.subject} Jacobian, {jac['samples']} samples: jacfwd "
                      f"{jac['jacfwd_ms']:.2f} ms, hand-written {jac['hand_written_ms']:.2f} ms,"
                      f" largest difference {jac['max_difference']:.1e} (entries up to "
                      f"{jac['max_entry']:.2f})", flush=True)
            modules = {"now": _parametric, "before": before}
            first, seconds = interleaved({side: (lambda m=m, c=c: fit_with(m, c).fit.rmse)
                                          for side, m in modules.items()}, args.rounds)
            row = {"subject": c.subject, "frames": len(c.train), "mask_pixels": int(c.mask.sum())}
            for side, m in modules.items():
                model = fit_with(m, c)
                score = jaxps.score_relighting(model, c.images[c.test60], c.ps.normals,
                                               c.ps.albedo, c.lights[c.test60], mask=c.mask)
                row[side] = {"first_call_s": first[side],
                             "fit_s": statistics.median(seconds[side]),
                             "fit_s_rounds": seconds[side], "steps": model.fit.steps,
                             "converged": model.fit.converged,
                             "shape": np.asarray(model.params.shape).tolist(),
                             "rmse_gray": 255 * model.fit.rmse,
                             "gain_invariant_30_over_lambert": score.ratio["gain_30"],
                             "raw_30_over_lambert": score.ratio["raw_30"]}
            rows.append(row)
            print(" ".join(f"{c.subject} {side}: {r['fit_s']:.2f} s ({r['first_call_s']:.1f} s "
                           f"first), {r['steps']} steps, converged {r['converged']}, shape "
                           f"{np.round(r['shape'], 4).tolist()}, RMSE {r['rmse_gray']:.3f}, "
                           f"gain-inv. 30 {r['gain_invariant_30_over_lambert']:.4f};"
                           for side, r in ((s, row[s]) for s in modules)), flush=True)
    path = write_json(args.name, {
        "command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/ab_parametric.py "
                   + " ".join(sys.argv[1:] if argv is None else argv),
        "environment": environment(), "before": args.before, "rounds": args.rounds,
        "jacobian": jac, "subjects": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
