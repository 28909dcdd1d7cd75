"""Gradient-based tuning of observer gains: losses over Monte Carlo seeds differentiable through the whole
simulation, checkpointed for long horizons, an optax loop with early stopping, and gains JSON I/O.

Pieces (each usable alone):

* :class:`LossSpec` / :func:`loss_spec`: a pointwise error ``e(t)`` (``"angle_sq"``: squared rotation angle of
  R^T R^ in deg^2; ``"angle"``: the angle in deg; ``"chordal"``: tr(I - R^T R^) = 2 (1 - cos angle);
  ``"euler_sq"``: sum of squared wrapped ZYX roll/pitch/yaw errors in deg^2, for AHRS observers; or any
  ``fn(truth, out) -> scalar``) averaged over time windows, weighted (e.g. transient and steady state), then
  averaged over runs.
* :func:`make_loss_fn` / :func:`simulation_loss`: ``loss(scenario, params, keys) -> (loss, aux)``, the same
  fused simulator + observer scan as :func:`jaxatt.montecarlo.monte_carlo` (same scenario interface
  ``truth_at / propagate / sample / n_channels``, same noise stream: run k of seed s is the same run in both),
  differentiable with ``jax.grad`` in the params. For long horizons the scan is split into segments wrapped in
  ``jax.checkpoint`` (nested scans): reverse mode keeps one carry per segment and recomputes a segment's steps
  during the backward pass, so memory grows like T / c + c (about sqrt(T) with the default segment length
  c ~ sqrt(T), in multiples of the 1000-step noise block) instead of T, for one more forward pass of compute.
* :func:`optimize`: an optax loop over unconstrained parameters (:mod:`jaxatt.parametrize`) with minibatches of
  training seeds, validation on held-out seeds, early stopping, a progress callback, and a save hook.
* :func:`tune` / :func:`evaluate`: the CLI-ready entry points (``jaxatt tune`` / ``jaxatt evaluate``), plain
  Python arguments, progress on stderr, results as JSON (gains JSON written atomically after every step, so an
  interrupted run keeps what it found; evaluation JSON with the same ``metrics.<name>.mean/std/min/max/per_run``
  layout as ``jaxatt reproduce``).
* :func:`save_gains` / :func:`load_gains` / :func:`gains_to_dict` / :func:`apply_gains`: a human-readable
  gains file (named gains with units, schedules with their intervals) that loads back into the experiment's
  Params.

Experiments plug in through :data:`TARGETS` (:func:`register_target`): a builder returning a :class:`Setup`
(scenario, observer, params, errors, windows, per-run initial-params draw, ...) and the gains declared in
:data:`jaxatt.parametrize.GAINS`. batista-ges and batista-so3 are registered here; the AHRS observers of
sensors2020 plug in the same way, e.g. (field names of their Params as declared there)::

    from jaxatt import parametrize as P, tune
    from jaxatt.experiments import nlio as E

    def build(**overrides):
        cfg = E.config("nlio-case1", **overrides)
        return tune.Setup("nlio-case1", cfg, E.scenario(cfg), E.observer(cfg, "NLIO-TV"),
                          E.params(cfg, "NLIO-TV", dtype=jnp.float64), E.errors, cfg.duration, cfg.dt, cfg.hold,
                          loss_windows={"steady": (300.0, math.inf), "transient": (0.0, 200.0)},
                          loss_kind="euler_sq", init_params=E.random_initial_attitude, windows=E.WINDOWS,
                          check_params=E.check_params, window_start=300.0)

    tune.register_target("nlio-case1", build)
    P.register_gains("nlio-case1", [P.Gain("kp", P.SPD(), "1/s", "attitude gain Kp"),
                                    P.Gain("k1", P.SPD(), "1/s", "auxiliary-observer gain K1"), ...])

after which ``tune("nlio-case1", ...)`` / ``evaluate("nlio-case1", ...)`` work (evaluate then also reports
the MAE/RMSE windows of ``Setup.windows``).

Conventions: rotations map body to reference (v_ref = R v_body); angles reported in degrees with ``_deg``;
times in s. Float64 is enabled by :func:`tune` and :func:`evaluate` (as the CLI does): the gradient checks
and the long horizons need it.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import sys
import time
from typing import Any, Callable, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple, Union

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec

from . import metrics as M
from . import sharding as _sharding
from . import montecarlo, so3
from . import parametrize as P
from .integrate import Interval
from .observers.base import Observer
from .sim import imu

__all__ = ["LossSpec", "loss_spec", "POINTWISE", "make_loss_fn", "simulation_loss", "segment_length",
           "Setup", "Target", "TARGETS", "register_target", "setup", "Problem", "make_problem", "optimize",
           "OptimizeResult", "tune",
           "TuneResult", "evaluate", "gains_to_dict", "apply_gains", "save_gains", "load_gains", "print_progress",
           "GAINS_FORMAT", "summarise"]

GAINS_FORMAT = "jaxatt-gains/1"
#: fold_in index of a run's key for its ``init_params`` draw (as :mod:`jaxatt.montecarlo`).
INIT_PARAMS_BLOCK = getattr(montecarlo, "INIT_PARAMS_BLOCK", 2**31 - 2)


# ------------------------------------------------------------------------------------------------------
# Losses
# ------------------------------------------------------------------------------------------------------
def _wrap(a):
    return jnp.arctan2(jnp.sin(a), jnp.cos(a))


def _angle_sq(truth, out):
    a = M.angle_error_deg(truth.r.astype(out.r.dtype), out.r)
    return a * a


def _angle(truth, out):
    return M.angle_error_deg(truth.r.astype(out.r.dtype), out.r)


def _chordal(truth, out):
    r = truth.r.astype(out.r.dtype)
    return 3.0 - jnp.sum(r * out.r)  # tr(I - R^T R^)


def _euler_sq(truth, out):
    et = so3.matrix_to_euler_zyx(truth.r.astype(out.r.dtype))
    ee = so3.matrix_to_euler_zyx(out.r)
    return sum(jnp.rad2deg(_wrap(a - b)) ** 2 for a, b in zip(ee, et))


#: Pointwise errors e(truth, out) -> scalar, by name (unit in the comment).
POINTWISE: Dict[str, Callable] = {
    "angle_sq": _angle_sq,  # deg^2, squared rotation angle of R^T R^ (eq. 23 of batista2019-ges)
    "angle": _angle,  # deg (gradient-safe at 0 and pi: jaxatt.so3.angle_of)
    "chordal": _chordal,  # tr(I - R^T R^) = 2 (1 - cos angle), dimensionless
    "euler_sq": _euler_sq,  # deg^2, roll^2 + pitch^2 + yaw^2 of wrapped ZYX differences (AHRS)
}
POINTWISE_UNITS = {"angle_sq": "deg^2", "angle": "deg", "chordal": "-", "euler_sq": "deg^2"}


class LossSpec(NamedTuple):
    """A loss over one run: sum over windows of weight * (mean of e(t) over the samples of the window),
    averaged over runs. Hashable (used as a cache key).

    Fields:
        kind: a key of :data:`POINTWISE` or a hashable callable ``e(truth, out) -> scalar``.
        windows: ((name, start_s, end_s, weight), ...); a sample at t (the output time t_k+1) is in a window
            when start_s <= t < end_s (``end_s = inf`` for open ended; the steady-state window of
            ``monte_carlo`` is ``(window_start, inf)`` and gives its ``mean_angle_error_deg`` exactly).
    """

    kind: Any = "angle_sq"
    windows: Tuple[Tuple[str, float, float, float], ...] = (("steady", 0.0, math.inf, 1.0),)

    def describe(self) -> dict:
        kind = self.kind if isinstance(self.kind, str) else getattr(self.kind, "__name__", repr(self.kind))
        return {"kind": kind, "unit": POINTWISE_UNITS.get(kind, "?"),
                "windows": [{"name": n, "start_s": s, "end_s": (None if math.isinf(e) else e), "weight": w}
                            for n, s, e, w in self.windows]}


def loss_spec(kind="angle_sq", *, steady_start: float = 0.0, steady_end: float = math.inf, w_steady: float = 1.0,
              transient_start: float = 0.0, transient_end: Optional[float] = None, w_transient: float = 0.0
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


def segment_length(n_steps: int, checkpoint: Union[str, int, bool, None] = "auto") -> int:
    """Steps per checkpointed segment (0 = no checkpointing).

    ``"auto"`` (or True): about sqrt(n_steps) rounded to a multiple of the 1000-step noise block, at least one
    block (360,000 steps -> 1000: 360 stored carries and 1000 recomputed steps; 4,000,000 -> 2000). An int
    must divide 1000 or be a multiple of it; a segment shorter than a block regenerates the block's noise
    for each segment (more random numbers; meant for tests of short horizons). False / None / 0 disables
    checkpointing (reverse mode stores every step: short horizons only).
    """
    L = imu.NOISE_BLOCK
    if checkpoint is None or checkpoint is False or checkpoint == 0:
        return 0
    if checkpoint is True or checkpoint == "auto":
        return L * max(1, int(round(math.sqrt(max(n_steps, 1)) / L)))
    if isinstance(checkpoint, str):
        raise ValueError(f"checkpoint must be 'auto', True/False/None or a number of steps, got {checkpoint!r}")
    c = int(checkpoint)
    if c < 1 or (L % c and c % L):
        raise ValueError(f"checkpoint segment must divide {L} or be a multiple of it, got {checkpoint!r}")
    return c


def _cast(tree, dtype):
    return jax.tree_util.tree_map(lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, tree)


class _Acc(NamedTuple):
    loss: jax.Array  # (n_windows,) sums of e(t)
    angle: jax.Array  # (n_windows,) sums of the angle error (deg)
    count: jax.Array  # (n_windows,)
    last_angle: jax.Array  # ()


def _build_loss(observer: Observer, *, n_steps: int, dt: float, spec: LossSpec, hold: str, obs_dtype, sim_dtype,
                segment: int, init_params=None, step_remat: bool = False):
    """``loss(scenario, params, keys) -> (loss, aux)``; see :func:`make_loss_fn`."""
    L = imu.NOISE_BLOCK
    point = POINTWISE[spec.kind] if isinstance(spec.kind, str) else spec.kind
    starts = np.asarray([w[1] for w in spec.windows], float)
    ends = np.asarray([w[2] for w in spec.windows], float)
    weights = np.asarray([w[3] for w in spec.windows], float)
    nw = len(spec.windows)
    dt_obs = np.asarray(dt, obs_dtype)
    remat = (lambda f: jax.checkpoint(f, prevent_cse=False)) if segment else (lambda f: f)

    def fn(scenario, params, keys):
        scn = _cast(scenario, sim_dtype)
        p = _cast(params, obs_dtype)
        nch = scn.n_channels

        def init_one(key):  # exactly montecarlo._batch_fn's init_one
            truth0 = scn.truth_at(scn.r0, jnp.zeros((), sim_dtype))
            s0 = _cast(scn.sample(truth0, imu.initial_noise(key, sim_dtype, nch), dt), obs_dtype)
            if init_params is None:
                st0 = observer.init(p, s0)
            else:
                st0 = observer.init(_cast(init_params(p, jax.random.fold_in(key, INIT_PARAMS_BLOCK)), obs_dtype), s0)
            z = jnp.zeros((nw,), obs_dtype)
            return scn.r0, s0, st0, _Acc(z, z, z, jnp.zeros((), obs_dtype))

        def step_one(k, r, s_prev, st, acc, noise):  # montecarlo's step_one with the loss accumulator
            t_k = k.astype(sim_dtype) * dt
            t_next = (k + 1).astype(sim_dtype) * dt
            r_next = scn.propagate(r, t_k, dt)
            truth = scn.truth_at(r_next, t_next)
            s_next = _cast(scn.sample(truth, noise, dt), obs_dtype)
            u = Interval(s_prev, s_next) if hold == "linear" else s_prev
            st, out = observer.step(p, st, u, dt_obs)
            e = point(truth, out).astype(obs_dtype)
            angle = M.angle_error_deg(truth.r.astype(obs_dtype), out.r)
            w = ((t_next >= starts) & (t_next < ends)).astype(obs_dtype)
            acc = _Acc(acc.loss + w * e, acc.angle + w * angle, acc.count + w, angle)
            return r_next, s_next, st, acc

        step_b = jax.vmap(step_one, in_axes=(None, -1, -1, -1, -1, -1), out_axes=-1)
        if step_remat:
            step_b = jax.checkpoint(step_b, prevent_cse=False)

        def step(carry, noise):
            k = carry[0]
            return (k + 1,) + step_b(*carry, noise), None

        def run_steps(carry, block, offset, length):
            """``length`` steps with rows offset ... offset + length - 1 of noise block ``block``."""
            def rows(key):
                nb = imu.noise_block(key, block, sim_dtype, nch)
                return nb if length == L else jax.lax.dynamic_slice_in_dim(nb, offset, length, 0)

            noise = jax.vmap(rows, out_axes=-1)(keys)  # (length, nch, B)
            carry, _ = jax.lax.scan(step, carry, noise)
            return carry

        carry = (jnp.zeros((), jnp.int32),) + jax.vmap(init_one, out_axes=-1)(keys)
        c = segment if segment else L
        if c <= L:  # segments inside noise blocks (c divides L)
            n_seg = n_steps // c

            @remat
            def seg(carry, s):
                start = s * c
                return run_steps(carry, start // L, start % L, c), None

            if n_seg:
                carry, _ = jax.lax.scan(seg, carry, jnp.arange(n_seg))
            pos = n_seg * c
            if n_steps > pos:  # remainder < c, inside one block
                carry = remat(lambda cr: run_steps(cr, pos // L, pos % L, n_steps - pos))(carry)
        else:  # segments of m whole blocks
            m = c // L
            n_seg = n_steps // c

            @remat
            def seg(carry, s):
                blk = lambda cr, j: (run_steps(cr, s * m + j, 0, L), None)  # noqa: E731
                return jax.lax.scan(blk, carry, jnp.arange(m))[0], None

            if n_seg:
                carry, _ = jax.lax.scan(seg, carry, jnp.arange(n_seg))
            pos = n_seg * c
            q, r_ = divmod(n_steps - pos, L)
            if q:
                blk = remat(lambda cr, j: (run_steps(cr, j, 0, L), None))
                carry, _ = jax.lax.scan(blk, carry, pos // L + jnp.arange(q))
            if r_:
                carry = remat(lambda cr: run_steps(cr, pos // L + q, 0, r_))(carry)
        acc: _Acc = carry[4]
        cnt = jnp.maximum(acc.count, 1.0)
        win_loss = acc.loss / cnt  # (nw, B)
        win_angle = acc.angle / cnt
        loss = jnp.sum(jnp.asarray(weights, obs_dtype) * jnp.mean(win_loss, axis=-1))
        state = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, -1, 0), carry[3])
        aux = {"window_loss": win_loss, "window_angle_deg": win_angle, "final_angle_deg": acc.last_angle,
               "window_count": acc.count[:, 0], "final_state": state}
        return loss, aux

    return fn


#: Partition specs of the loss outputs when the runs are split over devices (loss averaged by pmean).
_LOSS_OUT_SPECS = (PartitionSpec(), {"window_loss": PartitionSpec(None, _sharding.AXIS),
                                     "window_angle_deg": PartitionSpec(None, _sharding.AXIS),
                                     "final_angle_deg": PartitionSpec(_sharding.AXIS),
                                     "window_count": PartitionSpec(), "final_state": PartitionSpec(_sharding.AXIS)})


def _pmean_loss(out):
    loss, aux = out
    return jax.lax.pmean(loss, _sharding.AXIS), aux


def _sharded_loss(fn, mesh):
    """``fn`` with its runs split over ``mesh`` (None: unchanged); the loss (a mean over runs, equal shards) is
    the mean of the per-device losses, so its gradient is the gradient over all runs."""
    if mesh is None:
        return fn
    return _sharding.shard_runs(fn, mesh, out_specs=_LOSS_OUT_SPECS, reduce=_pmean_loss)


@functools.lru_cache(maxsize=32)
def _loss_fn_cached(observer: Observer, mesh=None, **static):
    return jax.jit(_sharded_loss(_build_loss(observer, **static), mesh))


def _dtypes(dtype):
    obs = jnp.dtype(dtype) if dtype is not None else jnp.result_type(float)
    return obs, jnp.result_type(float)


def make_loss_fn(observer: Observer, *, duration: float, dt: float, spec: LossSpec, hold: str = "zoh",
                 dtype=None, checkpoint: Union[str, int, bool, None] = "auto", init_params=None,
                 step_remat: Optional[bool] = None, jit: bool = True, devices=1):
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
    """
    if hold not in ("zoh", "linear"):
        raise ValueError(f"hold must be 'zoh' or 'linear', got {hold!r}")
    dt = montecarlo.check_dt(dt)
    n_steps = int(round(duration / dt))
    if n_steps < 1:
        raise ValueError(f"duration must be at least one step, got {duration} s with dt = {dt} s")
    obs_dtype, sim_dtype = _dtypes(dtype)
    segment = segment_length(n_steps, checkpoint)
    static = dict(n_steps=n_steps, dt=dt, spec=spec, hold=hold, obs_dtype=obs_dtype, sim_dtype=sim_dtype,
                  segment=segment, init_params=init_params,
                  step_remat=bool(segment) if step_remat is None else bool(step_remat))
    mesh = _sharding.seed_mesh(devices)
    if jit:
        fn = _loss_fn_cached(observer, mesh, **static)
    else:
        fn = _sharded_loss(_build_loss(observer, **static), mesh)
    if mesh is None:
        return fn

    def checked(scenario, params, keys):
        _sharding.check_batch(int(np.shape(keys)[0]), mesh)
        return fn(scenario, params, keys)

    return checked


def simulation_loss(scenario, observer: Observer, params, keys, *, duration: float, dt: float,
                    spec: Optional[LossSpec] = None, hold: str = "zoh", dtype=None, checkpoint="auto",
                    init_params=None, step_remat: Optional[bool] = None):
    """(loss, aux) of ``params`` over the runs of ``keys``; ``jax.grad`` of ``lambda p: simulation_loss(...)[0]``
    is the gradient through the whole simulation. See :func:`make_loss_fn`."""
    spec = spec or LossSpec()
    return make_loss_fn(observer, duration=duration, dt=dt, spec=spec, hold=hold, dtype=dtype,
                        checkpoint=checkpoint, init_params=init_params, step_remat=step_remat)(scenario, params, keys)


# ------------------------------------------------------------------------------------------------------
# Experiments
# ------------------------------------------------------------------------------------------------------
class Setup(NamedTuple):
    """Everything tune/evaluate need of one experiment configuration.

    Fields: experiment name; config (the experiment's Config NamedTuple); scenario, observer, params (the
    paper's gains); errors_fn (named errors for the Monte Carlo metrics); duration, dt (s); hold;
    loss_windows: name -> (start_s, end_s) with at least "steady" (the paper's steady-state window) and
    "transient"; loss_kind (default pointwise error); init_params (per-run initial-params draw or None);
    windows (MAE/RMSE windows of ``monte_carlo``, may be ()); check_params; paper (published numbers);
    notes (readings, printed and saved).
    """

    experiment: str
    config: Any
    scenario: Any
    observer: Observer
    params: Any
    errors_fn: Callable
    duration: float
    dt: float
    hold: str
    loss_windows: Mapping[str, Tuple[float, float]]
    loss_kind: str = "angle_sq"
    init_params: Optional[Callable] = None
    windows: tuple = ()
    check_params: Optional[Callable] = None
    paper: Mapping[str, Any] = {}
    notes: Sequence[str] = ()
    window_start: float = 0.0


class Target(NamedTuple):
    """An experiment that can be tuned: ``build(**config_overrides) -> Setup``."""

    name: str
    build: Callable[..., Setup]


TARGETS: Dict[str, Target] = {}


def register_target(name: str, build: Callable[..., Setup]) -> None:
    """Make ``name`` tunable: ``build(**config_overrides)`` returns a :class:`Setup`; its gains must be
    declared with :func:`jaxatt.parametrize.register_gains` under the same name."""
    TARGETS[name] = Target(name, build)


def _batista_builder(module):
    def build(**overrides) -> Setup:
        dur = float(overrides.get("duration", module.DURATION))
        overrides.setdefault("window_start", min(module.WINDOW_START, 2.0 * dur / 3.0))
        bad = set(overrides) - set(module.Config._fields)
        if bad:
            raise ValueError(f"unknown {module.NAME} config fields {sorted(bad)} (fields: {module.Config._fields})")
        cfg = module.Config(**overrides)
        return Setup(
            experiment=module.NAME, config=cfg, scenario=module.scenario(cfg), observer=module.observer(cfg),
            params=module.params(cfg, dtype=jnp.float64), errors_fn=module.errors, duration=cfg.duration,
            dt=cfg.dt, hold=cfg.hold,
            loss_windows={"steady": (cfg.window_start, math.inf), "transient": (0.0, cfg.window_start)},
            loss_kind="angle_sq", check_params=module.check_params,
            paper=module.PAPER.get(cfg.trajectory, {}), notes=module.notes(cfg), window_start=cfg.window_start)

    return build


#: NLIO-paper experiments that can be tuned, and the observer tuned in each (sensors2020-nlio Section 5).
NLIO_TARGETS = {"nlio-case1": "NLIO-FG", "nlio-case2": "NLIO-FG", "nlio-case3": "NLIO-FG"}


def _nlio_builder(name: str, label: str):
    """Setup of an NLIO-paper AHRS case with the fixed-gain NLIO (Kp, kv, K1, K2 tunable): the case's scenario,
    random initial estimate (Case 1), Euler-angle loss over the steady-state window 300-500 s, the paper's
    MAE / RMSE windows in the metrics."""

    def build(**overrides) -> Setup:
        from .experiments import nlio as X

        dur = float(overrides.get("duration", X.DURATION))
        if dur != X.DURATION and "windows" not in overrides:  # reduced horizons: windows scaled with it
            f = dur / X.DURATION
            overrides["windows"] = tuple((n, a * f, b * f) for n, a, b in X.CASES[name[5:]].windows)
        cfg = X.config(name, **overrides)
        ss = X._steady_start(cfg)
        ts, te = dict((w[0], (w[1], w[2])) for w in cfg.windows).get("transient", (0.0, ss))
        notes = [f"observer: {label} (Kp, kv, K1, K2 tuned; theta, l_b, L_b fixed)"] + [
            r if isinstance(r, str) else str(r) for r in X.READINGS]
        return Setup(
            experiment=name, config=cfg, scenario=X.scenario(cfg), observer=X.observer(cfg, label),
            params=X.params(cfg, label, dtype=jnp.float64), errors_fn=X.errors, duration=cfg.duration, dt=cfg.dt,
            hold=cfg.hold, loss_windows={"steady": (ss, math.inf), "transient": (ts, te)}, loss_kind="euler_sq",
            init_params=X.initial_attitude_hook(tuple(cfg.init_angles)) if cfg.random_init else None,
            windows=tuple(cfg.windows), check_params=X.check_params, paper=X.PAPER.get(cfg.case, {}),
            notes=notes, window_start=ss)

    return build


def _register_builtin():
    from .experiments import batista_ges, batista_so3

    register_target(batista_ges.NAME, _batista_builder(batista_ges))
    register_target(batista_so3.NAME, _batista_builder(batista_so3))
    for name, label in NLIO_TARGETS.items():
        register_target(name, _nlio_builder(name, label))


_register_builtin()


def setup(experiment: str, **config_overrides) -> Setup:
    """The :class:`Setup` of a registered experiment (paper configuration unless overridden)."""
    if experiment not in TARGETS:
        raise ValueError(f"unknown experiment {experiment!r}; tunable experiments: {sorted(TARGETS)}")
    return TARGETS[experiment].build(**config_overrides)


# ------------------------------------------------------------------------------------------------------
# Gains JSON
# ------------------------------------------------------------------------------------------------------
def _tolist(a):
    a = np.asarray(a, float)
    return a.tolist() if a.ndim else float(a)


def gains_to_dict(experiment: str, params) -> Dict[str, dict]:
    """Human-readable gains: name -> {value, unit, doc, parametrization} (+ switch times and intervals for a
    schedule, + the gain as a rate in 1/s where the unit is not one)."""
    out = {}
    for g in P.gains_of(experiment):
        v = np.asarray(getattr(params, g.field), float)
        d = {"value": _tolist(v), "unit": g.unit, "doc": g.doc, "parametrization": g.transform.describe()}
        if isinstance(g.transform, P.Schedule):
            st = np.asarray(getattr(params, g.transform.times_field), float)
            edges = [0.0] + st.tolist() + [None]
            d[f"{g.transform.times_field}_s"] = st.tolist()
            d["intervals_s"] = [[edges[i], edges[i + 1]] for i in range(len(edges) - 1)]
        if g.rate is not None:
            label, fn = g.rate
            d["as_rate"] = {"label": label, "value": _tolist(v * fn(params))}
        out[g.field] = d
    return out


def apply_gains(experiment: str, params, gains: Mapping[str, Any]):
    """``params`` with the gains of a gains dict (:func:`gains_to_dict` layout, or field -> value) put in;
    shapes must match; a schedule's switch times are taken from the dict when present."""
    known = {g.field: g for g in P.gains_of(experiment)}
    new = {}
    for name, entry in gains.items():
        if name not in known:
            raise ValueError(f"{name!r} is not a gain of {experiment} (gains: {sorted(known)})")
        val = entry["value"] if isinstance(entry, Mapping) else entry
        ref = jnp.asarray(getattr(params, name))
        arr = np.asarray(val, float)
        tr = known[name].transform
        if isinstance(tr, P.Schedule) and isinstance(entry, Mapping) and f"{tr.times_field}_s" in entry:
            st = np.asarray(entry[f"{tr.times_field}_s"], float)
            new[tr.times_field] = jnp.asarray(st, jnp.asarray(getattr(params, tr.times_field)).dtype)
            if arr.shape != (st.shape[0] + 1,):
                raise ValueError(f"{name}: {arr.shape[0]} values for {st.shape[0]} switch times")
        elif arr.shape != ref.shape:
            raise ValueError(f"{name}: shape {arr.shape} does not match the experiment's {ref.shape}")
        new[name] = jnp.asarray(arr, ref.dtype)
    return params._replace(**new)


def _write_json(path: Optional[str], payload: dict) -> None:
    """Atomic write (temporary file + os.replace): an interrupted write never leaves a broken file."""
    if not path:
        return
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(payload, f, indent=1, default=_json_default)
        f.write("\n")
    os.replace(tmp, path)


def _json_default(o):
    if isinstance(o, (np.generic,)):
        return o.item()
    if isinstance(o, (np.ndarray, jax.Array)):
        return np.asarray(o).tolist()
    return repr(o)


def _config_dict(cfg) -> dict:
    if cfg is None:
        return {}
    d = cfg._asdict() if hasattr(cfg, "_asdict") else dict(cfg)
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}


def save_gains(path: str, experiment: str, params, *, config=None, extra: Optional[dict] = None) -> None:
    """Write a gains JSON (atomically): ``{"format", "experiment", "gains": gains_to_dict(...), "config",
    ...extra}``."""
    payload = {"format": GAINS_FORMAT, "experiment": experiment, "gains": gains_to_dict(experiment, params),
               "config": _config_dict(config)}
    payload.update(extra or {})
    _write_json(path, payload)


def load_gains(path: str, base_params=None, *, experiment: Optional[str] = None):
    """Read a gains JSON. Returns ``(experiment, params, payload)``: params = the experiment's paper params
    (or ``base_params``) with the file's gains put in, validated by the experiment's ``check_params``."""
    with open(path) as f:
        payload = json.load(f)
    if payload.get("format") != GAINS_FORMAT:
        raise ValueError(f"{path}: not a jaxatt gains file (format {payload.get('format')!r}, want {GAINS_FORMAT!r})")
    name = payload["experiment"]
    if experiment is not None and experiment != name:
        raise ValueError(f"{path} holds gains of {name!r}, not of {experiment!r}")
    s = None
    if base_params is None:
        s = setup(name)
        base_params = s.params
    params = apply_gains(name, base_params, payload["gains"])
    check = s.check_params if s is not None else (TARGETS and setup(name).check_params)
    if check:
        check(params)
    return name, params, payload


# ------------------------------------------------------------------------------------------------------
# Optimisation loop
# ------------------------------------------------------------------------------------------------------
class OptimizeResult(NamedTuple):
    """theta and params with the best validation loss (the last ones without validation), the last theta,
    the history (one dict per step), and how the loop ended ("done", "early-stopped", "interrupted",
    "non-finite")."""

    best_theta: Dict[str, Any]
    best_params: Any
    last_theta: Dict[str, Any]
    best_step: int
    best_val: Optional[float]
    start_val: Optional[float]
    history: List[dict]
    status: str


def print_progress(info: dict, file=None) -> None:
    """Default progress display: one line per step (train loss, validation when computed, gradient norm)."""
    file = file or sys.stderr
    val = "" if info.get("val_loss") is None else (
        f"  val {info['val_loss']:.5g}{' *' if info.get('improved') else ''} (best {info['best_val']:.5g} @ step "
        f"{info['best_step']})")
    ang = info.get("train_angle_deg")
    angs = "" if ang is None else f" ({ang:.4g} deg)"
    print(f"step {info['step']:4d}/{info['steps']}  train {info['train_loss']:.5g}{angs}  |g| "
          f"{info['grad_norm']:.3g}{val}  {info['step_s']:.1f} s/step", file=file, flush=True)


def _global_norm(tree) -> float:
    return float(jnp.sqrt(sum(jnp.sum(jnp.square(x)) for x in jax.tree_util.tree_leaves(tree))))


def optimize(objective: Callable, theta0: Dict[str, Any], *, steps: int, train_keys, batch_runs: Optional[int] = None,
             val_keys=None, val_every: int = 5, patience: Optional[int] = None, min_delta: float = 0.0,
             optimizer=None, lr: float = 0.05, clip: Optional[float] = 1.0, shuffle_seed: int = 0,
             constrain: Optional[Callable] = None, callback: Optional[Callable[[dict], None]] = None,
             on_save: Optional[Callable[[OptimizeResult], None]] = None, jit: bool = True) -> OptimizeResult:
    """Minimise ``objective(theta, keys) -> (loss, aux)`` with optax.

    Each step uses ``batch_runs`` of ``train_keys`` (all of them when None; otherwise consecutive slices of a
    per-epoch shuffle, so every training seed is used equally). Every ``val_every`` steps (and at step 0 and
    the last step) the loss on ``val_keys`` is computed; the best-validation theta is kept, and after
    ``patience`` validations without an improvement larger than ``min_delta`` (relative) the loop stops.
    ``callback(info)`` is called after every step (``info``: step, steps, train_loss, train_angle_deg,
    grad_norm, val_loss, best_val, best_step, improved, step_s, elapsed_s); ``on_save(result_so_far)`` too
    (write files there). KeyboardInterrupt ends the loop with status "interrupted" and what was found.
    A non-finite loss or gradient skips the update (counted in the history); three in a row stop the loop.
    ``jit=False`` differentiates ``objective`` eagerly: right when its heavy part is already a jitted function
    (as :func:`make_loss_fn`'s), whose compiled forward and backward programs are then shared by every caller
    with the same static settings (a second :func:`tune` or a test does not compile again).
    """
    import optax

    if optimizer is None:
        optimizer = optax.adam(lr) if not clip else optax.chain(optax.clip_by_global_norm(clip), optax.adam(lr))
    train_keys = jnp.asarray(train_keys)
    n_train = int(train_keys.shape[0])
    batch_runs = n_train if batch_runs is None else int(min(batch_runs, n_train))
    rng = np.random.default_rng(shuffle_seed)
    order: List[int] = []

    def next_batch():
        nonlocal order
        if batch_runs == n_train:
            return train_keys
        if len(order) < batch_runs:
            order = order + rng.permutation(n_train).tolist()
        idx, order = order[:batch_runs], order[batch_runs:]
        return train_keys[np.asarray(idx)]

    vg = jax.value_and_grad(objective, has_aux=True)
    val_fn = objective if val_keys is not None else None
    if jit:
        vg, val_fn = jax.jit(vg), (jax.jit(val_fn) if val_fn is not None else None)
    theta = jax.tree_util.tree_map(jnp.asarray, dict(theta0))
    opt_state = optimizer.init(theta)
    history: List[dict] = []
    best_theta, best_val, best_step, start_val, bad, status, n_nonfinite = theta, None, 0, None, 0, "done", 0
    t_start = time.perf_counter()

    def validate(th):
        loss, aux = val_fn(th, val_keys)
        return float(loss), float(jnp.mean(aux["window_angle_deg"][0]))

    def result(st):
        params = constrain(best_theta) if constrain is not None else None
        return OptimizeResult(best_theta, params, theta, best_step, best_val, start_val, history, st)

    try:
        if val_fn is not None:
            start_val, start_ang = validate(theta)
            best_val = start_val
            history.append({"step": 0, "val_loss": start_val, "val_angle_deg": start_ang,
                            "elapsed_s": time.perf_counter() - t_start})
        for step in range(1, steps + 1):
            t0 = time.perf_counter()
            (loss, aux), grads = vg(theta, next_batch())
            loss = float(loss)
            gnorm = _global_norm(grads)
            finite = math.isfinite(loss) and math.isfinite(gnorm)
            rec = {"step": step, "train_loss": loss, "train_angle_deg": float(jnp.mean(aux["window_angle_deg"][0])),
                   "grad_norm": gnorm, "finite": finite}
            if finite:
                n_nonfinite = 0
                updates, opt_state = optimizer.update(grads, opt_state, theta)
                theta = optax.apply_updates(theta, updates)
            else:
                n_nonfinite += 1
            improved = False
            if val_fn is not None and (step % val_every == 0 or step == steps):
                vl, va = validate(theta)
                rec.update(val_loss=vl, val_angle_deg=va)
                if math.isfinite(vl) and vl < best_val * (1.0 - min_delta):
                    best_val, best_theta, best_step, bad, improved = vl, theta, step, 0, True
                else:
                    bad += 1
            elif val_fn is None:
                best_theta, best_step = theta, step
            rec.update(step_s=time.perf_counter() - t0, elapsed_s=time.perf_counter() - t_start)
            history.append(rec)
            if callback is not None:
                callback({**rec, "steps": steps, "val_loss": rec.get("val_loss"), "best_val": best_val,
                          "best_step": best_step, "improved": improved})
            stop = None
            if n_nonfinite >= 3:
                stop = "non-finite"
            elif patience is not None and val_fn is not None and bad >= patience:
                stop = "early-stopped"
            if on_save is not None:
                on_save(result("running" if stop is None and step < steps else (stop or "done")))
            if stop:
                status = stop
                break
    except KeyboardInterrupt:
        status = "interrupted"
        if on_save is not None:
            on_save(result(status))
    return result(status)


# ------------------------------------------------------------------------------------------------------
# tune / evaluate (CLI entry points)
# ------------------------------------------------------------------------------------------------------
class TuneResult(NamedTuple):
    """Output of :func:`tune`: experiment, best params, start params, optimisation result, gains path."""

    experiment: str
    params: Any
    start_params: Any
    result: OptimizeResult
    out_path: Optional[str]


def _start_params(experiment: str, base, start):
    if start is None:
        return base
    if isinstance(start, str):
        return load_gains(start, base, experiment=experiment)[1]
    if callable(start):
        return start(base)
    if isinstance(start, Mapping):
        return apply_gains(experiment, base, start)
    raise ValueError(f"start must be a gains JSON path, a dict of gains or a callable, got {type(start).__name__}")


class Problem(NamedTuple):
    """A tuning problem: the experiment :class:`Setup`, the bound parametrization of its gains, the loss
    and the (cached, jitted) loss function. ``objective(theta, keys) -> (loss, aux)``."""

    setup: Setup
    parametrization: P.BoundParametrization
    spec: LossSpec
    loss_fn: Callable
    checkpoint_segment: int

    def objective(self, theta, keys):
        return self.loss_fn(self.setup.scenario, self.parametrization.constrain(theta), keys)

    def theta0(self):
        return self.parametrization.init()

    def params(self, theta):
        return self.parametrization.constrain(theta)


def make_problem(experiment_name: str, *, loss: Optional[str] = None, transient_weight: float = 0.0,
                 duration: Optional[float] = None, config: Optional[Mapping] = None, freeze: Sequence[str] = (),
                 only: Optional[Sequence[str]] = None, masks: Optional[Mapping] = None, method: Optional[str] = None,
                 start=None, refine_schedule: Sequence[float] = (), checkpoint="auto",
                 step_remat: Optional[bool] = None, dtype=None, devices=None,
                 transforms: Optional[Mapping[str, P.Transform]] = None) -> Problem:
    """The :class:`Problem` :func:`tune` solves (arguments as there)."""
    overrides = dict(config or {})
    if duration is not None:
        overrides["duration"] = float(duration)
    s = setup(experiment_name, **overrides)
    if s.check_params:
        s.check_params(s.params)
    params0 = _start_params(experiment_name, s.params, start)
    if len(refine_schedule):
        fields = P.schedule_fields(experiment_name)
        if not fields:
            raise ValueError(f"refine_schedule: {experiment_name} has no piecewise-constant gain schedule")
        params0 = P.refine_schedule(params0, refine_schedule, fields)
    if s.check_params:
        s.check_params(params0)
    bound = P.for_experiment(experiment_name, freeze=freeze, only=only, masks=masks, method=method,
                             transforms=transforms).bind(params0)
    st, en = s.loss_windows["steady"]
    ts, te = s.loss_windows["transient"]
    spec = loss_spec(loss or s.loss_kind, steady_start=st, steady_end=en, transient_start=ts, transient_end=te,
                     w_transient=transient_weight)
    f = make_loss_fn(s.observer, duration=s.duration, dt=s.dt, spec=spec, hold=s.hold, dtype=dtype,
                     checkpoint=checkpoint, init_params=s.init_params, step_remat=step_remat, devices=devices)
    return Problem(s, bound, spec, f, segment_length(int(round(s.duration / s.dt)), checkpoint))


def tune(experiment_name: str, steps: int = 100, train_runs: int = 32, out_path: Optional[str] = "gains.json", *,
         seed: int = 0, batch_runs: Optional[int] = 8, val_runs: int = 16, val_every: int = 5,
         patience: Optional[int] = 4, lr: float = 0.05, clip: Optional[float] = 1.0, loss: Optional[str] = None,
         transient_weight: float = 0.0, duration: Optional[float] = None, config: Optional[Mapping] = None,
         freeze: Sequence[str] = (), only: Optional[Sequence[str]] = None, masks: Optional[Mapping] = None,
         method: Optional[str] = None, start=None, refine_schedule: Sequence[float] = (), checkpoint="auto",
         step_remat: Optional[bool] = None, dtype=None, callback: Optional[Callable[[dict], None]] = None,
         quiet: bool = False, devices=None, transforms: Optional[Mapping[str, P.Transform]] = None) -> TuneResult:
    """Tune an experiment's gains on simulated Monte Carlo runs (``jaxatt tune``).

    Args:
        experiment_name: a registered experiment (``"batista-ges"``, ``"batista-so3"``; see :data:`TARGETS`).
        steps: optimizer steps (each one gradient over ``batch_runs`` training runs).
        train_runs: training seeds: run indices 0 ... train_runs-1 of base ``seed`` (run k's key is
            ``fold_in(PRNGKey(seed), k)``, as ``monte_carlo``); validation (early stopping) uses the next
            ``val_runs`` indices. Evaluate on another ``seed`` (or higher run indices) to stay held out.
        out_path: gains JSON, rewritten atomically after every step (best-validation gains so far, the start
            gains, settings and history), so an interrupted run keeps what it found. None: no file.
        batch_runs: runs per gradient (minibatch of the training runs; None = all).
        val_every, patience: validation every ``val_every`` steps; stop after ``patience`` validations without
            improvement (None: never stop early).
        lr, clip: Adam learning rate (in the unconstrained space: 0.05 ~ 5 % change of a log-parametrized gain
            per step) and global-norm gradient clipping (None: off).
        loss: pointwise error (default: the experiment's, "angle_sq" for batista-*); ``transient_weight`` > 0
            adds the transient window (0 to the steady-state start) with that weight.
        duration: simulated horizon (s; default the paper's 3600 s); config: other Config overrides.
        freeze / only / masks / method / transforms: which gains are tuned and how (see
            :func:`jaxatt.parametrize.for_experiment`; ``transforms`` e.g. a :class:`~jaxatt.parametrize.LogBasis`
            that moves a whole schedule through a few numbers).
        start: starting gains (a gains JSON path, a dict of gains, or ``fn(params) -> params``); default the
            paper's.
        refine_schedule: extra switch times (s) inserted into the experiment's gain schedules before tuning
            (:func:`jaxatt.parametrize.refine_schedule`): the start observer is unchanged, the tuner may then
            vary the gains on the new intervals (e.g. batista-ges after Table 1's last switch at 720 s).
        checkpoint, step_remat: segment length of the checkpointed scan (:func:`segment_length`) and per-step
            rematerialisation (:func:`make_loss_fn`).
        callback: ``callback(info)`` after every step; default prints a line on stderr (unless ``quiet``).
        devices: split each minibatch / validation batch of runs over these devices (:mod:`jaxatt.sharding`;
            default every visible device; 1 = one device); batch_runs and val_runs must be multiples of their
            count.
    Returns a :class:`TuneResult`; ``result.status`` is "done", "early-stopped", "interrupted" or "non-finite".
    """
    jax.config.update("jax_enable_x64", True)
    if steps < 0 or train_runs < 1 or val_runs < 0:
        raise ValueError(f"need steps >= 0, train_runs >= 1, val_runs >= 0; got {steps}, {train_runs}, {val_runs}")
    prob = make_problem(experiment_name, loss=loss, transient_weight=transient_weight, duration=duration,
                        config=config, freeze=freeze, only=only, masks=masks, method=method, start=start,
                        refine_schedule=refine_schedule, checkpoint=checkpoint, step_remat=step_remat, dtype=dtype,
                        devices=devices, transforms=transforms)
    s, bound, spec = prob.setup, prob.parametrization, prob.spec
    params0 = bound.base
    train_keys = montecarlo.run_keys(seed, list(range(train_runs)))
    val_keys = montecarlo.run_keys(seed, list(range(train_runs, train_runs + val_runs))) if val_runs else None
    n_steps = int(round(s.duration / s.dt))
    settings = {"steps": steps, "train_runs": train_runs, "train_run_indices": [0, train_runs],
                "val_runs": val_runs, "val_run_indices": [train_runs, train_runs + val_runs], "seed": seed,
                "batch_runs": batch_runs, "val_every": val_every, "patience": patience, "lr": lr, "clip": clip,
                "optimizer": "adam" + (f" + clip_by_global_norm({clip})" if clip else ""),
                "loss": spec.describe(), "duration_s": s.duration, "dt_s": s.dt, "steps_per_run": n_steps,
                "checkpoint_segment": prob.checkpoint_segment,
                "tunable": {fld: tr.describe() for fld, tr in bound.transforms.items()},
                "masks": {fld: m.tolist() for fld, m in bound.masks.items()}, "n_tunable": bound.n_free()}
    start_gains = gains_to_dict(experiment_name, params0)
    from .report import environment

    env = environment()
    if not quiet:
        print(f"tune {experiment_name}: {bound.n_free()} tunable numbers in {sorted(bound.transforms)}; "
              f"{train_runs} training runs (batch {batch_runs or train_runs}), {val_runs} validation runs, "
              f"{s.duration:g} s at {1 / s.dt:g} Hz ({n_steps} steps, checkpoint segment "
              f"{prob.checkpoint_segment or 'off'}); loss {spec.describe()['kind']} over "
              f"{[w[0] for w in spec.windows]}; the first step compiles", file=sys.stderr, flush=True)

    def on_save(res: OptimizeResult):
        if not out_path:
            return
        params = bound.constrain(res.best_theta)
        save_gains(out_path, experiment_name, params, config=s.config, extra={
            "status": res.status, "best_step": res.best_step, "best_val_loss": res.best_val,
            "start_val_loss": res.start_val, "start_gains": start_gains, "tuning": settings,
            "history": res.history, "notes": list(s.notes), "environment": env})

    cb = callback if callback is not None else (None if quiet else print_progress)
    res = optimize(prob.objective, prob.theta0(), steps=steps, train_keys=train_keys, batch_runs=batch_runs,
                   val_keys=val_keys, val_every=val_every, patience=patience, lr=lr, clip=clip, shuffle_seed=seed,
                   constrain=bound.constrain, callback=cb, on_save=on_save, jit=False)
    if steps == 0:
        on_save(res)
    best = bound.constrain(res.best_theta)
    if not quiet:
        n_done = len([h for h in res.history if "train_loss" in h])
        msg = f"tune {experiment_name}: {res.status} after {n_done} steps"
        if res.best_val is not None:
            msg += (f"; validation loss {res.start_val:.5g} -> {res.best_val:.5g} (step {res.best_step}, "
                    f"{100 * (1 - res.best_val / res.start_val):.1f} % lower)")
        print(msg + (f"; gains written to {out_path}" if out_path else ""), file=sys.stderr, flush=True)
    return TuneResult(experiment_name, best, params0, res, out_path)


def summarise(per_run: Mapping[str, Any]) -> dict:
    """metric -> {mean, std, min, max, per_run}: the layout of ``jaxatt reproduce``'s JSON."""
    out = {}
    for k, v in per_run.items():
        v = np.asarray(v, float)
        out[k] = {"mean": float(np.mean(v)), "std": float(np.std(v)), "min": float(np.min(v)),
                  "max": float(np.max(v)), "per_run": v.tolist()}
    return out


def _mc(s: Setup, params, runs, seed, chunk, dtype, on_chunk=None):
    extra = {}  # only when used: monte_carlo's windows / init_params are recent additions
    if s.windows:
        extra["windows"] = s.windows
    if s.init_params is not None:
        extra["init_params"] = s.init_params
    return montecarlo.monte_carlo(s.scenario, s.observer, params, runs=runs, duration=s.duration, dt=s.dt, seed=seed,
                                  errors_fn=s.errors_fn, window_start=s.window_start, hold=s.hold, chunk=chunk,
                                  dtype=dtype, on_chunk=on_chunk, **extra)


def evaluate(experiment_name: str, gains_path: Optional[str], runs: int = 100, seed: int = 1,
             json_path: Optional[str] = None, *, duration: Optional[float] = None, config: Optional[Mapping] = None,
             chunk: int = 250, dtype=None, compare_paper: bool = True, quiet: bool = False) -> dict:
    """Monte Carlo of an experiment with the gains of ``gains_path`` (``jaxatt evaluate``).

    Runs ``runs`` runs of base ``seed`` (run k: ``fold_in(PRNGKey(seed), k)``) of the experiment's paper
    configuration (or ``duration`` / ``config`` overrides) through :func:`jaxatt.montecarlo.monte_carlo` and
    returns (and writes to ``json_path``, atomically, after every chunk) the same layout as ``jaxatt
    reproduce``: ``metrics.<name>.mean/std/min/max/per_run``, plus ``gains`` (the evaluated gains) and, with
    ``compare_paper``, ``paper_gains_metrics`` (the paper's gains on the same runs) and ``comparison`` (mean
    of each metric, tuned / paper). ``gains_path`` None evaluates the paper's gains. Warns when the runs
    overlap the training or validation runs recorded in the gains file.
    """
    jax.config.update("jax_enable_x64", True)
    if runs < 1:
        raise ValueError(f"runs must be >= 1, got {runs}")
    overrides = dict(config or {})
    if duration is not None:
        overrides["duration"] = float(duration)
    s = setup(experiment_name, **overrides)
    dtype = jnp.float64 if dtype is None else dtype
    payload_gains = None
    if gains_path:
        _, params, payload_gains = load_gains(gains_path, s.params, experiment=experiment_name)
        tun = payload_gains.get("tuning", {})
        if tun.get("seed") == seed:
            used = set(range(*tun.get("train_run_indices", [0, 0]))) | set(range(*tun.get("val_run_indices", [0, 0])))
            overlap = used & set(range(runs))
            if overlap and not quiet:
                print(f"warning: {len(overlap)} evaluation runs were used for tuning (same seed {seed}); "
                      "use another --seed for held-out numbers", file=sys.stderr)
    else:
        params = s.params
    if s.check_params:
        s.check_params(params)
    title = f"{experiment_name} evaluate"
    config_d = _config_dict(s.config)
    config_d.update(runs=runs, seed=seed, dtype=str(np.dtype(dtype)), chunk=chunk, gains=gains_path or "paper")
    from .report import environment

    base = {"experiment": title, "config": config_d, "environment": environment(), "notes": list(s.notes),
            "gains": gains_to_dict(experiment_name, params), "gains_path": gains_path}
    t0 = time.perf_counter()

    def on_chunk(res):
        if not quiet:
            print(f"  {len(res.run_indices)}/{runs} runs done, {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        _write_json(json_path, {**base, "complete": False, "runs_done": len(res.run_indices),
                                "metrics": summarise(res.per_run), "timing": {"wall_s": time.perf_counter() - t0}})

    res = _mc(s, params, runs, seed, chunk, dtype, on_chunk)
    wall = time.perf_counter() - t0
    metrics = summarise(res.per_run)
    payload = {**base, "complete": res.complete, "runs_done": len(res.run_indices), "metrics": metrics,
               "paper": dict(s.paper), "timing": {"wall_s": wall, "runs": len(res.run_indices),
                                                  "steps_per_run": int(round(s.duration / s.dt))}}
    if compare_paper and gains_path and res.complete:
        ref = _mc(s, s.params, runs, seed, chunk, dtype)
        pm = summarise(ref.per_run)
        payload["paper_gains_metrics"] = pm
        payload["comparison"] = {k: {"tuned": metrics[k]["mean"], "paper_gains": pm[k]["mean"],
                                     "ratio": (metrics[k]["mean"] / pm[k]["mean"] if pm[k]["mean"] else None)}
                                 for k in metrics if k in pm}
    if not quiet:
        print(f"{title}: {len(res.run_indices)} runs x {s.duration:g} s, seed {seed}, gains "
              f"{gains_path or 'paper'}" + ("" if res.complete else "  [INTERRUPTED: partial results]"))
        keys = [k for k in ("mean_angle_error_deg", "max_angle_error_deg", "final_angle_error_deg") if k in metrics]
        keys += [k for k in metrics if k.startswith(("mae_", "rmse_"))][:12]
        print(f"{'metric':34s} {'mean':>12s} {'std':>10s}" + (f" {'paper gains':>12s} {'ratio':>7s}"
                                                               if "comparison" in payload else ""))
        for k in keys:
            line = f"{k:34s} {metrics[k]['mean']:12.5g} {metrics[k]['std']:10.3g}"
            if "comparison" in payload:
                c = payload["comparison"][k]
                line += f" {c['paper_gains']:12.5g} {c['ratio']:7.3f}"
            print(line)
        print(f"wall {wall:.1f} s")
    _write_json(json_path, payload)
    if json_path and not quiet:
        print(f"results written to {json_path}")
    return payload
