"""Figures of the shading checks (matplotlib, imported when a figure is drawn)."""

from __future__ import annotations

import numpy as np

from ._lambertian_check import LambertianCheck

__all__ = ["plot_lambertian_check"]


def plot_lambertian_check(result: LambertianCheck, *, ax=None, title: str | None = None):
    """Draw a `LambertianCheck` like Hansen et al. 2010, Fig. 7.

    Binned mean $I/\\rho$ with a one-sd band, $\\cos\\theta$, the Oren–Nayar curve when the
    check was given `sigma`, and the 60-degree line. **Returns:** the matplotlib `Figure`.
    """
    import matplotlib.pyplot as plt

    if ax is None:
        fig, ax = plt.subplots(figsize=(5, 3.6))
    else:
        fig = ax.figure
    t, m, s = result.theta_deg, result.mean, result.sd
    ax.fill_between(t, m - s, m + s, color="tab:blue", alpha=0.25, lw=0, label="±1 sd")
    ax.plot(t, m, color="tab:blue", lw=1.5, label="mean I/ρ")
    ax.plot(t, np.cos(np.radians(t)), "k--", lw=1, label="cos θ (Lambert)")
    if result.oren_nayar is not None:
        ax.plot(t, result.oren_nayar, color="tab:red", lw=1.2,
                label=f"Oren–Nayar σ={result.sigma:.2f}")
    ax.axvline(60, color="grey", lw=0.8, ls=":")
    ax.set_xlim(0, 90)
    ax.set_ylim(0, 1.3)
    ax.set_xlabel("θ (degrees)")
    ax.set_ylabel("I / ρ")
    default = f"RMS vs cos: {result.rms_60:.3f} (θ≤60°), {result.rms_all:.3f} (all)"
    ax.set_title(title or default, fontsize=9)
    ax.legend(fontsize=7, loc="upper right")
    return fig
