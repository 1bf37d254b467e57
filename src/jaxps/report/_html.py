"""An HTML report for a run directory written by `jaxps reconstruct` (`jaxps report RUN_DIR`).

The page shows the normal map, the albedo, the height map shaded from the upper left, the
per-pixel status, error maps against ground truth where it is given (a normal map compared pixel
by pixel; a depth map or a scan file compared after ICP, as in
`jaxps.evaluate.compare_to_scan`), the Lambertian check plot ($I/\\rho$ against
$\\cos\\theta$) where the run has one, and the timings and settings from `summary.json`.
Figures go to `RUN_DIR/report_files/` and are linked relatively, so the folder can be moved or
served as it is.
"""

from __future__ import annotations

import datetime
import html
import json
import os
import pathlib

import numpy as np

from .. import evaluate
from ._figures import _img, _mesh_view, _save_rgb, _shade, _status_figure
from ._writers import read_normal_map

__all__ = ["write_report"]

_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.15em; margin-top: 1.6em; border-bottom: 1px solid #ddd; }
.grid { display: flex; flex-wrap: wrap; gap: 1em; align-items: flex-start; }
figure { margin: 0; } figure img { width: 320px; border: 1px solid #ccc; background: #fff; }
figure.grid-px img { image-rendering: pixelated; }
figure.wide img { width: auto; max-width: 100%; }
figcaption { font-size: 0.85em; color: #555; }
table { border-collapse: collapse; font-size: 0.9em; } td, th { padding: 2px 10px;
  border-bottom: 1px solid #eee; text-align: left; } td.num { text-align: right; }
code { background: #f4f4f4; padding: 0 3px; }
"""


def _table(rows) -> str:
    cells = []
    for k, v in rows:
        if isinstance(v, float):
            v, cls = f"{v:.4g}", ' class="num"'
        elif isinstance(v, int):
            v, cls = str(v), ' class="num"'
        else:
            v, cls = str(v), ""
        cells.append(f"<tr><th>{html.escape(str(k))}</th><td{cls}>{html.escape(v)}</td></tr>")
    return "<table>" + "".join(cells) + "</table>"


def _figure(src: str, caption: str, wide: bool = False) -> str:
    cls = ' class="wide"' if wide else ""
    return (f'<figure{cls}><img src="{html.escape(src, quote=True)}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def write_report(
    run_dir,
    *,
    truth_normals=None,
    truth_depth=None,
    intrinsics=None,
    truth_mask=None,
    truth_scan=None,
    out=None,
) -> pathlib.Path:
    """Write `RUN_DIR/report.html` (and its figures in `RUN_DIR/report_files/`).

    **Arguments:**
    - `run_dir`: a folder written by `jaxps reconstruct` (`normals.png`, `albedo.png`,
      `height.npy`, `status.npy`, `summary.json`; missing pieces are left out of the page).
    - `truth_normals`: a ground-truth normal-map PNG (16-bit, $n = v/65535 \\cdot 2 - 1$, the
      DiLiGenT layout) or `(H, W, 3)` array on the run's pixel grid: per-pixel angular and
      $\\ell_2$-norm error maps.
    - `truth_depth`: a ground-truth depth map (`.npz` with key `depth_gt`, `.npy`, or an
      array) and `intrinsics` (`K.txt` path or `(3, 3)`): the height map is aligned to its
      back-projection with scaled ICP and the height error is mapped.
    - `truth_mask`: a mask image or `(H, W)` bool for the ground truth (default: all finite).
    - `truth_scan`: a scan file (`jaxps.evaluate.read_scan`: a mesh or point cloud in any unit,
      axes roughly the camera's) or `(M, 3)` points, instead of `truth_depth`: aligned and
      mapped the same way, with the mesh's own normals for the angular error.
    - `out`: the HTML path (default `RUN_DIR/report.html`).

    **Returns:** the path of the HTML file.

    **Raises:** `FileNotFoundError` when `run_dir` has neither `normals.png` nor `summary.json`;
    `ValueError` when both `truth_depth` and `truth_scan` are given, or either without the
    run's `height.npy`.
    """
    if truth_depth is not None and truth_scan is not None:
        raise ValueError("truth_depth and truth_scan: give one ground-truth surface, not both")
    run = pathlib.Path(run_dir)
    if not (run / "normals.png").is_file() and not (run / "summary.json").is_file():
        raise FileNotFoundError(f"{run} is not a jaxps run directory (no normals.png, "
                                "no summary.json)")
    out = run / "report.html" if out is None else pathlib.Path(out)
    files = out.parent / "report_files"
    files.mkdir(parents=True, exist_ok=True)

    def rel(p) -> str:
        return os.path.relpath(p, out.parent).replace(os.sep, "/")

    summary = {}
    if (run / "summary.json").is_file():
        try:
            summary = json.loads((run / "summary.json").read_text())
        except json.JSONDecodeError as err:
            raise ValueError(f"{run / 'summary.json'} is not valid JSON: {err}") from None
    normals = read_normal_map(run / "normals.png") if (run / "normals.png").is_file() else None
    status = np.load(run / "status.npy") if (run / "status.npy").is_file() else None
    height = np.load(run / "height.npy") if (run / "height.npy").is_file() else None
    if status is not None:
        mask = status == 0
    elif normals is not None:
        mask = np.any(normals != np.array([0, 0, 1], np.float32), axis=-1)
    else:
        mask = np.isfinite(height) if height is not None else None

    parts = []
    pictures = []
    if normals is not None:
        _save_rgb(files / "normals_rgb.png",
                  np.where(mask[..., None], (normals + 1) / 2, 1.0))
        pictures.append(_figure(rel(files / "normals_rgb.png"),
                                "normal map (RGB = (n + 1) / 2; x right, y up, z to the viewer)"))
    if (run / "albedo.png").is_file():
        alb = _img(run / "albedo.png")
        shown = np.where(mask if alb.ndim == 2 else mask[..., None], alb, 1.0)
        _save_rgb(files / "albedo.png", shown)
        scale = summary.get("albedo_png_scale")
        pictures.append(_figure(rel(files / "albedo.png"), "albedo" + (
            f" (stored as albedo x {scale:.3g})" if isinstance(scale, float) else "")))
    if height is not None and mask is not None:
        _save_rgb(files / "height_shaded.png", _shade(height, mask))
        pictures.append(_figure(rel(files / "height_shaded.png"),
                                "height map, shaded from the upper left"))
    if status is not None:
        _status_figure(status, files / "status.png")
        pictures.append(_figure(rel(files / "status.png"), "per-pixel status"))
    if height is not None and mask is not None and (run / "albedo.png").is_file():
        _mesh_view(height, mask, _img(run / "albedo.png"), files / "mesh_view.png")
        pictures.append(_figure(rel(files / "mesh_view.png"),
                                "the textured mesh (albedo on the surface), seen obliquely"))
    parts.append("<h2>Reconstruction</h2><div class='grid'>" + "".join(pictures) + "</div>")

    # Ground truth: error maps.
    errors = []
    if truth_normals is not None and normals is not None:
        tn = (read_normal_map(truth_normals) if isinstance(truth_normals, (str, os.PathLike))
              else np.asarray(truth_normals, np.float32))
        if tn.shape != normals.shape:
            raise ValueError(f"truth_normals has shape {tn.shape}, the run's normals "
                             f"{normals.shape}")
        tm = _truth_mask(truth_mask, tn.shape[:2]) & mask & (np.linalg.norm(tn, axis=-1) > 0.5)
        ang = np.asarray(evaluate.angular_error(normals, tn, mask=tm))
        l2 = evaluate.l2_error(normals, tn, mask=tm)
        stats = evaluate.angular_stats(normals, tn, mask=tm)
        evaluate.plot_error_maps({"angular error": ang, "l2-norm error": l2}, mask=tm,
                                 units={"angular error": "degrees"},
                                 path=files / "normal_error_maps.png")
        errors.append(_figure(rel(files / "normal_error_maps.png"),
                              "normal error against the ground-truth normal map", wide=True))
        errors.append(_table([(f"angular error {k.replace('_deg', '')} (deg)", v)
                              for k, v in stats.items() if k != "pixels"]
                             + [("mean l2-norm error", float(l2[tm].mean())),
                                ("pixels compared", int(stats["pixels"]))]))
    if truth_depth is not None or truth_scan is not None:
        which = "truth_scan" if truth_scan is not None else "truth_depth"
        if height is None:
            raise ValueError(f"{which}: {run} has no height.npy to compare with a surface")
        scan_normals, what = None, "depth scan"
        if truth_scan is not None:
            if isinstance(truth_scan, (str, os.PathLike)):
                pts, scan_normals = evaluate.read_scan(truth_scan)
                what = f"scan {pathlib.Path(truth_scan).name}"
            else:
                pts = np.asarray(truth_scan)
        else:
            if intrinsics is None:
                raise ValueError("truth_depth needs intrinsics (K.txt or a (3, 3) matrix)")
            depth = _load_depth(truth_depth)
            k = (np.loadtxt(intrinsics) if isinstance(intrinsics, (str, os.PathLike))
                 else intrinsics)
            dm = _truth_mask(truth_mask, depth.shape)
            pts, _ = evaluate.points_from_depth(depth, k, mask=dm)
        try:
            comp = evaluate.compare_to_scan(height, pts, mask=mask, normals=normals,
                                            target_normals=scan_normals, trim=0.95)
        except ValueError as err:  # named by the argument given here, not compare_to_scan's
            raise ValueError(f"{which}: {str(err).removeprefix('target: ')}") from err
        maps = {"height error": comp.height_error}
        if normals is not None:
            maps["angular error"] = comp.angular_error
        units = {"height error": "scan units", "angular error": "degrees"}
        evaluate.plot_error_maps(maps, mask=comp.mask, signed=("height error",),
                                 units={k: v for k, v in units.items() if k in maps},
                                 path=files / "scan_error_maps.png")
        errors.append(_figure(rel(files / "scan_error_maps.png"),
                              f"errors against the {what} after scaled ICP", wide=True))
        errors.append(_table([
            ("RMS height error (scan units)", comp.rms_height),
            ("mean |height error| (scan units)", comp.mean_abs_height),
            ("median angular error after ICP (deg)", comp.median_angular),
            ("ICP scale (scan units per pixel)", comp.icp.scale),
            ("ICP steps", comp.icp.steps), ("ICP converged", str(comp.icp.converged)),
        ]))
    if "errors_vs_truth" in summary:
        errors.append("<p>Recorded in <code>summary.json</code> by the run itself:</p>"
                      + _table(sorted(summary["errors_vs_truth"].items())))
    if errors:
        parts.append("<h2>Against ground truth</h2>" + "".join(errors))

    # The Lambertian check, if the run has one.
    checks = sorted(run.glob("lambertian_check*.png"))
    if checks or "lambertian_check" in summary:
        body = "".join(_figure(rel(p), p.stem.replace("_", " ")) for p in checks)
        if isinstance(summary.get("lambertian_check"), dict):
            body += _table(sorted(summary["lambertian_check"].items()))
        parts.append("<h2>Lambertian check</h2><div class='grid'>" + body + "</div>")

    # Timings and settings.
    if summary.get("timings_s"):
        rows = [(k, float(v)) for k, v in summary["timings_s"].items()]
        rows.append(("total", float(sum(v for _, v in rows))))
        parts.append("<h2>Timings (s)</h2>" + _table(rows) + "<p>" + html.escape(
            summary.get("note", "")) + "</p>")
    settings = [(k, json.dumps(v) if isinstance(v, (list, dict)) else v)
                for k, v in summary.items()
                if k not in ("timings_s", "errors_vs_truth", "lambertian_check", "note",
                             "lights", "frames")]
    if "frames" in summary:
        settings.insert(0, ("frames", ", ".join(summary["frames"])))
    if settings:
        parts.append("<h2>Settings and counts</h2>" + _table(settings))

    title = f"jaxps report: {run.resolve().name}"
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    page = (f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
            f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>"
            f"<h1>{html.escape(title)}</h1><p>Run folder <code>{html.escape(str(run))}</code>, "
            f"report written {stamp}.</p>" + "".join(parts) + "</body></html>\n")
    out.write_text(page, encoding="utf-8")
    return out


def _truth_mask(mask, shape) -> np.ndarray:
    if mask is None:
        return np.ones(shape, bool)
    if isinstance(mask, (str, os.PathLike)):
        m = _img(mask)
        m = m.mean(axis=-1) if m.ndim == 3 else m
        m = m > 0
    else:
        m = np.asarray(mask, bool)
    if m.shape != tuple(shape):
        raise ValueError(f"truth_mask has shape {m.shape}, expected {tuple(shape)}")
    return m


def _load_depth(depth) -> np.ndarray:
    if isinstance(depth, (str, os.PathLike)):
        p = pathlib.Path(depth)
        if p.suffix == ".npz":
            with np.load(p) as z:
                key = "depth_gt" if "depth_gt" in z.files else z.files[0]
                return np.asarray(z[key], np.float32)
        return np.asarray(np.load(p), np.float32)
    return np.asarray(depth, np.float32)
