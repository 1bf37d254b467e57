"""`fit_brdf(method="auto")`: no more model than the scene needs, judged per face region by
leave-one-light-out error on the training frames.

With five flash frames, a richer reflectance model than Lambert's law can only be trusted where
it predicts a training light it was not fitted on. For each training frame $j$ (K >= 5), normals
and albedo are re-estimated from the other K-1 frames, every candidate method is fitted on them,
and frame $j$ is predicted by the candidate and by Lambert's law. The mask's bounding box is cut
into `regions` x `regions` cells; in each cell $r$ a candidate is kept when its per-fold mean
squared error beats Lambert's by more than `margin` standard errors of the per-fold differences,
$\\overline{d_r} + \\text{margin} \\cdot \\mathrm{SE}(d_r) < 0$ with
$d_{r,j} = \\mathrm{MSE}^{cand}_{r,j} - \\mathrm{MSE}^{Lambert}_{r,j}$ (at margin 1 the
one-standard-error rule: the simplest model within one SE of the best; Hastie, Tibshirani &
Friedman, *The Elements of Statistical Learning*, 2nd ed., §7.10). The candidate whose gated
prediction (its own where kept, Lambert's elsewhere) has the lowest pooled leave-one-light-out
error is fitted on all K frames and returned with a 0/1 `gate` per pixel; `relight` renders
$L + \\text{gate}\\,(M - L)$. When no cell keeps any candidate the result is Lambert's law.

A second, necessary test needs no held-out frame: the Bayesian information criterion of each
model fitted on all K frames (Schwarz, "Estimating the dimension of a model", Annals of
Statistics 6(2), 1978), $\\mathrm{BIC} = n \\ln(\\mathrm{RSS}/n) + p \\ln n$ over the $n$ usable
masked training samples, with $p$ the parameters beyond the normal and albedo per pixel that
Lambert's law has too (`BRDFFit.n_params`). A candidate whose BIC is not below Lambert's is not
chosen, whatever its leave-one-light-out figures. The BIC trusts independent Gaussian noise,
which neighbouring pixels of a face do not have, so it is the weaker test: it rejects a model
whose fit gain does not pay for its parameters (e.g. a Delaunay interpolant, one parameter
per sample), and leaves the rest to the held-out frames.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from ..lights._directions import MAX_LIGHT_CONDITION
from ..ps import photometric_stereo
from ._features import usable_normals

__all__ = ["bic", "choose_regions", "lolo_folds", "region_labels"]


def region_labels(mask, regions):
    """`(H, W)` int: the cell of a `regions` x `regions` grid over the mask's bounding box of
    each masked pixel (row-major), -1 outside the mask."""
    mask = np.asarray(mask, bool)
    rows, cols = np.nonzero(mask)
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    rr = np.clip(((np.arange(mask.shape[0]) - r0) * regions) // max(r1 - r0, 1), 0, regions - 1)
    cc = np.clip(((np.arange(mask.shape[1]) - c0) * regions) // max(c1 - c0, 1), 0, regions - 1)
    return np.where(mask, rr[:, None] * regions + cc[None, :], -1)


def lolo_folds(fit, relight, images, lights, mask, methods, *, ps_method, saturation, options):
    """Leave-one-light-out predictions: a list over the folds $j$ whose K-1 lights span 3-D of
    `(j, obs (H, W), valid (H, W) bool, lambert (H, W), {method: (H, W)})`, all float64, the
    models fitted by `fit(images, normals, albedo, lights, mask=, method=, **options)` on the
    other frames' normals and albedo (`photometric_stereo(method=ps_method)`). `lights`:
    `(K, 3)` distant or `(K, H, W, 3)` per pixel (a fold's span is judged on each light's mean
    direction over the image)."""
    k = images.shape[0]
    directions = np.asarray(lights, np.float64)
    if directions.ndim == 4:
        directions = directions.reshape(k, -1, 3).mean(axis=1)
    folds = []
    for j in range(k):
        keep = np.array([i for i in range(k) if i != j])
        if np.linalg.cond(directions[keep]) > MAX_LIGHT_CONDITION:
            continue
        ps = photometric_stereo(images[keep], lights[keep], mask=mask, method=ps_method)
        obs = np.asarray(images[j], np.float64)
        valid = (mask & np.isfinite(obs) & (obs < saturation) & (np.asarray(ps.albedo) > 0))
        preds, lam = {}, None
        for name in methods:
            model = fit(images[keep], ps.normals, ps.albedo, lights[keep], mask=mask,
                        method=name, **options)
            preds[name] = np.asarray(relight(model, ps.normals, ps.albedo, lights[j:j + 1]),
                                     np.float64)[0]
            if lam is None:
                base = dataclasses.replace(model, method="lambertian", params=None)
                lam = np.asarray(relight(base, ps.normals, ps.albedo, lights[j:j + 1]),
                                 np.float64)[0]
        folds.append((j, obs, valid, lam, preds))
    return folds


def bic(pred, obs, valid, n_params):
    """$n \\ln(\\mathrm{RSS}/n) + p \\ln n$ over the `valid` samples (float64)."""
    d = (np.asarray(pred, np.float64) - np.asarray(obs, np.float64))[np.asarray(valid)]
    n = d.size
    return float(n * math.log(max(float(d @ d), np.finfo(np.float64).tiny) / n)
                 + n_params * math.log(n))


def choose_regions(folds, mask, *, regions, margin, bics=None):
    """The choice of `fit_brdf(method="auto")` from `lolo_folds`' output: `(name, gate (H, W)
    float64 0/1 or None, report dict)`; name is "lambertian" when no candidate is kept.
    `bics`: `{name: BIC}` of Lambert's law (`"lambertian"`) and the candidates fitted on every
    frame; a candidate whose BIC is not below Lambert's is not chosen (None: no such test)."""
    base = {"regions": regions, "margin": margin, "folds": [f[0] for f in folds]}
    if bics is not None:
        base["bic"] = dict(bics)
    if len(folds) < 2:
        return "lambertian", None, {
            "choice": "lambertian", **base,
            "reason": f"{len(folds)} leave-one-light-out folds: at least 2 are needed (K >= 5 "
                      "training frames, the other K-1 lights spanning 3-D), so Lambert's law"}
    labels = region_labels(mask, regions)
    n_cells = regions * regions
    names = list(folds[0][4])

    def cell_sse(pred, obs, valid):
        sel = valid & (labels >= 0)
        sse = np.bincount(labels[sel], (pred - obs)[sel] ** 2, minlength=n_cells)
        return sse, np.bincount(labels[sel], minlength=n_cells)

    lam_sse, count = map(np.array, zip(*[cell_sse(lam, obs, valid)
                                         for _, obs, valid, lam, _ in folds]))
    n = np.maximum(count, 1)
    total = float(count.sum())
    report = {**base, "lolo_rmse": {"lambertian": math.sqrt(lam_sse.sum() / total)},
              "kept_cells": {}, "gated_lolo_rmse": {}, "bic_rejected": []}
    best, best_sse, best_keep = "lambertian", float(lam_sse.sum()), None
    for name in names:
        sse = np.array([cell_sse(p[name], obs, valid)[0] for _, obs, valid, _, p in folds])
        d = sse / n - lam_sse / n  # (folds, cells) per-fold MSE difference
        se = np.std(d, axis=0, ddof=1) / math.sqrt(len(folds))
        keep = (np.mean(d, axis=0) + margin * se < 0) & (count.min(axis=0) > 0)
        gated = float(np.where(keep[None], sse, lam_sse).sum())
        report["lolo_rmse"][name] = math.sqrt(sse.sum() / total)
        report["gated_lolo_rmse"][name] = math.sqrt(gated / total)
        report["kept_cells"][name] = np.flatnonzero(keep).tolist()
        if bics is not None and not bics[name] < bics["lambertian"]:
            report["bic_rejected"].append(name)
            continue
        if keep.any() and gated < best_sse:
            best, best_sse, best_keep = name, gated, keep
    report["choice"] = best
    if best_keep is None:
        report["reason"] = (f"no candidate beat Lambert's law by {margin:g} standard errors "
                            f"in any of the {n_cells} regions (leave-one-light-out)")
        if report["bic_rejected"]:
            report["reason"] += (" with a BIC below Lambert's (not below: "
                                 f"{', '.join(report['bic_rejected'])})")
        return "lambertian", None, report
    gate = np.where(labels >= 0, best_keep[np.maximum(labels, 0)], False).astype(np.float64)
    report["gate_fraction"] = float(gate[np.asarray(mask, bool)].mean())
    report["reason"] = (
        f"{best} beat Lambert's law by {margin:g} standard errors in {int(best_keep.sum())} of "
        f"{n_cells} regions ({report['gate_fraction']:.0%} of the mask); leave-one-light-out "
        f"RMSE {report['gated_lolo_rmse'][best]:.4g} against Lambert's "
        f"{report['lolo_rmse']['lambertian']:.4g}")
    return best, gate, report


def fit_auto(fit, relight, images, normals, albedo, lights, *, mask, candidates, regions, margin,
             ps_method, saturation, options):
    """`fit_brdf(method="auto")` (see the module docstring); `fit`, `relight` are `fit_brdf` and
    `relight` (passed in to avoid an import cycle)."""
    folds = []
    if images.shape[0] >= 5:  # with 3 frames a fold's Lambert fit is exact: nothing to learn
        folds = lolo_folds(fit, relight, images, lights, mask, candidates, ps_method=ps_method,
                           saturation=saturation, options=options)
    models, bics = {}, None
    if len(folds) >= 2:  # the information criterion of every model fitted on all K frames
        obs = np.asarray(images, np.float64)
        valid = (np.asarray(mask)[None] & np.isfinite(obs) & (obs < saturation)
                 & ((np.asarray(albedo) > 0) & usable_normals(normals))[None])
        bics = {}
        for name in ("lambertian", *candidates):
            models[name] = fit(images, normals, albedo, lights, mask=mask, method=name,
                               **options)
            pred = np.asarray(relight(models[name], normals, albedo, lights), np.float64)
            gains = models[name].fit.frame_gains  # the training fit renders each frame's gain
            if gains is not None:
                pred = pred * np.asarray(gains)[:, None, None]
            bics[name] = bic(pred, obs, valid, models[name].fit.n_params)
    choice, gate, report = choose_regions(folds, mask, regions=regions, margin=margin, bics=bics)
    model = models.get(choice)
    if model is None:
        model = fit(images, normals, albedo, lights, mask=mask, method=choice, **options)
    if gate is not None:
        model = dataclasses.replace(model, gate=jnp.asarray(gate, images.dtype))
    fit_report = model.fit._replace(choice=report,
                                    message=f"auto: {report['reason']}; {model.fit.message}")
    return dataclasses.replace(model, fit=fit_report)
