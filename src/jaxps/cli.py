"""The `jaxps` command line: `jaxps reconstruct`, `jaxps demo`, `jaxps report`, `jaxps relight`."""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def _add_light_args(p) -> None:
    """The options every frame-reading subcommand shares: where lights come from, ambient."""
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--lights", help="lights.txt: optional count line, then 'x y z' per frame")
    g.add_argument("--yale-names", action="store_true",
                   help="parse lights from Yale B names (..._P00A+035E+15.pgm)")
    p.add_argument("--ambient", help="ambient-only control frame to subtract")


def _add_reconstruct(sub) -> None:
    p = sub.add_parser(
        "reconstruct",
        help="frames -> normals, albedo, height, mesh and a JSON summary",
        description="Reconstruct normals, albedo and a height map from a photometric-stereo "
        "frame stack, and write normals.png (16-bit, n = v/65535*2-1), albedo.png, height.npy, "
        "mesh.ply, preview.png and summary.json to --out.",
    )
    p.add_argument("frames", nargs="+", help="a folder of frames, or the frame files in order; "
                   "several folders are several captures (one progress bar, a summary table)")
    p.add_argument("--check-quality", action="store_true",
                   help="drop frames flagged by jaxps.check_frames (corrupt, badly exposed or "
                   "inconsistent) before solving")
    _add_light_args(p)
    p.add_argument("--mask", help="mask image (non-zero inside), or 'auto' (from the mean image)")
    p.add_argument("--crop-face", action="store_true", help="crop to the Haar-detected face")
    p.add_argument("--equalize", action="store_true",
                   help="equalise mean intensity across frames (four-source scanner)")
    p.add_argument("--shadow-threshold", type=float, default=None,
                   help="drop samples below this intensity from each pixel's solve")
    p.add_argument("--method", default="l2", help="photometric-stereo method (jaxps.PS_METHODS)")
    p.add_argument("--integration", default="fc",
                   help="integration method (jaxps.INTEGRATION_METHODS)")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--report", action="store_true",
                   help="also write lambertian_check.png and report.html (see 'jaxps report')")
    p.set_defaults(func=_cmd_reconstruct)


def _add_report(sub) -> None:
    p = sub.add_parser(
        "report",
        help="an HTML page for a run folder: maps, error maps against ground truth, timings",
        description="Write RUN_DIR/report.html (figures in RUN_DIR/report_files/) for a folder "
        "written by 'jaxps reconstruct': normal map, albedo, shaded height, status, the "
        "Lambertian check plot if the run has one, timings; with ground truth, error maps.",
    )
    p.add_argument("run_dir", help="a folder written by 'jaxps reconstruct'")
    p.add_argument("--truth-normals", help="ground-truth normal map PNG (16-bit, same grid)")
    p.add_argument("--truth-depth", help="ground-truth depth (.npz key depth_gt, or .npy)")
    p.add_argument("--intrinsics", help="K.txt camera matrix for --truth-depth")
    p.add_argument("--truth-mask", help="mask image for the ground truth")
    p.add_argument("--out", help="HTML path (default RUN_DIR/report.html)")
    p.set_defaults(func=_cmd_report)


def _add_demo(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="render a synthetic face capture with known truth, reconstruct it, print errors",
        description="Render a face-like surface under five scanner-like lights (16-bit PNG "
        "frames, an ambient frame and lights.txt in OUT/frames), run the same pipeline as "
        "'jaxps reconstruct' on those files, and compare with the known truth.",
    )
    p.add_argument("--out", default="jaxps-demo", help="output folder (default: jaxps-demo)")
    p.add_argument("--size", type=int, default=320, help="image height in pixels (default 320)")
    p.add_argument("--noise", type=float, default=0.005,
                   help="Gaussian noise s.d. in [0, 1] units (default 0.005)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_demo)


def _add_relight(sub) -> None:
    p = sub.add_parser(
        "relight",
        help="fit a BRDF to the frames and render the face under new lights",
        description="Photometric stereo on the frames, then fit_brdf (default mlp_ratio), then "
        "write relit PNGs for each --light, relight.gif (a light circling the face) and "
        "relight.json (fit report) to --out.",
    )
    p.add_argument("frames", nargs="+", help="a folder of frames, or the frame files in order")
    _add_light_args(p)
    p.add_argument("--mask", default="auto", help="mask image, or 'auto' (default)")
    p.add_argument("--method", default="mlp_ratio", help="BRDF model (jaxps.BRDF_METHODS)")
    p.add_argument("--check-quality", action="store_true",
                   help="drop frames flagged by jaxps.check_frames (e.g. interlace-combed) "
                   "before fitting")
    p.add_argument("--light", action="append", default=[], metavar="AZ,EL",
                   help="a new light, azimuth,elevation in degrees (Yale B); repeatable; write "
                   "--light=-50,0 when the azimuth is negative")
    p.add_argument("--circle-zenith", type=float, default=30.0,
                   help="zenith angle (deg) of the animation's circling light (default 30)")
    p.add_argument("--circle-frames", type=int, default=36, help="animation frames (36)")
    p.add_argument("--samples", type=int, default=100_000, help="training samples (100000)")
    p.add_argument("--max-steps", type=int, default=30, help="Levenberg-Marquardt steps (30)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.set_defaults(func=_cmd_relight)


def _cmd_relight(args) -> int:
    from ._relight_cli import relight_capture

    try:
        new_lights = [tuple(float(v) for v in s.split(",")) for s in args.light]
    except ValueError:
        raise ValueError(f"--light must be AZ,EL in degrees, got {args.light}") from None
    if any(len(v) != 2 for v in new_lights):
        raise ValueError(f"--light must be AZ,EL in degrees, got {args.light}")
    s = relight_capture(
        args.frames, args.out, lights=args.lights, yale_names=args.yale_names,
        ambient=args.ambient, mask=args.mask, method=args.method, new_lights=new_lights,
        circle_zenith_deg=args.circle_zenith, circle_frames=args.circle_frames,
        n_samples=args.samples, max_steps=args.max_steps, seed=args.seed,
        check_quality=args.check_quality)
    if s["dropped_frames"]:
        print("relight: dropped flagged frames " + ", ".join(s["dropped_frames"]))
    fit = s["fit"]
    print(f"relight: {args.method} on {len(s['frames'])} frames, {s['mask_pixels']} pixels: "
          f"training RMSE {fit['rmse']:.4g} (x255 = {s['fit_rmse_gray_8bit']:.2f}), "
          f"R {fit['r']:.4f}, {fit['steps']} steps, converged {fit['converged']}")
    print(f"outputs: {args.out}/" + " ".join(s["files"]) + " relight.json")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = argparse.ArgumentParser(
        prog="jaxps", description="Photometric-stereo face capture and reflectance modelling."
    )
    parser.add_argument("--version", action="version", version=f"jaxps {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_reconstruct(sub)
    _add_demo(sub)
    _add_report(sub)
    _add_relight(sub)
    return parser


class _Stages:
    """A progress bar over named stages, with wall-clock time per stage."""

    def __init__(self, names: list[str]):
        from tqdm import tqdm

        self.bar = tqdm(total=len(names), unit="stage", file=sys.stderr, leave=False,
                        bar_format="{desc:<28}{bar:20}| {n_fmt}/{total_fmt} [{elapsed}]")
        self.times: dict[str, float] = {}

    def run(self, name: str, fn, *args, **kwargs):
        self.bar.set_description(name)
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        self.times[name] = round(time.perf_counter() - t0, 4)
        self.bar.update()
        return out

    def close(self):
        self.bar.close()


def reconstruct(
    frames,
    out: str,
    *,
    lights=None,
    yale_names: bool = False,
    ambient=None,
    mask=None,
    crop_face: bool = False,
    equalize: bool = False,
    shadow_threshold: float | None = None,
    method: str = "l2",
    integration: str = "fc",
    report: bool = False,
    check_quality: bool = False,
) -> dict:
    """Run the whole pipeline on files and write the outputs to `out`; returns the summary.

    `check_quality`: drop the frames `jaxps.check_frames` flags before solving (named under
    `"dropped_frames"` in the summary)."""
    import jax

    from . import integrate, photometric_stereo, status_counts
    from ._outputs import write_albedo, write_json, write_normal_map, write_ply, write_preview
    from .acquisition import load_capture

    if len(frames) == 1 and os.path.isdir(frames[0]):
        frames = frames[0]
    stages = _Stages(["load", "solve", "integrate", "write"])
    try:
        cap = stages.run("load frames", load_capture, frames, lights=lights,
                         yale_names=yale_names, ambient=ambient, mask=mask, equalize=equalize,
                         crop_face=crop_face, check_quality=check_quality)
        if cap.lights is None:
            raise ValueError("no lights: give --lights FILE or --yale-names")

        def solve():
            res = photometric_stereo(cap.images, cap.lights, mask=cap.mask, method=method,
                                     sample_mask=~cap.saturated,
                                     shadow_threshold=shadow_threshold)
            return jax.block_until_ready(res)

        res = stages.run("photometric stereo", solve)
        ok = np.asarray(res.status == 0)
        height = stages.run("integrate", lambda: np.asarray(
            integrate(res.normals, mask=ok if ok.any() else None, method=integration)))

        def write():
            os.makedirs(out, exist_ok=True)
            normals, albedo = np.asarray(res.normals), np.asarray(res.albedo)
            write_normal_map(os.path.join(out, "normals.png"), normals)
            scale = write_albedo(os.path.join(out, "albedo.png"), albedo)
            np.save(os.path.join(out, "height.npy"), height)
            np.save(os.path.join(out, "status.npy"), np.asarray(res.status))
            faces = write_ply(os.path.join(out, "mesh.ply"), height, ok)
            write_preview(os.path.join(out, "preview.png"), normals, albedo, height, ok,
                          title=f"{cap.names[0]} ... ({len(cap.names)} frames)")
            return scale, faces

        scale, faces = stages.run("write outputs", write)
    finally:
        stages.close()
    summary = {
        "frames": list(cap.names),
        "dropped_frames": list(cap.dropped),
        "lights": np.asarray(cap.lights).round(6).tolist(),
        "size": {"frames": len(cap.names), "height": int(cap.images.shape[1]),
                 "width": int(cap.images.shape[2]),
                 "channels": int(cap.images.shape[3]) if cap.images.ndim == 4 else 1},
        "crop": cap.crop,
        "gains": cap.gains.round(6).tolist(),
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
    if report:
        from .report import lambertian_check_plot, write_report

        summary["lambertian_check"] = lambertian_check_plot(
            cap.images, res.normals, res.albedo, cap.lights, mask=ok,
            path=os.path.join(out, "lambertian_check.png"))
    write_json(os.path.join(out, "summary.json"), summary)
    if report:
        write_report(out)
    return summary


def _cmd_reconstruct(args) -> int:
    if len(args.frames) > 1 and all(os.path.isdir(f) for f in args.frames):
        from ._batch import cli_reconstruct_many

        return cli_reconstruct_many(args)
    summary = reconstruct(
        args.frames, args.out, lights=args.lights, yale_names=args.yale_names,
        ambient=args.ambient, mask=args.mask, crop_face=args.crop_face, equalize=args.equalize,
        shadow_threshold=args.shadow_threshold, method=args.method,
        integration=args.integration, report=args.report, check_quality=args.check_quality,
    )
    if summary["dropped_frames"]:
        print("reconstruct: dropped flagged frames " + ", ".join(summary["dropped_frames"]))
    counts = ", ".join(f"{k} {v}" for k, v in summary["status_counts"].items())
    size = summary["size"]
    print(f"reconstructed {size['frames']} frames of {size['height']}x{size['width']} "
          f"-> {args.out}/ (pixels: {counts})")
    print("timings: " + ", ".join(f"{k} {v:.3f} s" for k, v in summary["timings_s"].items()))
    return 0


def _cmd_demo(args) -> int:
    from . import angular_error, synthetic
    from ._outputs import read_normal_map, write_json
    from .acquisition import read_image
    import cv2
    import jax

    frames_dir = os.path.join(args.out, "frames")
    os.makedirs(frames_dir, exist_ok=True)
    surface = synthetic.face_like(args.size)
    lights = synthetic.scanner_lights(20.0)
    scene = synthetic.render_scene(surface, lights, noise=args.noise,
                                   key=jax.random.key(args.seed))
    ambient = 0.03
    paths = []
    for k, img in enumerate(np.asarray(scene.images)):
        path = os.path.join(frames_dir, f"frame_{k}.png")
        cv2.imwrite(path, np.round(np.clip(img + ambient, 0, 1) * 65535).astype(np.uint16))
        paths.append(path)
    amb_path = os.path.join(frames_dir, "ambient.png")
    cv2.imwrite(amb_path, np.full(img.shape, round(ambient * 65535), np.uint16))
    np.savetxt(os.path.join(frames_dir, "lights.txt"), lights, header=str(len(lights)),
               comments="")
    mask_path = os.path.join(frames_dir, "mask.png")
    cv2.imwrite(mask_path, np.asarray(scene.mask).astype(np.uint8) * 255)

    summary = reconstruct(paths, args.out, lights=os.path.join(frames_dir, "lights.txt"),
                          ambient=amb_path, mask=mask_path)
    normals = read_normal_map(os.path.join(args.out, "normals.png"))
    mask = read_image(mask_path) > 0
    err = np.asarray(angular_error(normals, scene.normals, mask=mask))[mask]
    height = np.load(os.path.join(args.out, "height.npy"))
    truth = np.asarray(scene.height)
    dz = (height - truth)[mask]
    dz -= dz.mean()
    truth_range = float(np.ptp(truth[mask]))
    errors = {
        "angular_median_deg": float(np.median(err)),
        "angular_mean_deg": float(np.mean(err)),
        "height_rms_px": float(np.sqrt(np.mean(dz**2))),
        "height_range_px": truth_range,
        "noise_sd": args.noise,
    }
    summary["errors_vs_truth"] = errors
    write_json(os.path.join(args.out, "summary.json"), summary)
    print(f"demo: synthetic face {args.size}x{truth.shape[1]}, 5 scanner lights, noise "
          f"{args.noise}, 16-bit frames in {frames_dir}/")
    print(f"normals: median angular error {errors['angular_median_deg']:.3f} deg, mean "
          f"{errors['angular_mean_deg']:.3f} deg")
    print(f"height: RMS error {errors['height_rms_px']:.2f} px over a "
          f"{truth_range:.1f} px relief (Frankot-Chellappa)")
    print("timings: " + ", ".join(f"{k} {v:.3f} s" for k, v in summary["timings_s"].items()))
    print(f"outputs: {args.out}/normals.png albedo.png height.npy mesh.ply preview.png "
          "summary.json")
    return 0


def _cmd_report(args) -> int:
    from .report import write_report

    path = write_report(args.run_dir, truth_normals=args.truth_normals,
                        truth_depth=args.truth_depth, intrinsics=args.intrinsics,
                        truth_mask=args.truth_mask, out=args.out)
    print(f"wrote {path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError) as err:
        print(f"jaxps {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
