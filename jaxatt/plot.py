"""Matplotlib figures (the papers' convergence figures and Monte Carlo envelopes)."""
from __future__ import annotations

from typing import Dict, Optional

import numpy as np

__all__ = ["convergence_figure", "envelope"]


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def envelope(ax, t, traces: np.ndarray, label: str = "", color=None):
    """Median and 5-95 / 25-75 percentile bands of ``traces`` (runs, n) against ``t`` (n,)."""
    q = np.nanpercentile(traces, [5, 25, 50, 75, 95], axis=0)
    ax.fill_between(t, q[0], q[4], alpha=0.2, color=color, lw=0)
    ax.fill_between(t, q[1], q[3], alpha=0.35, color=color, lw=0)
    ax.plot(t, q[2], color=color, label=label)


def convergence_figure(trace: Dict[str, np.ndarray], path: str, *, title: str = "", transient_s: float = 300.0,
                       steady_from_s: float = 2400.0, panels: Optional[Dict[str, str]] = None,
                       mc_traces: Optional[Dict[str, np.ndarray]] = None):
    """Figures in the style of batista2019-ges Figs. 2-5 from one run's trace.

    ``panels`` maps trace keys to axis labels for the initial-convergence panels (log scale, first
    ``transient_s`` seconds); the last panel is the angle error after ``steady_from_s`` (Fig. 5), with the
    Monte Carlo envelope when ``mc_traces`` (runs x n) is given.
    """
    plt = _plt()
    panels = panels or {k: k for k in trace if k.startswith("norm_")}
    n = len(panels) + 1
    fig, axes = plt.subplots(n, 1, figsize=(7, 2.1 * n), constrained_layout=True)
    t = trace["t"]
    early = t <= transient_s
    for ax, (k, label) in zip(axes, panels.items()):
        ax.semilogy(t[early], np.maximum(trace[k][early], 1e-300))
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[len(panels) - 1].set_xlabel("t (s)")
    ax = axes[-1]
    late = t >= steady_from_s
    if mc_traces is not None:
        tm = mc_traces["t"][0]
        sel = tm >= steady_from_s
        envelope(ax, tm[sel], mc_traces["angle_error_deg"][:, sel], label="Monte Carlo median, 25-75 %, 5-95 %",
                 color="tab:blue")
    ax.plot(t[late], trace["angle_error_deg"][late], color="k", lw=0.6, label="run 0")
    ax.set_ylabel("angle error (deg)")
    ax.set_xlabel("t (s)")
    ax.legend(loc="upper right", fontsize=7)
    ax.grid(True, alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
