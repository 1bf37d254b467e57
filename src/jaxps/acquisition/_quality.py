"""Frame quality checks: which frames of a capture are corrupt, badly exposed or inconsistent.

A photometric-stereo solve trusts every frame; one corrupt frame (interlace combing, a block of
rows lost in transfer, a flash that did not fire) poisons every pixel. `check_frames` measures
each frame (in numpy: a few reductions per frame), flags frames whose
measures cross documented thresholds, and says which frame and why; `drop_flagged` removes the
flagged frames (and their lights) so the solve uses the K-1 (or fewer) good sources.

Measures per frame (grey mean of the channels, inside `mask` where one is given):
- `comb`: mean $|I_{y} - (I_{y-1} + I_{y+1})/2|$ over mean $|I_{x} - (I_{x-1} + I_{x+1})/2|$,
  the vertical against the horizontal second difference. Natural images give about 1 (1.0-1.5 on
  Yale B); interlaced or row-striped frames give tens.
- `bad_rows`: rows whose mean differs from both neighbouring rows in the same direction (a spike;
  a scene edge is a one-sided step) by more than `row_z` robust standard deviations (1.4826 times
  the median spike) and by more than 0.05.
- `truncated_rows`: rows at the bottom that are exactly constant (how a short read is padded).
  A frame is flagged when it has `max(min_truncated_rows, truncated_fraction * H)` such rows
  more than the median frame of the capture: a few black rows are an ordinary border, and a
  blank surround that every frame shares (a synthetic render, a background clipped to 0 by the
  ambient subtraction) is not a short read, which hits one file. `check_file` finds short
  PGM/PPM files from their headers. A frame of one value throughout is flagged *blank*
  instead: there is no image in it to have been cut short.
- `dark_fraction`, `saturated_fraction`: fractions of pixels below `dark_level` / at or above
  `saturation`; `nonfinite_fraction`. A frame is flagged dark when more than `dark_fraction` of
  its pixels are below `dark_level` and it is dark for the capture too: nearly all of it
  (`dark_all`) is, or its `mean` is below `dark_relative` times the median frame mean. A dark
  surround that every frame shares (an object on black, a face in a dark booth) is not a dark
  frame; a flash that did not fire, or the ambient frame, is.
- `inconsistency`: leave-one-out relative residual of predicting the frame as a linear
  combination of the other (unflagged) frames. Under Lambert's law without shadows every image is
  a linear combination of any three others (Shashua 1992; Belhumeur & Kriegman 1998), so a frame
  that cannot be predicted is corrupt, from another scene, or moved. It is compared with the
  median over the frames (`inconsistency_ratio`); the worst frame is flagged and the rest
  re-measured. It needs 5 unflagged frames and uses a sub-grid of pixels.
"""

from __future__ import annotations

import logging
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from ..lights._directions import validate_lights

__all__ = [
    "FrameCheck",
    "QualityReport",
    "QualityThresholds",
    "check_file",
    "check_frames",
    "drop_flagged",
    "screen_capture",
]


# The smallest frame `check_frames` measures (its row spikes and comb need neighbours).
_MIN_ROWS, _MIN_COLS = 5, 3
# The start of the reason `check_frames` gives a frame that the others do not predict.
INCONSISTENT = "inconsistent with the other frames"


class QualityThresholds(NamedTuple):
    """Where a frame measure becomes a flag (defaults chosen on Yale B and psm, see docs)."""

    comb: float = 3.0
    row_z: float = 8.0
    max_bad_rows: int = 0
    min_truncated_rows: int = 8
    truncated_fraction: float = 0.05
    dark_level: float = 0.02
    dark_fraction: float = 0.8
    saturation: float = 0.99
    saturated_fraction: float = 0.1
    inconsistency_ratio: float = 4.0
    inconsistency_min: float = 0.1
    dark_all: float = 0.99
    dark_relative: float = 0.25


class FrameCheck(NamedTuple):
    """One frame's verdict: `index`, `name`, `reasons` (empty if clean), `measures`."""

    index: int
    name: str
    reasons: tuple[str, ...]
    measures: dict

    @property
    def flagged(self) -> bool:
        return bool(self.reasons)


class QualityReport(NamedTuple):
    """Per-frame verdicts of `check_frames`, in frame order."""

    frames: tuple[FrameCheck, ...]

    @property
    def keep(self) -> np.ndarray:
        """`(K,)` bool: frames with no flag."""
        return np.array([not f.flagged for f in self.frames], bool)

    @property
    def flagged(self) -> tuple[FrameCheck, ...]:
        return tuple(f for f in self.frames if f.flagged)

    def summary(self) -> str:
        """One line per flagged frame, `name: reason; reason`, or a line saying all are clean."""
        if not self.flagged:
            return f"all {len(self.frames)} frames passed the quality checks"
        lines = [f"{len(self.flagged)} of {len(self.frames)} frames flagged:"]
        lines += [f"  {f.name}: {'; '.join(f.reasons)}" for f in self.flagged]
        return "\n".join(lines)


def _measures(grey, mask, dark_level, saturation):
    """Per-frame measures of `(K, H, W)` numpy grey frames inside the `(H, W)` bool `mask`, in numpy:
    a dict of `(K,)` scalars, the `(K, H)` masked row means and which rows are constant
    (finished by `_row_measures`). numpy, not a jitted kernel: the XLA-CPU version's many
    reductions ran slowly, and a fresh process paid its tracing, compiling or loading too. The
    "load frames" stage of `benchmarks/bench_cli.py` at 1 MP fell from 0.46 to 0.28 s (warm)
    and 0.76 to 0.28 s (first run) with this change and the L2 one (docs/speed.md)."""
    k, h, _ = grey.shape
    dtype = grey.dtype
    m = mask.astype(dtype)
    n = max(int(np.count_nonzero(mask)), 1)
    row_n = np.maximum(m.sum(axis=1), 1)
    # Comb: vertical vs horizontal second differences over pixels whose 3x3 cross is in the mask.
    cross = (mask[1:-1, 1:-1] & mask[:-2, 1:-1] & mask[2:, 1:-1] & mask[1:-1, :-2]
             & mask[1:-1, 2:]).astype(dtype).ravel()
    out = {key: np.empty(k, dtype) for key in
           ("comb", "dark_fraction", "mean", "saturated_fraction", "nonfinite_fraction")}
    out["rows"], out["const_rows"] = np.empty((k, h), dtype), np.empty((k, h), bool)
    for i, frame in enumerate(grey):
        finite = np.isfinite(frame)
        x = frame if finite.all() else np.where(finite, frame, 0)
        out["nonfinite_fraction"][i] = np.count_nonzero(~finite & mask) / n
        out["dark_fraction"][i] = np.count_nonzero((x < dark_level) & mask) / n
        out["saturated_fraction"][i] = np.count_nonzero((x >= saturation) & mask) / n
        rows = np.einsum("hw,hw->h", x, m)
        out["rows"][i], out["mean"][i] = rows / row_n, rows.sum() / n
        centre = x[1:-1, 1:-1]
        dy = np.abs(centre - 0.5 * (x[:-2, 1:-1] + x[2:, 1:-1])).ravel()
        dx = np.abs(centre - 0.5 * (x[1:-1, :-2] + x[1:-1, 2:])).ravel()
        out["comb"][i] = (dy @ cross) / max(dx @ cross, 1e-6)
        # rows that are constant and equal to the frame's last pixel
        out["const_rows"][i] = np.all(x == x[-1, 0], axis=1) & np.all(finite, axis=1)
    return out


def _row_measures(rows, const_rows, row_n, row_z):
    """`(bad_rows, truncated_rows)` per frame from `(K, H)` masked row means, constant-row
    flags and the `(H,)` mask count per row, in numpy: a few thousand numbers, whose traced
    median, cumulative product and shifts took a fresh process longer to trace and lower than
    to run (the "load frames" stage of `benchmarks/bench_cli.py`, docs/speed.md).

    Row spikes: a row that differs from BOTH neighbouring rows in the same direction (an edge
    in the scene is a step, one-sided; a corrupt row is a spike, two-sided), by more than
    `row_z` robust standard deviations of the frame's spikes and by more than 0.05.
    Truncation: the trailing rows that are constant (`const_rows`)."""
    up = rows - np.concatenate([rows[:, :1], rows[:, :-1]], axis=1)  # the row above (edge kept)
    down = rows - np.concatenate([rows[:, 1:], rows[:, -1:]], axis=1)
    spike = np.where(up * down > 0, np.minimum(np.abs(up), np.abs(down)), 0)
    valid = row_n >= max(0.25 * float(np.max(row_n)), 1.0)
    valid[0] = valid[-1] = False
    if valid.any():
        scale = np.maximum(1.4826 * np.median(np.abs(spike[:, valid]), axis=1), 1e-3)
    else:  # no row to judge
        scale = np.full(len(rows), np.inf)
    bad = valid & (spike > row_z * scale[:, None]) & (spike > 0.05)
    truncated = np.cumprod(const_rows[:, ::-1], axis=1).sum(axis=1)
    return bad.sum(axis=1), truncated


def _gram(x):
    """`(K, K)` Gram matrix of `(K, P)` samples, non-finite ones as 0 (numpy: a few thousand
    pixels, and one XLA program fewer to trace and load in a fresh process)."""
    x = np.where(np.isfinite(x), x, 0)
    return x @ x.T


def _inconsistency(grey, mask, candidates, max_pixels=20000):
    """Leave-one-out relative residual of each candidate frame predicted from the others."""
    k = grey.shape[0]
    out = np.full(k, np.nan)
    idx = np.flatnonzero(candidates)
    if len(idx) < 4:
        return out
    sel = np.asarray(mask, bool)
    stride = max(1, int(np.ceil(np.sqrt(sel.sum() / max_pixels))))
    sub = np.asarray(sel[::stride, ::stride])
    x = grey[:, ::stride, ::stride][:, sub]  # (K, P)
    g = np.asarray(_gram(x[idx]), np.float64)
    for a, f in enumerate(idx):
        others = [b for b in range(len(idx)) if b != a]
        goo = g[np.ix_(others, others)]
        goo = goo + 1e-9 * np.trace(goo) / len(others) * np.eye(len(others))
        gof = g[others, a]
        c = np.linalg.solve(goo, gof)
        res2 = max(g[a, a] - gof @ c, 0.0)
        out[f] = np.sqrt(res2 / max(g[a, a], 1e-30))
    return out


def flag_inconsistent(grey, mask, candidates, thresholds=None):
    """Leave-one-out consistency of the `(K, H, W)` numpy `grey` frames inside `mask`, one
    frame at a time among the `(K,)` bool `candidates`: flag the worst frame if it stands out,
    then re-measure the rest. Each frame must be predicted from at least 4 others (3 others
    may have coplanar lights and predict nothing), so this needs 5 candidates.

    `thresholds`: a `QualityThresholds` (default: the defaults).

    **Returns:** `(flagged, inconsistency)`: frame index -> reason (it starts with
    `INCONSISTENT`), and the `(K,)` leave-one-out residuals (NaN where not measured).
    """
    t = QualityThresholds() if thresholds is None else thresholds
    candidates = np.array(candidates, bool)
    flagged, incons = {}, np.full(grey.shape[0], np.nan)
    while candidates.sum() >= 5:
        current = _inconsistency(grey, mask, candidates)
        incons = np.where(candidates, current, incons)
        typical = float(np.nanmedian(current))
        worst = int(np.nanargmax(current))
        if current[worst] <= max(t.inconsistency_ratio * typical, t.inconsistency_min):
            break
        flagged[worst] = (f"{INCONSISTENT}: leave-one-out residual {current[worst]:.2f} vs "
                          f"median {typical:.2f}")
        candidates[worst] = False
    return flagged, incons


def check_frames(
    frames: Float[ArrayLike, "K H W *C"],
    *,
    names: list[str] | None = None,
    mask: Bool[ArrayLike, "H W"] | None = None,
    thresholds: QualityThresholds = QualityThresholds(),
) -> QualityReport:
    """Flag corrupt, badly exposed and inconsistent frames of one capture (see module notes).

    **Arguments:**
    - `frames`: `(K, H, W)` or `(K, H, W, C)` floating point in [0, 1] (ambient-subtracted or
      raw; use the raw frames to judge saturation).
    - `names`: `K` frame names for the report (default `frame 0`, `frame 1`, ...).
    - `mask`: `(H, W)` bool region to judge (e.g. the face); default the whole frame.
    - `thresholds`: a `QualityThresholds`.

    **Returns:** a `QualityReport`; `.keep` is the `(K,)` bool of unflagged frames and
    `.summary()` a readable list of what was flagged and why.
    """
    if not isinstance(frames, jax.Array):
        # Host stacks stay on the host: the jitted measures read them in place (64-byte
        # aligned, as `load_capture` makes them), and in a fresh process `jnp.asarray` traced
        # and lowered a copy of the stack first. Likewise the mask test and the thresholds
        # below are numpy, not small XLA programs of their own.
        frames = np.asarray(frames)
    if not jnp.issubdtype(frames.dtype, jnp.floating) or frames.ndim not in (3, 4):
        raise ValueError(
            f"frames must be floating (K, H, W) or (K, H, W, C), got {frames.shape} {frames.dtype}"
        )
    if frames.dtype.itemsize < 4:  # float16, bfloat16: numpy's einsum takes no bfloat16
        frames = frames.astype(np.float32)
    k, h, w = frames.shape[:3]
    if h < _MIN_ROWS or w < _MIN_COLS:
        raise ValueError(f"frames must be at least {_MIN_ROWS}x{_MIN_COLS} pixels, got {h}x{w}")
    if not isinstance(thresholds, QualityThresholds):
        raise TypeError(f"thresholds must be a QualityThresholds (the defaults: "
                        f"QualityThresholds()), got {type(thresholds).__name__}")
    bad = [f"{name}={value!r}" for name, value in thresholds._asdict().items()
           if not (np.isfinite(value) and value >= 0
                   and (value <= 1 or not name.endswith(("fraction", "all", "level"))))]
    if bad:
        raise ValueError(f"thresholds must be finite and >= 0, and the fractions and levels "
                         f"at most 1; got {', '.join(bad)}")
    names = [f"frame {i}" for i in range(k)] if names is None else [str(n) for n in names]
    if len(names) != k:
        raise ValueError(f"names has {len(names)} entries for K={k} frames")
    sel = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    if sel.shape != (h, w):
        raise ValueError(f"mask must have shape {(h, w)}, got {sel.shape}")
    if not sel.any():
        raise ValueError("mask is empty")
    # on the host once: the measures and the consistency test below are numpy
    grey = np.asarray(frames if frames.ndim == 3 else frames.mean(axis=-1))
    t = thresholds
    dt = grey.dtype
    meas = _measures(grey, sel, *(np.asarray(v, dt) for v in (t.dark_level, t.saturation)))
    meas["bad_rows"], meas["truncated_rows"] = _row_measures(
        meas.pop("rows"), meas.pop("const_rows"), sel.sum(axis=1, dtype=np.float32), t.row_z)

    reasons: list[list[str]] = [[] for _ in range(k)]
    typical = float(np.median(meas["mean"]))  # the capture's usual frame brightness
    blank = float(np.median(meas["truncated_rows"]))  # constant bottom rows every frame has
    for i in range(k):
        mi = {key: float(v[i]) for key, v in meas.items()}
        if mi["nonfinite_fraction"] > 0:
            reasons[i].append(f"non-finite values in {mi['nonfinite_fraction']:.1%} of pixels")
        if mi["truncated_rows"] - blank >= max(t.min_truncated_rows, t.truncated_fraction * h):
            if mi["truncated_rows"] >= h:  # one value throughout: no image to cut short
                reasons[i].append(f"blank: every pixel {float(grey[i][-1, 0]):.3g} (an empty "
                                  "frame, or a frame with itself subtracted as the ambient)")
            else:
                reasons[i].append(
                    f"truncated: last {int(mi['truncated_rows'])} rows constant (short read; "
                    f"the median frame has {blank:g})")
        if mi["comb"] > t.comb:
            reasons[i].append(
                f"row/interlace artefact: vertical/horizontal second difference "
                f"{mi['comb']:.1f} > {t.comb}")
        elif mi["bad_rows"] > t.max_bad_rows:
            reasons[i].append(f"corrupt rows: {int(mi['bad_rows'])} rows jump away from their "
                              "neighbours")
        if mi["dark_fraction"] > t.dark_fraction and (
                mi["dark_fraction"] > t.dark_all or mi["mean"] < t.dark_relative * typical):
            reasons[i].append(
                f"dark: {mi['dark_fraction']:.0%} of pixels below {t.dark_level}, mean "
                f"{mi['mean']:.3g} against a median frame mean of {typical:.3g}")
        if mi["saturated_fraction"] > t.saturated_fraction:
            reasons[i].append(
                f"saturated: {mi['saturated_fraction']:.0%} of pixels at or above "
                f"{t.saturation}")
    flagged, incons = flag_inconsistent(grey, sel, np.array([not r for r in reasons], bool),
                                        t)
    for i, reason in flagged.items():
        reasons[i].append(reason)
    checks = []
    for i in range(k):
        mi = {key: float(v[i]) for key, v in meas.items()}
        mi["inconsistency"] = float(incons[i])
        checks.append(FrameCheck(i, names[i], tuple(reasons[i]), mi))
    return QualityReport(tuple(checks))


def drop_flagged(
    frames: Float[ArrayLike, "K H W *C"],
    lights: Float[ArrayLike, "K 3"],
    report: QualityReport,
    *,
    min_frames: int = 3,
):
    """Remove the frames `report` flagged, with their lights.

    **Returns:** `(frames, lights, kept)` with `kept` the `(K',)` indices of the kept frames.

    **Raises:** `ValueError` listing every flagged frame and why when fewer than `min_frames`
    remain (e.g. every frame flagged), or when `report` does not match `frames` or
    `min_frames` is not a positive int.
    """
    if not (isinstance(min_frames, (int, np.integer)) and min_frames >= 1):
        raise ValueError(f"min_frames must be an int >= 1 (frames to keep), got {min_frames!r}")
    frames = jnp.asarray(frames)
    lights_arr = jnp.asarray(lights)
    k = frames.shape[0]
    if len(report.frames) != k or lights_arr.shape[0] != k:
        raise ValueError(
            f"report covers {len(report.frames)} frames and lights {lights_arr.shape[0]}, "
            f"but frames has K={k}")
    kept = np.flatnonzero(report.keep)
    if len(kept) < min_frames:
        raise ValueError(
            f"frames: only {len(kept)} of {k} frames passed the quality checks, need at least "
            f"{min_frames}.\n{report.summary()}")
    return frames[kept], lights_arr[kept], kept


def check_file(path: str | os.PathLike) -> str | None:
    """Why an image file cannot be trusted (unreadable, or a binary PGM/PPM shorter than its
    header says), or `None` if it looks whole."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        return "missing file"
    with open(path, "rb") as f:
        data = f.read()
    if data[:2] in (b"P5", b"P6"):
        fields, pos = [], 2
        while len(fields) < 3 and pos < len(data):
            while pos < len(data) and data[pos:pos + 1].isspace():
                pos += 1
            if data[pos:pos + 1] == b"#":
                while pos < len(data) and data[pos:pos + 1] not in (b"\n", b"\r"):
                    pos += 1
                continue
            start = pos
            while pos < len(data) and not data[pos:pos + 1].isspace():
                pos += 1
            fields.append(data[start:pos])
        try:
            w, h, maxval = (int(v) for v in fields)
        except ValueError:
            return "unreadable PGM/PPM header"
        channels = 3 if data[:2] == b"P6" else 1
        need = w * h * channels * (2 if maxval > 255 else 1)
        have = len(data) - (pos + 1)
        if have < need:
            return f"truncated: {have} of {need} pixel bytes"
        return None
    import cv2

    if cv2.imread(path, cv2.IMREAD_UNCHANGED) is None:
        return "unreadable image"
    return None


_LOG = logging.getLogger("jaxps")


def only_inconsistent(check: FrameCheck) -> bool:
    """Whether `check`'s only flag is the leave-one-out one: the frame is whole and well
    exposed, but the other frames do not predict it (it may have moved)."""
    return bool(check.reasons) and all(r.startswith(INCONSISTENT) for r in check.reasons)


def screen_capture(images, saturated, names, lights, mask=None, spare_inconsistent=False):
    """The acquisition hook (`load_capture(..., check_quality=True)`): check the frames, log
    what was flagged and why (logger `"jaxps"`, level WARNING), and drop flagged frames.

    With `spare_inconsistent`, frames flagged only as inconsistent (`only_inconsistent`) are
    kept: a frame that moved is inconsistent, and `load_capture` undoes the motion first and
    then checks them again.

    **Returns:** `(images, saturated, names, lights, report)` with the flagged frames removed;
    frames too small for `check_frames` are logged and returned unchecked (`report` None).

    **Raises:** `ValueError` listing every flagged frame when fewer than 3 frames remain.
    """
    h, w = np.shape(images)[1:3]
    if h < _MIN_ROWS or w < _MIN_COLS:
        _LOG.warning("frames of %dx%d pixels are too small for the quality checks; not checked",
                     h, w)
        return images, saturated, names, lights, None
    report = check_frames(np.asarray(images), names=list(names), mask=mask)
    spared = [f for f in report.flagged if spare_inconsistent and only_inconsistent(f)]
    if report.flagged:
        _LOG.warning("%s%s", report.summary(), "".join(
            f"\n  {f.name}: kept for now, to be checked again once the frames' motion is undone"
            for f in spared))
    kept = np.flatnonzero([f in spared or not f.flagged for f in report.frames])
    if len(kept) < 3:
        raise ValueError(
            f"frames: only {len(kept)} of {len(names)} frames passed the quality checks, need "
            f"at least 3.\n{report.summary()}")
    _check_span(lights, kept, names, report)
    return (images[kept], saturated[kept], tuple(names[i] for i in kept),
            None if lights is None else lights[kept], report)


def _span_error(lights, keep) -> str | None:
    """Why the lights of the frames `keep` selects cannot determine a normal (None when they
    can, or when there are no lights to judge)."""
    if lights is None:
        return None
    try:
        validate_lights(np.asarray(lights)[keep])
    except ValueError as err:
        return str(err)
    return None


def lights_span(lights, keep) -> bool:
    """Whether the lights of the frames `keep` selects can determine a normal (True when
    there are no lights to judge)."""
    return _span_error(lights, keep) is None


def _check_span(lights, kept, names, report):
    """Raise when the frames kept have lights that cannot determine a normal (e.g. the three
    left of a cross of five once both side frames are dropped), naming what was dropped,
    instead of letting the solve fail on lights the caller never chose."""
    err = None if len(kept) == len(names) else _span_error(lights, kept)
    if err is not None:
        raise ValueError(
            f"frames: the {len(kept)} frames that passed the quality checks "
            f"({', '.join(names[i] for i in kept)}) are lit from directions that cannot "
            f"determine a normal ({err}).\n{report.summary()}\nTo solve with every frame, "
            "flagged ones included, turn the checks off (check_quality=False; "
            "--no-check-quality).")
