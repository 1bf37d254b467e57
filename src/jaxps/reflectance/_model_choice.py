"""Model choice, "no more than a scene needs": Lambertian or Oren–Nayar, judged on held-out light.

Both models are fitted on the training lights (`l2` photometric stereo; Oren–Nayar-aware
photometric stereo with one global roughness, and optionally one roughness per region), the
held-out lights are re-rendered from the fitted normals, albedo (and $\\sigma$), and the RMSE
against the real held-out images decides, per scene and per region. The Bayesian information
criterion of the training fit, $n \\log(\\mathrm{RSS}/n) + k \\log n$, is reported alongside
(it needs no held-out light but trusts the noise model).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Int

from ..core._status import Status
from ..lights._directions import validate_lights
from ..ps import photometric_stereo
from ..shading import fit_roughness, render_lambertian, render_oren_nayar

__all__ = ["ModelChoice", "compare_models"]


class ModelChoice(NamedTuple):
    """Result of `compare_models` (RMSE in the units of `scale`, e.g. gray levels 0-255).

    - `rmse`: `{"lambertian": float, "oren_nayar": float}` on the held-out lights, per scene
      (plus `"oren_nayar_region"` when `labels` were given).
    - `bic`: the same keys, training-fit BIC.
    - `sigma`: the global $\\sigma$ (radians); `sigma_status`: its `Status` code.
    - `choice`: `"lambertian"` or `"oren_nayar"` for the scene (Oren–Nayar only when it
      lowers the held-out RMSE by more than `min_gain` with $\\sigma > 0$).
    - `region_rmse`: `(R, 2)` held-out RMSE per region (Lambertian, Oren–Nayar with the
      region's own $\\sigma$), `region_sigma` `(R,)`, `region_choice` list of names; None
      without `labels`.
    - `pixels`: pixels evaluated; `test_samples`: held-out samples evaluated.
    """

    rmse: dict
    bic: dict
    sigma: float
    sigma_status: int
    choice: str
    region_rmse: np.ndarray | None
    region_sigma: np.ndarray | None
    region_choice: list | None
    pixels: int
    test_samples: int


def _bic(res2_sum, n, k):
    return float(n * np.log(max(res2_sum, 1e-300) / n) + k * np.log(n))


def compare_models(
    images: Float[ArrayLike, "K H W"],
    lights: Float[ArrayLike, "K 3"],
    *,
    train: Bool[ArrayLike, " K"],
    mask: Bool[ArrayLike, "H W"] | None = None,
    labels: Int[ArrayLike, "H W"] | None = None,
    test_sample_mask: Bool[ArrayLike, "K H W"] | None = None,
    form: str = "qualitative",
    scale: float = 255.0,
    max_steps: int = 50,
    min_gain: float = 0.01,
) -> ModelChoice:
    """Fit Lambertian and Oren–Nayar photometric stereo on `train` lights; test on the rest.

    **Arguments:**
    - `images`: `(K, H, W)` grey, linear, ambient subtracted; `lights`: `(K, 3)`.
    - `train`: `(K,)` bool, the lights to fit on (at least 5 for the Oren–Nayar fit); every
      other light is held out.
    - `mask`: `(H, W)` bool pixels to use; `labels`: optional `(H, W)` int region map (a
      $\\sigma$ per region, negative = ignored).
    - `test_sample_mask`: `(K, H, W)` bool held-out samples to score (e.g. no cast shadow).
    - `form`: Oren–Nayar form; `scale`: multiply intensities by this for the RMSE (255 gives
      gray levels); `max_steps`: step limit of the Oren–Nayar solves.
    - `min_gain`: Oren–Nayar is chosen only if it lowers the held-out RMSE by more than this
      fraction (default 1%) with $\\sigma > 0$; otherwise the simpler Lambertian model is kept.

    **Returns:** a `ModelChoice`.

    **Raises:** `ValueError` for mismatched shapes, too few training or held-out lights, an
    empty mask, or no pixel where both photometric-stereo fits succeed.
    """
    images = jnp.asarray(images)
    if images.ndim != 3:
        raise ValueError(f"images must be (K, H, W), got {images.shape}")
    k, h, w = images.shape
    train = np.asarray(train, bool)
    if train.shape != (k,):
        raise ValueError(f"train must be a (K,) = ({k},) bool array, got {train.shape}")
    if train.sum() < 5 or (~train).sum() < 1:
        raise ValueError(f"train needs >= 5 lights and at least one held out, got "
                         f"{int(train.sum())} of {k}")
    if np.shape(lights) != (k, 3):
        raise ValueError(f"lights must be (K, 3) = ({k}, 3), got {np.shape(lights)}")
    lights = validate_lights(lights)  # unit float32, as the renderers take them
    mask = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    if mask.shape != (h, w):
        raise ValueError(f"mask must have shape (H, W) = {(h, w)}, got {mask.shape}")
    if not mask.any():
        raise ValueError("mask is empty: no pixel to fit and score")
    tr, te = np.flatnonzero(train), np.flatnonzero(~train)
    img_tr, img_te = images[tr], images[te]

    lam = photometric_stereo(img_tr, lights[tr], mask=mask)
    on = photometric_stereo(img_tr, lights[tr], mask=mask, method="oren_nayar", sigma="global",
                            form=form, max_steps=max_steps)
    good = mask & (np.asarray(lam.status) == Status.OK) & (np.asarray(on.status) == Status.OK)
    if not good.any():
        raise ValueError("no usable pixel: Lambertian or Oren-Nayar photometric stereo failed "
                         "at every masked pixel")
    sigma = float(np.max(np.asarray(on.info["sigma"])[good]))
    sigma_status = int(np.max(np.asarray(on.info["sigma_status"])[good]))

    pred = {
        "lambertian": render_lambertian(lam.normals, lam.albedo, lights[te]),
        "oren_nayar": render_oren_nayar(on.normals, on.albedo, lights[te], sigma, form=form),
    }
    fit = {
        "lambertian": render_lambertian(lam.normals, lam.albedo, lights[tr]),
        "oren_nayar": render_oren_nayar(on.normals, on.albedo, lights[tr], sigma, form=form),
    }
    n_params = {"lambertian": 3 * int(good.sum()), "oren_nayar": 3 * int(good.sum()) + 1}
    region_sigma = region_rmse = region_choice = None
    if labels is not None:
        labels = np.asarray(labels)
        rf = fit_roughness(img_tr, on.normals, on.albedo, lights[tr], mask=good, per="region",
                           labels=labels, form=form)
        region_sigma = np.asarray(rf.sigma)
        sig_map = np.where(labels >= 0, region_sigma[np.clip(labels, 0, None)], sigma)
        pred["oren_nayar_region"] = render_oren_nayar(on.normals, rf.albedo, lights[te],
                                                      sig_map.astype(np.float32), form=form)
        fit["oren_nayar_region"] = render_oren_nayar(on.normals, rf.albedo, lights[tr],
                                                     sig_map.astype(np.float32), form=form)
        n_params["oren_nayar_region"] = 3 * int(good.sum()) + len(region_sigma)

    sel_te = np.broadcast_to(good, (len(te), h, w))
    if test_sample_mask is not None:
        sel_te = sel_te & np.asarray(test_sample_mask, bool)[te]
    sel_tr = np.broadcast_to(good, (len(tr), h, w))
    real_te, real_tr = np.asarray(img_te, np.float64), np.asarray(img_tr, np.float64)
    rmse, bic = {}, {}
    for name in pred:
        d = (np.asarray(pred[name], np.float64) - real_te) * scale
        rmse[name] = float(np.sqrt(np.mean(d[sel_te] ** 2)))
        dr = (np.asarray(fit[name], np.float64) - real_tr) * scale
        bic[name] = _bic(float(np.sum(dr[sel_tr] ** 2)), int(sel_tr.sum()), n_params[name])
    def pick(lam_err, on_err, sig):
        return "oren_nayar" if (on_err < (1 - min_gain) * lam_err and sig > 0) else "lambertian"

    choice = pick(rmse["lambertian"], rmse["oren_nayar"], sigma)
    if labels is not None:
        n_reg = len(region_sigma)
        region_rmse = np.full((n_reg, 2), np.nan)
        dl = (np.asarray(pred["lambertian"], np.float64) - real_te) * scale
        do = (np.asarray(pred["oren_nayar_region"], np.float64) - real_te) * scale
        for r in range(n_reg):
            sel = sel_te & (labels == r)[None]
            if sel.any():
                region_rmse[r] = [np.sqrt(np.mean(dl[sel] ** 2)), np.sqrt(np.mean(do[sel] ** 2))]
        region_choice = [pick(a, b, s) for (a, b), s in zip(region_rmse, region_sigma)]
    return ModelChoice(rmse, bic, sigma, sigma_status, choice, region_rmse, region_sigma,
                       region_choice, int(good.sum()), int(sel_te.sum()))
