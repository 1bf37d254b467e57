"""Robust calibrated photometric stereo: per-pixel solvers that survive shadows and highlights.

Plain least squares (`method="l2"`, Woodham 1980) lets one cast-shadowed or specular sample pull
the normal of a pixel by tens of degrees. The solvers here treat such samples as outliers of
Lambert's law $i_k = l_k^T b$ ($b = \\rho n$). Each is jitted and written for one pixel whose K
samples are K scalars: on the image they are K planes of pixels (the reweighting loops lifted
by `jax.vmap`), not a `(K,)` vector per pixel, so that every step is elementwise work that
XLA-CPU fuses and vectorises (at 1 MP: `barsky` 1.8 -> 0.17 s, `irls` 1.1 -> 0.26 s, `sbl`
6.1 -> 1.2 s; docs/robust.md, "How the solvers are built"). The iterative ones run a
`lax.while_loop` with an explicit step limit and report `Status.NOT_CONVERGED` when they hit
it.

- `"barsky"`: shadow/highlight rejection in the spirit of Barsky & Petrou, "The 4-source
  photometric stereo technique for three-dimensional surfaces in the presence of highlights and
  shadows", IEEE TPAMI 25(10), 2003. Among the subsets that drop up to `max_drop` of the darkest
  and brightest samples, pick the one minimising (relative RMS residual) + `threshold` x (number
  dropped) -- a tiny L0 search. A dropped dark sample must be darker than the fit predicts (a
  shadow) and a dropped bright one brighter (a highlight); with 4 lights, where every 3-subset
  fits exactly, this sign test (then a preference for shadows) decides.
- `"irls"`: iteratively reweighted least squares for the L1 residual (`loss="l1"`, weights
  $1/\\max(|r_k|, \\epsilon)$ -- the algorithm of RobustPhotometricStereo's `L1_residual_min`,
  Ikehata et al., "Robust photometric stereo using sparse regression", CVPR 2012) or the Huber
  loss (`loss="huber"`, weights $\\min(1, \\delta/|r_k|)$).
- `"sbl"`: sparse Bayesian learning of the outlier vector (Ikehata et al. 2012, the $\\ell_0$
  surrogate; Wipf & Rao 2004): alternate the weighted solve with $W = \\mathrm{diag}(1/\\gamma)$
  and the update $\\gamma_k = r_k^2 + [\\Sigma_e]_{kk}$, as in RobustPhotometricStereo's
  `sparse_bayesian_learning`.

Colour stacks: the weights and the normal come from the channel-mean (grey) intensities, the
albedo per channel from the final weighted solve, exactly as in `method="l2"`. For every method
`n_used` counts the inliers of the final fit ($|r_k| \\le$ `threshold` x mean used intensity) and
`residual` is their RMS; `info["steps"]` holds per-pixel step counts of the iterative methods.
"""

from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np

from ..core._fusion import computed_once
from ..core._linalg import REL_DET_MIN, normal_equations, solve3
from ..core._safe import safe_divide, safe_sqrt
from ..core._status import Status
from ._l2 import PSResult, _count

__all__ = ["ps_barsky", "ps_irls", "ps_sbl"]

# Pixels per lax.map chunk of the iterative solvers. A chunk runs until its slowest pixel
# converges; small chunks waste fewer steps, but XLA-CPU splits larger loop bodies across
# threads at a cost. At 1280x1024 (`benchmarks/robust_speed_ab.py --chunk N`, same results
# for every N): irls 0.24 s at 64, 0.20-0.21 s at 128, 0.25 s at 192, 0.49 s at 256, 0.23-0.24
# s at 8192; sbl 0.66 / 0.59 / 1.04 / 1.93 / 1.09-1.14 s. At 192x168 128 and 8192 tie for irls,
# and sbl takes 25 against 35 ms.
_CHUNK = 128

# Pixels per block of a whole solve: its flags, search or loops, final weighted solve and
# outputs run on one block (a `lax.map` step) at a time. On the whole image at once, XLA-CPU
# wrote each of the final solve's intermediates to memory in its own pass over the image; on
# a block they stay in cache (`benchmarks/robust_speed_ab.py --block N`, docs/robust.md,
# "Solved in blocks").
_BLOCK = 32768


# ----------------------------------------------------------------------------------------------
# Barsky & Petrou 2003: drop the darkest / brightest samples when the residual says so.


def _drop_patterns(k: int, max_drop: int) -> tuple[np.ndarray, np.ndarray]:
    """Static candidate list: counts `(n_dark, n_bright)` to drop, ordered fewest drops first."""
    pats = [(d, b) for d, b in itertools.product(range(max_drop + 1), repeat=2)
            if d + b <= max_drop and d + b <= k - 3]
    pats.sort(key=lambda p: (p[0] + p[1], -p[0]))  # fewest drops, shadows before highlights
    arr = np.array(pats, dtype=np.int32)
    return arr[:, 0], arr[:, 1]


def _ranks(keys):
    """Each key's rank in ascending order, ties by index (`argsort(argsort(keys))` of a stable
    sort), from K scalars by pairwise comparison: elementwise work under `vmap`."""
    ks = range(len(keys))
    return [sum(((keys[i] < keys[j]) | ((keys[i] == keys[j]) & (i < j))).astype(jnp.int32)
                for i in ks if i != j) for j in ks]


def _barsky_planes(grey, used, lt, threshold, max_drop):
    """Barsky's subset search on planes (`grey`, `used`, `lt` as `_blockwise`'s kernels take
    them): for each candidate (`_drop_patterns`, fewest drops first) the fit without the `nd`
    darkest and `nb` brightest used samples, its score and its sign test; the first best
    candidate's kept samples (all used ones when no candidate is acceptable). Returns K keep
    flags."""
    ks = range(len(grey))
    dtype = grey[0].dtype
    inf = jnp.asarray(jnp.inf, dtype)
    count = sum(u.astype(dtype) for u in used)
    scale = jnp.maximum(sum(jnp.where(u, g, 0) for u, g in zip(used, grey))
                        / jnp.maximum(count, 1), jnp.finfo(dtype).tiny)
    rank_dark = _ranks([jnp.where(u, g, inf) for u, g in zip(used, grey)])
    rank_bright = _ranks([jnp.where(u, -g, inf) for u, g in zip(used, grey)])
    slack = threshold * scale
    best_score, best_keep = None, used
    for nd, nb in zip(*(a.tolist() for a in _drop_patterns(len(grey), max_drop))):
        drop_d = [u & (r < nd) for u, r in zip(used, rank_dark)]
        drop_b = [u & (r < nb) & ~d for u, r, d in zip(used, rank_bright, drop_d)]
        keep = [u & ~d & ~b for u, d, b in zip(used, drop_d, drop_b)]
        n_keep = _count(keep)
        w = [k.astype(dtype) for k in keep]
        a, (r,) = normal_equations(w, lt, [grey])
        b, rel_det = solve3(a, r)
        pred = [sum(lt[j][p] * b[p] for p in range(3)) for j in ks]
        sq = sum(jnp.where(keep[j], (grey[j] - pred[j]) ** 2, 0) for j in ks)
        rms = safe_sqrt(sq / jnp.maximum(n_keep, 1).astype(dtype)) / scale
        # A dropped dark sample must be a shadow (darker than predicted), a bright one a
        # highlight. (Lambert's clamp: a dark sample at 0 under a light behind the surface is
        # no shadow.)
        consistent = functools.reduce(jnp.logical_and, [
            (~drop_d[j] | (grey[j] <= jnp.maximum(pred[j], 0) + slack))
            & (~drop_b[j] | (grey[j] >= pred[j] - slack)) for j in ks])
        ok = (n_keep >= 3) & (rel_det >= REL_DET_MIN) & consistent & (b[2] > 0)
        score = jnp.where(ok, rms + threshold * (nd + nb), inf)
        if best_score is None:
            best_score, best_keep = score, keep
        else:  # strictly better only: the first of equal scores wins (fewest drops, shadows)
            better = score < best_score
            best_score = jnp.where(better, score, best_score)
            best_keep = [jnp.where(better, k, bk) for k, bk in zip(keep, best_keep)]
    found = jnp.isfinite(best_score)
    return [jnp.where(found, k, u) for k, u in zip(best_keep, used)]


# ----------------------------------------------------------------------------------------------
# Iteratively reweighted least squares (L1 as in Ikehata et al. 2012's L1 solver, or Huber).


def _irls_loop(g, used, lt, *, loss, delta, eps, rtol, max_steps):
    """The reweighting loop of one pixel, on scalars: `g` K grey samples, `used` K flags, `lt`
    K lights `[lx, ly, lz]`. Starts from the least-squares solution; each step solves the 3x3
    weighted normal equations by cofactors. Returns the final weights (K), the steps taken and
    whether it converged.

    Written on K scalars rather than `(K,)` vectors: lifted by `vmap`, each is a plane of
    pixels and every step is elementwise work that XLA-CPU fuses and vectorises, where the
    sums over a `(pixels, K)` block were slow (`benchmarks/bench_robust.py`, docs/robust.md).
    """
    ks = range(len(g))
    dtype = g[0].dtype
    count = sum(u.astype(dtype) for u in used)
    mean_used = sum(jnp.where(u, v, 0) for u, v in zip(used, g)) / jnp.maximum(count, 1)
    scale = jnp.maximum(mean_used, jnp.finfo(dtype).tiny)
    floor = eps * scale

    def solve(w):
        a, (r,) = normal_equations(w, lt, [g])
        b, rel_det = solve3(a, r)
        return [b[0], b[1], b[2]], rel_det

    def weights(b):
        r = [jnp.abs(g[j] - sum(lt[j][p] * b[p] for p in range(3))) for j in ks]
        if loss == "l1":
            w = [1 / jnp.maximum(rj, floor) for rj in r]
        else:
            w = [jnp.minimum(1, delta * scale / jnp.maximum(rj, floor)) for rj in r]
        return [jnp.where(u, wj, 0) for u, wj in zip(used, w)]

    def cond(state):
        _, step, done = state
        return (step < max_steps) & ~done

    def body(state):
        b, step, _ = state
        b_new, rel_det = solve(weights(b))
        ok = jnp.isfinite(b_new[0]) & jnp.isfinite(b_new[1]) & jnp.isfinite(b_new[2])
        b_new = [jnp.where(ok & (rel_det > 0), v, u) for v, u in zip(b_new, b)]
        # |db| <= rtol max(|b|, s), squared: no square roots in the loop
        moved = sum((v - u) ** 2 for v, u in zip(b_new, b))
        size = jnp.maximum(sum(v * v for v in b_new), scale * scale)
        return b_new, step + 1, moved <= rtol * rtol * size

    b0, _ = solve([u.astype(dtype) for u in used])
    b, steps, done = jax.lax.while_loop(cond, body, (b0, jnp.array(0, jnp.int32),
                                                     jnp.array(False)))
    return weights(b), steps, done


# ----------------------------------------------------------------------------------------------
# Shared by the solvers: the image as planes, chunked loops, the final weighted solve.


def _samples(x, usable, thresholds):
    """One pixel's samples sorted as `method="l2"` sorts them (on scalars or planes): `x` K
    lists of C samples, `usable` K flags (in `sample_mask` and `mask`). Returns `x` with
    non-finite samples zeroed, the K grey samples and the K finite / unsaturated / used flags
    (used: also not below the shadow threshold)."""
    _, saturation, shadow = thresholds
    xs, grey, finite, unsat, used = [], [], [], [], []
    for ch, u in zip(x, usable):
        ok = functools.reduce(jnp.logical_and, [jnp.isfinite(v) for v in ch])
        ch = [jnp.where(ok, v, 0) for v in ch]
        g = sum(ch) / len(ch)
        lit = ok & ~functools.reduce(jnp.logical_or, [v >= saturation for v in ch]) & u
        xs.append(ch)
        grey.append(g)
        finite.append(ok)
        unsat.append(lit)
        used.append(lit & (g >= shadow))
    return xs, grey, finite, unsat, used


def _in_chunks(fn, planes, n, size):
    """`fn` on `(n,)` planes (a pytree of them) in `lax.map` steps of `size` pixels (the last
    padded); its outputs, each `(size, ...)`, joined into `(n, ...)`."""
    if n <= size:
        return fn(planes)
    n_chunks = -(-n // size)
    pad = n_chunks * size - n
    chunks = jax.tree.map(lambda a: jnp.pad(a, (0, pad)).reshape(n_chunks, size), planes)
    outs = jax.lax.map(fn, chunks)
    return jax.tree.map(lambda a: a.reshape(n_chunks * size, *a.shape[2:])[:n], outs)


def _map_chunks(fn, planes, n):
    """`fn` (a kernel on scalars, lifted by `vmap`) over `(n,)` planes in `lax.map` chunks of
    `_CHUNK` pixels: a vmapped `while_loop` runs every lane until the slowest converges, so one
    slow pixel holds back only its own chunk."""
    return _in_chunks(jax.vmap(fn), planes, n, _CHUNK)


def _blockwise(kernel, images, lights, mask, sample_mask, thresholds):
    """A robust solve of every pixel, in blocks of `_BLOCK` pixels (`_in_chunks`).

    `kernel(x, grey, finite, unsat, used, lt)` solves one block, given as `(P,)` planes:
    the samples and flags of `_samples` and K unit lights `[lx, ly, lz]` (scalars for shared
    lights). It returns the normals `(P, 3)`, albedo `(P, C)`, status, inlier count,
    residual and per-pixel steps. Outside `mask`, and where the status is not OK, the outputs
    are the defaults; the status is `MASKED` outside `mask`. Returns a `PSResult` whose
    `info["steps"]` holds the steps.
    """
    k, h, w, c = images.shape
    dtype = images.dtype
    n = h * w
    flat = images.reshape(k, n, c)
    usable = (sample_mask & mask[None]).reshape(k, n)
    per_pixel = lights.ndim != 2
    if per_pixel:
        lights = lights.reshape(k, n, 3)
        lights = lights / jnp.maximum(jnp.linalg.norm(lights, axis=-1, keepdims=True),
                                      jnp.finfo(dtype).tiny)
    planes = ([[flat[j, :, q] for q in range(c)] for j in range(k)],
              [usable[j] for j in range(k)], mask.reshape(n),
              [[lights[j, :, p] for p in range(3)] for j in range(k)] if per_pixel else None)

    def block(planes):
        x, usable, inside, lt = planes
        if not per_pixel:
            lt = [[lights[j, p] for p in range(3)] for j in range(k)]
        normals, rho, status, n_in, residual, steps = kernel(*_samples(x, usable, thresholds),
                                                             lt)
        keep = inside & (status == Status.OK)
        return (jnp.where(keep[:, None], normals, jnp.array([0, 0, 1], dtype)),
                jnp.where(keep[:, None], rho, 0),
                jnp.where(inside, status, Status.MASKED).astype(jnp.int32),
                n_in.astype(jnp.int32), jnp.where(keep, residual, 0),
                jnp.where(inside, steps, 0).astype(jnp.int32))

    normals, albedo, status, n_used, residual, steps = _in_chunks(block, planes, n, _BLOCK)
    return PSResult(normals.reshape(h, w, 3), albedo.reshape(h, w, c), status.reshape(h, w),
                    n_used.reshape(h, w), residual.reshape(h, w),
                    {"steps": steps.reshape(h, w)})


def _finish_planes(x, grey, finite, unsat, used, w, lt, dark, outlier, converged):
    """The final weighted solve of every pixel, on planes (the arguments of `_blockwise`'s
    kernels, `w` K weight planes, held fixed: the gradient flows through this solve only):
    unit normal from the channel-mean solution, per-channel albedo, the inliers of the fit
    (within `outlier` x the mean used intensity), their RMS and the status. Returns normals
    `(P, 3)`, albedo `(P, C)`, status, number of inliers, residual."""
    ks = range(len(grey))
    dtype = grey[0].dtype
    w = [jnp.where(u & jnp.isfinite(v), v, 0) for u, v in zip(used, w)]
    top = functools.reduce(jnp.maximum, w)
    w = [v / jnp.where(top > 0, top, 1) for v in w]
    n_ch = len(x[0])
    a, r = normal_equations(w, lt, [[x[j][ch] for j in ks] for ch in range(n_ch)])
    # the channel-mean solution (the solve is linear in its right-hand side)
    b, rel_det_w = solve3(a, [sum(r[ch][p] for ch in range(n_ch)) / n_ch for p in range(3)])
    rho_grey = safe_sqrt(b[0] ** 2 + b[1] ** 2 + b[2] ** 2)
    n = [b[p] / jnp.where(rho_grey > 0, rho_grey, 1) for p in range(3)]
    nan_ = sum(n[p] * a[p][q] * n[q] for p in range(3) for q in range(3))
    rho = [safe_divide(sum(n[p] * r[ch][p] for p in range(3)), nan_) for ch in range(n_ch)]
    rho_mean = sum(rho) / n_ch
    res = [grey[j] - rho_mean * sum(lt[j][p] * n[p] for p in range(3)) for j in ks]
    count = _count(used)
    scale = sum(jnp.where(u, g, 0) for u, g in zip(used, grey)) / jnp.maximum(count, 1).astype(
        dtype)
    inlier = [u & (jnp.abs(e) <= outlier * scale) for u, e in zip(used, res)]
    n_in = _count(inlier)
    residual = safe_sqrt(sum(jnp.where(i, e**2, 0) for i, e in zip(inlier, res))
                         / jnp.maximum(n_in, 1).astype(dtype))
    # whether the usable lights span 3-D at all (unweighted), and whether the weighted fit does
    uw = [u.astype(dtype) for u in used]
    a_used = normal_equations(uw, lt, [])[0]
    _, rel_det_used = solve3(a_used, [jnp.zeros_like(grey[0])] * 3)
    brightest = functools.reduce(jnp.maximum, [jnp.where(f, g, -jnp.inf)
                                               for f, g in zip(finite, grey)])
    status = jnp.select(
        [
            _count(finite) < 3,
            brightest <= dark,
            _count(unsat) < 3,
            count < 3,
            (rel_det_used < REL_DET_MIN) | ~(rel_det_w > 0),
            ~(rho_grey > 0),
            n[2] < 0,
            ~converged,
        ],
        [Status.INVALID, Status.DARK, Status.SATURATED, Status.TOO_FEW_LIGHTS,
         Status.DEGENERATE, Status.DARK, Status.BACKFACING, Status.NOT_CONVERGED],
        Status.OK,
    )
    return jnp.stack(n, -1), jnp.stack(rho, -1), status, n_in, residual


# ----------------------------------------------------------------------------------------------
# Sparse Bayesian learning (Ikehata et al. 2012).


def _sbl_loop(g, used, lt, *, lambda1, lambda2, gamma_min, rtol, max_steps):
    """The SBL iterations of one pixel, on scalars (`g`, `used`, `lt` as in `_irls_loop`):
    alternate the weighted solve with $W = \\mathrm{diag}(1/\\gamma)$ and the update
    $\\gamma_k = r_k^2 + l_k^T (A + \\lambda_1 I)^{-1} l_k$, in units of the pixel's mean used
    intensity (so the priors do not depend on its brightness). Returns the final weights
    $1/\\gamma$ (K), the steps taken and whether it converged."""
    ks = range(len(g))
    dtype = g[0].dtype
    count = sum(u.astype(dtype) for u in used)
    mean_used = sum(jnp.where(u, v, 0) for u, v in zip(used, g)) / jnp.maximum(count, 1)
    scale = jnp.maximum(mean_used, jnp.finfo(dtype).tiny)
    y = [v / scale for v in g]
    uw = [u.astype(dtype) for u in used]

    def plus(a, lam):
        return [[a[p][q] + lam if p == q else a[p][q] for q in range(3)] for p in range(3)]

    def solve_b(gamma):
        a, (r,) = normal_equations([u / v for u, v in zip(uw, gamma)], lt, [y])
        b, _ = solve3(plus(a, lambda2), r)
        return [b[0], b[1], b[2]], a

    def cond(state):
        return (state[2] < max_steps) & ~state[3]

    def body(state):
        gamma, b_old, step, _ = state
        b, a = solve_b(gamma)
        m = plus(a, lambda1)
        gamma = []
        for j in ks:
            e = y[j] - sum(lt[j][p] * b[p] for p in range(3))
            xi, _ = solve3(m, lt[j])
            sigma = sum(lt[j][p] * xi[p] for p in range(3))
            gamma.append(jnp.where(used[j], jnp.maximum(e * e + sigma, gamma_min), 1))
        moved = jnp.sqrt(sum((v - u) ** 2 for v, u in zip(b, b_old)))
        size = jnp.sqrt(sum(v * v for v in b))
        return gamma, b, step + 1, moved <= rtol * jnp.maximum(size, 1)

    gamma0 = [jnp.ones_like(y[0]) for _ in ks]
    b_init = [jnp.full_like(y[0], jnp.inf) for _ in range(3)]
    gamma, _, steps, done = jax.lax.while_loop(
        cond, body, (gamma0, b_init, jnp.array(0, jnp.int32), jnp.array(False)))
    return [1 / v for v in gamma], steps, done


def _check_positive(**kw):
    for name, v in kw.items():
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a positive finite number, got {v}")


def ps_barsky(images, lights, mask, sample_mask, thresholds, *, threshold: float = 0.05,
              max_drop: int = 2) -> PSResult:
    """Shadow/highlight rejection (Barsky & Petrou 2003) over darkest/brightest subsets.

    **Arguments** (besides the solver arguments of `photometric_stereo`):
    - `threshold`: relative RMS residual (of the mean used intensity) worth one dropped sample;
      also the inlier bound for `n_used`. Roughly 3-5x the relative image noise.
    - `max_drop`: most samples dropped per pixel (never leaving fewer than 3).

    **Returns:** `PSResult`; `info["steps"]` is the number of samples dropped per pixel.
    """
    _check_positive(threshold=threshold)
    if int(max_drop) != max_drop or max_drop < 0:
        raise ValueError(f"max_drop must be a non-negative integer, got {max_drop}")
    return _ps_barsky(images, lights, mask, sample_mask, thresholds, threshold, int(max_drop))


@functools.partial(jax.jit, static_argnums=(6,))
def _ps_barsky(images, lights, mask, sample_mask, thresholds, threshold, max_drop):
    dt = images.dtype
    thr = jnp.asarray(threshold, dt)

    # The search picks samples; the gradient is that of the final solve on the kept ones.
    # It is computed once, as one plane (the kept samples as bits): left free, XLA-CPU ran
    # it again in the loop of each of the K keep planes (docs/robust.md).
    def search(grey, used, lt):
        keep = _barsky_planes(grey, used, lt, thr, max_drop)
        return sum(kj.astype(jnp.int32) << j for j, kj in enumerate(keep))

    def kernel(x, grey, finite, unsat, used, lt):
        bits = computed_once(search, *jax.lax.stop_gradient((grey, used, lt)),
                             key=thresholds[0])
        keep = [(bits >> j) & 1 == 1 for j in range(len(grey))]
        dropped = _count([u & ~k for u, k in zip(used, keep)])
        return *_finish_planes(x, grey, finite, unsat, keep, [k.astype(dt) for k in keep], lt,
                               thresholds[0], thr, jnp.array(True)), dropped

    return _blockwise(kernel, images, lights, mask, sample_mask, thresholds)


def ps_irls(images, lights, mask, sample_mask, thresholds, *, loss: str = "l1",
            delta: float = 0.05, eps: float = 1e-4, rtol: float = 1e-4, max_steps: int = 200,
            threshold: float = 0.05) -> PSResult:
    """Iteratively reweighted least squares for the L1 or Huber loss of the residual.

    Starts from the least-squares solution; each step solves the 3x3 weighted normal equations
    with weights $1/\\max(|r_k|, \\epsilon s)$ (L1) or $\\min(1, \\delta s / |r_k|)$ (Huber),
    $s$ the pixel's mean used intensity. Stops when $\\|\\Delta b\\| \\le$ `rtol` $\\|b\\|$.

    **Arguments** (besides the solver arguments of `photometric_stereo`):
    - `loss`: `"l1"` (Ikehata et al. 2012's L1 residual minimisation) or `"huber"`.
    - `delta`: Huber threshold, relative to the mean used intensity.
    - `eps`: floor of $|r_k|$ in the weights, relative to the mean used intensity.
    - `rtol`, `max_steps`: convergence tolerance and step limit (`NOT_CONVERGED` past it).
    - `threshold`: inlier bound for `n_used` / `residual`, relative to the mean intensity.

    **Returns:** `PSResult`; `info["steps"]` holds the steps taken per pixel.
    """
    if loss not in ("l1", "huber"):
        raise ValueError(f"loss must be 'l1' or 'huber', got {loss!r}")
    _check_positive(delta=delta, eps=eps, rtol=rtol, threshold=threshold)
    if int(max_steps) != max_steps or max_steps < 1:
        raise ValueError(f"max_steps must be a positive integer, got {max_steps}")
    return _ps_irls(images, lights, mask, sample_mask, thresholds, loss, delta, eps, rtol,
                    int(max_steps), threshold)


@functools.partial(jax.jit, static_argnums=(5, 9))
def _ps_irls(images, lights, mask, sample_mask, thresholds, loss, delta, eps, rtol, max_steps,
             threshold):
    dt = images.dtype
    loop = functools.partial(_irls_loop, loss=loss, delta=jnp.asarray(delta, dt),
                             eps=jnp.asarray(eps, dt), rtol=jnp.asarray(rtol, dt),
                             max_steps=max_steps)
    return _reweighted(loop, images, lights, mask, sample_mask, thresholds, threshold)


def _reweighted(loop, images, lights, mask, sample_mask, thresholds, threshold):
    """An iteratively reweighted solver: `loop(grey, used, lights)` (a kernel on one pixel's
    scalars, returning the final weights, steps and convergence) over every pixel in chunks,
    then the final weighted solve with those weights (`_finish_planes`), block by block."""
    threshold = jnp.asarray(threshold, images.dtype)

    def kernel(x, grey, finite, unsat, used, lt):
        # The loop runs on constants: reverse mode cannot differentiate a `while_loop`, and
        # the gradient is that of the final weighted solve, its weights held fixed.
        g_loop, lt_loop = jax.lax.stop_gradient((grey, lt))
        if lights.ndim == 2:  # the light scalars are closed over, not mapped
            weights, steps, done = _map_chunks(lambda p: loop(p[0], p[1], lt_loop),
                                               (g_loop, used), len(grey[0]))
        else:
            weights, steps, done = _map_chunks(lambda p: loop(*p), (g_loop, used, lt_loop),
                                               len(grey[0]))
        return *_finish_planes(x, grey, finite, unsat, used, weights, lt, thresholds[0],
                               threshold, done), steps

    return _blockwise(kernel, images, lights, mask, sample_mask, thresholds)


def ps_sbl(images, lights, mask, sample_mask, thresholds, *, lambda1: float = 100.0,
           lambda2: float = 1e-6, gamma_min: float = 1e-8, rtol: float = 1e-4,
           max_steps: int = 200, threshold: float = 0.05) -> PSResult:
    """Sparse Bayesian learning of sparse outliers (Ikehata et al. 2012).

    Intensities are divided by the pixel's mean used intensity $s$ first, so `lambda1`,
    `lambda2` (the priors of RobustPhotometricStereo's `sparse_bayesian_learning`) and
    `gamma_min` are brightness-free. RobustPhotometricStereo's `lambda1 = 1` on raw intensities
    equals `lambda1` $= 1/s^2$ here; the default 100 ($s$ = 0.1) was picked by hand on the
    benchmark scene (`benchmarks/bench_robust.py`; `lambda1 = 1` there was about L2's accuracy).
    It remains less accurate than RobustPhotometricStereo's SBL there (see docs/robust.md).

    **Arguments** (besides the solver arguments of `photometric_stereo`):
    - `lambda1`, `lambda2`: regularisers of the posterior covariance and of the solve.
    - `gamma_min`: floor of the per-sample variances $\\gamma_k$.
    - `rtol`, `max_steps`: convergence tolerance on $b$ and step limit (`NOT_CONVERGED`).
    - `threshold`: inlier bound for `n_used` / `residual`, relative to the mean intensity.

    **Returns:** `PSResult`; `info["steps"]` holds the steps taken per pixel.
    """
    _check_positive(lambda1=lambda1, lambda2=lambda2, gamma_min=gamma_min, rtol=rtol,
                    threshold=threshold)
    if int(max_steps) != max_steps or max_steps < 1:
        raise ValueError(f"max_steps must be a positive integer, got {max_steps}")
    return _ps_sbl(images, lights, mask, sample_mask, thresholds, lambda1, lambda2, gamma_min,
                   rtol, int(max_steps), threshold)


@functools.partial(jax.jit, static_argnums=(9,))
def _ps_sbl(images, lights, mask, sample_mask, thresholds, lambda1, lambda2, gamma_min, rtol,
            max_steps, threshold):
    dt = images.dtype
    loop = functools.partial(_sbl_loop, lambda1=jnp.asarray(lambda1, dt),
                             lambda2=jnp.asarray(lambda2, dt),
                             gamma_min=jnp.asarray(gamma_min, dt), rtol=jnp.asarray(rtol, dt),
                             max_steps=max_steps)
    return _reweighted(loop, images, lights, mask, sample_mask, thresholds, threshold)
