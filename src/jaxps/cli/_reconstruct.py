"""`jaxps reconstruct`: frames on disk to normals, albedo, height, mesh and a summary.

`reconstruct` runs the pipeline on one capture's files and writes its outputs; with several
folders, `reconstruct_many` solves each as a capture (one progress bar, a summary table).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..acquisition import load_capture
from ..acquisition._capture import MIN_SHIFT, _kept
from ..acquisition._files import _decodes_srgb, _frame_paths
from ..core import Status, status_counts
from ..core._progress import Stages
from ..integration import integrate
from ..lights import near_light_field, surface_points
from ..lights._directions import _read_xyz
from ..ps import PS_METHODS, PSResult, near_photometric_stereo, photometric_stereo
from ..report._mesh import write_meshes
from ..report._progress import progress_bar
from ..report._writers import (
    write_albedo,
    write_csv,
    write_json,
    write_normal_map,
    write_preview,
)

__all__ = ["reconstruct", "reconstruct_many", "run", "summary_table"]

# Near lamps: the heights of `near_photometric_stereo`'s steps only place the lamps' light
# field here (the commands integrate the final normals themselves, or use no height), and
# Frankot–Chellappa's take a third of the time of the library's default `"lsq"` for the same
# normals (docs/robust.md, "Near point lights").
_NEAR_STEPS_INTEGRATION = "fc"


def reconstruct(
    frames,
    out: str,
    *,
    lights=None,
    yale_names: bool = False,
    ambient=None,
    mask=None,
    crop_face: bool = False,
    intensities: str = "frontal",
    shadow_threshold: float | None = None,
    method: str = "l2",
    integration: str = "lsq",
    report: bool = False,
    check_quality: bool = True,
    obj: bool = False,
    points: bool = False,
    register: bool = True,
    intensity_mask=None,
    intensity_normal=None,
    intensity_ratios=None,
    light_positions=None,
    pixel_size: float | None = None,
    bits: int | None = None,
    linearize: str = "auto",
) -> dict:
    """Run the whole pipeline on files and write the outputs to `out`; returns the summary.

    `check_quality`: drop the frames `jaxps.check_frames` flags before solving (named under
    `"dropped_frames"` in the summary, with their reasons under `"dropped_why"`; on by
    default, as in `load_capture`). `intensities`:
    see `load_capture` (the summary's `"intensities"` holds the method, the per-frame
    estimates and, for `"semi_calibrated"`, the fit's report `"fit"`; `"gains"` holds their
    inverses). `intensity_mask`, `intensity_normal`, `intensity_ratios`: a reference target in
    view, as in `load_capture` (named in the summary's `"intensities"` as `"target"`).
    `register`: undo motion between frames (see `load_capture`; the summary's `"motion"` holds
    the measured shifts and whether the frames were moved).
    `obj`, `points`: also write the textured OBJ and the point cloud (`write_meshes`).
    `bits`, `linearize`: the camera's bit depth, for files that hold its codes unscaled, and
    whether to decode the files from sRGB (`load_capture`; the summary's `"srgb_decoded"`
    says whether they were).
    `integration`: a `jaxps.INTEGRATION_METHODS` name; the default `"lsq"` integrates over
    the pixels solved, where `integrate`'s own default `"fc"` (the seeds' Frankot–Chellappa,
    which also runs inside `jit`) treats the image as periodic and bends a face's borders
    (docs/integration.md, "On real faces").
    `light_positions`, `pixel_size`: near point lights, for a rig whose lamps are close
    enough that their directions and fall-off change over the face: `(K, 3)` positions (or a
    file of `x y z` lines) in millimetres in the camera frame, the origin at the frame's centre
    at the subject's mean depth, and the size of a pixel there in millimetres. The frames are
    then solved by `near_photometric_stereo` (the summary's `"near_lights"` holds its steps);
    the intensity estimate, registration and quality checks take the lamps' directions from
    the origin. `lights` is then not given. With `crop_face` the positions stay measured from
    the frame's centre: the crop is solved with that centre (`"centre_px"` in the summary)."""
    if len(frames) == 1 and os.path.isdir(frames[0]):
        frames = frames[0]
    positions = None
    if light_positions is not None or pixel_size is not None:
        positions = _positions(light_positions, pixel_size, lights, yale_names, intensities)
        lights = positions / np.linalg.norm(positions, axis=1, keepdims=True)
    stages = Stages(4, progress_bar())
    try:
        cap = stages.run("load frames", load_capture, frames, lights=lights,
                         yale_names=yale_names, ambient=ambient, mask=mask,
                         intensities=intensities, crop_face=crop_face,
                         check_quality=check_quality, register=register,
                         intensity_mask=intensity_mask, intensity_normal=intensity_normal,
                         intensity_ratios=intensity_ratios, bits=bits, linearize=linearize)
        if cap.lights is None:
            raise ValueError("no lights: give --lights FILE or --yale-names")

        near = None
        if positions is not None:
            near_positions, centre, cap = _near_capture(frames, cap, positions, pixel_size,
                                                        intensity_mask)

        def solve():
            nonlocal near
            if positions is not None:
                near = near_photometric_stereo(
                    cap.images, near_positions, mask=cap.mask, pixel_size=pixel_size,
                    centre=centre, method=method, integration=_NEAR_STEPS_INTEGRATION,
                    sample_mask=~cap.saturated, shadow_threshold=shadow_threshold)
                return near.ps
            return photometric_stereo(cap.images, cap.lights, mask=cap.mask, method=method,
                                      sample_mask=~cap.saturated,
                                      shadow_threshold=shadow_threshold)

        res = stages.run("photometric stereo", solve)
        height, ok = stages.run("integrate", lambda: _integrate_solved(res, integration))

        def write():
            return _write_outputs(out, res, height, ok, obj=obj, points=points,
                                 title=f"{cap.names[0]} ... ({len(cap.names)} frames)")

        scale, faces = stages.run("write outputs", write)
    finally:
        stages.close()
    summary = {
        "frames": list(cap.names),
        "dropped_frames": list(cap.dropped),
        "dropped_why": _dropped_why(cap),
        "lights": np.asarray(cap.lights).round(6).tolist(),
        "size": {"frames": len(cap.names), "height": int(cap.images.shape[1]),
                 "width": int(cap.images.shape[2]),
                 "channels": int(cap.images.shape[3]) if cap.images.ndim == 4 else 1},
        "srgb_decoded": _srgb_decoded(frames, linearize),
        "crop": cap.crop,
        "gains": cap.gains.round(6).tolist(),
        "intensities": _intensities(cap, intensity_mask, intensity_normal, intensity_ratios),
        "motion": _motion(cap),
        "light_check": _light_check(cap),
        "method": method,
        "integration": integration,
        "mask_pixels": int(cap.mask.sum()),
        "status_counts": status_counts(res.status),
        "saturated_samples": int(cap.saturated.sum()),
        "albedo_png_scale": scale,
        "mesh_faces": faces,
        "timings_s": stages.times,
        "note": "timings include JIT compilation on the first call",
    }
    if near is not None:
        summary["near_lights"] = _near_summary(near, near_positions, pixel_size, centre)
    if report:
        from ..report import lambertian_check_plot, write_report  # matplotlib: only when asked

        summary["lambertian_check"] = lambertian_check_plot(
            cap.images, res.normals, res.albedo, cap.lights, mask=ok,
            path=os.path.join(out, "lambertian_check.png"))
    write_json(os.path.join(out, "summary.json"), summary)
    if report:
        write_report(out)
    return summary


def _integrate_solved(res, method):
    """`(height, ok)`: `res`'s normals integrated with `method` over the pixels it solved
    (`ok`, status OK), or over the whole image when it solved none."""
    ok = np.asarray(res.status) == Status.OK
    return np.asarray(integrate(res.normals, mask=ok if ok.any() else None, method=method)), ok


def _write_outputs(out, res, height, ok, *, obj=False, points=False, title="", threads=2):
    """`reconstruct`'s files in the folder `out`: normals.png, albedo.png, height.npy,
    status.npy, mesh.ply (and the OBJ or point cloud on request), preview.png. Returns the
    albedo PNG's scale and the mesh's face count.

    The files are independent, and PNG encoding and numpy release the GIL, so they are written
    on `threads` threads (`benchmarks/bench_io.py` times one against two)."""
    os.makedirs(out, exist_ok=True)
    normals, albedo = np.asarray(res.normals), np.asarray(res.albedo)
    path = lambda name: os.path.join(out, name)
    with ThreadPoolExecutor(max(1, min(threads, os.cpu_count() or 1))) as pool:
        jobs = [pool.submit(write_meshes, out, height, ok, albedo, normals, obj=obj,
                            points=points),
                pool.submit(write_albedo, path("albedo.png"), albedo),
                pool.submit(write_normal_map, path("normals.png"), normals),
                pool.submit(write_preview, path("preview.png"), normals, albedo, height, ok,
                            title=title),
                pool.submit(np.save, path("height.npy"), height),
                pool.submit(np.save, path("status.npy"), np.asarray(res.status))]
        meshes, scale = (job.result() for job in jobs[:2])
        for job in jobs[2:]:
            job.result()
    return scale, meshes["faces"]


def _positions(light_positions, pixel_size, lights, yale_names, intensities) -> np.ndarray:
    """`reconstruct`'s near lights as `(K, 3)` float64 millimetres, checked; `ValueError`s
    name the option."""
    if light_positions is None or pixel_size is None:
        raise ValueError("near lights need both light_positions (--light-positions) and "
                         "pixel_size (--pixel-size)")
    if lights is not None or yale_names:
        raise ValueError("give either lights (or yale_names) or light_positions, not both")
    if intensities == "semi_calibrated":
        raise ValueError("intensities='semi_calibrated' (--intensities) fits distant lights; "
                         "with light_positions use 'frontal', 'mean' or 'none'")
    if not (np.isfinite(pixel_size) and pixel_size > 0):
        raise ValueError(f"pixel_size must be a positive number of millimetres, got "
                         f"{pixel_size}")
    where = ""
    if isinstance(light_positions, (str, os.PathLike)):
        where = f" ({os.fspath(light_positions)})"
        if not os.path.isfile(light_positions):
            raise FileNotFoundError(f"light positions file not found: "
                                    f"{os.fspath(light_positions)}")
        try:
            light_positions = _read_xyz(os.fspath(light_positions), "light positions file")
        except ValueError as err:
            raise ValueError(f"light_positions{where}: {err}") from None
    positions = np.asarray(light_positions, np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3 or len(positions) < 3:
        raise ValueError(f"light_positions{where}: need 'x y z' for each of at least 3 lights, "
                         f"got shape {positions.shape}")
    if not np.all(np.isfinite(positions)) or np.any(positions[:, 2] <= 0):
        raise ValueError(f"light_positions{where}: every lamp must be finite and in front of "
                         "the subject (z > 0)")
    return positions


def _near_capture(frames, cap, positions, pixel_size, intensity_mask):
    """`(positions, centre, cap)` for near lamps: the positions of the frames `cap` kept (the
    quality checks may drop some), the frame's centre in `cap`'s crop (`_frame_centre`), and
    `cap` with its flash strengths re-estimated for the lamps (`_near_intensities`) unless a
    reference target measured them."""
    given = [os.path.basename(p) for p in _frame_paths(frames)]
    positions = positions[_kept(given, cap.names)]
    centre = _frame_centre(cap)
    if intensity_mask is None:
        cap = _near_intensities(cap, positions, pixel_size, centre)
    return positions, centre, cap


def _near_summary(near, positions, pixel_size, centre) -> dict:
    """The summary's `"near_lights"`: the lamps, the centre and `near_photometric_stereo`'s
    steps."""
    return {"positions_mm": positions.round(3).tolist(), "pixel_size_mm": pixel_size,
            "centre_px": None if centre is None else [round(v, 3) for v in centre],
            "steps": int(near.steps), "converged": bool(near.converged),
            "height_changes_mm": np.asarray(near.changes).round(4).tolist()}


def _frame_centre(cap) -> tuple[float, float] | None:
    """The centre of the frames as read, `(row, column)` in the pixels of `cap`'s crop (near
    lamps' positions are measured from it), or None when `cap` is not cropped."""
    if cap.crop is None:
        return None
    top, left = cap.crop[:2]
    h0, w0 = cap.frame_size
    return (h0 - 1) / 2 - top, (w0 - 1) / 2 - left


def _near_intensities(cap, positions, pixel_size, centre):
    """`cap` with its flash strengths re-estimated for near lamps at `positions`.

    `load_capture` estimates them as distant lights from the origin: `"mean"` takes each
    frame's mean over the mask as its strength, `"frontal"` divides that by $l_{k,z}$. Near
    lamps light the face in the mask with the direction $l_k(X)$ and the fall-off $a_k(X)$ of
    its points $X$, which for a face off the camera axis differ by lamp; the fall-off would
    then be divided out twice, once here and once by `near_photometric_stereo`. So the
    estimates are divided by the mean over the mask, on the plane $z = 0$, of $a_k$
    (`"mean"`) or $a_k\\, l_{k,z}$ (`"frontal"`) instead."""
    if cap.intensity_method not in ("mean", "frontal"):
        return cap
    points = surface_points(np.zeros(cap.mask.shape, np.float32), pixel_size=pixel_size,
                            centre=centre)
    lights, falloff = near_light_field(positions, points)
    # only l_z leaves the device: all of `lights` as float64 was 157 MB at 1 MP
    falloff = np.asarray(falloff, np.float64)
    weight = (falloff if cap.intensity_method == "mean"
              else falloff * np.asarray(lights[..., 2], np.float64))
    near = weight[:, cap.mask].mean(axis=1)
    if cap.intensity_method == "frontal":
        near = near / (positions[:, 2] / np.linalg.norm(positions, axis=1))  # the l_z used
    e = np.asarray(cap.intensities, np.float64) / near
    e = e / np.exp(np.mean(np.log(e)))
    shape = (-1,) + (1,) * (cap.images.ndim - 1)
    factor = (np.asarray(cap.intensities, np.float64) / e).astype(np.float32).reshape(shape)
    return cap._replace(images=cap.images * factor, intensities=e.astype(np.float32),
                        gains=(1 / e).astype(np.float32))


def _intensities(cap, intensity_mask, intensity_normal, intensity_ratios=None) -> dict:
    """The summary's record of `load_capture`'s flash strengths: the method, the per-frame
    estimates, the semi-calibrated fit's report and the reference target, where there are."""
    out = {"method": cap.intensity_method,
           "per_frame": np.asarray(cap.intensities).round(6).tolist()}
    if cap.intensity_fit:
        out["fit"] = cap.intensity_fit
    if intensity_mask is not None:
        where = (os.fspath(intensity_mask) if isinstance(intensity_mask, (str, os.PathLike))
                 else f"array of {int(np.count_nonzero(intensity_mask))} pixels")
        normal = [0.0, 0.0, 1.0] if intensity_normal is None else [float(v) for v in
                                                                     intensity_normal]
        out["target"] = {"mask": where, "normal": normal}
        if intensity_ratios is not None:
            out["target"]["ratios"] = (
                os.fspath(intensity_ratios) if isinstance(intensity_ratios, (str, os.PathLike))
                else np.asarray(intensity_ratios, float).round(6).tolist())
    return out


def _card_line(intensities) -> str:
    """What the reference card measured, for the operator to check at a glance."""
    return ("flash strengths measured on the card: "
            + " ".join(f"{v:.3f}" for v in intensities["per_frame"]))


def _motion(cap) -> dict:
    """The summary's record of `load_capture`'s motion step."""
    shifts = None if cap.shifts is None else np.asarray(cap.shifts).round(3).tolist()
    return {"shifts_px": shifts, "registered": bool(cap.registered)}


def _motion_cell(cap) -> str:
    """The many-capture table's `motion`: the largest shift between frames and whether it was
    undone ("1.85 px, undone"; "6.10 px, left" when too large to undo; "" when not measured)."""
    if cap.shifts is None:
        return ""
    largest = float(np.abs(np.asarray(cap.shifts)).max())
    return f"{largest:.2f} px" + (", undone" if cap.registered
                                  else ", left" if largest >= MIN_SHIFT else "")


def _dropped_why(cap) -> dict[str, list[str]]:
    """The summary's reasons for each dropped frame (`check_frames`' words), by name."""
    report = cap.frame_check
    return {} if report is None else {f.name: list(f.reasons) for f in report.flagged}


def _dropped_text(why: dict[str, list[str]]) -> str:
    """`_dropped_why`'s frames, each with its first reason: "f2.pgm (row/interlace ...)"."""
    return ", ".join(f"{name} ({reasons[0]})" for name, reasons in why.items())


def _dropped_line(summary: dict, shown: int = 5) -> str:
    """The printed line naming the dropped frames, each with its first reason: the first
    `shown` of them, then how many more (a whole Yale B folder drops over 20)."""
    why = summary["dropped_why"]
    if len(why) <= shown:
        return "dropped flagged frames " + _dropped_text(why)
    first = dict(list(why.items())[:shown])
    return (f"dropped {len(why)} flagged frames: " + _dropped_text(first)
            + f", and {len(why) - shown} more (summary.json, \"dropped_why\")")


def _light_check(cap) -> dict | None:
    """The summary's record of `load_capture`'s `check_lights` (None without lights)."""
    c = cap.light_check
    if c is None:
        return None
    rounded = lambda v: None if not np.isfinite(v) else round(float(v), 4)
    return {"curl": rounded(c.curl), "convexity": rounded(c.convexity),
            "residual_ratio": rounded(c.residual_ratio),
            "mirrored": bool(c.mirrored), "reordered": bool(c.reordered),
            "best_order": None if c.best_order is None else list(c.best_order),
            "hollow": bool(c.hollow), "summary": c.summary()}


def _srgb_decoded(frames, linearize) -> bool:
    """Whether `load_capture` decoded the files `frames` (a folder or a list) from sRGB."""
    return _decodes_srgb(_frame_paths(frames)[0], linearize)


def _srgb_line(decoded: bool, linearize: str) -> str | None:
    """A line for a command's output when it decoded the frames from sRGB of its own accord:
    a camera that writes linear codes to 8-bit PNGs gets wrong normals that way (more than
    10 degrees off on a synthetic face, `tests/test_cli.py::test_linear_8bit_pngs`)."""
    if not decoded or linearize != "auto":
        return None
    return ("8-bit PNG/JPEG frames read as sRGB and decoded to linear radiance; "
            "--linearize none if the camera wrote linear codes")


def _light_line(check: dict | None) -> str | None:
    """One line for the end of a command's output when `check_lights` flagged the lights."""
    if not check or not (check["mirrored"] or check["reordered"] or check["hollow"]):
        return None
    said = []
    if check["mirrored"]:
        said.append("mirrored")
    if check["reordered"]:
        said.append(f"in another order, best {check['best_order']}")
    if check["hollow"]:
        said.append("turned by 180 degrees: the surface is hollow")
    return (f"the lights do not fit the frames ({'; '.join(said)}): see the warning "
            "above and \"light_check\" in summary.json")


def run(args) -> int:
    if len(args.frames) > 1 and all(os.path.isdir(f) for f in args.frames):
        return _run_many(args)
    summary = reconstruct(
        args.frames, args.out, lights=args.lights, yale_names=args.yale_names,
        ambient=args.ambient, mask=args.mask, crop_face=args.crop_face,
        intensities=args.intensities,
        shadow_threshold=args.shadow_threshold, method=args.method,
        integration=args.integration, report=args.report, check_quality=args.check_quality,
        obj=args.obj, points=args.points, register=args.register,
        intensity_mask=args.intensity_mask, intensity_normal=args.intensity_normal,
        intensity_ratios=args.intensity_ratios,
        light_positions=args.light_positions, pixel_size=args.pixel_size, bits=args.bits,
        linearize=args.linearize,
    )
    if line := _srgb_line(summary["srgb_decoded"], args.linearize):
        print("reconstruct: " + line)
    if summary["dropped_frames"]:
        print("reconstruct: " + _dropped_line(summary))
    if summary["motion"]["registered"]:
        largest = np.abs(np.asarray(summary["motion"]["shifts_px"])).max()
        print(f"reconstruct: frames moved up to {largest:.2f} px; registered")
    if "target" in summary["intensities"]:
        print("reconstruct: " + _card_line(summary["intensities"]))
    if line := _light_line(summary["light_check"]):
        print("reconstruct: " + line)
    counts = ", ".join(f"{k} {v}" for k, v in summary["status_counts"].items())
    size = summary["size"]
    print(f"reconstructed {size['frames']} frames of {size['height']}x{size['width']} "
          f"-> {args.out}/ (pixels: {counts})")
    print("timings: " + ", ".join(f"{k} {v:.3f} s" for k, v in summary["timings_s"].items()))
    if why := _nothing_solved(summary["status_counts"]):
        print(f"reconstruct: {why} (the outputs are written all the same)", file=sys.stderr)
        return 1
    return 0


def _nothing_solved(counts: dict[str, int]) -> str | None:
    """Why no pixel of a capture was solved, from its `status_counts`; None if one was."""
    if counts.get("OK", 0):
        return None
    failed = {k: v for k, v in counts.items() if k != "MASKED"}
    if not failed:
        return "no pixel was solved; the mask is empty"
    worst = max(failed, key=failed.get)
    return f"no pixel was solved; {failed[worst]} are {worst}: {Status[worst].message}"


def summary_table(rows: Sequence[dict]) -> str:
    """A plain-text table of per-capture summaries (one row per capture, columns from the keys
    of the first row)."""
    if not rows:
        return "(no captures)"
    cols = list(rows[0])
    cells = [[str(c) for c in cols]] + [[_fmt(r.get(c, "")) for c in cols] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(cols))]
    lines = ["  ".join(v.ljust(wd) for v, wd in zip(row, widths)).rstrip() for row in cells]
    lines.insert(1, "  ".join("-" * wd for wd in widths))
    return "\n".join(lines)


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


def reconstruct_many(
    folders: Sequence[str | os.PathLike],
    *,
    method: str = "l2",
    check_quality: bool = True,
    progress: bool = True,
    light_positions=None,
    pixel_size: float | None = None,
    shadow_threshold: float | None = None,
    **load_options,
) -> tuple[list[PSResult | None], list[dict]]:
    """Load, check and solve many capture folders, with one progress bar over the captures.

    Each folder is loaded with `jaxps.acquisition.load_capture(folder, check_quality=...,
    **load_options)`, so each capture is solved exactly as `reconstruct` solves it alone: with
    `check_quality`, flagged frames are dropped before the intensities are estimated and the
    frames registered, and named with their first reason in the `dropped` column. A
    capture that cannot be loaded or keeps fewer than 3 frames is reported (`error` column) and
    its result is None; one with no pixel solved is reported there too, with its result.
    Nothing is skipped silently. `light_positions`, `pixel_size`: near
    lamps, the same for every capture, as for `reconstruct` (each capture is then solved by
    `near_photometric_stereo`; the rows gain `near_steps` and `near_converged`).
    `method`, `shadow_threshold`: as for `reconstruct`. The `motion` column gives the largest
    shift between the frames kept (`Capture.shifts`) and whether it was undone, "left" when
    it was too large to undo (`load_capture`, `register`); the `lights` column
    `load_capture`'s `check_lights` verdict: `ok`, `mirrored?`, `reordered?`, `hollow?` or
    `unchecked`.

    **Returns:** `(results, rows)`: one `PSResult` (or None) and one summary dict per folder;
    `summary_table(rows)` formats the rows.
    """
    from tqdm.auto import tqdm

    if method not in PS_METHODS:  # every capture's row would carry the same error
        raise ValueError(f"method must be one of {PS_METHODS}, got {method!r}")
    positions = None
    if light_positions is not None or pixel_size is not None:
        positions = _positions(light_positions, pixel_size, load_options.get("lights"),
                               load_options.get("yale_names", False),
                               load_options.get("intensities", "frontal"))
        load_options["lights"] = positions / np.linalg.norm(positions, axis=1, keepdims=True)
    results, rows = [], []
    bar = tqdm(list(folders), desc="captures", unit="capture", disable=not progress)
    for folder in bar:
        row = {"capture": os.path.basename(os.path.normpath(os.fspath(folder))), "frames": 0,
               "dropped": "", "motion": "", "lights": "", "ok_pixels": 0, "ok_%": 0.0,
               "error": ""}
        if positions is not None:
            row.update(near_steps=0, near_converged=False)
        res = None
        try:
            # frames are checked and dropped inside load_capture, as for one capture, so that
            # the intensities, the registration and the light check see only the kept frames
            cap = load_capture(folder, check_quality=check_quality, **load_options)
            if cap.lights is None:
                raise ValueError("no lights (give lights= or yale_names=True)")
            c = cap.light_check
            row["lights"] = ("mirrored?" if c.mirrored else "reordered?" if c.reordered
                             else "hollow?" if c.hollow else "unchecked" if c.unchecked
                             else "ok")
            row["frames"] = len(cap.names) + len(cap.dropped)
            row["motion"] = _motion_cell(cap)
            row["dropped"] = _dropped_text(_dropped_why(cap))
            if positions is not None:  # load_capture has matched the frames to the lamps
                kept_positions, centre, cap = _near_capture(
                    folder, cap, positions, pixel_size, load_options.get("intensity_mask"))
            images, lights, sample_mask = cap.images, cap.lights, ~cap.saturated
            if positions is None:
                res = photometric_stereo(images, lights, mask=cap.mask, sample_mask=sample_mask,
                                         method=method, shadow_threshold=shadow_threshold)
            else:
                near = near_photometric_stereo(images, kept_positions, mask=cap.mask,
                                               pixel_size=pixel_size, centre=centre,
                                               method=method, sample_mask=sample_mask,
                                               shadow_threshold=shadow_threshold,
                                               integration=_NEAR_STEPS_INTEGRATION)
                res = near.ps
                row.update(near_steps=int(near.steps), near_converged=bool(near.converged))
            counts = status_counts(res.status)
            row["ok_pixels"] = counts.get("OK", 0)
            row["ok_%"] = 100.0 * row["ok_pixels"] / max(int(cap.mask.sum()), 1)
            if why := _nothing_solved(counts):
                row["error"] = why
        except (ValueError, FileNotFoundError) as err:
            row["error"] = str(err).splitlines()[0]
        results.append(res)
        rows.append(row)
    bar.close()
    return results, rows


def _run_many(args) -> int:
    """`jaxps reconstruct DIR1 DIR2 ... --out OUT`: every folder is one capture; writes into
    `OUT/<folder>/` what one capture's run writes (`_write_outputs`: normals, albedo, the
    height integrated with `--integration`, status, mesh.ply and the `--obj` / `--points`
    meshes, preview), prints a summary table and writes `OUT/summary.json` and
    `OUT/summary.csv` (the table). Returns 1 if any capture failed or had no pixel solved
    (named in the table), else 0. `--report` takes one capture."""
    if args.report:
        raise ValueError("--report takes one capture; give the frames of one capture, or run "
                         "'jaxps reconstruct' on each folder with --report")
    load_options = dict(lights=args.lights, yale_names=args.yale_names, ambient=args.ambient,
                        mask=args.mask, crop_face=args.crop_face,
                        intensities=args.intensities, register=args.register,
                        intensity_mask=args.intensity_mask,
                        intensity_normal=args.intensity_normal,
                        intensity_ratios=args.intensity_ratios, bits=args.bits,
                        linearize=args.linearize)
    results, rows = reconstruct_many(args.frames, method=args.method,
                                     check_quality=args.check_quality,
                                     light_positions=args.light_positions,
                                     pixel_size=args.pixel_size,
                                     shadow_threshold=args.shadow_threshold, **load_options)
    os.makedirs(args.out, exist_ok=True)
    from tqdm.auto import tqdm

    solved = [(res, row) for res, row in zip(results, rows) if res is not None]
    for res, row in tqdm(solved, desc="integrate and write", unit="capture"):
        height, ok = _integrate_solved(res, args.integration)
        _write_outputs(os.path.join(args.out, row["capture"]), res, height, ok, obj=args.obj,
                       points=args.points, title=row["capture"])
    write_json(os.path.join(args.out, "summary.json"), {"captures": rows})
    write_csv(os.path.join(args.out, "summary.csv"), rows)
    print(summary_table(rows))
    loaded = [f for f, row in zip(args.frames, rows) if row["frames"]]
    if line := _srgb_line(any(_srgb_decoded(f, args.linearize) for f in loaded),
                          args.linearize):
        print("reconstruct: " + line)
    return 1 if any(r["error"] for r in rows) else 0
