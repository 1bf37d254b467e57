"""L2's solves in this tree against the same solves at an earlier revision, interleaved.

Runs of `bench_core.py` one after another moved by up to 2x on this project's shared
machine, more than most kernel changes are worth. This loads `src/jaxps/ps/_l2.py` as it was
at `--before` (`git show`) next to the current one, in one process (the old module imports
the current tree's other modules), and times the same programs of both in alternating order,
so that a slow spell falls on both (each pair of programs alone, as the other program's
memory left behind shifted a program's time by up to 10%). At 1280x1024 with 5% of the
samples in the mask below a shadow threshold (every sample finite), for K = 5 and 12:

- `host, grey`: the host-chosen solve, `branch="weighted_finite"` (the packed solve), what a
  top-level CPU call runs;
- `traced`: `branch=None`, the flag pass and `cond` of a call inside `jit`;
- `host, colour`: three channels, `branch="weighted_finite"`;
- `traced, clean`: `branch=None` with every sample used (no shadow threshold);
- `vmap x4` and `vmap x4, clean`: `branch=None` under `jax.vmap` over four scaled copies of
  the capture, with the mask shared (closed over, not mapped).

Also recorded: whether both compile to the same optimised HLO (metadata left out), whether
status and n_used are equal, the largest normal difference, and the
minor page faults of one more call of each (`page_faults`: fresh memory of 32 MiB or more,
which glibc maps anew on every call). Run under glibc settings that keep freed memory
(`MALLOC_ARENA_MAX=1 MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=68719476736`, recorded in the
JSON's `allocator`), the timings leave those faults out.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/ab_l2.py --before REV [--name NAME]
    -> benchmarks/results/NAME.json (default ab_l2.json)
"""

from __future__ import annotations

import argparse
import functools
import pathlib
import re
import statistics
import sys
import tempfile

import jax
import jax.numpy as jnp
import numpy as np

import jaxps
from jaxps.ps import _l2

try:
    from benchmarks._common import environment, interleaved, module_at, page_faults, write_json
    from benchmarks.bench_core import ring_lights
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import environment, interleaved, module_at, page_faults, write_json
    from benchmarks.bench_core import ring_lights

H, W = 1024, 1280


def programs(module, k, captures=4):
    """The programs of `module` on one synthetic capture with K lights (and `captures`
    scaled copies of it for `jax.vmap`)."""
    lights = ring_lights(k) if k >= 8 else jaxps.synthetic.scanner_lights(20.0, k=k)
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(H, W), lights)
    grey = np.asarray(scene.images)
    mask = np.asarray(scene.mask)
    threshold = float(np.percentile(grey[:, mask], 5))
    thresholds = tuple(jnp.asarray(t, jnp.float32) for t in (0.0, jnp.inf, threshold))
    shared = _l2.host_constants(np.asarray(lights, np.float64))
    lt, msk = jnp.asarray(lights, jnp.float32), jax.device_put(mask)
    images = jax.device_put(grey)
    colour = jax.device_put(np.stack([grey, 0.8 * grey, 0.6 * grey], -1))
    stack = jax.device_put(np.stack([grey * s for s in np.linspace(0.9, 1.1, captures)]))
    clean = thresholds[:2] + (jnp.float32(-jnp.inf),)  # every sample used

    def vmapped(ths):
        return jax.jit(jax.vmap(lambda x: module.ps_l2(x, lt, msk, None, ths, shared)))

    host = {"branch": "weighted_finite"}
    return {  # name -> (jitted function, arguments, static keyword arguments)
        "host, grey": (module.ps_l2, (images, lt, msk, None, thresholds, shared), host),
        "traced": (module.ps_l2, (images, lt, msk, None, thresholds, shared), {}),
        "host, colour": (module.ps_l2, (colour, lt, msk, None, thresholds, shared), host),
        "traced, clean": (module.ps_l2, (images, lt, msk, None, clean, shared), {}),
        f"vmap x{captures}": (vmapped(thresholds), (stack,), {}),
        f"vmap x{captures}, clean": (vmapped(clean), (stack,), {}),
    }


def compiled_text(fn, args, kwargs):
    """The optimised HLO of `fn(*args, **kwargs)` without metadata (source lines, frame ids),
    which differs between two copies of a module even where the program is the same."""
    text = fn.lower(*args, **kwargs).compile().as_text()
    text = re.sub(r", metadata=\{[^}]*\}", "", text)
    return [line for line in text.splitlines()
            if " = " in line and "stack_frame_id" not in line and "file_name_id" not in line]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", required=True, help="git revision to compare with")
    parser.add_argument("--rounds", type=int, default=25)
    parser.add_argument("--name", default="ab_l2", help="results/NAME.json")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        before = module_at(args.before, "src/jaxps/ps/_l2.py", pathlib.Path(folder))
    rows = []
    for k in (5, 12):
        now, then = programs(_l2, k), programs(before, k)
        for name in now:
            calls = {side: functools.partial(lambda f, a, kw: f(*a, **kw), *case[name])
                     for side, case in (("now", now), ("before", then))}
            # each pair on its own, so that both programs follow the other one alike
            _, seconds = interleaved(calls, args.rounds)
            a, b = calls["now"](), calls["before"]()
            same = all(np.array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)))
                       for f in ("status", "n_used"))
            t_now, t_before = (statistics.median(seconds[v]) for v in ("now", "before"))
            rows.append({"K": k, "program": name, "now_ms": 1e3 * t_now,
                         "before_ms": 1e3 * t_before, "now_over_before": t_now / t_before,
                         "same_hlo": compiled_text(*now[name]) == compiled_text(*then[name]),
                         "status_and_n_used_equal": same,
                         "max_normal_difference": float(np.abs(np.asarray(a.normals)
                                                               - np.asarray(b.normals)).max()),
                         "now_page_faults": page_faults(calls["now"]),
                         "before_page_faults": page_faults(calls["before"])})
            r = rows[-1]
            print(f"K={k:2d} {name:13s} now {r['now_ms']:7.2f} ms  before {r['before_ms']:7.2f} "
                  f"ms  {r['now_over_before']:.3f}x  same HLO {r['same_hlo']}  equal {same}  "
                  f"normals {r['max_normal_difference']:.1e}  page faults {r['now_page_faults']}"
                  f" / {r['before_page_faults']}")
    path = write_json(args.name, {
        "command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/ab_l2.py "
                   + " ".join(sys.argv[1:] if argv is None else argv),
        "environment": environment(), "before": args.before, "rounds": args.rounds,
        "shape": [H, W], "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
