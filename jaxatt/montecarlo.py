"""Running observers: on a recorded log (:func:`run`), and fused with the simulator over many seeds
(:func:`simulate`, :func:`monte_carlo`). Every function here is a use of the one scan, :mod:`jaxatt.engine`.

The simulation of one run is a single ``lax.scan``: truth (exact omega(t), Magnus step), sensor samples and the
observer step are computed together, and metrics are reduced on the fly (:mod:`jaxatt.metrics`), so a run of
hundreds of thousands of steps holds only its state. Monte Carlo is ``vmap`` of that scan over PRNG keys, in
chunks of runs; run k uses ``fold_in(PRNGKey(seed), k)`` whatever the chunk or batch size, so seed k alone and
seed k inside a batch of 1000 give the same run. Decimated traces are kept only when asked for.

Alignment (:mod:`jaxatt.engine`): T samples give T estimates, estimate 0 being ``init``'s; the window metrics
count estimates 1 ... T-1 (the steps), traces start at estimate 0.
"""

from __future__ import annotations

import functools
import math
import time
from typing import Any, Callable, Dict, Mapping, NamedTuple, Optional, Tuple, Union

import jax
import jax.numpy as jnp
import numpy as np

from . import engine
from . import metrics as M
from . import progress as _progress
from . import sharding as _sharding
from .engine import INIT_PARAMS_BLOCK
from .types import MAX_RUNS, ImuSample, Observer, check_seed, check_step_count, check_window_start, shown

__all__ = [
    "run",
    "simulate",
    "simulate_log",
    "monte_carlo",
    "metrics_fn",
    "MonteCarloResult",
    "save_runs",
    "load_runs",
    "spec_differences",
    "load_result",
    "check_dt",
    "check_observer",
    "whole_steps",
    "run_keys",
    "seed_key",
    "INIT_PARAMS_BLOCK",
    "metrics_reducer",
    "default_trace",
    "log_runner",
]


def check_seconds(name: str, value) -> float:
    """``value`` as a float: a finite number of seconds > 0 (ValueError naming ``name`` otherwise)."""
    try:
        if isinstance(value, (str, bytes, bool)):
            raise TypeError
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number of seconds, got {shown(value)}") from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a finite positive number of seconds, got {value}")
    return v


def check_observer(observer) -> Observer:
    """``observer`` if it is a :class:`jaxatt.types.Observer` (ValueError saying how to get one otherwise)."""
    if not isinstance(observer, Observer):
        hint = (
            f": jaxatt.observers.registry.get({observer!r}).make() builds it (or jaxatt.filter / jaxatt.monte_carlo "
            "take the name)"
            if isinstance(observer, str)
            else ""
        )
        raise ValueError(f"observer must be a jaxatt.Observer(init, step), got {type(observer).__name__}{hint}")
    if observer.hold is not None:
        try:
            engine.check_hold(observer.hold)
        except ValueError as e:
            raise ValueError(f"observer {observer.name!r}: Observer.hold: {e}") from None
    return observer


def check_obs_dtype(dtype):
    """The observer's arithmetic: None (JAX's default float), float32, or float64 (with x64 on)."""
    if dtype is None:
        return None
    from .api import compute_dtype  # the front door's rule, one copy (imported when it runs: no cycle)

    return compute_dtype(dtype=dtype)


def check_dt(dt) -> float:
    """``dt`` as a float: finite and > 0 seconds (ValueError otherwise)."""
    return check_seconds("dt", dt)


def whole_steps(duration: float, dt: float) -> int:
    """The number of steps of dt (s) in ``duration`` (s): ValueError naming both unless it is a whole number, to
    the rounding of a float32 dt (np.float32(0.01) is 0.00999999977 s: 60 s are 6000.0001 of its steps)."""
    n_steps = check_step_count(duration, dt)
    if abs(float(duration) / float(dt) - n_steps) > 1e-6 + 5e-7 * n_steps:
        raise ValueError(f"duration ({duration:g} s) must be a whole number of steps of dt = {float(dt)!r} s")
    return n_steps


def check_duration(duration) -> float:
    """``duration`` as a float: finite and > 0 seconds (ValueError otherwise)."""
    return check_seconds("duration", duration)


def check_count(name: str, value, minimum: int = 0, maximum: Optional[int] = None) -> int:
    """``value`` as an int in [``minimum``, ``maximum``] (a whole number: 3 and 3.0 pass, 1.5, True and "3" do
    not)."""
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
    if not ok and isinstance(value, (float, np.floating)) and float(value).is_integer():
        ok, value = True, int(value)
    if not ok:
        raise ValueError(f"{name} must be a whole number, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    if maximum is not None and value > maximum:
        raise ValueError(f"{name} must be <= {maximum}, got {value}")
    return int(value)


# ------------------------------------------------------------------------------------------------------
# A recorded log
# ------------------------------------------------------------------------------------------------------
def _check_samples(samples):
    if not (hasattr(samples, "_fields") and "t" in samples._fields and "gyr" in samples._fields):
        raise ValueError(
            "samples must be a jaxatt.types.ImuSample(t, gyr, acc, mag) (or VectorSample) of arrays, got "
            f"{type(samples).__name__}"
        )
    g = np.shape(samples.gyr)
    if len(g) != 2 or g[1] != 3:
        raise ValueError(f"samples.gyr must have shape (T, 3), got {g}")
    if np.shape(samples.t) != (g[0],):
        raise ValueError(
            f"samples.t and samples.gyr must have one row per sample: t has shape {np.shape(samples.t)}, gyr {g}"
        )
    if isinstance(samples, ImuSample):
        for name in ("acc", "mag"):
            v = getattr(samples, name)
            if v is not None and np.shape(v) != g:
                raise ValueError(f"samples.{name} must have the shape of gyr {g}, got {np.shape(v)}")
    else:
        for name, v in samples._asdict().items():
            if v is not None and np.shape(v)[:1] != (g[0],):
                raise ValueError(f"samples.{name} must have {g[0]} rows (one per sample), got shape {np.shape(v)}")
    if g[0] < 2:
        raise ValueError("a log needs at least two samples")


#: what :class:`jaxatt.engine.Simulated` asks of a scenario (:class:`jaxatt.sim.imu.ImuScenario`)
SCENARIO_FIELDS = ("r0", "n_channels", "truth_at", "propagate", "sample")


def check_scenario(scenario) -> None:
    """ValueError (one line) unless ``scenario`` is a simulated scenario (e.g. ``jaxatt.api.ahrs_scenario()`` or
    a study's ``setup().scenario``): an object with :data:`SCENARIO_FIELDS`."""
    missing = [a for a in SCENARIO_FIELDS if not hasattr(scenario, a)]
    if missing:
        raise ValueError(
            "scenario must be a simulated scenario (jaxatt.api.ahrs_scenario(...), a study's setup().scenario), got "
            f"{type(scenario).__name__} (it lacks {', '.join(missing)})"
        )
    _check_scenario_values(scenario)


def _is_nonnegative_field(name: str) -> bool:
    """A noise level or scale by its name (``gyro_arw``, ``vec_noise_std``, ``noise_scale``, ``burst_scale``, ...)."""
    return "std" in name or name.endswith(("_arw", "scale"))


def _check_scenario_values(scenario) -> None:
    """ValueError (one line, naming the field) unless a scenario built by hand holds finite numbers, ``r0`` a
    rotation (3, 3), noise levels and scales >= 0, and its first simulated step (truth and sensors) runs (checked
    on shapes). Fields that are being traced (a vmap over scenarios) are not checked."""
    fields = getattr(scenario, "_fields", ())
    for name in fields:
        v = getattr(scenario, name)
        if callable(v) or hasattr(v, "rate") or isinstance(v, jax.core.Tracer):
            continue
        try:
            a = np.asarray(v, float)
        except (TypeError, ValueError):
            continue  # not numbers: the scenario's own business
        if not np.all(np.isfinite(a)):
            raise ValueError(f"scenario.{name} must be finite, got {shown(v)}")
        if _is_nonnegative_field(name) and np.any(a < 0):
            raise ValueError(f"scenario.{name} must be >= 0 (a noise level or scale), got {shown(v)}")
    r0 = getattr(scenario, "r0", None)
    if r0 is not None and not isinstance(r0, jax.core.Tracer):
        r = np.asarray(r0, float)
        if r.shape != (3, 3) or not (np.allclose(r @ r.T, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0):
            raise ValueError(f"scenario.r0 must be a rotation matrix (3, 3) (R R^T = I, det +1), got {shown(r0)}")
    dt = 0.01
    noise = jnp.zeros((scenario.n_channels,))

    def first_step(scn):
        r1 = scn.propagate(scn.r0, 0.0, dt)
        return scn.sample(scn.truth_at(r1, dt), noise, dt)

    try:
        jax.eval_shape(first_step, scenario)
    except Exception as e:  # noqa: BLE001 - the scenario's code failed: one line, the traceback as __cause__
        first = (str(e).strip().splitlines() or [""])[0]
        raise ValueError(
            f"scenario {type(scenario).__name__}: its first simulated step failed (check the shapes of its fields "
            f"and of rates.rate(t), (3,) rad/s): {type(e).__name__}: {first}"
        ) from e


def _pick_out(t, truth, out):
    return out


def log_runner(observer: Observer, hold: Optional[str] = None, dtype=None):
    """Pure ``fn(params, samples, dt) -> Out (T, ...)``: ``observer`` over one log of T samples (any sample
    pytree, time-major), T estimates (row 0 ``init``'s). ``dt``: a scalar step (s) or the T - 1 steps
    t_{k+1} - t_k. ``dtype``: the observer's arithmetic (default: the samples' float type); ``init`` sees the first
    sample in the samples' own precision (:mod:`jaxatt.engine`). No checks (see :func:`run`); vmap it over params
    for a batch of gains or initial estimates, or jit it.

    A log of more than one block of :data:`jaxatt.engine.BLOCK` steps is scanned to the end of its last block
    (:func:`jaxatt.engine.whole_blocks`; the last sample and step repeated, the extra estimates dropped): the
    compiled scan then holds one copy of the step instead of two (full blocks and a partial last one), which
    roughly halves its compile time, and logs of nearby lengths share it. Estimate k depends on samples 0..k only,
    so the T estimates are those of the unpadded scan. ``hold``: None, the observer's own, else "zoh"
    (:func:`jaxatt.engine.hold_for`). Cached on the observer, the resolved hold and the dtype."""
    return _log_runner(observer, engine.hold_for(observer, hold), None if dtype is None else jnp.dtype(dtype).name)


@functools.lru_cache(maxsize=32)
def _log_runner(observer: Observer, hold: str, dtype):
    obs_dtype = None if dtype is None else jnp.dtype(dtype)

    @jax.jit
    def go(params, samples, dt):
        n = jnp.shape(samples.gyr)[0]
        odt = obs_dtype or jnp.asarray(samples.gyr).dtype
        dt = jnp.asarray(dt)  # cast to the arithmetic in the scan (give float32 steps for a bit-exact float32 run)
        per_step = dt.ndim == 1
        dts = jnp.concatenate([dt[:1], dt]) if per_step else dt
        fn = engine.batch_fn(
            observer, engine.Recorded(n - 1, per_step), engine.records_of(_pick_out, 1), hold=hold, obs_dtype=odt
        )
        item = {
            "samples": jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], samples),
            "dt": dts[None],
            "truth": None,
        }
        return jax.tree_util.tree_map(lambda a: a[0], fn(None, params, item).records)

    def run_log(params, samples, dt):
        n = jnp.shape(samples.gyr)[0]
        extra = engine.whole_blocks(n - 1) - (n - 1)
        if not extra:
            return go(params, samples, dt)

        def repeat_last(a):
            return jnp.concatenate([a, jnp.repeat(a[-1:], extra, axis=0)], axis=0)

        padded = jax.tree_util.tree_map(repeat_last, samples)
        t = getattr(samples, "t", None)
        if t is not None and jnp.ndim(t) == 1:  # timestamps go on at the last step (an observer may read t)
            t = jnp.asarray(t)
            padded = padded._replace(
                t=jnp.concatenate([t, t[-1] + (t[-1] - t[-2]) * jnp.arange(1, extra + 1, dtype=t.dtype)])
            )
        dt = jnp.asarray(dt)
        out = go(params, padded, repeat_last(dt) if dt.ndim == 1 else dt)
        return jax.tree_util.tree_map(lambda a: a[:n], out)

    return run_log


def run(
    observer: Observer, params, samples, dt=None, *, hold: Optional[str] = None, validate: Optional[Callable] = None
):
    """Run ``observer`` over a log; returns its stacked outputs, T estimates for T samples (JAX arrays).

    Args:
        samples: :class:`jaxatt.types.ImuSample` (or ``VectorSample``) of arrays, time-major (T,) / (T, 3); body
            frame gyro (rad/s) and vector sensors. NaN marks a missing reading (each observer documents what it
            does then).
        dt: step (s); None takes dt_k = t_{k+1} - t_k from the timestamps.
        hold: "zoh", "linear" or "next" (:data:`jaxatt.types.HOLDS`); None: the observer's own
            (``Observer.hold``; :func:`jaxatt.observers.registry.recorded_observer` gives a registered observer
            with its entry's, the hold of :func:`jaxatt.filter`), else "zoh".
        validate: optional parameter check (e.g. ``batista_ges.check_params``), run on concrete params.
    Returns the observer's Out with a leading time axis: row 0 is ``init``'s estimate at t_0, row k the estimate
    at t_k (:mod:`jaxatt.engine`).
    """
    check_observer(observer)
    samples = _real_samples(samples)
    _check_samples(samples)
    from .api import compute_dtype  # the front door's precision rule (imported when it runs: no cycle)

    compute_dtype(*(v for v in samples if v is not None), what="input (samples)")  # float64 with x64 off: said
    hold = engine.hold_for(observer, hold)
    engine.check_finite_params(params, observer.name)
    if validate is not None:
        validate(params)
    steps: Union[np.ndarray, float]
    if dt is None:
        from .data.logs import check_timestamps

        check_timestamps(samples.t, "samples.t", getattr(samples.t, "dtype", None))
        steps = np.diff(np.asarray(samples.t, float))
    else:
        steps = check_dt(dt)
    try:
        out = log_runner(observer, hold)(params, samples, steps)
    except (AttributeError, TypeError) as e:  # params or samples of the wrong kind for this observer, found tracing
        first = (str(e).strip().splitlines() or [""])[0]
        raise ValueError(
            f"observer {observer.name!r}: init or step failed on these params and samples: {type(e).__name__}: {first}"
        ) from e
    _warn_nonfinite(out, samples.t, observer.name)
    return out


def _real_samples(samples):
    """``samples`` with lists as numpy arrays; ValueError for a field that is not real numbers (complex, text)."""
    if not hasattr(samples, "_fields"):
        return samples  # _check_samples says what it must be
    fields = {}
    for name, v in samples._asdict().items():
        if v is None:
            fields[name] = v
            continue
        try:
            a = v if isinstance(v, jax.Array) else np.asarray(v)  # a JAX array stays on its device
        except (TypeError, ValueError):
            raise ValueError(f"samples.{name} must be an array of numbers, got {type(v).__name__}") from None
        if a.dtype == bool or not (jnp.issubdtype(a.dtype, jnp.floating) or jnp.issubdtype(a.dtype, jnp.integer)):
            raise ValueError(f"samples.{name} must be real numbers, got dtype {a.dtype}")
        fields[name] = a
    return samples._replace(**fields)


def _warn_nonfinite(out, t, name: str) -> None:
    """A warning naming the first sample whose estimate is not finite (run returns the outputs as they are)."""
    import warnings

    try:
        q = engine.estimate_q(out)
    except ValueError:  # an output without an estimate (q / r): nothing to say of it here
        return
    bad = np.asarray(~jnp.all(jnp.isfinite(q), axis=-1))
    if bad.any():
        k = int(np.argmax(bad))
        warnings.warn(
            f"observer {name!r}: the estimate is first non-finite at sample {k} (t = {float(np.asarray(t)[k]):.6g} s), "
            f"{int(bad.sum())} of {len(bad)} estimates; check the inputs and gains",
            stacklevel=3,
        )


# ------------------------------------------------------------------------------------------------------
# Simulation fused with the observer
# ------------------------------------------------------------------------------------------------------
ErrorsFn = Callable[[Any, Any], Dict[str, jax.Array]]


def default_trace(truth, out, errors: Dict[str, jax.Array], angle_deg) -> Dict[str, jax.Array]:
    """Trace record: time, angle error (deg) and the norm of every named error."""
    rec = {"t": truth.t, "angle_error_deg": angle_deg}
    for k, v in errors.items():
        rec[f"norm_{k}"] = jnp.sqrt(jnp.sum(v**2))
    return rec


#: key of the metrics reducer's output: per run, the time (s) of the first non-finite estimate (inf if none); moved
#: out of the metrics into ``MonteCarloResult.first_nonfinite_t``
FIRST_NONFINITE = "first_nonfinite_t_s"


@functools.lru_cache(maxsize=64)
def metrics_reducer(
    errors_fn: ErrorsFn,
    window_start: float,
    windows: tuple = (),
    trace_every: int = 0,
    trace_fn: Optional[Callable] = None,
    tol: float = 0.0,
) -> engine.Reducer:
    """The Monte Carlo reducer: per-run window metrics (:func:`jaxatt.metrics.window_summary`) of the named
    errors of ``errors_fn(truth, out)`` and of the rotation angle over t >= ``window_start``; with ``windows``
    (((name, start_s, end_s), ...)) the MAE / RMSE of every error over each window (``tol``: half a step); with
    ``trace_every`` the records ``trace_fn(truth, out, errors, angle_deg)`` of every ``trace_every``-th estimate."""
    trace_fn = trace_fn or default_trace

    def first_bad(t, r, first):
        """The time of the first non-finite estimate (inf while every estimate is finite)."""
        bad = ~jnp.all(jnp.isfinite(r))
        return jnp.where(bad & (t < first), jnp.asarray(t, first.dtype), first)

    def init(t0, truth0, out0):
        r0 = engine.estimate_r(out0)
        dtype = r0.dtype
        errors = errors_fn(truth0, out0)
        shapes = {k: jnp.shape(v) for k, v in errors.items()}
        mom = M.moments_init(shapes, len(windows), dtype) if windows else None
        rec = None
        if trace_every:
            rec = trace_fn(truth0, out0, errors, M.angle_error_deg(truth0.r.astype(dtype), r0))
        first = first_bad(t0, r0, jnp.asarray(jnp.inf, jnp.result_type(t0)))
        return (M.window_init(shapes, dtype), mom, first), rec

    def update(acc, t, truth, out):
        win, mom, first = acc
        errors = errors_fn(truth, out)
        r = engine.estimate_r(out)
        angle = M.angle_error_deg(truth.r.astype(r.dtype), r)
        win = M.window_update(win, errors, angle, t >= window_start)
        if windows:
            mom = M.moments_update(mom, errors, t, windows, tol)
        rec = trace_fn(truth, out, errors, angle) if trace_every else None
        return (win, mom, first_bad(t, r, first)), rec

    def finish(acc):
        out = M.window_summary(acc[0])
        if windows:
            out.update(M.moments_summary(acc[1], windows))
        out[FIRST_NONFINITE] = acc[2]
        return out

    return engine.Reducer(init, update, finish, trace_every)


def seed_key(seed: int) -> jax.Array:
    """``jax.random.PRNGKey(seed)`` as JAX computes it with float64 on, for any |seed| < 2^63 and either mode:
    the seed's two 32-bit halves. (With float64 off, ``PRNGKey`` keeps the low 32 bits only, so seed 2^32 would
    silently repeat seed 0's runs.) Another default PRNG implementation than threefry gets ``PRNGKey(seed)``,
    and a seed outside [0, 2^31) is refused there unless float64 is on."""
    seed = check_seed(seed)
    if jax.config.values["jax_default_prng_impl"] == "threefry2x32":
        return jnp.array([(seed >> 32) & 0xFFFFFFFF, seed & 0xFFFFFFFF], dtype=jnp.uint32)
    if not (jax.config.values["jax_enable_x64"] or 0 <= seed < 2**31):
        raise ValueError(
            f"seed {seed}: with float64 off and the {jax.config.values['jax_default_prng_impl']} PRNG a seed must "
            "be in [0, 2^31) (JAX keeps its low 32 bits only)"
        )
    return jax.random.PRNGKey(seed)


def run_keys(seed: int, run_indices) -> jax.Array:
    """PRNG key of each run: fold_in(PRNGKey(seed), k) (:func:`seed_key`), independent of batching."""
    base = seed_key(seed)
    return jax.vmap(lambda k: jax.random.fold_in(base, k))(jnp.asarray(run_indices, jnp.uint32))


def _dtypes(dtype):
    obs = jnp.dtype(dtype) if dtype is not None else jnp.result_type(float)
    sim = jnp.result_type(float)  # float64 when x64 is enabled: truth is always as precise as available
    return obs, sim


def _simulation(
    observer,
    *,
    duration,
    dt,
    errors_fn,
    window_start,
    hold,
    trace_every,
    trace_fn,
    dtype,
    windows,
    init_params,
    mesh=None,
    progress=False,
    keep_state=False,
):
    """The compiled batch function of a simulated Monte Carlo (scenario, params, keys) -> engine.Result."""
    check_observer(observer)
    if not callable(errors_fn):
        raise ValueError(f"errors_fn must be a function (truth, out) -> dict of errors, got {errors_fn!r}")
    dtype = check_obs_dtype(dtype)
    dt = check_dt(dt)
    duration = check_duration(duration)
    window_start = check_window_start(window_start, duration)
    trace_every = check_count("trace_every", trace_every or 0)
    hold = engine.hold_for(observer, hold)
    n_steps = whole_steps(duration, dt)
    if trace_every and engine.BLOCK % trace_every:
        raise ValueError(f"trace_every must divide {engine.BLOCK}, got {trace_every}")
    if trace_every > n_steps:
        raise ValueError(
            f"trace_every = {trace_every} steps is longer than the run ({n_steps} steps of {dt:g} s): the trace would "
            "hold only the estimate at t = 0; give a smaller trace_every (a divisor of the steps you want)"
        )
    obs_dtype, sim_dtype = _dtypes(dtype)
    source = engine.Simulated(n_steps, dt, sim_dtype, init_params)
    reducer = metrics_reducer(
        errors_fn, float(window_start), M.check_windows(windows), int(trace_every or 0), trace_fn, 0.5 * dt
    )
    return n_steps, engine.compiled(
        observer, source, reducer, mesh, hold=hold, obs_dtype=obs_dtype, progress=progress, keep_state=keep_state
    )


def metrics_fn(
    observer: Observer,
    *,
    duration: float,
    dt: float,
    errors_fn: ErrorsFn,
    window_start: float = 0.0,
    hold: Optional[str] = None,
    dtype=None,
    windows=(),
    init_params: Optional[Callable] = None,
):
    """``fn(scenario, params, keys) -> {metric: (B,)}``: the per-run metrics of :func:`monte_carlo` (the same
    program, arguments as there) as a pure JAX function, to ``jax.vmap`` over a grid of gains or scenarios,
    ``jax.jit`` or differentiate. ``keys``: (B, 2) PRNG keys, :func:`run_keys` (run k of seed s:
    ``run_keys(s, [k])``, so a run's numbers do not depend on its batch). A grid of gains, every gain on the same
    runs: ``jax.vmap(fn, in_axes=(None, 0, None))(scenario, stacked_params, keys)``. The metrics are those of
    ``MonteCarloResult.per_run`` (degrees where named ``_deg``), plus ``first_nonfinite_t_s`` (s; inf for a run whose
    estimate stayed finite). Nothing is checked per call beyond what JAX checks: the checks of
    :func:`monte_carlo` run once, here, on the observer and the settings."""
    check_observer(observer)
    _, fn = _simulation(
        observer,
        duration=duration,
        dt=dt,
        errors_fn=errors_fn,
        window_start=window_start,
        hold=hold,
        trace_every=0,
        trace_fn=None,
        dtype=dtype,
        windows=windows,
        init_params=init_params,
    )

    def metrics(scenario, params, keys):
        return fn(scenario, params, keys).summary

    return metrics


def simulate(
    scenario,
    observer: Observer,
    params,
    *,
    duration: float,
    dt: float,
    seed: int = 0,
    run_index: int = 0,
    errors_fn: ErrorsFn,
    window_start: float = 0.0,
    hold: Optional[str] = None,
    trace_every: int = 1,
    trace_fn=None,
    dtype=None,
    windows=(),
    init_params=None,
):
    """One simulated run; returns (summary dict, trace dict of arrays, final observer state).

    ``trace_fn(truth, out, errors, angle_deg) -> dict`` picks what is recorded every ``trace_every`` estimates
    (default: time, angle error, error norms), from estimate 0 at t = 0. ``windows`` and ``init_params`` as in
    :func:`monte_carlo`.
    """
    _, fn = _simulation(
        observer,
        duration=duration,
        dt=dt,
        errors_fn=errors_fn,
        window_start=window_start,
        hold=hold,
        trace_every=trace_every,
        trace_fn=trace_fn,
        dtype=dtype,
        windows=windows,
        init_params=init_params,
        keep_state=True,
    )
    res = fn(scenario, params, run_keys(check_seed(seed), [check_count("run_index", run_index, 0, MAX_RUNS - 1)]))
    first = lambda a: np.asarray(a)[0]  # noqa: E731
    scalar = lambda a: float(first(a)) if np.ndim(a) == 1 else first(a)  # noqa: E731
    return (
        {k: scalar(v) for k, v in res.summary.items() if k != FIRST_NONFINITE},
        jax.tree_util.tree_map(first, res.records) if res.records is not None else None,
        jax.tree_util.tree_map(lambda a: a[0], res.state),
    )


def _sample_state_init(p, sample):
    return sample


def _sample_state_step(p, state, sample, dt):
    return sample, sample


#: A pass-through "observer" whose output is the sample itself (with ``hold="next"``): the engine then
#: records a simulated log.
_SAMPLES = Observer(_sample_state_init, _sample_state_step, "samples")


def _pick_sample_truth(t, truth, out):
    return out, truth


def simulate_log(scenario, *, duration: float, dt: float, seed: int = 0, run_index: int = 0, key=None):
    """A simulated log (samples at t_0 ... t_N) and its truth, with the same noise stream as :func:`simulate`
    (run ``run_index`` of ``seed``; or the run key ``key`` itself when given).

    Returns (sample pytree of (N+1,)/(N+1, 3) arrays, truth of stacked arrays), in the simulator's precision.
    Holds the whole trajectory: meant for short runs, tests and for feeding :func:`run`.
    """
    check_scenario(scenario)
    dt = check_dt(dt)
    n_steps = check_step_count(check_duration(duration), dt)
    if key is None:
        keys = run_keys(check_seed(seed), [check_count("run_index", run_index, 0, MAX_RUNS - 1)])
    else:
        keys = jnp.asarray(key)[None]
    _, sim_dtype = _dtypes(None)
    # Simulated whole noise blocks, the log cut after: the first n steps of a longer run are the same numbers,
    # and logs of any length up to a block share one compiled program (a test suite simulates dozens of lengths).
    n_simulated = -(-n_steps // engine.BLOCK) * engine.BLOCK
    fn = engine.compiled(
        _SAMPLES,
        engine.Simulated(n_simulated, dt, sim_dtype),
        engine.records_of(_pick_sample_truth, 1),
        hold="next",
        obs_dtype=sim_dtype,
    )
    samples, truth = fn(scenario, None, keys).records
    first = lambda a: a[0, : n_steps + 1]  # noqa: E731
    return jax.tree_util.tree_map(first, samples), jax.tree_util.tree_map(first, truth)


class MonteCarloResult(NamedTuple):
    """Per-run summaries (name -> (n_runs,) numpy array), optional decimated traces (name -> (n_runs, n)),
    the run indices done, wall time (s), whether every requested run finished, and per run the time (s) of the
    first non-finite estimate (inf when every estimate is finite)."""

    per_run: Dict[str, np.ndarray]
    traces: Optional[Dict[str, np.ndarray]]
    run_indices: np.ndarray
    wall_s: float
    complete: bool
    first_nonfinite_t: Optional[np.ndarray] = None

    def summary(self) -> Dict[str, Dict[str, Any]]:
        """metric -> {mean, std, min, max, per_run} over the runs done (NaN-aware; the layout of the CLI's
        Monte Carlo JSON, ``metrics.<name>``), in the metrics' own units (``_deg`` in degrees)."""
        from . import io

        return io.summarise(self.per_run)

    def save_json(self, path) -> None:
        """Write ``{runs, run_indices, complete, wall_s, first_nonfinite, metrics: summary(), environment}`` as
        JSON, atomically (``path`` is checked first: ValueError naming it)."""
        from . import io

        io.check_output_path(path, "path", suffixes=io.JSON_SUFFIXES)
        io.write_json(
            path,
            {
                "runs": int(len(self.run_indices)),
                "run_indices": np.asarray(self.run_indices).tolist(),
                "complete": bool(self.complete),
                "wall_s": float(self.wall_s),
                "first_nonfinite": self.first_nonfinite(),
                "metrics": self.summary(),
                "environment": io.environment(),
            },
        )

    def first_nonfinite(self) -> Optional[str]:
        """Where the first non-finite result appeared ("run k: ... at t = ... s"), or None when all are finite."""
        n = len(self.run_indices)
        bad = np.zeros(n, bool)
        what = {}
        for k, v in self.per_run.items():
            b = ~np.isfinite(np.asarray(v, float).reshape(n, -1)).all(axis=1)
            for j in np.flatnonzero(b & ~bad):
                what[int(j)] = k
            bad |= b
        t_bad = np.asarray(self.first_nonfinite_t, float) if self.first_nonfinite_t is not None else np.full(n, np.inf)
        bad |= np.isfinite(t_bad)
        if not bad.any():
            return None
        i = int(np.flatnonzero(bad)[np.argmin(np.asarray(self.run_indices)[bad])])
        where = f"run {int(self.run_indices[i])}"
        if np.isfinite(t_bad[i]):
            return f"{where}: the estimate is first non-finite at t = {float(t_bad[i]):.6g} s"
        return f"{where}: metric {what[i]} is not finite (the estimates are finite)"


def monte_carlo(
    scenario,
    observer: Observer,
    params,
    *,
    runs: int,
    duration: float,
    dt: float,
    seed: int = 0,
    errors_fn: ErrorsFn,
    window_start: float = 0.0,
    hold: Optional[str] = None,
    chunk: int = 250,
    trace_every: int = 0,
    trace_fn=None,
    dtype=None,
    validate: Optional[Callable] = None,
    on_chunk: Optional[Callable[[MonteCarloResult], None]] = None,
    windows=(),
    init_params: Optional[Callable] = None,
    devices=None,
    progress=None,
    previous: Optional[MonteCarloResult] = None,
) -> MonteCarloResult:
    """``runs`` simulated runs, vmapped in chunks of ``chunk`` runs, metrics reduced on the fly.

    ``windows`` = ((name, start_s, end_s), ...): per-run ``mae_{name}_{error}`` and ``rmse_{name}_{error}`` of
    every error of ``errors_fn`` over the estimates with start_s <= t <= end_s (shape of the error).
    ``init_params(params, key) -> params``: per-run parameters for ``observer.init`` only (e.g. a random initial
    estimate drawn from ``key``); must be a hashable callable (a module-level function), the jitted runner is
    cached on it. Run k's key is the same for every observer, so observers compared on the same seed see the
    same noise and the same initial estimates. ``hold``: the input of a step (:data:`jaxatt.types.HOLDS`); None:
    the observer's own (``Observer.hold``), else "zoh".

    After each chunk ``on_chunk(partial_result)`` is called (save, progress). On KeyboardInterrupt the runs
    finished so far are returned with ``complete=False``: nothing computed is lost. ``previous``: the result of an
    interrupted call with the same arguments (a resumed study): its runs are not run again and are part of every
    result (runs in index order), which then equals an uninterrupted call's.

    ``devices`` (default: every visible device): the runs of each chunk are split over them
    (:mod:`jaxatt.sharding`; the chunk is rounded up to a multiple of the device count, padding runs dropped);
    ``devices=1`` runs on one device. The result does not depend on the devices beyond rounding. Several processes
    (``jax.distributed``, :func:`jaxatt.sharding.initialize_distributed`): call it in every process with the same
    arguments; the runs split over every process's devices and every process gets the whole result.
    ``progress``: True for a line on stderr updated from inside the scan every 1000 steps, or a callable
    reporter (:mod:`jaxatt.progress`); None: off.
    Memory per chunk: the state and accumulators of ``chunk`` runs, one noise block (chunk x 1000 x channels)
    and the decimated traces; never the per-step trajectories.
    """
    check_scenario(scenario)
    check_observer(observer)
    for name, fn in (("validate", validate), ("on_chunk", on_chunk), ("init_params", init_params)):
        if fn is not None and not callable(fn):
            raise ValueError(f"{name} must be a function or None, got {fn!r}")
    runs = check_count("runs", runs, 1, MAX_RUNS)
    chunk = check_count("chunk", chunk, 1)
    seed = check_seed(seed)
    duration = check_duration(duration)
    window_start = check_window_start(window_start, duration)  # an empty window would give metrics of 0
    _check_previous(previous, runs, trace_every)
    engine.check_finite_params(params, observer.name)
    if validate is not None:
        validate(params)
    # the gains in the observer's arithmetic, as the scan casts them: weakly typed gains (a float, jnp.asarray(0.1))
    # reuse the program compiled for typed ones
    params = engine.cast_floats(params, _dtypes(dtype)[0])
    mesh = _sharding.seed_mesh(devices)
    reporter = _progress.make_reporter(progress)
    # ordered host callbacks are not supported on several devices: there the reports may arrive out of order
    # and jaxatt.progress keeps them monotone
    hook = False if reporter is None else ("ordered" if mesh is None else "unordered")
    n_steps, fn = _simulation(
        observer,
        duration=duration,
        dt=dt,
        errors_fn=errors_fn,
        window_start=window_start,
        hold=hold,
        trace_every=trace_every,
        trace_fn=trace_fn,
        dtype=dtype,
        windows=windows,
        init_params=init_params,
        mesh=mesh,
        progress=hook,
    )
    have = set() if previous is None else set(int(i) for i in previous.run_indices)
    todo = np.arange(runs) if previous is None else np.setdiff1d(np.arange(runs), np.asarray(sorted(have), int))
    chunk = max(1, min(chunk, max(len(todo), 1)))
    if mesh is not None:
        chunk = -(-chunk // mesh.size) * mesh.size  # a multiple of the device count
    prog = _progress._Run(reporter, len(todo), n_steps, engine.BLOCK) if reporter is not None else None
    per_run: Dict[str, list] = {}
    traces: Dict[str, list] = {}
    done: list = []
    first_bad: list = []
    t0 = time.perf_counter()

    def result(complete):
        new = MonteCarloResult(
            {k: np.concatenate(v) for k, v in per_run.items()},
            {k: np.concatenate(v) for k, v in traces.items()} if traces else None,
            np.asarray(done, int),
            time.perf_counter() - t0,
            complete,
            np.concatenate(first_bad) if first_bad else np.zeros(0),
        )
        return new if previous is None else merge_results(previous, new, complete)

    try:
        for start in range(0, len(todo), chunk):
            idx = todo[start : start + chunk]
            pad = chunk - len(idx)  # keep one compiled shape: pad the last chunk, drop the padding
            keys = run_keys(seed, np.concatenate([idx, np.full(pad, idx[-1])]))
            if prog is not None:
                prog.chunk_runs, prog.chunk_steps = len(idx), 0
            with _progress.active(prog):
                res = _sharding.to_host(fn(scenario, params, keys)[:2])
            summ, trace = res
            first_bad.append(np.asarray(summ.pop(FIRST_NONFINITE), float)[: len(idx)])
            for k, v in summ.items():
                per_run.setdefault(k, []).append(np.asarray(v)[: len(idx)])
            if trace is not None:
                for k, v in trace.items():
                    traces.setdefault(k, []).append(np.asarray(v)[: len(idx)])
            done.extend(idx.tolist())
            if prog is not None:  # after the chunk is kept: an interrupt in the reporter loses nothing
                prog.runs_done += len(idx)
                prog.chunk_runs = 0
                prog.report(0)
            if on_chunk is not None:
                on_chunk(result(len(done) == len(todo)))
    except KeyboardInterrupt:
        if not done and previous is None:
            raise
        return result(False)
    return result(True)


#: In :func:`spec_differences`' ``assumed``: a key an earlier version's spec lacks matches whatever its value now.
ANY = object()


def spec_differences(saved: Optional[str], now: str, assumed: Optional[Mapping] = None) -> list:
    """The keys (``config.name`` inside a nested dict) in which the spec of saved runs differs from the spec of
    this call (both JSON strings, :func:`save_runs`); [] when the runs can be continued. A key the saved spec
    lacks was added by a later version of jaxatt: it matches when this call's value is the one ``assumed`` for it
    (the value the earlier version used, :data:`ANY` for any, a dict for a nested dict such as a Config's
    defaults), so runs saved before an upgrade are resumed after it."""
    import json

    try:
        was, cur = json.loads(saved or "null"), json.loads(now)
    except (TypeError, ValueError):
        return ["the spec"] if saved != now else []

    def walk(was, cur, assumed, prefix):
        if not (isinstance(was, dict) and isinstance(cur, dict)):
            return [] if was == cur else [prefix.rstrip(".") or "the spec"]
        out = []
        for k in sorted(set(was) | set(cur)):
            a = (assumed or {}).get(k, None) if isinstance(assumed, dict) else None
            if k not in was and k in cur:
                ok = a is ANY or (isinstance(a, dict) and isinstance(cur[k], dict) and not walk(a, cur[k], None, ""))
                ok = ok or (a is not None and not isinstance(a, dict) and cur[k] == a)
                if not ok:
                    out.append(prefix + k)
            elif k not in cur:
                out.append(prefix + k)
            elif isinstance(was[k], dict) and isinstance(cur[k], dict):
                out += walk(was[k], cur[k], a, prefix + k + ".")
            elif was[k] != cur[k]:
                out.append(prefix + k)
        return out

    return walk(was, cur, assumed or {}, "")


def save_runs(path, spec: str, results: Mapping[str, MonteCarloResult]) -> None:
    """Write Monte Carlo results (label -> :class:`MonteCarloResult`) and the ``spec`` of the call that made them
    (a string: what must match to continue them) as one NPZ, atomically. Read back with :func:`load_runs`."""
    from . import io

    arrays: Dict[str, Any] = {"spec": np.asarray(spec), "labels": np.asarray(list(results), dtype=str)}
    for i, res in enumerate(results.values()):
        arrays[f"{i}/run_indices"] = res.run_indices
        arrays[f"{i}/complete"] = np.asarray(res.complete)
        arrays[f"{i}/wall_s"] = np.asarray(res.wall_s)
        if res.first_nonfinite_t is not None:
            arrays[f"{i}/first_nonfinite_t"] = res.first_nonfinite_t
        for k, v in res.per_run.items():
            arrays[f"{i}/per_run/{k}"] = v
        for k, v in (res.traces or {}).items():
            arrays[f"{i}/traces/{k}"] = v
    io.write_npz(path, arrays)


def load_runs(path, name: str = "path", again: str = "") -> Tuple[Optional[str], Dict[str, MonteCarloResult]]:
    """(spec, label -> :class:`MonteCarloResult`) written by :func:`save_runs`; (None, {}) when there is no file.
    ValueError starting with ``name`` (and ending with ``again``, what to do) for a file that is not one."""
    import os
    import zipfile

    if not os.path.exists(path):
        return None, {}
    try:
        z = np.load(path)
        if not hasattr(z, "files"):  # a bare .npy array, not the archive save_runs writes
            raise ValueError("not an .npz archive")
        with z:
            d = {k: z[k] for k in z.files}
        d["labels"], d["spec"]  # noqa: B018 (both are always written)
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile):
        raise ValueError(
            f"{name}: {path} is not a runs file of jaxatt (empty, damaged or another file)"
            + (f"; {again}" if again else "")
        ) from None
    out = {}
    for i, label in enumerate(d["labels"].tolist()):
        pre = f"{i}/"
        per_run = {k[len(pre + "per_run/") :]: v for k, v in d.items() if k.startswith(pre + "per_run/")}
        traces = {k[len(pre + "traces/") :]: v for k, v in d.items() if k.startswith(pre + "traces/")}
        out[label] = MonteCarloResult(
            per_run,
            traces or None,
            d[pre + "run_indices"],
            float(d[pre + "wall_s"]),
            bool(d[pre + "complete"]),
            d.get(pre + "first_nonfinite_t"),
        )
    return str(d["spec"]), out


def load_result(path) -> MonteCarloResult:
    """The :class:`MonteCarloResult` saved by ``jaxatt.monte_carlo(..., out=path)`` (ValueError naming ``path`` if
    it holds no runs, or the runs of several observers: a study's runs file; read those with :func:`load_runs`)."""
    _, saved = load_runs(path, "path")
    if len(saved) != 1:
        raise ValueError(
            f"path {path}: "
            + (
                "no such file"
                if not saved
                else f"holds the runs of {len(saved)} observers "
                f"({', '.join(saved)}): read them with jaxatt.montecarlo.load_runs"
            )
        )
    return next(iter(saved.values()))


def _check_previous(previous, runs: int, trace_every: int) -> None:
    """ValueError (one line) unless ``previous`` is None or a :class:`MonteCarloResult` this call can continue:
    distinct run indices in [0, runs), traces kept when ``trace_every`` asks for them. (Its seed, duration and
    scenario are not stored in it: resuming with other arguments is the caller's to avoid.)"""
    if previous is None:
        return
    if not isinstance(previous, MonteCarloResult):
        raise ValueError(f"previous must be the MonteCarloResult of an interrupted call, got {type(previous).__name__}")
    idx = np.asarray(previous.run_indices)
    if idx.ndim != 1 or (idx.size and not np.issubdtype(idx.dtype, np.integer)):
        raise ValueError(f"previous.run_indices must be a 1-D array of run indices, got {idx!r}")
    if len(np.unique(idx)) != len(idx):
        raise ValueError("previous.run_indices repeats a run: it is not the result of one interrupted call")
    if idx.size and not (idx.min() >= 0 and idx.max() < runs):
        raise ValueError(
            f"previous holds run {int(idx.max()) if idx.max() >= runs else int(idx.min())}, outside "
            f"the runs 0 ... {runs - 1} asked for now"
        )
    if idx.size and bool(trace_every) != (previous.traces is not None):
        raise ValueError(
            f"previous {'has no' if trace_every else 'has'} traces, and this call asks for "
            f"{'traces' if trace_every else 'none'} (trace_every={trace_every}): continue it with its own trace_every"
        )


def merge_results(a: MonteCarloResult, b: MonteCarloResult, complete: bool) -> MonteCarloResult:
    """The runs of two results of the same Monte Carlo (disjoint run indices) as one, in run-index order."""
    idx = np.concatenate([a.run_indices, b.run_indices]).astype(int)
    order = np.argsort(idx, kind="stable")

    def cat(x, y):
        parts = [d for d, r in ((x, a), (y, b)) if len(r.run_indices)]
        if not parts or any(d is None for d in parts):
            return None if any(d is None for d in parts) else {}
        return {k: np.concatenate([d[k] for d in parts])[order] for k in parts[0]}

    first = [
        r.first_nonfinite_t if r.first_nonfinite_t is not None else np.full(len(r.run_indices), np.inf) for r in (a, b)
    ]
    return MonteCarloResult(
        cat(a.per_run, b.per_run),
        cat(a.traces, b.traces),
        idx[order],
        a.wall_s + b.wall_s,
        complete,
        np.concatenate(first)[order],
    )
