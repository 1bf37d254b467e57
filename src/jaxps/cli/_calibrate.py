"""`jaxps calibrate`: a scanner's light directions from frames of a mirror (chrome) sphere.

The file-facing side of `jaxps.lights_from_chrome`: read the frames (one per light, in the
order the scanner fires them) and the sphere's mask, find each light's highlight, and write the
`lights.txt` that `jaxps reconstruct --lights` reads, with `calibration.json` (the sphere, each
highlight and light, and the angles to a reference set) and `calibration.png` (the highlights
on the sphere, the lights as seen from the camera) beside it. With frames of a flat board at
the subject's place (`--board`), it also writes the per-light `intensity_ratios.txt` that a
reference target needs under near lights (`acquisition.target_ratios`).
"""

from __future__ import annotations

import os
import sys

import numpy as np

from ..acquisition import list_frames, load_stack, read_image, read_mask, target_ratios
from ..acquisition._capture import _folder_ambient, _is_auto, _minus_ambient_file
from ..acquisition._files import _decodes_srgb, _exists, _frame_paths
from ..lights import (
    angles_from_lights,
    lights_from_chrome,
    load_lights,
    save_lights,
    validate_lights,
)
from ..report._writers import write_json
from ._reconstruct import _srgb_line

__all__ = ["calibrate", "run"]


def calibrate(frames, out: str, *, mask, ambient=None, level: float = 0.5,
              reference=None, board=None, board_mask=None, intensity_mask=None,
              intensity_normal=None, board_normal=None, bits: int | None = None,
              linearize: str = "auto") -> dict:
    """Calibrate the lights from frames of a mirror sphere; write `lights.txt`,
    `calibration.json` and `calibration.png` to `out`; return the JSON's contents. With
    `board`, also the reference target's `intensity_ratios.txt`.

    **Arguments:**
    - `frames`: a folder of frames (natural order, names with "mask" or "ambient" skipped) or
      the frame files, one per light (a multi-page TIFF stands for its pages, as in
      `load_capture`).
    - `mask`: the sphere's silhouette, an image file of the frames' size (non-zero inside; an
      anti-aliased edge refines the centre and radius).
    - `ambient`: an ambient-only frame to subtract, or `"auto"` (the folder's `*ambient*`).
    - `level`: a highlight is the pixels at or above `level` x the frame's brightest on the
      sphere (`lights_from_chrome`).
    - `reference`: a `lights.txt` to compare with (e.g. the previous calibration): the angle
      between each calibrated light and its reference is reported.
    - `board`, `board_mask`, `intensity_mask`: frames (a folder or files, one per light in the
      sphere's order) of a flat, matte board at the subject's place, its mask, and the mask of
      the reference target in view (`load_capture(intensity_mask=...)`): the per-light
      `acquisition.target_ratios` that a target needs under near lights are written to
      `intensity_ratios.txt` (`--intensity-ratios`). `intensity_normal`, `board_normal`: their
      normals (default facing the camera). `ambient`: a file is subtracted from the board's
      frames too; `"auto"` takes each folder's own.
    - `bits`, `linearize`: the camera's bit depth, for files that hold its codes unscaled,
      and whether to decode the files from sRGB (`read_image`); the sphere's, the board's and
      the ambient frames alike.

    **Raises:** `ValueError` naming the frames in which no highlight was found inside the
    sphere's outline (nothing is written then), or when the lights do not span 3-D;
    `FileNotFoundError` for a missing file.
    """
    board_ambient = ambient  # "auto": the board's folder has its own
    if isinstance(frames, (str, os.PathLike)) and os.path.isdir(frames):
        paths = list_frames(frames)
        ambient = _folder_ambient(frames, ambient)
    else:
        paths = _frame_paths(frames)
        if not paths:
            raise ValueError("frames: empty list of files")
        if _is_auto(ambient):
            raise ValueError("ambient='auto' takes the ambient frame from a folder of frames; "
                             "with a list of files, give the ambient file")
    given = (board is not None, board_mask is not None, intensity_mask is not None)
    if any(given) and not all(given):
        raise ValueError("board: the target's ratios need the board's frames, the board's mask "
                         "and the target's mask (--board, --board-mask, --intensity-mask)")
    for what, path in (("mask", mask), ("ambient frame", ambient), ("reference", reference),
                       ("board mask", board_mask), ("intensity mask", intensity_mask)):
        if path is not None and not _is_auto(path) and not _exists(path):
            raise FileNotFoundError(f"{what} not found: {os.fspath(path)}")
    names = [os.path.basename(p) for p in paths]
    codes = {"bits": bits, "linearize": linearize}
    images, _ = _frames(paths, ambient, codes)
    silhouette = read_image(mask, linearize="none")
    if silhouette.ndim == 3:
        silhouette = silhouette.max(axis=-1)
    if silhouette.shape != images.shape[1:3]:
        raise ValueError(f"mask {os.fspath(mask)} has shape {silhouette.shape}, frames have "
                         f"{images.shape[1:3]}")

    cal = lights_from_chrome(images, silhouette, level=level)
    missing = [n for n, ok in zip(names, cal.ok) if not ok]
    if missing:
        raise ValueError(f"no highlight found inside the sphere's outline in frame(s) "
                         f"{', '.join(missing)}: is the light off, or its reflection outside "
                         "the mask? (a highlight is a small bright spot: at most 5% of the "
                         "sphere at or above --level x its brightest pixel; for a broad lamp "
                         "raise --level)")
    try:
        lights = validate_lights(cal.lights)
    except ValueError as err:
        raise ValueError(f"the calibrated lights cannot be used: {err}") from None
    azimuth, elevation = angles_from_lights(lights)

    (r0, c0), radius = cal.centre, cal.radius
    report = {
        "frames": paths,
        "mask": os.fspath(mask),
        "ambient": None if ambient is None else os.fspath(ambient),
        "srgb_decoded": _decodes_srgb(paths[0], linearize),
        "level": level,
        "sphere": {"centre_row": r0, "centre_col": c0, "radius_px": radius},
        "lights": [
            {"frame": name, "direction": light.tolist(), "azimuth_deg": float(a),
             "elevation_deg": float(e), "highlight_row": float(h[0]),
             "highlight_col": float(h[1])}
            for name, light, a, e, h in zip(names, lights, azimuth, elevation, cal.highlights)
        ],
    }
    ref = None
    if reference is not None:
        ref = load_lights(reference)
        if len(ref) != len(lights):
            raise ValueError(f"reference {os.fspath(reference)} has {len(ref)} lights, "
                             f"the frames {len(lights)}")
        cos = np.clip(np.sum(lights.astype(np.float64) * ref, axis=1), -1, 1)
        angle = np.degrees(np.arccos(cos))
        report["reference"] = {"path": os.fspath(reference), "angle_deg": angle.tolist(),
                               "max_deg": float(angle.max()), "mean_deg": float(angle.mean())}

    ratios = None
    if board is not None:
        ratios = _board_ratios(board, board_ambient, lights, board_mask, intensity_mask,
                               intensity_normal, board_normal, codes)
        report["intensity_ratios"] = ratios

    os.makedirs(out, exist_ok=True)
    save_lights(os.path.join(out, "lights.txt"), lights, comment=(
        f"jaxps calibrate: mirror sphere at row {r0:.2f}, col {c0:.2f}, radius {radius:.2f} px\n"
        f"frames: {' '.join(names)}"))
    images_grey = images.mean(axis=-1) if images.ndim == 4 else images
    plot_calibration(os.path.join(out, "calibration.png"), images_grey.max(axis=0), cal, names,
                     lights, ref)
    report["outputs"] = ["lights.txt", "calibration.json", "calibration.png"]
    if ratios is not None:
        with open(os.path.join(out, "intensity_ratios.txt"), "w") as f:
            f.write("# jaxps calibrate: per light, the flash at the subject's place (the board) "
                    "over the flash at the reference target\n"
                    f"# target: {ratios['target_mask']}; board: {ratios['board_mask']}\n")
            f.writelines(f"{r:.6f}  # {name}\n"
                         for r, name in zip(ratios["ratios"], ratios["board_frames"]))
        report["outputs"].append("intensity_ratios.txt")
    write_json(os.path.join(out, "calibration.json"), report)
    return report


def _frames(paths, ambient, codes):
    """The frames at `paths` (`load_stack` with the options `codes`: `bits`, `linearize`),
    `ambient` (a file, or None) subtracted."""
    images, saturated = load_stack(paths, **codes)
    if ambient is not None:
        images = _minus_ambient_file(images, ambient, paths[0], **codes)
    return images, saturated


def _board_ratios(board, ambient, lights, board_mask, target_mask, target_normal,
                  board_normal, codes) -> dict:
    """`target_ratios` on the board's frames, and what they were measured on."""
    if isinstance(board, (str, os.PathLike)) and os.path.isdir(board):
        paths = list_frames(board)
        ambient = _folder_ambient(board, ambient)
    else:
        paths = _frame_paths(board)
        if _is_auto(ambient):
            raise ValueError("ambient='auto' takes the board's ambient frame from its folder; "
                             "with a list of files, give the ambient file")
    if len(paths) != len(lights):
        raise ValueError(f"board: {len(paths)} frames, but the sphere gave {len(lights)} "
                         "lights (one board frame per light, in the same order)")
    images, saturated = _frames(paths, ambient, codes)
    shape = images.shape[1:3]
    try:  # the board is target_ratios' subject
        ratios = target_ratios(images, lights, read_mask(target_mask, shape),
                               read_mask(board_mask, shape), target_normal=target_normal,
                               subject_normal=board_normal, saturated=saturated)
    except ValueError as err:
        raise ValueError(f"board: {err}".replace("board: subject", "board")) from None
    return {"board_frames": [os.path.basename(p) for p in paths],
            "board_mask": os.fspath(board_mask), "target_mask": os.fspath(target_mask),
            "board_normal": [0.0, 0.0, 1.0] if board_normal is None else list(board_normal),
            "target_normal": ([0.0, 0.0, 1.0] if target_normal is None
                              else list(target_normal)),
            "ratios": ratios.astype(float).round(6).tolist()}


def plot_calibration(path, image, cal, names, lights, reference=None) -> None:
    """Three panels: the brightest value of every frame over the sphere with its fitted
    outline; the highlights up close, numbered by frame; and the lights as seen from the camera
    ($l_x$, $l_y$; circles at 30, 60 and 90 degrees from the view axis), with the reference's
    beside them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (r0, c0), radius = cal.centre, cal.radius
    fig, (ax, zx, bx) = plt.subplots(1, 3, figsize=(15, 5))
    scale = np.percentile(image, 99.5)
    shown = np.clip(image / (scale if scale > 0 else 1.0), 0, 1) ** (1 / 2.2)
    hl = cal.highlights
    margin = 0.1 * radius
    zoom = (hl[:, 1].min() - margin, hl[:, 1].max() + margin,  # left, right, top, bottom
            hl[:, 0].min() - margin, hl[:, 0].max() + margin)
    for axis in (ax, zx):
        axis.imshow(shown, cmap="gray", vmin=0, vmax=1)
        axis.add_patch(plt.Circle((c0, r0), radius, fill=False, color="tab:orange", lw=1))
        axis.set_axis_off()
    pad = 1.1 * radius
    ax.set_xlim(c0 - pad, c0 + pad)
    ax.set_ylim(r0 + pad, r0 - pad)
    ax.add_patch(plt.Rectangle((zoom[0], zoom[2]), zoom[1] - zoom[0], zoom[3] - zoom[2],
                               fill=False, color="tab:red", lw=0.8))
    ax.set_title(f"sphere (brightest of {len(names)} frames) and its outline")
    zx.set_xlim(zoom[0], zoom[1])
    zx.set_ylim(zoom[3], zoom[2])
    for k, (row, col) in enumerate(hl):
        zx.plot(col, row, "+", color="tab:red", ms=12)
        zx.annotate(str(k), (col, row), xytext=(5, 5), textcoords="offset points",
                    color="tab:red", fontsize=9)
    zx.set_title("highlights, numbered by frame")

    t = np.linspace(0, 2 * np.pi, 200)
    for zenith in (30, 60, 90):
        s = np.sin(np.radians(zenith))
        bx.plot(s * np.cos(t), s * np.sin(t), color="0.85", lw=0.8)
        bx.annotate(f"{zenith} deg", (s * 0.71, -s * 0.71), color="0.6", fontsize=7)
    if reference is not None:
        for a, b in zip(lights, reference):
            bx.plot([a[0], b[0]], [a[1], b[1]], color="0.5", lw=0.8)
        bx.plot(reference[:, 0], reference[:, 1], "o", mfc="none", color="0.4",
                label="reference")
    bx.plot(lights[:, 0], lights[:, 1], "o", color="tab:red", ms=5, label="calibrated")
    for k, light in enumerate(lights):
        bx.annotate(str(k), light[:2], xytext=(4, 4), textcoords="offset points", fontsize=8)
    bx.set_aspect("equal")
    bx.set_xlim(-1.05, 1.05)
    bx.set_ylim(-1.05, 1.05)
    bx.set_xlabel("$l_x$ (image right)")
    bx.set_ylabel("$l_y$ (image up)")
    bx.set_title("lights seen from the camera")
    bx.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def run(args) -> int:
    """Returns 0, or 1 when a light moved more than `--tolerance` from `--reference` (the
    outputs are written either way), so that a daily check of the rig can fail by itself."""
    if args.tolerance is not None and (args.reference is None or not args.tolerance >= 0):
        raise ValueError("--tolerance is the largest angle (degrees, >= 0) a light may move "
                         "from --reference: give both")
    one_folder = len(args.frames) == 1 and os.path.isdir(args.frames[0])
    board = args.board
    if board is not None and len(board) == 1:
        board = board[0]
    report = calibrate(args.frames[0] if one_folder else args.frames, args.out, mask=args.mask,
                       ambient=args.ambient, level=args.level, reference=args.reference,
                       board=board, board_mask=args.board_mask,
                       intensity_mask=args.intensity_mask,
                       intensity_normal=args.intensity_normal, board_normal=args.board_normal,
                       bits=args.bits, linearize=args.linearize)
    if line := _srgb_line(report["srgb_decoded"], args.linearize):
        print("calibrate: " + line)
    sphere = report["sphere"]
    print(f"calibrated {len(report['lights'])} lights on the mirror sphere (centre row "
          f"{sphere['centre_row']:.1f}, col {sphere['centre_col']:.1f}, radius "
          f"{sphere['radius_px']:.1f} px)")
    ref = report.get("reference")
    for k, light in enumerate(report["lights"]):
        line = (f"  {light['frame']}: azimuth {light['azimuth_deg']:+.2f}, elevation "
                f"{light['elevation_deg']:+.2f} deg")
        if ref is not None:
            line += f"; {ref['angle_deg'][k]:.2f} deg from the reference"
        print(line)
    if ref is not None:
        worst = int(np.argmax(ref["angle_deg"]))
        print(f"against {ref['path']}: mean {ref['mean_deg']:.2f} deg, largest "
              f"{ref['max_deg']:.2f} deg ({report['lights'][worst]['frame']})")
    if "intensity_ratios" in report:
        print("flash at the subject's place over the target, per light: "
              + " ".join(f"{r:.3f}" for r in report["intensity_ratios"]["ratios"]))
    print(f"outputs: {args.out}/" + " ".join(report["outputs"]))
    if args.tolerance is not None and ref["max_deg"] > args.tolerance:
        moved = [f"{light['frame']} ({angle:.2f} deg)"
                 for light, angle in zip(report["lights"], ref["angle_deg"])
                 if angle > args.tolerance]
        print(f"jaxps calibrate: moved more than {args.tolerance:g} deg from the reference: "
              + ", ".join(moved), file=sys.stderr)
        return 1
    return 0
