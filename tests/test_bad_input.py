"""Bad arguments to the public functions: each raises a `ValueError` that names the argument.

One table over the public API, so that a new check, or one lost in a rewrite, shows here. The
rows marked "before" raised something else, or nothing, until the twenty-fifth session; the
tests of each module hold the values these functions return.
"""

import numpy as np
import pytest

import jaxps
from jaxps import acquisition as acq
from jaxps import evaluate as ev
from jaxps import report, stability

K, H, W = 5, 16, 12
LIGHTS = jaxps.lights_from_angles([0, 25, -25, 0, 0], [0, 0, 0, 20, -20])
_flat = np.zeros((H, W, 3), np.float32)
_flat[..., 2] = 1
NORMALS = _flat
_rng = np.random.default_rng(0)
IMAGES = (0.3 + 0.4 * _rng.random((K, H, W))).astype(np.float32)
ALBEDO = np.full((H, W), 0.5, np.float32)
MASK = np.ones((H, W), bool)
HEIGHT = np.zeros((H, W), np.float32)
POINTS = _rng.normal(size=(30, 3))

CASES = [
    # photometric stereo
    ("ps: 2-D images", lambda: jaxps.photometric_stereo(IMAGES[0], LIGHTS), r"images must be"),
    ("ps: two lights", lambda: jaxps.photometric_stereo(IMAGES[:2], LIGHTS[:2]), "at least 3"),
    ("ps: lights rows", lambda: jaxps.photometric_stereo(IMAGES, LIGHTS[:4]), "lights have 4"),
    ("ps: lights (K, 2)", lambda: jaxps.photometric_stereo(IMAGES, LIGHTS[:, :2]), "lights must"),
    ("ps: zero light", lambda: jaxps.photometric_stereo(
        IMAGES, np.vstack([LIGHTS[:4], [0, 0, 0]])), "zero vectors"),
    ("ps: coplanar lights", lambda: jaxps.photometric_stereo(
        IMAGES[:3], np.array([[0, 0, 1.0]] * 3)), "do not span 3-D"),
    ("ps: mask shape", lambda: jaxps.photometric_stereo(IMAGES, LIGHTS, mask=MASK[1:]), "mask"),
    ("ps: mask of 0.5", lambda: jaxps.photometric_stereo(IMAGES, LIGHTS, mask=MASK * 0.5),
     "mask must be bool"),
    ("ps: method", lambda: jaxps.photometric_stereo(IMAGES, LIGHTS, method="L2"), "method"),
    ("ps: option of another method", lambda: jaxps.photometric_stereo(
        IMAGES, LIGHTS, max_steps=5), "unknown option"),
    ("ps: sample_mask shape", lambda: jaxps.photometric_stereo(
        IMAGES, LIGHTS, sample_mask=MASK), "sample_mask"),
    ("ps: uint8 frames", lambda: jaxps.photometric_stereo(
        (IMAGES * 255).astype(np.uint8), LIGHTS), "floating point"),
    ("ps: 16-bit scale", lambda: jaxps.photometric_stereo(IMAGES * 65535, LIGHTS), r"\[0, 1\]"),
    ("ps: empty image", lambda: jaxps.photometric_stereo(IMAGES[:, :0], LIGHTS), "one pixel"),
    ("ps: shadow threshold at saturation", lambda: jaxps.photometric_stereo(
        IMAGES, LIGHTS, shadow_threshold=1.0), "shadow_threshold .1. must be below saturation"),
    ("batch: shadow threshold above saturation", lambda: jaxps.photometric_stereo_batch(
        np.stack([IMAGES] * 2), LIGHTS, shadow_threshold=0.5, saturation=0.4),
     "every sample would be dropped"),
    ("ps: irls max_steps", lambda: jaxps.photometric_stereo(
        IMAGES, LIGHTS, method="irls", max_steps=0), "max_steps"),
    ("ps: prior_weight", lambda: jaxps.photometric_stereo(
        IMAGES, LIGHTS, method="semi_calibrated", prior_weight=-1), "prior_weight"),
    ("batch: one capture", lambda: jaxps.photometric_stereo_batch(IMAGES, LIGHTS), "images"),
    ("batch: ragged", lambda: jaxps.photometric_stereo_batch([IMAGES, IMAGES[:, 1:]], LIGHTS),
     "capture 1"),
    ("batch: vmap_size", lambda: jaxps.photometric_stereo_batch(
        np.stack([IMAGES] * 2), LIGHTS, vmap_size=0), "vmap_size"),
    ("near: positions rows", lambda: jaxps.near_photometric_stereo(IMAGES, LIGHTS[:4] * 500),
     "positions"),
    ("near: pixel_size", lambda: jaxps.near_photometric_stereo(
        IMAGES, LIGHTS * 500, pixel_size=0), "pixel_size"),
    ("intensities: method", lambda: jaxps.intensity_estimate(IMAGES, LIGHTS, method="median"),
     "method"),
    ("visibility: (K, 2)", lambda: jaxps.flash_visibility(LIGHTS[:, :2]), "lights"),
    # lights
    ("angles: lengths", lambda: jaxps.lights_from_angles([0, 1], [0]), "same length"),
    ("angles: NaN", lambda: jaxps.lights_from_angles([np.nan], [0]), "finite"),
    ("angles_from_lights: zero", lambda: jaxps.angles_from_lights(np.zeros((2, 3))), "zero"),
    ("validate_lights: 1-D", lambda: jaxps.validate_lights(np.ones(3)), r"\(K, 3\)"),
    ("light field: points", lambda: jaxps.near_light_field(LIGHTS * 100, NORMALS[..., :2]),
     "points"),
    ("light field: mu", lambda: jaxps.near_light_field(LIGHTS * 100, NORMALS, mu=-1), "mu"),
    ("light field: lamp at the origin", lambda: jaxps.near_light_field(
        np.zeros((K, 3)), NORMALS), "origin"),
    ("surface_points: pixel_size", lambda: jaxps.surface_points(HEIGHT, pixel_size=0),
     "pixel_size"),
    ("chrome: empty mask", lambda: jaxps.lights_from_chrome(IMAGES, np.zeros((H, W))), "empty"),
    ("chrome: level", lambda: jaxps.lights_from_chrome(IMAGES, MASK, level=2), "level"),
    ("save_lights: NaN", lambda: jaxps.save_lights("unused.txt", np.full((3, 3), np.nan)),
     "NaN"),
    # integration
    ("integrate: (H, W, 2)", lambda: jaxps.integrate(NORMALS[..., :2]), "normals"),
    ("integrate: mask shape", lambda: jaxps.integrate(NORMALS, mask=MASK[1:]), "mask"),
    ("integrate: method", lambda: jaxps.integrate(NORMALS, method="poisson"), "method"),
    ("integrate: pixel_size NaN", lambda: jaxps.integrate(NORMALS, pixel_size=np.nan),
     "pixel_size"),
    ("integrate: no valid normal", lambda: jaxps.integrate(np.full((H, W, 3), np.nan)),
     "no finite"),
    ("integrate: intrinsics", lambda: jaxps.integrate(NORMALS, intrinsics=np.eye(2)),
     "intrinsics"),
    ("integrate: bilateral k", lambda: jaxps.integrate(NORMALS, method="bilateral", k=-1),
     "k must"),
    ("normals_from_height: 1-D", lambda: jaxps.normals_from_height(HEIGHT[0]), "z must"),
    ("angular_error: shapes", lambda: jaxps.angular_error(NORMALS, NORMALS[1:]), "normals_a"),
    # shading and reflectance
    ("oren_nayar: shapes (before)", lambda: jaxps.oren_nayar(
        np.zeros(3), np.zeros(2), np.zeros(3), 0.1), "broadcast together"),
    ("oren_nayar: sigma", lambda: jaxps.oren_nayar(0.1, 0.1, 0.1, -0.1), "sigma"),
    ("render_lambertian: albedo", lambda: jaxps.render_lambertian(NORMALS, ALBEDO[1:], LIGHTS),
     "albedo"),
    ("render_oren_nayar: sigma", lambda: jaxps.render_oren_nayar(
        NORMALS, ALBEDO, LIGHTS, np.zeros(3)), "sigma"),
    ("render_oren_nayar: form", lambda: jaxps.render_oren_nayar(
        NORMALS, ALBEDO, LIGHTS, 0.1, form="exact"), "form"),
    ("lambertian_check: bin_deg", lambda: jaxps.lambertian_check(
        IMAGES, NORMALS, ALBEDO, LIGHTS, bin_deg=0), "bin_deg"),
    ("fit_roughness: per", lambda: jaxps.fit_roughness(
        IMAGES, NORMALS, ALBEDO, LIGHTS, per="face"), "per must"),
    ("fit_brdf: method", lambda: jaxps.fit_brdf(IMAGES, NORMALS, ALBEDO, LIGHTS, method="nn"),
     "method"),
    ("fit_brdf: empty mask", lambda: jaxps.fit_brdf(
        IMAGES, NORMALS, ALBEDO, LIGHTS, mask=~MASK), "mask is empty"),
    ("fit_brdf: hidden", lambda: jaxps.fit_brdf(
        IMAGES, NORMALS, ALBEDO, LIGHTS, method="mlp", hidden=(0,)), "hidden"),
    ("brdf_features: lights", lambda: jaxps.brdf_features(NORMALS, LIGHTS[:, :2]), "lights"),
    ("compare_models: train", lambda: jaxps.compare_models(
        IMAGES, LIGHTS, train=np.ones(4, bool)), "train"),
    # acquisition
    ("check_frames: 2-D", lambda: jaxps.check_frames(IMAGES[0]), "frames"),
    ("check_frames: names", lambda: jaxps.check_frames(IMAGES, names=["a"]), "names"),
    ("check_frames: thresholds (before)", lambda: jaxps.check_frames(
        IMAGES, thresholds=jaxps.QualityThresholds(comb=-1.0)), "comb="),
    ("drop_flagged: min_frames (before)", lambda: acq.drop_flagged(
        IMAGES, LIGHTS, jaxps.check_frames(IMAGES), min_frames=0), "min_frames"),
    ("estimate_shifts: reference", lambda: jaxps.estimate_shifts(IMAGES, reference=9),
     "reference"),
    ("estimate_shifts: normalization", lambda: jaxps.estimate_shifts(
        IMAGES, normalization="none"), "normalization"),
    ("register_frames: max_shift", lambda: jaxps.register_frames(IMAGES, max_shift=-1),
     "max_shift"),
    ("shift_frames: rows", lambda: jaxps.shift_frames(IMAGES, np.zeros((4, 2))), "shifts"),
    ("subtract_ambient: shape", lambda: acq.subtract_ambient(IMAGES, IMAGES[0, 1:]), "ambient"),
    ("equalize_mean: dark", lambda: acq.equalize_mean(IMAGES * 0), "zero mean"),
    ("mask_from_intensity: threshold (before)", lambda: acq.mask_from_intensity(
        IMAGES, threshold="auto"), "threshold"),
    ("crop: over the edge (before)", lambda: acq.crop(IMAGES, (0, 0, 100, 100), axis=1),
     "box"),
    ("bucket_box: multiple", lambda: acq.bucket_box((0, 0, 4, 4), (H, W), multiple=0),
     "multiple"),
    ("detect_face: 1-D (before)", lambda: acq.detect_face(np.zeros(10)), "image must"),
    ("detect_face: pad (before)", lambda: acq.detect_face(HEIGHT, pad=-1), "pad"),
    ("load_stack: no files", lambda: acq.load_stack([]), "no frames"),
    ("load_capture: no files", lambda: acq.load_capture([]), "frames"),
    # evaluation
    ("height_stats: shapes", lambda: ev.height_stats(HEIGHT, HEIGHT[1:]), "reference"),
    ("height_stats: align", lambda: ev.height_stats(HEIGHT, HEIGHT, align="icp"), "align"),
    ("icp: (N, 2)", lambda: ev.icp(POINTS[:, :2], POINTS), "source"),
    ("icp: trim", lambda: ev.icp(POINTS, POINTS, trim=0), "trim"),
    ("icp: points on a line (before)", lambda: ev.icp(
        np.outer(np.arange(10.0), [1, 0, 0]), POINTS), "one line"),
    ("estimate_normals: neighbours (before)", lambda: ev.estimate_normals(
        POINTS, neighbours=2), "neighbours"),
    ("points_from_depth: intrinsics", lambda: ev.points_from_depth(HEIGHT, np.eye(2)),
     "intrinsics"),
    ("angular_stats: empty mask", lambda: ev.angular_stats(NORMALS, NORMALS, mask=~MASK),
     "empty"),
    ("plot_error_maps: shapes (before)", lambda: ev.plot_error_maps(
        {"a": HEIGHT, "b": HEIGHT[1:]}), "share one"),
    ("plot_error_maps: empty", lambda: ev.plot_error_maps({}), "empty"),
    ("plot_error_maps: units (before: ignored)", lambda: ev.plot_error_maps(
        {"height error": HEIGHT}, units={"height": "mm"}), r"units names \['height'\]"),
    # report and stability
    ("to_trimesh: pixel_size (before)", lambda: report.to_trimesh(
        HEIGHT, MASK, pixel_size=0), "pixel_size"),
    ("to_trimesh: mask", lambda: report.to_trimesh(HEIGHT, MASK[1:]), "mask"),
    ("ring_lights: zenith (before)", lambda: stability.ring_lights(5, 95.0), "zenith_deg"),
    ("perturb_lights: angle (before)", lambda: stability.perturb_lights(
        LIGHTS, np.nan, key=0), "angle_deg"),
    ("cast_shadow_mask: lights (before)", lambda: stability.cast_shadow_mask(
        HEIGHT, LIGHTS[:, :2]), "lights"),
    ("sweep: name", lambda: stability.sweep("blur"), "name"),
    ("status_counts: floats", lambda: jaxps.status_counts(np.array([1.5])), "status"),
    # synthetic scenes (`jaxps demo --size -5` was a TypeError, `--noise -1` no noise)
    ("face_like: negative size", lambda: jaxps.synthetic.face_like(-5), "h must be an int"),
    ("sphere: width", lambda: jaxps.synthetic.sphere(16, 1), "w must be an int"),
    ("render_scene: negative noise", lambda: jaxps.synthetic.render_scene(
        jaxps.synthetic.sphere(16), LIGHTS, noise=-0.01, key=0), "noise must be"),
]


@pytest.mark.parametrize("call, match", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_argument_raises_a_value_error_naming_it(call, match):
    with pytest.raises(ValueError, match=match):
        call()
