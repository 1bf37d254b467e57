"""A progress bar on stderr for the stages of a long call (`core._progress.Stages`)."""

from __future__ import annotations

import sys

from ..core._progress import ProgressHook


def progress_bar(file=None) -> ProgressHook:
    """A `progress=` hook that draws a bar on `file` (default stderr): it names the stage now
    running and its place ("fit wrap_ggx (2/5)"), fills with the stages finished, and is
    cleared when the call ends. One bar per call: make a new one for each call.

    `jaxps reconstruct` and `jaxps relight` show their stages on it; pass one to
    `brdf_photometric_stereo(progress=...)` or `stability.sweep(progress=...)`.
    """
    from tqdm import tqdm

    bar = None

    def hook(stage: str, done: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            bar = tqdm(total=total, unit="stage", file=sys.stderr if file is None else file,
                       leave=False, bar_format="{desc:<32}{bar:20}| [{elapsed}]")
        bar.update(done - bar.n)
        if stage:
            bar.set_description_str(f"{stage} ({done + 1}/{total})")
        else:
            bar.close()

    return hook
