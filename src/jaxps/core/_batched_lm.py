"""Levenberg–Marquardt for many tiny independent least-squares problems (one per pixel).

`optimistix.least_squares` under `jax.vmap` is exact but slow for a million 1-3 parameter
problems on a CPU (a batched while-loop around a batched QR: 0.15 s for 64 x 64 pixels here,
`benchmarks/bench_reflectance.py`). `lm_pixel` is the same damped Gauss–Newton iteration
(Levenberg 1944, Marquardt 1963) written for one pixel with every sum unrolled: the P x P
normal equations are solved by cofactors (P <= 3), the Jacobian comes from P `jax.jvp`s, box
bounds are enforced by projection, and it stops at a step limit or when the step or the cost
change is below tolerance, reporting a converged flag and its step count. Lifted with `vmap`,
every operation is elementwise over pixels.

`map_pixels` runs such a vmapped kernel over the image in tiles of a few thousand pixels with
`lax.map`: an LM step has a few hundred intermediate values per pixel, and whole-image
intermediates would go through memory (a one-off measurement on a prototype: 4 steps on
512 x 512 took 379 ms image-wide, 150 ms in tiles of 16k pixels). Tiles also stop early: a tile whose pixels have all converged
does no more steps.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._linalg import solve3

__all__ = ["BatchedLM", "lm_pixel", "map_pixels", "solve_pixels"]

# Pixels per tile for `map_pixels`: large enough to amortise the loop, small enough that one
# tile's intermediates stay in cache.
TILE = 16384


class BatchedLM(eqx.Module):
    """Per-pixel Levenberg–Marquardt settings (see the module docstring).

    - `rtol`, `atol`: a pixel has converged when its step satisfies
      $|\\delta| \\le atol + rtol |y|$ (elementwise) or its cost stops decreasing by more than
      `rtol` relatively.
    - `damping0`: initial Marquardt damping $\\lambda$ (scaled by diag($J^T J$)).
    """

    rtol: float = 1e-4
    atol: float = 1e-6
    damping0: float = 1e-3


def _solve_small(h, g):
    """Solve `h x = g` for one pixel: `h` nested lists `[P][P]` of scalars, `g` `[P]`."""
    p = len(g)
    one = jnp.ones_like(g[0])
    if p == 1:
        d = h[0][0]
        return [g[0] / jnp.where(d > 0, d, one)]
    if p == 2:
        det = h[0][0] * h[1][1] - h[0][1] * h[1][0]
        det = jnp.where(jnp.abs(det) > 0, det, one)
        return [(h[1][1] * g[0] - h[0][1] * g[1]) / det, (h[0][0] * g[1] - h[1][0] * g[0]) / det]
    if p == 3:
        x, _ = solve3(h, g)
        return [x[0], x[1], x[2]]
    raise ValueError(f"lm_pixel handles at most 3 parameters per problem, got {p}")


def lm_pixel(
    fn: Callable,
    y0: tuple[Float[Array, ""], ...],
    solver: BatchedLM,
    *,
    max_steps: int | Int[Array, ""],
    lower: tuple | None = None,
    upper: tuple | None = None,
    active: Bool[Array, ""] | bool = True,
    damping: Float[Array, ""] | None = None,
) -> tuple[tuple[Float[Array, ""], ...], Bool[Array, ""], Int[Array, ""], Float[Array, ""]]:
    """Minimise $\\frac12 |r(y)|^2$ for one pixel; lift with `jax.vmap`.

    **Arguments:**
    - `fn`: `fn(y) -> (K,)` residuals, `y` a tuple of P scalars (P <= 3); pure, traceable.
    - `y0`: the starting tuple.
    - `solver`: a `BatchedLM` (tolerances and initial damping).
    - `max_steps`: step limit (each step: residuals with their Jacobian, one trial residual);
      may be traced.
    - `lower`, `upper`: per-parameter bounds (scalars or None for unbounded), by projection.
    - `active`: False skips the pixel (`y0` back, converged, 0 steps).
    - `damping`: the starting damping (default `solver.damping0`), to resume a solve.

    **Returns:** `(y, converged, steps, damping)`. A pixel whose damping grows past 1e10 (no
    step lowers the cost) counts as converged: it sits at a minimum to working precision.
    """
    p = len(y0)
    dtype = y0[0].dtype
    rtol = jnp.asarray(solver.rtol, dtype)
    atol = jnp.asarray(solver.atol, dtype)
    tiny = jnp.asarray(jnp.finfo(dtype).tiny, dtype)
    lower = (None,) * p if lower is None else lower
    upper = (None,) * p if upper is None else upper
    zero, one = jnp.zeros((), dtype), jnp.ones((), dtype)

    def project(y):
        out = []
        for v, lo, hi in zip(y, lower, upper):
            v = v if lo is None else jnp.maximum(v, lo)
            out.append(v if hi is None else jnp.minimum(v, hi))
        return tuple(out)

    def cost(r):
        return 0.5 * sum(r[k] * r[k] for k in range(r.shape[0]))

    def step(y, lam):
        cols = []
        for j in range(p):
            r, col = jax.jvp(fn, (y,), (tuple(one if a == j else zero for a in range(p)),))
            cols.append(col)
        ks = range(r.shape[0])
        g = [sum(c[k] * r[k] for k in ks) for c in cols]
        h = [[sum(a[k] * b[k] for k in ks) for b in cols] for a in cols]
        hmax = h[0][0]
        for j in range(1, p):
            hmax = jnp.maximum(hmax, h[j][j])
        floor = 1e-9 * jnp.maximum(hmax, tiny)
        damped = [[h[a][b] + (lam * jnp.maximum(h[a][a], floor) + floor if a == b else 0)
                   for b in range(p)] for a in range(p)]
        delta = _solve_small(damped, g)
        y_new = project(tuple(v - d for v, d in zip(y, delta)))
        c_old, c_new = cost(r), cost(fn(y_new))
        ok = jnp.isfinite(c_new) & (c_new <= c_old)
        small = jnp.asarray(True)
        for v, v_new in zip(y, y_new):
            small = small & (jnp.abs(v_new - v) <= atol + rtol * jnp.abs(v))
        # The cost no longer changes beyond rounding, whether or not the step was accepted
        # (in float32 a pixel at its minimum sees rejected steps of the size of rounding).
        flat = jnp.abs(c_old - c_new) <= rtol * c_old
        return y_new, ok, small | flat | (c_old <= tiny)

    def cond(state):
        _, _, done, k = state
        return (k < max_steps) & ~done

    def body(state):
        y, lam, _, k = state
        y_new, ok, conv = step(y, lam)
        y = tuple(jnp.where(ok, a, b) for a, b in zip(y_new, y))
        lam = jnp.minimum(jnp.where(ok, lam / 3, lam * 4), jnp.asarray(1e10, dtype))
        return y, lam, conv | (lam >= 1e10), k + 1

    lam0 = jnp.asarray(solver.damping0 if damping is None else damping, dtype)
    state = (project(y0), lam0, ~jnp.asarray(active), jnp.asarray(0, jnp.int32))
    y, lam, done, steps = jax.lax.while_loop(cond, body, state)
    y = tuple(jnp.where(jnp.isfinite(a), a, b) for a, b in zip(y, y0))
    return y, done, steps, lam


def map_pixels(f: Callable, *args, tile: int | None = TILE):
    """`jax.vmap(f, in_axes=-1, out_axes=-1)(*args)` computed `tile` pixels at a time.

    Every array leaf of `args` has the pixel axis *last*, `(..., N)`; so does the output. The
    pixel axis stays minor inside the kernel too, which is what XLA-CPU vectorises: with the
    pixel axis first, a one-pixel `(K,)` array becomes `(N, K)` and every operation runs along
    a 5-wide minor axis (measured several times slower). N is padded to a multiple of `tile`
    with copies of the first pixel (cropped again), so `f` only sees valid data; the tiles run
    one after another under `lax.map`. `tile=None`: the whole image at once (better for
    short fixed-length kernels: measured 2.5x faster for the Oren–Nayar start).
    """
    kernel = jax.vmap(f, in_axes=-1, out_axes=-1)
    n = jax.tree_util.tree_leaves(args)[0].shape[-1]
    if tile is None or n <= tile:
        return kernel(*args)
    nt = -(-n // tile)
    pad = nt * tile - n

    def split(x):
        if pad:
            x = jnp.concatenate([x, jnp.broadcast_to(x[..., :1], x.shape[:-1] + (pad,))], -1)
        return jnp.moveaxis(x.reshape(x.shape[:-1] + (nt, tile)), -2, 0)

    def join(x):
        return jnp.moveaxis(x, 0, -2).reshape(x.shape[1:-1] + (nt * tile,))[..., :n]

    out = jax.lax.map(lambda a: kernel(*a), jax.tree_util.tree_map(split, args))
    return jax.tree_util.tree_map(join, out)


# `solve_pixels`: step limits of the rounds before the last (which takes what is left of
# `max_steps`), and the share of the image gathered per chunk.
ROUND_STEPS = (4, 4, 8)
CHUNK = 0.125


def solve_pixels(
    fn: Callable,
    y0: tuple[Float[Array, " N"], ...],
    args,
    active: Bool[Array, " N"],
    solver: BatchedLM,
    *,
    max_steps: int,
    lower: tuple | None = None,
    upper: tuple | None = None,
    round_steps: tuple[int, ...] = ROUND_STEPS,
    chunk: float = CHUNK,
    tile: int | None = TILE,
) -> tuple[tuple[Float[Array, " N"], ...], Bool[Array, " N"], Int[Array, " N"]]:
    """`lm_pixel` for every pixel, in rounds so that a few slow pixels cost little.

    A tile runs until its slowest pixel stops, and in a flat valley (e.g. roughness near normal
    incidence, where it barely changes the shading) a pixel can take tens of steps. So the
    solve runs in rounds of a few steps (`round_steps`, then the rest of `max_steps`); in each
    round the pixels still running are gathered, `chunk` of the image at a time, into compact
    arrays that run in tiles, and continue where they stopped, damping included. A late round
    touches only the few pixels left. The rounds change only the cost: the answer is that of
    one long round (tested). One LM kernel serves every round (the step limit is traced), so
    it is compiled once.

    **Arguments:** `fn(y, a) -> (K,)` residuals of one pixel for the parameter tuple `y` and
    that pixel's slice `a` of `args` (a pytree of `(..., N)` arrays); `y0` a tuple of `(N,)`
    starts; `active` `(N,)` pixels to solve; the rest as in `lm_pixel`.

    **Returns:** `(y, converged (N,), steps (N,) int32)`.
    """
    n = active.shape[0]
    bounds = {"lower": lower, "upper": upper}

    def one(y, a, act, lam, limit):
        return lm_pixel(lambda v: fn(v, a), y, solver, max_steps=limit, active=act,
                        damping=lam, **bounds)

    lam = jnp.full((n,), solver.damping0, y0[0].dtype)
    if tile is None or n <= tile:  # one tile: nothing to gain from rounds
        y, done, steps, _ = map_pixels(lambda *a: one(*a, max_steps), y0, args, active, lam,
                                       tile=tile)
        return y, done | ~active, steps
    limits, left = [], max_steps
    for s in round_steps:
        if left > 0:
            limits.append(min(s, left))
            left -= limits[-1]
    if left > 0:
        limits.append(left)
    cap = min(n, -(-max(int(n * chunk), 1) // tile) * tile)  # a whole number of tiles

    def run_chunk(state):
        y, lam, done, steps, pending, limit = state
        idx = jnp.nonzero(pending, size=cap, fill_value=n)[0]
        take = lambda x: x[..., jnp.minimum(idx, n - 1)]  # noqa: E731
        y2, done2, taken, lam2 = map_pixels(
            lambda *a: one(*a, limit), tuple(take(v) for v in y),
            jax.tree_util.tree_map(take, args), idx < n, take(lam), tile=tile)
        put = lambda x, v: x.at[idx].set(v, mode="drop")  # noqa: E731
        return (tuple(put(a, b) for a, b in zip(y, y2)), put(lam, lam2), put(done, done2),
                put(steps, take(steps) + taken), put(pending, jnp.zeros_like(done2)), limit)

    def run_round(r, state):
        y, lam, done, steps = state
        out = jax.lax.while_loop(lambda st: jnp.any(st[4]), run_chunk,
                                 (y, lam, done, steps, ~done, jnp.asarray(limits)[r]))
        return out[:4]

    state = (y0, lam, ~active, jnp.zeros((n,), jnp.int32))
    y, _, done, steps = jax.lax.fori_loop(0, len(limits), run_round, state)
    return y, done | ~active, steps
