"""The `jaxps` command line (also `python -m jaxps`): one module per subcommand.

Takes frame files and options; gives output folders (maps, mesh, summaries, reports, relit
images). `reconstruct` is the whole pipeline on one capture's files, callable from Python;
`reconstruct_many` solves many capture folders (also `jaxps.reconstruct_many`).
"""

from ._main import build_parser, main
from ._reconstruct import reconstruct, reconstruct_many, summary_table

__all__ = ["build_parser", "main", "reconstruct", "reconstruct_many", "summary_table"]
