"""The host side of `jaxps reconstruct` at 1 MP: reading frames, measuring motion, writing outputs.

`jaxps demo --size 1024 --width 1280` writes five 16-bit PNG frames, an ambient frame and a
mask (not timed). Then, in this one process, each timed case runs once to warm up and then
`ROUNDS` times, the cases of a row interleaved so that the load of a shared machine hits them
alike; medians and minima are recorded.

- `decode`: the five frames read one after another (`read_image`, then `np.stack`) against
  `load_stack` (a thread per frame, straight into one aligned stack).
- `fft`: numpy's forward FFT of a complex64 frame unscaled (`np.fft.fft2`), scaled by 1/n
  (`norm="forward"`, what `estimate_shifts` takes) and the scaled inverse, at the demo mask's
  correlation box and at the full frame.
- `load_capture`: the whole load of the demo capture (frames, ambient, mask, motion estimate,
  intensities).
- `write`: `jaxps reconstruct`'s output files on one thread against two
  (`_write_outputs` in `src/jaxps/cli/_reconstruct.py`).

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_io.py [--quick]
    -> benchmarks/results/io.json
"""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import tempfile

import numpy as np

try:
    from benchmarks._common import arguments, environment, interleaved, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, environment, interleaved, write_json

QUICK = "--quick" in sys.argv or os.environ.get("JAXPS_BENCH_QUICK") == "1"
ROUNDS = 3 if QUICK else 9
SIZE = (256, 320) if QUICK else (1024, 1280)  # rows, columns; --quick for a smoke run


def _rounds(cases):
    """{name: {"median_s", "min_s"}} over `ROUNDS` interleaved calls of each case."""
    _, times = interleaved(cases, ROUNDS)
    return {name: {"median_s": float(np.median(v)), "min_s": float(min(v))}
            for name, v in times.items()}


def main():
    import jaxps
    from jaxps.acquisition import load_capture, load_stack, read_image
    from jaxps.acquisition._register import _box, _fast_len
    from jaxps.cli import _reconstruct

    res = {"env": environment(), "rounds": ROUNDS, "quick": QUICK, "frame": list(SIZE),
           "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
           "numpy": np.__version__}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        subprocess.run([sys.executable, "-m", "jaxps", "demo", "--size", str(SIZE[0]), "--width",
                        str(SIZE[1]), "--out", str(tmp / "demo")], check=True, capture_output=True,
                       env={**os.environ, "JAXPS_CACHE_DIR": "off"})
        folder = tmp / "demo" / "frames"
        frames = [str(folder / f"frame_{i}.png") for i in range(5)]
        res["decode"] = _rounds({
            "one after another": lambda: np.stack([read_image(p) for p in frames]),
            "load_stack (threads)": lambda: load_stack(frames)})

        mask = read_image(folder / "mask.png") > 0
        box = _box(mask, pad=4)
        rng = np.random.default_rng(0)
        res["fft"] = {}
        for name, shape in (("mask box", (_fast_len(box[1] - box[0]),
                                           _fast_len(box[3] - box[2]))),
                            ("frame", mask.shape)):
            x = rng.random(shape).astype(np.complex64)
            res["fft"][f"{name} {shape[0]}x{shape[1]}"] = _rounds({
                "fft2 (unscaled)": lambda x=x: np.fft.fft2(x),
                "fft2 norm='forward' (scaled)": lambda x=x: np.fft.fft2(x, norm="forward"),
                "ifft2 (scaled)": lambda x=x: np.fft.ifft2(x)})

        kw = {"lights": folder / "lights.txt", "ambient": folder / "ambient.png",
              "mask": folder / "mask.png"}
        res["load_capture"] = _rounds({"load_capture": lambda: load_capture(frames, **kw)})

        cap = load_capture(frames, **kw)
        ps = jaxps.photometric_stereo(cap.images, cap.lights, mask=cap.mask)
        ok = np.asarray(ps.status) == 0
        height = np.asarray(jaxps.integrate(ps.normals, mask=ok))
        res["write"] = _rounds({
            f"{n} thread{'s' if n > 1 else ''}": lambda n=n: _reconstruct._write_outputs(
                tmp / f"out{n}", ps, height, ok, title="demo", threads=n) for n in (1, 2)})
    path = write_json("io", res)
    for row in ("decode", "load_capture", "write"):
        for name, r in res[row].items():
            print(f"{row:>12}: {name:<28} median {r['median_s']:.4f} s, min {r['min_s']:.4f} s")
    for size, cases in res["fft"].items():
        for name, r in cases.items():
            print(f"fft {size:>18}: {name:<28} median {1e3 * r['median_s']:.2f} ms")
    print(f"-> {path}")


if __name__ == "__main__":
    arguments(__doc__, quick=True)
    main()
