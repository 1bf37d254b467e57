"""Outputs that people open: maps, meshes, summaries and the HTML report of a run.

Takes a reconstruction (or a run folder written by `jaxps reconstruct`) and, optionally, ground
truth; gives 16-bit normal maps, albedo PNGs, PLY meshes, JSON summaries, a preview figure and
`report.html` with error maps.
"""

from ._figures import lambertian_check_plot
from ._html import write_report

__all__ = ["lambertian_check_plot", "write_report"]
