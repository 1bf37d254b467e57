"""Which elementwise expressions XLA-CPU compiles into one loop over memory, and which it splits.

    PYTHONPATH=src python benchmarks/fusion_rules.py [--out benchmarks/results/fusion_rules.json]

Each probe is one jitted expression of two `(1, 595000)` float32 inputs (the pixels of a
700x850 image) with one output, or two for the last three. It is compiled (not run), and the
script counts the loop fusions over the whole image in the compiled HLO: 1 per output means
one pass over memory each; each extra one is an intermediate written to memory and read back.
docs/brdf.md ("Speed") and docs/speed.md (L2's solve per output pass) use these rules. The
last line counts the same for `jaxps.relight` of an MLP model at 700x850.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

P = 595_000
TABLE = np.random.default_rng(0).uniform(size=64).astype(np.float32)  # a small lookup table


def _lookup(a):
    return jnp.asarray(TABLE)[jnp.clip(a.astype(jnp.int32), 0, 63)]


PROBES = {
    # a quotient of two computed arrays, used more than once: split
    "a / b, used twice": lambda a, b: (a / b) * 2 + (a / b) * (a / b),
    "a / b, used once": lambda a, b: (a / b) * 2 + a,
    "a * (1 / b), the product used twice": lambda a, b: (a * (1 / b)) * 2
    + (a * (1 / b)) * (a * (1 / b)),
    "1 / b, used three times": lambda a, b: (1 / b) * a + (1 / b) * (1 / b) * 3,
    "2 / b, used three times": lambda a, b: (2 / b) * a + (2 / b) * (2 / b) * 3,
    "a / b inside where, used three times": lambda a, b: jnp.where(
        a / b > 0.4, (a / b - 1) / (a / b + 1), a / b),
    "sqrt(a), used three times": lambda a, b: jnp.sqrt(a) * 2 + jnp.sqrt(a) * b
    + jnp.maximum(jnp.sqrt(a), b),
    "rsqrt(a), used twice": lambda a, b: jax.lax.rsqrt(a) * 2 + jax.lax.rsqrt(a) * b,
    "exp(a), used three times": lambda a, b: jnp.exp(a) * 2 + jnp.exp(a) * b
    + jnp.maximum(jnp.exp(a), b),
    "tanh(a * b + i), five of them summed": lambda a, b: sum(
        jnp.tanh(i * (a * b) + b) for i in range(5)),
    "a gather, used twice": lambda a, b: (lambda g: g * a + g * g)(_lookup(a)),
    "a gather, used once": lambda a, b: _lookup(a) * b,
    # two outputs that need the same value: XLA-CPU writes it once and both outputs read it,
    # also when it is written out twice (XLA's common-subexpression pass merges the copies),
    # and an optimization barrier around each copy's inputs does not keep them apart
    "two outputs of one shared value": lambda a, b: (lambda s: (s + 1, s * b))(
        jnp.sqrt(a * b + a)),
    "two outputs, the value written out twice": lambda a, b: (
        jnp.sqrt(a * b + a) + 1, jnp.sqrt(a * b + a) * b),
    "two outputs, each from its own barrier copy": lambda a, b: tuple(
        f(*jax.lax.optimization_barrier(((a, b), np.int32(i)))[0]) for i, f in enumerate(
            (lambda a, b: jnp.sqrt(a * b + a) + 1, lambda a, b: jnp.sqrt(a * b + a) * b))),
}


def image_loops(fn) -> int:
    x = jnp.ones((1, P), jnp.float32)
    text = jax.jit(fn).lower(x, x).compile().as_text()
    return len(re.findall(rf"= \S+\[1,{P}\]\S* fusion\(", text))


def relight_loops(h=700, w=850) -> int:
    """Loops over the image in `jaxps.relight` of an `mlp_ratio` model (700x850, one light),
    traced whole inside one `jit`, so that the count is the same for any version of the
    library."""
    import jaxps

    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(h, w),
                                         jaxps.synthetic.scanner_lights(20.0))
    model = jaxps.fit_brdf(scene.images, scene.normals, scene.albedo,
                           jaxps.synthetic.scanner_lights(20.0), mask=scene.mask,
                           method="mlp_ratio", n_samples=2000, max_steps=2,
                           key=jax.random.key(0))
    light = jnp.asarray(jaxps.lights_from_angles([30.0], [10.0]), jnp.float32)
    fn = jax.jit(lambda n, a, l: jaxps.relight(model, n, a, l))
    text = fn.lower(jnp.asarray(scene.normals), jnp.asarray(scene.albedo),
                    light).compile().as_text()
    return len(re.findall(rf"= \S+\[(1,)?{h * w}\]\S* fusion\(|= \S+\[(1,)?{h},{w}\]\S* "
                          r"fusion\(", text))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path,
                        default=Path(__file__).parent / "results" / "fusion_rules.json")
    args = parser.parse_args()
    res = {"jax": jax.__version__, "backend": jax.default_backend(), "pixels": P, "loops": {}}
    for name, fn in PROBES.items():
        res["loops"][name] = image_loops(fn)
        print(f"{res['loops'][name]:2d}  {name}", flush=True)
    res["relight_mlp_ratio_700x850_loops"] = relight_loops()
    print(f"{res['relight_mlp_ratio_700x850_loops']:2d}  jaxps.relight, mlp_ratio, 700x850")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
