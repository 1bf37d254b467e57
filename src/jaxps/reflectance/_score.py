"""The held-out relighting protocol: how well a fitted BRDF predicts photographs under lights it
was not trained on, raw and up to an unknown flash strength, against Lambert's law.

A relit image can be wrong in two ways: in shape (where it is bright, where dark) and in overall
brightness. The second is mostly the unknown strength of the held-out flash, which no model
fitted on other frames can know (Yale B's flashes vary by about ±10%). So every figure comes
twice: the raw RMSE, and the *gain-invariant* RMSE, where each held-out image is first scaled by
its own least-squares factor over the mask (the same for every model). Both are pooled over the
held-out lights within 30° and within 60° of the view axis, and split by the model's training
support (`extrapolation_mask`: inside, outside). Lambert's law rendered from the same normals
and albedo is scored alike, and every figure is also given as a ratio to Lambert's.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from ..lights._directions import frame_count_error
from ._brdf import BRDFModel, _check_images, _check_lights, extrapolation_mask, relight
from ._features import usable_normals

__all__ = ["RelightScore", "score_relighting"]

LIMITS_DEG = (30, 60)


class RelightScore(NamedTuple):
    """Result of `score_relighting` (RMSE in the units of `scale`, e.g. gray levels 0-255).

    `model`, `lambertian`: dicts of RMSE keyed `"{kind}_{limit}"` and
    `"{kind}_{limit}_{part}"`, with kind `raw` or `gain` (gain-invariant), limit 30 or 60
    (degrees between the held-out light and the view axis) and part `inside` or `outside` (the
    model's training support, `extrapolation_mask`; Lambert's figures use the same partition);
    NaN where no sample falls in the bin. `ratio`: the same keys, model / Lambert.
    `lights`: `{"30": n, "60": n}` held-out lights within each limit; `outside_fraction`:
    `{"30": f, "60": f}` fraction of scored samples outside the support. `gains`: `(K,)` the
    least-squares factor of each held-out image (NaN beyond 60°), model and Lambert.
    """

    model: dict
    lambertian: dict
    ratio: dict
    lights: dict
    outside_fraction: dict
    gains: dict


def rmse_gray(pred, obs, sel, scale=255.0):
    """RMSE of `pred - obs` over the bool selection `sel` (broadcast), times `scale`; NaN when
    `sel` is empty."""
    sel = np.broadcast_to(sel, np.shape(obs))
    d = (np.asarray(pred, np.float64) - np.asarray(obs, np.float64))[sel] * scale
    return float(np.sqrt(np.mean(d**2))) if d.size else float("nan")


def image_gains(pred, obs, valid):
    """`(K,)` least-squares factor $g_k = \\langle p_k, o_k \\rangle / \\lVert p_k \\rVert^2$ of
    each predicted image over its valid samples (`(K, H, W)` bool; 1 where the prediction is 0)."""
    p = np.where(valid, np.asarray(pred, np.float64), 0.0)
    o = np.where(valid, np.asarray(obs, np.float64), 0.0)
    pp = np.sum(p * p, axis=(1, 2))
    return np.where(pp > 0, np.sum(p * o, axis=(1, 2)) / np.where(pp > 0, pp, 1.0), 1.0)


def _figures(pred, obs, valid, near, outside, scale):
    """The RMSE dict of `RelightScore` and the `(K,)` gains, for one prediction."""
    g = image_gains(pred, obs, valid)
    out = {}
    for kind, p in (("raw", pred), ("gain", pred * g[:, None, None])):
        for limit, sel_k in (("30", near), ("60", np.ones_like(near))):
            sel = valid & sel_k[:, None, None]
            out[f"{kind}_{limit}"] = rmse_gray(p, obs, sel, scale)
            out[f"{kind}_{limit}_inside"] = rmse_gray(p, obs, sel & ~outside, scale)
            out[f"{kind}_{limit}_outside"] = rmse_gray(p, obs, sel & outside, scale)
    return out, g


def score_relighting(
    model: BRDFModel,
    images: Float[ArrayLike, "K H W"],
    normals: Float[ArrayLike, "H W 3"],
    albedo: Float[ArrayLike, "H W"],
    lights: Float[ArrayLike, "K 3"] | Float[ArrayLike, "K H W 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    scale: float = 255.0,
) -> RelightScore:
    """Score `model` on held-out photographs: raw and gain-invariant RMSE within 30° and 60°,
    inside and outside its training support, against Lambert's law from the same normals.

    **Arguments:**
    - `model`: from `fit_brdf`, fitted on other frames of the same capture.
    - `images`: `(K, H, W)` the held-out photographs (linear, ambient subtracted, in the
      training images' units); `lights`: `(K, 3)` their directions, or `(K, H, W, 3)` each
      pixel's own (near lamps, as `fit_brdf` takes them: the images then have the lamps'
      fall-off divided out). Lights more than 60° from the view axis (0, 0, 1) are not
      scored; a per-pixel light's angle is its mean direction's over the scored pixels.
    - `normals`, `albedo`: `(H, W, 3)`, `(H, W)`, the ones `model` was fitted with (e.g. L2
      photometric stereo on the training frames).
    - `mask`: `(H, W)` bool, the pixels to score (default all; must not be empty).
      Non-finite observations are left out, and so are the pixels whose normal is non-finite
      or of zero length or whose albedo is non-finite.
    - `scale`: multiply intensities by this, > 0 (255 gives gray levels for images in [0, 1]).

    **Returns:** a `RelightScore`. Lambert's law is `model` rendered with
    `method="lambertian"` (the same as `fit_brdf(..., method="lambertian")`).

    **Raises:** `ValueError` for mismatched shapes, integer images, `scale` not > 0, an empty
    mask, no held-out light within 60° or no usable sample.
    """
    obs = np.asarray(_check_images(np.asarray(images)), np.float64)
    k, h, w = obs.shape
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive number, got {scale!r}")
    unit = np.asarray(_check_lights(lights, np.float32, (h, w)), np.float64)
    if unit.shape[0] != k:
        raise frame_count_error(obs.shape, unit.shape[0])
    sel = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    if sel.shape != (h, w):
        raise ValueError(f"mask must have shape (H, W) = {(h, w)}, got {sel.shape}")
    if not sel.any():
        raise ValueError("mask is empty: no pixel to score")
    if np.shape(normals) != (h, w, 3):
        raise ValueError(f"normals must be (H, W, 3) = {(h, w, 3)}, got {np.shape(normals)}")
    if np.shape(albedo) != (h, w):
        raise ValueError(f"albedo must be (H, W) = {(h, w)}, got {np.shape(albedo)}")
    direction = unit if unit.ndim == 2 else unit[:, sel].mean(axis=1)
    direction = direction / np.linalg.norm(direction, axis=1, keepdims=True)
    zenith = np.degrees(np.arccos(np.clip(direction[:, 2], -1.0, 1.0)))
    keep = zenith <= LIMITS_DEG[1] + 1e-6
    if not keep.any():
        raise ValueError("lights: no held-out light within 60 degrees of the view axis")
    obs, lit, near = obs[keep], unit[keep], zenith[keep] <= LIMITS_DEG[0] + 1e-6
    pixels = sel & usable_normals(normals) & np.isfinite(np.asarray(albedo))
    valid = pixels[None] & np.isfinite(obs)
    if not valid.any():
        raise ValueError("no usable sample: every masked sample within 60 degrees is non-finite, "
                         "or its pixel's normal or albedo is")
    obs = np.where(valid, obs, 0.0)
    pred = np.asarray(relight(model, normals, albedo, lit), np.float64)
    base = dataclasses.replace(model, method="lambertian", params=None, gate=None)
    lam = np.asarray(relight(base, normals, albedo, lit), np.float64)
    outside = np.asarray(extrapolation_mask(model, normals, lit))
    figs, g_model = _figures(pred, obs, valid, near, outside, scale)
    lfigs, g_lam = _figures(lam, obs, valid, near, outside, scale)
    ratio = {key: figs[key] / lfigs[key] if lfigs[key] > 0 else float("nan") for key in figs}
    near_valid = outside[valid & near[:, None, None]]
    frac = {"30": float(near_valid.mean()) if near_valid.size else float("nan"),
            "60": float(outside[valid].mean())}
    gains = {}
    for name, g in (("model", g_model), ("lambertian", g_lam)):
        gains[name] = np.full(k, np.nan)
        gains[name][keep] = g
    return RelightScore(figs, lfigs, ratio, {"30": int(near.sum()), "60": int(keep.sum())},
                        frac, gains)
