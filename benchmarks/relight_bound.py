"""How far below Lambert can relighting from five frames go? Two probes on the shared Yale B faces.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/relight_bound.py [--register]

Same cases as bench_relight.py ("cross" training lights less flagged frames, L2 normals and
albedo from them, the face mask; every other clean light within 30 degrees held out), scored
with the gain-invariant RMSE of `jaxps.score_relighting` (one least-squares factor per held-out
image), as a ratio to Lambert's law:

- **span oracle**: each held-out image replaced by its least-squares fit as a combination of
  the training images, with coefficients fitted *on the held-out image itself*. Lambert's
  images lie in this span (three of its dimensions), so does any model linear in the
  training images, and the coefficients are the best possible, so it is a lower bound for
  such models (not for models nonlinear in the light, such as a specular lobe).
- **residual interpolation**: Lambert plus the training frames' Lambert residuals, each
  weighted by a Gaussian of the angle between its light and the held-out light (width
  `SIGMAS`, per pixel): does the misfit at a training light carry over to a light 5-25 degrees
  away?

Writes benchmarks/results/relight_bound.json (with `--register`, every frame moved onto the
(0,0) frame first, as in bench_relight.py: relight_bound_registered.json).
"""

from __future__ import annotations

import json
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from benchmarks.bench_brdf import cases, gain_rmse

OUT = pathlib.Path(__file__).resolve().parent / "results" / "relight_bound.json"
SUBJECTS = ("yaleB01", "yaleB02", "yaleB03", "yaleB04", "yaleB05")
SIGMAS = (5.0, 10.0, 20.0)


def subject_row(c):
    n, a = np.asarray(c.ps.normals, np.float64), np.asarray(c.ps.albedo, np.float64)
    unit = c.lights / np.linalg.norm(c.lights, axis=1, keepdims=True)
    tr, te, m = c.train, c.test60, c.mask

    def lambert(lights):
        return a[None] * np.clip(np.einsum("hwc,kc->khw", n, lights), 0, None)

    obs, base = c.images[te], lambert(unit[te])
    lam = gain_rmse(base, obs, m, c.near)
    row = {"train_frames": len(tr), "test_lights_30": int(c.near.sum()),
           "lambert_gain_30_gray": lam}
    train = c.images[tr][:, m].T  # (P, K)
    coef = np.linalg.lstsq(train, obs[:, m].T, rcond=None)[0]
    span = np.zeros_like(obs)
    span[:, m] = (train @ coef).T
    row["span_oracle_ratio"] = gain_rmse(span, obs, m, c.near) / lam
    resid = c.images[tr] - lambert(unit[tr])
    angle = np.degrees(np.arccos(np.clip(unit[te] @ unit[tr].T, -1, 1)))  # (T, K)
    for s in SIGMAS:
        pred = base + np.einsum("tk,khw->thw", np.exp(-0.5 * (angle / s) ** 2), resid)
        row[f"residual_interp_sigma{s:g}_ratio"] = gain_rmse(pred, obs, m, c.near) / lam
    return row


def main():
    import argparse

    from benchmarks import bench_brdf

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--register", action="store_true",
                        help="move every frame onto the (0,0) frame first")
    args = parser.parse_args()
    bench_brdf.REGISTER = args.register
    out = OUT.with_name("relight_bound_registered.json") if args.register else OUT
    rows = {}
    for c in cases(SUBJECTS, ["cross"]):
        rows[c.subject] = subject_row(c)
        print(c.subject, {k: round(v, 3) for k, v in rows[c.subject].items()}, flush=True)
    keys = [k for k in rows[SUBJECTS[0]] if k.endswith("_ratio")]
    mean = {k: float(np.mean([r[k] for r in rows.values()])) for k in keys}
    print("mean", {k: round(v, 3) for k, v in mean.items()})
    out.write_text(json.dumps({"subjects": rows, "mean": mean, "registered": args.register},
                              indent=1) + "\n")


if __name__ == "__main__":
    main()
