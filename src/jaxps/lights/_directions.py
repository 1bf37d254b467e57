"""Light directions: construction from angles, the ``lights.txt`` format, Yale B names, validation.

Lights are ``(K, 3)`` unit vectors from the surface toward the light in the camera frame of
DESIGN.md (x right, y up, z toward the viewer), or ``(K, H, W, 3)`` per pixel for near lights.
"""

from __future__ import annotations

import os
import re

import numpy as np
from jaxtyping import ArrayLike, Float

__all__ = [
    "angles_from_lights",
    "lights_from_angles",
    "load_lights",
    "parse_yale_name",
    "save_lights",
    "validate_lights",
]

# Condition number above which a light set is treated as not spanning 3-D.
MAX_LIGHT_CONDITION = 1e4

# "..._P00A+035E+15.pgm"; also without the pose ("A+035E+15.png", "face_A+35E+15.tif")
_YALE_RE = re.compile(r"(?:^|[_\W])(?:P\d+)?A([+-]\d+)E([+-]\d+)(?:\.[A-Za-z0-9]+)?$")


def lights_from_angles(
    azimuth_deg: Float[ArrayLike, " K"], elevation_deg: Float[ArrayLike, " K"]
) -> Float[np.ndarray, "K 3"]:
    """Unit light vectors from Yale B azimuth/elevation angles.

    $l = (-\\cos E \\sin A,\\ \\sin E,\\ \\cos E \\cos A)$: a positive azimuth lights the image's
    left side (the subject's right), a positive elevation lights from above; (0, 0) is the
    camera axis. Convention checked on the Extended Yale B images (shared/data/README.md).

    **Arguments:**
    - `azimuth_deg`, `elevation_deg`: `(K,)` angles in degrees (scalars are promoted to K=1).

    **Returns:** `(K, 3)` float32 unit vectors.
    """
    a = np.radians(np.atleast_1d(np.asarray(azimuth_deg, dtype=np.float64)))
    e = np.radians(np.atleast_1d(np.asarray(elevation_deg, dtype=np.float64)))
    if a.shape != e.shape or a.ndim != 1:
        raise ValueError(
            f"azimuth_deg and elevation_deg must be 1-D and the same length, got shapes "
            f"{a.shape} and {e.shape}"
        )
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(e))):
        raise ValueError("azimuth_deg and elevation_deg must be finite")
    lights = np.stack([-np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)], axis=-1)
    return lights.astype(np.float32)


def angles_from_lights(
    lights: Float[ArrayLike, "K 3"],
) -> tuple[Float[np.ndarray, " K"], Float[np.ndarray, " K"]]:
    """Yale B azimuth and elevation in degrees of unit light vectors: the inverse of
    `lights_from_angles`.

    $A = \\operatorname{atan2}(-l_x, l_z)$, $E = \\arcsin l_y$ (rows are normalised first).

    **Arguments:**
    - `lights`: `(K, 3)` (or one `(3,)`) directions toward the lights, camera frame.

    **Returns:** `(azimuth_deg, elevation_deg)`, two `(K,)` float64 arrays.

    **Raises:** `ValueError` if `lights` is not `(K, 3)`, or has a zero or non-finite row.
    """
    lights = np.asarray(lights, np.float64)
    if lights.shape == (3,):
        lights = lights[None]
    if lights.ndim != 2 or lights.shape[1] != 3:
        raise ValueError(f"lights must have shape (K, 3), got {lights.shape}")
    norms = np.linalg.norm(lights, axis=1)
    bad = np.flatnonzero(~(np.isfinite(norms) & (norms > 1e-8)))
    if bad.size:
        raise ValueError(f"lights {bad.tolist()} are zero or not finite")
    lx, ly, lz = (lights / norms[:, None]).T
    return np.degrees(np.arctan2(-lx, lz)), np.degrees(np.arcsin(np.clip(ly, -1, 1)))


def parse_yale_name(name: str | os.PathLike) -> tuple[float, float] | None:
    """Azimuth and elevation in degrees from a Yale B file name, or ``None``.

    ``yaleB01_P00A+035E+15.pgm`` -> ``(35.0, 15.0)``; ``yaleB01_P00_Ambient.pgm`` -> ``None``.
    The pose may be left out, so that a rig can name its frames the same way:
    ``A+035E+15.png`` and ``face_A+35E+15.tif`` -> ``(35.0, 15.0)``.
    """
    m = _YALE_RE.search(os.path.basename(os.fspath(name)))
    if m is None:
        return None
    return float(m.group(1)), float(m.group(2))


def load_lights(path: str | os.PathLike) -> Float[np.ndarray, "K 3"]:
    """Read a ``lights.txt`` file: an optional first line with the count, then ``x y z`` per line.

    The vectors are taken in the camera frame of DESIGN.md (x right, y up, z toward the viewer);
    the shared psm ``lights.txt`` uses that frame (checked against its chrome sphere:
    highlight directions agree within ~2-9 degrees). Rows are unit-normalised and validated.

    **Raises:** `FileNotFoundError` if the file is missing; `ValueError` naming the file if it
    cannot be parsed, the count disagrees with the rows, or the lights fail `validate_lights`.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"lights file not found: {path}")
    data = _read_xyz(path, "lights file")
    try:
        return validate_lights(data)
    except ValueError as err:
        raise ValueError(f"lights file {path}: {err}") from None


def _read_xyz(path: str, label: str) -> np.ndarray:
    """The ``x y z`` rows of a ``lights.txt``-style file as `(N, 3)` float64: ``#`` comments,
    spaces, tabs, commas or semicolons, an optional first line with the count. `ValueError`s start with
    `label` and the path (`load_lights`'s, and `jaxps reconstruct --light-positions`')."""
    rows = []
    try:
        with open(path, encoding="utf-8-sig") as f:  # a byte-order mark, as Notepad writes
            for line in f:
                line = line.split("#", 1)[0].strip()
                if line:
                    rows.append(line.replace(",", " ").replace(";", " ").split())
    except UnicodeDecodeError:
        raise ValueError(f"{label} {path}: not a text file") from None
    count = None
    if rows and len(rows[0]) == 1:
        count = rows.pop(0)[0]
    bad = [r for r in rows if len(r) != 3]
    if bad:
        hint = ("; two numbers a line look like angles: write the directions with "
                "jaxps.save_lights(path, jaxps.lights_from_angles(azimuths, elevations))"
                if label == "lights file" and all(len(r) == 2 for r in rows) else "")
        raise ValueError(f"{label} {path}: expected 3 numbers per line (x y z), got "
                         f"{bad[0]}{hint}")
    try:
        count = None if count is None else int(count)
        data = np.array([[float(v) for v in r] for r in rows], dtype=np.float64).reshape(-1, 3)
    except ValueError as err:
        raise ValueError(f"cannot parse {label} {path}: {err}") from None
    if count is not None and count != len(data):
        raise ValueError(f"{label} {path}: header says {count} lights, found {len(data)}")
    return data


def save_lights(path: str | os.PathLike, lights: Float[ArrayLike, "K 3"], *,
                comment: str | None = None) -> None:
    """Write a ``lights.txt`` that `load_lights` reads back: `comment` (each line after
    ``#``), the count, then ``x y z`` per light, unit-normalised, to 9 decimals.

    **Raises:** `ValueError` if `lights` fails `validate_lights` (nothing is written then).
    """
    lights = validate_lights(lights).astype(np.float64)
    lights = lights / np.linalg.norm(lights, axis=1, keepdims=True) + 0.0  # + 0.0: no "-0.0"
    head = "".join(f"# {line}\n" for line in (comment or "").splitlines())
    rows = "".join(f"{x:.9f} {y:.9f} {z:.9f}\n" for x, y, z in lights)
    with open(path, "w") as f:
        f.write(f"{head}{len(lights)}\n{rows}")


def frame_count_error(images_shape: tuple[int, ...], n_lights: int) -> ValueError:
    """The error for `images` of `images_shape` (frames first) and `n_lights` lights that
    disagree in number; it says how to fix images whose frames lie on the last axis."""
    hint = ""
    if images_shape[-1] == n_lights:
        hint = ("; images look like (H, W, K): put the frame axis first "
                "(np.moveaxis(images, -1, 0))")
    return ValueError(f"images have K={images_shape[0]} frames but lights have {n_lights} "
                      f"rows{hint}")


def validate_lights(lights: Float[ArrayLike, "K 3"]) -> Float[np.ndarray, "K 3"]:
    """Check a light set and return it unit-normalised as float32.

    **Raises:** `ValueError` if `lights` is not `(K, 3)`, has K < 3, contains NaN/Inf or zero
    vectors, or does not span 3-D (condition number above 1e4, which is reported).
    """
    lights = np.asarray(lights, dtype=np.float64)
    if lights.ndim != 2 or lights.shape[-1] != 3:
        raise ValueError(f"lights must have shape (K, 3), got {lights.shape}")
    if lights.shape[0] < 3:
        raise ValueError(f"photometric stereo needs at least 3 lights, got K={lights.shape[0]}")
    if not np.all(np.isfinite(lights)):
        raise ValueError("lights contain NaN or Inf")
    norms = np.linalg.norm(lights, axis=1)
    if np.any(norms < 1e-8):
        bad = np.flatnonzero(norms < 1e-8).tolist()
        raise ValueError(f"lights {bad} are zero vectors")
    lights = lights / norms[:, None]
    cond = np.linalg.cond(lights)
    if not np.isfinite(cond) or cond > MAX_LIGHT_CONDITION:
        raise ValueError(
            f"lights do not span 3-D (condition number {cond:.3g} > {MAX_LIGHT_CONDITION:.0e}); "
            "coplanar or repeated light directions cannot determine a normal"
        )
    return lights.astype(np.float32)
