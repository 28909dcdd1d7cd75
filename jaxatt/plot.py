"""Matplotlib figures: the papers' convergence figures, Monte Carlo envelopes, Euler-angle error curves,
tuning curves and paper-number comparisons.

Everything here works on plain numpy data: the *traces* recorded by :func:`jaxatt.montecarlo.simulate` /
:func:`jaxatt.montecarlo.monte_carlo` (dicts of arrays, ``t`` in s, ``(n,)`` for one run or ``(runs, n)`` for
a Monte Carlo), the history of :func:`jaxatt.fit`, or metric dicts. matplotlib is imported only when a
figure is drawn (``import jaxatt`` does not need it). Functions that draw into existing axes take ``ax=`` and
return it; functions that build a whole figure return the ``Figure`` (save it with :func:`save`).

Conventions: times in s, angles in degrees on every axis (``_deg`` keys), errors of the estimate against the
truth. Euler angles are ZYX (roll, pitch, yaw; :func:`jaxatt.so3.matrix_to_euler_zyx`) of the body-to-reference
rotation.

Backend: when pyplot has not been imported yet and ``MPLBACKEND`` is unset (scripts, the CLI), the file-only
"Agg" backend is selected; in a notebook (pyplot already imported, or ``MPLBACKEND`` set by the kernel) the
session's backend is left alone, so figures show inline.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Dict, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

__all__ = [
    "envelope",
    "convergence_plot",
    "convergence_figure",
    "angle_error_plot",
    "euler_error_deg",
    "euler_trace",
    "euler_error_plot",
    "tuning_curves",
    "comparison_plot",
    "save",
]

EULER_NAMES = ("roll", "pitch", "yaw")


def _plt():
    import matplotlib

    if "matplotlib.pyplot" not in sys.modules and not os.environ.get("MPLBACKEND"):
        matplotlib.use("Agg")  # scripts and the CLI only write files
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: Union[str, Path], *, dpi: int = 110, close: bool = False) -> str:
    """Write ``fig`` to ``path`` (PNG unless the suffix says otherwise), creating the folder; returns the path.
    ``close=True`` also closes the figure (scripts that draw many figures). In a multi-process run only process 0
    writes (:func:`jaxatt.io.is_main_process`)."""
    from .io import is_main_process

    path = Path(path)
    if is_main_process():
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=dpi)
    if close:
        _plt().close(fig)
    return str(path)


# ------------------------------------------------------------------------------------------------------
# Monte Carlo envelopes
# ------------------------------------------------------------------------------------------------------
def envelope(
    ax,
    t,
    traces: np.ndarray,
    label: str = "",
    color=None,
    *,
    bands: Sequence[Tuple[float, float]] = ((5, 95), (25, 75)),
    floor: Optional[float] = None,
):
    """Median and percentile bands (default 5-95 % and 25-75 %) of ``traces`` (runs, n) against ``t`` (n,).

    NaN samples are ignored. ``floor`` clips the values from below (for log axes: zeros would vanish).
    Returns the median line.
    """
    traces = np.asarray(traces, float)
    if floor is not None:
        traces = np.maximum(traces, floor)
    pcts = sorted({p for b in bands for p in b} | {50.0})
    q = dict(zip(pcts, np.nanpercentile(traces, pcts, axis=0)))
    for i, (lo, hi) in enumerate(bands):
        ax.fill_between(t, q[lo], q[hi], alpha=0.18 + 0.15 * i, color=color, lw=0)
    (line,) = ax.plot(t, q[50.0], color=color, label=label)
    return line


def _tidy_log_axis(ax):
    """On a log axis spanning less than a decade, label the ticks as plain numbers (not 2 x 10^0)."""
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    lo, hi = ax.get_ylim()
    if lo > 0 and hi / lo < 10.0:
        ax.yaxis.set_major_formatter(ScalarFormatter())
        ax.yaxis.set_minor_formatter(ScalarFormatter())
        if hi / lo > 3.0:
            ax.yaxis.set_minor_formatter(NullFormatter())


def _band_label(bands) -> str:
    return ", ".join(f"{lo:g}-{hi:g} %" for lo, hi in bands)


# ------------------------------------------------------------------------------------------------------
# Convergence figures (batista2019-ges Figs. 2-5, batista2019-so3 Figs. 1-4 style)
# ------------------------------------------------------------------------------------------------------
def convergence_plot(
    trace: Dict[str, np.ndarray],
    *,
    title: str = "",
    transient_s: float = 300.0,
    steady_from_s: float = 2400.0,
    panels: Optional[Dict[str, str]] = None,
    mc_traces: Optional[Dict[str, np.ndarray]] = None,
):
    """The papers' convergence figures from one run's trace; returns the Figure.

    ``panels`` maps trace keys to axis labels (with units) for the initial-convergence panels (log scale,
    first ``transient_s`` seconds; default every ``norm_*`` key); the last panel is the angle error after
    ``steady_from_s`` (batista2019-ges Fig. 5). With ``mc_traces`` (dict of (runs, n) arrays, as
    :class:`jaxatt.montecarlo.MonteCarloResult.traces`) every panel also shows the Monte Carlo median and
    5-95 % / 25-75 % bands.
    """
    plt = _plt()
    panels = panels or {k: k for k in trace if k.startswith("norm_")}
    n = len(panels) + 1
    fig, axes = plt.subplots(n, 1, figsize=(7, 1.9 * n + 0.4), constrained_layout=True)
    axes = np.atleast_1d(axes)
    t = np.asarray(trace["t"])
    early = t <= transient_s
    tm = None if mc_traces is None else np.asarray(mc_traces["t"])[0]
    run_style = dict(color="0.25", lw=0.5) if tm is not None else dict(color="tab:blue", lw=0.7)
    for ax, (k, label) in zip(axes, panels.items()):
        ax.semilogy(t[early], np.maximum(np.asarray(trace[k])[early], 1e-300), label="run 0", **run_style)
        if tm is not None and mc_traces is not None and k in mc_traces:
            sel = tm <= transient_s
            envelope(
                ax,
                tm[sel],
                np.asarray(mc_traces[k])[:, sel],
                color="tab:blue",
                floor=1e-300,
                label="Monte Carlo median",
            )
        ax.set_ylabel(label)
        ax.set_xlim(0.0, min(transient_s, float(t[-1])))
        ax.grid(True, which="both", alpha=0.3)
        _tidy_log_axis(ax)
    if len(panels):
        axes[len(panels) - 1].set_xlabel("t (s)")
        axes[0].legend(loc="upper right", fontsize=7)
    ax = axes[-1]
    late = t >= steady_from_s
    late_vals = np.asarray(trace["angle_error_deg"])[late]
    ax.plot(t[late], late_vals, label="run 0", **run_style)
    top = float(np.nanmax(late_vals)) if late_vals.size else 1.0
    if tm is not None and mc_traces is not None:
        sel = tm >= steady_from_s
        mc_late = np.asarray(mc_traces["angle_error_deg"])[:, sel]
        envelope(
            ax,
            tm[sel],
            mc_late,
            color="tab:blue",
            label=f"Monte Carlo median, {_band_label(((5, 95), (25, 75)))} ({len(mc_traces['t'])} runs)",
        )
        top = max(top, float(np.nanmax(np.nanpercentile(mc_late, 95, axis=0)))) if mc_late.size else top
    ax.set_ylabel("angle error (deg)")
    ax.set_xlabel("t (s)")
    ax.set_ylim(0.0, 1.08 * top if top > 0 else 1.0)
    ax.legend(loc="upper right", fontsize=7)
    ax.grid(True, alpha=0.3)
    if title:
        fig.suptitle(title)
    return fig


def convergence_figure(
    trace: Dict[str, np.ndarray],
    path: str,
    *,
    title: str = "",
    transient_s: float = 300.0,
    steady_from_s: float = 2400.0,
    panels: Optional[Dict[str, str]] = None,
    mc_traces: Optional[Dict[str, np.ndarray]] = None,
):
    """:func:`convergence_plot` written to ``path`` (PNG) and closed; returns ``path`` (used by the CLI's
    ``--plot``)."""
    fig = convergence_plot(
        trace, title=title, transient_s=transient_s, steady_from_s=steady_from_s, panels=panels, mc_traces=mc_traces
    )
    save(fig, path, close=True)
    return path


# ------------------------------------------------------------------------------------------------------
# Angle error over time
# ------------------------------------------------------------------------------------------------------
def angle_error_plot(
    trace: Optional[Mapping[str, np.ndarray]] = None,
    mc_traces: Optional[Mapping[str, np.ndarray]] = None,
    *,
    ax=None,
    key: str = "angle_error_deg",
    logy: bool = True,
    t_range: Optional[Tuple[float, float]] = None,
    label: str = "run 0",
    mc_label: Optional[str] = None,
    color=None,
    title: str = "",
):
    """Rotation-angle error (deg) against time: one run (``trace``: dict with ``t`` and ``key``, (n,)) and/or
    the Monte Carlo median and 5-95 % / 25-75 % bands (``mc_traces``: (runs, n) arrays). Returns the Axes."""
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(7, 3.2), constrained_layout=True)
    floor = 1e-6 if logy else None
    if mc_traces is not None:
        tm = np.asarray(mc_traces["t"])[0]
        vals = np.asarray(mc_traces[key])
        sel = _range(tm, t_range)
        envelope(
            ax,
            tm[sel],
            vals[:, sel],
            color=color or "tab:blue",
            floor=floor,
            label=mc_label or f"median, {_band_label(((5, 95), (25, 75)))} ({vals.shape[0]} runs)",
        )
    if trace is not None:
        t = np.asarray(trace["t"])
        v = np.asarray(trace[key], float)
        sel = _range(t, t_range)
        v = np.maximum(v, floor) if floor else v
        ax.plot(t[sel], v[sel], color="k" if mc_traces is not None else color, lw=0.7, label=label)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("angle error (deg)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    return ax


def _range(t, t_range):
    if t_range is None:
        return np.ones(np.shape(t), bool)
    return (t >= t_range[0]) & (t <= t_range[1])


# ------------------------------------------------------------------------------------------------------
# Euler-angle errors
# ------------------------------------------------------------------------------------------------------
def _euler_error_rad(r_true, r_est):
    import jax.numpy as jnp

    from . import so3

    return jnp.stack(so3.euler_error_zyx(r_true, r_est), axis=-1)


def euler_error_deg(r_true, r_est) -> np.ndarray:
    """ZYX Euler-angle errors (deg), estimate minus truth wrapped to (-180, 180], shape (..., 3) =
    (roll, pitch, yaw), of body-to-reference rotations ``r_true``, ``r_est`` (..., 3, 3). Undefined at
    pitch = +-90 deg (gimbal lock)."""
    return np.rad2deg(np.asarray(_euler_error_rad(r_true, r_est)))


def euler_trace(truth, out, errors, angle_deg) -> Dict[str, object]:
    """A ``trace_fn`` for :func:`jaxatt.montecarlo.simulate` / ``monte_carlo``: time (s), rotation-angle error
    (deg) and the ZYX Euler-angle errors ``euler_error_deg`` (3,) (roll, pitch, yaw; estimate minus truth,
    wrapped). Works for any observer (its estimate read as everywhere: :func:`jaxatt.engine.estimate_r`) and any
    scenario whose truth has ``t`` and ``r``."""
    import jax.numpy as jnp

    from . import engine

    r = engine.estimate_r(out)
    d = _euler_error_rad(truth.r.astype(r.dtype), r)
    return {"t": truth.t, "angle_error_deg": angle_deg, "euler_error_deg": jnp.rad2deg(d)}


def euler_error_plot(
    trace: Optional[Mapping[str, np.ndarray]] = None,
    mc_traces: Optional[Mapping[str, np.ndarray]] = None,
    *,
    key: str = "euler_error_deg",
    t_range: Optional[Tuple[float, float]] = None,
    band: Tuple[float, float] = (5, 95),
    ylim: Optional[Tuple[float, float]] = None,
    title: str = "",
    axes=None,
):
    """Roll, pitch and yaw errors (deg) against time, one panel each; returns the Figure.

    ``trace``: one run, dict with ``t`` (n,) and ``key`` (n, 3) (e.g. from :func:`euler_trace`, or
    ``{"t": t, "euler_error_deg": euler_error_deg(r_true, r_est)}`` for a log). ``mc_traces``: Monte Carlo
    traces, ``t`` (runs, n) and ``key`` (runs, n, 3): the mean over runs and the ``band`` percentiles are drawn.
    ``t_range`` selects a time window (e.g. the steady state, where the errors are small).
    """
    plt = _plt()
    if axes is None:
        fig, axes = plt.subplots(3, 1, figsize=(7, 5.6), sharex=True, constrained_layout=True)
    else:
        fig = axes[0].figure
    if mc_traces is not None:
        tm = np.asarray(mc_traces["t"])[0]
        v = np.asarray(mc_traces[key], float)
        sel = _range(tm, t_range)
        lo, hi = np.nanpercentile(v[:, sel], band, axis=0)
        mean = np.nanmean(v[:, sel], axis=0)
        for i, ax in enumerate(axes):
            ax.fill_between(
                tm[sel],
                lo[:, i],
                hi[:, i],
                color="tab:blue",
                alpha=0.25,
                lw=0,
                label=f"{band[0]:g}-{band[1]:g} % ({v.shape[0]} runs)",
            )
            ax.plot(tm[sel], mean[:, i], color="tab:blue", lw=1.0, label="Monte Carlo mean")
    if trace is not None:
        t = np.asarray(trace["t"])
        v = np.asarray(trace[key], float)
        sel = _range(t, t_range)
        for i, ax in enumerate(axes):
            ax.plot(
                t[sel],
                v[sel, i],
                color="k" if mc_traces is not None else f"C{i}",
                lw=0.7,
                label="run 0" if mc_traces is not None else None,
            )
    for i, ax in enumerate(axes):
        ax.set_ylabel(f"{EULER_NAMES[i]} error (deg)")
        ax.axhline(0.0, color="0.5", lw=0.5)
        ax.grid(True, alpha=0.3)
        if ylim is not None:
            ax.set_ylim(*ylim)
    axes[-1].set_xlabel("t (s)")
    if mc_traces is not None:
        axes[0].legend(loc="upper right", fontsize=7)
    if title:
        fig.suptitle(title)
    return fig


# ------------------------------------------------------------------------------------------------------
# Tuning curves
# ------------------------------------------------------------------------------------------------------
def _history_columns(history) -> Dict[str, np.ndarray]:
    """{step, train_<m>, val_<m>, ...} as float arrays (NaN where a step has no value) from a list of per-step
    dicts (:attr:`jaxatt.fitting.fitter.FitResult.history`) or a dict of equal-length lists."""
    if isinstance(history, Mapping):
        cols = {k: np.asarray(v, float) for k, v in history.items()}
        if "step" not in cols:
            n = len(next(iter(cols.values())))
            cols["step"] = np.arange(n, dtype=float)
        return cols
    keys = sorted({k for h in history for k in h})
    return {k: np.array([float(h[k]) if h.get(k) is not None else np.nan for h in history]) for k in keys}


def tuning_curves(
    history, *, ax=None, metric: str = "loss", logy: bool = True, title: str = "", ylabel: Optional[str] = None
):
    """Training and held-out (validation) curves against the optimizer step; returns the Axes.

    ``history``: :attr:`jaxatt.fitting.fitter.FitResult.history` (a list of dicts with ``step``, ``train_loss``,
    ``val_loss``, ``train_metric``, ``val_metric``: the fit's metric, the mean angle error in deg on a study, the
    mean total RMSE in deg on BROAD trials) or a dict of lists with the same keys. ``metric`` picks
    ``train_<metric>`` / ``val_<metric>`` ("loss" or "metric"). The best held-out step is marked. The training
    value recorded at step k is that of the params before update k, so it is drawn at k - 1, beside the held-out
    value of the same params.
    """
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(6.5, 3.4), constrained_layout=True)
    cols = _history_columns(history)
    step = cols["step"]
    tr, va = cols.get(f"train_{metric}"), cols.get(f"val_{metric}")
    if tr is None and va is None:
        raise ValueError(f"metric {metric!r}: the history has no train_{metric} / val_{metric} (keys: {sorted(cols)})")
    if tr is not None and np.any(np.isfinite(tr)):
        ok = np.isfinite(tr)
        ax.plot(step[ok] - 1, tr[ok], "-o", ms=3, color="tab:blue", label="training runs (minibatch)")
    if va is not None and np.any(np.isfinite(va)):
        ok = np.isfinite(va)
        ax.plot(step[ok], va[ok], "-s", ms=4, color="tab:orange", label="held-out runs")
        i = int(np.nanargmin(np.where(ok, va, np.nan)))
        ax.plot(step[i], va[i], "*", ms=13, color="tab:red", label=f"best held-out (step {int(step[i])})")
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel("optimizer step")
    ax.set_ylabel(ylabel or {"loss": "loss", "metric": "error (deg)"}.get(metric, metric))
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    return ax


# ------------------------------------------------------------------------------------------------------
# Comparison with published numbers
# ------------------------------------------------------------------------------------------------------
def comparison_plot(
    ours: Mapping[str, float],
    paper: Mapping[str, float],
    *,
    labels: Optional[Mapping[str, str]] = None,
    ax=None,
    title: str = "",
    ours_label: str = "jaxatt",
):
    """Ratio ours / published for every key of ``paper`` that ``ours`` has (horizontal bars, log scale,
    1 = agreement), each bar annotated with both numbers; returns the Axes."""
    plt = _plt()
    keys = [k for k in paper if k in ours and paper[k]]
    if ax is None:
        _, ax = plt.subplots(figsize=(7, 0.45 * len(keys) + 1.3), constrained_layout=True)
    ratio = np.array([float(ours[k]) / float(paper[k]) for k in keys])
    y = np.arange(len(keys))[::-1]
    colors = ["tab:green" if 0.8 <= r <= 1.25 else "tab:orange" if 0.5 <= r <= 2 else "tab:red" for r in ratio]
    ax.barh(y, np.log10(ratio), color=colors, height=0.6)
    ax.axvline(0.0, color="k", lw=0.8)
    lim = max(0.5, float(np.max(np.abs(np.log10(ratio)))) * 1.6) if len(keys) else 0.5
    ax.set_xlim(-lim, lim)
    ticks = [t for t in (0.1, 0.2, 0.5, 1, 2, 5, 10) if abs(np.log10(t)) <= lim]
    ax.set_xticks(np.log10(ticks))
    ax.set_xticklabels([f"{t:g}" for t in ticks])
    ax.set_yticks(y)
    ax.set_yticklabels([(labels or {}).get(k, k) for k in keys], fontsize=8)
    for yi, k, r in zip(y, keys, ratio):
        x = np.log10(r)
        ax.text(
            x + (0.02 if x >= 0 else -0.02) * lim * 2,
            yi,
            f"{float(ours[k]):.3g} vs {float(paper[k]):.3g}",
            va="center",
            ha="left" if x >= 0 else "right",
            fontsize=7,
        )
    ax.set_xlabel(f"{ours_label} / published (log scale)")
    ax.grid(True, axis="x", alpha=0.3)
    if title:
        ax.set_title(title)
    return ax
