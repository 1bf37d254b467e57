"""Masked least-squares and bilateral normal integration on the pixel grid (jitted, matrix-free).

Both methods minimise a weighted sum of squared one-sided finite-difference residuals over the
pixels of a mask. Written per edge of the 4-neighbour grid, that energy is
$\\sum_e a_e (\\delta_e)^2 - 2 g_e \\delta_e$ with $\\delta_e = z_j - z_i$ the height step along
edge $e = (i, j)$ (left to right, top to bottom), so its normal equations are a weighted graph
Laplacian $L_a z = \\operatorname{div}(g)$. $L_a$ is applied as a 5-point stencil on the
(cropped) image, never assembled, and solved by conjugate gradients inside one `jax.jit`
(`lax.while_loop`, explicit step limits), preconditioned by a geometric multigrid V-cycle
(`pcg`, `_vcycle`) or, as Cao et al.'s code does, by the diagonal (Jacobi).

Why a jitted matrix-free CG rather than `scipy.sparse`: the bilateral method's 10-40
reweighting steps need ~3000-5000 Jacobi-CG steps in all on a DiLiGenT object (~200-500 with
the multigrid preconditioner). A direct `splu` took 0.2-1 s per factorisation (one per step) on
these objects. `benchmarks/bench_integration.py` runs Cao et al.'s algorithm as their code does
it (system re-assembled each step, warm-started Jacobi `scipy.sparse.linalg.cg`, float64) in
the same run as a baseline. The multigrid V-cycle needs `_keep` to be fast under XLA on CPU:
without it XLA fuses each level's result into the next stencil's five reads and recomputes
it, ~5x more work per level (tens of times slower in all in exploratory timings).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from ..core._host import OLDER_EMITTERS, CpuTuned

__all__ = ["GridSolve", "bilateral", "edge_div", "laplacian", "lsq_midpoint", "pcg",
           "solve_laplacian"]


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


def _inverse(diag):
    one = jnp.ones((), diag.dtype)
    return jnp.where(diag > 0, one / jnp.where(diag > 0, diag, one), 0).astype(diag.dtype)


def _keep(x):
    """`x`, as a buffer: XLA would otherwise fuse its computation into each of the five reads of
    the next stencil, and the V-cycle's levels compound that (5^levels recomputation). A
    conditional it cannot resolve at compile time stops the fusion; the predicate is true unless
    `x` already holds a non-finite value, which the other branch keeps non-finite."""
    return lax.cond(jnp.isfinite(x[0, 0]), lambda v: v, lambda v: v + v[0, 0], x)


def _coarsen(ah, av):
    """Edge weights between the 2x2 aggregates of the grid (padded to even size with
    edge-less pixels): the sum of the fine weights crossing between two aggregates, which is
    the Galerkin operator $P^\\top L_a P$ of piecewise-constant prolongation $P$."""
    h, w = ah.shape[0] + ah.shape[0] % 2, av.shape[1] + av.shape[1] % 2
    ah = jnp.pad(ah, ((0, h - ah.shape[0]), (0, w - 1 - ah.shape[1])))[:, 1::2]
    av = jnp.pad(av, ((0, h - 1 - av.shape[0]), (0, w - av.shape[1])))[1::2, :]
    return ah[0::2] + ah[1::2], av[:, 0::2] + av[:, 1::2]


def _hierarchy(ah, av):
    """`(ah, av, 1/diag)` per level, 2x2 aggregation until the grid is at most 8 pixels wide."""
    levels = [(ah, av, _inverse(_edge_sum(ah, av)))]
    while max(ah.shape[0], av.shape[1]) > 8:
        ah, av = _coarsen(ah, av)
        levels.append((ah, av, _inverse(_edge_sum(ah, av))))
    return levels


_OMEGA = 0.8  # damped Jacobi; D^-1 L_a has eigenvalues in [0, 2], so omega < 1 smooths
_COARSE_SWEEPS = 10


def _vcycle(levels, r):
    """One V(1,1)-cycle from 0 for $L_a x = r$: damped Jacobi before and after the coarse
    correction, the coarsest level by `_COARSE_SWEEPS` damped Jacobi sweeps. Symmetric and
    positive semi-definite (same smoother before and after, symmetric coarse solve) on CG's
    residuals, which are 0 on pixels without edges and sum to 0 on each component, so a valid
    CG preconditioner. Pixels with no edge (at any level) get 0."""
    (ah, av, dinv), rest = levels[0], levels[1:]
    om = jnp.asarray(_OMEGA, r.dtype)
    if not rest:
        x = om * dinv * r
        for _ in range(_COARSE_SWEEPS - 1):
            x = _keep(x + om * dinv * (r - laplacian(x, ah, av)))
        return x
    h, w = r.shape
    x = om * dinv * r
    res = jnp.pad(_keep(r - laplacian(x, ah, av)), ((0, h % 2), (0, w % 2)))
    ec = _vcycle(rest, _keep(res[0::2, 0::2] + res[1::2, 0::2] + res[0::2, 1::2]
                             + res[1::2, 1::2]))
    e = _keep(jnp.repeat(jnp.repeat(ec, 2, axis=0), 2, axis=1)[:h, :w])
    x = x + jnp.where(dinv > 0, e, 0)
    return _keep(x + om * dinv * (r - laplacian(x, ah, av)))


def _keep_mean(x, x0, ah, av, labels):
    """`x` shifted on each connected component so that its $D$-weighted mean ($D$ = diag
    $L_a$) is that of `x0`, as Jacobi-preconditioned CG keeps it."""
    diag = _edge_sum(ah, av)
    lab = labels.reshape(-1)
    n = lab.shape[0]
    sd = jax.ops.segment_sum(diag.reshape(-1), lab, num_segments=n)
    sx = jax.ops.segment_sum((diag * (x - x0)).reshape(-1), lab, num_segments=n)
    one = jnp.ones((), x.dtype)
    shift = jnp.where(sd > 0, sx / jnp.where(sd > 0, sd, one), 0)[lab].reshape(x.shape)
    return jnp.where(diag > 0, x - shift, x0)


PRECONDITIONERS = ("multigrid", "jacobi")


def pcg(ah, av, rhs, x0, *, rtol, max_steps, preconditioner="multigrid"):
    """Preconditioned conjugate gradients for $L_a x = b$ (Hestenes & Stiefel, 1952).

    `preconditioner`: `"jacobi"` ($D^{-1}$) or `"multigrid"`: one V(1,1)-cycle of geometric
    multigrid with 2x2 piecewise-constant aggregation and Galerkin coarse weights (Braess,
    "Towards algebraic multigrid for elliptic problems of second order", Computing 55, 1995:
    unsmoothed aggregation, here on the grid's 2x2 blocks), damped Jacobi smoothing
    (`_vcycle`). On DiLiGenT: 10-21x fewer CG steps, each costing about 3 Jacobi-CG steps
    (docs/integration.md).

    $L_a$ is singular (constants per connected component); the right-hand side of an integration
    problem lies in its range, so CG converges. Jacobi-CG started from `x0` keeps each
    component's $D$-weighted mean ($D$ = diag $L_a$) of `x0`; `"multigrid"` does not (its
    coarse corrections move the constants; `solve_laplacian` shifts them back with
    `_keep_mean`). Pixels with no edge keep `x0`. Stops when $\\|r\\| \\le$ `rtol` $\\|b\\|$ or after
    `max_steps`. Returns `(x, steps, converged)`.
    """
    one = jnp.ones((), rhs.dtype)
    if preconditioner == "jacobi":
        minv = _inverse(_edge_sum(ah, av))

        def prec(r):
            return minv * r
    else:
        levels = _hierarchy(ah, av)

        def prec(r):
            return _vcycle(levels, r)
    bound = (rtol * jnp.linalg.norm(rhs)).astype(rhs.dtype)
    r = rhs - laplacian(x0, ah, av)

    def cond(state):
        _, r, _, _, i = state
        return (jnp.linalg.norm(r) > bound) & (i < max_steps)

    def body(state):
        # the preconditioner at the top of the step, so that it is compiled once (the first
        # step has rs = 0, hence beta = 0 and d = s)
        x, r, d, rs, i = state
        s = prec(r)
        rs_new = jnp.vdot(r, s)
        beta = jnp.where(rs > 0, rs_new / jnp.where(rs > 0, rs, one), 0).astype(rhs.dtype)
        d = s + beta * d
        ad = laplacian(d, ah, av)
        dad = jnp.vdot(d, ad)
        alpha = jnp.where(dad > 0, rs_new / jnp.where(dad > 0, dad, one), 0).astype(rhs.dtype)
        return x + alpha * d, r - alpha * ad, d, rs_new, i + 1

    zero = jnp.zeros((), rhs.dtype)
    x, r, _, _, steps = lax.while_loop(cond, body, (x0, r, jnp.zeros_like(r), zero,
                                                    jnp.asarray(0)))
    return x, steps, jnp.linalg.norm(r) <= bound


def _components(ah, av):
    """Connected components of the graph of positive-weight edges: each pixel's label is the
    smallest flat index in its component (min-label propagation with pointer jumping)."""
    h, w = ah.shape[0], av.shape[1]
    big = jnp.asarray(h * w, jnp.int32)
    eh, ev = ah > 0, av > 0

    def step(lab):
        right = jnp.pad(jnp.where(eh, lab[:, 1:], big), ((0, 0), (0, 1)), constant_values=big)
        left = jnp.pad(jnp.where(eh, lab[:, :-1], big), ((0, 0), (1, 0)), constant_values=big)
        down = jnp.pad(jnp.where(ev, lab[1:, :], big), ((0, 1), (0, 0)), constant_values=big)
        up = jnp.pad(jnp.where(ev, lab[:-1, :], big), ((1, 0), (0, 0)), constant_values=big)
        lab = jnp.minimum(jnp.minimum(lab, jnp.minimum(right, left)), jnp.minimum(down, up))
        return lab.reshape(-1)[lab]  # jump to the label's label: still in the component

    def body(state):
        lab, _ = state
        new = step(lab)
        return new, jnp.any(new != lab)

    lab0 = jnp.arange(h * w, dtype=jnp.int32).reshape(h, w)
    lab, _ = lax.while_loop(lambda s: s[1], body, (lab0, jnp.asarray(True)))
    return lab


def _project_to_range(b, ah, av, labels):
    """`b` minus, on each connected component $C$, $D \\mathbf 1_C \\sum_C b / \\sum_C D$ (with
    $D$ = diag $L_a$), and 0 on pixels with no edge: the part of `b` that the transpose of the
    solve `pcg` computes sees (see `solve_laplacian`)."""
    diag = _edge_sum(ah, av)
    lab = labels.reshape(-1)
    n = lab.shape[0]
    sb = jax.ops.segment_sum(b.reshape(-1), lab, num_segments=n)
    sd = jax.ops.segment_sum(diag.reshape(-1), lab, num_segments=n)
    one = jnp.ones((), b.dtype)
    ratio = jnp.where(sd > 0, sb / jnp.where(sd > 0, sd, one), 0)[lab].reshape(b.shape)
    return jnp.where(diag > 0, b - diag * ratio, 0)


def solve_laplacian(ah, av, rhs, x0, *, rtol, max_steps, preconditioner="multigrid"):
    """`pcg` for $L_a x = b$, differentiable by the implicit function theorem.

    Wrapped in `jax.lax.custom_linear_solve` (symmetric), so reverse mode never goes through
    the CG loop: the cotangent $\\bar x$ is carried back by one more `pcg` solve
    $L_a \\lambda = \\bar x$ (giving $\\bar b = \\lambda$ and $\\bar a_e = -\\lambda^\\top
    (\\partial L_a / \\partial a_e) x$), with the same tolerance and step limit. $L_a$ is
    singular: the solution returned has the Jacobi-weighted ($D$ = diag $L_a$) mean of `x0`
    on each connected component (as Jacobi-CG keeps it; `_keep_mean` makes it so for either
    preconditioner), i.e. $x = x_0 + G(b - L_a x_0)$ with
    $G = (I - N (N^\\top D N)^{-1} N^\\top D) L_a^+$ ($N$: one indicator column per component).
    The transpose solve therefore projects $\\bar x$ by $I - D N (N^\\top D N)^{-1} N^\\top$
    first (`_project_to_range`), which also makes its system consistent. $\\bar b$ is exact up
    to a constant per component, which the divergence of an integration problem ignores. Not
    differentiated: how the per-component constant moves when the weights `ah`, `av` change
    (0 for `"lsq"`, whose weights are constant; see `docs/integration.md`), and `x0`.

    Returns `(x, steps, converged)` of the forward solve.
    """
    x0 = lax.stop_gradient(x0)
    a_h, a_v = lax.stop_gradient(ah), lax.stop_gradient(av)
    labels = _components(a_h, a_v)
    kw = {"rtol": rtol, "max_steps": max_steps, "preconditioner": preconditioner}

    def matvec(x):
        return laplacian(x, ah, av)

    def solve_from(b, start):
        x, steps, ok = pcg(a_h, a_v, b, start, **kw)
        return _keep_mean(x, start, a_h, a_v, labels), (steps, ok)

    def solve(_, b):
        return solve_from(b, x0)

    def transpose_solve(_, b):
        return solve_from(_project_to_range(b, a_h, a_v, labels), jnp.zeros_like(b))

    x, (steps, ok) = lax.custom_linear_solve(matvec, rhs, solve, transpose_solve,
                                             symmetric=True, has_aux=True)
    return x, steps, ok


def _edges(valid):
    eh = valid[:, 1:] & valid[:, :-1]
    ev = valid[1:, :] & valid[:-1, :]
    return eh, ev


def lsq_midpoint(gc, gr, valid, *, rtol, max_steps, preconditioner="multigrid"):
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
    z, steps, ok = solve_laplacian(ah, av, edge_div(gh, gv), jnp.zeros_like(gc), rtol=rtol,
                                   max_steps=max_steps, preconditioner=preconditioner)
    return GridSolve(z, jnp.asarray(1), steps, ok)


def bilateral(mu, mv, bu, bv, valid, *, k, tol, cg_rtol, max_steps, cg_max_steps,
              preconditioner="multigrid"):
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
    each weighted system is solved by warm-started `pcg` (`preconditioner`).

    Gradients (reverse mode): the reweighting loop runs on `stop_gradient` inputs, and its last
    weighted least-squares solve is then repeated, warm-started from its own answer (so it
    takes 0-2 CG steps), by `solve_laplacian` with the weights of that solve held fixed: the
    gradient is that of the last weighted least-squares problem, by the implicit function
    theorem; how the weights (and the stopping step) move with the normals is not
    differentiated.

    All maps `(H, W)`; returns `GridSolve` with `steps` the reweighting count.
    """
    mu_in, mv_in, bu_in, bv_in = mu, mv, bu, bv
    mu, mv, bu, bv = (lax.stop_gradient(a) for a in (mu, mv, bu, bv))
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

    def system(wu, wv, mu, mv, bu, bv):
        wr, wl = wu[:, :-1], one - wu[:, 1:]
        wd, wup = wv[:-1, :], one - wv[1:, :]
        ah = eh * (wr * mu[:, :-1] ** 2 + wl * mu[:, 1:] ** 2)
        gh = eh * (wr * mu[:, :-1] * bu[:, :-1] + wl * mu[:, 1:] * bu[:, 1:])
        av = ev * (wd * mv[:-1, :] ** 2 + wup * mv[1:, :] ** 2)
        gv = ev * (wd * mv[:-1, :] * bv[:-1, :] + wup * mv[1:, :] * bv[1:, :])
        return ah, av, edge_div(gh, gv)

    def solve(z, wu, wv):
        ah, av, rhs = system(wu, wv, mu, mv, bu, bv)
        return pcg(ah, av, rhs, z, rtol=cg_rtol, max_steps=cg_max_steps,
                   preconditioner=preconditioner)

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
        _, _, _, _, _, e, e_old, i, _, _ = state
        change = jnp.abs(e - e_old) > tol * e_old
        return (i < max_steps) & ((i == 0) | change)

    def body(state):
        z, wu, wv, _, _, e, _, i, n_cg, _ = state
        z_new, n, ok = solve(z, wu, wv)
        wu_new, wv_new = weights(z_new)
        return z_new, wu_new, wv_new, wu, wv, energy(z_new, wu_new, wv_new), e, i + 1, n_cg + n, ok

    z0 = jnp.zeros_like(mu)
    e0 = energy(z0, half, half)
    init = (z0, half, half, half, half, e0, e0, jnp.asarray(0), jnp.asarray(0),
            jnp.asarray(True))
    z, _, _, wu, wv, e, e_old, i, n_cg, cg_ok = lax.while_loop(cond, body, init)
    converged = (jnp.abs(e - e_old) <= tol * e_old) & cg_ok
    # The last solve again, differentiable in mu, mv, bu, bv with its weights fixed.
    ah, av, rhs = system(wu, wv, mu_in, mv_in, bu_in, bv_in)
    z, n, ok = solve_laplacian(ah, av, rhs, z, rtol=cg_rtol, max_steps=cg_max_steps,
                               preconditioner=preconditioner)
    return GridSolve(z, i, n_cg + n, converged & ok)


# XLA-CPU's older loop emitters for the grid solvers, whose CG steps are many small fusions
# (the V-cycle's coarse levels, dot products): faster on every DiLiGenT object, with the same
# steps and MADE (`bench_integration.py`'s "default emitters" rows, which call `.plain`;
# docs/integration.md, "Measured on DiLiGenT").
lsq_midpoint = CpuTuned(lsq_midpoint, OLDER_EMITTERS,
                        static_argnames=("max_steps", "preconditioner"))
bilateral = CpuTuned(bilateral, OLDER_EMITTERS,
                     static_argnames=("max_steps", "cg_max_steps", "preconditioner"))
