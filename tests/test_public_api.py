"""The public API does not change when modules move.

`tests/data/public_api.json` is a snapshot of every name in `jaxps.__all__` and in the public
submodules (kind, signature, NamedTuple fields, enum members, constant values), taken from the
code before the restructure into one subpackage per stage. Rewrite it only for an intended API
change: `python tests/test_public_api.py > tests/data/public_api.json`, and say so in the note.
"""

import enum
import inspect
import json
import pathlib
import re
import subprocess
import sys
import types
import typing

ROOT = pathlib.Path(__file__).resolve().parents[1]
SNAPSHOT = ROOT / "tests" / "data" / "public_api.json"
PUBLIC_MODULES = ("acquisition", "evaluate", "synthetic", "stability", "report")
# Names added since the snapshot, on purpose: the stage subpackages (issue 14), and the quality,
# registration and psm loaders under `jaxps.acquisition`, the stage they belong to.
ADDED = {
    # Issue 16: the held-out relighting protocol (`score_relighting` and its result).
    # Issue 17: `flash_visibility`, how strongly a light layout shows its flash strengths.
    # Issue 18: `release_batch_outputs`, which frees the batch results kept for reuse.
    # Not from an issue: `angles_from_lights` and `save_lights`, the inverse of
    # `lights_from_angles` and the writer of the lights.txt that `load_lights` reads, which
    # `jaxps calibrate` uses. Not from an issue: `check_lights` and its result `LightCheck`
    # (is a lights file mirrored, or turned by 180 degrees? `load_capture` runs it).
    "jaxps": ["LightCheck", "RelightScore", "acquisition", "angles_from_lights",
              "check_lights", "cli", "core", "flash_visibility", "integration", "lights", "ps",
              "reflectance", "release_batch_outputs", "report", "save_lights",
              "score_relighting", "shading"],
    # Issue 18: `bucket_box`, face boxes grown to shape buckets (fewer compiles).
    # Issue 17: `target_ratios`, a reference target's per-light calibration for near lights.
    "jaxps.acquisition": ["FrameCheck", "QualityReport", "QualityThresholds", "Registration",
                          "bucket_box", "check_file", "check_frames", "drop_flagged",
                          "estimate_shifts", "load_psm", "register_frames", "shift_frames",
                          "target_ratios"],
    # Issue 15: a reconstruction as a textured trimesh mesh. Not from an issue: `progress_bar`,
    # a bar on stderr over the stages of a long call (`progress=`).
    "jaxps.report": ["progress_bar", "to_trimesh"],
    # Issue 18: the installed `jaxps` script's entry point (`main` with `gc.freeze`).
    "jaxps.cli": ["console"],
    # Not from an issue: `read_scan`, a ground-truth scan's mesh or point file for
    # `compare_to_scan` (and `jaxps report --truth-scan`), and the formats it reads.
    "jaxps.evaluate": ["SCAN_EXTENSIONS", "read_scan"],
}
# Changed on purpose since the snapshot (issue 17; the snapshot entries were rewritten):
# `load_capture(equalize=False)` and `reconstruct(equalize=False)` became
# `intensities="frontal"` (per-frame intensities estimated and divided out by default), and
# `Capture` gained `intensities` and `intensity_method`. Issue 18: `PS_METHODS` gained `"l1"`
# (exact L1 photometric stereo). Issue 15: every `key` parameter (fit_brdf,
# brdf_photometric_stereo, render_scene, render_corrupted, perturb_lights, sweep) is annotated
# `jax.Array | int` (an int seed is accepted); those snapshot entries were rewritten; and
# `jaxps.cli.reconstruct` gained `obj` and `points` (the OBJ and point cloud on request).
# Issue 18: `load_capture` gained `crop_multiple` (face boxes grown to shape buckets).
# Issue 16: `BRDF_METHODS` gained `"auto"` (per-region choice by leave-one-light-out error),
# `fit_brdf` gained its options `candidates`, `regions`, `margin`, `BRDFFit` the field `choice`
# and `BRDFModel` the field `gate`; those snapshot entries were rewritten.
# Issue 16 (part B): `BRDF_METHODS` gained the parametric models ("wrap", "oren_nayar", "ggx",
# "blinn_phong", "wrap_ggx", "oren_nayar_ggx", "wrap_ggx_residual") and `fit_brdf` gained
# `region` and `refine_normals` (their options); those two snapshot entries were rewritten.
# Issue 16: `fit_brdf`'s default `method` became "wrap_ggx" (below Lambert's law held out on
# every shared face; DESIGN.md named "mlp"), and `jaxps.cli`'s relight follows.
# Issue 18: `integrate` gained `cg_preconditioner` (multigrid by default, "jacobi" the CG of
# before, kept for Cao et al.'s figures to the digit); only that entry of the snapshot rewritten.
# Issue 16: `BRDFFit` gained `n_params` (the parameter count of `method="auto"`'s information
# criterion); only that entry of the snapshot rewritten.
# Issue 17: `intensity_estimate` gained `normal` (the mean normal of the "frontal" estimate's
# region), and `load_capture` and `jaxps.cli.reconstruct` gained `intensity_mask` and
# `intensity_normal` (flash strengths measured on a reference target in view); only those
# three entries of the snapshot rewritten.
# Issue 17: `load_capture` and `jaxps.cli.reconstruct` gained `register` (motion between frames
# measured and undone by default) and `Capture` the fields `shifts` and `registered`; those three
# entries rewritten.
# Issue 17: `QualityThresholds` gained `dark_all` and `dark_relative` (a dark frame must be dark
# for its capture too, not only share a dark surround); that entry and `check_frames` (whose
# default shows the thresholds) rewritten.
# Issue 17: `load_capture` and `jaxps.cli.reconstruct` check the frames by default
# (`check_quality=True`, as `reconstruct_many` already did); those two entries rewritten.
# Issue 18: `photometric_stereo_batch` gained `out` (a stream of batches writes into the previous
# result's arrays); only that entry rewritten.
# Issue 17: `Capture` gained `intensity_fit` (the semi-calibrated fit's report: converged,
# fallback, steps, objective, flash visibility); only that entry rewritten.
# Not from an issue: `lights_from_chrome`'s highlight became the centroid weighted by the height
# above `level` x the maximum, and its default `level` 0.9 became 0.5 (synthetic spheres with
# known lights, `benchmarks/bench_chrome.py`); only that entry rewritten.
# Issue 17: `load_capture` and `jaxps.cli.reconstruct` gained `intensity_ratios` (a reference
# target's flashes carried to the subject's place under near lights); those two entries
# rewritten.
# Not from an issue: `jaxps.cli.reconstruct` gained `light_positions` and `pixel_size` (near
# lamps, solved by `near_photometric_stereo`); that entry rewritten again.
# Issue 17 (near lamps with a face crop): `surface_points` and `near_photometric_stereo` gained
# `centre` (where the camera axis meets a cropped image) and `Capture` the field `frame_size`
# (the frame that `crop` is a box of); those three entries rewritten. `reconstruct_many` gained
# `light_positions` and `pixel_size` (near lamps for every capture); its entry rewritten.
# Not from an issue (relighting under near lamps): `fit_brdf`, `brdf_features`, `relight` and
# `extrapolation_mask` take per-pixel lights `(K, H, W, 3)` as well (their `lights` annotation);
# those four entries rewritten.
# Not from an issue: `read_image`, `load_stack`, `load_capture` and `jaxps.cli.reconstruct`
# gained `bits` (a camera's bit depth, for files that hold its codes unscaled); those four
# entries rewritten.
# Not from an issue: `brdf_photometric_stereo` and `stability.sweep` gained `progress` (a hook
# told of their stages, such as `jaxps.report.progress_bar()`); those two entries rewritten.
# Not from an issue: `jaxps.cli.reconstruct`'s default `integration` became "lsq" (the seeds'
# "fc" bends real faces: benchmarks/bench_face_heights.py); that entry rewritten.
# Not from an issue: `near_photometric_stereo` gained `integration` (each step's integrator,
# "lsq" by default, "fc" before: benchmarks/ab_near.py, tests/test_near.py); that entry rewritten.
# Not from an issue: `reconstruct_many` gained `shadow_threshold` (`jaxps reconstruct DIR1 DIR2`
# ignored `--shadow-threshold`); that entry rewritten.
# Not from an issue: `lights_from_chrome` gained `max_fraction` (a frame whose bright pixels
# cover more of the sphere than that, such as the noise of a lamp that did not fire, has no
# highlight); that entry rewritten.
# Not from an issue: `Capture` gained `light_check` (`check_lights` of the capture as loaded);
# that entry rewritten.
# Not from an issue: `Capture` gained `frame_check` (`check_frames`' report on the frames as
# given, so that `reconstruct_many` drops frames inside `load_capture`); that entry rewritten.
# Not from an issue: `jaxps.cli.reconstruct` gained `linearize` (`load_capture`'s, so that a
# camera's linear 8-bit PNGs are not decoded from sRGB); that entry rewritten.
# Not from an issue: `FRAME_EXTENSIONS` gained ".bmp" (machine-vision cameras' format, read as
# linear codes); that entry rewritten.
# Not from an issue: `write_report` gained `truth_scan` (a scan file or points, compared after
# ICP as `truth_depth` is); that entry rewritten, and `jaxps.evaluate`'s list of names, which
# gained `read_scan` and `SCAN_EXTENSIONS`.
CLI_NAMES = ("main", "reconstruct", "build_parser", "console")


def _annotation(a) -> str | None:
    if a is inspect.Parameter.empty:
        return None
    if isinstance(a, typing.ForwardRef):
        return a.__forward_arg__
    return a if isinstance(a, str) else repr(a)


def describe(obj) -> dict:
    """What a user relies on: the kind of object, its call signature, fields and values."""
    if isinstance(obj, types.ModuleType):
        return {"kind": "module", "all": sorted(getattr(obj, "__all__", []))}
    if not inspect.isclass(obj) and not callable(obj):
        return {"kind": "value", "repr": repr(obj)}
    d = {"kind": "class" if inspect.isclass(obj) else "function"}
    try:
        sig = inspect.signature(obj)
        d["parameters"] = [
            [p.name, p.kind.name, _annotation(p.annotation),
             None if p.default is inspect.Parameter.empty else repr(p.default)]
            for p in sig.parameters.values()]
        d["returns"] = _annotation(sig.return_annotation)
    except (TypeError, ValueError):
        d["parameters"] = None
    if hasattr(obj, "_fields"):
        d["fields"] = list(obj._fields)
    if inspect.isclass(obj) and issubclass(obj, enum.Enum):
        d["members"] = {m.name: int(m.value) for m in obj}
    return d


def api() -> dict:
    import importlib

    import jaxps

    out = {"jaxps": {n: describe(getattr(jaxps, n)) for n in jaxps.__all__}}
    for name in PUBLIC_MODULES:
        mod = importlib.import_module(f"jaxps.{name}")
        out[f"jaxps.{name}"] = {n: describe(getattr(mod, n)) for n in mod.__all__}
    cli = importlib.import_module("jaxps.cli")
    out["jaxps.cli"] = {n: describe(getattr(cli, n)) for n in CLI_NAMES}
    return out


def test_public_api_matches_snapshot():
    want, got = json.loads(SNAPSHOT.read_text()), api()
    for module, names in want.items():
        assert module in got, f"{module} is gone"
        for name, desc in names.items():
            assert name in got[module], f"{module}.{name} is gone"
            assert got[module][name] == desc, f"{module}.{name} changed"
    # New names are fine when they are listed in ADDED, so that each is seen in review.
    added = {m: sorted(set(got[m]) - set(want[m])) for m in want}
    assert {m: v for m, v in added.items() if v} == ADDED


# `jaxps.X.Y` in prose and code: not part of a path (`src/jaxps.md`) or of a longer word.
_DOTTED = re.compile(r"(?<![\w/.-])jaxps(?:\.[A-Za-z_]\w*)+")


def _documented_names() -> list[str]:
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")),
             *sorted((ROOT / "src").rglob("*.py")), *sorted((ROOT / "examples").glob("*.py")),
             *sorted((ROOT / "benchmarks").glob("*.py"))]
    names = set()
    for f in files:
        names.update(_DOTTED.findall(f.read_text(encoding="utf-8")))
    return sorted(n for n in names if not n.endswith((".md", ".py", ".json", ".png")))


def test_names_in_readme_docs_and_docstrings_resolve_right_after_import():
    names = _documented_names()
    assert "jaxps.acquisition.load_capture" in names and "jaxps.photometric_stereo" in names
    # A fresh interpreter: `import jaxps` alone must make every documented attribute reachable.
    code = ("import jaxps, json, sys\n"
            "bad = []\n"
            "for name in json.loads(sys.argv[1]):\n"
            "    obj = jaxps\n"
            "    for part in name.split('.')[1:]:\n"
            "        if not hasattr(obj, part):\n"
            "            bad.append(name); break\n"
            "        obj = getattr(obj, part)\n"
            "print(json.dumps(bad))\n")
    proc = subprocess.run([sys.executable, "-c", code, json.dumps(names)], capture_output=True,
                          text=True, check=True, timeout=300)
    assert json.loads(proc.stdout) == [], "documented names that do not resolve"


if __name__ == "__main__":
    json.dump(api(), sys.stdout, indent=1, sort_keys=True)
    print()
