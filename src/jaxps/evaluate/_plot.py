"""Error-map figures like the face-scanner papers' (matplotlib, imported when a figure is drawn)."""

from __future__ import annotations

import numpy as np
from jaxtyping import ArrayLike, Bool, Float

__all__ = ["plot_error_maps"]


def plot_error_maps(
    maps: dict[str, Float[ArrayLike, "H W"]],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    units: dict[str, str] | None = None,
    signed: tuple[str, ...] = (),
    vmax: dict[str, float] | None = None,
    path=None,
    dpi: int = 120,
):
    """Draw error maps side by side with colour bars, like the scanner papers' figures.

    Magnitude maps use the `jet` colour map from 0 to `vmax` (default: the 98th percentile over
    `mask`, so a few outliers do not wash the map out); maps named in `signed` use a diverging
    map symmetric about 0. Pixels off `mask` are white; panels are cropped to its box.

    **Arguments:**
    - `maps`: panel title -> `(H, W)` map (e.g. `{"height error": c.height_error}`).
    - `mask`: `(H, W)` bool, pixels to show (default: all).
    - `units`: panel title -> colour-bar label (e.g. `{"height error": "mm"}`).
    - `signed`: titles of signed maps.
    - `vmax`: panel title -> upper end of the colour scale.
    - `path`: where to save the figure (PNG), if given.

    **Returns:** the matplotlib `Figure` (closed when saved to `path`).

    **Raises:** `ValueError` when `maps` is empty, its maps are not `(H, W)` of one shape,
    `mask` has another shape, or `units`, `signed` or `vmax` name a title not in `maps`.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not maps:
        raise ValueError("maps is empty: nothing to draw")
    shapes = {name: np.shape(arr) for name, arr in maps.items()}
    for name, shape in shapes.items():
        if len(shape) != 2:
            raise ValueError(f"map {name!r} must be (H, W), got shape {shape}")
    if len(set(shapes.values())) > 1:
        raise ValueError(f"maps must share one (H, W) shape, got {shapes}")
    (shape,) = set(shapes.values())
    if mask is not None and np.shape(mask) != shape:
        raise ValueError(f"mask must have the maps' shape {shape}, got {np.shape(mask)}")
    units = units or {}
    vmax = vmax or {}
    for what, names in (("units", units), ("signed", signed), ("vmax", vmax)):
        unknown = [n for n in names if n not in maps]
        if unknown:  # a misspelt title would otherwise be ignored without a word
            raise ValueError(f"{what} names {unknown}, which are not in maps "
                             f"{list(maps)}")
    crop = (slice(None), slice(None))
    if mask is not None and np.any(mask):
        rows, cols = np.nonzero(np.asarray(mask, bool))
        pad = 4
        crop = (slice(max(rows.min() - pad, 0), rows.max() + pad + 1),
                slice(max(cols.min() - pad, 0), cols.max() + pad + 1))
    fig, axes = plt.subplots(1, len(maps), figsize=(4.2 * len(maps), 4.0), squeeze=False)
    for ax, (name, arr) in zip(axes[0], maps.items()):
        a = np.asarray(arr, np.float64)
        sel = np.isfinite(a) if mask is None else (np.asarray(mask, bool) & np.isfinite(a))
        vals = np.abs(a[sel]) if sel.any() else np.zeros(1)
        top = vmax.get(name, float(np.percentile(vals, 98)) or 1.0)
        shown = np.ma.masked_array(a, ~sel)[crop]
        if name in signed:
            cmap = plt.get_cmap("RdBu_r").with_extremes(bad="white")
            lo, hi = -top, top
        else:
            cmap = plt.get_cmap("jet").with_extremes(bad="white")
            lo, hi = 0.0, top
        im = ax.imshow(shown, cmap=cmap, vmin=lo, vmax=hi, interpolation="nearest")
        ax.set_title(name)
        ax.set_axis_off()
        cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
        if name in units:
            cb.set_label(units[name])
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=dpi)
        plt.close(fig)
    return fig
