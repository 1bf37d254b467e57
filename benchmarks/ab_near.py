"""Near lamps' light field (`near_light_field`) and `near_photometric_stereo` in this tree
against the same at an earlier revision, interleaved.

Loads `src/jaxps/lights/_near.py` as it was at `--before` next to the current one, in one
process, and times `near_light_field` of both (with the isotropic lamps of a scanner, mu = 0,
and with an LED lobe, mu = 1.5) and `near_photometric_stereo` with each field (the current
solver and integrator in both), in `--rounds` interleaved rounds after a first call of each;
then `near_photometric_stereo` with today's field, integrating each step with `"lsq"` (the
default since the twenty-seventh session) and with `"fc"` (before), timed the same way, with
each height's RMS error (mm, mean-free over the face) against the rendered depth.
The capture is rendered: the synthetic face (`face_like`, its mean depth at z = 0, 0.25 mm
pixels) under five lamps 1000 mm away in the directions of `scanner_lights(20)`, Lambertian,
albedo 0.6. Also recorded: the largest differences of the two fields and of the two
solutions (normals in degrees, heights in mm).

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/ab_near.py --before REV \
        [--size H W] [--rounds 7] [--name NAME]
    -> benchmarks/results/NAME.json (default ab_near.json)
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import tempfile

import jax.numpy as jnp
import numpy as np

import jaxps
from jaxps.lights import _near
from jaxps.ps import _near as near_ps

try:
    from benchmarks._common import environment, interleaved, module_at, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import environment, interleaved, module_at, write_json

PIXEL_MM = 0.25


def capture(h, w):
    """`(images (K, H, W) float32, mask, lamp positions (K, 3) mm, surface points)`."""
    face = jaxps.synthetic.face_like(h, w)
    inside = np.asarray(face.mask)
    depth = np.asarray(face.height, np.float64) * PIXEL_MM
    points = jaxps.surface_points(jnp.asarray(depth - depth[inside].mean(), jnp.float32),
                                  pixel_size=PIXEL_MM)
    positions = 1000.0 * np.asarray(jaxps.synthetic.scanner_lights(20.0), np.float64)
    directions, falloff = (np.asarray(a, np.float64)
                           for a in jaxps.near_light_field(positions, points))
    shade = np.maximum(np.einsum("khwc,hwc->khw", directions, np.asarray(face.normals)), 0)
    return (shade * falloff * 0.6 * inside).astype(np.float32), inside, positions, points


def solve_with(module, images, mask, positions):
    """`near_photometric_stereo` with `module`'s `near_light_field`."""
    near_ps.near_light_field = module.near_light_field
    try:
        return jaxps.near_photometric_stereo(images, positions, mask=mask, pixel_size=PIXEL_MM)
    finally:
        near_ps.near_light_field = _near.near_light_field


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", required=True, help="git revision to compare with")
    ap.add_argument("--size", nargs=2, type=int, default=[1024, 1280], metavar=("H", "W"))
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--name", default="ab_near")
    args = ap.parse_args(argv)
    images, mask, positions, points = capture(*args.size)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        modules = {"now": _near, "before": module_at(args.before, "src/jaxps/lights/_near.py",
                                                     pathlib.Path(folder))}
        for mu in (0.0, 1.5):
            calls = {side: (lambda m=m, mu=mu: m.near_light_field(positions, points, mu=mu))
                     for side, m in modules.items()}
            first, seconds = interleaved(calls, args.rounds)
            (l_now, a_now), (l_then, a_then) = calls["now"](), calls["before"]()
            rows.append({"work": f"near_light_field, mu = {mu}", "unit": "ms",
                         **{f"{side}_ms": 1e3 * statistics.median(s)
                            for side, s in seconds.items()},
                         **{f"{side}_first_s": t for side, t in first.items()},
                         "max_light_difference": float(jnp.max(jnp.abs(l_now - l_then))),
                         "max_falloff_relative_difference": float(
                             jnp.max(jnp.abs(a_now - a_then) / a_then))})
        calls = {side: (lambda m=m: solve_with(m, images, mask, positions).height)
                 for side, m in modules.items()}
        first, seconds = interleaved(calls, args.rounds)
        now, then = (solve_with(m, images, mask, positions) for m in modules.values())
        ok = mask & (np.asarray(now.ps.status) == 0) & (np.asarray(then.ps.status) == 0)
        cos = np.clip(np.sum(np.asarray(now.ps.normals, np.float64)
                             * np.asarray(then.ps.normals, np.float64), -1), -1, 1)
        rows.append({"work": "near_photometric_stereo", "unit": "ms",
                     **{f"{side}_ms": 1e3 * statistics.median(s) for side, s in seconds.items()},
                     **{f"{side}_first_s": t for side, t in first.items()},
                     "steps": [now.steps, then.steps],
                     "max_normal_difference_deg": float(np.degrees(np.arccos(cos[ok])).max()),
                     "max_height_difference_mm": float(np.abs(
                         np.asarray(now.height) - np.asarray(then.height))[mask].max())})
        # the integrator of each step (twenty-seventh session: "lsq", was "fc"), today's field
        depth = np.asarray(points)[..., 2]
        calls = {m: (lambda m=m: jaxps.near_photometric_stereo(
            images, positions, mask=mask, pixel_size=PIXEL_MM, integration=m).height)
            for m in ("lsq", "fc")}
        first, seconds = interleaved(calls, args.rounds)
        row = {"work": "near_photometric_stereo, integration lsq (now) / fc (before)",
               "unit": "ms", "now_ms": 1e3 * statistics.median(seconds["lsq"]),
               "before_ms": 1e3 * statistics.median(seconds["fc"]),
               "now_first_s": first["lsq"], "before_first_s": first["fc"]}
        solved = {}
        for m, side in (("lsq", "now"), ("fc", "before")):
            solved[m] = jaxps.near_photometric_stereo(images, positions, mask=mask,
                                                      pixel_size=PIXEL_MM, integration=m)
            dz = (np.asarray(solved[m].height, np.float64) - depth)[mask]
            row[f"{side}_height_rms_error_mm"] = float(np.sqrt(np.mean((dz - dz.mean()) ** 2)))
        ok = mask & (np.asarray(solved["lsq"].ps.status) == 0) & (
            np.asarray(solved["fc"].ps.status) == 0)
        cos = np.clip(np.sum(np.asarray(solved["lsq"].ps.normals, np.float64)
                             * np.asarray(solved["fc"].ps.normals, np.float64), -1), -1, 1)
        row["max_normal_difference_deg"] = float(np.degrees(np.arccos(cos[ok])).max())
        row["steps"] = [solved["lsq"].steps, solved["fc"].steps]
        rows.append(row)
    for r in rows:
        extra = {k: v for k, v in r.items() if k.startswith(("max_", "steps")) or "rms" in k}
        print(f"{r['work']:28s} now {r['now_ms']:8.1f} ms  before {r['before_ms']:8.1f} ms  "
              f"{r['now_ms'] / r['before_ms']:.2f}x  {extra}")
    path = write_json(args.name, {
        "command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/ab_near.py "
                   + " ".join(sys.argv[1:] if argv is None else argv),
        "environment": environment(), "before": args.before, "rounds": args.rounds,
        "size": args.size, "pixel_mm": PIXEL_MM, "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
