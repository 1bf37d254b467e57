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
- **cross-subject transfer** (leave one subject out): is the span oracle's departure from
  Lambert the same on every face? For a held-out light, each *other* subject's oracle
  coefficients over the same training lights, minus Lambert's coefficients $L^{+T} l$ (which
  depend on the lights only), are averaged and added to this subject's Lambert coefficients:
  - `transfer_same_light`: from the other subjects' photographs under this very light (a
    lookup, possible only at lights the other faces were photographed under);
  - `transfer_row_space` / `transfer_null_space`: only the part of that correction in the span
    of the training lights' columns (the same as a corrected light vector) / only the rest;
  - `transfer_other_lights_sigma*`: from the other subjects' *other* lights only, each
    weighted by a Gaussian of its angle to this light: does the correction carry over to a
    light the other faces were not photographed under?
  `effective_light_change_deg`: the median angle between the light vector that the oracle
  coefficients amount to ($L^T c$) and the nominal one, over this subject's held-out lights.

Writes benchmarks/results/relight_bound.json (with `--register`, every frame moved onto the
(0,0) frame first, as in bench_relight.py: relight_bound_registered.json).
"""

from __future__ import annotations

import json
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from benchmarks._common import yale_subjects
from benchmarks.bench_brdf import cases, gain_rmse

OUT = pathlib.Path(__file__).resolve().parent / "results" / "relight_bound.json"
SUBJECTS = yale_subjects()  # every yaleB* folder found (_common)
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


def oracle_coefficients(c, train_angles, test_angle):
    """Subject `c`'s span-oracle coefficients for its photograph under `test_angle`, over its
    frames at `train_angles`, or None when one of those frames is missing or flagged."""
    index = {tuple(a): i for i, a in enumerate(c.angles) if c.clean[i]}
    if test_angle not in index or any(a not in index for a in train_angles):
        return None
    train = c.images[[index[a] for a in train_angles]][:, c.mask].T
    return np.linalg.lstsq(train, c.images[index[test_angle]][c.mask], rcond=None)[0]


def transfer_row(c, others):
    """The cross-subject transfer probes for subject `c`, with donors `others`."""
    unit = c.lights / np.linalg.norm(c.lights, axis=1, keepdims=True)
    tr, te, m = c.train, c.test60, c.mask
    train_angles = [tuple(c.angles[i]) for i in tr]
    lt = unit[tr]
    pinv = np.linalg.pinv(lt)  # (3, K): Lambert's coefficients for light l are pinv.T @ l
    project = lt @ pinv  # onto the span of the light columns
    train = c.images[tr][:, m].T
    obs = c.images[te]

    def score(coefs):  # coefs (K, T)
        pred = np.zeros_like(obs)
        pred[:, m] = (train @ coefs).T
        return gain_rmse(pred, obs, m, c.near)

    lam_coef = (unit[te] @ pinv).T
    lam = score(lam_coef)
    # Each donor's corrections at every light it has (clean), over this subject's training set.
    donor = []  # (unit light, correction)
    for o in others:
        ounit = o.lights / np.linalg.norm(o.lights, axis=1, keepdims=True)
        for j, a in enumerate(o.angles):
            if tuple(a) in train_angles or not o.clean[j] or ounit[j, 2] < np.cos(np.radians(60)):
                continue
            coef = oracle_coefficients(o, train_angles, tuple(a))
            if coef is not None:
                donor.append((tuple(a), ounit[j], coef - pinv.T @ ounit[j]))
    row = {}
    same = np.stack([np.mean([d for a, _, d in donor if a == tuple(c.angles[i])] or
                             [np.zeros(len(tr))], axis=0) for i in te], 1)
    for name, corr in (("transfer_same_light", same), ("transfer_row_space", project @ same),
                       ("transfer_null_space", same - project @ same)):
        row[f"{name}_ratio"] = score(lam_coef + corr) / lam
    for s in SIGMAS[:2]:
        corr = []
        for i in te:
            w = np.array([0.0 if a == tuple(c.angles[i]) else np.exp(-0.5 * (np.degrees(
                np.arccos(np.clip(u @ unit[i], -1, 1))) / s) ** 2) for a, u, _ in donor])
            corr.append(w @ np.stack([d for *_, d in donor]) / max(w.sum(), 1e-12))
        row[f"transfer_other_lights_sigma{s:g}_ratio"] = score(
            lam_coef + np.stack(corr, 1)) / lam
    own = [oracle_coefficients(c, train_angles, tuple(c.angles[i])) for i in te]
    change = [np.degrees(np.arccos(np.clip(
        (lt.T @ k) @ unit[i] / np.linalg.norm(lt.T @ k), -1, 1))) for k, i in zip(own, te)]
    row["effective_light_change_deg"] = float(np.median(change))
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
    rows, loaded = {}, []
    for c in cases(SUBJECTS, ["cross"]):
        rows[c.subject] = subject_row(c)
        loaded.append(c)
    for c in loaded:
        rows[c.subject].update(transfer_row(c, [o for o in loaded if o is not c]))
        print(c.subject, {k: round(v, 3) for k, v in rows[c.subject].items()}, flush=True)
    keys = [k for k in rows[SUBJECTS[0]] if k.endswith("_ratio")]
    mean = {k: float(np.mean([r[k] for r in rows.values()])) for k in keys}
    print("mean", {k: round(v, 3) for k, v in mean.items()})
    out.write_text(json.dumps({"subjects": rows, "mean": mean, "registered": args.register},
                              indent=1) + "\n")


if __name__ == "__main__":
    main()
