"""Named stages of long eager work, timed, with a hook that shows them (a progress bar).

The numerical stages print nothing themselves (docs/design.md): a call that takes `progress=`
passes its hook here, and `jaxps.report.progress_bar()` is one such hook.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import jax

ProgressHook = Callable[[str, int, int], None]
"""`hook(stage, done, total)`: called as each stage starts, with the stages finished so far,
and once more at the end with `stage=""` and `done=total`."""


class Stages:
    """Run named stages one after another, timing each, and tell `hook` (if any) about them.

    `times` maps each stage's `time_key` (its name unless given) to its seconds. A stage that
    returns JAX arrays is timed to their completion, so the hook hears of the next stage when
    the work is done rather than when it was dispatched.
    """

    def __init__(self, total: int, hook: ProgressHook | None = None):
        self.total, self.hook, self.done = total, hook, 0
        self.times: dict[str, float] = {}

    def run(self, name: str, fn, *args, time_key: str | None = None, **kwargs):
        if self.hook is not None:
            self.hook(name, self.done, self.total)
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args, **kwargs))
        self.times[name if time_key is None else time_key] = round(time.perf_counter() - t0, 4)
        self.done += 1
        return out

    def close(self):
        if self.hook is not None:
            self.hook("", self.total, self.total)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
