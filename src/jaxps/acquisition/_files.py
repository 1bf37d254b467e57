"""Frames from files: PGM/PNG/TIFF/BMP, 8- or 16-bit, grey or colour, to linear float32 in [0, 1].

Intensities follow DESIGN.md: 8-bit / 255, 16-bit / 65535, linear in radiance; gamma-encoded
sources (8-bit PNG/JPEG by default) are decoded from sRGB. Two refinements of the full scale: a
PGM or PPM is divided by the maxval of its header, and `bits=` names a camera's bit depth
for files that hold, say, 12-bit codes in 16-bit pixels. A multi-page TIFF, as a high-speed
camera may write a capture, stands for its pages, each named as `stack.tif[2]` (page 2,
counted from 0). OpenCV is imported on the first read.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from jaxtyping import Bool, Float

from ..core._host import aligned_empty

__all__ = ["FRAME_EXTENSIONS", "list_frames", "load_stack", "read_image", "read_mask"]

FRAME_EXTENSIONS = (".pgm", ".ppm", ".png", ".tif", ".tiff", ".bmp")
_SRGB_EXTENSIONS = (".png", ".jpg", ".jpeg")
# Files in a frame folder whose names contain these words are not frames.
_NOT_FRAMES = re.compile(r"mask|ambient", re.IGNORECASE)
# A page of a multi-page TIFF: "stack.tif[2]".
_PAGE = re.compile(r"^(?P<file>.+\.tiff?)\[(?P<page>\d+)\]$", re.IGNORECASE)

PathLike = str | os.PathLike


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_frames(folder: PathLike) -> list[str]:
    """Frame files in `folder` (PGM/PPM/PNG/TIFF/BMP), in natural order (``x.2`` before ``x.10``).

    Files whose names contain "mask" or "ambient" are skipped: pass those explicitly. A
    multi-page TIFF stands for its pages, in order (``stack.tif[0]``, ``stack.tif[1]``, ...).

    **Raises:** `FileNotFoundError` if `folder` does not exist or holds no frame file.
    """
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"frame folder not found: {folder}")
    names = [
        n for n in os.listdir(folder)
        if n.lower().endswith(FRAME_EXTENSIONS) and not _NOT_FRAMES.search(n)
    ]
    if not names:
        raise FileNotFoundError(
            f"no frame files ({', '.join(FRAME_EXTENSIONS)}) in folder {folder}"
        )
    return [p for n in sorted(names, key=_natural_key) for p in _pages(os.path.join(folder, n))]


def _frame_paths(frames) -> list[str]:
    """The frames of `frames`: a folder (`list_frames`), one file or a list of files, each
    multi-page TIFF file standing for its pages (`_pages`)."""
    if isinstance(frames, (str, os.PathLike)):
        if os.path.isdir(frames):
            return list_frames(frames)
        frames = [frames]
    return [p for f in frames for p in _pages(os.fspath(f))]


def _pages(path: str) -> list[str]:
    """`[path]`, or for a TIFF file of several pages one `"path[i]"` per page."""
    if not (path.lower().endswith((".tif", ".tiff")) and os.path.isfile(path)):
        return [path]
    import cv2

    try:
        n = cv2.imcount(path)
    except cv2.error:  # not a TIFF OpenCV can read: named by the read
        return [path]
    return [path] if n <= 1 else [f"{path}[{i}]" for i in range(n)]


def _split_page(path: str) -> tuple[str, int | None]:
    """`(file, page)` of a frame path: `"stack.tif[2]"` is page 2 of `stack.tif` (when no file
    has that whole name), any other path the file itself (page None)."""
    match = _PAGE.match(path)
    if match is None or os.path.isfile(path):
        return path, None
    return match["file"], int(match["page"])


def _exists(path: PathLike) -> bool:
    """Whether the file of a frame path (`_split_page`) exists."""
    return os.path.isfile(_split_page(os.fspath(path))[0])


def read_image(path: PathLike, *, linearize: str = "auto",
               bits: int | None = None) -> Float[np.ndarray, "H W *C"]:
    """Read one frame as float32 in [0, 1]: `(H, W)` grey or `(H, W, 3)` RGB.

    Uses `cv2.imread(..., IMREAD_UNCHANGED)`, which keeps 16 bits (imageio and
    `skimage.io.imread` silently return 16-bit PNGs as 8-bit with Pillow 13). An alpha channel is
    dropped; colour comes back in RGB order. Integer pixels are divided by the largest code of
    their type (255 or 65535), or for PGM and PPM by the header's maxval: a 12-bit camera's
    4095 reads as 1 (saturated), not 0.0625.

    **Arguments:**
    - `path`: the file; `"stack.tif[2]"` is page 2 (from 0) of a multi-page TIFF.
    - `linearize`: `"auto"` decodes 8-bit PNG/JPEG from sRGB and leaves PGM/TIFF/BMP (the
      formats of machine-vision cameras, which write their codes as measured) and 16-bit
      files linear; `"srgb"` always decodes; `"none"` never does.
    - `bits`: the camera's bit depth, for integer files that hold its codes unscaled (a 12-bit
      camera's 0-4095 in 16-bit PNG or TIFF pixels): codes are divided by $2^{bits} - 1$.
      Default: the pixel type's largest code, or a PGM's maxval.

    **Raises:** `FileNotFoundError` if the file is missing, `ValueError` naming the file if it
    cannot be decoded, has an unsupported bit depth, codes above `bits`, or floating-point
    values that are not finite or above 1 (float frames are intensities in [0, 1]).
    """
    return _to_float(*_decode(path, linearize, bits))


def _header(path: str) -> tuple[int | None, bool]:
    """`(maxval, grey)` from a file's first bytes: the largest code value a binary or text
    PGM/PPM header declares (e.g. 4095 for a 12-bit camera; OpenCV returns the codes as they
    are), else None; and whether it is a PNG of grey pixels (with alpha OpenCV returns four
    equal-coloured channels)."""
    with open(path, "rb") as f:
        head = f.read(512)
    if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) > 25:
        return None, head[25] in (0, 4)  # IHDR colour type: grey, grey + alpha
    return _netpbm_maxval(head), False


def _netpbm_maxval(head: bytes) -> int | None:
    """The maxval of a PGM/PPM header (magic, width, height, maxval; `#` comments), or None."""
    if head[:2] not in (b"P2", b"P3", b"P5", b"P6"):
        return None
    fields = []
    for line in head[2:].split(b"\n"):
        fields += line.split(b"#")[0].split()
        if len(fields) >= 3:
            break
    try:
        return int(fields[2])
    except (IndexError, ValueError):
        return None  # OpenCV judges the header


def _check_bits(bits):
    if bits is not None and not (isinstance(bits, (int, np.integer)) and 1 <= bits <= 16):
        raise ValueError(f"bits must be an int from 1 to 16 (the camera's bit depth), got "
                         f"{bits!r}")


def _decode(path: PathLike, linearize: str,
            bits: int | None = None) -> tuple[np.ndarray, str, bool, int | None]:
    """`(raw, path, srgb, top)`: the file's pixels as stored (RGB order, no alpha), whether
    `linearize` asks for them to be decoded from sRGB, and the code value that reads as 1
    (`2**bits - 1`, else a PGM's or PPM's maxval; None: the pixel type's largest)."""
    path = os.fspath(path)
    if linearize not in ("auto", "srgb", "none"):
        raise ValueError(f"linearize must be 'auto', 'srgb' or 'none', got {linearize!r}")
    _check_bits(bits)
    file, page = _split_page(path)
    if not os.path.isfile(file):
        raise FileNotFoundError(f"frame not found: {path}")
    import cv2

    if page is None:
        raw = cv2.imread(file, cv2.IMREAD_UNCHANGED)
    else:
        pages = cv2.imcount(file)
        if page >= pages:
            raise ValueError(f"cannot read image {path}: {file} has {pages} page(s), "
                             f"numbered from 0")
        ok, found = cv2.imreadmulti(file, start=page, count=1, flags=cv2.IMREAD_UNCHANGED)
        raw = found[0] if ok and found else None
    if raw is None:
        raise ValueError(f"cannot read image {path}: not a decodable PGM/PNG/TIFF/BMP file")
    top, grey = _header(file)
    if raw.ndim == 3:
        raw = raw[..., :3][..., ::-1] if raw.shape[-1] >= 3 and not grey else raw[..., 0]
    srgb = _srgb(path, raw.dtype == np.uint8, linearize)
    if bits is not None and raw.dtype in (np.uint8, np.uint16):
        top = 2**bits - 1
        if raw.max(initial=0) > top:
            raise ValueError(f"image {path} has codes up to {raw.max()}, above the "
                             f"{top} of bits={bits}")
    return raw, path, srgb, top


def _srgb(path: str, eight_bit: bool, linearize: str) -> bool:
    """Whether `read_image` decodes the file at `path`, of 8-bit pixels or not, from sRGB."""
    return linearize == "srgb" or (
        linearize == "auto" and eight_bit and path.lower().endswith(_SRGB_EXTENSIONS))


def _decodes_srgb(path: PathLike, linearize: str = "auto") -> bool:
    """Whether `read_image(path, linearize=linearize)` decodes the file from sRGB, from its
    name and first bytes only (a PNG's bit depth is in its header; a JPEG is 8-bit), for a
    command's summary."""
    path = _split_page(os.fspath(path))[0]
    with open(path, "rb") as f:
        head = f.read(25)
    eight_bit = not (head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) == 25 and head[24] == 16)
    return _srgb(path, eight_bit, linearize)


def _to_float(raw: np.ndarray, path: str, srgb: bool, top: int | None = None,
              out: np.ndarray | None = None):
    """`raw` as linear float32 in [0, 1], written into `out` when given (one pass per step,
    no temporaries: `load_stack` fills its stack in place). Integer codes are divided by
    `top` (default: 255 or 65535 by pixel type)."""
    if raw.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        raise ValueError(f"image {path} has unsupported pixel type {raw.dtype}")
    if out is None:
        out = np.empty(raw.shape, np.float32)
    if raw.dtype in (np.uint8, np.uint16):
        full = 255 if raw.dtype == np.uint8 else 65535
        np.divide(raw, np.float32(full if top is None else top), out=out)
    else:
        out[...] = raw
        if not np.isfinite(out).all():  # integer pixels are always finite
            raise ValueError(f"image {path} contains NaN or Inf")
        if out.max(initial=0) > 1:  # else most samples would read as saturated, a bad frame
            raise ValueError(
                f"image {path} holds floating-point values up to {float(out.max()):.6g}: "
                "float frames are read as intensities in [0, 1] (1: saturated); scale them, "
                "e.g. by the camera's full-scale value")
    if srgb:
        out[...] = srgb_to_linear(out)
    return out


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """The sRGB decoding curve (IEC 61966-2-1), as `colour.cctf_decoding(v, function="sRGB")`.

    Written out because importing colour-science for it took about 1 s per command (it imports
    matplotlib); tests/test_acquisition.py checks it against colour-science.
    """
    v = np.asarray(v, np.float32)
    return np.where(v <= 0.04045, v / 12.92,
                    ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(v: np.ndarray) -> np.ndarray:
    """The sRGB encoding curve, the inverse of `srgb_to_linear`, for images written to be
    looked at (`colour.cctf_encoding(v, function="sRGB")`)."""
    v = np.clip(np.asarray(v, np.float32), 0, None)
    return np.where(v <= 0.0031308, 12.92 * v,
                    1.055 * v ** (1 / 2.4) - 0.055).astype(np.float32)


def load_stack(
    paths: Sequence[PathLike], *, linearize: str = "auto", bits: int | None = None
) -> tuple[Float[np.ndarray, "K H W *C"], Bool[np.ndarray, "K H W"]]:
    """Read frames into a `(K, H, W)` or `(K, H, W, C)` stack, with a saturation map.

    Returns the stack (float32, 64-byte aligned, as jitted solves read it in place) and a
    `(K, H, W)` bool array of samples at the top code value (any channel). Frames are decoded
    on up to `os.cpu_count()` threads (OpenCV and numpy release the GIL): on this project's
    2-core machine, five 1 MP 16-bit PNGs took 0.048 s against 0.066 s for `read_image` one
    after another (`benchmarks/bench_io.py`). `linearize`, `bits`: see `read_image`. Without
    `bits`, 16-bit frames whose largest code is that of a 10-, 12- or 14-bit camera (1023,
    4095, 16383), held by several samples, are named in a warning on the `"jaxps"` logger:
    read as 16-bit they are that much too dark, and none of them counts as saturated.

    **Raises:** `ValueError` naming the first file whose size or channels differ from the first
    frame's, or an empty list.
    """
    if len(paths) == 0:
        raise ValueError("no frames given")
    _check_bits(bits)
    first = _decode(paths[0], linearize, bits)
    tops = [0] * len(paths)  # each 16-bit frame's largest code and how many samples hold it
    stack = aligned_empty((len(paths), *first[0].shape), np.float32)
    saturated = np.empty(stack.shape[:3], bool)

    def fill(i, decoded):
        raw, path, srgb, top = (decoded if decoded is not None
                                else _decode(paths[i], linearize, bits))
        if raw.shape != first[0].shape:
            raise ValueError(
                f"frame {path} has shape {raw.shape}, but {first[1]} has {first[0].shape}: "
                "all frames must be the same size and channels"
            )
        if (raw.dtype, srgb) != (first[0].dtype, first[2]):  # one scale would be wrong
            raise ValueError(
                f"frame {path} holds {_pixels(raw.dtype, srgb)}, but {first[1]} holds "
                f"{_pixels(first[0].dtype, first[2])}: all frames of a capture must share a "
                "format (one camera, one export)")
        frame = _to_float(raw, path, srgb, top, out=stack[i])
        at_top = frame >= 1.0
        saturated[i] = at_top.any(axis=-1) if at_top.ndim == 3 else at_top
        if raw.dtype == np.uint16 and top in (None, 65535):  # full scale not set by bits=
            largest = int(raw.max(initial=0))
            tops[i] = (largest, int(np.count_nonzero(raw == largest))
                       if largest in _LOW_DEPTH_TOPS else 0)

    with ThreadPoolExecutor(min(len(paths), os.cpu_count() or 1)) as pool:
        jobs = [pool.submit(fill, i, first if i == 0 else None) for i in range(len(paths))]
        for job in jobs:  # in order: the first bad file is the one named
            job.result()
    _warn_low_depth(tops, paths)
    return stack, saturated


def _pixels(dtype, srgb: bool) -> str:
    """A frame's pixel format in words, for errors."""
    kind = {np.dtype(np.uint8): "8-bit", np.dtype(np.uint16): "16-bit"}.get(
        np.dtype(dtype), f"{np.dtype(dtype)}")
    return f"{kind} codes{' decoded from sRGB' if srgb else ''}"


# A 10-, 12- or 14-bit camera's largest code; held by this many samples of one frame (its
# saturated ones), it is no chance maximum of a dim 16-bit frame.
_LOW_DEPTH_TOPS = {2**b - 1: b for b in (10, 12, 14)}
_LOW_DEPTH_MIN_COUNT = 8


def _warn_low_depth(tops, paths):
    """The warning of `load_stack` (its docstring), from each 16-bit frame's `(largest code,
    samples holding it)` (0 for the other frames)."""
    code = max((t[0] for t in tops if t), default=None)
    if code in _LOW_DEPTH_TOPS and any(t and t[0] == code and t[1] >= _LOW_DEPTH_MIN_COUNT
                                       for t in tops):
        bits = _LOW_DEPTH_TOPS[code]
        logging.getLogger("jaxps").warning(
            "the 16-bit frames (%s ...) top out at code %d, the largest of a %d-bit camera: "
            "read as 16-bit they are %dx too dark and their saturated samples pass as "
            "unsaturated. If the camera writes %d-bit codes unscaled, give bits=%d "
            "(--bits %d).", os.path.basename(os.fspath(paths[0])), code, bits,
            2 ** (16 - bits), bits, bits, bits)


def read_mask(path: PathLike, shape: tuple[int, int] | None = None) -> Bool[np.ndarray, "H W"]:
    """Read a mask image (non-zero = inside). **Raises:** `ValueError` if `shape` differs."""
    img = read_image(path, linearize="none")
    mask = (img.max(axis=-1) if img.ndim == 3 else img) > 0
    if shape is not None and mask.shape != tuple(shape):
        raise ValueError(f"mask {os.fspath(path)} has shape {mask.shape}, frames have {shape}")
    return mask
