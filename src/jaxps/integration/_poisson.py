"""Poisson integration on the whole rectangle with Neumann borders, solved by a DCT."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.scipy.fft import dctn, idctn

from ._grid import edge_div

__all__ = ["dct_poisson"]


@jax.jit
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
    """
    h, w = gc.shape
    dt = gc.dtype
    gh = (gc[:, 1:] + gc[:, :-1]) / 2
    gv = (gr[1:, :] + gr[:-1, :]) / 2
    rhs = edge_div(gh, gv)
    kr = jnp.arange(h, dtype=dt)[:, None]
    kc = jnp.arange(w, dtype=dt)[None, :]
    four = jnp.asarray(4, dt)
    lam = four * jnp.sin(jnp.pi * kr / (2 * h)) ** 2 + four * jnp.sin(jnp.pi * kc / (2 * w)) ** 2
    one = jnp.ones((), dt)
    coef = dctn(rhs, type=2, norm="ortho")
    coef = jnp.where(lam > 0, coef / jnp.where(lam > 0, lam, one), 0)
    return idctn(coef, type=2, norm="ortho").astype(dt)
