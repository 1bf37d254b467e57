"""`jaxps report`: the HTML page of a run folder, with error maps where ground truth is given."""

from __future__ import annotations

from ..report import write_report

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
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
    p.set_defaults(func=run)


def run(args) -> int:
    path = write_report(args.run_dir, truth_normals=args.truth_normals,
                        truth_depth=args.truth_depth, intrinsics=args.intrinsics,
                        truth_mask=args.truth_mask, out=args.out)
    print(f"wrote {path}")
    return 0
