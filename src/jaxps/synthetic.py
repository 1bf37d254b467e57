"""Synthetic scenes with known truth: a sphere and a face-like relief, rendered under given lights.

Used by the demo, the tests and the benchmarks. Heights are in pixel units; gradients are exact
(from `jax.grad` of the analytic surface), so normals are the truth to the last bit.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .core._random import as_key
from .lights import lights_from_angles
from .shading import render_lambertian

__all__ = ["Scene", "face_like", "render_scene", "scanner_lights", "sphere"]


class Surface(NamedTuple):
    """A surface with known truth: `height` `(H, W)`, `normals` `(H, W, 3)`, `mask` `(H, W)`."""

    height: Float[Array, "H W"]
    normals: Float[Array, "H W 3"]
    mask: Bool[Array, "H W"]


class Scene(NamedTuple):
    """A rendered capture and its truth. `images` `(K, H, W)`, `lights` `(K, 3)`."""

    images: Float[Array, "K H W"]
    lights: Float[Array, "K 3"]
    normals: Float[Array, "H W 3"]
    albedo: Float[Array, "H W"]
    height: Float[Array, "H W"]
    mask: Bool[Array, "H W"]


def _pixel_grid(h: int, w: int):
    """Camera-frame pixel coordinates: x right, y up, origin at the image centre."""
    x = np.arange(w, dtype=np.float32) - (w - 1) / 2
    y = (h - 1) / 2 - np.arange(h, dtype=np.float32)
    return np.meshgrid(x, y)


_MIN_SIZE = 2


def _pixels(name: str, n) -> int:
    """`n` as an int image size, or a `ValueError` naming `name`."""
    if not (isinstance(n, (int, np.integer)) and n >= _MIN_SIZE):
        raise ValueError(f"{name} must be an int of at least {_MIN_SIZE} pixels, got {n!r}")
    return int(n)


def _surface_from_function(fn, h: int, w: int, mask) -> Surface:
    x, y = _pixel_grid(h, w)
    xs, ys = jnp.asarray(x.ravel()), jnp.asarray(y.ravel())
    z = jax.vmap(fn)(xs, ys)
    p, q = jax.vmap(jax.grad(fn, argnums=(0, 1)))(xs, ys)
    n = jnp.stack([-p, -q, jnp.ones_like(p)], axis=-1)
    n = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
    return Surface(z.reshape(h, w), n.reshape(h, w, 3), jnp.asarray(mask))


def sphere(h: int = 128, w: int | None = None, *, radius: float | None = None,
           max_zenith_deg: float = 80.0) -> Surface:
    """A hemisphere of `radius` pixels (default 0.45 min(H, W)) centred in the image.

    The mask keeps pixels whose normal is within `max_zenith_deg` of the view axis.
    """
    h = _pixels("h", h)
    w = h if w is None else _pixels("w", w)
    r = 0.45 * min(h, w) if radius is None else float(radius)
    x, y = _pixel_grid(h, w)
    rr = np.sqrt(x**2 + y**2)
    mask = rr < r * np.sin(np.radians(max_zenith_deg))

    def fn(x, y):
        return jnp.sqrt(jnp.maximum(r**2 - x**2 - y**2, 1e-3 * r**2))

    return _surface_from_function(fn, h, w, mask)


def face_like(h: int = 160, w: int | None = None) -> Surface:
    """A face-like relief: an ellipsoidal head with a nose, brow ridges, eye sockets and lips.

    Smooth everywhere inside an elliptical mask; heights up to about 0.35 H.
    """
    h = _pixels("h", h)
    w = round(h * 0.8) if w is None else _pixels("w", w)
    s = 0.5 * min(h, w / 0.8)
    a, b = 0.78 * s, 0.95 * s  # head half-width and half-height in pixels

    def bump(x, y, x0, y0, sx, sy, amp):
        return amp * jnp.exp(-0.5 * (((x - x0) / sx) ** 2 + ((y - y0) / sy) ** 2))

    def fn(x, y):
        u2 = (x / a) ** 2 + (y / b) ** 2
        head = 0.55 * s * jnp.sqrt(jnp.maximum(1.0 - u2, 0.0) + 0.05)
        nose = bump(x, y, 0.0, -0.05 * s, 0.09 * s, 0.28 * s, 0.22 * s)
        tip = bump(x, y, 0.0, -0.3 * s, 0.1 * s, 0.08 * s, 0.06 * s)
        brows = bump(x, y, -0.33 * s, 0.33 * s, 0.2 * s, 0.06 * s, 0.04 * s) + bump(
            x, y, 0.33 * s, 0.33 * s, 0.2 * s, 0.06 * s, 0.04 * s)
        eyes = bump(x, y, -0.33 * s, 0.18 * s, 0.13 * s, 0.08 * s, -0.07 * s) + bump(
            x, y, 0.33 * s, 0.18 * s, 0.13 * s, 0.08 * s, -0.07 * s)
        lips = bump(x, y, 0.0, -0.55 * s, 0.22 * s, 0.06 * s, 0.05 * s)
        return head + nose + tip + brows + eyes + lips

    x, y = _pixel_grid(h, w)
    mask = (x / a) ** 2 + (y / b) ** 2 < 0.9
    return _surface_from_function(fn, h, w, mask)


def scanner_lights(zenith_deg: float = 20.0, k: int = 5) -> Float[np.ndarray, "K 3"]:
    """A walk-through-scanner light set: one light at the camera (k=5) and four around it.

    The four outer lights sit at `zenith_deg` from the view axis, left, right, above, below.
    """
    if k not in (4, 5):
        raise ValueError(f"k must be 4 or 5, got {k}")
    az = [zenith_deg, -zenith_deg, 0.0, 0.0]
    el = [0.0, 0.0, zenith_deg, -zenith_deg]
    if k == 5:
        az, el = [0.0] + az, [0.0] + el
    return lights_from_angles(az, el)


def render_scene(
    surface: Surface,
    lights,
    *,
    albedo=None,
    noise: float = 0.0,
    key: jax.Array | int | None = None,
) -> Scene:
    """Render `surface` under `(K, 3)` lights with Lambert's law and optional Gaussian noise.

    `albedo` defaults to a smooth pattern in [0.45, 0.85]; outside the mask images are 0.
    Noise has standard deviation `noise` (in [0, 1] intensity units) and needs `key`, a JAX
    PRNG key or an int seed (`jax.random.key(seed)`).
    """
    if not noise >= 0:
        raise ValueError(f"noise must be a standard deviation >= 0, got {noise}")
    h, w = surface.mask.shape
    if albedo is None:
        x, y = _pixel_grid(h, w)
        albedo = 0.65 + 0.2 * np.sin(x / 9.0) * np.cos(y / 13.0)
    albedo = jnp.where(surface.mask, jnp.asarray(albedo, jnp.float32), 0)
    lights = jnp.asarray(lights, jnp.float32)
    images = render_lambertian(surface.normals, albedo, lights)
    if noise > 0:
        if key is None:
            raise ValueError("noise > 0 needs key (a jax.random.key or an int seed)")
        images = images + noise * jax.random.normal(as_key(key), images.shape, images.dtype)
    images = jnp.where(surface.mask, jnp.clip(images, 0, 1), 0)
    return Scene(images, lights, surface.normals, albedo, surface.height, surface.mask)
