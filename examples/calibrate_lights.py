"""Calibrate a scanner's lights by differentiating through photometric stereo.

A walk-through scanner's five flashes are mounted at design angles, but each sits a few degrees
off and fires at its own strength. Photometric stereo of a matte sphere, whose normals are
known from its outline, shows both errors. Here optimistix's Levenberg–Marquardt adjusts the
five light directions and the four relative flash strengths until the sphere's recovered normals
match its true ones, with the Jacobian taken through `jaxps.photometric_stereo` itself. The
calibration is then used on a face captured under the same lights.

    python examples/calibrate_lights.py --out calibrate-out
"""

import argparse
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import jaxps

# --8<-- [start:body]
# The truth, unknown to the calibration: the design lights tilted by up to 3 degrees, and the
# flashes firing at 0.92-1.10 of their nominal strength.
design = jnp.asarray(jaxps.synthetic.scanner_lights(zenith_deg=20.0))
rng = np.random.default_rng(7)
tilt = jnp.asarray(rng.uniform(-0.05, 0.05, design.shape), jnp.float32)
true_lights = (design + tilt) / jnp.linalg.norm(design + tilt, axis=1, keepdims=True)
true_strength = jnp.asarray([1.0, 0.92, 1.10, 1.04, 0.95])


def capture(surface, seed):
    """Frames of `surface` under the true lights and flash strengths, 0.5% noise."""
    return jaxps.synthetic.render_scene(surface, true_lights * true_strength[:, None],
                                        noise=0.005, key=jax.random.key(seed))


# The target: a matte sphere (normals within 60 degrees of the view axis: no attached shadow).
sphere = capture(jaxps.synthetic.sphere(64, max_zenith_deg=60.0), seed=0)


def lights_of(params):
    """Design lights moved sideways by `tilt` (x, y per light), unit length."""
    moved = design + jnp.pad(params["tilt"], ((0, 0), (0, 1)))
    return moved / jnp.linalg.norm(moved, axis=1, keepdims=True)


def misfit(params, args):
    """Per pixel: photometric stereo's normal minus the sphere's, and its Lambertian residual.

    The normals alone do not pin the lights down: with five lights, any light error that lies
    in the two directions the least-squares solve projects away leaves the normals unchanged.
    Those errors do show in the residual, so both are fitted."""
    lights = lights_of(params)
    strength = jnp.exp(jnp.concatenate([jnp.zeros(1), params["log_strength"]]))  # e_0 = 1
    res = jaxps.photometric_stereo(sphere.images / strength[:, None, None], lights,
                                   mask=sphere.mask)
    inside = sphere.mask
    return (jnp.where(inside[..., None], res.normals - sphere.normals, 0),
            jnp.where(inside, res.residual / sphere.albedo.max(), 0))


start = {"tilt": jnp.zeros((5, 2)), "log_strength": jnp.zeros(4)}
# 20 steps: in float32 the solver's own stopping test (changes below rtol) is not met, but the
# lights stop moving after about 10 (10 and 20 steps give the same face error below).
fit = optx.least_squares(misfit, optx.LevenbergMarquardt(rtol=1e-4, atol=1e-6), start,
                         max_steps=20, throw=False)
lights = lights_of(fit.value)
strength = jnp.exp(jnp.concatenate([jnp.zeros(1), fit.value["log_strength"]]))


def light_error_deg(estimate):
    cos = jnp.clip(jnp.sum(estimate * true_lights, axis=1), -1, 1)
    return np.degrees(np.asarray(jnp.arccos(cos)))


print(f"Levenberg-Marquardt: {int(fit.stats['num_steps'])} steps")
print(f"light direction error (deg): design {light_error_deg(design).max():.2f} max -> "
      f"calibrated {light_error_deg(lights).max():.3f} max")
print(f"flash strength error: assumed equal {np.abs(1 / true_strength - 1).max():.1%} max -> "
      f"calibrated {np.abs(np.asarray(strength / true_strength) - 1).max():.2%} max")

# The calibration on a face captured under the same flashes.
face = capture(jaxps.synthetic.face_like(128), seed=1)
before = jaxps.photometric_stereo(face.images, design, mask=face.mask)
after = jaxps.photometric_stereo(face.images / strength[:, None, None], lights, mask=face.mask)
truth = jaxps.photometric_stereo(face.images / true_strength[:, None, None], true_lights,
                                 mask=face.mask)  # the floor the noise leaves
err = {name: jaxps.evaluate.angular_stats(r.normals, face.normals, mask=face.mask)
       for name, r in (("design lights", before), ("calibrated", after), ("true lights", truth))}
for name, s in err.items():
    print(f"face normals, {name}: median {s['median_deg']:.2f} deg, p95 {s['p95_deg']:.2f} deg")
# --8<-- [end:body]


def main(out: pathlib.Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    maps = {name: np.asarray(jaxps.angular_error(r.normals, face.normals, mask=face.mask))
            for name, r in (("design lights", before), ("calibrated lights", after))}
    jaxps.evaluate.plot_error_maps(maps, mask=np.asarray(face.mask),
                                   units={k: "degrees" for k in maps},
                                   path=out / "calibrate_lights.png")
    return {name: s["median_deg"] for name, s in err.items()}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("calibrate-out"))
    main(ap.parse_args().out)
