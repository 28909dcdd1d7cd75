"""Piecewise-constant gain schedules (Table 1 of both Batista et al. papers): a Params field ``switch_times``
(n-1,) s and gains with one value per interval [0, t_1), [t_1, t_2), ..., [t_{n-1}, inf).

:func:`value_at` evaluates a schedule inside an observer step; :func:`refine` adds switch times without changing
the gains as functions of time (so a tuner can vary the gains where a paper keeps them constant);
:func:`mask` / :func:`mask_from` choose which intervals a tuner may change.
"""

from __future__ import annotations

from typing import Sequence

import jax.numpy as jnp
import numpy as np

from .types import shown

__all__ = ["value_at", "refine", "mask", "mask_from", "check"]


def value_at(switch_times, t, *gains):
    """The value of each schedule ``gains`` (n, ...) at time ``t`` (s): interval i holds for
    switch_times[i-1] <= t < switch_times[i]."""
    i = jnp.sum(jnp.asarray(t)[..., None] >= switch_times, axis=-1)
    return tuple(g[i] for g in gains)


def check(switch_times, gains: dict, why: str = "") -> None:
    """ValueError naming the first problem: gains (name -> (n,) array) of different lengths or not finite and
    positive, switch_times not (n-1,) finite and increasing. ``why``: the theorem that needs positive gains."""
    st = np.asarray(switch_times, float)
    arrays = {k: np.asarray(v, float) for k, v in gains.items()}
    shapes = {k: v.shape for k, v in arrays.items()}
    n = next(iter(arrays.values())).shape
    if any(v.ndim != 1 or v.shape != n for v in arrays.values()) or st.shape != (n[0] - 1,):
        raise ValueError(f"{', '.join(arrays)} must be (n,) and switch_times (n-1,); got {shapes}, {st.shape}")
    for name, v in arrays.items():
        if not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise ValueError(f"{name} must be finite and positive{f' ({why})' if why else ''}, got {shown(v)}")
    if not np.all(np.isfinite(st)) or np.any(np.diff(st) <= 0):
        raise ValueError(f"switch_times must be finite and increasing, got {shown(st)}")


def mask(n_intervals: int, tunable: Sequence[int]) -> np.ndarray:
    """Boolean mask (True = tunable) over the ``n_intervals`` values of a :class:`Schedule`; negative
    indices count from the end (``[-1]`` tunes the last interval only, i.e. the steady-state gain)."""
    m = np.zeros(n_intervals, bool)
    m[np.asarray(list(tunable), int)] = True
    return m


def mask_from(switch_times: Sequence[float], t_from: float) -> np.ndarray:
    """Boolean mask (True = tunable) of the schedule intervals that start at or after ``t_from`` s (the first
    interval starts at 0 s); earlier intervals keep their values, e.g. a paper's start-up schedule."""
    starts = np.concatenate([[0.0], np.asarray(switch_times, float)])
    return starts >= float(t_from)


def refine(params, times: Sequence[float], fields: Sequence[str], *, times_field: str = "switch_times"):
    """``params`` with extra switch times inserted into its piecewise-constant gain schedules, the gains
    unchanged as functions of time (each new interval copies the value in force there).

    Use it to give a tuner more freedom than the paper's schedule while starting from exactly the paper's
    observer: batista2019-ges Table 1 stops switching at 720 s; ``refine(p, [1200, 1800, 2400],
    ["alpha1", "alpha2"])`` lets the gains keep changing after it.

    Args:
        params: a Params NamedTuple with ``times_field`` (n-1,) s and schedule fields of shape (n, ...).
        times: new switch times, s (finite; ones already present are ignored).
        fields: the schedule fields, each of shape (n, ...) (the gains declared with the "schedule" constraint).
    """
    st = np.asarray(getattr(params, times_field), float)
    new = np.asarray(list(times), float)
    if new.ndim != 1 or not np.all(np.isfinite(new)):
        raise ValueError(f"refine: times must be finite numbers, got {times!r}")
    merged = np.unique(np.concatenate([st, new]))
    n = st.shape[0] + 1
    # interval of the old schedule in force on each new interval (gains[i] hold on [st[i-1], st[i]))
    starts = np.concatenate([[-np.inf], merged])
    idx = np.searchsorted(st, starts, side="right")
    out = {times_field: jnp.asarray(merged, jnp.asarray(getattr(params, times_field)).dtype)}
    for f in fields:
        v = jnp.asarray(getattr(params, f))
        if v.ndim < 1 or v.shape[0] != n:
            raise ValueError(f"refine: {f} has shape {v.shape}, want ({n}, ...) for {n - 1} switch times")
        out[f] = v[jnp.asarray(idx)]
    return params._replace(**out)
