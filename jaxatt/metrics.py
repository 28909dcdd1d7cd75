"""Metrics accumulated while a scan runs (nothing per-step is stored).

* :class:`RunningStats`: Welford mean / variance per element, over the steps whose weight is 1.
* :class:`WindowMetrics`: per-run Table-2 style statistics of named error vectors and the rotation-angle
  error over a steady-state window [window_start, end], plus the values at the last step.
"""
from __future__ import annotations

from typing import Dict, NamedTuple

import jax
import jax.numpy as jnp

from . import so3

__all__ = ["RunningStats", "stats_init", "stats_update", "stats_std", "WindowMetrics", "window_init",
           "window_update", "window_summary", "angle_error_deg"]


class RunningStats(NamedTuple):
    """Welford accumulator: count n, running mean and sum of squared deviations m2 (per element)."""

    n: jax.Array
    mean: jax.Array
    m2: jax.Array


def stats_init(shape, dtype) -> RunningStats:
    return RunningStats(jnp.zeros((), dtype), jnp.zeros(shape, dtype), jnp.zeros(shape, dtype))


def stats_update(s: RunningStats, x, weight) -> RunningStats:
    """Add ``x`` when ``weight`` is 1 (0 leaves ``s`` unchanged)."""
    n = s.n + weight
    delta = x - s.mean
    mean = s.mean + weight * delta / jnp.maximum(n, 1.0)
    m2 = s.m2 + weight * delta * (x - mean)
    return RunningStats(n, mean, m2)


def stats_std(s: RunningStats):
    """Population standard deviation per element."""
    return jnp.sqrt(s.m2 / jnp.maximum(s.n, 1.0))


def angle_error_deg(r_true, r_est):
    """Rotation-angle error (deg) of R_true^T R_est (eq. 23 of batista2019-ges)."""
    return jnp.rad2deg(so3.angle_error(r_true, r_est))


class WindowMetrics(NamedTuple):
    """Per-run accumulators: stats of each named error over the window, angle error (deg) sum / max over
    the window, and the last values."""

    errors: Dict[str, RunningStats]
    angle_sum: jax.Array
    angle_max: jax.Array
    count: jax.Array
    angle_last: jax.Array
    errors_last: Dict[str, jax.Array]


def window_init(error_shapes: Dict[str, tuple], dtype) -> WindowMetrics:
    z = jnp.zeros((), dtype)
    return WindowMetrics(
        {k: stats_init(s, dtype) for k, s in error_shapes.items()},
        z, z, z, z, {k: jnp.zeros(s, dtype) for k, s in error_shapes.items()},
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
