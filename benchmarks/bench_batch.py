"""Captures per second at 1280x1024x5 (L2, batched against single calls) and peak memory of a
64-capture batch.

Run: `OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_batch.py [--quick]
[--out PATH]` -> benchmarks/results/batch.json (or PATH) and batch.png. Baseline in the same
run: N single calls. The `_dropped` rows set a shadow threshold at the 5th percentile of the
samples in the mask, so every capture takes the weighted solve; the `_k12` rows take 12 lights.
The batch solves the stack as one image (`_l2_one_image`); the `lights_per_capture` rows give
the same lights once per capture, `(N, K, 3)`. A batch keeps its latest two results and
writes into a dropped one (`spare_outputs` in `core/_kept.py`), as the repeated calls here
do; the `_fresh` rows turn that off (`JAXPS_BATCH_KEEP_BYTES=0`), so every batch writes into
fresh outputs.
`--emitters` times the one-image solve compiled with XLA-CPU's default and older emitters
(results/batch_emitters.json), which chose `_BATCH_PROGRAMS` in `ps/_l2.py`; `--copy` times
moving an unaligned numpy stack to the device (results/batch_copy.json).
The 64-capture runs are fresh processes (`--peak-rss N CHUNK [--dropped]`, CHUNK `None` for
the default) whose peak resident memory (`ru_maxrss`) is recorded, input stack included:
clean captures in chunks of 8, and captures that drop samples in the default chunks and in
chunks of 8. Each row also records the minor page faults
of one more call (`page_faults`): first writes to pages the allocator just took from the
kernel, which fresh `(N, ...)` outputs pay on every batch.
"""

from __future__ import annotations

import functools
import json
import os
import pathlib
import platform
import resource
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np

import jaxps
from jaxps.core._host import aligned
from jaxps.ps._batch import _batched_fn

OUT = pathlib.Path(__file__).resolve().parent / "results"
QUICK = "--quick" in sys.argv or os.environ.get("JAXPS_BENCH_QUICK") == "1"
# --quick (used by `python -m benchmarks --quick`): 256x320, for a smoke run, marked in the JSON.
H, W, K, N = (256, 320, 5, 2) if QUICK else (1024, 1280, 5, 8)
N_BIG = 8 if QUICK else 64


try:
    from benchmarks._common import arguments, environment, interleaved, page_faults, timed
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, environment, interleaved, page_faults, timed


def captures(n, seed=0, k=K):
    """`n` copies of a synthetic face with per-frame flash gains in [0.85, 1.15]; the mask.
    The five scanner lights, or for `k` = 12 a frontal light and 11 on a 30-degree ring."""
    rng = np.random.default_rng(seed)
    if k == 5:
        lights = jaxps.synthetic.scanner_lights(20.0)
    else:
        t = np.linspace(0, 2 * np.pi, k - 1, endpoint=False)
        lights = jaxps.lights_from_angles(np.r_[0, 30 * np.cos(t)], np.r_[0, 30 * np.sin(t)])
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(H, W), lights)
    base = np.asarray(scene.images)
    caps = np.stack([base * rng.uniform(0.85, 1.15, (k, 1, 1)).astype(np.float32)
                     for _ in range(n)]).astype(np.float32)
    return caps, lights, np.asarray(scene.mask)


def emitters(rounds=8):
    """The one-image batch solve (`ps/_l2.py`, `_BATCH_PROGRAMS`, and `_BATCH_WEIGHTED`'s two
    programs for the weighted rows, into fresh memory) compiled with XLA-CPU's
    default and older emitters, 8 captures of 1 MP, K=5 and K=12, clean and weighted (the
    weighted rows with a shadow threshold at the 5th percentile of the samples in the mask,
    as the `_dropped` rows of the main run): medians of `rounds` interleaved rounds, in ms
    (`--emitters` -> results/batch_emitters.json)."""
    from jaxps.core._host import OLDER_EMITTERS
    from jaxps.ps import _l2
    from jaxps.ps._photometric_stereo import _sample_thresholds

    def weighted(options):  # the two programs of `_l2._BATCH_WEIGHTED`, one after the other
        planes = jax.jit(_l2._batch_planes, static_argnames="branch", **options)
        unpack = jax.jit(_l2._batch_unpack, static_argnames=("channels", "dtype"), **options)
        return lambda *a, dtype: unpack(  # a[-1], the constants of the clean solve, unused
            None, planes((None, None), *a[:-1], branch="weighted_finite"), channels=1,
            dtype=dtype)

    programs = {
        "default": {"all_used": jax.jit(_l2._batch_solve, static_argnames="dtype"),
                    "weighted_finite": weighted({})},
        "older": {"all_used": jax.jit(_l2._batch_solve, static_argnames="dtype",
                                      compiler_options=OLDER_EMITTERS),
                  "weighted_finite": weighted({"compiler_options": OLDER_EMITTERS})}}
    fns = {}
    for k in (5, 12):
        caps, lights, mask = captures(N, k=k)
        shadow = float(np.percentile(caps[0][:, mask], 5))
        lights = np.asarray(lights, np.float64)
        lights /= np.linalg.norm(lights, axis=-1, keepdims=True)
        for branch in ("all_used", "weighted_finite"):
            thresholds = tuple(jnp.asarray(t, np.float32) for t in _sample_thresholds(
                shadow_threshold=shadow if branch == "weighted_finite" else None))
            args = (jax.device_put(aligned(caps)), jax.device_put(lights.astype(np.float32)),
                    jax.device_put(aligned(np.broadcast_to(mask, (N, *mask.shape)))), None,
                    thresholds, jax.device_put(_l2.host_constants(lights)))
            for name, program in programs.items():
                fns[f"k{k}_{branch}_{name}"] = functools.partial(
                    program[branch], *args, dtype=np.dtype(np.float32))
    _, times = interleaved(fns, rounds)
    res = {"env": environment(), "shape": [N, "K", H, W], "rounds": rounds,
           "median_ms": {k: 1e3 * float(np.median(v)) for k, v in times.items()}}
    OUT.mkdir(exist_ok=True)
    (OUT / "batch_emitters.json").write_text(json.dumps(res, indent=1))
    print(json.dumps(res["median_ms"], indent=1))


def copies(repeats=5):
    """An unaligned numpy stack of 8 captures of 1 MP x 5 moved to the device: by
    `jax.device_put` (its own copy), and by `core._host.aligned` on one thread and on every
    core into fresh memory, and on every core into one aligned buffer used by every call (as
    `photometric_stereo_batch` keeps it, `_staged`), then `device_put` in place. Medians in ms
    (`--copy` -> results/batch_copy.json)."""
    from jaxps.core._host import aligned_empty, cpu_cores

    caps = captures(N)[0]
    if caps.ctypes.data % 64 == 0:  # numpy's allocation happened to be aligned: shift it
        caps = np.frombuffer(np.empty(caps.nbytes + 16, np.uint8)[16:], np.float32).reshape(
            caps.shape)
    fns = {"device_put": lambda: jax.device_put(caps),
           "aligned_1_thread": lambda: jax.device_put(aligned(caps)),
           f"aligned_{cpu_cores()}_threads": lambda: jax.device_put(
               aligned(caps, threads=cpu_cores())),
           f"aligned_{cpu_cores()}_threads_kept_buffer": lambda: jax.device_put(
               aligned(caps, threads=cpu_cores(), out=kept))}
    kept = aligned_empty(caps.shape, caps.dtype)
    _, times = interleaved(fns, repeats)
    res = {"env": environment(), "shape": list(caps.shape), "address_mod_64":
           caps.ctypes.data % 64, "median_ms": {k: 1e3 * float(np.median(v))
                                                for k, v in times.items()}}
    OUT.mkdir(exist_ok=True)
    (OUT / "batch_copy.json").write_text(json.dumps(res, indent=1))
    print(json.dumps(res["median_ms"], indent=1))


def peak_rss(n, chunk, dropped=False):
    """Solve `n` captures in chunks of `chunk` (None: the default) in this process, with a
    shadow threshold at the 5th percentile of the samples if `dropped` (every capture then
    takes the weighted solve); print the peak RSS in GB."""
    caps, lights, mask = captures(n)
    options = ({"shadow_threshold": float(np.percentile(caps[0][:, mask], 5))} if dropped
               else {})
    res = jaxps.photometric_stereo_batch(caps, lights, mask=mask, chunk=chunk, **options)
    jax.block_until_ready(res)
    ok = float(np.mean(np.asarray(res.status) == 0))
    print(json.dumps({"peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
                      "ok_fraction": ok}))


def peak_rss_run(n, chunk, dropped=False):
    """`peak_rss` in a fresh process: `{"captures", "chunk", "dropped", "peak_rss_gb",
    "ok_fraction"}` (`chunk` None: the default)."""
    out = subprocess.run([sys.executable, __file__, "--peak-rss", str(n), str(chunk)]
                         + (["--dropped"] if dropped else []) + (["--quick"] if QUICK else []),
                         capture_output=True, text=True, check=True)
    return {"captures": n, "chunk": chunk, "dropped": dropped,
            **json.loads(out.stdout.strip().splitlines()[-1])}


def main():
    caps, lights, mask = captures(N)
    res = {"device": str(jax.devices()[0]), "device_count": jax.device_count(),
           "platform": platform.processor() or platform.machine(),
           "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
           "env": environment(), "shape": [N, K, H, W], "quick": QUICK}
    # Captures as numpy arrays (as loaded from files) and already on the device: each call
    # then pays, or does not pay, for moving them there.
    # numpy stacks are 16-byte aligned and copied on every call; `load_capture` returns
    # 64-byte-aligned frames, which XLA-CPU reads in place (src/jaxps/core/_host.py).
    dev = jax.device_put(caps)
    caps_aligned = aligned(caps)
    threshold = float(np.percentile(caps[0][:, mask], 5))
    caps12, lights12, _ = captures(N, k=12)
    caps12 = aligned(caps12)
    lax_map = _batched_fn("l2", {}, True, True, None)
    # the same lights given once per capture, `(N, K, 3)`
    per_capture = np.broadcast_to(lights, (N, *np.shape(lights)))

    def stream(**options):  # a stream of batches, each written into the previous result
        previous = []

        def run():
            out = jaxps.photometric_stereo_batch(caps_aligned, lights, mask=mask,
                                                 out=previous.pop() if previous else None,
                                                 **options)
            previous.append(out)
            return out
        return run

    def fresh(**options):  # nothing kept between batches: every batch into fresh outputs
        def run():
            before = os.environ.get("JAXPS_BATCH_KEEP_BYTES")
            os.environ["JAXPS_BATCH_KEEP_BYTES"] = "0"
            try:
                return jaxps.photometric_stereo_batch(caps_aligned, lights, mask=mask, **options)
            finally:
                if before is None:
                    del os.environ["JAXPS_BATCH_KEEP_BYTES"]
                else:
                    os.environ["JAXPS_BATCH_KEEP_BYTES"] = before
        return run

    rows = {
        "batch_l2": lambda: jaxps.photometric_stereo_batch(caps, lights, mask=mask),
        "single_calls_l2": lambda: [jaxps.photometric_stereo(c, lights, mask=mask)
                                    for c in caps],
        "batch_l2_aligned": lambda: jaxps.photometric_stereo_batch(caps_aligned, lights,
                                                                   mask=mask),
        "single_calls_l2_aligned": lambda: [jaxps.photometric_stereo(c, lights, mask=mask)
                                            for c in caps_aligned],
        "batch_l2_on_device": lambda: jaxps.photometric_stereo_batch(dev, lights, mask=mask),
        "single_calls_l2_on_device": lambda: [jaxps.photometric_stereo(dev[i], lights,
                                                                       mask=mask)
                                              for i in range(N)],
        "batch_l2_vmap": lambda: jaxps.photometric_stereo_batch(dev, lights, mask=mask,
                                                                vmap_size=N),
        # The previous default for L2 (the one other methods still take): one jitted
        # `lax.map` over the captures.
        "batch_l2_lax_map_aligned": lambda: lax_map(jax.device_put(caps_aligned),
                                                    jnp.asarray(lights), jnp.asarray(mask),
                                                    None),
        # A stream of batches: each call writes into the previous call's result (`out=`).
        "batch_l2_aligned_reusing_out": stream(),
        # Every batch into fresh outputs (`JAXPS_BATCH_KEEP_BYTES=0`): what the other batch
        # rows were before a batch kept its results for reuse.
        "batch_l2_aligned_fresh": fresh(),
        "batch_l2_aligned_dropped": lambda: jaxps.photometric_stereo_batch(
            caps_aligned, lights, mask=mask, shadow_threshold=threshold),
        "single_calls_l2_aligned_dropped": lambda: [jaxps.photometric_stereo(
            c, lights, mask=mask, shadow_threshold=threshold) for c in caps_aligned],
        "batch_l2_aligned_dropped_reusing_out": stream(shadow_threshold=threshold),
        "batch_l2_aligned_dropped_fresh": fresh(shadow_threshold=threshold),
        "batch_l2_aligned_k12": lambda: jaxps.photometric_stereo_batch(caps12, lights12,
                                                                       mask=mask),
        "single_calls_l2_aligned_k12": lambda: [jaxps.photometric_stereo(c, lights12, mask=mask)
                                                for c in caps12],
    }
    rows["batch_l2_aligned_lights_per_capture"] = lambda: jaxps.photometric_stereo_batch(
        caps_aligned, per_capture, mask=mask)
    rows["batch_l2_aligned_lights_per_capture_dropped"] = lambda: jaxps.photometric_stereo_batch(
        caps_aligned, per_capture, mask=mask, shadow_threshold=threshold)
    for name, fn in rows.items():
        _, first, run = timed(fn, repeats=5)
        res[name] = {"compile_plus_first_s": first, "run_s": run, "captures_per_s": N / run,
                     "page_faults": page_faults(fn)}
    # Throughput ratios: each batch row against the single calls on the same input.
    for key, batch, single in (
            ("batch_over_single_throughput", "batch_l2", "single_calls_l2"),
            ("batch_over_single_throughput_aligned", "batch_l2_aligned",
             "single_calls_l2_aligned"),
            ("batch_over_single_throughput_on_device", "batch_l2_on_device",
             "single_calls_l2_on_device"),
            ("reusing_out_over_single_throughput_aligned", "batch_l2_aligned_reusing_out",
             "single_calls_l2_aligned"),
            ("fresh_over_single_throughput_aligned", "batch_l2_aligned_fresh",
             "single_calls_l2_aligned"),
            ("fresh_over_single_throughput_aligned_dropped", "batch_l2_aligned_dropped_fresh",
             "single_calls_l2_aligned_dropped"),
            ("lax_map_over_single_throughput_aligned", "batch_l2_lax_map_aligned",
             "single_calls_l2_aligned"),
            ("batch_over_single_throughput_aligned_dropped", "batch_l2_aligned_dropped",
             "single_calls_l2_aligned_dropped"),
            ("reusing_out_over_single_throughput_aligned_dropped",
             "batch_l2_aligned_dropped_reusing_out", "single_calls_l2_aligned_dropped"),
            ("batch_over_single_throughput_aligned_k12", "batch_l2_aligned_k12",
             "single_calls_l2_aligned_k12"),
            ("lights_per_capture_over_single_throughput_aligned",
             "batch_l2_aligned_lights_per_capture", "single_calls_l2_aligned"),
            ("lights_per_capture_over_single_throughput_aligned_dropped",
             "batch_l2_aligned_lights_per_capture_dropped", "single_calls_l2_aligned_dropped")):
        res[key] = res[batch]["captures_per_s"] / res[single]["captures_per_s"]
    res["batch_peak_memory"] = peak_rss_run(N_BIG, 8)
    # the default chunks and chunks of 8, every capture taking the weighted solve
    res["batch_peak_memory_dropped"] = [peak_rss_run(N_BIG, c, dropped=True) for c in (None, 8)]
    _, first, run = timed(lambda: jaxps.photometric_stereo(caps[0], lights, mask=mask,
                                                           method="semi_calibrated"), repeats=1)
    res["semi_calibrated_one_capture"] = {"compile_plus_first_s": first, "run_s": run}
    _, first, run = timed(lambda: jaxps.intensity_estimate(caps[0], lights, mask=mask,
                                                           method="frontal"), repeats=1)
    res["frontal_estimate_one_capture"] = {"compile_plus_first_s": first, "run_s": run}
    path = pathlib.Path(sys.argv[sys.argv.index("--out") + 1]) if "--out" in sys.argv \
        else OUT / "batch.json"
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps(res, indent=1))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = {
        "batch_l2": "batch\n(numpy)", "single_calls_l2": "singles\n(numpy)",
        "batch_l2_aligned": "batch\n(aligned)", "single_calls_l2_aligned": "singles\n(aligned)",
        "batch_l2_on_device": "batch\n(device)", "single_calls_l2_on_device": "singles\n(device)",
        "batch_l2_vmap": "batch vmap\n(device)", "batch_l2_lax_map_aligned": "lax.map\n(aligned)",
        "batch_l2_aligned_reusing_out": "batch, out=\n(aligned)",
        "batch_l2_aligned_fresh": "batch, fresh\n(aligned)",
        "batch_l2_aligned_dropped_fresh": "batch, fresh\n(dropped)",
        "batch_l2_aligned_dropped": "batch\n(dropped)",
        "single_calls_l2_aligned_dropped": "singles\n(dropped)",
        "batch_l2_aligned_dropped_reusing_out": "batch, out=\n(dropped)",
        "batch_l2_aligned_k12": "batch\n(K=12)", "single_calls_l2_aligned_k12": "singles\n(K=12)",
        "batch_l2_aligned_lights_per_capture": "batch, lights\nper capture",
        "batch_l2_aligned_lights_per_capture_dropped": "lights per\ncapture, dropped"}
    labels = [labels[k] for k in rows] + ["semi-cal.\n(one)"]
    vals = [res[k]["run_s"] / N for k in rows] + [res["semi_calibrated_one_capture"]["run_s"]]
    plt.figure(figsize=(18, 3.2))
    plt.bar(labels, vals)
    plt.ylabel("seconds per capture")
    plt.title(f"{W}x{H}x{K}, {res['device']}")
    plt.tight_layout()
    plt.savefig(path.with_suffix(".png"), dpi=100)
    print(json.dumps(res, indent=1))


def _options(parser):
    parser.add_argument("--out", help="JSON path (default results/batch.json; the chart beside it)")
    parser.add_argument("--peak-rss", nargs=2, metavar=("N", "CHUNK"),
                        help="one fresh-process memory run: N captures in chunks of CHUNK "
                             "(None: the default)")
    parser.add_argument("--dropped", action="store_true",
                        help="with --peak-rss: every capture drops samples")
    parser.add_argument("--emitters", action="store_true",
                        help="time the solve with default and older emitters instead")
    parser.add_argument("--copy", action="store_true",
                        help="time moving an unaligned stack to the device instead")


if __name__ == "__main__":
    args = arguments(__doc__, quick=True, configure=_options)
    if args.peak_rss:
        n, chunk = args.peak_rss
        peak_rss(int(n), None if chunk == "None" else int(chunk), dropped=args.dropped)
    elif args.emitters:
        emitters()
    elif args.copy:
        copies()
    else:
        main()
