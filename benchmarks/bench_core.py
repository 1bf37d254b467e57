"""Core speed, each figure as a ratio to its numpy/scipy baseline in the same run.

At 1280x1024: L2 photometric stereo (K = 4, 5, 12; K = 12 with about 5% of the samples in the
mask dropped by a shadow threshold), Frankot–Chellappa and the DCT Poisson solve, and PS + FC
together. Beside each L2 row, `bare_l2`: the least an XLA kernel does for the same solve
(normals and albedo only), as the limit of XLA on the machine. Then time per pixel from
0.25 MP to 16 MP (PS K=5 and FC, numpy's PS, scipy's FC and the bare kernel beside them;
the sizes take turns over the rounds), and the peak resident
memory of a fresh process that solves and integrates one 16 MP five-frame capture.

Compile time and run time are reported apart (first call vs. the median of repeated calls,
each ended by `block_until_ready`). Each 1 MP row takes turns with its baseline over the
rounds (`--repeats` of them). The ratio is jaxps / baseline: below 1 is faster.

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_core.py [--repeats 30] [--quick] [--out FILE]
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import resource
import statistics
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import scipy.fft

import jaxps
from jaxps.core._host import OLDER_EMITTERS, CpuTuned
from jaxps.integration._poisson import dct_poisson

try:
    from benchmarks._common import block, environment, interleaved, page_faults
except ImportError:  # run as a script
    import pathlib

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import block, environment, interleaved, page_faults

H, W = 1024, 1280


def ring_lights(k):
    """A frontal light and k-1 on a 30-degree ring."""
    t = np.linspace(0, 2 * np.pi, k - 1, endpoint=False)
    return jaxps.lights_from_angles(np.r_[0, 30 * np.cos(t)], np.r_[0, 30 * np.sin(t)])


def numpy_ps(images, pinv):
    """Baseline: pinv-matmul over all pixels, then normalise (float32)."""
    k, h, w = images.shape
    b = pinv @ images.reshape(k, -1)
    rho = np.sqrt(np.einsum("ij,ij->j", b, b))
    n = b / np.where(rho > 0, rho, 1)
    return n.T.reshape(h, w, 3), rho.reshape(h, w)


def bare_l2(lights, shadow=None, default_emitters=False):
    """The least an XLA program does for L2 PS: a jitted kernel on a `(K, H, W)` stack that
    writes only the normals `(H, W, 3)` and the albedo `(H, W)`, with no status, `n_used`,
    residual or finiteness guard, the sums over K and the 3 axes unrolled and the lights baked
    in as constants. With `shadow`, a sample below it gets weight 0 and each pixel solves its
    own normal equations by cofactors, as the weighted solve does; without, $L^+$ is applied.

    Each call writes into the buffers of the previous call's result (donated: that result is
    gone), as jaxps's large calls write into kept ones, so that at 16 MP the kernel maps no
    fresh memory. It is compiled with XLA-CPU's older loop emitters, as jaxps's L2 programs
    are: with the default ones the kernel took 1.38-1.44x as long at K=5 and 1.51-1.68x at
    K=12 (`core_s19_1..3.json`; `default_emitters=True` compiles it with those, as the row
    `DEFAULT_EMITTERS`). jaxps's rows over this kernel's, in the same run, say how far the
    library's core is from the limit of XLA on the machine (issue 18's title), apart from
    numpy's speed on it."""
    lt = np.asarray(lights, np.float64)
    lt = lt / np.linalg.norm(lt, axis=1, keepdims=True)
    k = len(lt)
    ks = range(k)
    pinv = np.linalg.pinv(lt)

    def normalised(b, scale=None):
        sq = b[0] * b[0] + b[1] * b[1] + b[2] * b[2]
        inv = jax.lax.rsqrt(jnp.where(sq > 0, sq, 1))
        rho = sq * inv if scale is None else sq * inv * scale
        return jnp.stack([v * inv for v in b], -1), rho

    if default_emitters:
        into = functools.partial(jax.jit, donate_argnums=0, keep_unused=True)
    else:
        into = functools.partial(CpuTuned, options=OLDER_EMITTERS, donate_argnums=0,
                                 keep_unused=True)

    @into
    def clean(out, x):
        return normalised([sum(float(pinv[p, j]) * x[j] for j in ks) for p in range(3)])

    @into
    def weighted(out, x, t):
        w = [(x[j] >= t).astype(x.dtype) for j in ks]
        a = [[sum(w[j] * float(lt[j, p] * lt[j, q]) for j in ks) for q in range(3)]
             for p in range(3)]
        r = [sum(w[j] * x[j] * float(lt[j, p]) for j in ks) for p in range(3)]
        c = [[a[(p + 1) % 3][(q + 1) % 3] * a[(p + 2) % 3][(q + 2) % 3]
              - a[(p + 1) % 3][(q + 2) % 3] * a[(p + 2) % 3][(q + 1) % 3] for q in range(3)]
             for p in range(3)]  # cofactors of the symmetric A: adj(A) = C
        det = a[0][0] * c[0][0] + a[0][1] * c[0][1] + a[0][2] * c[0][2]
        b = [c[p][0] * r[0] + c[p][1] * r[1] + c[p][2] * r[2] for p in range(3)]
        return normalised(b, 1 / jnp.abs(jnp.where(det != 0, det, 1)))

    last = {}

    def call(x):
        h, w = x.shape[1:]
        out = last.pop((h, w), None)
        if out is None:
            out = (jnp.zeros((h, w, 3), x.dtype), jnp.zeros((h, w), x.dtype))
        res = clean(out, x) if shadow is None else weighted(out, x, jnp.float32(shadow))
        last[h, w] = res
        return res

    return call


def fft_fc(p, q, fft=np.fft, **workers):
    """Baseline Frankot–Chellappa with the real FFTs of `fft` (numpy.fft, or scipy.fft with
    `workers=2`) on the given gradients."""
    h, w = p.shape
    wc = 2 * np.pi * np.fft.rfftfreq(w)[None, :]
    wr = 2 * np.pi * np.fft.fftfreq(h)[:, None]
    denom = wc**2 + wr**2
    denom[0, 0] = 1
    z_hat = -1j * (wc * fft.rfft2(p, **workers) + wr * fft.rfft2(-q, **workers)) / denom
    z_hat[0, 0] = 0
    return fft.irfft2(z_hat, s=(h, w), **workers)


def scipy_fc(p, q):
    """Baseline Frankot–Chellappa with scipy.fft (2 workers) on float32 gradients."""
    return fft_fc(p, q, scipy.fft, workers=2)


def scipy_dct_poisson(gc, gr):
    """Baseline Neumann Poisson solve with scipy.fft.dctn (2 workers)."""
    h, w = gc.shape
    gh = (gc[:, 1:] + gc[:, :-1]) / 2
    gv = (gr[1:] + gr[:-1]) / 2
    rhs = np.zeros((h, w), gc.dtype)
    rhs[:, 1:] += gh
    rhs[:, :-1] -= gh
    rhs[1:] += gv
    rhs[:-1] -= gv
    lam = (4 * np.sin(np.pi * np.arange(h)[:, None] / (2 * h)) ** 2
           + 4 * np.sin(np.pi * np.arange(w)[None, :] / (2 * w)) ** 2).astype(gc.dtype)
    lam[0, 0] = 1
    c = scipy.fft.dctn(rhs, type=2, norm="ortho", workers=2) / lam
    c[0, 0] = 0
    return scipy.fft.idctn(c, type=2, norm="ortho", workers=2)


BARE = "bare XLA kernel: normals + albedo only"
DEFAULT_EMITTERS = "the same kernel with XLA-CPU's default emitters"


def _difference(a, b, where=None):
    """Largest absolute difference of two normal maps (over `where`, an `(H, W)` bool)."""
    d = np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))
    return float((d if where is None else d[where]).max())


def row(rows, work, impl, run, baseline=None, **extra):
    r = {"work": work, "impl": impl, "run_s": run, **extra}
    if baseline is not None:
        r["baseline_s"] = baseline
        r["ratio"] = run / baseline
    rows.append(r)
    return r


def together(cases, repeats):
    """`_common.interleaved` over `repeats` rounds: `{name: (first-call s minus the median,
    median s, median minor page faults of a call)}`, so that a slow spell of the machine
    falls on a row and its baseline alike. The page faults say which calls wrote to memory
    that glibc had just mapped afresh (docs/speed.md, "Why the time per pixel grows"): at
    1 MP, whether it does differs from one process to another."""
    faults = {}
    first, seconds = interleaved(cases, repeats, faults)
    med = {name: statistics.median(s) for name, s in seconds.items()}
    return {name: (first[name] - med[name], med[name], statistics.median(faults[name]))
            for name in cases}


def core_rows(repeats, h, w):
    """The 1 MP rows. Each row is timed in the same interleaved rounds as its baseline (and,
    for L2, the bare kernel), the median of `repeats` calls."""
    rows = []
    surface = jaxps.synthetic.face_like(h, w)
    for k in (4, 5, 12):
        lights = jaxps.synthetic.scanner_lights(20.0, k=k) if k < 12 else ring_lights(k)
        scene = jaxps.synthetic.render_scene(surface, lights)
        images = jax.device_put(scene.images)
        images_np = np.asarray(scene.images)
        pinv = np.linalg.pinv(lights).astype(np.float32)
        mask = np.asarray(scene.mask)
        bare, bare_default = bare_l2(lights), bare_l2(lights, default_emitters=True)
        cases = {"numpy": lambda: numpy_ps(images_np, pinv), "bare": lambda: bare(images),
                 "bare_default": lambda: bare_default(images),
                 "jaxps": lambda: jaxps.photometric_stereo(images, lights)}
        if k == 12:
            # A shadow threshold at the 5th percentile of the samples in the mask.
            inside = images_np[:, mask]
            threshold = float(np.percentile(inside, 5))
            bare_dropping = bare_l2(lights, threshold)
            cases["bare_dropped"] = lambda: bare_dropping(images)
            cases["jaxps_dropped"] = lambda: jaxps.photometric_stereo(
                images, lights, mask=mask, shadow_threshold=threshold)
        t = together(cases, repeats)
        base = t["numpy"][1]
        row(rows, "ps_l2", "numpy pinv-matmul+normalise", base, K=k, page_faults=t["numpy"][2])
        row(rows, "ps_l2", BARE, t["bare"][1], base, K=k, page_faults=t["bare"][2],
            max_normal_difference=_difference(bare(images)[0], numpy_ps(images_np, pinv)[0]))
        row(rows, "ps_l2", DEFAULT_EMITTERS, t["bare_default"][1], base, K=k,
            page_faults=t["bare_default"][2],
            over_bare_kernel=t["bare_default"][1] / t["bare"][1])
        row(rows, "ps_l2", "jaxps", t["jaxps"][1], base, K=k, compile_s=t["jaxps"][0],
            page_faults=t["jaxps"][2],
            over_bare_kernel=t["jaxps"][1] / t["bare"][1])
        if k == 12:
            ours = jaxps.photometric_stereo(images, lights, mask=mask, shadow_threshold=threshold)
            ok = np.asarray(ours.status) == 0
            row(rows, "ps_l2_dropped", BARE, t["bare_dropped"][1], base, K=k,
                page_faults=t["bare_dropped"][2],
                max_normal_difference=_difference(bare_dropping(images)[0], ours.normals, ok))
            row(rows, "ps_l2_dropped", "jaxps", t["jaxps_dropped"][1], base, K=k,
                compile_s=t["jaxps_dropped"][0], page_faults=t["jaxps_dropped"][2],
                over_bare_kernel=t["jaxps_dropped"][1] / t["bare_dropped"][1],
                dropped_fraction=float(np.mean(inside < threshold)),
                pixels_dropping=float(np.mean((inside < threshold).any(0))))
        if k != 5:
            continue
        normals = jax.block_until_ready(jaxps.photometric_stereo(images, lights).normals)
        p, q = (np.asarray(a) for a in jaxps.gradients_from_normals(
            normals, jnp.ones((h, w), bool)))
        gc, gr = p, -q
        gcj, grj = jnp.asarray(gc), jnp.asarray(gr)
        t = together({
            "scipy_fc": lambda: scipy_fc(p, q), "numpy_fc": lambda: fft_fc(p, q),
            "fc": lambda: jaxps.integrate(normals),
            "scipy_dct": lambda: scipy_dct_poisson(gc, gr),
            "dct": lambda: jaxps.integrate(normals, method="dct"),
            # the solve alone, from the same height steps as scipy's (no normals, no mean)
            "dct_solve": lambda: dct_poisson(gcj, grj),
            "numpy_scipy": lambda: scipy_fc(*_pq(numpy_ps(images_np, pinv)[0])),
            "ps_fc": lambda: jaxps.integrate(jaxps.photometric_stereo(images, lights).normals),
        }, repeats)
        row(rows, "fc", "scipy rfft2 float32, 2 workers", t["scipy_fc"][1],
            page_faults=t["scipy_fc"][2])
        row(rows, "fc", "numpy rfft2 (float64)", t["numpy_fc"][1], t["scipy_fc"][1],
            page_faults=t["numpy_fc"][2])
        row(rows, "fc", "jaxps", t["fc"][1], t["scipy_fc"][1], compile_s=t["fc"][0],
            page_faults=t["fc"][2])
        row(rows, "dct", "scipy dctn float32, 2 workers", t["scipy_dct"][1],
            page_faults=t["scipy_dct"][2])
        row(rows, "dct", "jaxps", t["dct"][1], t["scipy_dct"][1], compile_s=t["dct"][0],
            page_faults=t["dct"][2])
        row(rows, "dct_solve", "jaxps dct_poisson", t["dct_solve"][1], t["scipy_dct"][1],
            compile_s=t["dct_solve"][0], page_faults=t["dct_solve"][2])
        row(rows, "ps_l2+fc", "numpy PS + scipy FC", t["numpy_scipy"][1], K=k,
            page_faults=t["numpy_scipy"][2])
        row(rows, "ps_l2+fc", "jaxps", t["ps_fc"][1], t["numpy_scipy"][1], K=k,
            compile_s=t["ps_fc"][0], page_faults=t["ps_fc"][2])
    return rows


def _pq(n):
    nz = np.maximum(n[..., 2], 0.05)
    return -n[..., 0] / nz, -n[..., 1] / nz


def scaling_rows(rounds, sizes):
    """Time per pixel for PS (K=5) and FC at each (rows, columns), with numpy's PS and scipy's
    FC beside them as the same work's baselines, and PS's `bare_l2` kernel.

    The sizes take turns over `rounds` rounds, so that the machine's slow spells fall on all
    of them alike. In each round, each size runs each method as a block of about as many
    calls as fit the time of one call at the largest size (at least one), so that every size
    gets about as many seconds of samples and a block keeps the cache as repeated calls of a
    caller would. Each figure is the median call. The page faults are those of one more call.
    """
    lights = jaxps.synthetic.scanner_lights(20.0)
    pinv = np.linalg.pinv(np.asarray(lights, np.float32)).astype(np.float32)
    bare = bare_l2(lights)
    cases, calls = {}, {}
    for h, w in sizes:
        scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(h, w), lights)
        images_np = np.asarray(scene.images, np.float32)
        images = jax.device_put(images_np)
        normals = jax.block_until_ready(jaxps.photometric_stereo(images, lights).normals)
        p, q = (a.astype(np.float32) for a in _pq(np.asarray(normals)))
        cases[h, w] = {
            "ps_l2": lambda images=images: jaxps.photometric_stereo(images, lights),
            "fc": lambda normals=normals: jaxps.integrate(normals),
            "numpy_ps": lambda images_np=images_np: numpy_ps(images_np, pinv),
            "bare_ps": lambda images=images: bare(images),
            "scipy_fc": lambda p=p, q=q: scipy_fc(p, q)}
        calls[h, w] = max(1, round(sizes[-1][0] * sizes[-1][1] / (h * w)))
        for fn in cases[h, w].values():  # compile and warm up
            block(fn())
    times = {(size, name): [] for size in cases for name in cases[size]}
    for _ in range(rounds):
        for size, fns in cases.items():
            for name, fn in fns.items():
                for _ in range(calls[size]):
                    t0 = time.perf_counter()
                    block(fn())
                    times[size, name].append(time.perf_counter() - t0)
    rows = []
    for (h, w), fns in cases.items():
        mp = h * w / 1e6
        med = {name: statistics.median(times[(h, w), name]) for name in fns}
        rows.append({
            "rows": h, "columns": w, "megapixels": mp, "calls": rounds * calls[h, w],
            "ps_l2_s": med["ps_l2"], "fc_s": med["fc"],
            **{f"{name}_ns_per_px": 1e3 * t / mp for name, t in med.items()},
            "ps_l2_page_faults_per_kpx": page_faults(fns["ps_l2"]) / (1e3 * mp),
            "fc_page_faults_per_kpx": page_faults(fns["fc"]) / (1e3 * mp)})
    return rows


def peak_rss(h, w):
    """In this (fresh) process: render, solve and integrate one five-frame capture; print the
    peak resident memory in GB (the rendering included)."""
    lights = jaxps.synthetic.scanner_lights(20.0)
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(h, w), lights)
    res = jaxps.photometric_stereo(scene.images, lights, mask=scene.mask)
    height = jax.block_until_ready(jaxps.integrate(res.normals))
    print(json.dumps({"rows": h, "columns": w, "peak_rss_gb":
                      resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
                      "height_finite": bool(np.isfinite(np.asarray(height)).all())}))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--quick", action="store_true",
                    default=os.environ.get("JAXPS_BENCH_QUICK") == "1")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                  "core.json"))
    ap.add_argument("--peak-rss", nargs=2, type=int, metavar=("ROWS", "COLUMNS"),
                    help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.peak_rss:
        return peak_rss(*args.peak_rss)

    h, w = (256, 320) if args.quick else (H, W)
    repeats = 3 if args.quick else args.repeats
    sizes = ([(256, 320), (512, 640)] if args.quick else
             [(512, 512), (1024, 1024), (2048, 2048), (4096, 4096)])
    results = {"shape": [h, w], "repeats": repeats, "quick": args.quick,
               "rows": core_rows(repeats, h, w),
               "scaling": scaling_rows(max(2, repeats // 4), sizes)}
    big = sizes[-1]
    out = subprocess.run([sys.executable, __file__, "--peak-rss", *map(str, big)],
                         capture_output=True, text=True, check=True)
    results["peak_memory"] = json.loads(out.stdout.strip().splitlines()[-1])
    results["env"] = environment()
    results["env"]["OPENBLAS_NUM_THREADS"] = os.environ.get("OPENBLAS_NUM_THREADS")
    results["env"]["XLA_FLAGS"] = os.environ.get("XLA_FLAGS")
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=2)
    for r in results["rows"]:
        ratio = f"  {r['ratio']:5.2f}x baseline" if "ratio" in r else ""
        comp = f"  (compile {r['compile_s']:.2f} s)" if "compile_s" in r else ""
        print(f"{r['work']:>14} K={r.get('K', '-'):>2} {r['impl']:<41} "
              f"{1e3 * r['run_s']:8.2f} ms{ratio}{comp}  {r.get('page_faults', 0):6.0f} faults")
    for r in results["scaling"]:
        print(f"{r['rows']:>5}x{r['columns']:<5} PS {r['ps_l2_ns_per_px']:6.2f} ns/px "
              f"({r['ps_l2_page_faults_per_kpx']:.2f} page faults per 1000 px; numpy "
              f"{r['numpy_ps_ns_per_px']:.2f}, bare kernel {r['bare_ps_ns_per_px']:.2f}), "
              f"FC {r['fc_ns_per_px']:6.2f} ns/px "
              f"({r['fc_page_faults_per_kpx']:.2f}; scipy {r['scipy_fc_ns_per_px']:.2f})")
    print("peak memory:", results["peak_memory"])
    _chart(results, args.out.replace(".json", ".png"))


def _chart(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in results["rows"] if "ratio" in r]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 0.45 * len(rows) + 1.5),
                                 constrained_layout=True)
    labels = [f"{r['work']} K={r.get('K', '-')}\n{r['impl']}" for r in rows]
    ax.barh(range(len(rows)), [r["ratio"] for r in rows],
            color=["tab:blue" if r["impl"].startswith("jaxps") else
                   "tab:green" if r["impl"] == BARE else "tab:gray" for r in rows])
    ax.axvline(1, color="k", lw=0.8)
    ax.set_yticks(range(len(rows)), labels, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("time / numpy-scipy baseline in the same run (below 1: faster)")
    ax.set_title(f"{results['shape'][1]}x{results['shape'][0]}, after compile")
    sc = results["scaling"]
    mp = [r["megapixels"] for r in sc]
    bx.plot(mp, [r["ps_l2_ns_per_px"] for r in sc], "o-", color="tab:blue", label="PS L2, K=5")
    bx.plot(mp, [r["fc_ns_per_px"] for r in sc], "s-", color="tab:orange",
            label="Frankot–Chellappa")
    bx.plot(mp, [r["numpy_ps_ns_per_px"] for r in sc], "o--", color="tab:blue", alpha=0.5,
            label="numpy PS")
    bx.plot(mp, [r["scipy_fc_ns_per_px"] for r in sc], "s--", color="tab:orange", alpha=0.5,
            label="scipy FC")
    if "bare_ps_ns_per_px" in sc[0]:
        bx.plot(mp, [r["bare_ps_ns_per_px"] for r in sc], "o:", color="tab:green",
                label="bare XLA kernel (normals + albedo)")
    bx.set_xscale("log")
    bx.set_xlabel("megapixels")
    bx.set_ylabel("ns per pixel")
    bx.set_ylim(0, None)
    bx.legend()
    bx.set_title(f"time per pixel; {results['peak_memory']['rows']}x"
                 f"{results['peak_memory']['columns']} capture: "
                 f"{results['peak_memory']['peak_rss_gb']:.2f} GB peak RSS")
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
