"""Poisson integration on the whole rectangle with Neumann borders, solved by a DCT."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

__all__ = ["dct_poisson"]


def _even_odd(x, axis):
    """Makhoul's reordering: the even samples, then the odd ones reversed."""
    n = x.shape[axis]
    return jnp.concatenate([lax.slice_in_dim(x, 0, n, 2, axis),
                            jnp.flip(lax.slice_in_dim(x, 1, n, 2, axis), axis)], axis=axis)


def _even_odd_inverse(v, axis):
    n = v.shape[axis]
    h = (n + 1) // 2
    even = lax.slice_in_dim(v, 0, h, 1, axis)
    odd = jnp.flip(lax.slice_in_dim(v, h, n, 1, axis), axis)
    if n % 2:
        odd = jnp.concatenate([odd, jnp.zeros_like(lax.slice_in_dim(v, 0, 1, 1, axis))], axis)
    shape = list(v.shape)
    shape[axis] = 2 * h
    out = jnp.stack([even, odd], axis=axis + 1).reshape(shape)  # interleave
    return lax.slice_in_dim(out, 0, n, 1, axis)


def _reorder(x):
    """Makhoul's reordering along both axes. For even sides the four quadrants are stacked in
    one expression, which XLA-CPU fuses into one pass (two nested concatenates were not)."""
    n1, n2 = x.shape
    if n1 % 2 or n2 % 2:
        return _even_odd(_even_odd(x, 0), 1)
    ee, eo = x[0::2, 0::2], jnp.flip(x[0::2, 1::2], 1)
    oe, oo = jnp.flip(x[1::2, 0::2], 0), jnp.flip(x[1::2, 1::2], (0, 1))
    return jnp.stack([jnp.stack([ee, eo], 1), jnp.stack([oe, oo], 1)]).reshape(n1, n2)


def _reorder_inverse(v):
    n1, n2 = v.shape
    if n1 % 2 or n2 % 2:
        return _even_odd_inverse(_even_odd_inverse(v, 0), 1)
    h1, h2 = n1 // 2, n2 // 2
    ee, eo = v[:h1, :h2], jnp.flip(v[:h1, h2:], 1)
    oe, oo = jnp.flip(v[h1:, :h2], 0), jnp.flip(v[h1:, h2:], (0, 1))
    return jnp.stack([jnp.stack([ee, eo], -1), jnp.stack([oe, oo], -1)], 1).reshape(n1, n2)


def _neumann_spectrum(rhs):
    """The half spectrum of $L^{-1}$ rhs reordered, for the Neumann Laplacian $L$ (mean 0):
    $L^{-1}$ rhs is `_neumann_from_spectrum` of it, so the solve is one real 2-D FFT each way.

    The DCT-II of rhs, a division by $L$'s eigenvalues and the inverse DCT-II, composed into
    one pass over the half spectrum. Makhoul ("A fast cosine transform in one and multiple
    dimensions", IEEE TASSP 28(1), 1980) gets the 2-D DCT-II $X$ of $x$ from the FFT $V$ of
    $x$ reordered along both axes: with $e_j = e^{-i\\pi k_j/2N_j}$, $A = e_1 e_2 V(k_1,k_2)$,
    $B = e_1 \\bar e_2 \\overline{V(-k_1,k_2)}$, $S = A + B$ and $D = A - B$,

    $X(k_1,k_2) = 2\\,\\mathrm{Re}\\,S$, $X(-k_1,k_2) = -2\\,\\mathrm{Im}\\,S$,
    $X(k_1,-k_2) = -2\\,\\mathrm{Im}\\,D$, $X(-k_1,-k_2) = -2\\,\\mathrm{Re}\\,D$

    ($-k$ meaning $N-k$). Dividing each by its eigenvalue $\\lambda$ and inverting the same map
    gives the reordered solution's spectrum
    $V' = \\tfrac12 \\bar e_1 \\bar e_2 [\\mathrm{Re}\\,S/\\lambda_{++}
    + \\mathrm{Re}\\,D/\\lambda_{--}
    + i(\\mathrm{Im}\\,S/\\lambda_{-+} + \\mathrm{Im}\\,D/\\lambda_{+-})]$, with
    $\\lambda_{\\pm\\pm} = 4\\sin^2$ or $4\\cos^2(\\pi k_1/2N_1)$ plus the same in $k_2$
    ($\\cos^2$ for $N - k$: $4 - 4\\sin^2$ would cancel in float32 near $k = N$).
    The full DCT is never formed, and the twiddles are 1-D constants.
    """
    return _neumann_spectrum_parts(rhs)[1]


def _neumann_spectrum_parts(rhs):
    """`_neumann_spectrum` with its two full-size intermediates: `((reordered rhs, its half
    spectrum), spectrum)`.

    The twiddles are applied on the real and imaginary planes in real arithmetic, which
    XLA-CPU vectorises and its complex multiplies were not: with the same map written on
    `complex64` arrays, `integrate(method="dct")` at 1280x1024 took 13.5-17.0 ms against
    11.1-13.2 ms (medians, `benchmarks/ab_integrate.py`, `ab_integrate_after_*.json` and
    `ab_integrate_twiddle_*.json`). The spectrum is the same to the bit."""
    n1, n2 = rhs.shape
    dt = np.dtype(rhs.dtype)
    r = _reorder(rhs)
    f = jnp.fft.rfft2(r)  # (n1, n2 // 2 + 1)
    fr, fi = jnp.real(f), jnp.imag(f)
    gr, gi = (jnp.roll(jnp.flip(a, 0), 1, axis=0) for a in (fr, fi))  # V(-k1, k2)
    t1 = np.pi * np.arange(n1)[:, None] / (2 * n1)
    t2 = np.pi * np.arange(n2 // 2 + 1)[None, :] / (2 * n2)
    c1r, c1i, c2r, c2i = (jnp.asarray(v.astype(dt)) for t in (t1, t2)
                          for v in (np.cos(t), -np.sin(t)))  # e_j = exp(-i t_j)
    s1, c1, s2, c2 = (jnp.asarray((4 * g(t) ** 2).astype(dt))
                      for t in (t1, t2) for g in (np.sin, np.cos))
    pr, pi = c2r * fr - c2i * fi, c2r * fi + c2i * fr  # p = e2 V(k1, k2)
    qr, qi = c2r * gr - c2i * gi, -(c2r * gi + c2i * gr)  # q = conj(e2 V(-k1, k2))
    ur, ui, vr, vi = pr + qr, pi + qi, pr - qr, pi - qi
    sr, si = c1r * ur - c1i * ui, c1r * ui + c1i * ur  # S = e1 (p + q)
    dr, di = c1r * vr - c1i * vi, c1r * vi + c1i * vr  # D = e1 (p - q)
    lam = s1 + s2  # 0 only at k = (0, 0): the mean, set to 0
    inv_lam = jnp.where(lam > 0, 1 / jnp.where(lam > 0, lam, 1), 0)
    re = sr * inv_lam + dr / (c1 + c2)
    im = si / (c1 + s2) + di / (s1 + c2)
    er, ei = 0.5 * (c1r * c2r - c1i * c2i), -0.5 * (c1r * c2i + c1i * c2r)  # conj(e1 e2) / 2
    return (r, f), lax.complex(er * re - ei * im, er * im + ei * re)


def _neumann_from_spectrum(g, shape):
    """`_neumann_spectrum`'s half spectrum back to the `shape` grid (inverse FFT, reorder)."""
    return _reorder_inverse(jnp.fft.irfft2(g, s=shape))


def _edge_div_of_means(gc, gr):
    """`edge_div` of the edge means of `gc` and `gr`, in one expression: each pixel gains the
    mean step of the edge on its left/top and loses that of the edge on its right/bottom."""
    h, w = gc.shape
    z = jnp.zeros((), gc.dtype)
    gcp = jnp.pad(gc, ((0, 0), (1, 1)), constant_values=z)
    grp = jnp.pad(gr, ((1, 1), (0, 0)), constant_values=z)
    col, row = jnp.arange(w)[None, :], jnp.arange(h)[:, None]
    wc = (col >= 1).astype(gc.dtype) - (col <= w - 2).astype(gc.dtype)
    wr = (row >= 1).astype(gc.dtype) - (row <= h - 2).astype(gc.dtype)
    return 0.5 * (gcp[:, :-2] - gcp[:, 2:] + gc * wc + grp[:-2] - grp[2:] + gr * wr)


def dct_poisson(gc, gr):
    """Least-squares height on the full `(H, W)` grid from per-pixel height steps.

    Solves $\\min_z \\sum_{e=(i,j)} (z_j - z_i - (g_i + g_j)/2)^2$ over every 4-neighbour edge of
    the rectangle: the discrete Poisson equation $L z = \\operatorname{div} g$ with natural
    (Neumann) borders. The Neumann Laplacian is diagonal in the DCT-II basis, with eigenvalues
    $4\\sin^2(\\pi k/2H) + 4\\sin^2(\\pi l/2W)$ (Simchony, Chellappa & Shao, "Direct analytical
    methods for solving Poisson equations in computer vision problems", IEEE TPAMI 12(5), 1990).
    Unlike Frankot–Chellappa it does not assume a periodic surface, so borders are not bent.

    **Arguments:** `gc`, `gr`: `(H, W)` height steps per column and per row.

    **Returns:** `(H, W)` height with mean 0 over the rectangle, dtype of `gc`.

    Called outside a trace, this runs as two programs split at the half spectrum (the comment
    above `_poisson_spectrum` says why); inside a user's `jit` both are traced into the
    caller's program.
    """
    return _poisson_height(_poisson_spectrum(gc, gr), gc.shape, gc.dtype)


# Why two programs: on XLA-CPU the inverse FFT of a spectrum computed in the same program ran
# at about half the speed of the same FFT on a program argument (6.6-7.5 against 3.2-4.3 ms
# at 1280x1024, per-thunk times from `jax.profiler`). Split, `integrate(method="dct")` took
# 21.5-22.7 against 22.4-25.4 ms and FC 16.6-18.8 against 18.5-21.6 ms, results the same to
# float32 rounding (`benchmarks/bench_spectral_split.py`, three runs).
@jax.jit
def _poisson_spectrum(gc, gr):
    return _neumann_spectrum(_edge_div_of_means(gc, gr))


@functools.partial(jax.jit, static_argnums=(1, 2))
def _poisson_height(g, shape, dtype):
    return _neumann_from_spectrum(g, shape).astype(dtype)
