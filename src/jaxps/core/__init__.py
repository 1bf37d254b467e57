"""The shared numerical core that every stage builds on.

Per-pixel status codes, sums over the short light axis written for XLA-CPU, 3x3 solves by
cofactors, and a Levenberg–Marquardt for millions of tiny per-pixel problems. Nothing here
knows about images, files or lights.
"""

import importlib

from ._status import Status, status_counts

__all__ = ["BatchedLM", "Status", "status_counts"]


def __getattr__(name):
    # BatchedLM needs equinox; load it (and it) only when asked for.
    if name == "BatchedLM":
        return importlib.import_module(f"{__name__}._batched_lm").BatchedLM
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
