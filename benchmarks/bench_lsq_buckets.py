"""How often `integrate(method="lsq")` compiles over a scanner's session, by crop-size rule.

`"lsq"` solves on the box of the valid pixels, its sides grown to a bucket size, and the
multigrid solve compiles once per size (1-3 s). A scanner's face boxes differ
from capture to capture by tens of pixels. The session here: `--captures` synthetic faces
(`synthetic.face_like`, 520-720 px tall, 0.8 as wide) at random places in 1024x1280 frames,
their true normals with Gaussian noise (sd `--noise` per component, then normalised),
integrated one after another in one process, as `jaxps reconstruct DIR...` does. Each rule
runs in a fresh process, the rules alternating over `--rounds`:

- `"32 px"`: each side rounded up to a multiple of 32 px (the rule until the twenty-seventh
  session, patched in here);
- `"ladder"`: `_integrate._bucket`, 32-px steps up to 256 px, then a quarter of the power of
  two below (320, 384, 448, 512, 640, ...);
- `"whole frame"`: no crop, the whole 1024x1280 frame solved with its mask (one compile).

Per rule and round: the crop sizes, the session's total seconds (compiles included), each
capture's warm time (the median of `--repeats` further calls, after the session), and each
height's RMS error (px) against the true height, over the face, both mean-free.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_lsq_buckets.py

Writes benchmarks/results/lsq_buckets.json and lsq_buckets.png.

With `--emitters`, it compares instead the program that `"lsq"` runs as (`_lsq_height`)
compiled with XLA-CPU's default emitters (`.plain`, as until the twenty-seventh session) and
with the older ones (`.tuned`, now): for faces of three sizes in a 1024x1280 frame, each
variant's compile time (`lower(...).compile()`, the two in turn, first one then the other
for alternate sizes), the median of `--repeats` warm calls taken in turn, and the largest
difference of the heights. Writes benchmarks/results/lsq_emitters.json.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import subprocess
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
RULES = ("32 px", "ladder", "whole frame")
FRAME = (1024, 1280)


def session(captures: int, noise: float, seed: int):
    """`captures` (normals, mask, height) of faces of random size and place in FRAME."""
    from jaxps import synthetic

    rng = np.random.default_rng(seed)
    for _ in range(captures):
        h = int(rng.integers(520, 721))
        face = synthetic.face_like(h)
        n_face, m_face = np.asarray(face.normals), np.asarray(face.mask)
        top = int(rng.integers(0, FRAME[0] - h + 1))
        left = int(rng.integers(0, FRAME[1] - n_face.shape[1] + 1))
        normals = np.zeros((*FRAME, 3), np.float32)
        normals[..., 2] = 1
        mask = np.zeros(FRAME, bool)
        height = np.zeros(FRAME, np.float32)
        window = np.s_[top:top + h, left:left + n_face.shape[1]]
        normals[window], mask[window], height[window] = n_face, m_face, np.asarray(face.height)
        normals += rng.normal(0, noise, normals.shape).astype(np.float32)
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        yield normals, mask, height


def child(rule: str, captures: int, noise: float, seed: int, repeats: int) -> dict:
    import jax

    from jaxps.integration import _integrate, integrate

    if rule == "32 px":
        _integrate._bucket = lambda n: -(-n // 32) * 32
    elif rule == "whole frame":
        _integrate._bucket = lambda n: 1 << 30  # every side then takes the whole frame
    data = list(session(captures, noise, seed))
    # warm the process (imports, the normals' programs) on a size no capture uses
    integrate(np.dstack([np.zeros((64, 64, 2), np.float32), np.ones((64, 64), np.float32)]),
              method="lsq").block_until_ready()
    first, sizes, rms = [], [], []
    start = time.perf_counter()
    for normals, mask, height in data:
        t = time.perf_counter()
        z = np.asarray(integrate(normals, mask=mask, method="lsq").block_until_ready())
        first.append(time.perf_counter() - t)
        box = _integrate._crop(mask)
        sizes.append([box[0].stop - box[0].start, box[1].stop - box[1].start])
        dz = (z - height)[mask]
        rms.append(float(np.sqrt(np.mean((dz - dz.mean()) ** 2))))
    total = time.perf_counter() - start
    warm = []
    for normals, mask, _ in data:
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            integrate(normals, mask=mask, method="lsq").block_until_ready()
            ts.append(time.perf_counter() - t)
        warm.append(float(np.median(ts)))
    return {"rule": rule, "crop_sizes": sizes, "distinct_sizes": len({tuple(s) for s in sizes}),
            "session_s": total, "first_call_s": first, "warm_s": warm,
            "height_rms_px": rms, "jax": jax.__version__}


def emitters(repeats: int, noise: float, seed: int) -> list[dict]:
    import jax.numpy as jnp

    from jaxps import synthetic
    from jaxps.core._host import to_device
    from jaxps.integration import _integrate

    rng = np.random.default_rng(seed)
    rows = []
    for i, h in enumerate((300, 480, 620)):
        face = synthetic.face_like(h)
        fh, fw = face.mask.shape
        top, left = (FRAME[0] - fh) // 2, (FRAME[1] - fw) // 2
        normals = np.zeros((*FRAME, 3), np.float32)
        normals[..., 2] = 1
        mask = np.zeros(FRAME, bool)
        normals[top:top + fh, left:left + fw] = np.asarray(face.normals)
        mask[top:top + fh, left:left + fw] = np.asarray(face.mask)
        normals += rng.normal(0, noise, normals.shape).astype(np.float32)
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        box = _integrate._crop(mask)
        size = (box[0].stop - box[0].start, box[1].stop - box[1].start)
        args = (to_device(normals), to_device(mask),
                to_device(np.array([box[0].start, box[1].start], np.int32)),
                to_device(1.0, jnp.float32))
        static = {"size": size, "rtol": _integrate._LSQ_RTOL, "max_steps": 10_000,
                  "preconditioner": "multigrid"}
        variants = {"default emitters (before)": _integrate._lsq_height.plain,
                    "older emitters (now)": _integrate._lsq_height.tuned}
        order = list(variants) if i % 2 == 0 else list(variants)[::-1]
        compiled, compile_s = {}, {}
        for name in order:
            t = time.perf_counter()
            compiled[name] = variants[name].lower(*args, **static).compile()
            compile_s[name] = time.perf_counter() - t
        warm = {name: [] for name in variants}
        for _ in range(repeats):
            for name, f in compiled.items():
                t = time.perf_counter()
                f(*args).block_until_ready()
                warm[name].append(time.perf_counter() - t)
        a, b = (np.asarray(f(*args)) for f in compiled.values())
        rows.append({"face_rows": h, "crop": list(size), "compile_order": order,
                     "compile_s": compile_s,
                     "warm_s_median": {k: float(np.median(v)) for k, v in warm.items()},
                     "max_height_difference_px": float(np.abs(a - b).max()),
                     "height_range_px": float(np.ptp(a[mask]))})
        print(rows[-1], flush=True)
    return rows


def plot(results: list[dict], path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    colours = dict(zip(RULES, ("C0", "C1", "C2")))
    for r in results:
        colour = colours[r["rule"]]
        label = f"{r['rule']} (round {r['round']}): {r['distinct_sizes']} sizes, " \
                f"{r['session_s']:.1f} s"
        a.plot(np.cumsum(r["first_call_s"]), "o-", color=colour, label=label,
               alpha=1.0 if r["round"] == 1 else 0.5)
        b.plot(r["warm_s"], "o", color=colour, alpha=1.0 if r["round"] == 1 else 0.5)
    a.set_xlabel("capture")
    a.set_ylabel("session time so far (s, compiles included)")
    a.legend(fontsize=8)
    b.set_xlabel("capture")
    b.set_ylabel("warm call (s)")
    fig.suptitle('integrate(method="lsq") over a session of 1024x1280 faces, by crop-size rule')
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", type=int, default=24)
    ap.add_argument("--noise", type=float, default=0.02)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--child", choices=RULES, help=argparse.SUPPRESS)
    ap.add_argument("--out", default="lsq_buckets")
    ap.add_argument("--emitters", action="store_true",
                    help="compare the default and the older XLA-CPU emitters instead")
    args = ap.parse_args()
    meta = {"command": "OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python "
                       "benchmarks/bench_lsq_buckets.py " + " ".join(sys.argv[1:]),
            "frame": FRAME, "noise": args.noise, "seed": args.seed, "repeats": args.repeats,
            "machine": platform.machine(), "cpus": os.cpu_count(),
            "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS")}
    out_dir = ROOT / "benchmarks" / "results"
    if args.emitters:
        rows = emitters(args.repeats, args.noise, args.seed)
        (out_dir / "lsq_emitters.json").write_text(json.dumps({"meta": meta, "rows": rows},
                                                              indent=1) + "\n")
        return
    if args.child:
        print(json.dumps(child(args.child, args.captures, args.noise, args.seed, args.repeats)))
        return
    results = []
    for round_ in range(1, args.rounds + 1):
        for rule in RULES:
            cmd = [sys.executable, __file__, "--child", rule, "--captures", str(args.captures),
                   "--noise", str(args.noise), "--seed", str(args.seed),
                   "--repeats", str(args.repeats)]
            out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
            r = json.loads(out.strip().splitlines()[-1]) | {"round": round_}
            results.append(r)
            print(f"round {round_} {rule:11s}: {r['distinct_sizes']} sizes, session "
                  f"{r['session_s']:.1f} s, warm median {np.median(r['warm_s']):.3f} s, "
                  f"height RMS median {np.median(r['height_rms_px']):.3f} px", flush=True)
    meta["captures"] = args.captures
    (out_dir / f"{args.out}.json").write_text(json.dumps({"meta": meta, "runs": results},
                                                         indent=1) + "\n")
    plot(results, out_dir / f"{args.out}.png")


if __name__ == "__main__":
    main()
