"""How far a surface departs from Lambert's law: binned $I/\\rho$ against the light angle.

Hansen, Atkinson, Smith and Smith, "3D face reconstructions from photometric stereo using near
infrared and visible light", CVIU 114(8), 2010, Sec. 4 / Fig. 7 / Table 1: for every sample of
every pixel, $\\theta = \\arccos(n \\cdot l)$ and $I / \\rho$ are computed from photometric-stereo
normals and albedo, averaged in 1-degree bins of $\\theta$, and compared with $\\cos\\theta$
(RMS 0.04 NIR / 0.06 visible for $\\theta \\le 60°$, 0.11 / 0.16 overall). This is an eager
analysis (numpy); `plot_lambertian_check` draws the figure.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from ._oren_nayar import _check_form, _check_stack, _coefficients, _geometry, _shading

__all__ = ["LambertianCheck", "lambertian_check"]


class LambertianCheck(NamedTuple):
    """Result of `lambertian_check`. Per-bin arrays are `(B,)` over bins of `bin_deg` in [0, 90).

    - `theta_deg`: bin centres (degrees); `mean`, `sd`, `count`: $I/\\rho$ per bin (empty bins
      have count 0 and mean/sd NaN).
    - `rms_60`, `rms_all`: RMS over the non-empty bins of (bin mean $- \\cos\\theta$), for bin
      centres $\\le 60°$ and for all bins (the paper's Table 1 figure).
    - `sd_60`, `sd_all`: mean per-bin standard deviation over the same bins (the width of the
      band in the paper's Fig. 7).
    - `rms_samples_60`, `rms_samples_all`: RMS of $I/\\rho - \\cos\\theta$ over the samples
      themselves.
    - `oren_nayar`: per-bin mean of $f_{ON}(\\sigma)/A(\\sigma)$ over the same samples when
      `sigma` was given (the Oren–Nayar curve on the data's own geometry), else None.
    - `sigma`: that $\\sigma$ (radians) or None; `n_samples`: samples binned.
    """

    theta_deg: np.ndarray
    mean: np.ndarray
    sd: np.ndarray
    count: np.ndarray
    rms_60: float
    rms_all: float
    sd_60: float
    sd_all: float
    rms_samples_60: float
    rms_samples_all: float
    oren_nayar: np.ndarray | None
    sigma: float | None
    n_samples: int


def lambertian_check(
    images: Float[ArrayLike, "K H W"],
    normals: Float[ArrayLike, "H W 3"],
    albedo: Float[ArrayLike, "H W"],
    lights: Float[ArrayLike, "K 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    bin_deg: float = 1.0,
    sample_mask: Bool[ArrayLike, "K H W"] | None = None,
    sigma: float | None = None,
    form: str = "qualitative",
) -> LambertianCheck:
    """Bin $I/\\rho$ against $\\theta = \\angle(n, l)$ vs. $\\cos\\theta$ (Hansen et al.).

    **Arguments:**
    - `images`: `(K, H, W)` grey, linear (ambient already subtracted).
    - `normals`: `(H, W, 3)` unit normals; `albedo`: `(H, W)` (pixels with albedo <= 0 are
      skipped).
    - `lights`: `(K, 3)` directions toward the lights.
    - `mask`: `(H, W)` bool pixels to use; `sample_mask`: `(K, H, W)` bool samples to use.
    - `bin_deg`: bin width in degrees (bins cover [0, 90); samples at or beyond 90 degrees,
      in attached shadow, are left out).
    - `sigma`: if given, also bin the Oren–Nayar prediction for this roughness (radians).
    - `form`: Oren–Nayar form for that curve (one of `OREN_NAYAR_FORMS`).

    Samples that are non-finite, or whose pixel's albedo is not > 0 (NaN included) or normal is
    non-finite, are left out.

    **Returns:** a `LambertianCheck`.

    **Raises:** `ValueError` for mismatched shapes, integer images, `bin_deg`, `sigma` or
    `form` out of range, or no usable sample (an empty mask, no albedo > 0, ...).
    """
    images, normals, albedo, lights, mask = _check_stack(images, normals, albedo, lights, mask)
    _check_form(form)
    k, h, w = images.shape
    if not (0 < bin_deg <= 30):
        raise ValueError(f"bin_deg must be in (0, 30] degrees, got {bin_deg}")
    if sigma is not None and not (np.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"sigma must be finite and >= 0 (radians), got {sigma}")
    if sample_mask is None:
        sample_mask = np.ones((k, h, w), bool)
    elif np.shape(sample_mask) != (k, h, w):
        raise ValueError(f"sample_mask must be (K, H, W) = {(k, h, w)}, got "
                         f"{np.shape(sample_mask)}")
    cos_i, cos_r, p = _geometry(normals, lights)
    cos_i = np.asarray(cos_i, np.float64)
    img = np.asarray(images, np.float64)
    rho = np.asarray(albedo, np.float64)
    theta = np.degrees(np.arccos(np.clip(cos_i, -1, 1)))
    sel = (np.asarray(sample_mask, bool) & np.asarray(mask)[None] & (rho > 0)[None]
           & np.isfinite(img) & (theta < 90))
    if not sel.any():
        raise ValueError("no usable samples: none is masked, lit (theta < 90 degrees), finite "
                         "and of a pixel with albedo > 0")
    ratio = img[sel] / np.broadcast_to(rho, img.shape)[sel]
    th = theta[sel]
    nb = int(np.ceil(90 / bin_deg))
    idx = np.minimum((th / bin_deg).astype(int), nb - 1)
    count = np.bincount(idx, minlength=nb)
    s1 = np.bincount(idx, ratio, minlength=nb)
    s2 = np.bincount(idx, ratio**2, minlength=nb)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / count
        sd = np.sqrt(np.maximum(s2 / count - mean**2, 0))
    centres = (np.arange(nb) + 0.5) * bin_deg
    cos_c = np.cos(np.radians(centres))
    filled = count > 0
    lo = filled & (centres <= 60)

    def rms(sel_bins):
        return float(np.sqrt(np.mean((mean[sel_bins] - cos_c[sel_bins]) ** 2))) if sel_bins.any() \
            else float("nan")

    dev = ratio - np.cos(np.radians(th))
    on = None
    if sigma is not None:
        f = _shading(jnp.asarray(cos_i), jnp.asarray(cos_r)[None], p, jnp.asarray(sigma**2),
                     form)
        a = float(_coefficients(jnp.asarray(sigma**2), form)[0])
        pred = np.asarray(f, np.float64)[sel] / a
        with np.errstate(invalid="ignore", divide="ignore"):
            on = np.bincount(idx, pred, minlength=nb) / count
    return LambertianCheck(
        centres, mean, sd, count, rms(lo), rms(filled),
        float(np.mean(sd[lo])) if lo.any() else float("nan"),
        float(np.mean(sd[filled])) if filled.any() else float("nan"),
        float(np.sqrt(np.mean(dev[th <= 60] ** 2))) if np.any(th <= 60) else float("nan"),
        float(np.sqrt(np.mean(dev**2))) if dev.size else float("nan"),
        on, None if sigma is None else float(sigma), int(ratio.size),
    )
