"""Losses for tuning gains on simulated seeds, differentiable through the whole simulation (the one scan,
:mod:`jaxatt.engine`).

* :class:`LossSpec` / :func:`loss_spec`: a pointwise error ``e(t)`` (``"angle_sq"``: squared rotation angle of
  R^T R^ in deg^2; ``"angle"``: the angle in deg; ``"chordal"``: tr(I - R^T R^) = 2 (1 - cos angle);
  ``"euler_sq"``: sum of squared wrapped ZYX roll/pitch/yaw errors in deg^2, for AHRS observers;
  ``"innovation_nll"``: the filter's negative log-likelihood of its innovations (nats per step, ``Out.nll`` of
  Kalman filters such as the MEKF; the maximum-likelihood loss of noise parameters); or any hashable
  ``fn(truth, out) -> scalar``) averaged over time windows, weighted (e.g. transient and steady state), then
  averaged over runs.
* :func:`make_loss_fn`: ``loss(scenario, params, keys) -> (loss, aux)``, the same fused simulator + observer scan
  as :func:`jaxatt.montecarlo.monte_carlo` (same noise stream: run k of seed s is the same run in both),
  differentiable with ``jax.grad`` in the params. For long horizons the scan is split into segments wrapped in
  ``jax.checkpoint``: reverse mode keeps one carry per segment and recomputes a segment's steps during the
  backward pass, so memory grows like T / c + c (about sqrt(T) with the default c ~ sqrt(T)) instead of T, for one
  more forward pass of compute.

The loss on recorded trials (the BROAD metric) is :data:`jaxatt.data.broad.METRIC_REDUCER`, used by
:mod:`jaxatt.fitting.fitter`.

Conventions: rotations map body to reference (v_ref = R v_body); angles in degrees (``_deg``); times in s.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Callable, Dict, NamedTuple, Optional, Tuple, Union

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec

from .. import engine, so3
from .. import metrics as M
from .. import sharding as _sharding
from ..types import Observer

__all__ = ["LossSpec", "loss_spec", "POINTWISE", "POINTWISE_UNITS", "loss_reducer", "make_loss_fn", "segment_length"]


def _angle_sq(truth, out):
    r = engine.estimate_r(out)
    a = M.angle_error_deg(truth.r.astype(r.dtype), r)
    return a * a


def _angle(truth, out):
    r = engine.estimate_r(out)
    return M.angle_error_deg(truth.r.astype(r.dtype), r)


def _chordal(truth, out):
    r = engine.estimate_r(out)
    return 3.0 - jnp.sum(truth.r.astype(r.dtype) * r)  # tr(I - R^T R^)


def _euler_sq(truth, out):
    r = engine.estimate_r(out)
    return sum(jnp.rad2deg(e) ** 2 for e in so3.euler_error_zyx(truth.r.astype(r.dtype), r))


def _innovation_nll(truth, out):
    nll = getattr(out, "nll", None)
    if nll is None:
        raise ValueError(
            f"loss 'innovation_nll' needs an observer whose Out has an 'nll' field (e.g. mekf); {type(out).__name__} "
            "has none"
        )
    return nll


#: Pointwise errors e(truth, out) -> scalar, by name (unit in the comment).
POINTWISE: Dict[str, Callable] = {
    "angle_sq": _angle_sq,  # deg^2, squared rotation angle of R^T R^ (eq. 23 of batista2019-ges)
    "angle": _angle,  # deg (gradient-safe at 0 and pi: jaxatt.so3.angle_of)
    "chordal": _chordal,  # tr(I - R^T R^) = 2 (1 - cos angle), dimensionless
    "euler_sq": _euler_sq,  # deg^2, roll^2 + pitch^2 + yaw^2 of wrapped ZYX differences (AHRS)
    # nats per step: the filter's negative log-likelihood of its own innovations (Out.nll, e.g. the MEKF's); needs
    # no truth, and its minimiser over the noise parameters is their maximum-likelihood estimate
    "innovation_nll": _innovation_nll,
}
POINTWISE_UNITS = {"angle_sq": "deg^2", "angle": "deg", "chordal": "-", "euler_sq": "deg^2", "innovation_nll": "nats"}


class LossSpec(NamedTuple):
    """A loss over one run: sum over windows of weight * (mean of e(t) over the samples of the window),
    averaged over runs. Hashable (used as a cache key).

    Fields:
        kind: a key of :data:`POINTWISE` or a hashable callable ``e(truth, out) -> scalar``.
        windows: ((name, start_s, end_s, weight), ...); an estimate at t (estimate k, at t_k, k >= 1) is in a window
            when start_s <= t < end_s (``end_s = inf`` for open ended; the steady-state window of
            ``monte_carlo`` is ``(window_start, inf)`` and gives its ``mean_angle_error_deg`` exactly).
    """

    kind: Any = "angle_sq"
    windows: Tuple[Tuple[str, float, float, float], ...] = (("steady", 0.0, math.inf, 1.0),)

    def describe(self) -> dict:
        kind = self.kind if isinstance(self.kind, str) else getattr(self.kind, "__name__", repr(self.kind))
        return {
            "kind": kind,
            "unit": POINTWISE_UNITS.get(kind, "?"),
            "windows": [
                {"name": n, "start_s": s, "end_s": (None if math.isinf(e) else e), "weight": w}
                for n, s, e, w in self.windows
            ],
        }


def loss_spec(
    kind="angle_sq",
    *,
    steady_start: float = 0.0,
    steady_end: float = math.inf,
    w_steady: float = 1.0,
    transient_start: float = 0.0,
    transient_end: Optional[float] = None,
    w_transient: float = 0.0,
) -> LossSpec:
    """A :class:`LossSpec` with a steady-state window [steady_start, steady_end) of weight ``w_steady`` and,
    when ``w_transient`` > 0, a transient window [transient_start, transient_end) (default end: steady_start)."""
    if not (isinstance(kind, str) and kind in POINTWISE) and not callable(kind):
        raise ValueError(f"loss kind must be one of {sorted(POINTWISE)} or a callable, got {kind!r}")
    wins = []
    if w_steady:
        wins.append(("steady", float(steady_start), float(steady_end), float(w_steady)))
    if w_transient:
        te = steady_start if transient_end is None else transient_end
        wins.append(("transient", float(transient_start), float(te), float(w_transient)))
    if not wins:
        raise ValueError("at least one of w_steady, w_transient must be non-zero")
    for n, s, e, w in wins:
        if not e > s:
            raise ValueError(f"window {n!r} must have end > start, got [{s}, {e})")
        if not (math.isfinite(w) and w > 0):
            raise ValueError(f"window weights must be finite and positive, got {n}: {w}")
    return LossSpec(kind, tuple(wins))


segment_length = engine.segment_length


class _Acc(NamedTuple):
    loss: jax.Array  # (n_windows,) sums of e(t)
    angle: jax.Array  # (n_windows,) sums of the angle error (deg)
    n: jax.Array  # (n_windows,) sample counts (a field named count would shadow tuple.count)
    last_angle: jax.Array  # ()


@functools.lru_cache(maxsize=64)
def loss_reducer(spec: LossSpec) -> engine.Reducer:
    """The engine reducer of a :class:`LossSpec`: per-run window sums of e(t), of the angle error and counts."""
    point = POINTWISE[spec.kind] if isinstance(spec.kind, str) else spec.kind
    starts = np.asarray([w[1] for w in spec.windows], float)
    ends = np.asarray([w[2] for w in spec.windows], float)
    nw = len(spec.windows)

    def init(t0, truth0, out0):
        dtype = engine.estimate_r(out0).dtype
        z = jnp.zeros((nw,), dtype)
        return _Acc(z, z, z, jnp.zeros((), dtype)), None

    def update(acc, t, truth, out):
        r = engine.estimate_r(out)
        dtype = r.dtype
        e = point(truth, out).astype(dtype)
        angle = M.angle_error_deg(truth.r.astype(dtype), r)
        w = ((t >= starts) & (t < ends)).astype(dtype)
        return _Acc(acc.loss + w * e, acc.angle + w * angle, acc.n + w, angle), None

    return engine.Reducer(init, update, lambda acc: acc)


@functools.lru_cache(maxsize=64)
def _loss_post(weights: tuple):
    """Result -> (loss, aux): the weighted window means averaged over the runs of the batch."""

    def post(res):
        acc: _Acc = res.summary  # runs first: (B, n_windows)
        cnt = jnp.maximum(acc.n, 1.0)
        win_loss = (acc.loss / cnt).T  # (n_windows, B)
        win_angle = (acc.angle / cnt).T
        loss = jnp.sum(jnp.asarray(weights, win_loss.dtype) * jnp.mean(win_loss, axis=-1))
        aux = {
            "window_loss": win_loss,
            "window_angle_deg": win_angle,
            "final_angle_deg": acc.last_angle,
            "window_count": acc.n[0],
            "final_state": res.state,
        }
        return loss, aux

    return post


#: Partition specs of the loss outputs when the runs are split over devices (loss averaged by pmean).
_LOSS_OUT_SPECS = engine.Static(
    (
        PartitionSpec(),
        {
            "window_loss": PartitionSpec(None, _sharding.AXIS),
            "window_angle_deg": PartitionSpec(None, _sharding.AXIS),
            "final_angle_deg": PartitionSpec(_sharding.AXIS),
            "window_count": PartitionSpec(),
            "final_state": PartitionSpec(_sharding.AXIS),
        },
    )
)


def _pmean_loss(out):
    loss, aux = out
    return jax.lax.pmean(loss, _sharding.AXIS), aux


def _dtypes(dtype):
    obs = jnp.dtype(dtype) if dtype is not None else jnp.result_type(float)
    return obs, jnp.result_type(float)


def make_loss_fn(
    observer: Observer,
    *,
    duration: float,
    dt: float,
    spec: LossSpec,
    hold: Optional[str] = None,
    dtype=None,
    checkpoint: Union[str, int, bool, None] = "auto",
    init_params=None,
    step_remat: Optional[bool] = None,
    jit: bool = True,
    devices=1,
):
    """``loss(scenario, params, keys) -> (loss, aux)`` for a batch of run keys (:func:`montecarlo.run_keys`).

    The simulation is :func:`jaxatt.montecarlo.monte_carlo`'s (same truth, sensor samples, noise stream,
    ``init_params`` draw and observer steps), with the loss of ``spec`` accumulated on the fly; differentiable
    in ``params`` (and in the scenario's arrays). ``aux``: ``window_loss`` and ``window_angle_deg`` (n_windows,
    B) per-run window means of e(t) and of the angle error (deg), ``final_angle_deg`` (B,), ``window_count``
    (n_windows,) and ``final_state`` (the observer states at the end, runs first).

    ``checkpoint``: see :func:`segment_length`. ``step_remat`` (default: on when checkpointing) also wraps
    each time step in ``jax.checkpoint``: while a segment is recomputed only the per-step carries (state,
    truth, sample, accumulators) are kept, not the step's intermediate values; the step is recomputed once
    more during its backward pass. That divides the segment's memory by about 8 and, on CPU, is slightly
    faster (fewer stacked residuals to write and read). ``jit``: return the cached jitted function (compiled
    once per observer and static settings, reused for new params, scenarios of the same structure and keys).
    ``devices``: split the runs of each call over these devices (:mod:`jaxatt.sharding`; None = every visible
    device; default 1 = one device); the number of keys must then be a multiple of the device count.
    ``hold``: "zoh" or "linear"; None: the observer's own (``Observer.hold``), else "zoh".
    """
    given = hold
    hold = engine.hold_for(observer, hold)
    if hold not in ("zoh", "linear"):
        own = "" if given else f" (observer {observer.name!r}'s own hold: pass hold='zoh' or 'linear')"
        raise ValueError(f"hold must be 'zoh' or 'linear', got {hold!r}{own}")
    from ..montecarlo import check_dt, check_duration, whole_steps  # monte_carlo's checks of the run's steps

    n_steps = whole_steps(check_duration(duration), check_dt(dt))
    obs_dtype, sim_dtype = _dtypes(dtype)
    segment = segment_length(n_steps, checkpoint)
    mesh = _sharding.seed_mesh(devices)
    source = engine.Simulated(n_steps, dt, sim_dtype, init_params)
    kw = dict(
        post=_loss_post(tuple(float(w[3]) for w in spec.windows)),
        hold=hold,
        obs_dtype=obs_dtype,
        segment=segment,
        step_remat=bool(segment) if step_remat is None else bool(step_remat),
        keep_state=True,
    )
    if mesh is not None:
        kw.update(out_specs=_LOSS_OUT_SPECS, reduce=_pmean_loss)
    fn = engine.compiled(observer, source, loss_reducer(spec), mesh, **kw)
    if not jit:
        fn = fn.__wrapped__ if hasattr(fn, "__wrapped__") else fn
    if mesh is None:
        return fn

    def checked(scenario, params, keys):
        _sharding.check_batch(int(np.shape(keys)[0]), mesh)
        return fn(scenario, params, keys)

    return checked


def simulation_loss(
    scenario,
    observer: Observer,
    params,
    keys,
    *,
    duration: float,
    dt: float,
    spec: Optional[LossSpec] = None,
    hold: Optional[str] = None,
    dtype=None,
    checkpoint="auto",
    init_params=None,
    step_remat: Optional[bool] = None,
):
    """(loss, aux) of ``params`` over the runs of ``keys``; ``jax.grad`` of ``lambda p: simulation_loss(...)[0]``
    is the gradient through the whole simulation. See :func:`make_loss_fn`."""
    spec = spec or LossSpec()
    return make_loss_fn(
        observer,
        duration=duration,
        dt=dt,
        spec=spec,
        hold=hold,
        dtype=dtype,
        checkpoint=checkpoint,
        init_params=init_params,
        step_remat=step_remat,
    )(scenario, params, keys)


# ------------------------------------------------------------------------------------------------------
# Experiments
# ------------------------------------------------------------------------------------------------------
