"""Where photometric-stereo methods fail: corrupted synthetic captures and stability sweeps.

`render_corrupted` renders a `jaxps.synthetic` surface with what plain Lambertian PS ignores --
cast shadows (ray-marched over the height map), a Blinn-Phong specular lobe, saturation, light
directions that are wrong by a known angle, near point lights -- and `sweep` measures the angular
error of each `photometric_stereo` method as one of these grows. `benchmarks/bench_stability.py`
runs the sweeps listed in `SWEEPS` and writes JSON and charts.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .core._progress import ProgressHook, Stages
from .core._random import as_key
from .core._status import Status
from .evaluate import angular_stats
from .lights import near_light_field, surface_points
from .ps import near_photometric_stereo, photometric_stereo
from .synthetic import face_like

__all__ = [
    "Corrupted",
    "ROBUST_SWEEP_METHODS",
    "SWEEPS",
    "cast_shadow_mask",
    "perturb_lights",
    "render_corrupted",
    "ring_lights",
    "sweep",
]


class Corrupted(NamedTuple):
    """A rendered capture with its truth and what corrupted it.

    `images` `(K, H, W)` in [0, 1]; `lights` `(K, 3)` the true (distant) lights or `(K, H, W, 3)`
    per-pixel unit lights (near); `normals` `(H, W, 3)`, `albedo` `(H, W)`, `mask` `(H, W)`;
    `shadow` `(K, H, W)` bool cast-shadowed samples; `specular` `(K, H, W)` the added lobe.
    """

    images: Float[Array, "K H W"]
    lights: Float[Array, "K 3"] | Float[Array, "K H W 3"]
    normals: Float[Array, "H W 3"]
    albedo: Float[Array, "H W"]
    mask: Bool[Array, "H W"]
    shadow: Bool[Array, "K H W"]
    specular: Float[Array, "K H W"]


def ring_lights(k: int, zenith_deg: float = 35.0, *, centre: bool = True) -> Float[np.ndarray, "K 3"]:
    """`k` lights: one on the camera axis (if `centre`) and the rest evenly on a cone of
    `zenith_deg` around it, starting at the image's right. `(K, 3)` float32 unit vectors."""
    if k < 3:
        raise ValueError(f"k must be at least 3, got {k}")
    if not 0 <= zenith_deg < 90:
        raise ValueError(f"zenith_deg must be in [0, 90) (lights above the horizon), got "
                         f"{zenith_deg}")
    m = k - 1 if centre else k
    phi = 2 * np.pi * np.arange(m) / m
    t = np.radians(zenith_deg)
    ring = np.stack([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi),
                     np.full(m, np.cos(t))], axis=-1)
    if centre:
        ring = np.concatenate([[[0.0, 0.0, 1.0]], ring])
    return ring.astype(np.float32)


def perturb_lights(lights: Float[ArrayLike, "K 3"], angle_deg: float, *,
                   key: jax.Array | int) -> Float[np.ndarray, "K 3"]:
    """Rotate each light by exactly `angle_deg` about a random axis perpendicular to it.

    `key` is a JAX PRNG key or an int seed (`jax.random.key(seed)`).
    """
    lights = np.asarray(lights, np.float64)
    if lights.ndim != 2 or lights.shape[1] != 3:
        raise ValueError(f"lights must be (K, 3), got shape {lights.shape}")
    length = np.linalg.norm(lights, axis=-1, keepdims=True)
    if not np.all(np.isfinite(length) & (length > 0)):
        raise ValueError("lights must be finite, non-zero directions")
    if not np.isfinite(angle_deg):
        raise ValueError(f"angle_deg must be finite, got {angle_deg}")
    key = as_key(key)
    lights = lights / length
    r = np.asarray(jax.random.normal(key, lights.shape), np.float64)
    perp = r - np.sum(r * lights, axis=-1, keepdims=True) * lights
    perp /= np.linalg.norm(perp, axis=-1, keepdims=True)
    t = np.radians(angle_deg)
    return (np.cos(t) * lights + np.sin(t) * perp).astype(np.float32)


@functools.partial(jax.jit, static_argnums=2)
def _cast_shadows(height, lights, n_steps):
    h, w = height.shape
    rows, cols = jnp.meshgrid(jnp.arange(h, dtype=height.dtype), jnp.arange(w, dtype=height.dtype),
                              indexing="ij")

    def one_light(l):
        # Step one pixel at a time toward the light in the image plane (row axis is -y).
        lxy = jnp.hypot(l[0], l[1])
        safe = jnp.maximum(lxy, 1e-6)
        dc, dr = l[0] / safe, -l[1] / safe
        rise = l[2] / safe  # height gained by the ray per pixel travelled

        def step(blocked, s):
            s = s.astype(height.dtype)
            z = jax.scipy.ndimage.map_coordinates(
                height, [rows + s * dr, cols + s * dc], order=1, mode="nearest")
            return blocked | (z > height + s * rise + 1e-3), None

        blocked, _ = jax.lax.scan(step, jnp.zeros((h, w), bool), jnp.arange(1, n_steps + 1))
        return blocked & (lxy > 1e-6)

    return jax.vmap(one_light)(lights)


def cast_shadow_mask(height: Float[ArrayLike, "H W"], lights: Float[ArrayLike, "K 3"], *,
                     n_steps: int = 64) -> Bool[Array, "K H W"]:
    """Cast shadows of a height map (pixel units, z to the viewer) under distant lights.

    Marches `n_steps` one-pixel steps from each pixel toward each light's image-plane
    direction; a sample is shadowed when the surface rises above the ray. Attached shadows
    ($l \\cdot n \\le 0$) are not included (Lambert's clamp gives them).

    **Returns:** `(K, H, W)` bool.
    """
    height = jnp.asarray(height, jnp.float32)
    lights = jnp.asarray(lights, jnp.float32)
    if height.ndim != 2:
        raise ValueError(f"height must be (H, W), got shape {height.shape}")
    if lights.ndim != 2 or lights.shape[1] != 3:
        raise ValueError(f"lights must be (K, 3), got shape {lights.shape}")
    if not (isinstance(n_steps, (int, np.integer)) and n_steps >= 1):
        raise ValueError(f"n_steps must be a positive int, got {n_steps!r}")
    return _cast_shadows(height, lights, n_steps)


def render_corrupted(
    surface,
    lights: Float[ArrayLike, "K 3"] | Float[ArrayLike, "K H W 3"],
    *,
    albedo: Float[ArrayLike, "H W"] | None = None,
    shadows: bool = True,
    specular: float = 0.0,
    shininess: float = 40.0,
    falloff: Float[ArrayLike, "K H W"] | None = None,
    noise: float = 0.0,
    key: jax.Array | int | None = None,
) -> Corrupted:
    """Render a surface with cast shadows, a specular lobe, noise and clipping at 1.

    $I_k = \\mathrm{clip}(a_k [\\rho \\max(0, l_k \\cdot n) + k_s (n \\cdot h_k)^s] s_k
    + \\epsilon, 0, 1)$ with $h_k$ the unit half-vector of $l_k$ and the view $(0, 0, 1)$
    (Blinn-Phong), $s_k = 0$ in cast shadow, $a_k$ the near-light `falloff` (default 1) and
    $\\epsilon \\sim N(0, \\sigma^2)$. Values at 1 are saturated.

    **Arguments:**
    - `surface`: a `jaxps.synthetic` `Surface` (height in pixels, normals, mask).
    - `lights`: `(K, 3)` distant unit lights or `(K, H, W, 3)` per-pixel unit lights.
    - `albedo`: `(H, W)`; default the smooth pattern of `jaxps.synthetic.render_scene`.
    - `shadows`: ray-march cast shadows (distant lights only; per-pixel lights use the mean
      direction per light).
    - `specular`, `shininess`: Blinn-Phong strength $k_s$ and exponent $s$.
    - `falloff`: `(K, H, W)` per-sample light intensity (near lights), default 1.
    - `noise`: Gaussian noise standard deviation (needs `key`).
    - `key`: a JAX PRNG key or an int seed (`jax.random.key(seed)`).

    **Returns:** `Corrupted`.
    """
    h, w = surface.mask.shape
    n = jnp.asarray(surface.normals, jnp.float32)
    mask = jnp.asarray(surface.mask, bool)
    if albedo is None:
        x = np.arange(w, dtype=np.float32) - (w - 1) / 2
        y = (h - 1) / 2 - np.arange(h, dtype=np.float32)
        x, y = np.meshgrid(x, y)
        albedo = 0.65 + 0.2 * np.sin(x / 9.0) * np.cos(y / 13.0)
    albedo = jnp.where(mask, jnp.asarray(albedo, jnp.float32), 0)
    lights = jnp.asarray(lights, jnp.float32)
    if lights.ndim == 2 and lights.shape[1] == 3:
        lpix = jnp.broadcast_to(lights[:, None, None, :], (lights.shape[0], h, w, 3))
    elif lights.shape[1:] == (h, w, 3):
        lpix = lights
    else:
        raise ValueError(f"lights must be (K, 3) or (K, H, W, 3) = (K, {h}, {w}, 3), "
                         f"got {lights.shape}")
    k = lpix.shape[0]
    if shadows:
        mean_dir = jnp.mean(lpix, axis=(1, 2)) if lights.ndim == 4 else lights
        mean_dir = mean_dir / jnp.linalg.norm(mean_dir, axis=-1, keepdims=True)
        shadow = cast_shadow_mask(surface.height, mean_dir) & mask[None]
    else:
        shadow = jnp.zeros((k, h, w), bool)
    cos = jnp.einsum("khwc,hwc->khw", lpix, n)
    half = lpix + jnp.array([0.0, 0.0, 1.0], jnp.float32)[None, None, None]
    half = half / jnp.maximum(jnp.linalg.norm(half, axis=-1, keepdims=True), 1e-6)
    spec = specular * jnp.maximum(jnp.einsum("khwc,hwc->khw", half, n), 0) ** shininess
    spec = jnp.where(cos > 0, spec, 0)
    images = (albedo[None] * jnp.maximum(cos, 0) + spec) * (~shadow).astype(jnp.float32)
    if falloff is not None:
        images = images * jnp.asarray(falloff, jnp.float32)
    if noise > 0:
        if key is None:
            raise ValueError("noise > 0 needs key (a jax.random.key or an int seed)")
        images = images + noise * jax.random.normal(as_key(key), images.shape, images.dtype)
    images = jnp.where(mask[None], jnp.clip(images, 0, 1), 0)
    return Corrupted(images, lights, n, albedo, mask, shadow, jnp.where(mask[None], spec, 0))


ROBUST_SWEEP_METHODS: tuple[str, ...] = ("l2", "barsky", "irls", "sbl")

SWEEPS: dict[str, tuple[float, ...]] = {
    "noise": (0.0, 0.005, 0.01, 0.02, 0.05),
    "n_lights": (3, 4, 5, 6, 8, 10, 12),
    "light_error_deg": (0.0, 1.0, 2.0, 5.0, 10.0),
    "zenith_deg": (10.0, 20.0, 30.0, 45.0, 60.0),
    "gain": (1.0, 1.5, 2.0, 3.0),
    "near_distance_mm": (300.0, 600.0, 1200.0, 2400.0),
}
"""The sweeps `sweep` knows, with default values. Base scene: `face_like(h)`, 5 lights (one on
the axis, four on a 20-degree cone), 0.5% noise, cast shadows and a Blinn-Phong lobe
($k_s$ = 0.3, exponent 60) unless the sweep varies them:

- `noise`: image noise sigma (no specular lobe);
- `n_lights`: K lights on a 35-degree cone (K >= 4 with one on the axis);
- `light_error_deg`: every light given to the solver is rotated by this angle (random axis);
- `zenith_deg`: cone angle of the four outer lights (more cast and attached shadow);
- `gain`: exposure gain (more saturation at 1);
- `near_distance_mm`: point lights at this distance, face ~190 mm high (3 mm pixels), solved as
  distant lights and with `near_photometric_stereo` (`"near-l2"`).
"""


def _scene_for(name, value, h, key):
    surf = jaxps_synthetic_face(h)
    k1, k2 = jax.random.split(key)
    base = dict(specular=0.3, shininess=60.0, noise=0.005, key=k1)
    lights = ring_lights(5, 20.0)
    solver_lights = lights
    gain = 1.0
    extra = {}
    if name == "noise":
        base.update(specular=0.0, noise=float(value))
    elif name == "n_lights":
        k = int(value)
        lights = solver_lights = ring_lights(k, 35.0, centre=k >= 4)
    elif name == "light_error_deg":
        solver_lights = perturb_lights(lights, float(value), key=k2)
    elif name == "zenith_deg":
        lights = solver_lights = ring_lights(5, float(value))
    elif name == "gain":
        gain = float(value)
    elif name == "near_distance_mm":
        pixel = 3.0 * 64 / h
        positions = float(value) * np.asarray(lights, np.float64)
        height = np.asarray(surf.height) * pixel
        field, fall = near_light_field(positions, surface_points(height, pixel_size=pixel))
        extra = dict(positions=positions, pixel=pixel, level=float(height[np.asarray(surf.mask)]
                                                                    .mean()))
        scene = render_corrupted(surf, field, falloff=fall, **base)
        return scene, lights, extra
    else:
        raise ValueError(f"unknown sweep {name!r}; choose from {tuple(SWEEPS)}")
    scene = render_corrupted(surf, lights, **base)
    if gain != 1.0:
        scene = scene._replace(images=jnp.clip(scene.images * gain, 0, 1))
    return scene, solver_lights, extra


def jaxps_synthetic_face(h):
    return face_like(h)


def sweep(
    name: str,
    values=None,
    *,
    methods: tuple[str, ...] | None = None,
    h: int = 96,
    key: jax.Array | int | None = None,
    progress: ProgressHook | None = None,
) -> dict:
    """Angular error of each method as one corruption grows (see `SWEEPS`).

    **Arguments:**
    - `name`: a key of `SWEEPS`; `values` default to its values.
    - `methods`: `photometric_stereo` methods (default `ROBUST_SWEEP_METHODS`: L2 and the
      robust solvers; the reflectance-aware and semi-calibrated solvers answer other questions
      and are far slower).
    - `h`: image height of the `face_like` scene.
    - `key`: PRNG key or int seed for noise and light perturbations (default
      `jax.random.key(0)`).
    - `progress`: a hook told of each solve (one per value and method) as it starts:
      `jaxps.report.progress_bar()` draws a bar on stderr.

    **Returns:** a JSON-ready dict: `name`, `values`, per-value scene facts (`shadowed`,
    `saturated`, `specular` fractions of object samples) and, per method, lists of
    `median_deg`, `mean_deg`, `p95_deg` (over the object), `ok_fraction` (status OK) and
    `nonfinite` (count of NaN/Inf outputs, which must be 0).
    """
    if name not in SWEEPS:
        raise ValueError(f"name must be one of {tuple(SWEEPS)}, got {name!r}")
    values = SWEEPS[name] if values is None else tuple(values)
    methods = ROBUST_SWEEP_METHODS if methods is None else tuple(methods)
    key = as_key(key, default=0)
    names = list(methods) + (["near-l2"] if name == "near_distance_mm" else [])
    out = {"name": name, "values": list(values), "h": h, "scene": [],
           "methods": {m: {f: [] for f in ("median_deg", "mean_deg", "p95_deg", "ok_fraction",
                                           "nonfinite")} for m in names}}
    with Stages(len(values) * len(names), progress) as stages:
        for i, value in enumerate(values):
            scene, solver_lights, extra = _scene_for(name, value, h, jax.random.fold_in(key, i))
            m = np.asarray(scene.mask)
            out["scene"].append({
                "shadowed": float(np.asarray(scene.shadow)[:, m].mean()),
                "saturated": float((np.asarray(scene.images)[:, m] >= 1).mean()),
                "specular": float((np.asarray(scene.specular)[:, m] > 0.02).mean()),
            })
            for meth in names:
                label = f"{name}={value:g}: {meth}"
                if meth == "near-l2":
                    # only the normals are scored: FC's steps, as the sweep's figures were
                    # measured (the default "lsq" gives the same normals, in 3x the time)
                    res = stages.run(label, near_photometric_stereo, scene.images,
                                     extra["positions"], mask=m, height0=extra["level"],
                                     pixel_size=extra["pixel"], max_steps=8,
                                     integration="fc").ps
                else:
                    res = stages.run(label, photometric_stereo, scene.images, solver_lights,
                                     mask=m, method=meth)
                _record(out["methods"][meth], res, scene.normals, m)
    return out


def _record(rec, res, truth, mask):
    """Append `res`'s error against `truth` over `mask` to `sweep`'s lists for one method."""
    st = angular_stats(res.normals, truth, mask=mask)
    for f in ("median_deg", "mean_deg", "p95_deg"):
        rec[f].append(st[f])
    rec["ok_fraction"].append(float((np.asarray(res.status)[mask] == Status.OK).mean()))
    rec["nonfinite"].append(int(sum((~np.isfinite(np.asarray(a))).sum()
                                    for a in (res.normals, res.albedo, res.residual))))
