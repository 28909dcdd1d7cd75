"""Metrics accumulated while a scan runs (nothing per-step is stored).

* :class:`RunningStats`: Welford mean / variance per element, over the steps whose weight is 1.
* :class:`WindowMetrics`: per-run Table-2 style statistics of named error vectors and the rotation-angle
  error over a steady-state window [window_start, end], plus the values at the last step.
* :class:`WindowMoments`: per-run mean absolute error and RMS of named errors over several named time windows
  (e.g. the transient 0-200 s and steady-state 300-500 s windows of sensors2020-interconnected-observer).
"""

from __future__ import annotations

from typing import Dict, NamedTuple

import jax
import jax.numpy as jnp

from . import so3

__all__ = [
    "RunningStats",
    "stats_init",
    "stats_update",
    "stats_std",
    "WindowMetrics",
    "window_init",
    "window_update",
    "window_summary",
    "angle_error_deg",
    "WindowMoments",
    "moments_init",
    "moments_update",
    "moments_summary",
    "check_windows",
]


class RunningStats(NamedTuple):
    """Welford accumulator: count n, running mean and sum of squared deviations m2 (per element)."""

    n: jax.Array
    mean: jax.Array
    m2: jax.Array


def stats_init(shape, dtype) -> RunningStats:
    return RunningStats(jnp.zeros((), dtype), jnp.zeros(shape, dtype), jnp.zeros(shape, dtype))


def stats_update(s: RunningStats, x, weight) -> RunningStats:
    """Add ``x`` when ``weight`` is 1 (0 leaves ``s`` unchanged). Welford's update with x - mean_new written as
    delta (1 - weight / n): ``x`` is read once, so m2 cannot go negative when XLA rounds two reads of ``x``
    differently (a one-sample window's std was NaN in float64 and 1e-5 deg in float32, 0 in a batch of 3)."""
    n = s.n + weight
    delta = x - s.mean
    frac = weight / jnp.maximum(n, 1.0)
    mean = s.mean + frac * delta
    m2 = s.m2 + weight * (1.0 - frac) * delta * delta
    return RunningStats(n, mean, m2)


def stats_std(s: RunningStats):
    """Population standard deviation per element."""
    return jnp.sqrt(jnp.maximum(s.m2, 0.0) / jnp.maximum(s.n, 1.0))


def angle_error_deg(r_true, r_est):
    """Rotation-angle error (deg) of R_true^T R_est (eq. 23 of batista2019-ges)."""
    return jnp.rad2deg(so3.angle_error(r_true, r_est))


class WindowMetrics(NamedTuple):
    """Per-run accumulators: stats of each named error over the window, angle error (deg) sum / max over
    the window, and the last values."""

    errors: Dict[str, RunningStats]
    angle_sum: jax.Array
    angle_max: jax.Array
    count: jax.Array  # type: ignore[assignment]  # public field name; shadows tuple.count, as intended
    angle_last: jax.Array
    errors_last: Dict[str, jax.Array]


def window_init(error_shapes: Dict[str, tuple], dtype) -> WindowMetrics:
    z = jnp.zeros((), dtype)
    return WindowMetrics(
        {k: stats_init(s, dtype) for k, s in error_shapes.items()},
        z,
        z,
        z,
        z,
        {k: jnp.zeros(s, dtype) for k, s in error_shapes.items()},
    )


def window_update(acc: WindowMetrics, errors: Dict[str, jax.Array], angle_deg, in_window) -> WindowMetrics:
    w = in_window.astype(acc.angle_sum.dtype)
    return WindowMetrics(
        {k: stats_update(acc.errors[k], errors[k].astype(acc.angle_sum.dtype), w) for k in acc.errors},
        acc.angle_sum + w * angle_deg,
        jnp.maximum(acc.angle_max, w * angle_deg),
        acc.count + w,
        angle_deg.astype(acc.angle_sum.dtype),
        {k: errors[k].astype(acc.angle_sum.dtype) for k in acc.errors},
    )


def window_summary(acc: WindowMetrics) -> Dict[str, jax.Array]:
    """Per-run numbers: mean / max angle error over the window (deg), final angle error (deg), and for each
    named error the standard deviation averaged over its elements (Table 2 of batista2019-ges) and its
    final norm."""
    out = {
        "mean_angle_error_deg": acc.angle_sum / jnp.maximum(acc.count, 1.0),
        "max_angle_error_deg": acc.angle_max,
        "final_angle_error_deg": acc.angle_last,
    }
    for k, s in acc.errors.items():
        out[f"std_{k}"] = jnp.mean(stats_std(s))
        out[f"final_norm_{k}"] = jnp.sqrt(jnp.sum(acc.errors_last[k] ** 2))
    return out


# ------------------------------------------------------------------------------------------------------
# MAE / RMSE of named errors over named time windows
# ------------------------------------------------------------------------------------------------------
def check_windows(windows) -> tuple:
    """Validate and normalise ``windows`` = ((name, start_s, end_s), ...) into a hashable tuple."""
    out = []
    for w in windows:
        try:
            name, start, end = w
        except (TypeError, ValueError) as e:
            raise ValueError(f"each window must be (name, start_s, end_s), got {w!r}") from e
        start, end = float(start), float(end)
        if not isinstance(name, str) or not name.isidentifier():
            raise ValueError(f"window names must be identifiers, got {name!r}")
        if not (start == start and end == end) or end < start:  # NaN or reversed
            raise ValueError(f"window {name!r} must have start <= end, got ({start}, {end})")
        out.append((name, start, end))
    if len({w[0] for w in out}) != len(out):
        raise ValueError(f"window names must be unique, got {[w[0] for w in out]}")
    return tuple(out)


class WindowMoments(NamedTuple):
    """Per-run sums over each window (leading axis = window): sample count, sum |e| and sum e^2 per element."""

    count: jax.Array  # type: ignore[assignment]  # public field name; shadows tuple.count, as intended
    sum_abs: Dict[str, jax.Array]
    sum_sq: Dict[str, jax.Array]


def moments_init(error_shapes: Dict[str, tuple], n_windows: int, dtype) -> WindowMoments:
    return WindowMoments(
        jnp.zeros((n_windows,), dtype),
        {k: jnp.zeros((n_windows,) + tuple(s), dtype) for k, s in error_shapes.items()},
        {k: jnp.zeros((n_windows,) + tuple(s), dtype) for k, s in error_shapes.items()},
    )


def moments_update(acc: WindowMoments, errors: Dict[str, jax.Array], t, windows, tol) -> WindowMoments:
    """Add the errors at sample time ``t`` to every window with start - tol <= t <= end + tol."""
    dtype = acc.count.dtype
    starts = jnp.asarray([w[1] for w in windows], dtype)
    ends = jnp.asarray([w[2] for w in windows], dtype)
    t = jnp.asarray(t, dtype)
    w = ((t >= starts - tol) & (t <= ends + tol)).astype(dtype)  # (n_windows,)

    def add(total, e, f):
        e = f(e.astype(dtype))
        return total + w.reshape((-1,) + (1,) * e.ndim) * e[None]

    return WindowMoments(
        acc.count + w,
        {k: add(acc.sum_abs[k], errors[k], jnp.abs) for k in acc.sum_abs},
        {k: add(acc.sum_sq[k], errors[k], jnp.square) for k in acc.sum_sq},
    )


def moments_summary(acc: WindowMoments, windows) -> Dict[str, jax.Array]:
    """Per-run ``mae_{window}_{error}`` and ``rmse_{window}_{error}`` (shape of the error; NaN for an empty
    window)."""
    out = {}
    for i, (name, _, _) in enumerate(windows):
        n = acc.count[i]
        inv = jnp.where(n > 0, 1.0 / jnp.maximum(n, 1.0), jnp.nan)
        for k in acc.sum_abs:
            out[f"mae_{name}_{k}"] = acc.sum_abs[k][i] * inv
            out[f"rmse_{name}_{k}"] = jnp.sqrt(acc.sum_sq[k][i] * inv)
    return out
