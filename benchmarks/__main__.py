"""Run every benchmark and chart speed against accuracy: `python -m benchmarks`.

1. Runs each `benchmarks/bench_<topic>.py` as its own process (one at a time, with
   `OPENBLAS_NUM_THREADS=1` unless set, `PYTHONPATH=src`, `--quick` passed to the scripts that
   accept it, `JAXPS_BENCH_QUICK=1` set for the others) and collects the
   `benchmarks/results/<topic>.json` each one writes.
2. Runs every method the library lists, in this process, next to numpy/scipy baselines:
   `jaxps.PS_METHODS` on a synthetic face with known normals and on Yale B (five scanner-like
   lights against L2 over all lights within 50 degrees), and `jaxps.INTEGRATION_METHODS` on the
   DiLiGenT ground-truth normals (MADE after a scale+offset fit). Compile time (first call less a
   later call) and run time (best later call) are kept apart.
3. Adds the points that benchmark JSON files offer under `"points"` (a list of
   `{"panel", "method", "run_s", "error", "error_name", "compile_s"?, "baseline"?}`), and draws
   one panel per task: run time against error, one point per method, the Pareto front marked.

Writes `benchmarks/results/summary.json` and `benchmarks/results/summary.png`.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python -m benchmarks            # everything
    PYTHONPATH=src python -m benchmarks --quick --only icp core           # a subset, quickly
    PYTHONPATH=src python -m benchmarks --no-modules                      # the method sweep only
    PYTHONPATH=src python -m benchmarks --reuse-modules                   # sweep + last topic JSONs
    PYTHONPATH=src python -m benchmarks --chart-only                      # redraw summary.png
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import time
import traceback

import numpy as np

from benchmarks._common import RESULTS, ROOT, data_dir, environment, timed, write_json

HERE = ROOT / "benchmarks"


# ----------------------------------------------------------------------------- bench_*.py
def discover() -> list[str]:
    """Topics of the `bench_<topic>.py` scripts beside this file, sorted."""
    return sorted(p.stem[len("bench_"):] for p in HERE.glob("bench_*.py"))


def run_module(topic: str, quick: bool, timeout_s: float) -> dict:
    script = HERE / f"bench_{topic}.py"
    env = dict(os.environ)
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    env["PYTHONPATH"] = os.pathsep.join(
        [str(ROOT / "src"), str(ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    cmd = [sys.executable, str(script)]
    if quick:
        env["JAXPS_BENCH_QUICK"] = "1"
        if "--quick" in script.read_text():
            cmd.append("--quick")
    out_json = RESULTS / f"{topic}.json"
    before = out_json.stat().st_mtime if out_json.exists() else None
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True,
                              timeout=timeout_s)
        rc, tail = proc.returncode, (proc.stdout + proc.stderr)[-2000:]
    except subprocess.TimeoutExpired as exc:
        rc, tail = "timeout", str(exc)[-2000:]
    seconds = time.perf_counter() - t0
    record = {"command": " ".join([os.path.relpath(cmd[0])] + cmd[1:]), "returncode": rc,
              "seconds": seconds, "output_tail": tail, "json": None, "fresh": False}
    if out_json.exists():
        record["json"] = str(out_json.relative_to(ROOT))
        record["fresh"] = before is None or out_json.stat().st_mtime > before
        try:
            record["result"] = json.loads(out_json.read_text())
        except ValueError as exc:
            record["result_error"] = f"unreadable JSON: {exc}"
    print(f"  bench_{topic}: rc={rc} in {seconds:.1f} s"
          + ("" if record["fresh"] else " (no fresh JSON)"), flush=True)
    return record


def points_from_results(topic: str, result: dict) -> list[dict]:
    pts = []
    for p in result.get("points", []) if isinstance(result, dict) else []:
        try:
            pts.append({"panel": str(p["panel"]), "method": str(p["method"]),
                        "run_s": float(p["run_s"]), "error": float(p["error"]),
                        "error_name": str(p.get("error_name", "error")),
                        "compile_s": (None if p.get("compile_s") is None
                                      else float(p["compile_s"])),
                        "baseline": bool(p.get("baseline", False)), "source": f"bench_{topic}"})
        except (KeyError, TypeError, ValueError):
            continue
    return pts


# ----------------------------------------------------------------------------- method sweep
def _point(panel, method, error, error_name, first_s, run_s, baseline=False, **extra):
    return {"panel": panel, "method": method, "error": float(error), "error_name": error_name,
            "run_s": float(run_s), "compile_s": max(float(first_s) - float(run_s), 0.0),
            "first_call_s": float(first_s), "baseline": baseline, "source": "sweep", **extra}


def _numpy_l2(images, lights):
    """Baseline: numpy pseudo-inverse matmul and normalise (every sample used)."""
    k, h, w = images.shape
    b = (np.linalg.pinv(lights) @ images.reshape(k, -1)).T.reshape(h, w, 3)
    rho = np.linalg.norm(b, axis=-1)
    return b / np.maximum(rho, 1e-12)[..., None], rho


def _median_angle(n, ref, mask):
    import jaxps

    return float(np.median(np.asarray(jaxps.angular_error(n, ref))[mask]))


def sweep_ps(panel, images, lights, truth, mask, repeats, failures):
    import jaxps

    pts = []
    for method in jaxps.PS_METHODS:
        try:
            res, first, run = timed(jaxps.photometric_stereo, images, lights, mask=mask,
                                    method=method, repeats=repeats)
            err = _median_angle(res.normals, truth, mask)
            ok = float(np.mean(np.asarray(res.status)[mask] == 0))
            pts.append(_point(panel, method, err, "median angular error (deg)", first, run,
                              ok_fraction=ok))
        except Exception as exc:  # a method that cannot run here is reported, not fatal
            failures.append({"panel": panel, "method": method, "error": repr(exc)})
    imgs, lts = np.asarray(images), np.asarray(lights)
    (n, _), first, run = timed(_numpy_l2, imgs, lts, repeats=repeats)
    pts.append(_point(panel, "numpy pinv (baseline)", _median_angle(n, truth, mask),
                      "median angular error (deg)", first, run, baseline=True))
    return pts


def sweep_yale(repeats, failures):
    import jaxps

    from jaxps.acquisition import load_capture

    folder = data_dir() / "yaleb" / "yaleB01"
    cap = load_capture(sorted(folder.glob("yaleB01_P00A*.pgm")), yale_names=True,
                       ambient=folder / "yaleB01_P00_Ambient.pgm")
    frames, lights = cap.images, cap.lights
    az, el = np.array([jaxps.parse_yale_name(n) for n in cap.names]).T
    zen = np.degrees(np.arccos(np.clip(lights[:, 2], -1, 1)))
    ref = jaxps.photometric_stereo(frames[zen <= 50], lights[zen <= 50], shadow_threshold=0.02)
    mask = (np.asarray(ref.status) == 0) & (np.asarray(ref.albedo) > 0.05)
    pick = [int(np.flatnonzero((az == a) & (el == e))[0])
            for a, e in [(0, 0), (25, 0), (-25, 0), (0, 20), (0, -20)]]
    return sweep_ps("PS, Yale B01, 5 lights vs 29-light L2 (192x168)", frames[pick],
                    lights[pick], ref.normals, mask, repeats, failures)


def sweep_synthetic(repeats, failures, quick):
    import jax

    import jaxps

    h = 96 if quick else 256
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(h),
                                         jaxps.synthetic.scanner_lights(20.0), noise=0.01,
                                         key=jax.random.key(0))
    mask = np.asarray(scene.mask)
    return sweep_ps(f"PS, synthetic face {h}x{int(round(h * 0.8))}, noise 0.01", scene.images,
                    scene.lights, scene.normals, mask, repeats, failures)


def _made(z, gt, mask):
    """Mean |s z + t - gt| over mask after the least-squares scale s and offset t (mm)."""
    a = np.stack([z[mask], np.ones(mask.sum())], axis=-1).astype(np.float64)
    coef, *_ = np.linalg.lstsq(a, gt[mask].astype(np.float64), rcond=None)
    return float(np.mean(np.abs(a @ coef - gt[mask])))


def _numpy_fc(normals, mask):
    """Baseline: Frankot-Chellappa with numpy's complex FFT (same set-up as jaxps "fc")."""
    nz = np.maximum(normals[..., 2], 0.05)
    p = np.where(mask, -normals[..., 0] / nz, 0)
    q = np.where(mask, -normals[..., 1] / nz, 0)
    h, w = p.shape
    wc = 2 * np.pi * np.fft.fftfreq(w)[None, :]
    wr = 2 * np.pi * np.fft.fftfreq(h)[:, None]
    denom = np.where((wc == 0) & (wr == 0), 1, wc**2 + wr**2)
    zh = -1j * (wc * np.fft.fft2(p) + wr * np.fft.fft2(-q)) / denom
    zh[0, 0] = 0
    return np.real(np.fft.ifft2(zh))


def sweep_integration(repeats, failures, quick):
    import cv2

    import jaxps

    objects = ("bear", "cat") if quick else ("bear", "cat", "pot1", "reading")
    panel = "integration, DiLiGenT GT normals, mean MADE over " + "/".join(objects)
    per = {}
    for obj in objects:
        root = data_dir() / "diligent_gt" / obj
        depth = np.load(root / "depth_gt.npz")["depth_gt"]
        mask = (cv2.imread(str(root / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0) & np.isfinite(depth)
        raw = cv2.imread(str(root / "normal_map.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
        n = raw.astype(np.float32) / 65535 * 2 - 1
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
        n = np.where(mask[..., None], n, np.array([0, 0, 1], np.float32))
        runs = {}
        for method in jaxps.INTEGRATION_METHODS:
            if method == "auto":
                continue
            try:
                z, first, run = timed(jaxps.integrate, n, mask=mask, method=method,
                                      repeats=repeats)
                runs[method] = (_made(np.asarray(z), -depth, mask), first, run)
            except Exception as exc:
                failures.append({"panel": panel, "method": method, "object": obj,
                                 "error": repr(exc)})
        z, first, run = timed(_numpy_fc, n, mask, repeats=repeats)
        runs["numpy fc (baseline)"] = (_made(z, -depth, mask), first, run)
        for method, r in runs.items():
            per.setdefault(method, []).append((obj, *r))
    pts = []
    for method, rows in per.items():
        if len(rows) != len(objects):
            continue
        pts.append(_point(panel, method, np.mean([r[1] for r in rows]), "MADE (mm)",
                          np.mean([r[2] for r in rows]), np.mean([r[3] for r in rows]),
                          baseline="baseline" in method,
                          per_object={r[0]: {"made_mm": r[1], "run_s": r[3]} for r in rows}))
    return pts


# ----------------------------------------------------------------------------- chart
def pareto(points: list[dict]) -> list[dict]:
    """The points no other point beats on both run time and error (lower is better).

    Errors within 0.1% of each other count as a tie (float32 against float64 round-off).
    """
    front, best = [], float("inf")
    for p in sorted(points, key=lambda p: (p["run_s"], p["error"])):
        if p["error"] < best * (1 - 1e-3):
            front.append(p)
            best = p["error"]
    return front


# Tasks, in the order the figures are drawn: (file suffix, title, test on the panel name).
TASKS = (
    ("ps", "photometric stereo", lambda panel: panel.startswith("PS")),
    ("robust", "robust photometric stereo", lambda panel: panel.startswith("robust")),
    ("integration", "integration", lambda panel: panel.startswith("integration")),
    ("relight", "relighting", lambda panel: panel.startswith("relight")),
    ("icp", "alignment to a scan (ICP)", lambda panel: panel.startswith("ICP")),
)


def task_of(panel: str) -> str:
    """The suffix of the task figure a panel belongs to (`"other"` if none matches)."""
    return next((key for key, _, test in TASKS if test(panel)), "other")


def _tick(v, _):
    """Log-axis labels: 0.1, 1, 10, 100, 1000, then 1e4, 1e5 (no '1e+06')."""
    return f"{v:g}" if v < 1e4 else f"1e{round(np.log10(v))}"


def _panel(ax, pts, styles):
    """One panel: run time against error, a marker per method (its legend entry), baselines
    hollow, the Pareto front a grey step line through black-edged points."""
    import matplotlib.ticker as mticker

    front = pareto(pts)
    ax.step([p["run_s"] * 1e3 for p in front], [p["error"] for p in front], where="post",
            color="0.55", lw=1.2, zorder=1)
    for p in pts:
        colour, marker = styles[p["method"]]
        on = p in front
        ax.scatter(p["run_s"] * 1e3, p["error"], s=70 if on else 45, marker=marker, zorder=3,
                   facecolors="white" if p["baseline"] else colour,
                   edgecolors="black" if on else colour, linewidths=1.6 if on else 1.0)
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(mticker.LogLocator(base=10, numticks=6))
    ax.xaxis.set_major_formatter(mticker.FuncFormatter(_tick))
    ax.xaxis.set_minor_formatter(mticker.NullFormatter())
    ax.margins(x=0.15, y=0.1)
    errs = [p["error"] for p in pts if p["error"] > 0]
    if errs and max(errs) / min(errs) > 30:
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(mticker.FuncFormatter(_tick))
        ax.yaxis.set_minor_formatter(mticker.NullFormatter())
    else:
        ax.set_ylim(0, 1.12 * max([p["error"] for p in pts] + [1e-9]))
    ax.set_xlabel("run time per call (ms, after compile)", fontsize=8)
    ax.set_ylabel(pts[0]["error_name"], fontsize=8)
    ax.tick_params(labelsize=8)
    ax.grid(alpha=0.25, which="major")


def _figure(points, title, path):
    import matplotlib.lines as mlines
    import matplotlib.pyplot as plt

    panels = list(dict.fromkeys(p["panel"] for p in points))
    methods = list(dict.fromkeys(p["method"] for p in points))
    markers = "osD^vP*XhH<>p8d"
    styles = {m: (f"C{i % 10}", markers[i % len(markers)]) for i, m in enumerate(methods)}
    cols = min(3, len(panels))
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols + 2.6, 3.6 * rows + 0.6),
                             squeeze=False, constrained_layout=True)
    for ax, panel in zip(axes.flat, panels):
        _panel(ax, [p for p in points if p["panel"] == panel], styles)
        ax.set_title(panel, fontsize=9)
    for ax in list(axes.flat)[len(panels):]:
        ax.set_axis_off()
    baseline = {p["method"] for p in points if p["baseline"]}
    handles = [mlines.Line2D([], [], ls="none", marker=styles[m][1], markersize=7,
                             markerfacecolor="white" if m in baseline else styles[m][0],
                             markeredgecolor=styles[m][0],
                             label=m if m not in baseline or "baseline" in m else f"{m} (baseline)")
               for m in methods]
    handles.append(mlines.Line2D([], [], color="0.55", lw=1.2, marker="o", markersize=7,
                                 markerfacecolor="white", markeredgecolor="black",
                                 label="Pareto front (black edge)"))
    fig.legend(handles=handles, loc="outside right upper", fontsize=8, frameon=False)
    fig.suptitle(f"jaxps, {title}: speed against accuracy (lower left is better; hollow: "
                 "numpy/scipy baselines)", fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def draw(points: list[dict], path) -> list:
    """Write one figure per task (`summary_<task>.png` beside `path`) and an overview at `path`
    (the first panel of each task). **Returns:** the paths written."""
    import matplotlib

    matplotlib.use("Agg")
    path = pathlib.Path(path)
    written = []
    firsts = []
    for key, title, _ in TASKS + (("other", "other", None),):
        pts = [p for p in points if task_of(p["panel"]) == key]
        if not pts:
            continue
        out = path.with_name(f"{path.stem}_{key}.png")
        _figure(pts, title, out)
        written.append(out)
        first = pts[0]["panel"]
        firsts += [p for p in pts if p["panel"] == first]
    if firsts:
        _figure(firsts, "one panel per task (all panels: summary_<task>.png)", path)
        written.insert(0, path)
    return written


# ----------------------------------------------------------------------------- main
def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m benchmarks",
                                 description="Run the benchmarks and chart speed against accuracy.")
    ap.add_argument("--quick", action="store_true",
                    help="small inputs and few repeats (CI smoke run)")
    ap.add_argument("--only", nargs="*", metavar="TOPIC",
                    help=f"bench_<topic>.py scripts to run (default all: {', '.join(discover())})")
    ap.add_argument("--no-modules", action="store_true", help="skip the bench_*.py scripts")
    ap.add_argument("--reuse-modules", action="store_true",
                    help="do not run the bench_*.py scripts; chart the results/<topic>.json "
                         "they last wrote")
    ap.add_argument("--no-sweep", action="store_true", help="skip the in-process method sweep")
    ap.add_argument("--timeout", type=float, default=1800, help="seconds per script")
    ap.add_argument("--chart-only", action="store_true",
                    help="redraw summary.png from the existing summary.json; run nothing")
    args = ap.parse_args(argv)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    if args.chart_only:
        payload = json.loads((RESULTS / "summary.json").read_text())
        for out in draw(payload["points"], RESULTS / "summary.png"):
            print(f"redrew {out} from {RESULTS / 'summary.json'}")
        return payload

    topics = [] if args.no_modules else (args.only if args.only is not None else discover())
    unknown = sorted(set(topics) - set(discover()))
    if unknown:
        ap.error(f"no benchmarks/bench_<topic>.py for {unknown}; have {discover()}")
    t0 = time.perf_counter()
    modules = {}
    for topic in topics:
        out_json = RESULTS / f"{topic}.json"
        if args.reuse_modules:
            if out_json.exists():
                modules[topic] = {"json": str(out_json.relative_to(ROOT)), "reused": True,
                                  "result": json.loads(out_json.read_text())}
            continue
        print(f"running bench_{topic} ...", flush=True)
        modules[topic] = run_module(topic, args.quick, args.timeout)

    points, failures = [], []
    for topic, rec in modules.items():
        points += points_from_results(topic, rec.get("result", {}))
    if not args.no_sweep:
        repeats = 2 if args.quick else 5
        print("method sweep ...", flush=True)
        for name, fn in [("synthetic", lambda: sweep_synthetic(repeats, failures, args.quick)),
                         ("yale", lambda: sweep_yale(repeats, failures)),
                         ("integration", lambda: sweep_integration(repeats, failures,
                                                                   args.quick))]:
            needs = {"yale": "yaleb", "integration": "diligent_gt"}.get(name)
            if needs and not (data_dir() / needs).is_dir():
                failures.append({"panel": name, "error": f"no data at {data_dir() / needs}"})
                continue
            try:
                points += fn()
            except Exception:
                failures.append({"panel": name, "error": traceback.format_exc()[-1500:]})

    panels = {}
    for panel in dict.fromkeys(p["panel"] for p in points):
        pts = [p for p in points if p["panel"] == panel]
        panels[panel] = [p["method"] for p in pareto(pts)]
    payload = {
        "benchmark": "summary",
        "command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python -m benchmarks"
                   + (" --quick" if args.quick else "")
                   + (" --reuse-modules" if args.reuse_modules else "")
                   + (f" --only {' '.join(args.only)}" if args.only else ""),
        "environment": environment(),
        "seconds": time.perf_counter() - t0,
        "points": points,
        "pareto": panels,
        "failures": failures,
        "modules": modules,
    }
    path = write_json("summary", payload)
    draw(points, RESULTS / "summary.png")
    for panel, names in panels.items():
        print(f"{panel}: Pareto front {names}")
    for p in points:
        print(f"  {p['method']:28s} {p['error']:8.3f} {p['error_name']:28s} "
              f"run {p['run_s'] * 1e3:9.2f} ms  compile {p['compile_s'] or 0:6.2f} s")
    for f in failures:
        print(f"  FAILED {f}")
    print(f"wrote {path} and {RESULTS / 'summary.png'}")
    return payload


if __name__ == "__main__":
    main()
