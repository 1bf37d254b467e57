"""Masked least-squares and bilateral normal integration on the pixel grid (jitted, matrix-free).

Both methods minimise a weighted sum of squared one-sided finite-difference residuals over the
pixels of a mask. Written per edge of the 4-neighbour grid, that energy is
$\\sum_e a_e (\\delta_e)^2 - 2 g_e \\delta_e$ with $\\delta_e = z_j - z_i$ the height step along
edge $e = (i, j)$ (left to right, top to bottom), so its normal equations are a weighted graph
Laplacian $L_a z = \\operatorname{div}(g)$. $L_a$ is applied as a 5-point stencil on the
(cropped) image, never assembled, and solved by conjugate gradients with a Jacobi
preconditioner inside one `jax.jit` (`lax.while_loop`, explicit step limits).

Why a jitted matrix-free CG rather than `scipy.sparse`: the bilateral method's 10-30
reweighting steps need ~3000-5000 CG steps in all on a DiLiGenT object. A direct `splu` took
0.2-1 s per factorisation (one per step) on these objects. `benchmarks/bench_integration.py`
runs Cao et al.'s algorithm as their code does it (system re-assembled each step, warm-started
Jacobi `scipy.sparse.linalg.cg`, float64) in the same run as a baseline: same heights and step
counts, 2-3x slower than this stencil version. A 2x2-aggregation multigrid preconditioner was
tried: far fewer CG steps, but slower in all under XLA on CPU, and its near-exact solves moved
the result away from Cao et al.'s figures, which depend on their inexact (`rtol=1e-3`) solves.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

__all__ = ["GridSolve", "bilateral", "edge_div", "laplacian", "lsq_midpoint", "pcg"]


class GridSolve(NamedTuple):
    """Result of a grid solve: height (on the crop), outer steps, CG steps, converged flag."""

    z: jax.Array
    steps: jax.Array
    cg_steps: jax.Array
    converged: jax.Array


def edge_div(gh, gv):
    """Sum edge values into pixels: `+g` at an edge's right/bottom end, `-g` at its left/top end.

    `gh` is `(H, W-1)` (edge between columns c and c+1), `gv` is `(H-1, W)`; returns `(H, W)`.
    """
    z = jnp.zeros((), gh.dtype)
    return (
        jnp.pad(gh, ((0, 0), (1, 0)), constant_values=z)
        - jnp.pad(gh, ((0, 0), (0, 1)), constant_values=z)
        + jnp.pad(gv, ((1, 0), (0, 0)), constant_values=z)
        - jnp.pad(gv, ((0, 1), (0, 0)), constant_values=z)
    )


def laplacian(z, ah, av):
    """$(L_a z)_i = \\sum_{e \\ni i} a_e (z_i - z_j)$; edge weights `ah (H, W-1)`, `av (H-1, W)`."""
    return edge_div(ah * (z[:, 1:] - z[:, :-1]), av * (z[1:, :] - z[:-1, :]))


def _edge_sum(ah, av):
    z = jnp.zeros((), ah.dtype)
    return (
        jnp.pad(ah, ((0, 0), (1, 0)), constant_values=z)
        + jnp.pad(ah, ((0, 0), (0, 1)), constant_values=z)
        + jnp.pad(av, ((1, 0), (0, 0)), constant_values=z)
        + jnp.pad(av, ((0, 1), (0, 0)), constant_values=z)
    )


def pcg(ah, av, rhs, x0, *, rtol, max_steps):
    """Jacobi-preconditioned conjugate gradients for $L_a x = b$ (Hestenes & Stiefel, 1952).

    $L_a$ is singular (constants per connected component); the right-hand side of an integration
    problem lies in its range, so CG converges, and started from a zero-mean `x0` it keeps each
    component's mean. Pixels with no edge keep `x0`. Stops when $\\|r\\| \\le$ `rtol` $\\|b\\|$
    or after `max_steps`. Returns `(x, steps, converged)`.
    """
    one = jnp.ones((), rhs.dtype)
    diag = _edge_sum(ah, av)
    minv = jnp.where(diag > 0, one / jnp.where(diag > 0, diag, one), 0).astype(rhs.dtype)
    bound = (rtol * jnp.linalg.norm(rhs)).astype(rhs.dtype)
    r = rhs - laplacian(x0, ah, av)
    s = minv * r
    rs = jnp.vdot(r, s)

    def cond(state):
        _, r, _, _, i = state
        return (jnp.linalg.norm(r) > bound) & (i < max_steps)

    def body(state):
        x, r, d, rs, i = state
        ad = laplacian(d, ah, av)
        dad = jnp.vdot(d, ad)
        alpha = jnp.where(dad > 0, rs / jnp.where(dad > 0, dad, one), 0).astype(rhs.dtype)
        x = x + alpha * d
        r = r - alpha * ad
        s = minv * r
        rs_new = jnp.vdot(r, s)
        beta = jnp.where(rs > 0, rs_new / jnp.where(rs > 0, rs, one), 0).astype(rhs.dtype)
        return x, r, s + beta * d, rs_new, i + 1

    x, r, _, _, steps = lax.while_loop(cond, body, (x0, r, s, rs, jnp.asarray(0)))
    return x, steps, jnp.linalg.norm(r) <= bound


def _edges(valid):
    eh = valid[:, 1:] & valid[:, :-1]
    ev = valid[1:, :] & valid[:-1, :]
    return eh, ev


@partial(jax.jit, static_argnames=("max_steps",))
def lsq_midpoint(gc, gr, valid, *, rtol, max_steps):
    """Masked least squares: $\\min_z \\sum_{e=(i,j)} (z_j - z_i - (g_i + g_j)/2)^2$ over the
    edges with both ends in `valid`.

    `gc`, `gr`: `(H, W)` height steps per column and per row ($\\partial z/\\partial$col, row).
    This is the discrete Poisson equation with natural (Neumann) borders on the mask, the
    formulation of the survey by Quéau, Durou & Aujol, "Normal integration: a survey", JMIV 60,
    2018 (section 4).
    """
    eh, ev = _edges(valid)
    dt = gc.dtype
    ah, av = eh.astype(dt), ev.astype(dt)
    gh = ah * (gc[:, 1:] + gc[:, :-1]) / 2
    gv = av * (gr[1:, :] + gr[:-1, :]) / 2
    z, steps, ok = pcg(ah, av, edge_div(gh, gv), jnp.zeros_like(gc), rtol=rtol,
                       max_steps=max_steps)
    return GridSolve(z, jnp.asarray(1), steps, ok)


@partial(jax.jit, static_argnames=("max_steps", "cg_max_steps"))
def bilateral(mu, mv, bu, bv, valid, *, k, tol, cg_rtol, max_steps, cg_max_steps):
    """Bilateral normal integration (Cao, Shi, Nakaya, Li, Shi, "Bilateral Normal Integration",
    ECCV 2022): iteratively reweighted least squares over one-sided differences.

    Each pixel $i$ has four residuals, e.g. to the right $r^+_i = m^u_i (z_{i+1} - z_i) - b^u_i$
    and to the left $r^-_i = m^u_i (z_i - z_{i-1}) - b^u_i$, weighted $w_i$ and $1 - w_i$ with
    $w_i = \\sigma(k [(m^u_i \\Delta^-_i z)^2 - (m^u_i \\Delta^+_i z)^2])$: the side whose
    height step is smaller (the same side of a depth jump) gets the weight, so a jump costs
    almost nothing. Orthographic: $m = n_z$, $b^u = -n_x$, $b^v = n_y$ (rows go down); the
    perspective variant only changes $m$ (see `_integrate.py`). Starts from $w = 1/2$ (plain
    least squares), stops when the energy's relative change is below `tol` or after
    `max_steps` reweightings (the energy as Cao et al.'s code computes it, see `energy`);
    each weighted system is solved by warm-started `pcg`.

    All maps `(H, W)`; returns `GridSolve` with `steps` the reweighting count.
    """
    eh, ev = _edges(valid)
    dt = mu.dtype
    eh, ev = eh.astype(dt), ev.astype(dt)
    half = jnp.full_like(mu, 0.5)
    one = jnp.ones((), dt)
    kk = jnp.asarray(k, dt)
    vd = valid.astype(dt)
    zero = jnp.zeros((), dt)
    no_right = vd - jnp.pad(eh, ((0, 0), (0, 1)), constant_values=zero)
    no_left = vd - jnp.pad(eh, ((0, 0), (1, 0)), constant_values=zero)
    no_down = vd - jnp.pad(ev, ((0, 1), (0, 0)), constant_values=zero)
    no_up = vd - jnp.pad(ev, ((1, 0), (0, 0)), constant_values=zero)

    def steps_of(z):
        return eh * (z[:, 1:] - z[:, :-1]), ev * (z[1:, :] - z[:-1, :])

    def energy(z, wu, wv):
        dh, dv = steps_of(z)
        e_right = wu[:, :-1] * (mu[:, :-1] * dh - bu[:, :-1]) ** 2
        e_left = (one - wu[:, 1:]) * (mu[:, 1:] * dh - bu[:, 1:]) ** 2
        e_down = wv[:-1, :] * (mv[:-1, :] * dv - bv[:-1, :]) ** 2
        e_up = (one - wv[1:, :]) * (mv[1:, :] * dv - bv[1:, :]) ** 2
        inner = jnp.sum(eh * (e_right + e_left)) + jnp.sum(ev * (e_down + e_up))
        # Cao et al.'s energy also counts the equations of a pixel whose neighbour on that side
        # is outside the mask (its difference is 0, so the residual is b); only the stopping
        # rule sees this term.
        return inner + jnp.sum(no_right * wu * bu**2 + no_left * (one - wu) * bu**2
                               + no_down * wv * bv**2 + no_up * (one - wv) * bv**2)

    def solve(z, wu, wv):
        wr, wl = wu[:, :-1], one - wu[:, 1:]
        wd, wup = wv[:-1, :], one - wv[1:, :]
        ah = eh * (wr * mu[:, :-1] ** 2 + wl * mu[:, 1:] ** 2)
        gh = eh * (wr * mu[:, :-1] * bu[:, :-1] + wl * mu[:, 1:] * bu[:, 1:])
        av = ev * (wd * mv[:-1, :] ** 2 + wup * mv[1:, :] ** 2)
        gv = ev * (wd * mv[:-1, :] * bv[:-1, :] + wup * mv[1:, :] * bv[1:, :])
        return pcg(ah, av, edge_div(gh, gv), z, rtol=cg_rtol, max_steps=cg_max_steps)

    def weights(z):
        dh, dv = steps_of(z)
        zero = jnp.zeros((), dt)
        right = jnp.pad(mu[:, :-1] * dh, ((0, 0), (0, 1)), constant_values=zero)
        left = jnp.pad(mu[:, 1:] * dh, ((0, 0), (1, 0)), constant_values=zero)
        down = jnp.pad(mv[:-1, :] * dv, ((0, 1), (0, 0)), constant_values=zero)
        up = jnp.pad(mv[1:, :] * dv, ((1, 0), (0, 0)), constant_values=zero)
        wu = jax.nn.sigmoid(kk * (left**2 - right**2))
        wv = jax.nn.sigmoid(kk * (up**2 - down**2))
        return wu, wv

    def cond(state):
        _, _, _, e, e_old, i, _, _ = state
        change = jnp.abs(e - e_old) > tol * e_old
        return (i < max_steps) & ((i == 0) | change)

    def body(state):
        z, wu, wv, e, _, i, n_cg, _ = state
        z, n, ok = solve(z, wu, wv)
        wu, wv = weights(z)
        return z, wu, wv, energy(z, wu, wv), e, i + 1, n_cg + n, ok

    z0 = jnp.zeros_like(mu)
    e0 = energy(z0, half, half)
    init = (z0, half, half, e0, e0, jnp.asarray(0), jnp.asarray(0), jnp.asarray(True))
    z, _, _, e, e_old, i, n_cg, cg_ok = lax.while_loop(cond, body, init)
    converged = (jnp.abs(e - e_old) <= tol * e_old) & cg_ok
    return GridSolve(z, i, n_cg, converged)

