"""Integration accuracy and speed on the four DiLiGenT objects (ground-truth depth).

For every object and method: MADE (mean absolute depth error, mm, after a least-squares
scale+offset fit over the mask), RMS error, compile time (first call) and run time (best of
`--repeat` warm calls, `block_until_ready`). Baseline in the same run: Cao et al.'s bilateral
normal integration as their reference code does it (scipy.sparse, system re-assembled every
step, warm-started Jacobi CG). Also: do normals re-derived from the integrated height come
closer to the ground truth than noisy input normals?

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_integration.py

Writes benchmarks/results/integration.json and integration.png (MADE against run time).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import pathlib
import platform
import sys
import time

import cv2
import jax
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

import jaxps
from jaxps.evaluate import angular_stats, height_stats

try:
    from benchmarks._common import cpu_model
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import cpu_model

ROOT = pathlib.Path(__file__).resolve().parents[1]
OBJECTS = ("bear", "cat", "pot1", "reading")
# (label, method, perspective, CG preconditioner); the "jacobi" rows: the CG preconditioner
# before the multigrid one (Cao et al.'s), timed in the same process
RUNS = (
    ("fc", "fc", False, "multigrid"),
    ("dct", "dct", False, "multigrid"),
    ("lsq", "lsq", False, "multigrid"),
    ("lsq persp", "lsq", True, "multigrid"),
    ("lsq jacobi", "lsq", False, "jacobi"),
    ("bilateral", "bilateral", False, "multigrid"),
    ("bilateral persp", "bilateral", True, "multigrid"),
    ("bilateral jacobi", "bilateral", False, "jacobi"),
    ("bilateral persp jacobi", "bilateral", True, "jacobi"),
    ("auto persp", "auto", True, "multigrid"),
    ("lsq persp default emitters", "lsq", True, "multigrid"),
    ("bilateral persp default emitters", "bilateral", True, "multigrid"),
)
# Rows timed with the grid solvers compiled by XLA-CPU's default (fusion) emitters, as before
# `core._host.OLDER_EMITTERS`: the same solve, in the same process.
DEFAULT_EMITTERS = ("lsq persp default emitters", "bilateral persp default emitters")


def data_dir() -> pathlib.Path:
    return pathlib.Path(os.environ.get("JAXPS_DATA", ROOT.parent / "shared" / "data"))


def load_diligent(name: str):
    """Normals (H, W, 3) float32 in the DESIGN frame, mask, depth (mm, NaN outside), K."""
    d = data_dir() / "diligent_gt" / name
    raw = cv2.imread(str(d / "normal_map.png"), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.dtype != np.uint16:
        raise RuntimeError(f"{d / 'normal_map.png'} did not load as 16-bit")
    normals = raw[..., ::-1].astype(np.float32) / 65535 * 2 - 1
    mask = cv2.imread(str(d / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    depth = np.load(d / "depth_gt.npz")["depth_gt"].astype(np.float64)
    return normals, mask, depth, np.loadtxt(d / "K.txt")


def bini_reference(normals, mask, K, k=2.0, max_iter=150, tol=1e-4, cg_tol=1e-3):
    """Bilateral normal integration as in Cao et al.'s published code (perspective), scipy.

    Returns the depth map (up to scale) and the iteration count.
    """
    h, w = mask.shape
    n = normals / np.linalg.norm(normals, axis=-1, keepdims=True)
    nx, ny, nz = n[..., 0][mask], n[..., 1][mask], n[..., 2][mask]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    rows, cols = np.nonzero(mask)
    m = nz - nx * (cols - cx) / fx + ny * (rows - cy) / fy
    num = int(mask.sum())
    idx = -np.ones((h, w), np.int64)
    idx[mask] = np.arange(num)

    def one_sided(dr, dc, coef):
        """Rows coef_i * (z[i + d] - z[i]) (forward) or coef_i * (z[i] - z[i - d]) (backward)."""
        rr, cc = rows + dr, cols + dc
        ok = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
        ok[ok] = mask[rr[ok], cc[ok]]
        i = np.arange(num)[ok]
        j = idx[rr[ok], cc[ok]]
        sign = 1.0 if dr + dc > 0 else -1.0
        data = np.concatenate([sign * coef[ok], -sign * coef[ok]])
        return sp.csr_matrix((data, (np.concatenate([i, i]), np.concatenate([j, i]))),
                             shape=(num, num))

    a1, a2 = one_sided(0, 1, m), one_sided(0, -1, m)
    a3, a4 = one_sided(1, 0, m * fy / fx), one_sided(-1, 0, m * fy / fx)
    a = sp.vstack([a1, a2, a3, a4]).tocsr()
    b = np.concatenate([-nx, -nx, ny, ny])
    wts = sp.diags(np.full(4 * num, 0.5))
    z = np.zeros(num)
    energy = (a @ z - b) @ wts @ (a @ z - b)
    it = 0
    for it in range(1, max_iter + 1):
        a_mat = (a.T @ wts @ a).tocsr()
        b_vec = a.T @ wts @ b
        precond = sp.diags(1 / np.clip(a_mat.diagonal(), 1e-5, None))
        z, _ = sla.cg(a_mat, b_vec, x0=z, M=precond, maxiter=5000, rtol=cg_tol)
        with np.errstate(over="ignore"):
            wu = 1 / (1 + np.exp(-k * ((a2 @ z) ** 2 - (a1 @ z) ** 2)))
            wv = 1 / (1 + np.exp(-k * ((a4 @ z) ** 2 - (a3 @ z) ** 2)))
        wts = sp.diags(np.concatenate([wu, 1 - wu, wv, 1 - wv]))
        old, energy = energy, (a @ z - b) @ wts @ (a @ z - b)
        if abs(energy - old) / old < tol:
            break
    depth = np.full((h, w), np.nan)
    depth[mask] = np.exp(-z / fx)
    return depth, it


@contextlib.contextmanager
def default_emitters(on):
    """`integrate`'s grid solvers without `core._host.OLDER_EMITTERS` while `on`."""
    from jaxps.integration import _integrate

    saved = _integrate.bilateral, _integrate.lsq_midpoint
    if on:
        _integrate.bilateral = saved[0].plain
        _integrate.lsq_midpoint = saved[1].plain
    try:
        yield
    finally:
        _integrate.bilateral, _integrate.lsq_midpoint = saved


def timed(fn, repeat):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t0)
    return out, first, runs


def rederived_normals(normals, mask, depth, key, sigma):
    """Noisy GT normals -> integrate -> normals again; angular error of each against GT."""
    noise = np.asarray(jax.random.normal(key, normals.shape, dtype=np.float32)) * sigma
    noisy = normals + noise
    noisy = noisy / np.linalg.norm(noisy, axis=-1, keepdims=True)
    noisy[..., 2] = np.abs(noisy[..., 2])
    out = {"sigma": sigma, "input": angular_stats(noisy, normals, mask=mask)}
    for method in ("lsq", "bilateral"):
        z = jaxps.integrate(noisy, mask=mask, method=method)
        again = jaxps.normals_from_height(z, mask=mask)
        out[method] = angular_stats(again, normals, mask=mask)
    # the floor: GT depth itself, differentiated the same way (orthographic, pixel units)
    ps = np.nanmedian(depth[mask]) / 3770.0
    again = jaxps.normals_from_height(np.where(mask, -depth / ps, 0), mask=mask)
    out["gt_depth"] = angular_stats(again, normals, mask=mask)
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--objects", nargs="*", default=list(OBJECTS))
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "integration"))
    parser.add_argument("--quick", action="store_true", help="one warm call per method")
    parser.add_argument("--redraw", action="store_true",
                        help="only: re-read the JSON, refresh its summary points and the chart")
    parser.add_argument("--sweep-cg-rtol", action="store_true",
                        help="only: bilateral (perspective) MADE and CG steps against cg_rtol")
    parser.add_argument("--preconditioner", default="jacobi",
                        help="CG preconditioner of --sweep-cg-rtol (jacobi: the file "
                             "integration_cg_rtol.json, else integration_cg_rtol_NAME.json)")
    args = parser.parse_args()
    if args.quick:
        args.repeat = 1
    if args.redraw:
        out = pathlib.Path(args.out)
        results = json.loads(out.with_suffix(".json").read_text())
        results["points"] = summary_points(results)
        out.with_suffix(".json").write_text(json.dumps(results, indent=2))
        chart(results, out.with_suffix(".png"))
        return
    if args.sweep_cg_rtol:
        sweep = {}
        for name in args.objects:
            normals, mask, depth, K = load_diligent(name)
            for rtol in (1e-2, 3e-3, 1e-3, 1e-4):
                res = jaxps.integrate(normals, mask=mask, method="bilateral", intrinsics=K,
                                      cg_rtol=rtol, cg_preconditioner=args.preconditioner,
                                      return_info=True)
                sweep.setdefault(name, {})[str(rtol)] = {
                    "made_mm": height_stats(res.height, depth, mask=mask)["made"],
                    "steps": res.steps, "cg_steps": res.solver_steps}
                print(name, rtol, sweep[name][str(rtol)], flush=True)
        tail = "" if args.preconditioner == "jacobi" else "_" + args.preconditioner
        path = pathlib.Path(args.out + f"_cg_rtol{tail}.json")
        path.write_text(json.dumps(sweep, indent=2))
        print("wrote", path)
        return

    results = {
        "setup": {
            "machine": platform.processor() or platform.machine(),
            "cpu": cpu_model(),
            "cpus": os.cpu_count(),
            "load_average_at_start": os.getloadavg(),
            "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
            "jax": jax.__version__,
            "dtype": "float32 (jaxps), float64 (scipy baseline)",
            "made": "mean |s*z + t - depth_gt| over the mask, mm, least-squares scale+offset",
            "time": "run_s = best of --repeat warm calls; compile_s = first call minus run_s",
            "repeat": args.repeat,
        },
        "objects": {},
    }
    for name in args.objects:
        normals, mask, depth, K = load_diligent(name)
        row = {"pixels": int(mask.sum())}
        for label, method, persp, precond in RUNS:
            kw = {"mask": mask, "method": method, "intrinsics": K if persp else None,
                  "cg_preconditioner": precond, "return_info": True}
            with default_emitters(label in DEFAULT_EMITTERS):
                res, first, runs = timed(lambda kw=kw: jaxps.integrate(normals, **kw),
                                         args.repeat)
            stats = height_stats(res.height, depth, mask=mask)
            row[label] = {
                "made_mm": stats["made"], "rms_mm": stats["rms"],
                "run_s": min(runs), "compile_s": max(first - min(runs), 0.0),
                "picked": res.method, "reason": res.reason, "steps": res.steps,
                "cg_steps": res.solver_steps, "converged": res.converged,
            }
            print(f"{name:8s} {label:16s} MADE {stats['made']:.3f} mm  "
                  f"run {min(runs):.3f} s  compile {row[label]['compile_s']:.2f} s  "
                  f"steps {res.steps}/{res.solver_steps} {res.method}", flush=True)
        runs = []
        for _ in range(max(1, args.repeat - 1)):
            t0 = time.perf_counter()
            ref_depth, it = bini_reference(normals.astype(np.float64), mask, K)
            runs.append(time.perf_counter() - t0)
        stats = height_stats(ref_depth, depth, mask=mask)
        row["scipy reference bilateral persp"] = {
            "made_mm": stats["made"], "rms_mm": stats["rms"], "run_s": min(runs),
            "compile_s": 0.0, "steps": it}
        print(f"{name:8s} {'scipy ref bilat':16s} MADE {stats['made']:.3f} mm  "
              f"run {min(runs):.3f} s  steps {it}", flush=True)
        row["rederived_normals"] = rederived_normals(normals, mask, depth,
                                                     jax.random.key(4), 0.05)
        rd = row["rederived_normals"]
        print(f"{name:8s} normals: noisy input {rd['input']['mean_deg']:.2f} deg, re-derived "
              f"lsq {rd['lsq']['mean_deg']:.2f} / bilateral {rd['bilateral']['mean_deg']:.2f}"
              f" / from GT depth {rd['gt_depth']['mean_deg']:.2f} (mean)", flush=True)
        results["objects"][name] = row

    results["points"] = summary_points(results)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(results, indent=2))
    chart(results, out.with_suffix(".png"))
    print("wrote", out.with_suffix(".json"), out.with_suffix(".png"))


def summary_points(results):
    """Points for `python -m benchmarks`' summary chart: one per object and method."""
    pts = []
    for name, row in results["objects"].items():
        for label in [r[0] for r in RUNS] + ["scipy reference bilateral persp"]:
            e = row[label]
            pts.append({"panel": f"integration, DiLiGenT {name}", "method": label,
                        "run_s": e["run_s"], "error": e["made_mm"], "error_name": "MADE (mm)",
                        "compile_s": e["compile_s"], "baseline": label.startswith("scipy")})
    return pts


def chart(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    objects = results["objects"]
    fig, axes = plt.subplots(1, len(objects), figsize=(4 * len(objects), 3.8), squeeze=False)
    labels = [r[0] for r in RUNS] + ["scipy reference bilateral persp"]
    colours = plt.cm.tab20(np.linspace(0, 1, len(labels)))
    for ax, (name, row) in zip(axes[0], objects.items()):
        for i, label in enumerate(labels):
            ax.scatter(row[label]["run_s"], row[label]["made_mm"], color=colours[i],
                       marker="x" if label.startswith("scipy") else "o", label=label)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(f"{name} ({row['pixels']} px)")
        ax.set_xlabel("run time per object (s)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("MADE (mm, scale+offset fit)")
    axes[0][-1].legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
