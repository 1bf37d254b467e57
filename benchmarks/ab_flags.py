"""The L2 flag passes with their flags reduced at once against `_max_flags` (groups of 8
pixels as uint8 first), interleaved in one process.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/ab_flags.py [--rounds 100]
    -> benchmarks/results/ab_flags.json

At 1280x1024, K=5, every sample used:

- `switch`: a single call's one program, `ps_l2(branch="switch")` (flags, then `lax.switch`
  over the three solves), compiled with `OLDER_EMITTERS` as `photometric_stereo` does;
- `batch_flags`: `l2_batch_flags` over 8 such captures.

Both are `ps/_l2.py`'s own functions, traced once with `_max_flags` and once with it replaced
by the reduction it replaced.

Each pair is timed alternately for `--rounds` rounds (the order swapped every round); the
JSON holds the best and median ms of each, whether the outputs are equal, and the minor page
faults of one more call of each.
"""

from __future__ import annotations

import contextlib
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

from benchmarks.bench_batch import captures
from jaxps.core._host import OLDER_EMITTERS, aligned
from jaxps.ps import _l2
from jaxps.ps._photometric_stereo import _sample_thresholds


def _reduced_at_once(needs, per_capture=False):
    """The reduction before `_max_flags`: int32 flags, all pixels at once."""
    return jnp.max(needs, axis=tuple(range(int(per_capture), needs.ndim)))


@contextlib.contextmanager
def _reduction(max_flags):
    """`ps/_l2.py`'s own programs traced with `max_flags` as their flag reduction."""
    kept = _l2._max_flags
    _l2._max_flags = max_flags
    try:
        yield
    finally:
        _l2._max_flags = kept


def _switch(max_flags, args):
    """A single call's one program, `ps_l2(branch="switch")`, compiled as
    `photometric_stereo` compiles it."""
    with _reduction(max_flags):
        return jax.jit(lambda *a: _l2.ps_l2(*a, branch="switch")).lower(*args).compile(
            compiler_options=OLDER_EMITTERS)


def _batch_flags(max_flags, args):
    """`l2_batch_flags`, compiled afresh with `max_flags`."""
    with _reduction(max_flags):
        # a new function each time: JAX keeps one trace per function
        return jax.jit(lambda *a: _l2.l2_batch_flags.__wrapped__(*a)).lower(*args).compile()


def _interleaved(fns, args, rounds):
    times = {k: [] for k in fns}
    for r in range(rounds):
        for k in (list(fns) if r % 2 else list(fns)[::-1]):
            t0 = time.perf_counter()
            jax.block_until_ready(fns[k](*args))
            times[k].append(time.perf_counter() - t0)
    return {k: {"best_ms": 1e3 * min(v), "median_ms": 1e3 * float(np.median(v))}
            for k, v in times.items()}


def main(rounds):
    caps, lights, mask = captures(8)
    thresholds = tuple(jnp.float32(t) for t in _sample_thresholds())
    unit = np.asarray(lights, np.float64)
    unit = unit / np.linalg.norm(unit, axis=1, keepdims=True)
    one = (jax.device_put(aligned(caps[0]))[..., None], jnp.asarray(unit, jnp.float32),
           jnp.asarray(mask), None, thresholds,
           _l2._cast_shared(tuple(jnp.asarray(c) for c in _l2.host_constants(unit)),
                            jnp.float32))
    stack = (jax.device_put(aligned(caps)),
             jax.device_put(aligned(np.broadcast_to(mask, (8, *mask.shape)))), None, thresholds)
    res = {"env": environment(), "shape": [8, 5, *mask.shape], "rounds": rounds}
    for name, make, args in (("switch", _switch, one), ("batch_flags", _batch_flags, stack)):
        fns = {"reduced_at_once": make(_reduced_at_once, args),
               "max_flags": make(_l2._max_flags, args)}
        outs = {k: jax.tree.leaves(f(*args)) for k, f in fns.items()}
        equal = all(bool(jnp.array_equal(a, b)) for a, b in zip(*outs.values()))
        del outs
        res[name] = {"equal": equal, **_interleaved(fns, args, rounds),
                     "page_faults": {k: page_faults(lambda f=f, a=args: f(*a))
                                     for k, f in fns.items()}}
        print(name, res[name], flush=True)
    write_json("ab_flags", res)


def _options(parser):
    parser.add_argument("--rounds", type=int, default=100)


if __name__ == "__main__":
    args = arguments(__doc__, configure=_options)
    main(args.rounds)
