"""Running observers: on a recorded log (:func:`run`), and fused with the simulator over many seeds
(:func:`simulate`, :func:`monte_carlo`).

The simulation of one run is a single ``lax.scan``: truth (exact omega(t), Magnus step), sensor samples and the
observer step are computed together, and metrics are reduced on the fly (:mod:`jaxatt.metrics`), so a run of
hundreds of thousands of steps holds only its state. Monte Carlo is ``vmap`` of that scan over PRNG keys, in
chunks of runs; run k uses ``fold_in(PRNGKey(seed), k)`` whatever the chunk or batch size, so seed k alone and
seed k inside a batch of 1000 give the same run. Decimated traces are kept only when asked for.
"""
from __future__ import annotations

import functools
import math
import time
from typing import Any, Callable, Dict, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from . import metrics as M
from . import progress as _progress
from . import sharding as _sharding
from .integrate import Interval
from .observers.base import ImuSample, Observer
from .sim import imu

__all__ = ["run", "simulate", "simulate_log", "monte_carlo", "MonteCarloResult", "check_dt", "run_keys",
           "INIT_PARAMS_BLOCK"]

#: fold_in index of a run's key for its ``init_params`` draw (noise uses 0 ... and imu.INIT_BLOCK = 2**31 - 1).
INIT_PARAMS_BLOCK = 2**31 - 2


def check_dt(dt) -> float:
    dt = float(dt)
    if not math.isfinite(dt) or dt <= 0:
        raise ValueError(f"dt must be a finite positive number of seconds, got {dt}")
    return dt


def _check_samples(samples: ImuSample):
    g = np.shape(samples.gyr)
    if len(g) != 2 or g[1] != 3:
        raise ValueError(f"samples.gyr must have shape (T, 3), got {g}")
    if np.shape(samples.t) != (g[0],):
        raise ValueError(f"samples.t must have shape (T,) = ({g[0]},), got {np.shape(samples.t)}")
    for name in ("acc", "mag"):
        v = getattr(samples, name, None)
        if v is not None and np.shape(v) != g:
            raise ValueError(f"samples.{name} must have the shape of gyr {g}, got {np.shape(v)}")
    if g[0] < 2:
        raise ValueError("a log needs at least two samples")


def run(observer: Observer, params, samples: ImuSample, dt=None, *, hold: str = "zoh", validate: Optional[Callable] = None):
    """Run ``observer`` over a log and return its stacked outputs at t_1 ... t_{T-1}.

    Args:
        samples: ImuSample of arrays, time-major (T,) / (T, 3); body-frame gyro (rad/s) and vector sensors.
            NaN marks a missing reading (each observer documents what it does then).
        dt: step (s); None takes dt_k = t_{k+1} - t_k from the timestamps.
        hold: "zoh" (sample k held over [t_k, t_k+1]) or "linear" (interpolate to sample k+1).
        validate: optional parameter check (e.g. ``batista_ges.check_params``), run on concrete params.
    """
    _check_samples(samples)
    if hold not in ("zoh", "linear"):
        raise ValueError(f"hold must be 'zoh' or 'linear', got {hold!r}")
    if validate is not None:
        validate(params)
    t = np.asarray(samples.t, float)
    if dt is None:
        dts = np.diff(t)
        if not np.all(np.isfinite(dts)) or np.any(dts <= 0):
            raise ValueError("timestamps must be finite and strictly increasing")
    else:
        dts = np.full(len(t) - 1, check_dt(dt))
    return _run_jit(observer, hold)(params, samples, jnp.asarray(dts, jnp.asarray(samples.gyr).dtype))


@functools.lru_cache(maxsize=32)
def _run_jit(observer: Observer, hold: str):
    """Jitted log runner, cached per (observer, hold) so repeated calls with new params do not recompile."""
    @jax.jit
    def go(params, samples, dts):
        first = jax.tree_util.tree_map(lambda a: a[0], samples)
        state = observer.init(params, first)
        cur = jax.tree_util.tree_map(lambda a: a[:-1], samples)
        nxt = jax.tree_util.tree_map(lambda a: a[1:], samples)

        def body(st, xs):
            u0, u1, dt = xs
            u = Interval(u0, u1) if hold == "linear" else u0
            return observer.step(params, st, u, dt)

        _, outs = jax.lax.scan(body, state, (cur, nxt, dts))
        return outs

    return go


# ------------------------------------------------------------------------------------------------------
# Simulation fused with the observer
# ------------------------------------------------------------------------------------------------------
ErrorsFn = Callable[[imu.Truth, Any], Dict[str, jax.Array]]


def default_trace(truth: imu.Truth, out, errors: Dict[str, jax.Array], angle_deg) -> Dict[str, jax.Array]:
    """Trace record: time, angle error (deg) and the norm of every named error."""
    rec = {"t": truth.t, "angle_error_deg": angle_deg}
    for k, v in errors.items():
        rec[f"norm_{k}"] = jnp.sqrt(jnp.sum(v**2))
    return rec


def _cast(tree, dtype):
    return jax.tree_util.tree_map(lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, tree)


def _make_batch_fn(scenario, observer: Observer, params, *, n_steps: int, dt: float, errors_fn: ErrorsFn,
                   window_start: float, hold: str, trace_every: int, trace_fn, obs_dtype, sim_dtype,
                   windows: tuple = (), init_params=None):
    """Build ``batch_run(keys) -> (summary, trace, final_state)`` for a batch of run keys (scenario and
    params closed over; :func:`_batch_fn_jit` is the cached, jitted form that takes them as arguments)."""
    fn = _batch_fn(observer, n_steps=n_steps, dt=dt, errors_fn=errors_fn, window_start=window_start, hold=hold,
                   trace_every=trace_every, trace_fn=trace_fn, obs_dtype=obs_dtype, sim_dtype=sim_dtype,
                   windows=windows, init_params=init_params)
    return lambda keys: fn(scenario, params, keys)


@functools.lru_cache(maxsize=64)
def _batch_fn_jit(observer: Observer, mesh=None, **static):
    """``jit(batch_run(scenario, params, keys))``, cached on the observer, the device mesh (None: one device)
    and every static setting, so calls with new params, a new scenario of the same structure, or new seeds do
    not compile again. With a mesh the runs are split over its devices (:func:`jaxatt.sharding.shard_runs`)."""
    return jax.jit(_sharding.shard_runs(_batch_fn(observer, **static), mesh))


def _batch_fn(observer: Observer, *, n_steps: int, dt: float, errors_fn: ErrorsFn, window_start: float, hold: str,
              trace_every: int, trace_fn, obs_dtype, sim_dtype, windows: tuple = (), init_params=None,
              progress=False):
    """``batch_run(scenario, params, keys) -> (summary, trace, final_state)`` for a batch of run keys.

    ``windows`` (((name, start_s, end_s), ...)) adds per-run MAE and RMSE of every named error over each window
    (:func:`jaxatt.metrics.moments_summary`). ``init_params(params, key) -> params`` (optional) gives each run
    its own parameters for ``observer.init`` only (e.g. a random initial estimate), from a key of the run
    (``fold_in(run_key, INIT_PARAMS_BLOCK)``) that no noise stream uses. ``progress``: report every finished
    noise block to :func:`jaxatt.progress.block_hook` (``jax.debug.callback``, ordered when "ordered" - one
    device only -, unordered when "unordered"; nothing when False).

    The scenario provides the simulator interface ``n_channels``, ``truth_at(r, t)``, ``propagate(r, t, dt)``
    and ``sample(truth, noise, dt)`` (see :class:`jaxatt.sim.imu.ImuScenario`); its truth has ``t`` and ``r``.

    Layout: the scan runs outside ``vmap`` and every per-run array carries the batch on its LAST axis
    (``vmap(..., in_axes=-1, out_axes=-1)`` inside the step). Vectors are then (3, B): each component is a
    contiguous row of B numbers, which XLA vectorises about twice as well as (B, 3).
    """
    L = imu.NOISE_BLOCK
    n_full, rem = divmod(n_steps, L)
    if trace_every and L % trace_every:
        raise ValueError(f"trace_every must divide {L}, got {trace_every}")
    dt_obs = np.asarray(dt, obs_dtype)
    bl = dict(in_axes=-1, out_axes=-1)

    def batch_run(scenario, params, keys):
        scn = _cast(scenario, sim_dtype)
        p = _cast(params, obs_dtype)
        nch = scn.n_channels

        def init_one(key):
            truth0 = scn.truth_at(scn.r0, jnp.zeros((), sim_dtype))
            s0 = _cast(scn.sample(truth0, imu.initial_noise(key, sim_dtype, nch), dt), obs_dtype)
            if init_params is None:
                st0 = observer.init(p, s0)
            else:
                st0 = observer.init(_cast(init_params(p, jax.random.fold_in(key, INIT_PARAMS_BLOCK)), obs_dtype), s0)

            def probe():
                _, out = observer.step(p, st0, s0, dt_obs)
                return errors_fn(truth0, out)

            err_shapes = {k: v.shape for k, v in jax.eval_shape(probe).items()}
            mom = M.moments_init(err_shapes, len(windows), obs_dtype) if windows else None
            return scn.r0, s0, st0, M.window_init(err_shapes, obs_dtype), mom

        def step_one(k, r, s_prev, st, acc, mom, noise):
            t_k = k.astype(sim_dtype) * dt
            t_next = (k + 1).astype(sim_dtype) * dt
            r_next = scn.propagate(r, t_k, dt)
            truth = scn.truth_at(r_next, t_next)
            s_next = _cast(scn.sample(truth, noise, dt), obs_dtype)
            u = Interval(s_prev, s_next) if hold == "linear" else s_prev
            st, out = observer.step(p, st, u, dt_obs)
            errors = errors_fn(truth, out)
            angle = M.angle_error_deg(truth.r.astype(obs_dtype), out.r)
            acc = M.window_update(acc, errors, angle, t_next >= window_start)
            if windows:
                mom = M.moments_update(mom, errors, t_next, windows, 0.5 * dt)
            rec = trace_fn(truth, out, errors, angle) if trace_every else None
            return r_next, s_next, st, acc, mom, rec

        step_b = jax.vmap(step_one, in_axes=(None, -1, -1, -1, -1, -1, -1), out_axes=-1)
        carry = (jnp.zeros((), jnp.int32),) + jax.vmap(init_one, out_axes=-1)(keys)  # keys: (B, 2)

        def step(carry, noise):
            k = carry[0]
            r, s, st, acc, mom, rec = step_b(*carry, noise)
            return (k + 1, r, s, st, acc, mom), rec

        def block(carry, j, length):
            noise = jax.vmap(lambda key: imu.noise_block(key, j, sim_dtype, nch)[:length], out_axes=-1)(keys)
            carry, rec = jax.lax.scan(step, carry, noise)  # rec: (length, ..., B)
            if progress:
                jax.debug.callback(_progress.block_hook, j, ordered=progress == "ordered")
            if trace_every:
                rec = jax.tree_util.tree_map(lambda a: a[trace_every - 1 :: trace_every], rec)
            return carry, rec

        traces = []
        if n_full:
            carry, rec = jax.lax.scan(lambda c, j: block(c, j, L), carry, jnp.arange(n_full))
            if trace_every:
                traces.append(jax.tree_util.tree_map(lambda a: a.reshape((-1,) + a.shape[2:]), rec))
        if rem:
            carry, rec = block(carry, n_full, rem)
            if trace_every:
                traces.append(rec)
        summary = jax.vmap(M.window_summary, **bl)(carry[4])
        if windows:
            mom = jax.vmap(lambda m: M.moments_summary(m, windows), **bl)(carry[5])
            summary.update({k: jnp.moveaxis(v, -1, 0) for k, v in mom.items()})  # runs first, as the scalars
        trace = None
        if trace_every:
            trace = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a, 0), *traces) if len(traces) > 1 else traces[0]
            trace = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, -1, 0), trace)  # (B, n_trace, ...)
        state = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, -1, 0), carry[3])
        return summary, trace, state

    return batch_run


def _extras(windows, init_params, progress=False) -> dict:
    """Static extras of the batch runner, only when used (so the cache key and graph of existing calls are
    unchanged)."""
    ex = {"progress": progress} if progress else {}
    if windows:
        ex["windows"] = M.check_windows(windows)
    if init_params is not None:
        ex["init_params"] = init_params
    return ex


def run_keys(seed: int, run_indices) -> jax.Array:
    """PRNG key of each run: fold_in(PRNGKey(seed), k), independent of batching."""
    base = jax.random.PRNGKey(seed)
    return jax.vmap(lambda k: jax.random.fold_in(base, k))(jnp.asarray(run_indices, jnp.uint32))


def _dtypes(dtype):
    obs = jnp.dtype(dtype) if dtype is not None else jnp.result_type(float)
    sim = jnp.result_type(float)  # float64 when x64 is enabled: truth is always as precise as available
    return obs, sim


def simulate(scenario, observer: Observer, params, *, duration: float, dt: float, seed: int = 0, run_index: int = 0,
             errors_fn: ErrorsFn, window_start: float = 0.0, hold: str = "zoh", trace_every: int = 1,
             trace_fn=None, dtype=None, windows=(), init_params=None):
    """One simulated run; returns (summary dict, trace dict of arrays, final observer state).

    ``trace_fn(truth, out, errors, angle_deg) -> dict`` picks what is recorded every ``trace_every`` steps
    (default: time, angle error, error norms). ``windows`` and ``init_params`` as in :func:`monte_carlo`.
    """
    dt = check_dt(dt)
    n_steps = int(round(duration / dt))
    obs_dtype, sim_dtype = _dtypes(dtype)
    fn = _batch_fn_jit(observer, n_steps=n_steps, dt=dt, errors_fn=errors_fn, window_start=float(window_start),
                       hold=hold, trace_every=trace_every, trace_fn=trace_fn or default_trace, obs_dtype=obs_dtype,
                       sim_dtype=sim_dtype, **_extras(windows, init_params))
    summary, trace, state = fn(scenario, params, run_keys(seed, [run_index]))
    first = lambda a: np.asarray(a)[0]  # noqa: E731
    scalar = lambda a: float(first(a)) if np.ndim(a) == 1 else first(a)  # noqa: E731
    return ({k: scalar(v) for k, v in summary.items()},
            jax.tree_util.tree_map(first, trace) if trace is not None else None,
            jax.tree_util.tree_map(lambda a: a[0], state))


def simulate_log(scenario, *, duration: float, dt: float, seed: int = 0, run_index: int = 0):
    """A simulated log (samples at t_0 ... t_N) and its truth, with the same noise stream as :func:`simulate`.

    Returns (ImuSample of (N+1,)/(N+1, 3) arrays, Truth of stacked arrays). Holds the whole trajectory:
    meant for short runs, tests and for feeding :func:`run`.
    """
    dt = check_dt(dt)
    n_steps = int(round(duration / dt))
    sim_dtype = jnp.result_type(float)
    key = run_keys(seed, [run_index])[0]
    n_blocks = -(-n_steps // imu.NOISE_BLOCK)

    @jax.jit
    def go(scn):
        nch = scn.n_channels
        truth0 = scn.truth_at(scn.r0, jnp.zeros((), sim_dtype))
        s0 = scn.sample(truth0, imu.initial_noise(key, sim_dtype, nch), dt)
        noise = jax.vmap(lambda j: imu.noise_block(key, j, sim_dtype, nch))(jnp.arange(n_blocks))
        noise = noise.reshape(-1, nch)[:n_steps]

        def body(carry, xs):
            r, k = carry
            r_next = scn.propagate(r, k.astype(sim_dtype) * dt, dt)
            truth = scn.truth_at(r_next, (k + 1).astype(sim_dtype) * dt)
            return (r_next, k + 1), (truth, scn.sample(truth, xs, dt))

        _, (truths, samples) = jax.lax.scan(body, (scn.r0, jnp.zeros((), jnp.int32)), noise)
        cat = lambda a, b: jnp.concatenate([a[None], b], 0)  # noqa: E731
        return (jax.tree_util.tree_map(cat, s0, samples), jax.tree_util.tree_map(cat, truth0, truths))

    return go(_cast(scenario, sim_dtype))


class MonteCarloResult(NamedTuple):
    """Per-run summaries (name -> (n_runs,) numpy array), optional decimated traces (name -> (n_runs, n)),
    the run indices done, wall time (s), and whether every requested run finished."""

    per_run: Dict[str, np.ndarray]
    traces: Optional[Dict[str, np.ndarray]]
    run_indices: np.ndarray
    wall_s: float
    complete: bool


def monte_carlo(scenario, observer: Observer, params, *, runs: int, duration: float, dt: float, seed: int = 0,
                errors_fn: ErrorsFn, window_start: float = 0.0, hold: str = "zoh", chunk: int = 250,
                trace_every: int = 0, trace_fn=None, dtype=None, validate: Optional[Callable] = None,
                on_chunk: Optional[Callable[[MonteCarloResult], None]] = None, windows=(),
                init_params: Optional[Callable] = None, devices=None, progress=None) -> MonteCarloResult:
    """``runs`` simulated runs, vmapped in chunks of ``chunk`` runs, metrics reduced on the fly.

    ``windows`` = ((name, start_s, end_s), ...): per-run ``mae_{name}_{error}`` and ``rmse_{name}_{error}`` of
    every error of ``errors_fn`` over the samples with start_s <= t <= end_s (shape of the error).
    ``init_params(params, key) -> params``: per-run parameters for ``observer.init`` only (e.g. a random initial
    estimate drawn from ``key``); must be a hashable callable (a module-level function), the jitted runner is
    cached on it. Run k's key is the same for every observer, so observers compared on the same seed see the
    same noise and the same initial estimates.

    After each chunk ``on_chunk(partial_result)`` is called (save, progress). On KeyboardInterrupt the runs
    finished so far are returned with ``complete=False``: nothing computed is lost.

    ``devices`` (default: every visible device): the runs of each chunk are split over them
    (:mod:`jaxatt.sharding`; the chunk is rounded up to a multiple of the device count, padding runs dropped);
    ``devices=1`` runs on one device. The result does not depend on the devices beyond rounding.
    ``progress``: True for a line on stderr updated from inside the scan every 1000 steps, or a callable
    reporter (:mod:`jaxatt.progress`); None: off.
    Memory per chunk: the state and accumulators of ``chunk`` runs, one noise block (chunk x 1000 x 6) and
    the decimated traces; never the per-step trajectories.
    """
    dt = check_dt(dt)
    if runs < 1:
        raise ValueError(f"runs must be >= 1, got {runs}")
    if hold not in ("zoh", "linear"):
        raise ValueError(f"hold must be 'zoh' or 'linear', got {hold!r}")
    if validate is not None:
        validate(params)
    n_steps = int(round(duration / dt))
    if n_steps < 1:
        raise ValueError(f"duration must be at least one step, got {duration} s with dt = {dt} s")
    obs_dtype, sim_dtype = _dtypes(dtype)
    chunk = max(1, min(chunk, runs))
    mesh = _sharding.seed_mesh(devices)
    if mesh is not None:
        chunk = -(-chunk // mesh.size) * mesh.size  # a multiple of the device count
    reporter = _progress.make_reporter(progress)
    # ordered host callbacks are not supported on several devices: there the reports may arrive out of order
    # and jaxatt.progress keeps them monotone
    hook = False if reporter is None else ("ordered" if mesh is None else "unordered")
    fn = _batch_fn_jit(observer, mesh, n_steps=n_steps, dt=dt, errors_fn=errors_fn, window_start=float(window_start),
                       hold=hold, trace_every=trace_every, trace_fn=trace_fn or default_trace, obs_dtype=obs_dtype,
                       sim_dtype=sim_dtype, **_extras(windows, init_params, hook))
    batched = lambda k: _sharding.to_host(fn(scenario, params, k)[:2])  # noqa: E731 (final states dropped)
    prog = _progress._Run(reporter, runs, n_steps, imu.NOISE_BLOCK) if reporter is not None else None
    per_run: Dict[str, list] = {}
    traces: Dict[str, list] = {}
    done: list = []
    t0 = time.perf_counter()

    def result(complete):
        pr = {k: np.concatenate(v) for k, v in per_run.items()}
        tr = {k: np.concatenate(v) for k, v in traces.items()} if traces else None
        return MonteCarloResult(pr, tr, np.asarray(done, int), time.perf_counter() - t0, complete)

    try:
        for start in range(0, runs, chunk):
            idx = np.arange(start, min(start + chunk, runs))
            pad = chunk - len(idx)  # keep one compiled shape: pad the last chunk, drop the padding
            keys = run_keys(seed, np.concatenate([idx, np.full(pad, idx[-1])]))
            if prog is not None:
                prog.chunk_runs, prog.chunk_steps = len(idx), 0
            with _progress.active(prog):
                summ, trace = batched(keys)
            if prog is not None:
                prog.runs_done += len(idx)
                prog.chunk_runs = 0
                prog.report(0)
            for k, v in summ.items():
                per_run.setdefault(k, []).append(np.asarray(v)[: len(idx)])
            if trace is not None:
                for k, v in trace.items():
                    traces.setdefault(k, []).append(np.asarray(v)[: len(idx)])
            done.extend(idx.tolist())
            if on_chunk is not None:
                on_chunk(result(len(done) == runs))
    except KeyboardInterrupt:
        if not done:
            raise
        return result(False)
    return result(True)
