"""The report's pictures: a shaded height map, the status map, the Lambertian-check histogram.

OpenCV and matplotlib are imported when a picture is read, written or drawn.
"""

from __future__ import annotations

import os

import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from ..core import Status
from ..integration import normals_from_height

__all__ = ["lambertian_check_plot"]

_STATUS_COLOURS = [
    (0.20, 0.63, 0.17), (0.85, 0.85, 0.85), (0.89, 0.10, 0.11), (0.12, 0.12, 0.12),
    (1.00, 0.50, 0.00), (0.99, 0.75, 0.44), (0.42, 0.24, 0.60), (0.65, 0.81, 0.89),
    (0.98, 0.60, 0.60), (0.70, 0.35, 0.16),
]


def _img(path) -> np.ndarray:
    import cv2

    raw = cv2.imread(os.fspath(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ValueError(f"cannot read image {path}")
    if raw.ndim == 3:
        raw = raw[..., ::-1]
    scale = 65535.0 if raw.dtype == np.uint16 else 255.0
    return raw.astype(np.float32) / scale


def _save_rgb(path, rgb: np.ndarray) -> None:
    import cv2

    v = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
    if v.ndim == 3:
        v = v[..., ::-1]
    if not cv2.imwrite(os.fspath(path), v):
        raise OSError(f"could not write {path}")


def _shade(height: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The height map lit from the upper left (normals of the height, Lambert, white outside)."""
    from scipy.ndimage import distance_transform_edt

    ok = mask & np.isfinite(height)
    if not ok.any():
        return np.ones(height.shape)
    # Outside the mask, repeat the nearest valid height so the outline casts no false edge.
    _, (r, c) = distance_transform_edt(~ok, return_indices=True)
    n = np.asarray(normals_from_height(height[r, c].astype(np.float32)))
    light = np.array([-1.0, 1.0, 1.5])
    light /= np.linalg.norm(light)
    shade = np.clip(n @ light, 0, 1) * 0.85 + 0.1
    return np.where(mask, shade, 1.0)


def _mesh_view(height: np.ndarray, mask: np.ndarray, albedo: np.ndarray, path,
               *, cells: int = 90) -> None:
    """The textured mesh seen from above and to the left: one quad per cell of a grid of at
    most `cells` x `cells` over the mask, coloured by the albedo (the texture of `mesh.obj`)
    times Lambert shading from the upper left, drawn with matplotlib's 3-D polygons."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    h, w = height.shape
    step = max(1, -(-max(h, w) // cells))
    z = np.where(mask, height, np.nan)[::step, ::step]
    ok = mask[::step, ::step] & np.isfinite(z)
    alb = np.asarray(albedo, np.float64)
    alb = (alb if alb.ndim == 3 else np.repeat(alb[..., None], 3, axis=-1))[::step, ::step]
    top = np.percentile(alb[ok], 99.5) if ok.any() else 1.0
    alb = np.clip(alb / (top or 1.0), 0, 1)
    shade = _shade(np.nan_to_num(z), ok)
    rows, cols = np.mgrid[:z.shape[0], :z.shape[1]]
    x, y = cols * step, (h - 1 - rows * step)
    quad = ok[:-1, :-1] & ok[1:, :-1] & ok[:-1, 1:] & ok[1:, 1:]
    r, c = np.nonzero(quad)
    corners = [(r, c), (r, c + 1), (r + 1, c + 1), (r + 1, c)]
    # matplotlib's vertical axis is the image's y; the height points toward the viewer (-depth).
    verts = np.stack([np.stack([x[i, j], -z[i, j], y[i, j]], -1) for i, j in corners], axis=1)
    colours = np.clip(alb[r, c] * shade[r, c][:, None], 0, 1)
    fig = plt.figure(figsize=(5, 5))
    ax = fig.add_subplot(projection="3d")
    ax.add_collection3d(Poly3DCollection(verts, facecolors=colours, edgecolors=colours,
                                         linewidths=0.3, shade=False))
    if len(verts):
        lo, hi = verts.reshape(-1, 3).min(0), verts.reshape(-1, 3).max(0)
        ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]))
        ax.set_box_aspect(np.maximum(hi - lo, 1e-9))
    ax.view_init(elev=15, azim=-60)
    ax.set_axis_off()
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)


def _status_figure(status: np.ndarray, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    codes = [int(c) for c in np.unique(status)]
    rgb = np.ones(status.shape + (3,))
    for c in codes:
        rgb[status == c] = _STATUS_COLOURS[c % len(_STATUS_COLOURS)]
    fig, ax = plt.subplots(figsize=(5.5, 4.0))
    ax.imshow(rgb, interpolation="nearest")
    ax.set_axis_off()
    names = {int(s): s.name for s in Status}
    ax.legend(handles=[Patch(color=_STATUS_COLOURS[c % len(_STATUS_COLOURS)],
                             label=names.get(c, str(c))) for c in codes],
              loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=8, frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def lambertian_check_plot(
    images: Float[ArrayLike, "K H W *C"],
    normals: Float[ArrayLike, "H W 3"],
    albedo: Float[ArrayLike, "H W *C"],
    lights: Float[ArrayLike, "K 3"],
    *,
    mask: Bool[ArrayLike, "H W"] | None = None,
    path=None,
) -> dict[str, float]:
    """Draw $I/\\rho$ against $\\cos\\theta = l \\cdot n$ for every lit sample (a 2-D histogram).

    A Lambertian surface puts every sample on the diagonal; specular highlights lie above it,
    shadows and dark skin below. The RMS of $I/\\rho - \\cos\\theta$ is given for
    $\\theta \\le 60°$ and over all samples with $\\cos\\theta > 0$ (the measure of the
    five-source face-scanner paper).

    **Arguments:**
    - `images`: `(K, H, W)` or `(K, H, W, C)` (grey mean used), the frames the normals came from.
    - `normals`, `albedo`: the photometric-stereo result (`(H, W, 3)`, `(H, W)` or `(H, W, C)`).
    - `lights`: `(K, 3)` unit directions.
    - `mask`: `(H, W)` pixels to use (default: albedo > 0).
    - `path`: where to write the PNG, if given.

    **Returns:** `{"rms_60": ..., "rms_all": ..., "samples": ...}`.
    """
    imgs = np.asarray(images, np.float64)
    if imgs.ndim == 4:
        imgs = imgs.mean(axis=-1)
    n = np.asarray(normals, np.float64)
    rho = np.asarray(albedo, np.float64)
    if rho.ndim == 3:
        rho = rho.mean(axis=-1)
    lt = np.asarray(lights, np.float64)
    if imgs.ndim != 3 or n.shape != imgs.shape[1:] + (3,) or lt.shape != (imgs.shape[0], 3):
        raise ValueError(f"images {np.shape(images)}, normals {n.shape} and lights {lt.shape} "
                         "do not match: need (K, H, W), (H, W, 3) and (K, 3)")
    sel = rho > 0 if mask is None else (np.asarray(mask, bool) & (rho > 0))
    cos = np.einsum("kc,hwc->khw", lt, n)[:, sel]
    ratio = imgs[:, sel] / rho[sel][None]
    lit = cos > 0
    err = (ratio - cos)[lit]
    within = (cos > np.cos(np.radians(60)))[lit]
    out = {"rms_60": float(np.sqrt(np.mean(err[within] ** 2))) if within.any() else float("nan"),
           "rms_all": float(np.sqrt(np.mean(err**2))) if err.size else float("nan"),
           "samples": int(err.size)}
    if path is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5.0, 4.2))
        ax.hist2d(cos[lit], ratio[lit], bins=80, range=[[0, 1], [0, 1.6]], cmin=1,
                  cmap="viridis", norm=matplotlib.colors.LogNorm())
        ax.plot([0, 1], [0, 1], "r-", lw=1, label="Lambert: I/ρ = cos θ")
        ax.axvline(np.cos(np.radians(60)), color="0.5", ls=":", lw=1, label="θ = 60°")
        ax.set_xlabel("cos θ (light · normal)")
        ax.set_ylabel("I / ρ")
        ax.set_title(f"Lambertian check: RMS {out['rms_60']:.3f} (θ ≤ 60°), "
                     f"{out['rms_all']:.3f} (all)", fontsize=9)
        ax.legend(fontsize=8, loc="upper left")
        fig.tight_layout()
        fig.savefig(path, dpi=100)
        plt.close(fig)
    return out
