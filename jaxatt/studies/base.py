"""The study protocol: one typed object per paper set-up, and the one runner that reproduces, evaluates and feeds
the fitter for every study.

A :class:`Study` says, for a configuration (a NamedTuple whose defaults are the paper's set-up), what to simulate
(``scenario``), which observers are compared with which gains (``observers``), what their errors are
(``errors``), over which windows they are measured, what the paper published and how its tables look.
:func:`reproduce` runs every compared observer through :func:`jaxatt.montecarlo.monte_carlo`, writes one JSON
layout (atomically, after every chunk, so an interrupted run keeps its finished runs) and prints the study's
tables; :func:`evaluate` compares gains from a gains file with the paper's on the same runs; :func:`setup` gives
the fitter what it needs to tune the study's tuned observer on simulated seeds.

JSON layout of :func:`reproduce` / :func:`evaluate` (stable keys): ``experiment``, ``study``, ``config``,
``environment``, ``notes``, ``complete``, ``runs_done``, ``paper``, ``observers.<label>.{runs_done, metrics,
timing}`` and, when one observer is compared, ``metrics.<name>.{mean, std, min, max, per_run}`` at the top; the
study may add its own keys (the NLIO tables: ``observers.<label>.mae`` / ``.rmse``).
"""

from __future__ import annotations

import abc
import collections.abc
import functools
import math
import numbers
import time
import typing
from typing import Any, Callable, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple, Union

import jax
import numpy as np

from .. import io
from ..progress import done_reporting, report_line

__all__ = ["Study", "Setup", "reproduce", "evaluate", "table", "config_dict", "check_settings", "setup_params"]


#: About how many times per run :meth:`Study.angle_error_trace` keeps for the figure.
FIGURE_POINTS = 500


def _angle_trace(truth, out, errors, angle_deg):
    """The angle-error figure's record: t (s) and the rotation-angle error (deg, float32)."""
    return {"t": truth.t, "angle_error_deg": angle_deg.astype(np.float32)}


def paper_dtype():
    """The arithmetic of a study's paper gains and runs: float64 when JAX's x64 mode is on (the papers' Earth rate,
    7.3e-5 rad/s beside body rates of rad/s, needs it); float32 otherwise, with a warning (jaxatt never switches the
    mode: ``jax.config.update("jax_enable_x64", True)``; the ``jaxatt`` command does it for you)."""
    import jax.numpy as jnp

    if jax.config.values["jax_enable_x64"]:
        return jnp.float64
    import warnings

    warnings.warn(
        "jaxatt studies run in float32 because JAX's x64 mode is off; call "
        "jax.config.update('jax_enable_x64', True) first for the papers' float64",
        stacklevel=3,
    )
    return jnp.float32


def config_dict(cfg) -> dict:
    """A Config NamedTuple as a JSON-ready dict (tuples as lists)."""
    if cfg is None:
        return {}
    d = cfg._asdict() if hasattr(cfg, "_asdict") else dict(cfg)
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}


class _Bad(Exception):
    """A setting's value does not fit its declared type (internal to :func:`check_settings`)."""


@functools.lru_cache(maxsize=None)
def _hints(config_type) -> Dict[str, Any]:
    return typing.get_type_hints(config_type)


def _describe(hint, shapes) -> str:
    """What a setting of type ``hint`` must be, in words (``shapes``: the allowed shapes of a list of numbers)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Union:
        inner = [a for a in args if a is not type(None)]
        return f"{_describe(inner[0], shapes)} or None"
    if hint is float:
        return "a finite number"
    if hint is int:
        return "a whole number"
    if hint is bool:
        return "True or False"
    if hint is str:
        return "a string"
    if origin in (tuple, list, collections.abc.Sequence) or hint in (tuple, list):
        if args and (len(args) == 1 or args[-1] is Ellipsis):
            if args[0] is float:
                n = " or ".join("x".join(map(str, sh)) for sh in shapes) if shapes else ""
                return f"a list of {n + ' ' if n else ''}finite numbers"
            if args[0] is str:
                return "a list of strings"
            return f"a list of {_describe(args[0], None)}"
        if args:
            if all(a is float for a in args):
                return f"a list of {len(args)} finite numbers"
            return "(" + ", ".join(_describe(a, None).replace("a finite ", "").replace("a ", "") for a in args) + ")"
        return "a list"
    return f"a {getattr(hint, '__name__', hint)}"


def _conform(v, hint, shapes):
    """``v`` as a value of the setting type ``hint`` (lists as tuples, numbers as float): raises :class:`_Bad`."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Union:
        if v is None:
            return None
        inner = [a for a in args if a is not type(None)]
        return _conform(v, inner[0], shapes)
    if hint is float or hint is int:
        if isinstance(v, (np.ndarray, jax.Array)) and np.ndim(v) == 0:  # a 0-d array: its number
            v = np.asarray(v).item()
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real) or not math.isfinite(v):
            raise _Bad
        if hint is int:
            if not float(v).is_integer():
                raise _Bad
            return int(v)
        return float(v)
    if hint is bool:
        if not isinstance(v, (bool, np.bool_)):
            raise _Bad
        return bool(v)
    if hint is str:
        if not isinstance(v, str):
            raise _Bad
        return v
    if origin in (tuple, list, collections.abc.Sequence) or hint in (tuple, list):
        if isinstance(v, (str, bytes, Mapping)) or not isinstance(v, (list, tuple, np.ndarray, jax.Array)):
            raise _Bad
        if args and (len(args) == 1 or args[-1] is Ellipsis):
            if args[0] is float:  # numbers: a list (or array) of one of the allowed shapes
                try:
                    a = np.asarray(v)
                except (TypeError, ValueError):
                    raise _Bad from None
                if a.dtype == bool or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
                    raise _Bad
                if (shapes and a.shape not in shapes) or (not shapes and a.ndim != 1) or not np.all(np.isfinite(a)):
                    raise _Bad
                return tuple(float(x) for x in a.ravel())
            return tuple(_conform(x, args[0], None) for x in v)
        if args:
            if len(v) != len(args):
                raise _Bad
            return tuple(_conform(x, a, None) for x, a in zip(v, args))
        return tuple(v)
    return v


def check_settings(config_type, overrides: Mapping[str, Any], study: str, shapes=None) -> Dict[str, Any]:
    """``overrides`` of a study's Config (a NamedTuple class) checked against the Config's declared field types,
    once for every study and every caller (``jaxatt.fit(config=...)``, the command line, :meth:`Study.setup`):
    ValueError (one line, naming the setting) for an unknown setting or a value of the wrong kind; otherwise the
    overrides with lists as tuples and numbers as Python floats. Numbers must be finite. A list of numbers must
    have the length of the field's default, or one of ``shapes[field]`` (tuples of array shapes) when given (the
    default is None). What values are allowed beyond their type (ranges, names) each study checks itself."""
    if not isinstance(overrides, Mapping):
        raise ValueError(f"{study} settings must be a dict of setting name -> value, got {type(overrides).__name__}")
    fields = config_type._fields
    bad = sorted(map(str, set(overrides) - set(fields)))
    if bad:
        raise ValueError(f"unknown {study} settings {bad} (settings: {', '.join(fields)})")
    hints = _hints(config_type)
    out = {}
    for k, v in overrides.items():
        default = config_type._field_defaults.get(k)
        allowed = (shapes or {}).get(k)
        if allowed is None and isinstance(default, tuple) and all(isinstance(x, numbers.Real) for x in default):
            allowed = ((len(default),),)
        try:
            out[k] = _conform(v, hints[k], allowed)
        except _Bad:
            text = " ".join(repr(v).split())  # one line (an array's repr spans several)
            text = text if len(text) <= 80 else text[:77] + "..."
            raise ValueError(f"{study} setting {k!r} must be {_describe(hints[k], allowed)}, got {text}") from None
    return out


def setup_params(setup: "Setup", params, what: str = "params"):
    """The params of a study fit or prediction: ``setup.params`` (the paper's gains) for None, a dict of gain name
    -> value put into them, a gains-file path read onto them, or params of the observer's own type (checked by the
    study). ValueError (one line) for anything else."""
    from ..fitting import gainsfile

    if params is None:
        p = setup.params
    elif isinstance(params, Mapping):
        p = gainsfile.apply(setup.params, params, source=what)
    elif isinstance(params, str) or hasattr(params, "__fspath__"):
        p = gainsfile.read_params(params, setup.entry, base=setup.params)
    elif type(params) is type(setup.params):
        p = params
    else:
        fields = ", ".join(getattr(setup.params, "_fields", ()))
        raise ValueError(
            f"{what} of {setup.entry} (study {setup.study}) must be its {type(setup.params).__name__} ({fields}), "
            f"a dict of some of those fields or a gains-file path, got {type(params).__name__}"
        )
    if setup.check_params is not None:
        setup.check_params(p)
    return p


class Setup(NamedTuple):
    """What the fitter and :func:`evaluate` need of one study configuration: the tuned observer on the scenario.

    Fields: study (name), config, scenario, observer, params (the paper's gains), entry (registry name of the
    observer: its gain declarations), errors_fn, duration, dt (s), hold, windows (MAE/RMSE windows), window_start
    (s), init_params (per-run initial-params draw or None), loss_kind, loss_windows (name -> (start_s, end_s) with
    "steady" and "transient"), check_params, paper (published numbers), notes.
    """

    study: str
    config: Any
    scenario: Any
    observer: Any
    params: Any
    entry: str
    errors_fn: Callable
    duration: float
    dt: float
    hold: str
    windows: tuple
    window_start: float
    init_params: Optional[Callable]
    loss_kind: str
    loss_windows: Mapping[str, Tuple[float, float]]
    check_params: Optional[Callable]
    paper: Mapping[str, Any]
    notes: Sequence[str]


class Study(abc.ABC):
    """A paper's simulation study. Subclasses set the class attributes and implement the abstract methods.

    Class attributes: ``name`` (CLI name), ``paper`` (reference, with the section), ``tuned`` (label of the observer
    that ``jaxatt tune`` tunes), ``entry`` (its registry name), ``fittable`` (registry name -> label of the other
    observers the fitter may tune on this study, ``jaxatt.fit(observer=name, data=study)``), ``loss_kind``
    (pointwise loss of :mod:`jaxatt.fitting.losses`), ``units`` (metric -> unit, for tables), ``error_units``
    (error name of :meth:`errors` -> unit, for the metrics of the JSON; ``std_<e>`` in ``units`` gives ``e``'s
    too), ``rows`` ((metric, label) rows of the table).
    """

    name: str = ""
    paper: str = ""
    tuned: str = ""
    entry: str = ""
    fittable: Mapping[str, str] = {}
    loss_kind: str = "angle_sq"
    units: Mapping[str, str] = {}
    error_units: Mapping[str, str] = {}
    rows: Sequence[Tuple[str, str]] = ()

    # ---- configuration -------------------------------------------------------------------------------
    @abc.abstractmethod
    def config(self, **overrides):
        """The study's Config with ``overrides`` (validated; ValueError naming the field)."""

    @abc.abstractmethod
    def scenario(self, cfg):
        """The simulated platform (``truth_at / propagate / sample / n_channels / r0``)."""

    @abc.abstractmethod
    def observers(self, cfg, dtype=None) -> Dict[str, Tuple[Any, Any]]:
        """label -> (Observer, params with the paper's gains) of every compared observer."""

    @abc.abstractmethod
    def errors(self, truth, out) -> Dict[str, Any]:
        """Named error vectors of one estimate (:func:`jaxatt.montecarlo.monte_carlo`'s ``errors_fn``)."""

    def windows(self, cfg) -> tuple:
        """MAE / RMSE windows ((name, start_s, end_s), ...); none by default."""
        return ()

    def window_start(self, cfg) -> float:
        return float(cfg.window_start)

    def init_params(self, cfg) -> Optional[Callable]:
        return None

    def hold(self, cfg) -> str:
        return cfg.hold

    def loss_windows(self, cfg) -> Dict[str, Tuple[float, float]]:
        ws = self.window_start(cfg)
        return {"steady": (ws, math.inf), "transient": (0.0, ws)}

    def published(self, cfg) -> dict:
        """The paper's numbers for this configuration ({} when none apply)."""
        return {}

    def comparable(self, cfg) -> Optional[str]:
        """None when ``cfg`` is the set-up of the published numbers, else a short reason (printed, stored)."""
        return None

    def notes(self, cfg) -> List[str]:
        return []

    def check_params(self, params) -> None:
        pass

    def check_step(self, cfg, params) -> None:
        """ValueError when ``cfg.dt`` is too long for these gains (an explicit integrator's stability limit)."""

    # ---- reporting -----------------------------------------------------------------------------------
    def trace(self, cfg, plotting: bool) -> Tuple[int, Optional[Callable]]:
        """(trace_every, trace_fn) of the Monte Carlo (0: no traces)."""
        return 0, None

    def entry_extra(self, cfg, per_run: Mapping[str, np.ndarray]) -> dict:
        """Study-specific keys of ``observers.<label>`` (e.g. the NLIO tables' MAE / RMSE)."""
        return {}

    def add_results(self, cfg, payload: dict, results: Mapping[str, Any]) -> None:
        """Add study-specific keys computed from the Monte Carlo results (label -> MonteCarloResult) to
        ``payload`` (e.g. averaged error curves); nothing by default."""

    def format_report(self, payload: dict) -> str:
        """The printed tables of a :func:`reproduce` payload (default: one row per metric of :attr:`rows`)."""
        return table(self.rows, payload, self.units)

    def plot(self, cfg, payload: dict, results: Mapping[str, Any], path: str, dtype=None) -> None:
        """Write the study's figure to ``path`` (``results``: label -> MonteCarloResult)."""
        raise ValueError(f"{self.name} has no figure")

    # ---- the angle-error figure of a study whose paper has none: ``trace = Study.angle_error_trace`` and
    # ``plot = Study.angle_error_figure`` in the subclass ----------------------------------------------------
    def angle_error_trace(self, cfg, plotting: bool) -> Tuple[int, Optional[Callable]]:
        """When plotting, each run's rotation-angle error (deg, float32) at about :data:`FIGURE_POINTS` times: the
        largest record interval that divides the engine's noise block and leaves that many; no traces otherwise."""
        if not plotting:
            return 0, None
        from ..engine import BLOCK

        most = max(1, int(round(cfg.duration / cfg.dt)) // FIGURE_POINTS)
        return max(d for d in range(1, min(most, BLOCK) + 1) if BLOCK % d == 0), _angle_trace

    def angle_error_figure(self, cfg, payload: dict, results: Mapping[str, Any], path: str, dtype=None) -> None:
        """The rotation-angle error (deg, log scale) against time (s) over every run: the median and the 5-95 % /
        25-75 % bands per observer, and the start of the metrics' window."""
        from .. import plot

        plt = plot._plt()
        fig, ax = plt.subplots(figsize=(7, 3.4), constrained_layout=True)
        for i, (label, res) in enumerate(results.items()):
            traces = {"t": res.traces["t"], "angle_error_deg": res.traces["angle_error_deg"]}
            runs = traces["t"].shape[0]
            plot.angle_error_plot(mc_traces=traces, ax=ax, color=f"C{i}", mc_label=f"{label}: median ({runs} runs)")
        ws = self.window_start(cfg)
        ax.axvline(ws, color="0.4", lw=0.8, ls="--", label=f"metrics from t = {ws:.4g} s")
        ax.legend(loc="best", fontsize=8)
        plot._tidy_log_axis(ax)
        ax.set_title(f"{payload.get('experiment', self.name)}: median, 25-75 % and 5-95 % of the runs", fontsize=10)
        plot.save(fig, path, close=True)

    # ---- the fitter's view ----------------------------------------------------------------------------
    def compared(self, cfg, label: str) -> Tuple[Any, Any]:
        """(Observer, params with the paper's gains) of the compared observer ``label``."""
        return self.observers(cfg)[label]

    def setup(self, observer: Optional[str] = None, **overrides) -> Setup:
        """The fitter's view of the study with config ``overrides``, for its tuned observer (``observer`` None or
        :attr:`entry`) or for another registered observer of :attr:`fittable`."""
        cfg = self.config(**overrides)
        entry, label = self.entry, self.tuned
        if observer is not None and observer != self.entry:
            if observer not in self.fittable:
                raise ValueError(f"study {self.name} tunes {', '.join([self.entry, *self.fittable])}, not {observer!r}")
            entry, label = observer, self.fittable[observer]
        obs, params = self.compared(cfg, label)
        return Setup(
            self.name,
            cfg,
            self.scenario(cfg),
            obs,
            params,
            entry,
            self.errors,
            float(cfg.duration),
            float(cfg.dt),
            self.hold(cfg),
            tuple(self.windows(cfg)),
            self.window_start(cfg),
            self.init_params(cfg),
            self.loss_kind,
            self.loss_windows(cfg),
            self.check_params,
            self.published(cfg),
            self.notes(cfg),
        )


# ------------------------------------------------------------------------------------------------------------
# Tables
# ------------------------------------------------------------------------------------------------------------
def metric_units(
    per_run: Mapping[str, Any], units: Mapping[str, str], error_units: Mapping[str, str]
) -> Dict[str, str]:
    """The unit of each Monte Carlo metric that has one: ``*_deg`` in deg; a name in the study's ``units``; any
    other metric of an error ``e`` (``std_e``, ``final_norm_e``, ``rmse_steady_e``, ...: the name ends in ``_e``)
    in ``e``'s unit (``error_units``, or ``units["std_e"]``; the longest matching error name)."""
    errs = {k[len("std_") :]: u for k, u in units.items() if k.startswith("std_")}
    errs.update(error_units)
    by_length = sorted(errs.items(), key=lambda eu: -len(eu[0]))
    out = {}
    for key in per_run:
        unit = "deg" if key.endswith("_deg") else units.get(key)
        if unit is None:
            unit = next((u for e, u in by_length if key.endswith("_" + e)), None)
        if unit is not None:
            out[key] = unit
    return out


def table(rows: Sequence[Tuple[str, str]], payload: dict, units: Mapping[str, str]) -> str:
    """quantity | paper | measured (mean over runs) | std over runs | ratio, for the single compared observer."""
    values, paper = payload.get("metrics", {}), payload.get("paper", {})
    units = dict(units, final_angle_error_deg="deg", max_angle_error_deg="deg")
    lines = [f"{'quantity':34s} {'paper':>10s} {'measured':>12s} {'(std over runs)':>16s} {'ratio':>7s}"]
    for key, label in rows:
        meas = values.get(key)
        if meas is None or (key not in paper and key not in units):
            continue
        m = units.get(key, "")
        pv = paper.get(key)
        ratio = f"{meas['mean'] / pv:7.2f}" if (pv and meas) else ""
        lines.append(
            f"{label + (' [' + m + ']' if m else ''):34s} {pv if pv is not None else '-':>10} "
            f"{meas['mean']:12.4g} {meas['std']:16.3g} {ratio}"
        )
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------------------
# Reproduce / evaluate
# ------------------------------------------------------------------------------------------------------------
def _log(quiet):
    return (lambda *a: None) if quiet else (lambda *a: report_line(" ".join(map(str, a))))


def reproduce(
    study: Study,
    cfg,
    *,
    runs: int,
    seed: int = 0,
    chunk: int = 250,
    dtype=None,
    json_path: Optional[str] = None,
    plot_path: Optional[str] = None,
    quiet: bool = False,
    progress=None,
    title: Optional[str] = None,
    observers: Optional[Mapping[str, Tuple[Any, Any]]] = None,
    extra: Optional[dict] = None,
    resume: bool = False,
    pending: bool = False,
) -> dict:
    """Monte Carlo of every compared observer of ``study`` at ``cfg``: prints the study's tables beside the
    paper's numbers, writes the JSON (see the module docstring) after every chunk and at the end, and the figure.

    ``observers`` (label -> (Observer, params)) replaces the study's (e.g. tuned gains); ``extra`` keys are added
    to the payload. Returns the payload; ``payload["complete"]`` is False when interrupted (Ctrl-C: the finished
    runs are kept) and ``payload["nonfinite"]`` names the first non-finite metric (run index) if any.

    With ``json_path``, every finished run's metrics and traces are also saved after every chunk to
    ``runs_file(json_path)`` (NPZ); ``resume=True`` reads it and runs only the runs not in it (same study, config,
    runs, seed, precision and gains, else ValueError): the result equals an uninterrupted run's. A complete result
    already at ``json_path`` is not replaced by the partial result of an interrupted run (nor by that of a
    resumed one). ``pending``: the caller computes more after this call (:func:`evaluate`'s comparison), so the
    JSON written here says ``"complete": false`` even when every run finished.
    """
    from .. import montecarlo

    if not isinstance(study, Study):
        raise ValueError(f"study must be a jaxatt study (jaxatt.studies.get(name)), got {type(study).__name__}")
    if type(cfg) is not type(study.config()):
        raise ValueError(
            f"cfg must be the {study.name} study's Config (jaxatt.studies.get({study.name!r}).config(...)), got "
            f"{type(cfg).__module__}.{type(cfg).__name__}"
        )
    if runs < 1:
        raise ValueError(f"runs must be >= 1, got {runs}")
    if resume and not runs_file(json_path):
        raise ValueError("--resume needs --json of a file (the finished runs are saved beside it)")
    io.check_output_path(json_path, "--json", suffixes=io.JSON_SUFFIXES, keep_gains=True)
    io.check_output_path(runs_file(json_path), "--json (the runs file saved beside it)")
    io.check_figure_path(plot_path, "--plot")
    if plot_path and type(study).plot is Study.plot:
        raise ValueError(f"--plot: {study.name} has no figure (leave --plot out)")
    log = _log(quiet)
    obs = dict(observers) if observers is not None else study.observers(cfg)
    for _, (_, p) in obs.items():
        study.check_params(p)
        study.check_step(cfg, p)
    dtype_name = str(np.dtype(dtype if dtype is not None else jax.numpy.result_type(float)))
    trace_every, trace_fn = study.trace(cfg, bool(plot_path))
    spec = _runs_spec(study, cfg, runs, seed, dtype_name, obs, trace_every)
    saved = _read_runs(runs_file(json_path), spec, study, study.trace(cfg, False)[0]) if resume else {}
    if resume:  # per observer: a study interrupted in its third observer holds the first two's runs
        have = ", ".join(f"{k} {len(saved[k].run_indices) if k in saved else 0}/{runs}" for k in obs)
        log(f"resuming: runs already saved in {runs_file(json_path)}: {have}")
    keep_complete = bool(json_path) and _is_complete(json_path)
    published = study.published(cfg)
    why = study.comparable(cfg)
    n_steps = int(round(cfg.duration / cfg.dt))
    payload: Dict[str, Any] = {
        "experiment": title or f"{study.name} reproduce",
        "study": study.name,
        "paper_reference": study.paper,
        "config": {**config_dict(cfg), "runs": runs, "seed": seed, "dtype": dtype_name, "chunk": chunk},
        "environment": io.environment(),
        "notes": study.notes(cfg),
        "paper": published,
        "comparable_with_paper": why is None,
        "observers": {},
        "complete": False,
        "runs_done": 0,
    }
    if why is not None:
        payload["not_comparable_because"] = why
    payload.update(extra or {})
    results: Dict[str, Any] = {}
    t_all = time.perf_counter()
    complete = True
    for label, (observer, params) in obs.items():
        t0 = time.perf_counter()

        def entry(res, t0=t0):
            e = {
                "runs_done": len(res.run_indices),
                "metrics": io.summarise(res.per_run),
                "metric_units": metric_units(res.per_run, study.units, study.error_units),
                "timing": {
                    "wall_s": time.perf_counter() - t0,
                    "runs": len(res.run_indices),
                    "steps_per_run": n_steps,
                    "run_steps_per_s": len(res.run_indices) * n_steps / max(time.perf_counter() - t0, 1e-9),
                    "note": "compile included",
                },
            }
            e.update(study.entry_extra(cfg, res.per_run))
            return e

        def on_chunk(res, label=label, entry=entry):
            log(f"  {label}: {len(res.run_indices)}/{runs} runs, {time.perf_counter() - t_all:.1f} s")
            payload["observers"][label] = entry(res)
            _finish(payload, complete=False, n_observers=len(obs))
            if runs_file(json_path):
                montecarlo.save_runs(runs_file(json_path), spec, {**results, label: res})
            if not keep_complete:
                io.write_json(json_path, payload)

        previous = saved.get(label)
        if previous is not None and previous.complete:  # resumed: nothing left to run
            res = previous
        else:
            res = montecarlo.monte_carlo(
                study.scenario(cfg),
                observer,
                params,
                runs=runs,
                duration=cfg.duration,
                dt=cfg.dt,
                seed=seed,
                errors_fn=study.errors,
                window_start=study.window_start(cfg),
                hold=study.hold(cfg),
                chunk=chunk,
                trace_every=trace_every,
                trace_fn=trace_fn,
                dtype=dtype,
                windows=study.windows(cfg),
                init_params=study.init_params(cfg),
                on_chunk=on_chunk,
                progress=progress,
                previous=previous,
            )
        results[label] = res
        payload["observers"][label] = entry(res)
        bad = res.first_nonfinite()
        if bad and "nonfinite" not in payload:
            payload["nonfinite"] = f"{label}: {bad}"
        complete &= res.complete
        if not res.complete:
            break
    payload["timing"] = {"wall_s": time.perf_counter() - t_all, "runs": runs, "steps_per_run": n_steps}
    payload["notes"] = unsettled_notes(results, study.window_start(cfg)) + payload["notes"]
    study.add_results(cfg, payload, results)
    _finish(payload, complete=complete and len(payload["observers"]) == len(obs), n_observers=len(obs))
    if len(obs) == 1:
        payload["timing"].update(next(iter(payload["observers"].values()))["timing"])
    report = study.format_report(payload)
    done_reporting()
    head = (
        f"{payload['experiment']}: {payload['runs_done']} runs x {cfg.duration:g} s at {1 / cfg.dt:g} Hz, "
        f"observers in {dtype_name}" + ("" if payload["complete"] else "  [INTERRUPTED: partial results]")
    )
    print(head)
    if why is not None:
        print(f"  NOT comparable with the paper's numbers: {why}")
    for n in payload["notes"][:3]:
        print(f"  {n}")
    print(report)
    payload["tables_text"] = report
    wall = payload["timing"]["wall_s"]
    print(
        f"wall {wall:.1f} s, {payload['runs_done'] * n_steps * len(payload['observers']) / max(wall, 1e-9):.3g} "
        "run-steps/s (compile included)"
    )
    if plot_path and payload["complete"] and io.is_main_process():  # several processes: process 0 writes
        study.plot(cfg, payload, results, plot_path, dtype=dtype)
        payload["plot"] = plot_path
        print(f"plot written to {plot_path}")
    if runs_file(json_path):
        montecarlo.save_runs(runs_file(json_path), spec, results)
    on_disk = {**payload, "complete": False} if pending else payload
    if on_disk["complete"] or not keep_complete:
        io.write_json(json_path, on_disk)
        if json_path and not pending:
            print(f"results written to {json_path}" + ("" if payload["complete"] else " (complete: false)"))
    elif not pending:
        print(f"the complete result already in {json_path} is kept")
    if runs_file(json_path) and not payload["complete"]:
        print(f"finished runs saved in {runs_file(json_path)}: rerun with --resume to finish")
    return payload


#: Mean angle error (deg) over the steady-state window above which a Monte Carlo says its observer has not settled:
#: far above any converged number of the studies (< 1 deg), so only a run still in its transient crosses it.
UNSETTLED_DEG = 20.0


def unsettled_notes(results: dict, window_start: float) -> List[str]:
    """One note per observer whose mean angle error over the steady-state window exceeds :data:`UNSETTLED_DEG`:
    its "steady-state" numbers are a transient (e.g. batista-ges at latitude -38.7 deg with the default field:
    168.7 deg over 2400-3600 s, 0.5 deg after 9000 s, since its gains shrink with |I_omegaE x I_m|)."""
    notes = []
    for label, res in results.items():
        err = np.asarray(res.per_run.get("mean_angle_error_deg", []), float)
        if err.size and np.isfinite(err).all() and float(np.mean(err)) > UNSETTLED_DEG:
            notes.append(
                f"{label} has not settled: its mean angle error over the window t >= {window_start:g} s is "
                f"{float(np.mean(err)):.1f} deg. Its settling time depends on the set-up (gains, latitude, field, "
                "trajectory): lengthen --duration and --window-start before reading these as steady-state numbers"
            )
    return notes


def runs_file(json_path) -> Optional[str]:
    """Where :func:`reproduce` saves the finished runs of ``json_path`` (for ``resume``): ``<json_path>.runs.npz``;
    None without ``json_path`` or when it is a device or FIFO such as /dev/null (nothing is saved to resume)."""
    if not json_path or io.is_special(json_path):
        return None
    return f"{json_path}.runs.npz"


def _runs_spec(study, cfg, runs, seed, dtype_name, obs, trace_every=None) -> str:
    """What must match for saved runs to be resumed: study, config, runs, seed, precision, labels, gains and the
    spacing of the saved traces (``--plot`` keeps them finer)."""
    import json

    gains = {label: [np.asarray(x).tolist() for x in jax.tree_util.tree_leaves(p)] for label, (_, p) in obs.items()}
    return json.dumps(
        {
            "study": study.name,
            "config": config_dict(cfg),
            "runs": runs,
            "seed": seed,
            "dtype": dtype_name,
            "gains": gains,
            "trace_every": trace_every,
        },
        sort_keys=True,
        default=str,
    )


def _read_runs(path, spec: str, study=None, plain_trace_every=0) -> Dict[str, Any]:
    """label -> MonteCarloResult of the runs file ``path`` of the same set-up; {} when there is no file. A file
    of an earlier version, whose spec lacks a key added since, is read when this run uses that key's old value
    (the traces kept without --plot, ``plain_trace_every``; a config field at its default)."""
    from ..montecarlo import load_runs, spec_differences

    saved_spec, results = load_runs(path, "--resume", again="delete it to start again")
    assumed = {"trace_every": plain_trace_every, "config": config_dict(study.config()) if study is not None else {}}
    differ = spec_differences(saved_spec, spec, assumed) if results else []
    if differ:
        said = ", ".join("--plot" if k == "trace_every" else k for k in differ)
        raise ValueError(
            f"--resume: {path} holds runs of another set-up ({said} {'differ' if len(differ) > 1 else 'differs'}); "
            "rerun with the same flags, or without "
            "--resume to start again"
        )
    return results


def _is_complete(json_path) -> bool:
    """Whether ``json_path`` holds a complete result of an earlier run."""
    try:
        return bool(io.read_json(json_path).get("complete"))
    except ValueError:
        return False


def _finish(payload: dict, complete: bool, n_observers: int) -> None:
    """Top-level ``complete``, ``runs_done`` and, for a study of one observer, its ``metrics`` / ``metric_units``
    (a study of several has them per observer only: not the first observer's while it alone has runs)."""
    entries = payload["observers"]
    payload["complete"] = complete
    payload["runs_done"] = min((e["runs_done"] for e in entries.values()), default=0)
    if n_observers == 1 and len(entries) == 1:
        payload["metrics"] = next(iter(entries.values()))["metrics"]
        payload["metric_units"] = next(iter(entries.values())).get("metric_units", {})


def evaluate(
    study: Study,
    params,
    *,
    runs: int = 100,
    seed: int = 1,
    json_path: Optional[str] = None,
    cfg=None,
    gains_source: str = "paper",
    compare_paper: bool = True,
    chunk: int = 250,
    dtype=None,
    quiet: bool = False,
    extra: Optional[dict] = None,
    progress=None,
    resume: bool = False,
) -> dict:
    """Monte Carlo of the study's tuned observer with ``params`` (e.g. from a gains file) on ``runs`` runs of base
    ``seed``; with ``compare_paper`` also the paper's gains on the same runs: ``paper_gains_metrics`` and
    ``comparison`` (mean of each metric, tuned / paper). Same JSON layout as :func:`reproduce` (``progress``,
    ``resume``: as there; the comparison with the paper's gains is run again on resume)."""
    from ..fitting import gainsfile
    from ..observers import registry

    cfg = cfg if cfg is not None else study.config()
    s = study.setup(**config_dict(cfg))
    study.check_params(params)
    gains = registry.get(s.entry).gains
    obs = {study.tuned: (s.observer, params)}
    same = all(
        np.array_equal(np.asarray(a), np.asarray(b))
        for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(s.params))
    )
    kept = bool(json_path) and _is_complete(json_path)  # a complete result there is replaced by a complete one only
    payload = reproduce(
        study,
        cfg,
        runs=runs,
        seed=seed,
        chunk=chunk,
        dtype=dtype,
        json_path=json_path,
        quiet=quiet,
        title=f"{study.name} evaluate",
        observers=obs,
        progress=progress,
        resume=resume,
        extra={"gains": gainsfile.gains_to_dict(params, gains), "gains_path": gains_source, **(extra or {})},
        pending=compare_paper and not same,  # complete only with the comparison
    )
    if compare_paper and not same and payload["complete"]:
        try:
            ref = reproduce(
                study,
                cfg,
                runs=runs,
                seed=seed,
                chunk=chunk,
                dtype=dtype,
                json_path=None,
                quiet=True,
                title=f"{study.name} paper gains",
                observers={study.tuned: (s.observer, s.params)},
            )
        except KeyboardInterrupt:  # before its first chunk finished
            ref = {"complete": False, "runs_done": 0}
        if not ref["complete"]:  # interrupted: the tuned runs are saved, the comparison is run again on resume
            payload["complete"] = False
            payload["paper_gains_runs_done"] = ref["runs_done"]
            if not kept:
                io.write_json(json_path, payload)
            print(
                f"INTERRUPTED during the comparison with the paper's gains ({ref['runs_done']}/{runs} runs): "
                "no comparison written"
                + (f"; rerun with --resume to finish {json_path}" if json_path else "")
                + (f" (the complete result already in {json_path} is kept)" if kept else "")
            )
            return payload
        pm = ref["metrics"]
        metrics = payload["metrics"]
        payload["paper_gains_metrics"] = pm
        payload["comparison"] = {
            k: {
                "tuned": metrics[k]["mean"],
                "paper_gains": pm[k]["mean"],
                "ratio": (metrics[k]["mean"] / pm[k]["mean"] if pm[k]["mean"] else None),
            }
            for k in metrics
            if k in pm and np.ndim(metrics[k]["mean"]) == 0
        }
        lines = [f"{'metric':34s} {'tuned':>12s} {'paper gains':>12s} {'ratio':>7s}"]
        for k, c in list(payload["comparison"].items())[:16]:
            lines.append(
                f"{k:34s} {c['tuned']:12.5g} {c['paper_gains']:12.5g} "
                f"{(c['ratio'] if c['ratio'] is not None else float('nan')):7.3f}"
            )
        print("\n".join(lines))
        io.write_json(json_path, payload)
        if json_path:
            print(f"results written to {json_path}")
    return payload
