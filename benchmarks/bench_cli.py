"""End to end, as a user runs it: `jaxps reconstruct` in a fresh process, cold and warm.

For each frame size, `jaxps demo` writes five 16-bit PNG frames, an ambient frame, a mask and
lights.txt (not timed); then `jaxps reconstruct` runs on them twice, each in a new process:
first with an empty compilation-cache folder (`JAXPS_CACHE_DIR`), then again with the folder
the first run filled. Wall time is measured around the process; the per-stage times come from
its summary.json, and the rest (start-up, imports, tracing, the summary) is wall minus stages.
`jaxps relight` (the default `wrap_ggx` fit, relit images and a 36-frame GIF) runs the same
way, cold then warm, on the 192x168 frames. Also timed: `jaxps --help`, `python -c "import
jaxps"`, `python -c "from jaxps.cli import _reconstruct"` (what the command imports before
it starts), `python -c "import jax"` and `python -c "import ml_dtypes"` (best of 3; the
installed ml_dtypes version is recorded).

Garbage collection: warm runs of the largest size alternate between the `jaxps` script
(`jaxps.cli.console`, with `gc.freeze`) and `jaxps.cli.main` without it (`gc_freeze`).

A real face (when ../shared/data is there): the same, cold and warm, on yaleB01's five cross
frames with `--yale-names --ambient` (the frames moved, so the run registers them).

For `jaxps relight` and the real face, one more warm run counts the XLA programs the process
traces and lowers (`JAX_LOG_COMPILES=1`, "Compiling" lines): each costs tracing and lowering
even when its compiled code comes from the cache.

Shape buckets (when ../shared/data is there): the five Yale B subjects' frontal five-light
captures, face-cropped, solved and integrated one after another in one fresh process with the
compilation cache off, once with the detector's boxes (`crop_multiple=1`: one compile per new
box size) and once with boxes grown to multiples of 64 (the default): seconds per capture.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_cli.py [--quick]
        [--integration METHOD] [--out NAME]
    -> benchmarks/results/cli.json, cli.png (NAME.json, NAME.png)

`--integration` passes that method to every `jaxps reconstruct` run (default: the command's
own default).
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

try:
    from benchmarks._common import arguments, data_dir, environment, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, data_dir, environment, write_json

QUICK = "--quick" in sys.argv or os.environ.get("JAXPS_BENCH_QUICK") == "1"
# (name, rows, columns): a 1.3 MP scanner frame and a Yale B frame.
SIZES = [("192x168", 192, 168)] if QUICK else [("1280x1024", 1024, 1280), ("192x168", 192, 168)]


def _command() -> list[str]:
    """The `jaxps` console script beside this Python, else `python -m jaxps`."""
    script = pathlib.Path(sys.executable).with_name("jaxps")
    return [str(script)] if script.is_file() else [sys.executable, "-m", "jaxps"]


def _wall(argv, env) -> float:
    t0 = time.perf_counter()
    subprocess.run(argv, env=env, check=True, capture_output=True, text=True)
    return time.perf_counter() - t0


def main(integration=None, out_name="cli"):
    env = dict(os.environ)
    extra = [] if integration is None else ["--integration", integration]
    # Python's bytecode cache on, as on a user's machine (pip compiles an installed package's
    # modules; an editable install writes them on first import). This project's machines set
    # PYTHONDONTWRITEBYTECODE=1, and every run then compiled jaxps's modules from source.
    bytecode_off = env.pop("PYTHONDONTWRITEBYTECODE", None)
    jaxps = _command()
    res = {"command": " ".join(pathlib.Path(a).name for a in jaxps), "quick": QUICK,
           "env": environment(), "integration": integration or "the command's default",
           "start_up_s": {}, "reconstruct": {}}
    res["env"]["OPENBLAS_NUM_THREADS"] = env.get("OPENBLAS_NUM_THREADS")
    res["env"]["PYTHONDONTWRITEBYTECODE"] = (f"{bytecode_off} in the calling shell, unset for the "
                                             "timed commands" if bytecode_off else None)
    res["env"]["ml_dtypes"] = importlib.metadata.version("ml_dtypes")
    for name, argv in [("jaxps --help", [*jaxps, "--help"]),
                       ("import jaxps", [sys.executable, "-c", "import jaxps"]),
                       # what `jaxps reconstruct` imports before it starts (no optimiser)
                       ("import the reconstruct command",
                        [sys.executable, "-c", "from jaxps.cli import _reconstruct"]),
                       ("import jax", [sys.executable, "-c", "import jax"]),
                       ("import ml_dtypes", [sys.executable, "-c", "import ml_dtypes"])]:
        res["start_up_s"][name] = min(_wall(argv, env) for _ in range(3))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        for name, rows, cols in SIZES:
            demo = tmp / f"demo_{name}"
            subprocess.run([*jaxps, "demo", "--size", str(rows), "--width", str(cols),
                            "--out", str(demo)], env={**env, "JAXPS_CACHE_DIR": "off"},
                           check=True, capture_output=True)
            frames = demo / "frames"
            cache = tmp / f"cache_{name}"
            runs = {}
            for run in ("first (empty cache)", "second (warm cache)"):
                out = tmp / f"out_{name}"
                shutil.rmtree(out, ignore_errors=True)
                argv = [*jaxps, "reconstruct", *sorted(str(p) for p in frames.glob("frame_*.png")),
                        "--lights", str(frames / "lights.txt"),
                        "--ambient", str(frames / "ambient.png"),
                        "--mask", str(frames / "mask.png"), "--out", str(out), *extra]
                wall = _wall(argv, {**env, "JAXPS_CACHE_DIR": str(cache)})
                stages = json.loads((out / "summary.json").read_text())["timings_s"]
                runs[run] = {"wall_s": wall, "stages_s": stages,
                             "start_up_and_rest_s": wall - sum(stages.values()),
                             "outputs": sorted(p.name for p in out.iterdir())}
            res["reconstruct"][name] = {"frames": 5, "rows": rows, "columns": cols, **runs}
            if name == SIZES[0][0]:
                res["gc_freeze"] = _freeze_ab(jaxps, argv[len(jaxps):],
                                              {**env, "JAXPS_CACHE_DIR": str(cache)})
            if name == "192x168":
                relight = [*jaxps, "relight", *sorted(str(p) for p in frames.glob("frame_*.png")),
                           "--lights", str(frames / "lights.txt"),
                           "--ambient", str(frames / "ambient.png"),
                           "--mask", str(frames / "mask.png"), "--out", str(tmp / "relit")]
                relight_env = {**env, "JAXPS_CACHE_DIR": str(tmp / "cache_relight")}
                res["relight"] = {"frames": 5, "rows": rows, "columns": cols, **{
                    run: {"wall_s": _wall(relight, relight_env)}
                    for run in ("first (empty cache)", "second (warm cache)")},
                    "programs_per_run": _programs(relight, relight_env)}
        res["yaleb"] = _yaleb(jaxps, env, tmp, extra)
    res["shape_buckets"] = _buckets(env)
    path = write_json(out_name, res)
    _chart(res, path.with_suffix(".png"))
    for name, runs in res["reconstruct"].items():
        for run, r in runs.items():
            if isinstance(r, dict):
                print(f"reconstruct {name:>9}, {run:<20} {r['wall_s']:6.2f} s wall  "
                      + ", ".join(f"{k} {v:.3f}" for k, v in r["stages_s"].items())
                      + f", start-up and rest {r['start_up_and_rest_s']:.2f}")
    for run, r in res.get("yaleb", {}).items():
        if isinstance(r, dict) and "wall_s" in r:
            print(f"reconstruct yaleB01, {run:<20} {r['wall_s']:6.2f} s wall  "
                  + ", ".join(f"{k} {v:.3f}" for k, v in r["stages_s"].items()))
    for run, r in res.get("relight", {}).items():
        if isinstance(r, dict):
            print(f"relight 192x168, {run:<20} {r['wall_s']:6.2f} s wall")
    for key, r in res.get("gc_freeze", {}).items():
        if isinstance(r, dict):
            print(f"warm {SIZES[0][0]}, {key}: median {r['median_s']:.2f} s, "
                  f"min {r['min_s']:.2f} s")
    for name in ("relight", "yaleb"):
        if "programs_per_run" in res.get(name, {}):
            print(f"{name}: {res[name]['programs_per_run']} XLA programs traced per run")
    for name, t in res["start_up_s"].items():
        print(f"{name:>14}: {t:.3f} s")
    for mode, r in res["shape_buckets"].items():
        if isinstance(r, dict):
            print(f"{mode}: {r['distinct_shapes']} shapes, "
                  + ", ".join(f"{c['seconds']:.2f}" for c in r["captures"])
                  + f" s per capture, {r['total_s']:.2f} s in all")


SUBJECTS = ("yaleB01", "yaleB02", "yaleB03", "yaleB04", "yaleB05")
NAMES = ("A+000E+00", "A+025E+00", "A-025E+00", "A+000E+20", "A+000E-20")


def _freeze_ab(jaxps, argv, env, rounds=5):
    """Warm runs of the same command, alternating: the `jaxps` script (`jaxps.cli.console`,
    which calls `gc.freeze` once the command's modules are imported and again at the end)
    against `jaxps.cli.main` run without it. Median and min wall seconds of each."""
    plain = [sys.executable, "-c", "import sys; from jaxps.cli import main; sys.exit(main())"]
    walls = {"jaxps (console, gc.freeze)": [], "main() without gc.freeze": []}
    for _ in range(rounds):
        for key, cmd in zip(walls, (jaxps, plain)):
            walls[key].append(_wall([*cmd, *argv], env))
    return {"rounds": rounds, **{k: {"median_s": sorted(v)[len(v) // 2], "min_s": min(v)}
                                 for k, v in walls.items()}}


def _programs(argv, env) -> int:
    """XLA programs one more (warm) run of `argv` compiles or loads from the cache: each was
    traced and lowered in that process (`JAX_LOG_COMPILES=1`, "Compiling" lines)."""
    proc = subprocess.run(argv, env={**env, "JAX_LOG_COMPILES": "1"}, check=True,
                          capture_output=True, text=True)
    return sum("Compiling " in line for line in proc.stderr.splitlines())


def _yaleb(jaxps, env, tmp, extra=()):
    """`jaxps reconstruct` on a real face, the issue-17 command line (yaleB01's five cross
    frames, `--yale-names --ambient`): its frames moved, so the run registers them. Cold, then
    warm."""
    folder = data_dir() / "yaleb" / "yaleB01"
    if not folder.is_dir():
        return {"skipped": f"no Yale B data at {folder}"}
    out = tmp / "out_yaleb"
    argv = ["reconstruct", *[str(folder / f"yaleB01_P00{n}.pgm") for n in NAMES], "--yale-names",
            "--ambient", str(folder / "yaleB01_P00_Ambient.pgm"), "--out", str(out), *extra]
    run_env = {**env, "JAXPS_CACHE_DIR": str(tmp / "cache_yaleb")}
    res = {"frames": 5, "rows": 192, "columns": 168}
    for run in ("first (empty cache)", "second (warm cache)"):
        wall = _wall([*jaxps, *argv], run_env)
        summary = json.loads((out / "summary.json").read_text())
        res[run] = {"wall_s": wall, "stages_s": summary["timings_s"],
                    "start_up_and_rest_s": wall - sum(summary["timings_s"].values()),
                    "registered": summary["motion"]["registered"]}
    res["programs_per_run"] = _programs([*jaxps, *argv], run_env)
    return res


def _buckets(env):
    """Seconds per face-cropped capture, without and with shape buckets (fresh processes)."""
    data = data_dir() / "yaleb"
    if not data.is_dir():
        return {"skipped": f"no Yale B data at {data}"}
    out = {}
    for multiple in (1, 64):
        proc = subprocess.run([sys.executable, __file__, "--buckets-child", str(multiple)],
                              env={**env, "JAXPS_CACHE_DIR": "off", "JAXPS_YALEB": str(data)},
                              check=True, capture_output=True, text=True)
        out[f"crop_multiple={multiple}"] = json.loads(proc.stdout.strip().splitlines()[-1])
    return out


def _buckets_child(multiple):
    import jax

    import jaxps

    data = pathlib.Path(os.environ["JAXPS_YALEB"])
    rows = []
    for subject in SUBJECTS:
        folder = data / subject
        t0 = time.perf_counter()
        cap = jaxps.acquisition.load_capture(
            [folder / f"{subject}_P00{n}.pgm" for n in NAMES], yale_names=True,
            ambient=folder / f"{subject}_P00_Ambient.pgm", crop_face=True,
            crop_multiple=multiple)
        res = jaxps.photometric_stereo(cap.images, cap.lights, mask=cap.mask)
        z = jaxps.integrate(res.normals, mask=res.status == 0)
        jax.block_until_ready(jaxps.normals_from_height(z))
        rows.append({"subject": subject, "shape": list(cap.images.shape[1:3]),
                     "seconds": time.perf_counter() - t0})
    print(json.dumps({"captures": rows, "distinct_shapes": len({tuple(r["shape"]) for r in rows}),
                      "total_s": sum(r["seconds"] for r in rows)}))


def _chart(res, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bars = [(f"{name}\n{run.split(' ')[0]} run", r) for name, runs in res["reconstruct"].items()
            for run, r in runs.items() if isinstance(r, dict)]
    stages = list(bars[0][1]["stages_s"]) + ["start-up and rest"]
    fig, ax = plt.subplots(figsize=(8, 0.6 * len(bars) + 1.6), constrained_layout=True)
    for i, (_, r) in enumerate(bars):
        left = 0.0
        for j, stage in enumerate(stages):
            v = r["stages_s"].get(stage, r["start_up_and_rest_s"])
            ax.barh(i, v, left=left, color=f"C{j}", label=stage if i == 0 else None)
            left += v
        ax.text(left + 0.03, i, f"{r['wall_s']:.2f} s", va="center", fontsize=8)
    ax.set_yticks(range(len(bars)), [b[0] for b in bars], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("wall-clock seconds, fresh process")
    ax.set_title("jaxps reconstruct, five 16-bit frames + ambient + mask")
    ax.legend(fontsize=7, loc="lower right")
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    def configure(p):
        p.add_argument("--buckets-child", type=int, metavar="MULTIPLE",
                       help="internal: one bucketing run")
        p.add_argument("--integration", help="passed to every `jaxps reconstruct` run")
        p.add_argument("--out", default="cli", help="results name (default cli)")

    args = arguments(__doc__, quick=True, configure=configure)
    if args.buckets_child is not None:
        _buckets_child(args.buckets_child)
    else:
        main(args.integration, args.out)
