"""The command line's parser: one function per subcommand, and the options they share.

argparse only, no jax or jaxps import, so that `jaxps --help` answers at once; `_main` imports
a subcommand's module (named by `module` in the parsed arguments) only to run it.
"""

from __future__ import annotations

import argparse

# jaxps.INTENSITY_METHODS, PS_METHODS and INTEGRATION_METHODS, repeated so that building the
# parser imports no jax (a test checks that they agree).
INTENSITY_METHODS = ("none", "mean", "frontal", "semi_calibrated")
PS_METHODS = ("l2", "l1", "barsky", "irls", "sbl", "semi_calibrated", "oren_nayar")
INTEGRATION_METHODS = ("fc", "dct", "lsq", "bilateral", "auto")

__all__ = ["add_decoding_args", "add_intensity_args", "add_light_args", "add_register_arg",
           "calibrate_parser", "demo_parser", "reconstruct_parser", "relight_parser",
           "report_parser"]


def add_register_arg(p) -> None:
    p.add_argument("--no-register", dest="register", action="store_false",
                   help="use the frames where they are; by default motion between frames "
                   "(from 0.5 px up to 4 px per 168 px of the frame, against the frame lit "
                   "closest to the view axis) is measured and undone, and a frame that moved "
                   "further is dropped (see load_capture)")


def add_intensity_args(p) -> None:
    """How each frame's flash strength is estimated and divided out (`load_capture`)."""
    p.add_argument("--intensities", default="frontal", choices=INTENSITY_METHODS,
                   help="per-frame light intensity estimate divided out before solving "
                   "(default frontal: mean equalisation corrected for each light's obliquity; "
                   "see load_capture)")
    p.add_argument("--no-equalize", dest="intensities", action="store_const", const="none",
                   help="use the frames as read (same as --intensities none)")
    p.add_argument("--equalize", dest="intensities", action="store_const", const="mean",
                   help="plain mean equalisation (same as --intensities mean)")
    p.add_argument("--intensity-mask", metavar="MASK",
                   help="mask image (full frame) of a flat, matte reference target in view, "
                   "fixed to the scanner: each frame's flash strength is measured on it "
                   "instead of on the face (frontal or mean; see load_capture)")
    p.add_argument("--intensity-normal", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="the reference target's normal in the camera frame (default 0 0 1: "
                   "facing the camera)")
    p.add_argument("--intensity-ratios", metavar="FILE",
                   help="with --intensity-mask: per frame, the flash at the subject's place over "
                   "the flash at the target (one number per line), which near lights make differ "
                   "from lamp to lamp; 'jaxps calibrate --board' writes it")


def add_light_args(p, near=False) -> None:
    """The options every frame-reading subcommand shares: where lights come from, ambient;
    with `near`, also near point lights (`--light-positions`, `--pixel-size`)."""
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--lights", help="lights.txt: optional count line, then 'x y z' per frame; "
                   "'auto': the .txt file named *light* in each folder of frames (one per "
                   "capture)")
    g.add_argument("--yale-names", action="store_true",
                   help="parse lights from Yale B names (..._P00A+035E+15.pgm: azimuth +35, "
                   "elevation +15 degrees; a rig's own frames may be named A+035E+15.png)")
    if near:
        g.add_argument("--light-positions", metavar="FILE",
                       help="near lamps: 'x y z' per frame in mm, camera frame, origin at the "
                       "frame's centre at the subject's mean depth; solved by "
                       "near_photometric_stereo (needs --pixel-size)")
        p.add_argument("--pixel-size", type=float, metavar="MM",
                       help="with --light-positions: the size of a pixel at the subject, mm")
    p.add_argument("--ambient", help="ambient-only control frame to subtract; 'auto': the "
                   "file named *ambient* in each folder of frames (one per capture)")
    add_decoding_args(p)


def add_decoding_args(p) -> None:
    """How the files' codes become radiance: `--bits` and `--linearize` (see `read_image`)."""
    p.add_argument("--bits", type=int, metavar="N",
                   help="the camera's bit depth, for 16-bit PNG/TIFF files that hold its codes "
                   "unscaled (e.g. 12: 4095 is full scale and saturated); PGM headers say it "
                   "themselves")
    p.add_argument("--linearize", choices=("auto", "srgb", "none"), default="auto",
                   help="auto (default): decode 8-bit PNG/JPEG files from sRGB, read PGM, TIFF "
                   "and 16-bit files as linear; none: read every file as linear (a camera "
                   "that writes its linear codes to 8-bit PNGs); srgb: decode every file")


def reconstruct_parser(sub) -> None:
    p = sub.add_parser(
        "reconstruct",
        help="frames -> normals, albedo, height, meshes and a JSON summary",
        description="Reconstruct normals, albedo and a height map from a photometric-stereo "
        "frame stack, and write normals.png (16-bit, n = v/65535*2-1), albedo.png, height.npy, "
        "mesh.ply (binary, vertex colours from the albedo), preview.png and summary.json to "
        "--out; with --obj also mesh.obj with mesh.mtl and the albedo as texture.png, with "
        "--points points.ply (point cloud with normals). "
        "Several capture folders: each capture's files in OUT/<folder>/ (all but the report), "
        "summary.json and summary.csv. Exit status 2 for bad input, 1 when a capture has no "
        "pixel solved (its files are written all the same) or, with several, fails.",
    )
    p.add_argument("frames", nargs="+", help="a folder of frames, or the frame files in order "
                   "(a multi-page TIFF: its pages; one page: FILE.tif[N]); several folders are "
                   "several captures (one progress bar, a summary table)")
    p.add_argument("--check-quality", action=argparse.BooleanOptionalAction, default=True,
                   help="drop frames flagged by jaxps.check_frames (corrupt, badly exposed or "
                   "inconsistent) before solving (default; --no-check-quality keeps every frame)")
    add_light_args(p, near=True)
    p.add_argument("--mask", help="mask image (non-zero inside), or 'auto' (from the mean image)")
    p.add_argument("--crop-face", action="store_true", help="crop to the Haar-detected face")
    add_intensity_args(p)
    add_register_arg(p)
    p.add_argument("--shadow-threshold", type=float, default=None,
                   help="drop samples below this intensity from each pixel's solve")
    p.add_argument("--method", default="l2", choices=PS_METHODS,
                   help="photometric-stereo method (default l2: on five-light faces no robust "
                   "method was more accurate; barsky suits strong, sharp highlights; "
                   "docs/captures.md)")
    p.add_argument("--integration", default="lsq", choices=INTEGRATION_METHODS,
                   help="integration method (default lsq: least squares on the mask, which "
                   "bends real faces less than fc, the seeds' Frankot-Chellappa; "
                   "docs/integration.md)")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--report", action="store_true",
                   help="also write lambertian_check.png and report.html (see 'jaxps report')")
    p.add_argument("--obj", action="store_true",
                   help="also write the textured mesh: mesh.obj, mesh.mtl, texture.png (a text "
                   "format: about 7 s and 200 MB at 1280x1024)")
    p.add_argument("--points", action="store_true",
                   help="also write points.ply, a point cloud with normals")
    p.set_defaults(module="_reconstruct")


def demo_parser(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="render a synthetic face capture with known truth, reconstruct it, print errors",
        description="Render a face-like surface under five scanner-like lights (16-bit PNG "
        "frames, an ambient frame and lights.txt in OUT/frames), run the same pipeline as "
        "'jaxps reconstruct' on those files, and compare with the known truth.",
    )
    p.add_argument("--out", default="jaxps-demo", help="output folder (default: jaxps-demo)")
    p.add_argument("--size", type=int, default=320, help="image height in pixels (default 320)")
    p.add_argument("--width", type=int, default=None,
                   help="image width in pixels (default 0.8 x --size)")
    p.add_argument("--noise", type=float, default=0.005,
                   help="Gaussian noise s.d. in [0, 1] units (default 0.005)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(module="_demo")


def report_parser(sub) -> None:
    p = sub.add_parser(
        "report",
        help="an HTML page for a run folder: maps, error maps against ground truth, timings",
        description="Write RUN_DIR/report.html (figures in RUN_DIR/report_files/) for a folder "
        "written by 'jaxps reconstruct': normal map, albedo, shaded height, status, the "
        "Lambertian check plot if the run has one, timings; with ground truth, error maps.",
    )
    p.add_argument("run_dir", help="a folder written by 'jaxps reconstruct'")
    p.add_argument("--truth-normals", help="ground-truth normal map PNG (16-bit, same grid)")
    truth = p.add_mutually_exclusive_group()
    truth.add_argument("--truth-depth", help="ground-truth depth (.npz key depth_gt, or .npy)")
    truth.add_argument("--truth-scan", metavar="FILE",
                       help="ground-truth scan: a mesh (.ply, .obj, .stl, .off, .glb), points "
                       "(.xyz/.txt/.csv: x y z [nx ny nz] per line) or a range image (.abs) in "
                       "any unit, axes roughly the camera's (x right, y up, z toward it); "
                       "aligned by scaled ICP")
    p.add_argument("--intrinsics", help="K.txt camera matrix for --truth-depth")
    p.add_argument("--truth-mask", help="mask image for the ground truth")
    p.add_argument("--out", help="HTML path (default RUN_DIR/report.html)")
    p.set_defaults(module="_report")


def relight_parser(sub) -> None:
    p = sub.add_parser(
        "relight",
        help="fit a BRDF to the frames and render the face under new lights",
        description="Photometric stereo on the frames, then fit_brdf (default wrap_ggx: wrap "
        "diffuse + GGX specular lobe, normals refined jointly; see docs/brdf.md), then "
        "write relit PNGs for each --light, relight.gif (a light circling the face) and "
        "relight.json (fit report) to --out.",
    )
    p.add_argument("frames", nargs="+", help="a folder of frames, or the frame files in order "
                   "(a multi-page TIFF: its pages; one page: FILE.tif[N])")
    add_light_args(p, near=True)
    p.add_argument("--mask", default="auto", help="mask image, or 'auto' (default)")
    p.add_argument("--crop-face", action="store_true",
                   help="crop to the Haar-detected face (the relit images are of the crop)")
    p.add_argument("--method", default="wrap_ggx",
                   help="BRDF model (jaxps.BRDF_METHODS; default wrap_ggx, see docs/brdf.md)")
    p.add_argument("--check-quality", action=argparse.BooleanOptionalAction, default=True,
                   help="drop frames flagged by jaxps.check_frames (e.g. interlace-combed) "
                   "before fitting (default; --no-check-quality keeps every frame)")
    add_intensity_args(p)
    add_register_arg(p)
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
    p.set_defaults(module="_relight")


def calibrate_parser(sub) -> None:
    p = sub.add_parser(
        "calibrate",
        help="a mirror sphere's frames -> lights.txt for 'jaxps reconstruct --lights'",
        description="Find each light's highlight on a mirror (chrome) sphere, one frame per "
        "light in firing order, and write its direction (the reflection of the view) to "
        "OUT/lights.txt, with calibration.json (sphere, highlights, angles) and "
        "calibration.png. A frame without a highlight inside the mask is an error.",
    )
    p.add_argument("frames", nargs="+", help="a folder of frames, or the frame files in order "
                   "(a multi-page TIFF: its pages; one page: FILE.tif[N])")
    p.add_argument("--mask", required=True,
                   help="the sphere's silhouette (image, non-zero inside; an anti-aliased edge "
                   "refines the centre and radius)")
    p.add_argument("--ambient", help="ambient-only frame to subtract; 'auto': the file named "
                   "*ambient* in the folder of frames")
    add_decoding_args(p)
    p.add_argument("--level", type=float, default=0.5,
                   help="a highlight is the pixels at or above LEVEL x the frame's brightest on "
                   "the sphere, weighted by their height above that level (default 0.5)")
    p.add_argument("--reference", metavar="LIGHTS",
                   help="a lights.txt to compare with (e.g. the previous calibration): the "
                   "angle to each of its lights is printed and kept in calibration.json")
    p.add_argument("--board", nargs="+", metavar="FRAMES",
                   help="a reference target's one-time calibration for near lights: frames of a "
                   "flat, matte board at the subject's place, one per light in the sphere's "
                   "order, with the target in view; writes OUT/intensity_ratios.txt for "
                   "'jaxps reconstruct --intensity-ratios' (needs --board-mask and "
                   "--intensity-mask)")
    p.add_argument("--board-mask", metavar="MASK", help="the board's mask (with --board)")
    p.add_argument("--board-normal", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="the board's normal (default 0 0 1: facing the camera)")
    p.add_argument("--intensity-mask", metavar="MASK",
                   help="the reference target's mask (full frame), as for 'jaxps reconstruct'")
    p.add_argument("--intensity-normal", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="the reference target's normal (default 0 0 1: facing the camera)")
    p.add_argument("--tolerance", type=float, metavar="DEG",
                   help="with --reference: exit with status 1 (outputs still written) when a "
                   "light moved more than DEG degrees, naming it")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.set_defaults(module="_calibrate")
