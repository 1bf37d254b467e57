"""Speed of the per-pixel helpers around the solvers, at 1280x1024: angular error, normals from a
height map, Lambertian rendering; each beside a numpy baseline and beside its previous form
(on the length-3 axis: `einsum`, `cross`, `norm`, `moveaxis`), all timed in one process.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_evaluate.py \
        [--rounds 15] [--out benchmarks/results/evaluate_speed.json]

Rounds interleave the rows so that the load of a shared machine hits them alike; median and
min over rounds, compile (first call) apart. Every row's result is checked against the first
row of its work before timing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxps
from jaxps.core._safe import safe_norm

try:
    from benchmarks._common import environment, interleaved
except ImportError:  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from benchmarks._common import environment, interleaved

OUT = Path(__file__).resolve().parent / "results"


@jax.jit
def angular_error_previous(a, b):
    """`jaxps.angular_error`'s kernel before it was written on the component planes."""
    a = a / jnp.maximum(safe_norm(a), 1e-12)[..., None]
    b = b / jnp.maximum(safe_norm(b), 1e-12)[..., None]
    cross = safe_norm(jnp.cross(a, b))
    dot = jnp.sum(a * b, axis=-1)
    both_zero = (cross == 0) & (dot == 0)
    return jnp.degrees(jnp.arctan2(cross, jnp.where(both_zero, 1, dot)))


def angular_error_numpy(a, b):
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1),
                                 np.einsum("hwc,hwc->hw", a, b)))


@jax.jit
def normals_from_height_previous(z, pixel_size):
    dzdr, dzdc = jnp.gradient(z)
    p, q = dzdc / pixel_size, -dzdr / pixel_size
    n = jnp.stack([-p, -q, jnp.ones_like(p)], axis=-1)
    return n / jnp.linalg.norm(n, axis=-1, keepdims=True)


def _masked_derivative_previous(z, mask, axis):
    zt, mt = jnp.moveaxis(z, axis, 0), jnp.moveaxis(mask, axis, 0)
    fwd = jnp.pad(zt[1:] - zt[:-1], ((0, 1), (0, 0)))
    has_fwd = jnp.pad(mt[1:] & mt[:-1], ((0, 1), (0, 0)))
    bwd = jnp.pad(zt[1:] - zt[:-1], ((1, 0), (0, 0)))
    has_bwd = jnp.pad(mt[1:] & mt[:-1], ((1, 0), (0, 0)))
    d = jnp.where(has_fwd & has_bwd, (fwd + bwd) / 2,
                  jnp.where(has_fwd, fwd, jnp.where(has_bwd, bwd, 0)))
    return jnp.moveaxis(d, 0, axis)


@jax.jit
def normals_from_height_masked_previous(z, mask, pixel_size):
    p = _masked_derivative_previous(z, mask, 1) / pixel_size
    q = -_masked_derivative_previous(z, mask, 0) / pixel_size
    n = jnp.stack([-p, -q, jnp.ones_like(p)], axis=-1)
    n = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
    return jnp.where(mask[..., None], n, jnp.zeros_like(n).at[..., 2].set(1))


def normals_from_height_numpy(z, pixel_size):
    dzdr, dzdc = np.gradient(z)
    n = np.stack([-dzdc / pixel_size, dzdr / pixel_size, np.ones_like(z)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


@jax.jit
def render_previous(normals, albedo, lights):
    return jnp.maximum(jnp.einsum("kc,hwc->khw", lights, normals), 0) * albedo[None]


def render_numpy(normals, albedo, lights):
    return np.maximum(np.einsum("kc,hwc->khw", lights, normals), 0) * albedo[None]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--size", type=int, nargs=2, default=(1024, 1280), metavar=("H", "W"))
    parser.add_argument("--out", type=Path, default=OUT / "evaluate_speed.json")
    args = parser.parse_args()
    h, w = args.size
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(h, w),
                                         jaxps.synthetic.scanner_lights(20.0))
    rng = np.random.default_rng(0)
    normals = np.asarray(scene.normals, np.float32)
    other = normals + rng.normal(scale=0.05, size=normals.shape).astype(np.float32)
    z = np.asarray(jaxps.integrate(normals, mask=scene.mask), np.float32)
    mask = np.asarray(scene.mask)
    albedo = np.asarray(scene.albedo, np.float32)
    lights = np.asarray(scene.lights, np.float32)
    nj, oj, zj, mj = (jax.device_put(a) for a in (normals, other, z, mask))
    aj, lj = jax.device_put(albedo), jax.device_put(lights)
    one = jnp.float32(1.0)

    rows = {  # name -> (work, callable, numpy reference for the check, tolerance)
        "angular_error numpy": ("angular_error", lambda: angular_error_numpy(normals, other)),
        "angular_error jaxps": ("angular_error", lambda: jaxps.angular_error(nj, oj)),
        "angular_error previous": ("angular_error", lambda: angular_error_previous(nj, oj)),
        "normals_from_height numpy": ("normals_from_height",
                                      lambda: normals_from_height_numpy(z, 1.0)),
        "normals_from_height jaxps": ("normals_from_height",
                                      lambda: jaxps.normals_from_height(zj)),
        "normals_from_height previous": ("normals_from_height",
                                         lambda: normals_from_height_previous(zj, one)),
        "normals_from_height masked jaxps": ("normals_from_height_masked",
                                             lambda: jaxps.normals_from_height(zj, mask=mj)),
        "normals_from_height masked previous": (
            "normals_from_height_masked",
            lambda: normals_from_height_masked_previous(zj, mj, one)),
        "render_lambertian numpy": ("render_lambertian",
                                    lambda: render_numpy(normals, albedo, lights)),
        "render_lambertian jaxps": ("render_lambertian",
                                    lambda: jaxps.render_lambertian(nj, aj, lj)),
        "render_lambertian previous": ("render_lambertian",
                                       lambda: render_previous(nj, aj, lj)),
    }
    tolerance = {"angular_error": 1e-3, "normals_from_height": 1e-5,
                 "normals_from_height_masked": 1e-5, "render_lambertian": 1e-5}
    reference = {}
    for name, (work, fn) in rows.items():
        out = np.asarray(fn())
        ref = reference.setdefault(work, out)  # the first row of a work is its baseline
        np.testing.assert_allclose(out, ref, rtol=0, atol=tolerance[work], err_msg=name)
    first, runs = interleaved({name: fn for name, (_, fn) in rows.items()}, args.rounds)
    res = {"image": [h, w], "rounds": args.rounds, "rows": {}, "machine": environment()}
    base = {}
    for name, (work, _) in rows.items():
        r = np.asarray(runs[name]) * 1e3
        base.setdefault(work, float(np.median(r)))
        res["rows"][name] = {"work": work, "first_call_s": first[name],
                             "ms_median": float(np.median(r)), "ms_min": float(r.min()),
                             "ratio_to_first_row": float(np.median(r)) / base[work]}
        print(f"{name:40s} median {np.median(r):8.2f} ms  min {r.min():8.2f} ms  "
              f"x{float(np.median(r)) / base[work]:.2f}", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
