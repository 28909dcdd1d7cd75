"""BROAD: real IMU recordings with optical ground truth, and the benchmark's error metric.

Data: D. Laidig, M. Caruso, A. Cereatti, T. Seel, "BROAD - A Benchmark for Robust Inertial Orientation
Estimation", Data 6(7), 2021, https://doi.org/10.3390/data6070072 (public repository dlaidig/broad),
licensed CC BY 4.0: keep this attribution wherever the data or derived excerpts are used or shipped.

Each trial file (HDF5) holds ``imu_gyr`` (rad/s), ``imu_acc`` (m/s^2), ``imu_mag`` (uT), all (N, 3) in the
sensor frame, ``opt_quat`` (N, 4): the optical ground truth as a sensor-to-ENU unit quaternion (w, x, y, z),
NaN where the markers were lost, ``movement`` (N,) bool: the samples that are scored, and the attribute
``sampling_rate`` (Hz). The optical truth is already expressed in the IMU's own ENU frame (y = horizontal
direction of the local magnetic field), so estimates are compared with no offset fitted.

Conventions: quaternions Hamilton, scalar first (w, x, y, z); q maps sensor coordinates to ENU; angles in the
returned metrics are in degrees (``_deg``), everything else SI.

Sample alignment: BROAD's filters update with sample k and report the estimate *after* processing sample k,
which is compared with ``opt_quat[k]``; the filter is started (``setState``) from sample 0 and then sample 0 is
processed too. In jaxatt's step convention (advance from ``sample.t`` to ``sample.t + dt`` with ``sample``)
that estimate carries the label t_k + dt; :func:`run_on_trial` follows BROAD and pairs it with sample k.

Reproducing BROAD's published Mahony numbers (``published/results_mahony_average_rmse.json``, computed by the
dataset authors with S. Madgwick's C implementation in float32, compiled without FMA): :mod:`jaxatt.observers.mahony`
performs the same float32 operations in the same order, and :func:`run_on_trial` / :func:`run_on_padded` start
it from a float64 start quaternion as their ``setState`` does and rotate the float32 output into ENU in float64.
With ``dtype="float32"`` and the process started with ``XLA_FLAGS=--xla_cpu_max_isa=SSE4_2`` (x86 CPUs; without it
XLA contracts a*b + c into fused multiply-adds and rewrites 1/sqrt(x) as rsqrt(x), which round differently) the
per-trial RMSEs agree with the published ones to ~1e-14 deg. The float64 filter (the default) is the exact
algorithm; it differs from the float32 reference by its rounding: up to ~6e-4 deg in the RMSEs (about 1e-3 deg in
the orientation), far below the errors themselves (2-41 deg). The group averages in that file are over all 39
trials of the full dataset and cannot be recomputed from a subset.

h5py is needed only to read the files: ``pip install "jaxatt[data]"``.
"""
from __future__ import annotations

import functools
import json
import re
from pathlib import Path
from typing import Dict, Iterable, List, NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..observers.base import ImuSample, Observer

__all__ = ["Trial", "PaddedTrials", "load_trial", "list_trials", "load_trials", "load_trial_info", "trial_groups",
           "group_trials", "error_angles", "broad_errors", "error_angles_jax", "broad_errors_jax", "pad_trials",
           "run_on_trial", "run_on_padded", "batch_errors_jax", "evaluate", "ATTRIBUTION", "METRICS"]

ATTRIBUTION = ("BROAD dataset: D. Laidig, M. Caruso, A. Cereatti, T. Seel, 'BROAD - A Benchmark for Robust "
               "Inertial Orientation Estimation', Data 6(7), 2021, doi:10.3390/data6070072, CC BY 4.0.")

#: Names of the three BROAD metrics (RMSE in degrees over the movement samples).
METRICS = ("total_rmse_deg", "heading_rmse_deg", "inclination_rmse_deg")


class Trial(NamedTuple):
    """One BROAD trial, as numpy arrays.

    Fields:
        name: trial name (file stem), e.g. "01_undisturbed_slow_rotation_A".
        samples: ImuSample with t (N,) s (k / rate_hz), gyr (N, 3) rad/s, acc (N, 3) m/s^2, mag (N, 3) uT, all in
            the sensor frame.
        quat_true: (N, 4) ground truth, sensor-to-ENU quaternion (w, x, y, z), NaN where missing.
        movement: (N,) bool, the samples that are scored.
        rate_hz: sampling rate (Hz).
    """

    name: str
    samples: ImuSample
    quat_true: np.ndarray
    movement: np.ndarray
    rate_hz: float


class PaddedTrials(NamedTuple):
    """Trials of different lengths stacked for ``vmap``: padded with the last sample repeated (never NaN).

    Fields:
        samples: ImuSample of (B, T) / (B, T, 3) arrays.
        mask: (B, T) bool, True on real samples, False on padding.
        quat_true: (B, T, 4) ground truth (sensor-to-ENU, NaN where the optical system lost the markers, as in
            the files; the padding repeats the last row).
        movement: (B, T) bool, BROAD's movement flag, False on padding.
        lengths: (B,) int, number of real samples.
        names: tuple of B trial names.
        rate_hz: (B,) sampling rates (Hz).
    """

    samples: ImuSample
    mask: np.ndarray
    quat_true: np.ndarray
    movement: np.ndarray
    lengths: np.ndarray
    names: tuple
    rate_hz: np.ndarray


# ------------------------------------------------------------------------------------------------------------
# Loading
# ------------------------------------------------------------------------------------------------------------
def _h5py():
    try:
        import h5py
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError('reading BROAD trials needs h5py: pip install "jaxatt[data]"') from e
    return h5py


def load_trial(path) -> Trial:
    """Load one BROAD HDF5 trial file (see :class:`Trial` for units and frames)."""
    path = Path(path)
    h5py = _h5py()
    with h5py.File(path, "r") as f:
        rate = float(np.asarray(f.attrs["sampling_rate"]).reshape(()))
        gyr = np.asarray(f["imu_gyr"][()], dtype=np.float64)
        acc = np.asarray(f["imu_acc"][()], dtype=np.float64)
        mag = np.asarray(f["imu_mag"][()], dtype=np.float64)
        quat = np.asarray(f["opt_quat"][()], dtype=np.float64)
        movement = np.asarray(f["movement"][()]).reshape(-1).astype(bool)
    n = gyr.shape[0]
    for k, v in (("imu_acc", acc), ("imu_mag", mag)):
        if v.shape != (n, 3):
            raise ValueError(f"{path.name}: {k} has shape {v.shape}, expected ({n}, 3)")
    if quat.shape != (n, 4) or movement.shape != (n,):
        raise ValueError(f"{path.name}: opt_quat {quat.shape} / movement {movement.shape} do not match N = {n}")
    t = np.arange(n, dtype=np.float64) / rate
    return Trial(path.stem, ImuSample(t, gyr, acc, mag), quat, movement, rate)


def list_trials(data_dir) -> List[str]:
    """Names of the trial files (``*.hdf5``) in ``data_dir``, sorted."""
    return sorted(p.stem for p in Path(data_dir).glob("*.hdf5"))


def load_trials(data_dir, names: Optional[Iterable[str]] = None) -> List[Trial]:
    """Load the named trials (default: every trial file in ``data_dir``), in the given / sorted order."""
    names = list_trials(data_dir) if names is None else list(names)
    missing = [n for n in names if not (Path(data_dir) / f"{n}.hdf5").exists()]
    if missing:
        raise FileNotFoundError(f"trial files not found in {data_dir}: {missing}")
    return [load_trial(Path(data_dir) / f"{n}.hdf5") for n in names]


def load_trial_info(data_dir) -> Optional[dict]:
    """The content of ``trials.json`` (groups and trials, as in dlaidig/broad) or None if absent."""
    p = Path(data_dir) / "trials.json"
    if not p.exists():
        return None
    with open(p) as f:
        return json.load(f)


def trial_groups(name: str, info: Optional[dict] = None) -> List[str]:
    """Groups a trial belongs to: from ``info`` (trials.json) when it lists the trial, otherwise from the trial
    number: 1-23 -> ["all_trials", "undisturbed"], 24-39 -> ["all_trials", "disturbed"]."""
    if info is not None and name in info.get("trials", {}):
        return list(info["trials"][name]["groups"])
    m = re.match(r"(\d+)", name)
    if not m:
        raise ValueError(f"cannot tell the group of trial {name!r} (no leading trial number)")
    num = int(m.group(1))
    if 1 <= num <= 23:
        return ["all_trials", "undisturbed"]
    if 24 <= num <= 39:
        return ["all_trials", "disturbed"]
    raise ValueError(f"trial number {num} of {name!r} is outside BROAD's 1-39")


def group_trials(names: Sequence[str], group: str, info: Optional[dict] = None) -> List[str]:
    """The trials among ``names`` that belong to ``group`` (see :func:`trial_groups`)."""
    return [n for n in names if group in trial_groups(n, info)]


# ------------------------------------------------------------------------------------------------------------
# The BROAD metric
# ------------------------------------------------------------------------------------------------------------
def _quatmult_np(a, b):
    """Hamilton product, component formulas as in BROAD's broad_utils.quatmult."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), float)
    out[..., 0] = a[..., 0] * b[..., 0] - a[..., 1] * b[..., 1] - a[..., 2] * b[..., 2] - a[..., 3] * b[..., 3]
    out[..., 1] = a[..., 0] * b[..., 1] + a[..., 1] * b[..., 0] + a[..., 2] * b[..., 3] - a[..., 3] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 2] - a[..., 1] * b[..., 3] + a[..., 2] * b[..., 0] + a[..., 3] * b[..., 1]
    out[..., 3] = a[..., 0] * b[..., 3] + a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1] + a[..., 3] * b[..., 0]
    return out


def error_angles(quat_est, quat_true):
    """Per-sample BROAD errors (rad): (total, heading, inclination), each (N,); NaN where quat_true is NaN.

    q_err = q_est (x) conj(q_true) (both normalised, result normalised): the error expressed in the ENU frame.
    total = 2 arccos(|w|); heading = 2 arctan(|z / w|) (the angle of the rotation about ENU z in the
    swing-twist decomposition q_err = q_z(heading) (x) q_h, q_h about a horizontal axis); inclination =
    2 arccos(sqrt(w^2 + z^2)) (the angle of q_h). These are the formulas of BROAD's broad_utils.py
    (calculateTotalError / calculateHeadingError / calculateInclinationError), evaluated in float64.
    """
    qe = np.asarray(quat_est, np.float64)
    qt = np.asarray(quat_true, np.float64)
    qe = qe / np.linalg.norm(qe, axis=-1, keepdims=True)
    qt = qt / np.linalg.norm(qt, axis=-1, keepdims=True)
    conj = qt * np.array([1.0, -1.0, -1.0, -1.0])
    d = _quatmult_np(qe, conj)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        total = 2 * np.arccos(np.clip(np.abs(d[..., 0]), 0, 1))
        heading = 2 * np.arctan(np.abs(d[..., 3] / d[..., 0]))
        incl = 2 * np.arccos(np.clip(np.sqrt(d[..., 0] ** 2 + d[..., 3] ** 2), 0, 1))
    return total, heading, incl


def broad_errors(quat_est, quat_true, movement) -> Dict[str, float]:
    """BROAD's metric (float64 numpy): RMSE (deg) of the total, heading and inclination errors over the
    ``movement`` samples, ignoring samples whose ground truth is NaN; no offset is fitted.

    Args:
        quat_est: (N, 4) estimated sensor-to-ENU quaternions (w, x, y, z).
        quat_true: (N, 4) ground truth (BROAD's ``opt_quat``), NaN where missing.
        movement: (N,) bool.

    Returns dict(total_rmse_deg, heading_rmse_deg, inclination_rmse_deg): for each error e_k (rad, see
    :func:`error_angles`), rad2deg(sqrt(nanmean(e_k^2 over k in movement))) - the same numbers as BROAD's
    ``calculateRMSE``.
    """
    movement = np.asarray(movement).astype(bool)
    total, heading, incl = error_angles(quat_est, quat_true)
    rmse = lambda e: float(np.rad2deg(np.sqrt(np.nanmean(e[movement] ** 2))))  # noqa: E731
    return dict(total_rmse_deg=rmse(total), heading_rmse_deg=rmse(heading), inclination_rmse_deg=rmse(incl))


def _safe_sqrt(x):
    ok = x > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def error_angles_jax(quat_est, quat_true):
    """Differentiable per-sample BROAD errors (rad), (total, heading, inclination), shape (...).

    Same quantities as :func:`error_angles` written with atan2 (accurate at 0 and gradient-safe):
    total = 2 atan2(|v|, |w|), heading = 2 atan2(|z|, |w|), inclination = 2 atan2(sqrt(x^2 + y^2),
    sqrt(w^2 + z^2)) of q_err = q_est (x) conj(q_true) (inputs normalised). NaN in ``quat_true`` propagates;
    :func:`broad_errors_jax` masks it out safely.
    """
    qe = quat_est / _safe_sqrt(jnp.sum(quat_est * quat_est, -1, keepdims=True))
    qt = quat_true / _safe_sqrt(jnp.sum(quat_true * quat_true, -1, keepdims=True))
    w, x, y, z = [c[..., 0] for c in jnp.split(_qmul_conj(qe, qt), 4, axis=-1)]
    aw, az = jnp.abs(w), jnp.abs(z)
    total = 2 * jnp.arctan2(_safe_sqrt(x * x + y * y + z * z), aw)
    heading = 2 * jnp.arctan2(az, aw)
    incl = 2 * jnp.arctan2(_safe_sqrt(x * x + y * y), _safe_sqrt(w * w + z * z))
    return total, heading, incl


def _qmul_conj(a, b):
    """a (x) conj(b)."""
    from ..so3 import quat_conjugate, quat_multiply

    return quat_multiply(a, quat_conjugate(b))


def broad_errors_jax(quat_est, quat_true, movement, mask=None) -> Dict[str, jax.Array]:
    """Differentiable BROAD metric (jit / vmap / grad): RMSE (deg) over ``movement`` (& ``mask``) samples whose
    ground truth is finite. Shapes (..., N, 4), (..., N, 4), (..., N); reduces the last sample axis.

    Agrees with :func:`broad_errors` to rounding (atan2 forms instead of arccos/arctan; see
    :func:`error_angles_jax`). NaN rows of ``quat_true`` are replaced before any arithmetic (double-where), so
    gradients stay finite.
    """
    movement = jnp.asarray(movement, bool)
    if mask is not None:
        movement = movement & jnp.asarray(mask, bool)
    finite = jnp.all(jnp.isfinite(quat_true), axis=-1)
    use = movement & finite
    qt = jnp.where(finite[..., None], quat_true, jnp.array([1.0, 0.0, 0.0, 0.0], quat_est.dtype))
    qe = jnp.where(use[..., None], quat_est, qt)  # unused samples: zero error, no NaN reaches the gradient
    errs = error_angles_jax(qe, qt)
    n = jnp.maximum(jnp.sum(use, axis=-1), 1).astype(quat_est.dtype)
    out = {}
    for name, e in zip(METRICS, errs):
        ms = jnp.sum(jnp.where(use, e * e, 0.0), axis=-1) / n
        out[name] = jnp.rad2deg(_safe_sqrt(ms))
    return out


# ------------------------------------------------------------------------------------------------------------
# Batching and running observers
# ------------------------------------------------------------------------------------------------------------
def pad_trials(trials: Sequence[Trial]) -> PaddedTrials:
    """Stack trials of different lengths into (B, T_max, ...) arrays for ``vmap``.

    Padding repeats each trial's last sample (finite data, so no NaN enters a scan or a gradient); ``mask`` is
    False there and ``movement`` is False there. Time continues at the trial's rate on the padding.
    """
    if not trials:
        raise ValueError("no trials to pad")
    lengths = np.array([len(tr.samples.t) for tr in trials], int)
    tmax = int(lengths.max())

    def pad(a, n):
        a = np.asarray(a)
        if n == tmax:
            return a
        reps = np.repeat(a[-1:], tmax - n, axis=0)
        return np.concatenate([a, reps], axis=0)

    ts, gyr, acc, mag, qt, mov, mask = [], [], [], [], [], [], []
    for tr, n in zip(trials, lengths):
        ts.append(np.arange(tmax, dtype=np.float64) / tr.rate_hz)
        gyr.append(pad(tr.samples.gyr, n))
        acc.append(pad(tr.samples.acc, n))
        mag.append(pad(tr.samples.mag, n))
        qt.append(pad(tr.quat_true, n))
        mov.append(np.concatenate([tr.movement, np.zeros(tmax - n, bool)]))
        mask.append(np.arange(tmax) < n)
    samples = ImuSample(np.stack(ts), np.stack(gyr), np.stack(acc), np.stack(mag))
    return PaddedTrials(samples, np.stack(mask), np.stack(qt), np.stack(mov), lengths,
                        tuple(tr.name for tr in trials), np.array([tr.rate_hz for tr in trials], float))


def _scan_trial(observer: Observer, pick, params, first, params_run, samples: ImuSample, dt):
    """init from sample 0, then step through every sample k = 0..N-1; returns stacked outputs, output k being
    the estimate after processing sample k (BROAD's alignment).

    ``init`` runs on ``params`` / ``first`` (the highest precision at hand) and its state is cast to the dtype of
    ``samples``: BROAD computes its start quaternion in float64 and hands it to the float32 filter (setState).
    ``pick(out)`` selects what is stacked (None: the whole Out).
    """
    state = observer.init(params, first)
    dtype = samples.gyr.dtype
    state = jax.tree_util.tree_map(
        lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, state)

    def body(st, u):
        st, out = observer.step(params_run, st, u, dt)
        return st, (out if pick is None else pick(out))

    _, outs = jax.lax.scan(body, state, samples)
    return outs


def _pick_quat(out):
    """Only the quaternions: the ENU one and, where the observer has one, its own-frame one (q_nwu)."""
    return {"q": out.q, "q_nwu": getattr(out, "q_nwu", None)}


def _to_enu_quat(outs):
    """Sensor-to-ENU quaternions of the outputs in float64. Observers that keep their own earth frame (Mahony:
    ``q_nwu``) are converted here in float64, as BROAD's example code does with its float32 filter output."""
    def get(k):
        return outs.get(k) if isinstance(outs, dict) else getattr(outs, k, None)

    q_nwu = get("q_nwu")
    if q_nwu is not None:
        from ..observers.mahony import Q_ENU_FROM_NWU

        q = np.asarray(q_nwu, np.float64)
        return _quatmult_np(np.asarray(Q_ENU_FROM_NWU)[None], q)
    return np.asarray(get("q"), np.float64)


def _cast_float(tree, dtype):
    return jax.tree_util.tree_map(
        lambda a: jnp.asarray(a, dtype) if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating) else jnp.asarray(a),
        tree)


@functools.lru_cache(maxsize=32)
def _runner(observer: Observer, batched: bool, full: bool):
    fn = functools.partial(_scan_trial, observer, None if full else _pick_quat)
    if batched:
        fn = jax.vmap(fn, in_axes=(None, 0, None, 0, 0))
    return jax.jit(fn)


def _run(observer, params, samples: ImuSample, rate_hz, dtype, batched, full=False):
    hi = jnp.result_type(float)  # float64 when x64 is enabled
    first = jax.tree_util.tree_map(lambda a: np.asarray(a)[:, 0] if batched else np.asarray(a)[0], samples)
    run = _runner(observer, batched, full)
    return run(_cast_float(params, hi), _cast_float(first, hi), _cast_float(params, dtype), _cast_float(samples, dtype),
               _dt(rate_hz, dtype))


def _dt(rate_hz, dtype):
    """Step dt = 1 / rate computed in ``dtype`` (as the C filters do: 1.0f / sampleFreq in float32)."""
    one = np.asarray(1.0, dtype)
    return one / np.asarray(rate_hz, dtype)


def run_on_trial(observer: Observer, params, trial: Trial, *, dtype=None, outputs: bool = False):
    """Run ``observer`` over one trial with BROAD's alignment; returns quat_est (N, 4) float64, sensor-to-ENU.

    ``init(params, sample_0)`` starts the filter, then ``step`` processes samples 0 .. N-1 with dt = 1/rate;
    quat_est[k] is the estimate after processing sample k (jaxatt label t_k + dt), which BROAD compares with
    ``opt_quat[k]``. ``dtype`` (default: jax's default float) is the arithmetic of the run (float32 emulates
    BROAD's C filters; float64 is the exact filter). With ``outputs=True`` returns (quat_est, stacked Out).
    """
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.result_type(float)
    outs = _run(observer, params, trial.samples, trial.rate_hz, dtype, batched=False, full=outputs)
    q = _to_enu_quat(outs)
    return (q, outs) if outputs else q


def run_on_padded(observer: Observer, params, padded: PaddedTrials, *, dtype=None):
    """Run ``observer`` over a batch of padded trials (vmap, one jit); returns quat_est (B, T_max, 4) float64
    (sensor-to-ENU), same alignment as :func:`run_on_trial`; rows past each trial's length are padding."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.result_type(float)
    outs = _run(observer, params, padded.samples, padded.rate_hz, dtype, batched=True)
    return _to_enu_quat(outs)


def batch_errors_jax(observer: Observer, params, padded: PaddedTrials, dtype=None) -> Dict[str, jax.Array]:
    """Differentiable BROAD metric of ``observer`` on every padded trial: {metric: (B,) RMSE deg}.

    Pure JAX in ``params`` (wrap it in ``jax.jit`` / ``jax.grad`` for gain learning); the padded data are
    constants. Same alignment as :func:`run_on_trial`; uses ``Out.q`` (sensor-to-ENU) and
    :func:`broad_errors_jax` with the padding masked out. Init runs in ``dtype`` here (no float64 start).
    """
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.result_type(float)
    samples = _cast_float(padded.samples, dtype)
    dts = jnp.asarray(_dt(padded.rate_hz, dtype))
    qt = jnp.asarray(padded.quat_true, dtype)
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(a).astype(dtype), params)

    def one(s, q_true, movement, mask, dt):
        first = jax.tree_util.tree_map(lambda a: a[0], s)
        outs = _scan_trial(observer, lambda o: o.q, params, first, params, s, dt)
        return broad_errors_jax(outs, q_true, movement, mask)

    return jax.vmap(one)(samples, qt, jnp.asarray(padded.movement), jnp.asarray(padded.mask), dts)


def evaluate(observer: Observer, params, trials: Sequence[Trial], *, dtype=None) -> Dict[str, Dict[str, float]]:
    """BROAD metric of ``observer`` on each trial: {trial name: {metric: RMSE deg}} (one vmapped run)."""
    padded = pad_trials(trials)
    q = run_on_padded(observer, params, padded, dtype=dtype)
    res = {}
    for i, tr in enumerate(trials):
        n = padded.lengths[i]
        res[tr.name] = broad_errors(q[i, :n], tr.quat_true, tr.movement)
    return res
