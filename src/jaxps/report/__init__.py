"""Outputs that people open: maps, meshes, summaries and the HTML report of a run.

Takes a reconstruction (or a run folder written by `jaxps reconstruct`) and, optionally, ground
truth; gives 16-bit normal maps, albedo PNGs, meshes (textured OBJ, coloured PLY, a point
cloud with normals; `to_trimesh` gives a `trimesh.Trimesh`), JSON summaries, a preview figure
and `report.html` with error maps; `progress_bar` shows a long call's stages on stderr.
"""

from ._figures import lambertian_check_plot
from ._html import write_report
from ._mesh import to_trimesh
from ._progress import progress_bar

__all__ = ["lambertian_check_plot", "progress_bar", "to_trimesh", "write_report"]
