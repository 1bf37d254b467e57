"""Calibrated Lambertian photometric stereo: a one-pixel least-squares kernel lifted with vmap.

Woodham, "Photometric method for determining surface orientation from multiple images",
Optical Engineering 19(1), 1980. For a pixel with intensities $i \\in \\mathbb{R}^K$ under unit
lights $L \\in \\mathbb{R}^{K \\times 3}$, Lambert's law $i = L b$ with $b = \\rho n$ gives the
least-squares $b = (L^T W L)^{-1} L^T W i$ over the usable samples ($W$ a 0/1 diagonal); albedo
$\\rho = |b|$ and normal $n = b / |b|$. When every sample of a pixel is usable and the lights are
shared, $b = L^+ i$ with the pseudo-inverse $L^+$ computed once for the whole image.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..core._fusion import computed_once
from ..core._host import OLDER_EMITTERS, CpuTuned, cpu_top_level
from ..core._linalg import REL_DET_MIN, adjugate3, normal_equations, relative_det, solve3
from ..core._safe import safe_divide, safe_sqrt
from ..core._status import Status, first_status
from ..core._store import call as stored_call
from ..lights._directions import MAX_LIGHT_CONDITION

__all__ = ["SOLVES", "PSResult", "branch_of", "host_constants", "l2_batch_flags",
           "l2_batch_solve", "l2_branch", "l2_needs_weights", "ps_l2", "ps_l2_eager",
           "solve_index"]


# The solves a host-chosen `branch` names, in the order of `solve_index`.
SOLVES = ("all_used", "weighted_finite", "weighted")


class PSResult(NamedTuple):
    """Per-pixel photometric-stereo result.

    - `normals`: `(H, W, 3)` unit normals (camera frame, n_z >= 0 where `status == 0`).
    - `albedo`: `(H, W)` for grey stacks, `(H, W, C)` for colour stacks.
    - `status`: `(H, W)` int32 codes from `jaxps.Status` (0 = ok).
    - `n_used`: `(H, W)` int32 number of samples the solve used.
    - `residual`: `(H, W)` RMS of $i - \\rho\\, l \\cdot n$ over the used samples (grey mean for
      colour).
    - `info`: method-specific extras (e.g. step counts, per-frame light intensities), or None.
    """

    normals: Float[Array, "H W 3"]
    albedo: Float[Array, "H W *C"]
    status: Int[Array, "H W"]
    n_used: Int[Array, "H W"]
    residual: Float[Array, "H W"]
    info: dict | None = None


def working_dtype(dtype):
    """The dtype the solves compute in: float32 for narrower floats (float16, bfloat16, which
    the packed complex planes do not take and whose range a near lamp's distance exceeds),
    else `dtype` itself."""
    return jnp.dtype(jnp.float32) if jnp.finfo(dtype).bits < 32 else dtype


def _widened(images):
    """`images` in `working_dtype` (a no-op for float32 and float64)."""
    dtype = working_dtype(images.dtype)
    return images if images.dtype == dtype else images.astype(dtype)


def _any(xs):
    return functools.reduce(jnp.logical_or, xs)


def _grey(x):
    """Channel mean of one sample, `x` a list of C scalars (unrolled: no reduction op)."""
    return x[0] if len(x) == 1 else sum(x) / len(x)


def _count(flags):
    return sum(f.astype(jnp.int32) for f in flags)


def _samples(x, usable, thresholds, all_finite=False):
    """Sort one pixel's samples: `x` (K lists of C scalars) with non-finite ones zeroed, the
    grey values `g`, and the per-sample flags finite / unsaturated (and usable) / used (also
    above the shadow threshold). Also the status cases they decide, in `first_status` order.

    `all_finite`: the caller has checked that every sample is finite (`l2_branch`), so
    nothing is zeroed and `INVALID` cannot occur. XLA-CPU wrote each zeroed sample to memory
    as its own plane, read again by every output's pass. At 1 MP with 5% of the samples
    dropped the weighted solve took 21.6-25.9 against 50.8-53.2 ms at K=12 and 11.4-15.9
    against 24.9-26.6 ms at K=5, results bit-identical (`benchmarks/bench_l2_programs.py`,
    four runs)."""
    dark, saturation, shadow = thresholds
    ks = range(len(x))
    g = [_grey(xk) for xk in x]
    if all_finite:
        unsat = [usable[k] & ~_any([v >= saturation for v in x[k]]) for k in ks]
        used = [unsat[k] & (g[k] >= shadow) for k in ks]
        cases = [
            (functools.reduce(jnp.maximum, g) <= dark, Status.DARK),
            (_count(unsat) < 3, Status.SATURATED),
            (_count(used) < 3, Status.TOO_FEW_LIGHTS),
        ]
        return x, g, used, cases
    finite = [jnp.isfinite(v) for v in g]
    g = [jnp.where(finite[k], g[k], 0) for k in ks]
    x = [[jnp.where(finite[k], v, 0) for v in x[k]] for k in ks]
    unsat = [finite[k] & usable[k] & ~_any([v >= saturation for v in x[k]]) for k in ks]
    used = [unsat[k] & (g[k] >= shadow) for k in ks]
    brightest = functools.reduce(jnp.maximum, [jnp.where(finite[k], g[k], -jnp.inf) for k in ks])
    cases = [
        (_count(finite) < 3, Status.INVALID),
        (brightest <= dark, Status.DARK),
        (_count(unsat) < 3, Status.SATURATED),
        (_count(used) < 3, Status.TOO_FEW_LIGHTS),
    ]
    return x, g, used, cases


def _finish(solve, n_used, cases, inside, backfacing_from_b=False):
    """Normal, albedo, status, residual from `solve()`, which returns $b = \\rho n$, the squared
    misfit and the colour albedo's function of $n$ (None for grey).

    `solve` is called once for the status and once for each output. Where it computes from
    the samples (`_pixel_all_used`), XLA-CPU then computes $b$ again in each output's loop
    over the image. From one call, it wrote $|b|$, $1/|b|$ and $n_z$ to memory for the other
    loops to read back: 7 loop fusions at K=5 instead of 4, and slower
    (`benchmarks/bench_l2_passes.py`, `benchmarks/hlo_l2.py`; docs/speed.md).

    `backfacing_from_b`: test the sign of $b_z$ for `BACKFACING`, not of $n_z = b_z / |b|$
    (the same test but where $n_z$ underflows to -0). The weighted solve then needs no
    $1/|b|$ in its status pass, where XLA-CPU wrote $n_z$ to memory for it: 11 loop fusions
    instead of 13, and faster (`benchmarks/bench_l2_passes.py`). The every-sample-used solve
    keeps $n_z$: with $b_z$ XLA-CPU fused it into one more loop, not fewer.
    """

    def normal():
        b, sq, colour_albedo = solve()
        rho_grey = safe_sqrt(b[0] ** 2 + b[1] ** 2 + b[2] ** 2)
        inv_rho = 1 / jnp.where(rho_grey > 0, rho_grey, 1)
        return [v * inv_rho for v in b], rho_grey, sq, colour_albedo, b

    n, rho_grey, _, _, b = normal()
    status = first_status([
        (~inside, Status.MASKED),
        *cases,
        (~(rho_grey > 0), Status.DARK),
        ((b[2] if backfacing_from_b else n[2]) < 0, Status.BACKFACING),
    ])
    ok = status == Status.OK
    n = normal()[0]
    normal_out = (jnp.where(ok, n[0], 0), jnp.where(ok, n[1], 0), jnp.where(ok, n[2], 1))
    n, rho_grey, _, colour_albedo, _ = normal()
    rho = [rho_grey] if colour_albedo is None else colour_albedo(n)
    albedo = tuple(jnp.where(ok, v, 0) for v in rho)
    sq = solve()[1]
    residual = safe_sqrt(sq / jnp.maximum(n_used, 1).astype(sq.dtype))
    return normal_out, albedo, status, n_used, jnp.where(ok, residual, 0)


def _pixel_flags(x, usable, inside, thresholds):
    """The host's flags for one pixel (`x` and `usable` as in `_pixel_all_used`): an int32,
    0 outside the mask, with bit 0 set when `_pixel_all_used`'s assumption fails (a sample
    non-finite, saturated, shadowed or not usable), so that the pixel must be solved by
    `_pixel_weighted`, and bit 1 set when a sample is not finite (that solve must then zero
    it: `_samples`).

    A kernel of its own rather than an output of the solve: the flag programs then trace and
    lower only these tests, not the whole solve that XLA would discard.
    """
    _, saturation, shadow = thresholds
    g = [_grey(xk) for xk in x]
    finite = jnp.isfinite(sum(g))  # one test: a NaN or Inf in any sample makes the sum so
    clean = (finite
             & functools.reduce(jnp.logical_and, usable)
             & ~_any([v >= saturation for xk in x for v in xk])
             & ~_any([v < shadow for v in g]))
    flags = (~clean).astype(jnp.int32) | (~finite).astype(jnp.int32) << 1
    return jnp.where(inside, flags, 0)


def _pixel_all_used(x, usable, inside, shared, thresholds):
    """Solve one pixel assuming all K samples are usable (`_pixel_flags` says where they are
    not), with the shared `(3, K)` $L^+$.

    `x` is a list of K samples, each a list of C channel scalars; `usable` K bools; `shared`
    = (lights, pinv, null, gram, full_rank) computed once per image. The squared misfit is
    $\\|N i\\|^2$ with the rows of `null` spanning the complement of the light columns: exact,
    and cheaper than recomputing $i - L b$. Returns the outputs of `_finish`.
    """
    dark = thresholds[0]
    lights, pinv, null, gram, full_rank = shared
    ks = range(len(x))
    g = [_grey(xk) for xk in x]

    def solve():  # called per output by `_finish`: each output's loop solves b again
        gv = [_grey(xk) for xk in x]
        b = [sum(pinv[p, k] * gv[k] for k in ks) for p in range(3)]
        sq = sum((sum(null[j, k] * gv[k] for k in ks) ** 2 for j in range(null.shape[0])),
                 jnp.zeros((), gv[0].dtype))  # K = 3: no null space, zero misfit

        def colour_albedo(n):  # rho_c = n.(L^T i_c) / n.(L^T L) n: the channel's LS albedo
            nan = sum(n[p] * gram[p, q] * n[q] for p in range(3) for q in range(3))
            return [safe_divide(sum(n[p] * sum(lights[k, p] * x[k][c] for k in ks)
                                     for p in range(3)), nan) for c in range(len(x[0]))]

        return b, sq, None if len(x[0]) == 1 else colour_albedo

    brightest = functools.reduce(jnp.maximum, g)
    cases = [(brightest <= dark, Status.DARK), (~full_rank, Status.DEGENERATE)]
    return _finish(solve, jnp.int32(len(x)), cases, inside)


def _weighted_system(x, usable, lights, thresholds, all_finite):
    """One pixel's weighted normal equations (arguments as `_pixel_weighted` takes them): the
    grey samples `g`, the 0/1 weights `w`, the status cases in `first_status` order, the
    number of samples used, $A = L^T W L$, $r = L^T W g$ and each colour channel's
    $L^T W i_c$."""
    dtype = x[0][0].dtype
    x, g, used, cases = _samples(x, usable, thresholds, all_finite)
    w = [u.astype(dtype) for u in used]
    channels = [] if len(x[0]) == 1 else [[xk[c] for xk in x] for c in range(len(x[0]))]
    a, (r, *r_channels) = normal_equations(w, lights, [g, *channels])
    return g, w, cases, _count(used), a, r, r_channels


def _misfit(g, w, lights, b):
    """$\\sum_k w_k (g_k - l_k \\cdot b)^2$."""
    return sum(wk * (gk - sum(lk[p] * b[p] for p in range(3))) ** 2
               for gk, wk, lk in zip(g, w, lights))


def _pixel_weighted(x, usable, inside, lights, thresholds, all_finite=False):
    """Solve one pixel over its usable samples: $b = (L^T W L)^{-1} L^T W i$ by cofactors.

    `x` and `usable` as in `_pixel_all_used`; `lights` a list of K `[lx, ly, lz]` (shared
    scalars or this pixel's own vectors); `all_finite` as in `_samples`. Every output takes
    this one solve: solved again in each output's loop, it was slower at K=12 with 5% of the
    samples dropped (docs/speed.md).
    """
    g, w, cases, n_used, a, r, r_channels = _weighted_system(x, usable, lights, thresholds,
                                                             all_finite)
    b, rel_det = solve3(a, r)
    b = [b[p] for p in range(3)]
    cases.append((rel_det < REL_DET_MIN, Status.DEGENERATE))
    sq = _misfit(g, w, lights, b)

    def colour_albedo(n):
        nan = sum(n[p] * a[p][q] * n[q] for p in range(3) for q in range(3))
        return [safe_divide(sum(n[p] * r_c[p] for p in range(3)), nan) for r_c in r_channels]

    colour_albedo = None if len(x[0]) == 1 else colour_albedo
    return _finish(lambda: (b, sq, colour_albedo), n_used, cases, inside,
                   backfacing_from_b=True)


def _pixel_weighted_packed(x, usable, inside, lights, thresholds, all_finite=False):
    """`_pixel_weighted`'s solve of one pixel, packed for `_unpack_weighted`: complex numbers
    $b_x + i b_y$ and $b_z + i m$, with $m$ the squared misfit (or minus the status code,
    where a case before the normal's own fired), then for C > 1 channels $f_0 + i f_1$, ...
    (see below), and n_used.

    XLA-CPU computes each output of the solve in a loop over the image of its own, and each
    loop that needs $b$ solves the pixel's system again from all K samples. A complex output
    carries two values out of one loop, so two loops solve it where `_pixel_weighted` took
    five. The second divides by det itself instead of reusing the first's $1/\\det$: XLA
    writes a divide that two loops share to memory, in one more loop over the samples.

    Colour: channel c's least-squares albedo along $n$ is $n \\cdot r_c / n^T A n$, which is
    $|b| f_c$ with $f_c = b \\cdot r_c / b \\cdot r$ (as $A b = r$). The grey samples are the
    channel mean, so the $f_c$ sum to C: the first C-1 are packed in pairs, and the last is
    C minus their sum.
    """
    g, w, cases, n_used, a, r, r_channels = _weighted_system(x, usable, lights, thresholds,
                                                             all_finite)
    adj, det = adjugate3(a)
    cases.append((relative_det(a, det) < REL_DET_MIN, Status.DEGENERATE))
    code = first_status([(~inside, Status.MASKED), *cases])
    num = [adj[p][0] * r[0] + adj[p][1] * r[1] + adj[p][2] * r[2] for p in range(3)]
    det = jnp.where(det != 0, det, 1)
    inv_det = 1 / det
    sq = _misfit([gk * det for gk in g], w, lights, num) / (det * det)  # b = num / det
    misfit = jnp.where(code == Status.OK, sq, -code.astype(det.dtype))
    b = [v * inv_det for v in num]
    planes = [jax.lax.complex(b[0], b[1]), jax.lax.complex(num[2] / det, misfit)]
    if r_channels:
        along_b = [b[0] * v[0] + b[1] * v[1] + b[2] * v[2] for v in (r, *r_channels[:-1])]
        f = [safe_divide(v, along_b[0]) for v in along_b[1:]]
        f += [jnp.zeros_like(det)] * (len(f) % 2)
        planes += [jax.lax.complex(f[i], f[i + 1]) for i in range(0, len(f), 2)]
    return *planes, n_used


def _unpack_weighted(bxy, bz_misfit, *rest, channels=1):
    """`_pixel_weighted`'s outputs from `_pixel_weighted_packed`'s (`rest`: the colour
    planes, then n_used)."""
    *colour, n_used = rest
    b = [jnp.real(bxy), jnp.imag(bxy), jnp.real(bz_misfit)]
    misfit = jnp.imag(bz_misfit)
    code = jnp.where(misfit < 0, -misfit, 0).astype(jnp.int32)
    colour_albedo = None
    if channels > 1:
        f = [v for plane in colour for v in (jnp.real(plane), jnp.imag(plane))][:channels - 1]
        f.append(channels - sum(f))
        rho = safe_sqrt(b[0] ** 2 + b[1] ** 2 + b[2] ** 2)
        colour_albedo = lambda n: [rho * fc for fc in f]
    return _finish(lambda: (b, jnp.maximum(misfit, 0), colour_albedo), n_used,
                   [(code != 0, code)], code != Status.MASKED, backfacing_from_b=True)


@jax.custom_jvp
def _null_basis(lights):
    """`(K-3, K)` orthonormal rows spanning the null space of $L^T$ (the misfit directions).

    The basis is not unique, and JAX cannot differentiate the full SVD that finds it; the
    tangent rule picks the smooth basis that stays orthogonal to $L$: $dN = -N\\,dL\\,L^+$
    (it keeps $N L = 0$ and $N N^T = I$ to first order), so that the misfit $\\|N i\\|^2$,
    which depends only on $N^T N = I - L L^+$, gets its exact gradient.
    """
    return jnp.linalg.svd(lights, full_matrices=True)[0][:, 3:].T


@_null_basis.defjvp
def _null_basis_jvp(primals, tangents):
    (lights,), (d_lights,) = primals, tangents
    null = _null_basis(lights)
    return null, -null @ d_lights @ jnp.linalg.pinv(lights)


def _shared_constants(lights):
    """$L^+$, a basis of the null space of $L^T$, $L^T L$ and whether $L$ spans 3-D."""
    s = jnp.linalg.svd(jax.lax.stop_gradient(lights), compute_uv=False)
    full_rank = s[2] > s[0] / MAX_LIGHT_CONDITION
    return lights, jnp.linalg.pinv(lights), _null_basis(lights), lights.T @ lights, full_rank


def host_constants(lights: np.ndarray) -> tuple[np.ndarray, ...]:
    """`_shared_constants` in float64 numpy, for `(K, 3)` unit lights known before tracing.

    With these as arguments the jitted solve lowers no SVD: lowering a LAPACK call imports
    `scipy.linalg` (0.12-0.15 s of every command-line run). Not differentiable: traced lights
    take `_shared_constants`.
    """
    lights = np.asarray(lights, np.float64)
    u, s, _ = np.linalg.svd(lights, full_matrices=True)
    full_rank = np.bool_(s[2] > s[0] / MAX_LIGHT_CONDITION)
    return lights, np.linalg.pinv(lights), u[:, 3:].T, lights.T @ lights, full_rank


def _planes(images, sample_mask, mask, flat, batched=False):
    """One plane per sample and channel of `(K, H, W, C)` or grey `(K, H, W)` images, the
    usable planes (or K `True`s) and the mask (or one `True` for a mask of None: no all-true
    plane to write): `(H*W,)` planes if `flat`, else `(H, W)`.
    `batched`: images `(N, K, H, W[, C])`, sample mask `(N, K, H, W)` and mask `(N, H, W)`,
    planes `(N, H, W)` (strided slices of the stack, read in place by the passes)."""
    lead = (slice(None),) if batched else ()
    k = images.shape[len(lead)]
    plane = (lambda a: a.reshape(-1)) if flat else (lambda a: a)
    if images.ndim == 3 + len(lead):  # grey sliced as it is: a channel axis changed the fusions
        x = [[plane(images[(*lead, i)])] for i in range(k)]
    else:
        x = [[plane(images[(*lead, i, Ellipsis, j)]) for j in range(images.shape[-1])]
             for i in range(k)]
    usable = [True] * k if sample_mask is None else [plane(sample_mask[(*lead, i)])
                                                     for i in range(k)]
    return x, usable, jnp.asarray(True) if mask is None else plane(mask)


def _axis(mask):
    """The mapped axis of `_planes`'s mask: None for a mask of None (one `True`)."""
    return None if mask is None else 0


def _lift(kernel, in_axes, flat, batched=False, per_capture=False):
    """`kernel` over every pixel of `(H*W,)` planes if `flat`, else of `(H, W)` planes (of
    `(N, H, W)` planes if `batched`, with the lights argument (the 4th) per capture, a leading
    N axis on each leaf, if `per_capture`)."""
    lifted = jax.vmap(kernel, in_axes) if flat else jax.vmap(jax.vmap(kernel, in_axes), in_axes)
    if not batched:
        return lifted
    return jax.vmap(lifted, tuple(0 if i == 3 and per_capture else a
                                  for i, a in enumerate(in_axes)))


def _flags(images, mask, sample_mask, thresholds, flat=True, batched=False):
    """`_pixel_flags` over every pixel (`batched`: `(N, K, ...)` images as in `_planes`)."""
    axis = None if sample_mask is None else 0  # None: every sample allowed, no mask planes
    return _lift(_pixel_flags, (0, axis, _axis(mask), None), flat, batched)(
        *_planes(images, sample_mask, mask, flat, batched), thresholds)


def _max_flags(needs, per_capture=False):
    """The bitwise-or (a max: bit 1 comes with bit 0) of `_pixel_flags` over the pixels, the
    last axes of `needs` (`per_capture`: one per leading capture), as int32.

    Reduced at once, the int32 flags were written to memory first: at 8 x 1 MP a 40 MiB plane
    that glibc mapped afresh for every batch (10,251 page faults a call). A first max over
    groups of g pixels along the last axis fuses into the pass that computes the flags, so
    only 1/g of them, as uint8, reach memory. `benchmarks/ab_flags.py` (three runs of 100
    interleaved rounds, same outputs): the batch's flag pass at 8 x 1 MP took 8.3-8.6 against
    10.7-16.3 ms (best), with no page fault left; a single 1 MP call's switch program was
    unchanged within the noise (3.72-4.16 against 3.87-4.17 ms)."""
    w = needs.shape[-1]
    g = math.gcd(w, 8)
    part = jnp.max(needs.astype(jnp.uint8).reshape(*needs.shape[:-1], w // g, g), axis=-1)
    return jnp.max(part, axis=tuple(range(int(per_capture), part.ndim))).astype(jnp.int32)


def _solve_all_used(images, mask, sample_mask, thresholds, shared, flat=True, batched=False):
    """`_pixel_all_used` over every pixel. `batched`: `(N, K, ...)` images as in `_planes`,
    `shared` for all (`(K, 3)` lights) or per capture (`(N, K, 3)` lights, each constant with
    a leading N axis)."""
    axis = None if sample_mask is None else 0  # None: every sample allowed, no mask planes
    per_capture = batched and shared[0].ndim == 3
    return _lift(_pixel_all_used, (0, axis, _axis(mask), None, None), flat, batched,
                 per_capture)(
        *_planes(images, sample_mask, mask, flat, batched), shared, thresholds)


def _solve_weighted(images, lights, mask, sample_mask, thresholds, flat=True, all_finite=False,
                    batched=False, packed=False):
    """`_pixel_weighted` over every pixel, with `(K, 3)` or per-pixel `(K, H, W, 3)` lights
    (`batched`: `(N, K, ...)` images as in `_planes`, with `(K, 3)` or `(N, K, 3)` lights).

    `packed`: solve with `_pixel_weighted_packed` (`computed_once`: inside a `cond` whose
    two branches are the same), then `_unpack_weighted`. XLA does not simplify across a
    `cond`, so the complex
    planes are written to memory as they are. Without one, and with an
    `optimization_barrier` in its place, it simplified `real(complex(x, y))` back to `x` and
    solved the system again in every output's loop. At 1 MP with 5% of the samples dropped
    the packed solve took 0.66-0.71x the time of the unpacked one at K=12, 0.81-0.93x at K=8
    and 0.91-1.02x at K=4-5 (`benchmarks/bench_weighted_packed.py`, two runs); for three
    colour channels 0.58-0.64x at K=5 and 12 (`benchmarks/ab_l2.py`). Only for a
    program of its own (a branch taken on the host): under `vmap` a `cond` on a batched
    predicate runs both branches."""
    args = (images, lights, mask, sample_mask, thresholds)
    solve = functools.partial(_weighted_planes, flat=flat, all_finite=all_finite,
                              batched=batched, packed=packed)
    if not packed:
        return solve(*args)
    channels = 1 if images.ndim == 3 + batched else images.shape[-1]
    planes = computed_once(solve, *args, key=lights.reshape(-1)[0])
    return _unpack_planes(planes, channels, flat, batched)


def _weighted_planes(images, lights, mask, sample_mask, thresholds, flat, all_finite, batched,
                     packed):
    """`_pixel_weighted` (or `_pixel_weighted_packed` if `packed`) over every pixel, arguments
    as `_solve_weighted` takes them."""
    kernel = _pixel_weighted_packed if packed else _pixel_weighted
    per_capture = batched and lights.ndim == 3
    k = lights.shape[1 if per_capture else 0]
    per_pixel = lights.ndim == 4
    pixel = functools.partial(kernel, all_finite=all_finite)
    if per_pixel:
        lt = [[(lights[i, ..., p].reshape(-1) if flat else lights[i, ..., p])
               for p in range(3)] for i in range(k)]
        pixel = functools.partial(_unit_lights, pixel)
    else:
        lt = [[lights[..., i, p] for p in range(3)] for i in range(k)]
    axis = None if sample_mask is None else 0
    return _lift(pixel, (0, axis, _axis(mask), 0 if per_pixel else None, None), flat, batched,
                 per_capture)(*_planes(images, sample_mask, mask, flat, batched), lt, thresholds)


def _unpack_planes(planes, channels, flat, batched):
    """`_unpack_weighted` over every pixel of `_pixel_weighted_packed`'s planes."""
    unpack = functools.partial(_unpack_weighted, channels=channels)
    return _lift(unpack, (0,) * len(planes), flat, batched)(*planes)


def _unit_lights(pixel, x, usable, inside, lights, thresholds):
    """`pixel` with this pixel's own light vectors normalised here, in its loops. Normalised
    as a `(K, H, W, 3)` array first, the weighted solve at 1 MP, K=5 took about three times
    as long (`benchmarks/bench_weighted_packed.py --per-pixel`)."""
    unit = [[v * jax.lax.rsqrt(sum(c * c for c in lk)) for v in lk] for lk in lights]
    return pixel(x, usable, inside, unit, thresholds)


@jax.custom_batching.custom_vmap
def _any_in_batch(flag):
    """`flag` (a scalar bool); under `jax.vmap`, one unbatched bool: any capture's flag.

    `ps_l2`'s traced `cond` takes this as its predicate, so that under `vmap` over captures
    it stays a `cond`: one capture that drops a sample sends every capture of the batch
    through the weighted solve, which agrees with the every-sample-used one to rounding
    where nothing is dropped (as `photometric_stereo_batch` does for a chunk). On a batched
    predicate `lax.cond` becomes a select that runs both solves, and XLA-CPU fused the clean
    solve into the select's stacked `(N, H, W, 3)` loop (`benchmarks/ab_l2.py`, the `vmap`
    rows). The predicate has no tangent, so the rule needs no derivative of its own."""
    return flag


@_any_in_batch.def_vmap
def _any_in_batch_vmap(axis_size, in_batched, flag):
    (batched,) = in_batched
    return (jnp.any(flag) if batched else flag), False


@jax.custom_batching.custom_vmap
def _mask_per_capture(mask, probe):
    """`mask` as it is; under `jax.vmap` over the images (`probe`, a bool computed from them,
    is batched) with the mask shared, one copy of it per capture, written to memory.

    A shared `(H, W)` mask is broadcast over the captures inside every loop that reads it,
    and XLA-CPU then wrote $|b|$ and $1/|b|$ to memory as planes of their own (as
    `l2_batch_solve` describes). Both arguments are bools, which have no tangent, so
    gradients pass by."""
    return mask


@_mask_per_capture.def_vmap
def _mask_per_capture_vmap(axis_size, in_batched, mask, probe):
    mask_batched, probe_batched = in_batched
    if mask_batched or not probe_batched:
        return mask, mask_batched
    copies = jnp.broadcast_to(mask, (axis_size, *mask.shape))
    return jax.lax.optimization_barrier(copies), True


def _stacked(out):
    """Normals (and colour albedo) stacked here, in the pass that computes them. Stacked after
    a `cond`, the three planes were written, then read and written again (`bench_core.py`). A
    single albedo plane is left as it is: stacked inside, its reshape became a copy."""
    normal, albedo, *rest = out
    return jnp.stack(normal, -1), jnp.stack(albedo, -1) if len(albedo) > 1 else albedo[0], *rest


def _cast_shared(shared, dtype):
    return tuple(a.astype(dtype) if a.dtype != bool else a for a in shared)


@functools.partial(jax.jit, static_argnames=("branch",))
def ps_l2(images, lights, mask, sample_mask, thresholds, shared=None, branch=None):
    """Jitted core. `images` `(K, H, W, C)`, or grey `(K, H, W)` (albedo then `(H, W)`);
    `lights` `(K, 3)` or `(K, H, W, 3)`; `mask` `(H, W)` bool or None (every pixel);
    `sample_mask` `(K, H, W)` bool or None (every sample allowed: no mask planes are read, or
    copied into the `cond` below); `shared`: `host_constants(lights)` or None (computed here,
    differentiably); `branch`: None (decided in the program, by the `cond` below, as a call
    inside a user's `jit` or `vmap` does), `"switch"` (the flag pass and all three solves
    of `SOLVES` in one program, of which `lax.switch` runs one: what `photometric_stereo`
    compiles for a top-level call on the CPU with shared lights), or the solve already
    chosen on the host with `l2_branch`: `"all_used"` or `"weighted"`, or
    `"weighted_finite"` when it has also found every sample inside the mask finite.
    Per-pixel lights always take the weighted solve: None (traced), or
    `"weighted"`/`"weighted_finite"` from the host, which packs it (`_solve_weighted`).

    The kernels take one plane per sample and channel (`(H*W,)` each in the `cond`'s
    branches, `(H, W)` in a host-chosen solve: see docs/photometric_stereo.md) rather than
    slicing a `(K, H*W, C)` block: under `vmap`, indexing a batched block moves the pixel axis first (a
    transposed copy), while separate planes are read in place. Shared lights take a single
    pass with $L^+$ (`_pixel_all_used`); only if some pixel in the mask dropped a sample is the
    image solved again with per-pixel weights, a real branch outside `vmap` (under `vmap` over
    captures `lax.cond` runs both; `photometric_stereo_batch` makes the same choice on the
    host for a whole stack, with `l2_batch_flags` and `l2_batch_solve`).
    """
    h, w = images.shape[1:3]
    if mask is not None:
        mask = _mask_per_capture(mask, jnp.isnan(images.reshape(-1)[0]))
    if shared is None and lights.ndim == 2:
        shared = _shared_constants(lights)
    elif shared is not None:
        shared = _cast_shared(shared, images.dtype)

    if branch not in (None, "switch", *SOLVES):
        raise ValueError("branch must be None, 'switch', 'all_used', 'weighted' or "
                         f"'weighted_finite', got {branch!r}")
    if lights.ndim == 4 and branch in ("all_used", "switch"):
        raise ValueError(f"per-pixel lights take the weighted solve, not branch={branch!r}")
    if branch == "switch":
        # The flag pass and the three solves in one program, one solve run: at 1 MP this
        # took 0.69-0.91x the time of the flag program, its read on the host and the chosen
        # solve's program, at K=5 and 12, every sample used or 5% dropped
        # (`benchmarks/bench_l2_switch.py`, four runs; docs/speed.md).
        flags = _max_flags(_flags(images, mask, sample_mask, thresholds, flat=False))
        out = jax.lax.switch(solve_index(flags), [
            lambda im, lt, *a: _stacked(_solve_all_used(im, *a, shared, flat=False)),
            lambda *a: _stacked(_solve_weighted(*a, flat=False, all_finite=True, packed=True)),
            lambda *a: _stacked(_solve_weighted(*a, flat=False, packed=True)),
        ], images, lights, mask, sample_mask, thresholds)
    elif branch == "all_used":
        out = _stacked(_solve_all_used(images, mask, sample_mask, thresholds, shared,
                                       flat=False))
    elif branch in ("weighted", "weighted_finite"):  # shared or per-pixel lights
        out = _stacked(_solve_weighted(images, lights, mask, sample_mask, thresholds,
                                       flat=False, all_finite=branch == "weighted_finite",
                                       packed=True))
    elif lights.ndim == 2:
        # The flag pass costs one read of the images; it lets the branches take only the inputs
        # as operands (planes or results built outside a `cond` would be copied into it). Where
        # no sample is dropped the two solves agree to rounding (the tests hold both to numpy
        # lstsq), so the weighted one replaces the fast one whole rather than pixel by pixel:
        # a per-pixel merge made XLA-CPU fuse the weighted solve into every output.
        needs = _flags(images, mask, sample_mask, thresholds)
        out = jax.lax.cond(
            _any_in_batch(jnp.any(needs & 1 == 1)),
            lambda *a: _stacked(_solve_weighted(*a)),
            lambda im, lt, *a: _stacked(_solve_all_used(im, *a, shared)),
            images, lights, mask, sample_mask, thresholds)
    else:
        out = _stacked(_solve_weighted(images, lights, mask, sample_mask, thresholds))
    normal, albedo, status, n_used, residual = out
    return PSResult(normal.reshape(h, w, 3), albedo.reshape(h, w, *images.shape[3:]),
                    status.reshape(h, w), n_used.reshape(h, w), residual.reshape(h, w))


@jax.jit
def l2_needs_weights(images, mask, sample_mask, thresholds):
    """The flag pass of `ps_l2`'s branch, taken on the host: an int32 whose bit 0 says that
    some pixel in `mask` must be solved by `_pixel_weighted` (a sample non-finite, saturated,
    shadowed or not in `sample_mask`) and bit 1 that some pixel in `mask` has a non-finite
    sample (one test of the sum of its samples: a sum that overflows counts as non-finite).
    One reduction over the pixels' flags, as cheap as a single bool. `images` `(K, H, W[,
    C])`, `mask` `(H, W)` or None (every pixel), `sample_mask` `(K, H, W)` or None and
    `thresholds` (cast to the images' dtype here) as `ps_l2` takes them (the flags do
    not depend on the lights)."""
    images = _widened(images)
    thresholds = tuple(jnp.asarray(t, images.dtype) for t in thresholds)
    return _max_flags(_flags(images, mask, sample_mask, thresholds))


def l2_branch(images, mask, sample_mask, thresholds) -> str:
    """`ps_l2`'s `branch`, taken on the host from one read of `l2_needs_weights`:
    `"all_used"`, or `"weighted_finite"` / `"weighted"` as every sample inside the mask is
    finite or not (outside it, the solve's status codes hide whatever a NaN computes)."""
    return branch_of(int(stored_call(l2_needs_weights, images, mask, sample_mask, thresholds)))


def ps_l2_eager(images, lights, mask, sample_mask, thresholds) -> PSResult:
    """`ps_l2` for solvers that run outside `jit` (`semi_calibrated`, `oren_nayar`), same
    arguments. A call on the CPU with no tracer in its arguments and `(K, 3)` lights takes the
    branch on the host, as `photometric_stereo` does for L2 (`l2_branch`, then only the
    chosen solve is compiled); anything else is `ps_l2` with its `cond`."""
    if lights.ndim != 2 or not cpu_top_level(images, lights, mask, sample_mask, thresholds):
        return ps_l2(images, lights, mask, sample_mask, thresholds)
    shared = host_constants(np.asarray(lights, np.float64))
    return ps_l2(images, lights, mask, sample_mask, thresholds, shared,
                 branch=l2_branch(images, mask, sample_mask, thresholds))


def solve_index(flags):
    """The index into `SOLVES` of the solve that the flags of `l2_needs_weights` (or their
    bitwise or) call for: 0 if no sample is dropped, else 1, or 2 if some sample is not
    finite. Integer arithmetic, so that it serves a host int and a traced int32 alike."""
    return (flags & 1) * (1 + ((flags >> 1) & 1))


def branch_of(flags: int) -> str:
    """`ps_l2`'s `branch` from the flags of `l2_needs_weights` (or their bitwise or)."""
    return SOLVES[solve_index(flags)]


@jax.jit
def l2_batch_flags(images, mask, sample_mask, thresholds):
    """`l2_needs_weights` of each capture of a stack: `(N,)` int32. `images`, `mask`,
    `sample_mask` and `thresholds` as `l2_batch_solve` takes them."""
    images = _widened(images)
    thresholds = tuple(jnp.asarray(t, images.dtype) for t in thresholds)
    return _max_flags(_flags(images, mask, sample_mask, thresholds, flat=False, batched=True),
                      per_capture=True)


def _batch_solve(images, lights, mask, sample_mask, thresholds, shared, dtype):
    """The every-sample-used solve of a stack (`l2_batch_solve`), in one program; `lights`
    is unused (their constants are in `shared`), taken so that both solves share arguments."""
    images = _widened(images)
    res = _solve_all_used(images, mask, sample_mask, thresholds,
                          _cast_shared(shared, images.dtype), flat=False, batched=True)
    normal, albedo, status, n_used, residual = _stacked(res)
    return normal.astype(dtype), albedo.astype(dtype), status, n_used, residual.astype(dtype)


def _batch_solve_into(out, *args, **kwargs):
    del out  # donated: XLA writes each output into its buffer (`keep_unused` keeps it)
    return _batch_solve(*args, **kwargs)


def _batch_planes(scratch, images, lights, mask, sample_mask, thresholds, branch):
    """The weighted solve of a stack, first program: `_pixel_weighted_packed`'s planes, n_used
    last. `scratch`: `(planes, n_used)` of an earlier call of the same shapes, either None,
    donated: XLA writes the outputs into their buffers."""
    del scratch
    images = _widened(images)
    return _weighted_planes(images, lights.astype(images.dtype), mask, sample_mask, thresholds,
                            flat=False, all_finite=branch == "weighted_finite", batched=True,
                            packed=True)


def _batch_unpack(out, planes, channels, dtype):
    """The weighted solve of a stack, second program: normals, albedo, status and residual
    from `_batch_planes`'s `planes`, into `out`'s four arrays (donated) unless None."""
    del out
    normal, albedo, status, _, residual = _stacked(_unpack_planes(planes, channels, False, True))
    return normal.astype(dtype), albedo.astype(dtype), status, residual.astype(dtype)


_INTO = {"donate_argnums": 0, "keep_unused": True}
# into `out` -> program, with XLA-CPU's older emitters (as `photometric_stereo`'s). At 8 x 1 MP,
# medians of 8 interleaved rounds (`bench_batch.py --emitters`, two runs:
# `batch_emitters_1.json`, `batch_emitters.json`), older against default: every sample used
# 85.8 and 86.7 against 117.3 and 115.3 ms (K=5), 127.2 and 126.4 against 177.7 and 174.9 ms
# (K=12); 5% of the samples dropped (then one program) 154.0 and 157.4 against 156.2 and 161.2 ms
# (K=5), 201.2 and 205.4 against 209.7 and 218.2 ms (K=12).
_BATCH_PROGRAMS = {
    False: CpuTuned(_batch_solve, OLDER_EMITTERS, static_argnames="dtype"),
    True: CpuTuned(_batch_solve_into, OLDER_EMITTERS, static_argnames="dtype", **_INTO),
}
# The weighted solve in two programs: the packed planes are outputs of the first, so they can
# be written into kept buffers (`scratch`). Inside one program (a `cond` keeps XLA from
# unpacking them, `_solve_weighted`) they were temporaries, fresh memory for every batch: at
# 8 x 1 MP 2 x 84 MB, 40,961 page faults, and 0.75x of single calls against 0.97-1.02x now
# (`benchmarks/bench_batch.py`; docs/speed.md, "Many captures").
_BATCH_WEIGHTED = (
    CpuTuned(_batch_planes, OLDER_EMITTERS, static_argnames="branch", **_INTO),
    CpuTuned(_batch_unpack, OLDER_EMITTERS, static_argnames=("channels", "dtype"), **_INTO),
)


def l2_batch_solve(images, lights, mask, sample_mask, thresholds, shared, *, branch, dtype,
                   out=None, scratch=None):
    """N captures solved as one image of N times the pixels: each output is one pass over the
    stack, on all threads, written straight into its `(N, ...)` array (no per-capture
    program, no copy).

    `images` `(N, K, H, W[, C])` (float16 and bfloat16 are solved in float32); `lights`
    `(K, 3)` unit vectors shared by all, or `(N, K, 3)`; `mask` `(N, H, W)`, one plane per
    capture even where they are the same: with one `(H, W)` plane broadcast inside, XLA-CPU
    wrote $|b|$ and $1/|b|$ to memory (6 fusions against 4, `benchmarks/hlo_l2.py`), as `_finish`
    describes; `sample_mask` `(N, K, H, W)` or None; `shared`: `host_constants(lights)`, or
    each capture's stacked along a leading N axis; `branch`
    (`branch_of` the or of `l2_batch_flags`): the solve every capture takes, so one capture
    that drops a sample sends the whole stack through the weighted solve, as one such pixel
    does a single image; `out`: the five arrays of an earlier result of the same shapes,
    donated, whose buffers take the outputs (no fresh memory, so no page faults);
    `scratch`: the packed planes an earlier weighted call of the same `images` shape and
    dtype returned, donated, whose buffers take this call's (None: fresh memory).

    **Returns:** `(outputs, planes)`: normals `(N, H, W, 3)`, albedo `(N, H, W[, C])`, status,
    n_used and residual `(N, H, W)` (normals, albedo and residual in `dtype`); and the
    weighted solve's packed planes, for a later call's `scratch` (None for `"all_used"`)."""
    args = (images, lights, mask, sample_mask, thresholds)
    if branch == "all_used":
        program = _BATCH_PROGRAMS[out is not None]
        return program(*((out,) if out is not None else ()), *args, shared, dtype=dtype), None
    planes_program, unpack_program = _BATCH_WEIGHTED
    planes = planes_program((scratch, None if out is None else out[3]), *args, branch=branch)
    channels = 1 if images.ndim == 4 else images.shape[-1]
    normal, albedo, status, residual = unpack_program(
        None if out is None else (out[0], out[1], out[2], out[4]), planes, channels=channels,
        dtype=dtype)
    return (normal, albedo, status, planes[-1], residual), planes[:-1]
