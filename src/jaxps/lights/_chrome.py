"""Light calibration from a mirror (chrome) sphere.

A mirror sphere of known outline reflects each distant light in one highlight. At the
highlight's pixel the sphere's normal is $n = ((x - x_0)/r,\\ (y - y_0)/r,\\ \\sqrt{1 - \\cdot})$
(DESIGN.md frame: x right, y up, z toward the viewer; orthographic view $v = (0, 0, 1)$), and the
light is the mirror reflection of the view, $l = 2 (n \\cdot v) n - v$. The outline comes from
the (anti-aliased) mask: centre = its weighted centroid, radius = $\\sqrt{\\mathrm{area}/\\pi}$.
The highlight is the centroid of the largest connected blob at or above `level` x the
brightest value $m$ on the sphere, each pixel weighted by its height above that level,
$I - \\text{level}\\, m$. This is the classic calibration of e.g. Woodham's and the UW CSE 455
photometric-stereo set-up (the source of shared/data/psm). The weights fall to 0 at the
blob's edge, so the centroid moves smoothly with the highlight; with weights $I$, a pixel
that crosses the threshold enters or leaves with its full weight. On synthetic spheres of
41 px radius the largest error of five lights was 0.16-0.35 degrees (median over 8 seeds,
for four kinds of lamp), against 0.51-0.81 for the intensity-weighted centroid of the pixels
above 0.9 m (`benchmarks/bench_chrome.py`; docs/robust.md).

A highlight is small: in shared/data/psm's twelve chrome frames the pixels at or above
0.5 m cover 0.15-0.23% of the sphere (`benchmarks/input_checks.py`). A frame where they cover
more than `max_fraction` has no highlight to find: a flash that did not fire leaves a frame of
noise, about half of which is at or above half its maximum, and its largest blob of noise
would otherwise give a light in a random direction.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from jaxtyping import ArrayLike, Bool, Float

__all__ = ["ChromeCalibration", "lights_from_chrome", "sphere_from_mask"]


class ChromeCalibration(NamedTuple):
    """Result of `lights_from_chrome`.

    - `lights`: `(K, 3)` float32 unit directions toward the lights (DESIGN.md camera frame).
    - `highlights`: `(K, 2)` sub-pixel highlight centres `(row, col)`.
    - `centre`: `(row, col)` of the sphere; `radius` in pixels.
    - `ok`: `(K,)` bool, False where no highlight was found: no bright pixel on the sphere,
      one outside its outline, or none that stands out (`max_fraction`). That light is then
      (0, 0, 1).
    """

    lights: Float[np.ndarray, "K 3"]
    highlights: Float[np.ndarray, "K 2"]
    centre: tuple[float, float]
    radius: float
    ok: Bool[np.ndarray, " K"]


def sphere_from_mask(mask: Float[ArrayLike, "H W"]) -> tuple[tuple[float, float], float]:
    """Centre `(row, col)` and radius (pixels) of a disc mask (bool, or anti-aliased in [0, 1]).

    **Raises:** `ValueError` if `mask` is not 2-D or is empty.
    """
    m = np.asarray(mask, np.float64)
    if m.ndim != 2:
        raise ValueError(f"mask must be (H, W), got shape {m.shape}")
    if m.max() > 1:
        m = m / m.max()
    area = m.sum()
    if area <= 0:
        raise ValueError("mask is empty: no sphere to fit")
    rows, cols = np.indices(m.shape)
    centre = (float((rows * m).sum() / area), float((cols * m).sum() / area))
    return centre, float(np.sqrt(area / np.pi))


def lights_from_chrome(
    images: Float[ArrayLike, "K H W *C"],
    mask: Float[ArrayLike, "H W"],
    *,
    level: float = 0.5,
    max_fraction: float = 0.05,
) -> ChromeCalibration:
    """Distant light directions from images of a mirror sphere.

    **Arguments:**
    - `images`: `(K, H, W)` or `(K, H, W, C)` images of the sphere, one light each (any
      monotonic encoding: only the location of the highlight is used).
    - `mask`: `(H, W)` the sphere's silhouette (bool, or anti-aliased grey).
    - `level`: a highlight is the pixels at or above `level` x the image's maximum $m$ on the
      sphere (the largest connected blob; its centroid with weights $I - \\text{level}\\, m$).
    - `max_fraction`: in (0, 1]; a frame whose pixels at or above `level` x $m$ cover more
      than this fraction of the sphere has no distinct highlight (a dark frame of noise, an
      overexposed one, a matte ball), and its light is not `ok`.

    **Returns:** `ChromeCalibration`.
    """
    images = np.asarray(images, np.float64)
    if images.ndim == 4:
        images = images.mean(axis=-1)
    if images.ndim != 3:
        raise ValueError(f"images must be (K, H, W) or (K, H, W, C), got shape {images.shape}")
    mask = np.asarray(mask, np.float64)
    if mask.shape != images.shape[1:]:
        raise ValueError(f"mask must have shape {images.shape[1:]}, got {mask.shape}")
    if not 0 < level <= 1:
        raise ValueError(f"level must be in (0, 1], got {level}")
    if not 0 < max_fraction <= 1:
        raise ValueError(f"max_fraction must be in (0, 1], got {max_fraction}")
    import scipy.ndimage as ndi  # here, not at import: `import jaxps` stays quick

    (r0, c0), radius = sphere_from_mask(mask)
    inside = mask >= 0.5 * mask.max()
    most_bright = max_fraction * np.count_nonzero(inside)  # pixels a highlight may cover
    k = images.shape[0]
    lights = np.tile([0.0, 0.0, 1.0], (k, 1))
    highlights = np.full((k, 2), np.nan)
    ok = np.zeros(k, bool)
    for j, img in enumerate(images):
        vals = np.where(inside, np.nan_to_num(img, nan=0.0), 0.0)
        top = vals.max()
        if not top > 0:
            continue
        bright = vals >= level * top
        if np.count_nonzero(bright) > most_bright:
            continue
        labels, count = ndi.label(bright)
        sizes = ndi.sum_labels(vals, labels, index=np.arange(1, count + 1))
        blob = labels == 1 + int(np.argmax(sizes))
        weights = np.where(blob, vals - level * top, 0.0)
        if not weights.sum() > 0:  # level 1: a plateau at the maximum, all weights 0
            weights = blob.astype(np.float64)
        row, col = ndi.center_of_mass(weights)
        x, y = (col - c0) / radius, -(row - r0) / radius
        rr = x * x + y * y
        if rr >= 1:
            continue
        n = np.array([x, y, np.sqrt(1 - rr)])
        lights[j] = 2 * n[2] * n - np.array([0.0, 0.0, 1.0])
        highlights[j] = row, col
        ok[j] = True
    lights /= np.linalg.norm(lights, axis=-1, keepdims=True)
    return ChromeCalibration(lights.astype(np.float32), highlights, (r0, c0), radius, ok)
