"""The shared numerical core that every stage builds on.

Per-pixel status codes, sums over the short light axis written for XLA-CPU, 3x3 solves by
cofactors, and a Levenberg–Marquardt for millions of tiny per-pixel problems. Nothing here
knows about images, files or lights.
"""

from ._batched_lm import BatchedLM
from ._status import Status, status_counts

__all__ = ["BatchedLM", "Status", "status_counts"]
