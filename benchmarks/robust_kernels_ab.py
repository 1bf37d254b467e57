"""Compare the robust solvers' results between two versions of jaxps (an A/B of kernels).

Each version solves the same 96x80 stacks (`bench_robust.py`'s corruption: cast shadows, a
Blinn-Phong lobe, 0.5% noise; six lights on a 40-degree cone) with one method and saves every
output; `--compare` then reports, over the pixels both call OK, how far the normals moved,
whether status and `n_used` agree and whether every output is equal to the bit. Stacks: grey;
colour (three scaled channels, one NaN, 5% of the samples masked out); per-pixel lights (1%
jitter) with a shadow threshold (not for `l1`, which takes shared lights only); for `irls`
also the Huber loss. `--block N` solves in blocks of N pixels (the stacks have 7680), for
versions that solve in blocks.

    PYTHONPATH=src python benchmarks/robust_kernels_ab.py --save new_irls.npz --method irls
    PYTHONPATH=/tmp/old/src python benchmarks/robust_kernels_ab.py --save old_irls.npz --method irls
    python benchmarks/robust_kernels_ab.py --compare new_irls.npz old_irls.npz
"""

from __future__ import annotations

import argparse

import numpy as np


def save(path: str, method: str, block: int | None = None) -> None:
    import jax

    import jaxps
    from jaxps.stability import render_corrupted, ring_lights

    if block:  # a version that solves in blocks: several of them, the last one padded
        from jaxps.ps import _robust

        _robust._BLOCK = block

    scene = render_corrupted(jaxps.synthetic.face_like(96, 80), ring_lights(6, 40.0),
                             specular=0.6, shininess=100.0, noise=0.005, key=jax.random.key(1))
    im, lights, mask = (np.asarray(a) for a in (scene.images, scene.lights, scene.mask))
    colour = np.stack([im, 0.8 * im, 1.2 * im], -1)
    colour[2, 10, 10, 1] = np.nan
    rng = np.random.default_rng(0)
    sample_mask = rng.random(im.shape) > 0.05
    per_pixel = (np.broadcast_to(lights[:, None, None, :], (*im.shape, 3))
                 * (1 + 0.01 * rng.standard_normal((*im.shape, 3)))).astype(np.float32)
    stacks = {"grey": (im, lights, {}), "colour": (colour, lights, {"sample_mask": sample_mask}),
              "per_pixel": (im, per_pixel,
                            {"shadow_threshold": 0.02})}
    if method == "irls":
        stacks["huber"] = (im, lights, {"loss": "huber"})
    if method == "l1":  # shared lights only
        del stacks["per_pixel"]
    out = {}
    for name, (x, lt, kw) in stacks.items():
        r = jaxps.photometric_stereo(x, lt, mask=mask, method=method, **kw)
        for field in ("normals", "albedo", "status", "n_used", "residual"):
            out[f"{name}/{field}"] = np.asarray(getattr(r, field))
    np.savez(path, **out)


def compare(a_path: str, b_path: str) -> dict:
    a, b = np.load(a_path), np.load(b_path)
    names = sorted({k.split("/")[0] for k in a.files})
    moved, ok_px = [], 0
    status_diff = n_used_diff = 0
    for name in names:
        ok = a[f"{name}/status"] == 0
        na, nb = a[f"{name}/normals"].astype(np.float64), b[f"{name}/normals"].astype(np.float64)
        # atan2 of |a x b| and a.b: exact near 0, where arccos of a float32 dot is not
        angle = np.arctan2(np.linalg.norm(np.cross(na, nb), axis=-1), np.sum(na * nb, -1))
        moved.append(np.degrees(angle)[ok])
        ok_px += int(ok.sum())
        status_diff += int((a[f"{name}/status"] != b[f"{name}/status"]).sum())
        n_used_diff += int((a[f"{name}/n_used"] != b[f"{name}/n_used"]).sum())
    d = np.concatenate(moved)
    identical = all(np.array_equal(a[f], b[f], equal_nan=True) for f in a.files)
    return {"stacks": names, "every_output_identical": identical, "ok_pixels": ok_px, "status_differs": status_diff,
            "n_used_differs": n_used_diff, "moved_over_0.1_deg": int((d > 0.1).sum()),
            "moved_max_deg": float(d.max()),
            "moved_p99_deg_worst_stack": float(max(np.percentile(m, 99) for m in moved))}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--save")
    ap.add_argument("--method", default="irls")
    ap.add_argument("--compare", nargs=2)
    ap.add_argument("--block", type=int, help="pixels per block of the solve, in versions "
                    "that solve in blocks (patches `_robust._BLOCK`)")
    args = ap.parse_args()
    if args.save:
        save(args.save, args.method, args.block)
    if args.compare:
        print(compare(*args.compare))


if __name__ == "__main__":
    main()
