"""Per-pixel status codes shared by every solver (DESIGN.md: 0 = ok, one code per failure)."""

from __future__ import annotations

import enum

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

__all__ = ["Status", "first_status", "status_counts"]


class Status(enum.IntEnum):
    """Why a pixel's result is (or is not) trustworthy.

    Failed pixels always carry finite outputs: normal ``(0, 0, 1)``, albedo ``0``.
    When several reasons apply, the lowest non-zero code wins (masked before invalid, and so on).
    """

    OK = 0
    MASKED = 1
    INVALID = 2
    DARK = 3
    SATURATED = 4
    TOO_FEW_LIGHTS = 5
    DEGENERATE = 6
    BACKFACING = 7
    NOT_CONVERGED = 8
    AT_BOUND = 9

    @property
    def message(self) -> str:
        return _MESSAGES[self]


_MESSAGES = {
    Status.OK: "solved",
    Status.MASKED: "outside the mask",
    Status.INVALID: "fewer than 3 finite samples (NaN/Inf in the input)",
    Status.DARK: "every sample below the dark threshold",
    Status.SATURATED: "fewer than 3 usable samples once saturated samples are dropped",
    Status.TOO_FEW_LIGHTS: "fewer than 3 usable samples once shadowed samples are dropped",
    Status.DEGENERATE: "the usable lights do not span 3-D (ill-conditioned solve)",
    Status.BACKFACING: "the solved normal faces away from the camera (n_z < 0)",
    Status.NOT_CONVERGED: "an iterative solve hit its step limit",
    Status.AT_BOUND: "a fitted parameter ended at its bound",
}


def status_counts(status) -> dict[str, int]:
    """Count pixels per status name, e.g. ``{"OK": 1200, "MASKED": 40}`` (zero counts omitted).

    `status`: an integer array of `Status` codes of any shape, or a result with a `.status`
    (a `PSResult`, say).
    """
    status = getattr(status, "status", status)
    try:
        codes = np.asarray(status)
    except ValueError:  # e.g. a tuple of arrays of different shapes
        codes = None
    if codes is None or not (np.issubdtype(codes.dtype, np.integer) or codes.dtype == bool):
        raise ValueError(
            "status must be an integer array of Status codes (a result's .status), got "
            f"{type(status).__name__}" + ("" if codes is None else f" of dtype {codes.dtype}"))
    values, counts = np.unique(codes, return_counts=True)
    unknown = [int(v) for v in values if int(v) not in _MESSAGES]
    if unknown:
        raise ValueError(f"status holds codes that are not a Status: {unknown}")
    return {Status(int(v)).name: int(c) for v, c in zip(values, counts)}


def first_status(cases) -> Array:
    """The code of the first true condition in `[(condition, code), ...]`, else `Status.OK`.

    Nested `jnp.where` rather than `jnp.select`: under `vmap`, `select` stacks the conditions
    along a small minor axis and reduces over it, which is several times slower on XLA-CPU.
    """
    status = jnp.int32(Status.OK)
    for condition, code in reversed(cases):
        status = jnp.where(condition, jnp.int32(code), status)
    return status
