"""Observers on the BROAD benchmark: evaluation per trial and per group, and gains learned from data by gradient
descent through the whole filter run.

Data: BROAD (D. Laidig, M. Caruso, A. Cereatti, T. Seel, "BROAD - A Benchmark for Robust Inertial Orientation
Estimation", Data 6(7), 2021, doi:10.3390/data6070072, CC BY 4.0); see :mod:`jaxatt.data.broad` for the files,
frames (sensor-to-ENU quaternions, w, x, y, z), units (rad/s, m/s^2, uT) and the metric.

Functions (plain arguments; the CLI's ``jaxatt broad`` / ``jaxatt broad-tune`` call them):

* :func:`broad_eval` - run an observer on every trial (one vmapped, jitted run) and print / return the BROAD
  metric (total, heading, inclination RMSE in degrees over the movement samples) per trial and the group means
  (undisturbed 01-23, disturbed 24-39).
* :func:`broad_tune` - learn the gains of an observer on training trials: optax Adam on the mean per-trial total
  RMSE (each group weighted equally), differentiated (reverse mode) through the full scan, every step
  ``jax.checkpoint``-ed (the reverse pass stores only the filter state); positive gains learnt in log space
  within bounds. On CPU (jax 0.10) ``XLA_FLAGS=--xla_cpu_use_fusion_emitters=false`` roughly halves the time of a
  gradient (XLA's default CPU fusion duplicates much of the reverse pass) and compiles 5x faster. The gains
  file is written atomically while it runs (interrupt-safe) and is what ``broad_eval(gains_path=...)`` reads.
* :func:`broad_crossval` - 2-fold cross-validation stratified by group (:func:`stratified_folds`): tune on one
  fold, evaluate on the other, so every trial gets an out-of-fold number.

Observers (``observer_name``): ``"robust"`` (:mod:`jaxatt.observers.robust_ahrs`; default gains: the shipped
``robust_broad_all.json``), ``"mahony"`` (BROAD's Mahony, their start and TAGP gains, reproduces the published
numbers), ``"complementary"`` (Trumpf et al. eq. (18), acc "up" and the trial's own first field direction as ENU
references, TRIAD start, bias integrator), and, when their modules import, ``"nlio"`` (NLIO-TV), ``"nlio-fg"``,
``"nlo"`` and ``"mekf"`` with references and noise levels in BROAD's units (m/s^2, uT, rad/s), started from TRIAD.

Gains file (JSON): ``{"format": "jaxatt-gains/1", "observer": NAME, "gains": {name: value}, "tuned": [...],
"train_trials": [...], "loss_deg": ..., "history": [...], ...}``; ``gains`` holds every user-facing gain.
"""
from __future__ import annotations

import datetime as _dt
import json
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, NamedTuple, Optional, Sequence, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from . import so3
from .data import broad
from .observers.base import ImuSample, Observer

__all__ = ["broad_eval", "broad_tune", "broad_crossval", "stratified_folds", "resolve_trials", "observer_names",
           "get_spec", "load_gains", "save_gains", "params_from_gains", "ObserverSpec", "ANCHORS", "GROUPS",
           "make_loss"]

GROUPS = ("undisturbed", "disturbed")

#: Mean total RMSE (deg, BROAD metric) of other libraries on the 20 shared trials (issue 7's anchors table;
#: benchmarks/broad.py re-measures them).
ANCHORS = {
    "VQF online 9D": {"undisturbed": 1.90, "disturbed": 3.49},
    "VQF offline 9D": {"undisturbed": 1.95, "disturbed": 2.28},
    "ahrs Madgwick beta=0.12": {"undisturbed": 3.87, "disturbed": 7.14},
    "ahrs Mahony (BROAD best)": {"undisturbed": 7.22, "disturbed": 11.40},
    "imufusion defaults": {"undisturbed": 8.14, "disturbed": 20.45},
}

_DEG = math.pi / 180.0


# ------------------------------------------------------------------------------------------------------------
# Observer registry
# ------------------------------------------------------------------------------------------------------------
class ObserverSpec(NamedTuple):
    """How one observer runs on BROAD.

    Fields:
        name: registry name.
        observer: the Observer run per trial (wrapped so that ``init`` computes per-trial quantities - start
            attitude, field reference - from the first sample; ``Out.q`` is sensor-to-ENU).
        defaults: {gain: value}, the gains used when no file is given.
        build: ``build(gains: dict of scalars) -> Params`` (differentiable in the gains).
        tunable: gains :func:`broad_tune` learns by default (all positive, learnt in log space).
        bounds: {gain: (lo, hi)} for the tuned gains.
        note: one line on what the defaults are.
        prepare: optional ``prepare(params, dt)`` -> what ``step`` takes (coefficients hoisted out of the scan).
        start: {gain: value} :func:`broad_tune` starts from when no ``init_gains`` are given (None: ``defaults``).
            The robust AHRS starts from its untuned defaults, never from the shipped gains (which were tuned on
            every trial and would leak other trials into a cross-validation fold).
    """

    name: str
    observer: Observer
    defaults: Dict[str, float]
    build: Callable[[Dict[str, Any]], Any]
    tunable: Tuple[str, ...]
    bounds: Dict[str, Tuple[float, float]]
    note: str = ""
    prepare: Optional[Callable] = None
    start: Optional[Dict[str, float]] = None


class _TrialState(NamedTuple):
    inner: Any
    trial_params: Any

    @property
    def t(self):
        return self.inner.t


class BroadOut(NamedTuple):
    """Output of a wrapped observer: t (s), q (4,) sensor-to-ENU (w, x, y, z), r (3, 3), bias (3,) rad/s."""

    t: jax.Array
    q: jax.Array
    r: jax.Array
    bias: jax.Array


def _triad_enu(acc, mag):
    from .observers.robust_ahrs import quat_from_acc_mag_enu

    return quat_from_acc_mag_enu(acc, mag)


def _per_trial(base: Observer, fill: Callable, per_trial_fields: Sequence[str], name: str, to_out: Callable):
    """Wrap ``base`` so that ``init`` fills the per-trial fields of the params from the first sample (stored in
    the state) and ``step`` combines them with the gains of the params it is given (so gradients reach them)."""

    def init(p, sample):
        pt = fill(p, sample)
        return _TrialState(base.init(pt, sample), tuple(getattr(pt, f) for f in per_trial_fields))

    def step(p, s: _TrialState, sample, dt):
        pt = p._replace(**dict(zip(per_trial_fields, s.trial_params)))
        inner, out = base.step(pt, s.inner, sample, dt)
        return _TrialState(inner, s.trial_params), to_out(out)

    return Observer(init, step, name)


def _first_field_enu(sample):
    """(q0, R0, m_ENU, |a|) from the first acc / mag sample: TRIAD start and the field in the estimated ENU."""
    acc, mag = jnp.asarray(sample.acc), jnp.asarray(sample.mag)
    q0 = _triad_enu(acc, mag)
    r0 = so3.quat_to_matrix(q0)
    return q0, r0, r0 @ mag, jnp.sqrt(jnp.sum(acc * acc))


def _spec_robust() -> ObserverSpec:
    from .observers import robust_ahrs as ra

    try:
        from .data import gains as shipped

        defaults = dict(shipped.load("robust_broad_all.json")["gains"])
        note = "shipped gains robust_broad_all.json (tuned on all 20 trials: in-sample here)"
    except Exception:  # noqa: BLE001 - no shipped file yet
        defaults = ra.params_to_dict(ra.default_params(jnp.float64 if jax.config.jax_enable_x64 else None))
        note = "untuned defaults"
    defaults = {k: float(defaults.get(k, v)) for k, v in ra._DEFAULTS.items()}
    start = {k: float(v) for k, v in ra._DEFAULTS.items()}

    def build(g):
        return ra.Params(**{k: jnp.asarray(g[k]) for k in ra.PARAM_NAMES})

    bounds = dict(
        tau_acc=(0.05, 30.0), tau_acc_2=(1e-3, 30.0), tau_mag=(0.5, 200.0), tau_bias=(1.0, 1e4),
        tau_bias_rest=(0.1, 100.0), tau_rest=(0.05, 10.0), rest_hold=(0.05, 20.0),
        rest_th_gyr=(0.1 * _DEG, 20 * _DEG), rest_th_acc=(0.02, 5.0), acc_th=(0.5, 200.0), acc_hold=(0.005, 5.0),
        mag_norm_th=(0.01, 2.0), mag_dip_th=(0.5 * _DEG, 90 * _DEG), mag_hold=(0.01, 20.0),
        tau_mag_ref=(1.0, 1e4))
    return ObserverSpec("robust", ra.make_observer(), defaults, build, tuple(ra.TUNABLE), bounds, note,
                        prepare=ra.coefficients, start=start)


def _spec_mahony() -> ObserverSpec:
    from .observers import mahony

    def build(g):
        return mahony.Params(jnp.asarray(g["kp"]), jnp.asarray(g["ki"]))

    return ObserverSpec("mahony", mahony.make_observer("broad"), {"kp": 0.74, "ki": 0.0012}, build, ("kp", "ki"),
                        {"kp": (1e-3, 50.0), "ki": (1e-7, 10.0)},
                        "BROAD's TAGP gains, their start (quatFromAccMag) and ENU conversion")


def _spec_complementary() -> ObserverSpec:
    from .observers import complementary as cf

    base = cf.make_observer(form="quaternion", imu_fields=("acc", "mag"), normalize=True)

    def fill(p, sample):
        q0, r0, m_enu, _ = _first_field_enu(sample)
        up = jnp.array([0.0, 0.0, 1.0], m_enu.dtype)
        return p._replace(r_hat_0=r0, ref_inertial=jnp.stack([up, m_enu / jnp.sqrt(jnp.sum(m_enu ** 2))]))

    def to_out(o):
        return BroadOut(o.t, o.q, o.r, o.bias)

    obs = _per_trial(base, fill, ("r_hat_0", "ref_inertial"), "complementary", to_out)
    dummy = cf.imu_params(1.0, 1.0, mag_ref=(0.0, 1.0, -1.0), frame="ENU")

    def build(g):
        k = jnp.stack([jnp.asarray(g["k_acc"]), jnp.asarray(g["k_mag"])])
        return dummy._replace(k=k.astype(jnp.result_type(k)), k_i=jnp.asarray(g["k_i"]),
                              r_hat_0=dummy.r_hat_0.astype(k.dtype), bias_0=dummy.bias_0.astype(k.dtype),
                              ref_inertial=dummy.ref_inertial.astype(k.dtype), l=dummy.l.astype(k.dtype),
                              ref_body=dummy.ref_body.astype(k.dtype))

    return ObserverSpec("complementary", obs, {"k_acc": 0.5, "k_mag": 0.2, "k_i": 0.02}, build,
                        ("k_acc", "k_mag", "k_i"), {"k_acc": (1e-3, 50.0), "k_mag": (1e-3, 50.0), "k_i": (1e-5, 10.0)},
                        "Trumpf et al. eq. (18) with bias integrator; refs: up and the first sample's field (ENU)")


def _spec_nlio(variant: str) -> ObserverSpec:
    from .observers import nlio

    base = nlio.make_observer(variant=variant)

    def fill(p, sample):
        q0, r0, m_enu, anorm = _first_field_enu(sample)
        return p._replace(r_hat_0=r0, mag_ref_nav=m_enu,
                          acc_ref_nav=jnp.stack([jnp.zeros_like(anorm), jnp.zeros_like(anorm), anorm]))

    def to_out(o):
        return BroadOut(o.t, so3.quat_canonical(so3.matrix_to_quat(o.r)), o.r, o.bias)

    obs = _per_trial(base, fill, ("r_hat_0", "mag_ref_nav", "acc_ref_nav"), variant, to_out)
    dummy = nlio.default_params((0.0, 0.0, 9.81), (0.0, 17.0, -40.0))
    eye = np.eye(3)

    def build(g):
        dt = jnp.result_type(jnp.asarray(g["kp"]))
        cast = lambda a: jnp.asarray(a, dt)  # noqa: E731
        base_p = jax.tree_util.tree_map(cast, dummy)
        return base_p._replace(
            kp=cast(g["kp"]) * eye, kv=cast(g["kv"]), k1=cast(g["k1"]) * eye, k2=cast(g["k2"]) * eye,
            gyro_noise_std=cast(g["gyro_noise_std"]), r_acc=cast(g["acc_noise_std"]) ** 2 * eye,
            r_mag=cast(g["mag_noise_std"]) ** 2 * eye, p0_acc=cast(g["acc_noise_std"]) ** 2 * eye,
            p0_mag=cast(g["mag_noise_std"]) ** 2 * eye, bias_bound=cast(g["bias_bound"]),
            bias_max=cast(g["bias_bound"]) * 1.2)

    defaults = {"kp": 0.3, "kv": 0.02, "k1": 1.0, "k2": 0.3, "gyro_noise_std": 0.002, "acc_noise_std": 0.5,
                "mag_noise_std": 1.0, "bias_bound": 0.02}
    tunable = ("kp", "kv") + (("k1", "k2") if variant == "nlio-fg" else
                              ("gyro_noise_std", "acc_noise_std", "mag_noise_std") if variant == "nlio-tv" else ())
    bounds = {k: (v * 1e-3, v * 1e3) for k, v in defaults.items()}
    name = {"nlio-tv": "nlio", "nlio-fg": "nlio-fg", "nlo": "nlo"}[variant]
    return ObserverSpec(name, obs, defaults, build, tunable, bounds,
                        "untuned BROAD-unit defaults (m/s^2, uT), TRIAD start, first field as reference")


def _spec_mekf() -> ObserverSpec:
    from .observers import mekf

    base = mekf.make_observer()

    def fill(p, sample):
        q0, r0, m_enu, anorm = _first_field_enu(sample)
        return p._replace(r_hat_0=r0, mag_ref_nav=m_enu,
                          acc_ref_nav=jnp.stack([jnp.zeros_like(anorm), jnp.zeros_like(anorm), anorm]))

    def to_out(o):
        return BroadOut(o.t, o.q, o.r, o.bias)

    obs = _per_trial(base, fill, ("r_hat_0", "mag_ref_nav", "acc_ref_nav"), "mekf", to_out)
    dummy = mekf.default_params((0.0, 0.0, 9.81), (0.0, 17.0, -40.0))
    eye = np.eye(3)

    def build(g):
        dt = jnp.result_type(jnp.asarray(g["gyro_noise_std"]))
        cast = lambda a: jnp.asarray(a, dt)  # noqa: E731
        base_p = jax.tree_util.tree_map(cast, dummy)
        p0 = jnp.diag(jnp.concatenate([jnp.full(3, cast(g["p0_att"])), jnp.full(3, cast(g["p0_bias"]))]))
        return base_p._replace(gyro_noise_std=cast(g["gyro_noise_std"]), bias_rw=cast(g["bias_rw"]),
                               r_acc=cast(g["acc_noise_std"]) ** 2 * eye, r_mag=cast(g["mag_noise_std"]) ** 2 * eye,
                               p0=p0)

    defaults = {"gyro_noise_std": 0.002, "bias_rw": 1e-5, "acc_noise_std": 1.0, "mag_noise_std": 3.0,
                "p0_att": 1e-4, "p0_bias": 1e-5}
    bounds = {k: (v * 1e-3, v * 1e3) for k, v in defaults.items()}
    return ObserverSpec("mekf", obs, defaults, build, ("gyro_noise_std", "bias_rw", "acc_noise_std",
                                                      "mag_noise_std"), bounds,
                        "untuned BROAD-unit defaults (m/s^2, uT), TRIAD start, first field as reference")


_BUILDERS = {
    "robust": _spec_robust,
    "mahony": _spec_mahony,
    "complementary": _spec_complementary,
    "nlio": lambda: _spec_nlio("nlio-tv"),
    "nlio-fg": lambda: _spec_nlio("nlio-fg"),
    "nlo": lambda: _spec_nlio("nlo"),
    "mekf": _spec_mekf,
}
_SPECS: Dict[str, ObserverSpec] = {}


def get_spec(name: str) -> ObserverSpec:
    """The :class:`ObserverSpec` of a registered observer (ImportError if its module is not available)."""
    if name not in _BUILDERS:
        raise ValueError(f"unknown observer {name!r}; known: {sorted(_BUILDERS)}")
    if name not in _SPECS:
        _SPECS[name] = _BUILDERS[name]()
    return _SPECS[name]


def observer_names(available_only: bool = True) -> List[str]:
    """Registered observer names (by default only those whose modules import)."""
    out = []
    for n in _BUILDERS:
        if not available_only:
            out.append(n)
            continue
        try:
            get_spec(n)
            out.append(n)
        except Exception:  # noqa: BLE001 - a module that does not import is simply not offered
            pass
    return out


# ------------------------------------------------------------------------------------------------------------
# Gains files
# ------------------------------------------------------------------------------------------------------------
def _atomic_write_json(path, payload: dict) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=str(path.parent))
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(payload, f, indent=2)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def save_gains(path, observer_name: str, gains: Dict[str, float], **extra) -> None:
    """Write a gains file atomically (see the module docstring for the format)."""
    payload = {"format": "jaxatt-gains/1", "observer": observer_name,
               "gains": {k: float(v) for k, v in gains.items()}, **extra}
    _atomic_write_json(path, payload)


def load_gains(path) -> Tuple[str, Dict[str, float], dict]:
    """Read a gains file: (observer name, {gain: value}, whole JSON)."""
    with open(path) as f:
        d = json.load(f)
    if "gains" not in d or "observer" not in d:
        raise ValueError(f"{path}: not a jaxatt gains file (needs 'observer' and 'gains')")
    return d["observer"], {k: float(v) for k, v in d["gains"].items()}, d


def params_from_gains(spec: ObserverSpec, gains: Optional[Dict[str, float]] = None, dtype=None):
    """Params of ``spec`` from a {gain: value} mapping (missing gains take the spec's defaults)."""
    gains = dict(gains or {})
    unknown = set(gains) - set(spec.defaults)
    if unknown:
        raise ValueError(f"gains {sorted(unknown)} are not gains of observer {spec.name!r} "
                         f"(known: {sorted(spec.defaults)})")
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.result_type(float)
    g = {k: jnp.asarray(gains.get(k, v), dtype) for k, v in spec.defaults.items()}
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), spec.build(g))


# ------------------------------------------------------------------------------------------------------------
# Trials and folds
# ------------------------------------------------------------------------------------------------------------
def _group_of(name: str, info) -> str:
    gs = broad.trial_groups(name, info)
    return "disturbed" if "disturbed" in gs else "undisturbed"


def stratified_folds(names: Sequence[str], info=None, k: int = 2) -> List[List[str]]:
    """k folds of trial names stratified by group: within each group (sorted by name) trial i goes to fold
    i mod k. For the 20 shared trials and k = 2: fold 1 = 01 04 06 08 11 14 18 24 28 32, fold 2 = 02 05 07 10 12
    15 21 26 30 34 (each fold has one tapping / vibration, one stationary-magnet and one attached-magnet trial)."""
    folds: List[List[str]] = [[] for _ in range(k)]
    for g in GROUPS:
        members = sorted(n for n in names if _group_of(n, info) == g)
        for i, n in enumerate(members):
            folds[i % k].append(n)
    return [sorted(f) for f in folds]


def resolve_trials(data_dir, trials=None) -> List[str]:
    """Trial names from a spec: None (all), or a list / comma-separated string of trial names, leading numbers
    ("01", "24"), group names ("undisturbed", "disturbed") or "fold1" / "fold2" (:func:`stratified_folds`)."""
    names = broad.list_trials(data_dir)
    if not names:
        raise FileNotFoundError(f"no BROAD trial files (*.hdf5) in {data_dir}")
    if trials is None:
        return names
    if isinstance(trials, str):
        trials = [t for t in trials.replace(",", " ").split() if t]
    info = broad.load_trial_info(data_dir)
    out: List[str] = []
    for t in trials:
        t = str(t)
        if t in names:
            sel = [t]
        elif t in GROUPS:
            sel = [n for n in names if _group_of(n, info) == t]
        elif t.startswith("fold") and t[4:].isdigit():
            folds = stratified_folds(names, info)
            i = int(t[4:]) - 1
            if not 0 <= i < len(folds):
                raise ValueError(f"{t}: there are {len(folds)} folds")
            sel = folds[i]
        else:
            sel = [n for n in names if n.split("_")[0] == t.zfill(2)]
            if not sel:
                raise ValueError(f"trial {t!r} not found in {data_dir}")
        out.extend(s for s in sel if s not in out)
    return out


# ------------------------------------------------------------------------------------------------------------
# Evaluation
# ------------------------------------------------------------------------------------------------------------
def _summaries(per_trial: Dict[str, dict], info) -> Dict[str, dict]:
    groups: Dict[str, dict] = {}
    for g in GROUPS + ("all",):
        rows = [v for n, v in per_trial.items() if g == "all" or _group_of(n, info) == g]
        if rows:
            groups[g] = {"n_trials": len(rows), **{m: float(np.mean([r[m] for r in rows])) for m in broad.METRICS}}
    return groups


def _print_table(title: str, per_trial: Dict[str, dict], groups: Dict[str, dict], info, extra_cols=None) -> None:
    print(f"\n{title}")
    print(f"{'trial':48s} {'group':11s} {'total':>7s} {'heading':>8s} {'incl':>7s}")
    for n, v in per_trial.items():
        print(f"{n:48s} {_group_of(n, info):11s} {v['total_rmse_deg']:7.2f} {v['heading_rmse_deg']:8.2f} "
              f"{v['inclination_rmse_deg']:7.2f}")
    for g, v in groups.items():
        print(f"{'mean ' + g + ' (' + str(v['n_trials']) + ' trials)':60s} {v['total_rmse_deg']:7.2f} "
              f"{v['heading_rmse_deg']:8.2f} {v['inclination_rmse_deg']:7.2f}")
    print("anchors (mean total RMSE, deg; issue 7): " + "; ".join(
        f"{k}: {v['undisturbed']:.2f} / {v['disturbed']:.2f}" for k, v in ANCHORS.items()) + "  (undisturbed / disturbed)")


def broad_eval(data_dir, observer_name: str = "robust", gains_path=None, json_path=None, trials=None, *,
               dtype: str = "float64", verbose: bool = True, loaded=None) -> dict:
    """Evaluate an observer on BROAD trials with the BROAD metric; prints per-trial numbers and group means.

    Args:
        data_dir: folder of BROAD ``*.hdf5`` trial files (and ``trials.json``).
        observer_name: see :func:`observer_names`.
        gains_path: a gains file written by :func:`broad_tune` (None: the observer's defaults; for "robust" the
            shipped ``robust_broad_all.json``).
        json_path: write the result dict there as JSON (atomically).
        trials: which trials (:func:`resolve_trials`; default all).
        dtype: "float64" (default) or "float32" arithmetic of the filter.
        verbose: print the table.
        loaded: optional {name: Trial} cache of already loaded trials.
    Returns {"observer", "gains", "gains_source", "dtype", "trials": {name: {group, metrics}}, "groups": {group:
    {n_trials, mean metrics}}, "wall_s", "anchors"}.
    """
    spec = get_spec(observer_name)
    source = spec.note
    gains = dict(spec.defaults)
    if gains_path is not None:
        obs_name, file_gains, _ = load_gains(gains_path)
        if obs_name != spec.name:
            raise ValueError(f"{gains_path} holds gains of observer {obs_name!r}, not {spec.name!r}")
        gains.update(file_gains)
        source = str(gains_path)
    names = resolve_trials(data_dir, trials)
    info = broad.load_trial_info(data_dir)
    trs = [loaded[n] if loaded and n in loaded else broad.load_trial(Path(data_dir) / f"{n}.hdf5") for n in names]
    params = params_from_gains(spec, gains, dtype=jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)
    t0 = time.perf_counter()
    res = broad.evaluate(spec.observer, params, trs, dtype=jnp.dtype(dtype))
    wall = time.perf_counter() - t0
    per_trial = {n: {"group": _group_of(n, info), **res[n]} for n in names}
    groups = _summaries(per_trial, info)
    out = {"observer": spec.name, "gains": gains, "gains_source": source, "dtype": str(dtype),
           "trials": per_trial, "groups": groups, "wall_s": wall, "anchors": ANCHORS,
           "data": broad.ATTRIBUTION}
    if verbose:
        _print_table(f"BROAD, observer {spec.name} ({source}), {dtype}", per_trial, groups, info)
    if json_path is not None:
        _atomic_write_json(json_path, out)
    return out


# ------------------------------------------------------------------------------------------------------------
# Differentiable loss: mean per-trial total RMSE through the full (checkpointed) scan
# ------------------------------------------------------------------------------------------------------------
def _err2_total(q_est, q_true):
    """Squared total error angle (rad^2) between unit quaternions, gradient-safe at zero error."""
    w, x, y, z = (c[..., 0] for c in jnp.split(so3.quat_multiply(q_est, so3.quat_conjugate(q_true)), 4, -1))
    v2 = x * x + y * y + z * z
    ok = v2 > 0
    vn = jnp.where(ok, jnp.sqrt(jnp.where(ok, v2, 1.0)), 0.0)
    ang = 2.0 * jnp.arctan2(vn, jnp.abs(w))
    return ang * ang


class _Batch(NamedTuple):
    gyr: jax.Array  # (B, T, 3)
    acc: jax.Array
    mag: jax.Array
    q_true: jax.Array  # (B, T, 4), finite
    use: jax.Array  # (B, T) bool: movement & finite truth & real sample
    dt: jax.Array  # (B,)
    weight: jax.Array  # (B,) loss weight (sums to 1)


def _make_batch(trials, dtype, info) -> Tuple[_Batch, List[str]]:
    padded = broad.pad_trials(trials)
    qt = np.asarray(padded.quat_true)
    finite = np.all(np.isfinite(qt), axis=-1)
    qt = np.where(finite[..., None], qt, np.array([1.0, 0.0, 0.0, 0.0]))
    use = padded.movement & padded.mask & finite
    groups = [_group_of(n, info) for n in padded.names]
    present = sorted(set(groups))
    w = np.array([1.0 / (len(present) * groups.count(g)) for g in groups])
    cast = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    batch = _Batch(cast(padded.samples.gyr), cast(padded.samples.acc), cast(padded.samples.mag), cast(qt),
                   jnp.asarray(use), cast(1.0 / padded.rate_hz), cast(w))
    return batch, list(padded.names)


def make_loss(observer: Observer, prepare: Optional[Callable] = None) -> Callable:
    """``loss(params, batch) -> (loss, per-trial total RMSE (B,) deg)``: the group-weighted mean of the per-trial
    total RMSE (deg) over the scored samples. Each step is ``jax.checkpoint``-ed, so the reverse pass stores only
    the filter state per step (memory O(B T x state size)) and recomputes the step; ``prepare(params, dt)``
    (optional) maps the params to what ``step`` takes, once per trial, outside the scan."""

    def trial_rmse(p, gyr, acc, mag, q_true, use, dt):
        dtype = gyr.dtype
        first = ImuSample(jnp.zeros((), dtype), gyr[0], acc[0], mag[0])
        s0 = observer.init(p, first)
        s0 = jax.tree_util.tree_map(lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, s0)
        ps = prepare(p, dt) if prepare is not None else p

        @jax.checkpoint
        def body(carry, x):
            st, sse = carry
            g, a, m, qt, u = x
            st, out = observer.step(ps, st, ImuSample(st.t, g, a, m), dt)
            e2 = _err2_total(out.q, qt)
            return (st, sse + jnp.where(u, e2, 0.0)), None

        (_, sse), _ = jax.lax.scan(body, (s0, jnp.zeros((), dtype)), (gyr, acc, mag, q_true, use))
        n = jnp.maximum(jnp.sum(use), 1).astype(dtype)
        return jnp.rad2deg(jnp.sqrt(jnp.maximum(sse / n, 1e-30)))

    def loss(p, batch: _Batch):
        rmse = jax.vmap(trial_rmse, in_axes=(None, 0, 0, 0, 0, 0, 0))(
            p, batch.gyr, batch.acc, batch.mag, batch.q_true, batch.use, batch.dt)
        return jnp.sum(batch.weight * rmse), rmse

    return loss


# ------------------------------------------------------------------------------------------------------------
# Tuning
# ------------------------------------------------------------------------------------------------------------
def broad_tune(data_dir, observer_name: str = "robust", trials=None, out_path="gains.json", steps: int = 150, *,
               lr: float = 0.05, tune: Optional[Sequence[str]] = None, init_gains=None, dtype: str = "float32", save_every: int = 5, verbose: bool = True, loaded=None) -> dict:
    """Learn an observer's gains on BROAD trials by gradient descent through the whole filter run.

    Loss: mean over the training trials of the total RMSE (deg, BROAD metric: movement samples, NaN truth
    skipped), the undisturbed and disturbed groups weighted equally when both are present. Optimiser: optax
    Adam (learning rate ``lr`` on log-gains, cosine decay to lr / 10, gradient clipping at global norm 1).
    The tuned gains are positive and learnt as log(gain), clipped to the spec's bounds.

    Args:
        data_dir: BROAD folder.
        observer_name: see :func:`observer_names`.
        trials: training trials (:func:`resolve_trials`; default all).
        out_path: gains file, rewritten atomically every ``save_every`` steps with the best gains so far (by
            training loss) and at the end; readable by :func:`broad_eval` (``gains_path``) at any time.
        steps: optimiser steps (each: one forward and backward pass over all training trials).
        tune: gains to learn (default: the spec's ``tunable``); the others stay fixed.
        init_gains: starting gains: a dict or a gains-file path (default: the spec's ``start`` gains - for
            "robust" its untuned defaults - else its defaults).
        dtype: arithmetic of the filter during tuning ("float32" default: faster; evaluate in float64).
    Returns {"gains", "best_loss_deg", "history", "train_trials", "out_path", "wall_s"}.
    """
    import optax

    spec = get_spec(observer_name)
    gains0 = dict(spec.start if spec.start is not None else spec.defaults)
    if isinstance(init_gains, (str, Path)):
        obs_name, g, _ = load_gains(init_gains)
        if obs_name != spec.name:
            raise ValueError(f"{init_gains} holds gains of {obs_name!r}, not {spec.name!r}")
        gains0.update(g)
    elif init_gains:
        gains0.update({k: float(v) for k, v in init_gains.items()})
    tune = tuple(tune) if tune is not None else spec.tunable
    bad = [k for k in tune if k not in spec.defaults]
    if bad:
        raise ValueError(f"cannot tune {bad}: not gains of {spec.name!r}")
    names = resolve_trials(data_dir, trials)
    info = broad.load_trial_info(data_dir)
    trs = [loaded[n] if loaded and n in loaded else broad.load_trial(Path(data_dir) / f"{n}.hdf5") for n in names]
    jdt = jnp.dtype(dtype)
    batch, names = _make_batch(trs, jdt, info)
    loss_fn = make_loss(spec.observer, spec.prepare)
    fixed = {k: jnp.asarray(v, jdt) for k, v in gains0.items() if k not in tune}
    lo = jnp.asarray([math.log(spec.bounds.get(k, (1e-12, 1e12))[0]) for k in tune], jdt)
    hi = jnp.asarray([math.log(spec.bounds.get(k, (1e-12, 1e12))[1]) for k in tune], jdt)

    def to_gains(theta):
        g = dict(fixed)
        for i, k in enumerate(tune):
            g[k] = jnp.exp(theta[i])
        return g

    def objective(theta, batch):
        return loss_fn(spec.build(to_gains(theta)), batch)

    sched = optax.cosine_decay_schedule(lr, max(int(steps), 1), alpha=0.1)
    opt = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(sched))
    theta = jnp.clip(jnp.asarray([math.log(gains0[k]) for k in tune], jdt), lo, hi)
    opt_state = opt.init(theta)

    @jax.jit
    def update(theta, opt_state, batch):
        (loss, rmse), grad = jax.value_and_grad(objective, has_aux=True)(theta, batch)
        grad = jnp.where(jnp.isfinite(grad), grad, 0.0)
        upd, opt_state = opt.update(grad, opt_state, theta)
        theta_new = jnp.clip(optax.apply_updates(theta, upd), lo, hi)
        return theta_new, opt_state, loss, rmse, grad

    def gains_dict(theta):
        g = {k: float(v) for k, v in gains0.items()}
        g.update({k: float(math.exp(float(theta[i]))) for i, k in enumerate(tune)})
        return g

    history: List[dict] = []
    best = (math.inf, theta, None)
    t0 = time.perf_counter()
    meta = {"train_trials": names, "tuned": list(tune), "dtype": dtype, "lr": lr, "steps": int(steps),
            "loss": "group-weighted mean per-trial total RMSE (deg), BROAD metric",
            "data": broad.ATTRIBUTION}

    def save(final: bool):
        save_gains(out_path, spec.name, gains_dict(best[1]), **meta, best_loss_deg=float(best[0]),
                   best_train_rmse_deg=dict(zip(names, [float(x) for x in best[2]])) if best[2] is not None else None,
                   steps_done=len(history), finished=final, history=history,
                   created_utc=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))

    for it in range(int(steps)):
        theta_new, opt_state, loss, rmse, grad = update(theta, opt_state, batch)
        loss_f = float(loss)
        if not math.isfinite(loss_f):
            raise FloatingPointError(f"loss is {loss_f} at step {it}")
        if loss_f < best[0]:
            best = (loss_f, theta, np.asarray(rmse))
        history.append({"step": it, "loss_deg": loss_f, "wall_s": round(time.perf_counter() - t0, 2)})
        if verbose:
            print(f"step {it:4d}  loss {loss_f:.4f} deg  |grad| {float(jnp.linalg.norm(grad)):.3g}  "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
        theta = theta_new
        if out_path is not None and (it + 1) % save_every == 0:
            save(False)
    # the last update was not evaluated: evaluate it once
    loss_last, rmse_last = jax.jit(objective)(theta, batch)
    if float(loss_last) < best[0]:
        best = (float(loss_last), theta, np.asarray(rmse_last))
    history.append({"step": int(steps), "loss_deg": float(loss_last), "wall_s": round(time.perf_counter() - t0, 2)})
    if out_path is not None:
        save(True)
    result = {"gains": gains_dict(best[1]), "best_loss_deg": best[0], "history": history, "train_trials": names,
              "out_path": str(out_path) if out_path is not None else None, "wall_s": time.perf_counter() - t0}
    if verbose:
        print(f"best training loss {best[0]:.4f} deg; gains -> {out_path}")
        for k in tune:
            print(f"  {k:16s} {result['gains'][k]:.6g}")
    return result


def broad_crossval(data_dir, observer_name: str = "robust", out_dir=".", steps: int = 150, *,
                   prefix: Optional[str] = None, json_path=None, verbose: bool = True, tune_kwargs=None,
                   eval_dtype: str = "float64") -> dict:
    """2-fold cross-validation stratified by group: tune on fold k (``<prefix>_fold<k>.json`` in ``out_dir``),
    evaluate on the other fold; every trial gets one out-of-fold number. Returns {"folds", "trials" (out of
    fold), "groups"} and prints the table (and writes ``json_path`` if given)."""
    names = resolve_trials(data_dir, None)
    info = broad.load_trial_info(data_dir)
    folds = stratified_folds(names, info)
    prefix = prefix or f"{observer_name}_broad"
    loaded = {n: broad.load_trial(Path(data_dir) / f"{n}.hdf5") for n in names}
    oof: Dict[str, dict] = {}
    fold_info = []
    for k, train in enumerate(folds, start=1):
        test = [n for n in names if n not in train]
        path = Path(out_dir) / f"{prefix}_fold{k}.json"
        broad_tune(data_dir, observer_name, train, path, steps, verbose=verbose, loaded=loaded, **(tune_kwargs or {}))
        ev = broad_eval(data_dir, observer_name, gains_path=path, trials=test, verbose=verbose, loaded=loaded,
                        dtype=eval_dtype)
        for n in test:
            oof[n] = {**ev["trials"][n], "gains": path.name}
        fold_info.append({"fold": k, "train": train, "test": test, "gains": str(path)})
    oof = {n: oof[n] for n in names}
    groups = _summaries(oof, info)
    out = {"observer": observer_name, "folds": fold_info, "trials": oof, "groups": groups, "anchors": ANCHORS}
    if verbose:
        _print_table(f"BROAD out-of-fold (2-fold CV stratified by group), observer {observer_name}", oof, groups, info)
    if json_path is not None:
        _atomic_write_json(json_path, out)
    return out
