"""Stability sweeps: angular error of every PS method as one corruption grows.

Writes benchmarks/results/stability.json and stability.png. Run:
    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_stability.py [--h 96]
Scene and sweeps: `jaxps.stability.SWEEPS` (face_like relief, 5 scanner lights at 20 deg,
0.5% noise, cast shadows and a Blinn-Phong lobe unless the sweep varies them).
"""

import argparse
import json
import os
import pathlib
import time

import jax
import numpy as np

from jaxps.report import progress_bar
from jaxps.stability import SWEEPS, sweep

OUT = pathlib.Path(__file__).resolve().parent / "results"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--h", type=int, default=96)
    ap.add_argument("--sweeps", nargs="*", default=list(SWEEPS))
    ap.add_argument("--quick", action="store_true", help="48-pixel scenes")
    args = ap.parse_args()
    if args.quick:
        args.h = 48
    t0 = time.perf_counter()
    results = {}
    for name in args.sweeps:
        t = time.perf_counter()
        results[name] = sweep(name, h=args.h, key=jax.random.key(7), progress=progress_bar())
        print(f"{name}: {time.perf_counter() - t:.1f} s", flush=True)
    # "Tolerant to errors in the light source vectors": normal error per degree of light error.
    le = results.get("light_error_deg")
    summary = {}
    if le:
        x = np.asarray(le["values"])
        for m, rec in le["methods"].items():
            y = np.asarray(rec["median_deg"])
            summary[m] = {"median_at_0": float(y[0]),
                          "slope_deg_per_deg": float(np.polyfit(x, y, 1)[0]),
                          "added_median_at_5deg": float(np.interp(5.0, x, y) - y[0])}
    nonfinite = sum(sum(r["nonfinite"]) for s in results.values() for r in s["methods"].values())
    doc = {"machine": {"OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
                       "jax": jax.__version__, "device": str(jax.devices()[0])},
           "h": args.h, "seconds": time.perf_counter() - t0, "nonfinite_total": nonfinite,
           "light_error_tolerance": summary, "sweeps": results}
    OUT.mkdir(exist_ok=True)
    (OUT / "stability.json").write_text(json.dumps(doc, indent=1))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(13, 7.5))
    for ax, (name, res) in zip(axes.ravel(), results.items()):
        for m, rec in res["methods"].items():
            ax.plot(res["values"], rec["median_deg"], "o-", label=m)
        ax.set_xlabel(name)
        ax.set_ylabel("median angular error (deg)")
        if name == "zenith_deg":
            sh = [s["shadowed"] for s in res["scene"]]
            ax.set_title("shadowed samples " + ", ".join(f"{100 * v:.0f}%" for v in sh),
                         fontsize=8)
        if name == "gain":
            sat = [s["saturated"] for s in res["scene"]]
            ax.set_title("saturated samples " + ", ".join(f"{100 * v:.0f}%" for v in sat),
                         fontsize=8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"jaxps stability sweeps (face_like {args.h} px, median over the object)")
    fig.tight_layout()
    fig.savefig(OUT / "stability.png", dpi=110)
    print(json.dumps({"nonfinite_total": nonfinite, "light_error_tolerance": summary}, indent=1))


if __name__ == "__main__":
    main()
