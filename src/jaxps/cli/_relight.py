"""`jaxps relight`: fit a BRDF to a capture and render it under new lights (PNGs + animation).

The eager, file-facing side of `jaxps.fit_brdf` / `jaxps.relight`: `relight_capture` does the
work, `run` parses the command's arguments and calls it.
"""

from __future__ import annotations

import json
import os

import numpy as np

from ..acquisition import load_capture
from ..acquisition._files import linear_to_srgb
from ..core._progress import Stages
from ..lights import lights_from_angles
from ..ps import near_photometric_stereo, photometric_stereo
from ..reflectance import fit_brdf, relight
from ..report._progress import progress_bar
from ..report._writers import write_json
from ._reconstruct import (
    _NEAR_STEPS_INTEGRATION,
    _card_line,
    _dropped_line,
    _dropped_why,
    _intensities,
    _light_check,
    _light_line,
    _motion,
    _near_capture,
    _near_summary,
    _positions,
    _srgb_decoded,
    _srgb_line,
)

__all__ = ["circle_lights", "relight_capture", "run"]


def circle_lights(n: int, zenith_deg: float) -> np.ndarray:
    """`(n, 3)` unit lights at `zenith_deg` from the view axis, azimuths 0..360° (camera frame)."""
    phi = np.linspace(0, 2 * np.pi, n, endpoint=False)
    z = np.radians(zenith_deg)
    return np.stack([np.sin(z) * np.cos(phi), np.sin(z) * np.sin(phi),
                     np.full(n, np.cos(z))], -1).astype(np.float32)


def _to_8bit(img: np.ndarray, scale: float, srgb: bool) -> np.ndarray:
    """`img / scale` as 8-bit codes, sRGB-encoded when the frames were decoded from sRGB (so
    that a relit image looks like the photographs it was fitted to), else linear."""
    v = np.clip(img / scale, 0, 1)
    return np.round((linear_to_srgb(v) if srgb else v) * 255).astype(np.uint8)


def relight_capture(
    frames,
    out: str,
    *,
    lights=None,
    yale_names: bool = False,
    ambient=None,
    mask="auto",
    crop_face: bool = False,
    method: str = "wrap_ggx",
    new_lights: list[tuple[float, float]] = (),
    circle_zenith_deg: float = 30.0,
    circle_frames: int = 36,
    n_samples: int = 100_000,
    max_steps: int = 30,
    seed: int = 0,
    check_quality: bool = True,
    register: bool = True,
    intensities: str = "frontal",
    intensity_mask=None,
    intensity_normal=None,
    intensity_ratios=None,
    light_positions=None,
    pixel_size: float | None = None,
    bits: int | None = None,
    linearize: str = "auto",
) -> dict:
    """Fit `method` to a capture and write relit PNGs, `relight.gif` and `relight.json` to `out`.

    **Arguments:**
    - `frames`, `lights`, `yale_names`, `ambient`, `mask`, `bits`, `linearize`: as for
      `jaxps.acquisition.load_capture` (grey frames; colour frames are averaged to grey;
      `"srgb_decoded"` in the summary says whether the files were decoded from sRGB).
    - `crop_face`: crop the frames to the detected face first, as `jaxps reconstruct
      --crop-face` does (`"crop"` in the summary: top, left, height, width); the relit
      images are of the crop.
    - `method`: one of `jaxps.BRDF_METHODS` (default `"wrap_ggx"`, `fit_brdf`'s default: wrap
      diffuse + GGX lobe with normals refined jointly, the one model below Lambert's law on
      held-out lights on every shared Yale B face; `"auto"`: Lambert's law unless the training
      frames show, leave-one-light-out, that a richer model predicts unseen lights).
    - `new_lights`: (azimuth, elevation) pairs in degrees (Yale B convention), one PNG each.
    - `circle_zenith_deg`, `circle_frames`: the animation's light circles the view axis at this
      zenith angle in this many frames.
    - `n_samples`, `max_steps`, `seed`: passed to `fit_brdf` (`key=jax.random.key(seed)`).
    - `check_quality`: drop the frames `jaxps.check_frames` flags (corrupt, badly exposed or
      inconsistent) before fitting; they are listed under `"dropped_frames"` in the summary,
      with their reasons under `"dropped_why"` (on by default, as in `load_capture`).
    - `register`: undo motion between frames (see `load_capture`; `"motion"` in the summary).
    - `intensities`, `intensity_mask`, `intensity_normal`, `intensity_ratios`: each frame's
      flash strength, as for `load_capture` (`"intensities"` in the summary, as
      `jaxps reconstruct` writes it).
    - `light_positions`, `pixel_size`: near lamps, as for `jaxps reconstruct` (millimetres,
      origin at the frame's centre at the subject's mean depth; `lights` is then not given).
      The frames are solved by `near_photometric_stereo`, and the BRDF is fitted with each
      pixel's own light directions and the fall-off divided out (`fit_brdf` with
      `NearResult.lights`). The new lights stay distant: a relit image shows the face under a
      distant light as bright as a lamp is at the origin. `relight.json` holds
      `"near_lights"`.

    The PNGs and the GIF are scaled so that the frames' 99.5th percentile in the mask is full
    scale (`"png_scale"`), and sRGB-encoded when the frames were decoded from sRGB, so that
    they look like the photographs, else linear (`"png_encoding"`).

    **Returns:** the summary written to `relight.json` (fit report, files, timings).
    """
    import jax
    from PIL import Image

    if len(frames) == 1 and os.path.isdir(frames[0]):
        frames = frames[0]
    if circle_frames < 1:
        raise ValueError(f"circle_frames must be >= 1, got {circle_frames}")
    if not 0 <= circle_zenith_deg < 90:
        raise ValueError(f"circle_zenith_deg must be in [0, 90), got {circle_zenith_deg}")
    positions = None
    if light_positions is not None or pixel_size is not None:
        positions = _positions(light_positions, pixel_size, lights, yale_names, intensities)
        lights = positions / np.linalg.norm(positions, axis=1, keepdims=True)
    stages = Stages(3, progress_bar())
    try:
        def load():
            cap = load_capture(frames, lights=lights, yale_names=yale_names, ambient=ambient,
                               mask=mask, crop_face=crop_face, check_quality=check_quality,
                               register=register, intensities=intensities,
                               intensity_mask=intensity_mask, intensity_normal=intensity_normal,
                               intensity_ratios=intensity_ratios, bits=bits,
                               linearize=linearize)
            if cap.lights is None:
                raise ValueError("no lights: give --lights FILE or --yale-names")
            if positions is None:
                return None, None, cap
            return _near_capture(frames, cap, positions, pixel_size, intensity_mask)

        near_positions, centre, cap = stages.run("load frames", load, time_key="load")
        images = cap.images.mean(axis=-1) if cap.images.ndim == 4 else cap.images

        def fit():
            # A sample clipped in its raw frame is left out of the fit (NaN): divided by its
            # frame's intensity it may read below `fit_brdf`'s saturation level.
            unclipped = np.where(cap.saturated, np.nan, images)
            if near_positions is None:
                ps = photometric_stereo(images, cap.lights, mask=cap.mask,
                                        sample_mask=~cap.saturated)
                near, fit_images, fit_lights = None, unclipped, cap.lights
            else:
                near = near_photometric_stereo(images, near_positions, mask=cap.mask,
                                               pixel_size=pixel_size, centre=centre,
                                               sample_mask=~cap.saturated,
                                               integration=_NEAR_STEPS_INTEGRATION)
                ps = near.ps
                # each sample as a unit-strength lamp at the pixel's own direction would give it
                fit_images = unclipped / np.asarray(near.falloff)
                fit_lights = near.lights
            fit_mask = cap.mask & (np.asarray(ps.status) == 0)
            model = fit_brdf(fit_images, ps.normals, ps.albedo, fit_lights, mask=fit_mask,
                             method=method, key=jax.random.key(seed), n_samples=n_samples,
                             max_steps=max_steps)
            return ps, near, fit_mask, model

        ps, near, fit_mask, model = stages.run(f"fit {method}", fit, time_key="fit")
        os.makedirs(out, exist_ok=True)
        scale = float(np.percentile(images[:, fit_mask], 99.5)) or 1.0
        srgb = _srgb_decoded(frames, linearize)

        def render():
            files = []
            if new_lights:
                az, el = zip(*new_lights)
                relit = np.asarray(relight(model, ps.normals, ps.albedo,
                                           lights_from_angles(az, el), mask=fit_mask))
                for (a, e), img in zip(new_lights, relit):
                    name = f"relit_A{a:+04.0f}E{e:+03.0f}.png"
                    Image.fromarray(_to_8bit(img, scale, srgb)).save(os.path.join(out, name))
                    files.append(name)
            circle = circle_lights(circle_frames, circle_zenith_deg)
            anim = np.asarray(relight(model, ps.normals, ps.albedo, circle, mask=fit_mask))
            frames_8 = [Image.fromarray(_to_8bit(img, scale, srgb)) for img in anim]
            frames_8[0].save(os.path.join(out, "relight.gif"), save_all=True,
                             append_images=frames_8[1:], duration=80, loop=0)
            return [*files, "relight.gif"]

        files = stages.run("relight and write", render, time_key="relight_and_write")
    finally:
        stages.close()

    fit = model.fit._asdict()
    summary = {
        "frames": list(cap.names), "dropped_frames": list(cap.dropped),
        "dropped_why": _dropped_why(cap), "crop": cap.crop,
        "srgb_decoded": srgb,
        "method": method,
        "intensities": _intensities(cap, intensity_mask, intensity_normal, intensity_ratios),
        "motion": _motion(cap),
        "light_check": _light_check(cap),
        "fit": fit,
        "fit_rmse_gray_8bit": fit["rmse"] * 255,
        "mask_pixels": int(fit_mask.sum()), "png_scale": scale,
        "png_encoding": "srgb" if srgb else "linear",
        "circle_zenith_deg": circle_zenith_deg, "files": files,
        "timings_s": {k: round(v, 3) for k, v in stages.times.items()},
        "note": "timings include JIT compilation",
    }
    if near is not None:
        summary["near_lights"] = _near_summary(near, near_positions, pixel_size, centre)
    write_json(os.path.join(out, "relight.json"), json.loads(json.dumps(summary)))
    return summary


def run(args) -> int:
    try:
        new_lights = [tuple(float(v) for v in s.split(",")) for s in args.light]
    except ValueError:
        raise ValueError(f"--light must be AZ,EL in degrees, got {args.light}") from None
    if any(len(v) != 2 for v in new_lights):
        raise ValueError(f"--light must be AZ,EL in degrees, got {args.light}")
    s = relight_capture(
        args.frames, args.out, lights=args.lights, yale_names=args.yale_names,
        ambient=args.ambient, mask=args.mask, crop_face=args.crop_face, method=args.method,
        new_lights=new_lights, circle_zenith_deg=args.circle_zenith,
        circle_frames=args.circle_frames,
        n_samples=args.samples, max_steps=args.max_steps, seed=args.seed,
        check_quality=args.check_quality, register=args.register,
        intensities=args.intensities, intensity_mask=args.intensity_mask,
        intensity_normal=args.intensity_normal, intensity_ratios=args.intensity_ratios,
        light_positions=args.light_positions, pixel_size=args.pixel_size, bits=args.bits,
        linearize=args.linearize)
    if line := _srgb_line(s["srgb_decoded"], args.linearize):
        print("relight: " + line)
    if s["dropped_frames"]:
        print("relight: " + _dropped_line(s))
    if "target" in s["intensities"]:
        print("relight: " + _card_line(s["intensities"]))
    if line := _light_line(s["light_check"]):
        print("relight: " + line)
    fit = s["fit"]
    print(f"relight: {args.method} on {len(s['frames'])} frames, {s['mask_pixels']} pixels: "
          f"training RMSE {fit['rmse']:.4g} (x255 = {s['fit_rmse_gray_8bit']:.2f}), "
          f"R {fit['r']:.4f}, {fit['steps']} steps, converged {fit['converged']}")
    if fit.get("choice"):
        print(f"relight: {fit['message']}")
    print(f"outputs: {args.out}/" + " ".join(s["files"]) + " relight.json")
    return 0
