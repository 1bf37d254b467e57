"""Core speed: L2 photometric stereo and Frankot–Chellappa at 1280x1024, K = 4, 5, 12.

Compile time and run time are reported apart (first call vs. the median of repeated calls,
each ended by `block_until_ready`); numpy/scipy baselines run in the same process.

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_core.py [--repeats 20] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform

import jax
import jax.numpy as jnp
import numpy as np
import scipy.fft

import jaxps

try:
    from benchmarks._common import time_calls
except ImportError:  # run as a script
    import pathlib
    import sys

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import time_calls

H, W = 1024, 1280


def timed(fn, repeats):
    """(first-call seconds, median seconds of `repeats` further calls)."""
    t = time_calls(fn, repeats)
    return t["first_call_s"], t["run_s_median"]


def numpy_ps(images, pinv):
    """Baseline: pinv-matmul over all pixels, then normalise (float32)."""
    k = images.shape[0]
    b = pinv @ images.reshape(k, -1)
    rho = np.sqrt(np.einsum("ij,ij->j", b, b))
    n = b / np.where(rho > 0, rho, 1)
    return n.T.reshape(H, W, 3), rho.reshape(H, W)


def fc_numpy(p, q, rfft2, irfft2):
    """Baseline Frankot–Chellappa with a given real FFT pair (numpy or scipy)."""
    wc = 2 * np.pi * np.fft.rfftfreq(W)[None, :]
    wr = 2 * np.pi * np.fft.fftfreq(H)[:, None]
    denom = wc**2 + wr**2
    denom[0, 0] = 1
    z_hat = -1j * (wc * rfft2(p) + wr * rfft2(-q)) / denom
    z_hat[0, 0] = 0
    return irfft2(z_hat, s=(H, W))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                  "core.json"))
    args = ap.parse_args()

    surface = jaxps.synthetic.face_like(H, W)
    results = {"shape": [H, W], "repeats": args.repeats, "rows": []}
    for k in (4, 5, 12):
        if k in (4, 5):
            lights = jaxps.synthetic.scanner_lights(20.0, k=k)
        else:
            az = 30 * np.cos(np.linspace(0, 2 * np.pi, 11, endpoint=False))
            el = 30 * np.sin(np.linspace(0, 2 * np.pi, 11, endpoint=False))
            lights = jaxps.lights_from_angles(np.r_[0, az], np.r_[0, el])
        scene = jaxps.synthetic.render_scene(surface, lights)
        images = jax.device_put(scene.images)
        images_np = np.asarray(scene.images)
        pinv = np.linalg.pinv(lights).astype(np.float32)

        first, run = timed(lambda: jaxps.photometric_stereo(images, lights), args.repeats)
        results["rows"].append({"work": "ps_l2", "impl": "jaxps", "K": k,
                                "compile_s": first - run, "run_s": run})
        first, run = timed(lambda: jaxps.photometric_stereo(
            images, lights, mask=scene.mask, shadow_threshold=0.01), args.repeats)
        results["rows"].append({"work": "ps_l2_mask_shadow", "impl": "jaxps", "K": k,
                                "compile_s": first - run, "run_s": run})
        _, run = timed(lambda: numpy_ps(images_np, pinv), args.repeats)
        results["rows"].append({"work": "ps_l2", "impl": "numpy pinv-matmul+normalise",
                                "K": k, "run_s": run})

        if k == 5:
            res = jaxps.photometric_stereo(images, lights)
            normals = jax.block_until_ready(res.normals)
            first, run = timed(lambda: jaxps.integrate(normals), args.repeats)
            results["rows"].append({"work": "fc", "impl": "jaxps", "compile_s": first - run,
                                    "run_s": run})
            p, q = (np.asarray(a) for a in jaxps.gradients_from_normals(
                normals, jnp.ones((H, W), bool)))
            _, run = timed(lambda: fc_numpy(p, q, np.fft.rfft2, np.fft.irfft2), args.repeats)
            results["rows"].append({"work": "fc", "impl": "numpy rfft2 (float64)",
                                    "run_s": run})

            def scipy_r(x):
                return scipy.fft.rfft2(x, workers=2)

            def scipy_i(x, s):
                return scipy.fft.irfft2(x, s=s, workers=2)

            _, run = timed(lambda: fc_numpy(p, q, scipy_r, scipy_i), args.repeats)
            results["rows"].append({"work": "fc", "impl": "scipy rfft2 float32, 2 workers",
                                    "run_s": run})

            def both():
                r = jaxps.photometric_stereo(images, lights)
                return jaxps.integrate(r.normals)

            first, run = timed(both, args.repeats)
            results["rows"].append({"work": "ps_l2+fc", "impl": "jaxps", "K": k,
                                    "compile_s": first - run, "run_s": run})

    results["env"] = {
        "jax": jax.__version__, "numpy": np.__version__, "device": str(jax.devices()[0]),
        "cpu_count": os.cpu_count(), "platform": platform.platform(),
        "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
        "XLA_FLAGS": os.environ.get("XLA_FLAGS"),
    }
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=2)
    for r in results["rows"]:
        comp = f"  (compile {r['compile_s']:.2f} s)" if "compile_s" in r else ""
        print(f"{r['work']:>18} K={r.get('K', 5):>2} {r['impl']:<32} "
              f"{1e3 * r['run_s']:8.2f} ms{comp}")
    _chart(results, args.out.replace(".json", ".png"))


def _chart(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = results["rows"]
    labels = [f"{r['work']} K={r.get('K', 5)}\n{r['impl']}" for r in rows]
    fig, ax = plt.subplots(figsize=(9, 0.42 * len(rows) + 1), constrained_layout=True)
    colours = ["tab:blue" if r["impl"] == "jaxps" else "tab:gray" for r in rows]
    ax.barh(range(len(rows)), [1e3 * r["run_s"] for r in rows], color=colours)
    ax.set_yticks(range(len(rows)), labels, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("run time per call (ms), 1280x1024, after compile")
    ax.set_title("jaxps core (blue) vs numpy/scipy baselines (grey)")
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
