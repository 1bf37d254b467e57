"""Reconstruct and relight a face lit by lamps 60 cm away, with each pixel's own light.

A walk-through scanner's lamps stand close to the subject, so each lamp reaches each point of
the face from a slightly different direction, and more weakly the farther the point is. Taken
as distant lights seen from the frame's centre they bend the normals and the fitted
reflectance. Here a rendered face under five lamps 600 mm away is solved both ways:
photometric stereo with the lamps' directions from the centre, and
`jaxps.near_photometric_stereo` with their positions; then a BRDF is fitted to each
(`jaxps.fit_brdf`, with per-pixel lights for the near solve) and the face is relit under a new
distant light, where the truth is known.

    python examples/near_lamps.py --out near-out
"""

import argparse
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

import jaxps

# --8<-- [start:body]
pixel_mm = 1.0  # the size of a pixel at the face
surface = jaxps.synthetic.face_like(128)
mask = np.asarray(surface.mask)
y, x = np.mgrid[:mask.shape[0], :mask.shape[1]]
albedo = jnp.asarray(np.where(mask, 0.65 + 0.2 * np.sin(x / 9.0) * np.cos(y / 13.0), 0),
                     jnp.float32)
depth = surface.height * pixel_mm
points = jaxps.surface_points(depth - depth[mask].mean(), pixel_size=pixel_mm)

# Five lamps 600 mm from the face's centre, in mm, camera frame (x right, y up, z toward the
# camera), the origin at the frame's centre at the face's mean depth.
positions = 600.0 * jaxps.synthetic.scanner_lights(zenith_deg=20.0)
lamp_lights, falloff = jaxps.near_light_field(positions, points)  # (K, H, W, 3), (K, H, W)
noise = 0.005 * jax.random.normal(jax.random.key(0), falloff.shape)
images = jnp.where(mask, jaxps.render_lambertian(surface.normals, albedo, lamp_lights)
                   * falloff + noise, 0)

# The lamps as distant lights, from the frame's centre, against their positions.
directions = positions / np.linalg.norm(positions, axis=1, keepdims=True)
distant = jaxps.photometric_stereo(images, directions, mask=mask)
near = jaxps.near_photometric_stereo(images, positions, mask=mask, pixel_size=pixel_mm)
print(f"near_photometric_stereo: {near.steps} steps, converged {near.converged}")
for name, res in (("lamps as distant lights", distant), ("near lamps", near.ps)):
    s = jaxps.evaluate.angular_stats(res.normals, surface.normals, mask=mask)
    print(f"normals, {name}: median {s['median_deg']:.2f} deg, p95 {s['p95_deg']:.2f} deg")

# A BRDF from each: the near fit takes each pixel's light and the frames with the lamps'
# fall-off divided out. Relit under a distant light at 30 degrees, where the truth is known.
new = jaxps.lights_from_angles([30.0], [10.0])
truth = np.asarray(jaxps.render_lambertian(surface.normals, albedo, new))[0]
fits = {
    "lamps as distant lights": (images, distant, directions),
    "near lamps": (images / near.falloff, near.ps, near.lights),
}
relit = {}
for name, (frames, res, lights) in fits.items():
    ok = mask & (np.asarray(res.status) == 0)
    model = jaxps.fit_brdf(frames, res.normals, res.albedo, lights, mask=ok)
    relit[name] = np.asarray(jaxps.relight(model, res.normals, res.albedo, new))[0]
    rms = np.sqrt(np.mean((relit[name] - truth)[mask] ** 2))
    print(f"relit at (30, 10) deg, {name}: RMS error {rms:.4f} (albedo 0.45-0.85)")
# --8<-- [end:body]


def main(out: pathlib.Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    short = {"lamps as distant lights": "distant", "near lamps": "near"}
    maps = {f"normals, {short[name]}": np.asarray(jaxps.angular_error(
        res.normals, surface.normals, mask=mask)) for name, res in (
            ("lamps as distant lights", distant), ("near lamps", near.ps))}
    maps |= {f"relit, {short[name]}": np.abs(img - truth) for name, img in relit.items()}
    units = {k: "degrees" if k.startswith("normals") else "|relit - truth|" for k in maps}
    vmax = {k: 8.0 if k.startswith("normals") else 0.05 for k in maps}  # one scale per row
    jaxps.evaluate.plot_error_maps(maps, mask=mask, units=units, vmax=vmax,
                                   path=out / "near_lamps.png")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("near-out"))
    main(ap.parse_args().out)
