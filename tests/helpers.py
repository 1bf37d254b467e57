"""Shared test helpers: synthetic scenes and a dtype-aware tolerance."""

import numpy as np

import jaxps


def tol(dtype) -> float:
    return {np.dtype(np.float32): 1e-4, np.dtype(np.float64): 1e-9}[np.dtype(dtype)]


def face_scene(h=96, lights=None, noise=0.0, seed=0):
    import jax

    surface = jaxps.synthetic.face_like(h)
    lights = jaxps.synthetic.scanner_lights(20.0) if lights is None else lights
    return jaxps.synthetic.render_scene(surface, lights, noise=noise,
                                        key=jax.random.key(seed) if noise else None)


def sphere_scene(h=96, lights=None):
    surface = jaxps.synthetic.sphere(h, max_zenith_deg=60.0)
    lights = jaxps.synthetic.scanner_lights(20.0) if lights is None else lights
    return jaxps.synthetic.render_scene(surface, lights)
