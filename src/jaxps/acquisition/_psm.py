"""The psm capture format: `NAME.0.png ... NAME.{K-1}.png` and `NAME.mask.png` in one folder.

The format of the UW CSE 455 photometric-stereo set (shared/data/psm): 8-bit sRGB PNGs, the
chrome sphere's frames in a folder of their own (calibrate with `jaxps.lights_from_chrome`).
"""

from __future__ import annotations

import os

import numpy as np
from jaxtyping import Float

from ._files import read_image

__all__ = ["load_psm"]


def load_psm(folder: str | os.PathLike, *, name: str | None = None, linear: bool = True
             ) -> tuple[Float[np.ndarray, "K H W 3"], Float[np.ndarray, "H W"]]:
    """Read a psm capture `NAME.0.png ... NAME.{K-1}.png` and `NAME.mask.png` from `folder`.

    The PNGs are 8-bit sRGB: with `linear` they are decoded to linear radiance with the sRGB
    transfer function (`colour.cctf_decoding(x, "sRGB")`), as DESIGN.md requires for PS.

    **Arguments:**
    - `folder`: e.g. `shared/data/psm/cat`; `name` defaults to the folder's name.
    - `linear`: decode sRGB to linear (default) or keep the encoded values / 255.

    **Returns:** `images` `(K, H, W, 3)` float32 RGB in [0, 1] and `mask` `(H, W)` float32 in
    [0, 1] (anti-aliased; threshold at 0.5 for a bool mask).

    **Raises:** `FileNotFoundError` if no `NAME.0.png` or mask exists.
    """
    folder = os.fspath(folder)
    name = os.path.basename(os.path.normpath(folder)) if name is None else name
    paths = []
    while os.path.isfile(p := os.path.join(folder, f"{name}.{len(paths)}.png")):
        paths.append(p)
    mask_path = os.path.join(folder, f"{name}.mask.png")
    if not paths or not os.path.isfile(mask_path):
        raise FileNotFoundError(f"no psm capture {name}.0.png + {name}.mask.png in {folder}")

    images = np.stack([read_image(p, linearize="srgb" if linear else "none") for p in paths])
    if images.ndim == 3:
        images = np.repeat(images[..., None], 3, axis=-1)
    mask = read_image(mask_path, linearize="none")
    mask = mask.mean(axis=-1) if mask.ndim == 3 else mask
    return np.ascontiguousarray(images, np.float32), mask.astype(np.float32)
