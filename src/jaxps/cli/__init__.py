"""The `jaxps` command line (also `python -m jaxps`): one module per subcommand.

Takes frame files and options; gives output folders (maps, mesh, summaries, reports, relit
images). `reconstruct` is the whole pipeline on one capture's files, callable from Python;
`reconstruct_many` solves many capture folders (also `jaxps.reconstruct_many`).
"""

import importlib

from ._cache import enable_compilation_cache
from ._main import build_parser, console, main

__all__ = ["build_parser", "console", "enable_compilation_cache", "main", "reconstruct", "reconstruct_many", "summary_table"]


def __getattr__(name):
    # The pipeline functions import jax; `jaxps --help` should not wait for it.
    if name in ("reconstruct", "reconstruct_many", "summary_table"):
        return getattr(importlib.import_module(f"{__name__}._reconstruct"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
