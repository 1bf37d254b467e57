"""`jaxps report`: the HTML page of a run folder, with error maps where ground truth is given."""

from __future__ import annotations

from ..report import write_report

__all__ = ["run"]


def run(args) -> int:
    path = write_report(args.run_dir, truth_normals=args.truth_normals,
                        truth_depth=args.truth_depth, intrinsics=args.intrinsics,
                        truth_mask=args.truth_mask, truth_scan=args.truth_scan,
                        out=args.out)
    print(f"wrote {path}")
    return 0
