"""A progress bar on stderr for the stages of a long call (`core._progress.Stages`)."""

from __future__ import annotations

import logging
import sys

from ..core._progress import ProgressHook


class BarSafeHandler(logging.Handler):
    """Writes the `jaxps` logger's warnings on lines of their own: a progress bar is cleared
    first and drawn again after (`tqdm.write`), where Python's fallback handler wrote them into
    the bar's line."""

    def emit(self, record):
        from tqdm import tqdm

        try:
            tqdm.write(self.format(record), file=sys.stderr)
        except Exception:  # noqa: BLE001  logging must not stop the caller
            self.handleError(record)


def log_above_bars(*, always: bool = False) -> BarSafeHandler | None:
    """Give the `jaxps` logger a `BarSafeHandler` for its warnings, unless it has one, or
    (without `always`, which the `jaxps` commands use) logging is already set up for it: a
    handler on it or an ancestor, the caller's, left alone. Returns the handler added, or
    None."""
    logger = logging.getLogger("jaxps")
    if (any(isinstance(h, BarSafeHandler) for h in logger.handlers)
            or (not always and logger.hasHandlers())):
        return None
    handler = BarSafeHandler(logging.WARNING)
    handler.setFormatter(logging.Formatter("%(message)s"))
    logger.addHandler(handler)
    return handler


def progress_bar(file=None) -> ProgressHook:
    """A `progress=` hook that draws a bar on `file` (default stderr): it names the stage now
    running and its place ("fit wrap_ggx (2/5)"), fills with the stages finished, and is
    cleared when the call ends. One bar per call: make a new one for each call.

    `jaxps reconstruct` and `jaxps relight` show their stages on it; pass one to
    `brdf_photometric_stereo(progress=...)` or `stability.sweep(progress=...)`. While the bar
    is drawn, the `jaxps` logger's warnings are written above it (`BarSafeHandler`) when no
    logging is set up for them; a caller's own handlers are left alone.
    """
    from tqdm import tqdm

    bar, handler = None, None

    def hook(stage: str, done: int, total: int) -> None:
        nonlocal bar, handler
        if bar is None:
            bar = tqdm(total=total, unit="stage", file=sys.stderr if file is None else file,
                       leave=False, bar_format="{desc:<32}{bar:20}| [{elapsed}]")
            handler = log_above_bars()
        bar.update(done - bar.n)
        if stage:
            bar.set_description_str(f"{stage} ({done + 1}/{total})")
        else:
            bar.close()
            if handler is not None:
                logging.getLogger("jaxps").removeHandler(handler)
                handler = None

    return hook
