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

Sample alignment (jaxatt's, :mod:`jaxatt.engine`): estimate 0 is the observer's start from sample 0 and, with the
"next" hold, estimate k is the update with sample k; it is scored against ``opt_quat[k]``. BROAD's example code
also starts (``setState``) from sample 0 but then processes sample 0 a second time; that moves the RMSEs by at
most ~1e-4 deg.

Reproducing BROAD's published Mahony numbers (``published/results_mahony_average_rmse.json``, computed by the
dataset authors with S. Madgwick's C implementation in float32, compiled without FMA): :mod:`jaxatt.observers.mahony`
(``make_observer("broad")``) performs the same float32 operations in the same order; replaying BROAD's protocol
(start from sample 0 computed in float64, sample 0 processed twice, the float32 NWU output rotated into ENU in
float64; ``tests/test_broad.py``) with ``XLA_FLAGS=--xla_cpu_max_isa=SSE4_2`` (x86 CPUs; without it XLA contracts
a*b + c into fused multiply-adds and rewrites 1/sqrt(x) as rsqrt(x), which round differently) gives the published
per-trial RMSEs to ~1e-14 deg. The float64 filter differs from the float32 reference by its rounding: up to ~6e-4
deg. The group averages in that file are over all 39 trials of the full dataset and cannot be recomputed from a
subset.

h5py is needed only to read the files: ``pip install "jaxatt[data]"``.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Dict, Iterable, List, NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .. import engine
from ..types import ImuSample, Observer
from .logs import check_timestamps, non_unit_row

__all__ = [
    "Trial",
    "PaddedTrials",
    "check_trials",
    "load",
    "load_trial",
    "list_trials",
    "load_trials",
    "load_trial_info",
    "trial_groups",
    "group_trials",
    "group_of",
    "resolve_trials",
    "stratified_folds",
    "error_angles",
    "metric_fn",
    "metric_batch",
    "broad_errors",
    "scored_samples",
    "error_angles_jax",
    "broad_errors_jax",
    "pad_trials",
    "batch_item",
    "score",
    "METRIC_REDUCER",
    "ATTRIBUTION",
    "METRICS",
    "GROUPS",
    "ANCHORS",
]

ATTRIBUTION = (
    "BROAD dataset: D. Laidig, M. Caruso, A. Cereatti, T. Seel, 'BROAD - A Benchmark for Robust "
    "Inertial Orientation Estimation', Data 6(7), 2021, doi:10.3390/data6070072, CC BY 4.0."
)

#: Names of the three BROAD metrics (RMSE in degrees over the movement samples).
METRICS = ("total_rmse_deg", "heading_rmse_deg", "inclination_rmse_deg")
#: The two groups of BROAD trials: 1-23 undisturbed, 24-39 disturbed (tapping, vibration, magnets).
GROUPS = ("undisturbed", "disturbed")

#: Mean total RMSE (deg, BROAD metric) of other libraries on the 20 shared trials (benchmarks/broad.py
#: re-measures them).
ANCHORS = {
    "VQF online 9D": {"undisturbed": 1.90, "disturbed": 3.49},
    "VQF offline 9D": {"undisturbed": 1.95, "disturbed": 2.28},
    "ahrs Madgwick beta=0.12": {"undisturbed": 3.87, "disturbed": 7.14},
    "ahrs Mahony (BROAD best)": {"undisturbed": 7.22, "disturbed": 11.40},
    "imufusion defaults": {"undisturbed": 8.14, "disturbed": 20.45},
}


class Trial(NamedTuple):
    """One BROAD trial, as numpy arrays.

    Fields:
        name: trial name (file stem), e.g. "01_undisturbed_slow_rotation_A".
        samples: ImuSample with t (N,) s (k / rate_hz), gyr (N, 3) rad/s, acc (N, 3) m/s^2, mag (N, 3) uT, all in
            the sensor frame.
        quat_true: (N, 4) ground truth, sensor-to-ENU quaternion (w, x, y, z), NaN where missing.
        movement: (N,) bool, the samples that are scored.
        rate_hz: sampling rate (Hz).
        group: "undisturbed" or "disturbed" (:data:`GROUPS`; from trials.json when present, else the number).
    """

    name: str
    samples: ImuSample
    quat_true: np.ndarray
    movement: np.ndarray
    rate_hz: float
    group: str = ""


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
        dt: None when every trial is sampled uniformly at its rate (steps within 0.1 % of 1 / rate: each is scanned
            with the constant step 1 / rate, as BROAD's filters do), else (B, T) the step of each sample in s,
            dt[:, k] = t_k - t_{k-1} from the trials' own timestamps (dt[:, 0] unused; 1 / rate on the padding).
    """

    samples: ImuSample
    mask: np.ndarray
    quat_true: np.ndarray
    movement: np.ndarray
    lengths: np.ndarray
    names: tuple
    rate_hz: np.ndarray
    dt: Optional[np.ndarray] = None


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
    if path.suffix.lower() in (".csv", ".npz"):
        raise ValueError(
            f"{path.name}: a CSV / NPZ log, not a BROAD .hdf5 trial: read it with jaxatt.data.logs.load_trial"
        )
    h5py = _h5py()
    if not path.is_file():
        raise FileNotFoundError(f"BROAD trial file not found: {path}")
    try:
        with h5py.File(path, "r") as f:
            missing = [k for k in ("imu_gyr", "imu_acc", "imu_mag", "opt_quat", "movement") if k not in f]
            if missing or "sampling_rate" not in f.attrs:
                raise ValueError(f"{path.name}: not a BROAD trial (missing {missing or ['sampling_rate attribute']})")
            rate_attr = np.asarray(f.attrs["sampling_rate"])
            if rate_attr.size != 1 or rate_attr.dtype == bool:
                raise ValueError(f"{path.name}: the sampling_rate attribute must be one number, got {rate_attr!r}")
            try:
                rate = float(rate_attr.reshape(()))
            except (TypeError, ValueError):
                raise ValueError(f"{path.name}: sampling_rate must be a number of Hz, got {rate_attr!r}") from None
            raw = {k: np.asarray(f[k][()]) for k in ("imu_gyr", "imu_acc", "imu_mag", "opt_quat")}
            for k, v in raw.items():
                if not (np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer)):
                    raise ValueError(f"{path.name}: {k} must hold real numbers, got dtype {v.dtype}")
            gyr, acc, mag, quat = (raw[k].astype(np.float64) for k in ("imu_gyr", "imu_acc", "imu_mag", "opt_quat"))
            movement = np.asarray(f["movement"][()]).reshape(-1).astype(bool)
    except (OSError, TypeError, KeyError, AttributeError) as e:  # unreadable, or a group where a dataset belongs
        why = " ".join(str(e).split())
        raise ValueError(f"{path.name}: cannot read the HDF5 file as a BROAD trial ({why})") from None
    if gyr.ndim != 2 or gyr.shape[1:] != (3,):
        raise ValueError(f"{path.name}: imu_gyr has shape {gyr.shape}, expected (N, 3)")
    n = gyr.shape[0]
    if n < 2:
        raise ValueError(f"{path.name}: imu_gyr has {n} samples, a trial needs at least 2")
    for k, v in (("imu_acc", acc), ("imu_mag", mag)):
        if v.shape != (n, 3):
            raise ValueError(f"{path.name}: {k} has shape {v.shape}, expected ({n}, 3)")
    if quat.shape != (n, 4) or movement.shape != (n,):
        raise ValueError(f"{path.name}: opt_quat {quat.shape} / movement {movement.shape} do not match N = {n}")
    if not (np.isfinite(rate) and rate > 0):
        raise ValueError(f"{path.name}: sampling_rate must be a positive number of Hz, got {rate}")
    for k, v in (("imu_gyr", gyr), ("imu_acc", acc), ("imu_mag", mag), ("opt_quat", quat)):
        if np.isinf(v).any():
            raise ValueError(f"{path.name}: {k} contains +-inf (NaN marks a missing reading or truth)")
    t = np.arange(n, dtype=np.float64) / rate
    try:
        group = group_of(path.stem, load_trial_info(path.parent))
    except ValueError:
        group = ""
    # the checks every trial gets (unit truth, a bool movement of one row per sample), naming the file
    return check_trials([Trial(path.stem, ImuSample(t, gyr, acc, mag), quat, movement, rate, group)], path.name)[0]


def check_trials(trials, what: str = "trials", need_scored: bool = False) -> List[Trial]:
    """``trials`` as a list, or ValueError (one line naming the trial and field) unless each is a :class:`Trial`
    with a unique name, N >= 2 samples, gyr / acc / mag (N, 3) real without +-inf (gyr and acc with at least one
    finite reading; a trial without magnetometer readings is a 6D trial), quat_true (N, 4) unit
    quaternions (w, x, y, z) where finite, movement (N,) bool, ``samples.t`` (N,) finite and strictly increasing
    seconds, rate_hz a positive number agreeing with its median step (1 %). ``need_scored``: every trial has a
    scored sample (movement and finite truth), as a fit's loss needs (a trial with none would add a zero error)."""
    if isinstance(trials, Trial):
        raise ValueError(f"{what} must be a list of trials, got one Trial ({trials.name}): pass [trial]")
    trials = list(trials)
    if not trials:
        raise ValueError(f"{what} is empty (load them with jaxatt.data.broad.load)")
    if not all(isinstance(tr, Trial) for tr in trials):
        raise ValueError(f"{what} must be jaxatt.data.broad.Trial objects (jaxatt.data.broad.load)")
    names = [tr.name for tr in trials]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(
            f"{what}: trial names must be unique, {', '.join(map(repr, dup))} appears more than once (rename one: "
            "trial._replace(name=...), or jaxatt.data.logs.load_trial(..., name=...))"
        )
    for tr in trials:
        where = f"trial {tr.name}"
        if not isinstance(tr.group, str) or not tr.group.strip():
            try:  # BROAD's trials: the group from the trial number (a fit and the group means need it)
                group_of(tr.name)
            except ValueError as e:
                raise ValueError(
                    f"{where}: {e}: give its group, Trial(..., group='mine') or load_trial(..., group='mine')"
                ) from None
        s = tr.samples
        gyr = np.asarray(s.gyr)
        n = gyr.shape[0] if gyr.ndim == 2 else -1
        for field, v in (("gyr", s.gyr), ("acc", s.acc), ("mag", s.mag)):
            a = np.asarray(v) if v is not None else None
            if a is None or a.shape != (n, 3) or n < 2:
                got = "None" if a is None else str(a.shape)
                hint = (
                    " (a trial without a magnetometer has NaN rows: mag=np.full((N, 3), np.nan))"
                    if field == "mag" and a is None
                    else ""
                )
                raise ValueError(
                    f"{where}: samples.{field} must have shape (N, 3) with N >= 2 like gyr, got {got}{hint}"
                )
            if not np.issubdtype(a.dtype, np.floating) and not np.issubdtype(a.dtype, np.integer):
                raise ValueError(f"{where}: samples.{field} must be real numbers, got dtype {a.dtype}")
            if np.isinf(a).any():
                raise ValueError(f"{where}: samples.{field} contains +-inf (mark a missing reading with NaN)")
            if field != "mag" and not np.isfinite(a).any():
                raise ValueError(f"{where}: samples.{field} has no finite reading (every row NaN): nothing to filter")
        q = np.asarray(tr.quat_true)
        if q.shape != (n, 4) or not np.issubdtype(q.dtype, np.floating):
            raise ValueError(f"{where}: quat_true must be float (N, 4) = ({n}, 4), got {q.dtype}{list(q.shape)}")
        if np.isinf(q).any():
            raise ValueError(f"{where}: quat_true contains +-inf (use NaN where the truth is unknown)")
        bad = non_unit_row(q)
        if bad is not None:
            raise ValueError(
                f"{where}: quat_true[{bad[0]}] has norm {bad[1]:.6g}; the ground truth must be unit "
                "quaternions (w, x, y, z), NaN where missing"
            )
        m = np.asarray(tr.movement)
        if m.shape != (n,) or m.dtype != bool:
            raise ValueError(
                f"{where}: movement must be a bool array of shape ({n},), got {m.dtype}{list(m.shape)} "
                "(a 0 / 1 array: .astype(bool))"
            )
        try:
            if isinstance(tr.rate_hz, (str, bytes, bool, np.bool_)):  # float("100") works, and then arithmetic fails
                raise TypeError
            rate = float(tr.rate_hz)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: rate_hz must be a number of Hz, got {tr.rate_hz!r}") from None
        if not (np.isfinite(rate) and rate > 0):
            raise ValueError(f"{where}: rate_hz must be a positive number of Hz, got {tr.rate_hz}")
        try:
            t = np.asarray(s.t, np.float64) if s.t is not None else None
        except (TypeError, ValueError):
            raise ValueError(f"{where}: samples.t must be real seconds, got {np.asarray(s.t).dtype}") from None
        if t is None or t.shape != (n,):
            got = "None" if t is None else str(list(t.shape))
            raise ValueError(f"{where}: samples.t must have shape (N,) = ({n},) like gyr, seconds; got {got}")
        check_timestamps(t, "samples.t", getattr(s.t, "dtype", None), f"{where}: ")
        step = float(np.median(np.diff(t)))
        if not abs(step * rate - 1.0) <= 0.01:
            raise ValueError(f"{where}: rate_hz = {rate:g} Hz but samples.t steps by {step:.6g} s ({1 / step:.6g} Hz)")
        if need_scored and not np.any(scored_samples(tr)):
            raise ValueError(
                f"{where}: no scored sample (movement and finite quat_true); it would add a zero error to the "
                f"loss: leave it out of {what}"
            )
    return trials


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
    try:
        with open(p, encoding="utf-8") as f:
            info = json.load(f)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{p}: cannot read it as JSON ({' '.join(str(e).split())})") from None
    trials = info.get("trials", {}) if isinstance(info, dict) else None
    if not isinstance(trials, dict) or not all(
        isinstance(v, dict) and isinstance(v.get("groups"), list) for v in trials.values()
    ):
        raise ValueError(f"{p}: not BROAD's trials.json (want {{'trials': {{name: {{'groups': [...]}}}}}})")
    return info


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


def group_of(name: str, info: Optional[dict] = None) -> str:
    """ "disturbed" or "undisturbed" (see :func:`trial_groups`)."""
    return "disturbed" if "disturbed" in trial_groups(name, info) else "undisturbed"


def stratified_folds(names: Sequence[str], info=None, k: int = 2) -> List[List[str]]:
    """k folds of trial names stratified by group: within each group (sorted by name) trial i goes to fold
    i mod k. For the 20 shared trials and k = 2: fold 1 = 01 04 06 08 11 14 18 24 28 32, fold 2 = 02 05 07 10 12
    15 21 26 30 34 (each fold has one tapping / vibration, one stationary-magnet and one attached-magnet trial)."""
    folds: List[List[str]] = [[] for _ in range(k)]
    for g in GROUPS:
        members = sorted(n for n in names if group_of(n, info) == g)
        for i, n in enumerate(members):
            folds[i % k].append(n)
    return [sorted(f) for f in folds]


def resolve_trials(data_dir, trials=None) -> List[str]:
    """Trial names from a spec: None (all), or a list / comma-separated string of trial names, leading numbers
    ("01", "24"), group names ("undisturbed", "disturbed") or "fold1" / "fold2" (:func:`stratified_folds`).
    ValueError naming what is not found."""
    if Path(data_dir).is_file():
        raise FileNotFoundError(
            f"BROAD data folder {data_dir}: is a file; give the folder that holds the trials (and --trials NAME), "
            "or read one file with jaxatt.data.broad.load_trial"
        )
    if not Path(data_dir).is_dir():
        raise FileNotFoundError(f"BROAD data folder not found: {data_dir}")
    names = list_trials(data_dir)
    if not names:
        raise FileNotFoundError(f"no BROAD trial files (*.hdf5) in {data_dir}")
    if trials is None:
        return names
    if isinstance(trials, str):
        trials = [t for t in trials.replace(",", " ").split() if t]
    trials = [t for t in trials if str(t).strip()]
    if not trials:
        raise ValueError("no trial named: give trial names, numbers, groups or fold1 / fold2 (or leave it out: all)")
    info = load_trial_info(data_dir)
    out: List[str] = []
    for t in trials:
        t = str(t)
        if t in names:
            sel = [t]
        elif t in GROUPS:
            sel = [n for n in names if group_of(n, info) == t]
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
        out.extend(x for x in sel if x not in out)
    return out


def load(data_dir, trials=None) -> List[Trial]:
    """Load BROAD trials from a folder of ``.hdf5`` files: ``trials`` as in :func:`resolve_trials` (names, numbers
    such as "01", groups, folds; None: all), in that order. Each :class:`Trial` knows its group."""
    return load_trials(data_dir, resolve_trials(data_dir, trials))


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
    with np.errstate(divide="ignore", invalid="ignore"):  # NaN rows (no truth, a diverged estimate) stay NaN
        qe = qe / np.linalg.norm(qe, axis=-1, keepdims=True)
        qt = qt / np.linalg.norm(qt, axis=-1, keepdims=True)
        conj = qt * np.array([1.0, -1.0, -1.0, -1.0])
        d = _quatmult_np(qe, conj)
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        total = 2 * np.arccos(np.clip(np.abs(d[..., 0]), 0, 1))
        heading = 2 * np.arctan(np.abs(d[..., 3] / d[..., 0]))
        incl = 2 * np.arccos(np.clip(np.sqrt(d[..., 0] ** 2 + d[..., 3] ** 2), 0, 1))
    return total, heading, incl


def scored_samples(trial: Trial) -> np.ndarray:
    """(N,) bool: the samples of a trial that the metric scores (movement and finite ground truth)."""
    return np.asarray(trial.movement, bool) & np.all(np.isfinite(np.asarray(trial.quat_true)), axis=-1)


def broad_errors(quat_est, quat_true, movement) -> Dict[str, float]:
    """BROAD's metric (float64 numpy): RMSE (deg) of the total, heading and inclination errors over the
    ``movement`` samples, ignoring samples whose ground truth is NaN; no offset is fitted.

    Args:
        quat_est: (N, 4) estimated sensor-to-ENU quaternions (w, x, y, z).
        quat_true: (N, 4) ground truth (BROAD's ``opt_quat``), NaN where missing.
        movement: (N,) bool.

    Returns dict(total_rmse_deg, heading_rmse_deg, inclination_rmse_deg): for each error e_k (rad, see
    :func:`error_angles`), rad2deg(sqrt(nanmean(e_k^2 over k in movement))) - the same numbers as BROAD's
    ``calculateRMSE``. One departure: a non-finite estimate on a scored sample (movement, finite truth) makes
    every metric NaN, where BROAD's nanmean would skip the sample (a diverged filter must not score well).
    """
    movement = np.asarray(movement).astype(bool)
    total, heading, incl = error_angles(quat_est, quat_true)
    scored = movement & np.all(np.isfinite(np.asarray(quat_true, float)), axis=-1)
    if not scored.any() or not np.all(np.isfinite(np.asarray(quat_est, float))[scored]):  # none, or diverged
        nan = float("nan")
        return dict(total_rmse_deg=nan, heading_rmse_deg=nan, inclination_rmse_deg=nan)
    rmse = lambda e: float(np.rad2deg(np.sqrt(np.nanmean(e[movement] ** 2))))  # noqa: E731
    return dict(total_rmse_deg=rmse(total), heading_rmse_deg=rmse(heading), inclination_rmse_deg=rmse(incl))


def _safe_sqrt(x):
    """sqrt(x) with a finite gradient at x <= 0 (0 there); NaN stays NaN, so a diverged estimate never scores 0."""
    ok = x > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), jnp.where(jnp.isnan(x), x, 0.0))


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
    :func:`error_angles_jax`), NaN with no such sample as there. NaN rows of ``quat_true`` are replaced before
    any arithmetic (double-where), so gradients stay finite.
    """
    movement = jnp.asarray(movement, bool)
    if mask is not None:
        movement = movement & jnp.asarray(mask, bool)
    finite = jnp.all(jnp.isfinite(quat_true), axis=-1)
    use = movement & finite
    qt = jnp.where(finite[..., None], quat_true, jnp.array([1.0, 0.0, 0.0, 0.0], quat_est.dtype))
    qe = jnp.where(use[..., None], quat_est, qt)  # unused samples: zero error, no NaN reaches the gradient
    errs = error_angles_jax(qe, qt)
    count = jnp.sum(use, axis=-1)
    n = jnp.maximum(count, 1).astype(quat_est.dtype)
    out = {}
    for name, e in zip(METRICS, errs):
        ms = jnp.sum(jnp.where(use, e * e, 0.0), axis=-1) / n
        out[name] = jnp.where(count > 0, jnp.rad2deg(_safe_sqrt(ms)), jnp.nan)  # none scored: NaN, as broad_errors
    return out


# ------------------------------------------------------------------------------------------------------------
# Batching and scoring observers (through the one scan, :mod:`jaxatt.engine`)
# ------------------------------------------------------------------------------------------------------------
def pad_trials(trials: Sequence[Trial]) -> PaddedTrials:
    """Stack trials of different lengths into (B, T_max, ...) arrays for ``vmap``.

    Padding repeats each trial's last sample (finite data, so no NaN enters a scan or a gradient); ``mask`` is
    False there and ``movement`` is False there. t is k / rate when every trial's steps are uniform (within
    :data:`UNIFORM_TOLERANCE`); a trial whose steps are not (a gap, a change of rate) makes t each trial's own
    timestamps from its first (t - t_0) and the batch's steps per sample (``dt``). On the padding, time continues
    at the trial's rate. A batch
    longer than one :data:`jaxatt.engine.BLOCK` of steps is padded to a whole number of blocks (T_max - 1 a
    multiple of BLOCK): the compiled scan then holds one copy of the observer's step, not a second one for a
    partial last block (at most BLOCK - 1 more padded samples per trial).
    """
    if not trials:
        raise ValueError("no trials to pad")
    lengths = np.array([len(tr.samples.t) for tr in trials], int)
    tmax = int(lengths.max())
    if tmax - 1 > engine.BLOCK:
        tmax = 1 + engine.BLOCK * -(-(tmax - 1) // engine.BLOCK)

    def pad(a, n):
        a = np.asarray(a)
        if n == tmax:
            return a
        reps = np.repeat(a[-1:], tmax - n, axis=0)
        return np.concatenate([a, reps], axis=0)

    ts, gyr, acc, mag, qt, mov, mask = [], [], [], [], [], [], []
    uniform = True
    for tr, n in zip(trials, lengths):
        t = np.asarray(tr.samples.t, np.float64)
        t = t - t[0]
        uniform = uniform and (n < 2 or float(np.max(np.abs(np.diff(t) * tr.rate_hz - 1.0))) <= UNIFORM_TOLERANCE)
        ts.append(np.concatenate([t, t[-1] + np.arange(1, tmax - n + 1, dtype=np.float64) / tr.rate_hz]))
        gyr.append(pad(tr.samples.gyr, n))
        acc.append(pad(tr.samples.acc, n))
        mag.append(pad(tr.samples.mag, n))
        qt.append(pad(tr.quat_true, n))
        mov.append(np.concatenate([tr.movement, np.zeros(tmax - n, bool)]))
        mask.append(np.arange(tmax) < n)
    rates = np.array([tr.rate_hz for tr in trials], float)
    if uniform:  # the timestamps BROAD's filters assume: k / rate
        ts = [np.arange(tmax, dtype=np.float64) / r for r in rates]
    samples = ImuSample(np.stack(ts), np.stack(gyr), np.stack(acc), np.stack(mag))
    dt = None
    if not uniform:
        dt = np.diff(samples.t, axis=1, prepend=samples.t[:, :1] - 1.0 / rates[:, None])
    return PaddedTrials(
        samples, np.stack(mask), np.stack(qt), np.stack(mov), lengths, tuple(tr.name for tr in trials), rates, dt
    )


#: Largest |step x rate - 1| of a trial scanned with the constant step 1 / rate (:func:`pad_trials`): timestamps
#: rounded to 1e-6 s at 1 kHz, or a clock's ppm drift, stay below it; a gap or a change of rate does not.
UNIFORM_TOLERANCE = 1e-3


def step_dt(rate_hz, dtype):
    """Step dt = 1 / rate computed in ``dtype`` (as the C filters do: 1.0f / sampleFreq in float32)."""
    one = np.asarray(1.0, dtype)
    return one / np.asarray(rate_hz, dtype)


def batch_item(padded: PaddedTrials, dtype, run_params: Optional[dict] = None) -> dict:
    """The engine's recorded batch of padded trials: samples (B, T, ...) as given (cast in the scan), a constant
    dt per trial (1 / rate in ``dtype``; (B, T) steps from the timestamps when ``padded.dt`` holds them: then
    scan it with ``engine.Recorded(n_steps, per_step_dt=True)``) and the truth the BROAD reducer scores against:
    ``q`` (B, T, 4) sensor-to-ENU with missing rows replaced by the identity and ``use`` (B, T) = movement & real
    sample & finite truth (so no NaN enters a scan or a gradient). ``run_params``: optional ``{field: (B, ...)}``,
    each trial's own value of those params fields (:data:`jaxatt.engine.RUN_PARAMS`)."""
    qt = np.asarray(padded.quat_true, np.float64)
    finite = np.all(np.isfinite(qt), axis=-1)
    qt = np.where(finite[..., None], qt, np.array([1.0, 0.0, 0.0, 0.0]))
    use = padded.movement & padded.mask & finite
    hi = jnp.result_type(float)
    item = {
        "samples": jax.tree_util.tree_map(jnp.asarray, padded.samples),
        "dt": jnp.asarray(step_dt(padded.rate_hz, dtype) if padded.dt is None else np.asarray(padded.dt, dtype)),
        "truth": {"q": jnp.asarray(qt, hi), "use": jnp.asarray(use)},
    }
    if run_params:
        item[engine.RUN_PARAMS] = {k: jnp.asarray(v) for k, v in run_params.items()}
    return item


def _sq_errors(q_est, q_true):
    """Squared total, heading and inclination errors (rad^2) of :func:`error_angles_jax`, gradient-safe."""
    total, heading, incl = error_angles_jax(q_est, q_true)
    return jnp.stack([total * total, heading * heading, incl * incl])


def _metric_init(t0, truth0, out0):
    acc = jnp.zeros((3,), truth0["q"].dtype), jnp.zeros((), truth0["q"].dtype)
    return _metric_update(acc, t0, truth0, out0)[0], None


def _metric_update(acc, t, truth, out):
    sse, n = acc
    q = engine.estimate_q(out).astype(truth["q"].dtype)
    use = truth["use"]
    qe = jnp.where(use, q, truth["q"])  # unused samples: zero error, no NaN reaches the gradient
    return (sse + jnp.where(use, _sq_errors(qe, truth["q"]), 0.0), n + use.astype(sse.dtype)), None


def _metric_finish(acc):
    sse, n = acc
    ms = sse / jnp.maximum(n, 1.0)
    return dict(zip(METRICS, jnp.where(n > 0, jnp.rad2deg(_safe_sqrt(ms)), jnp.nan)))  # none scored: NaN


#: The BROAD metric accumulated while the scan runs: per trial the RMSE (deg) of the total, heading and
#: inclination errors over the scored samples (movement, real, finite truth), differentiable. Computed in the
#: truth's precision (float64 when available) whatever the filter's.
METRIC_REDUCER = engine.Reducer(_metric_init, _metric_update, _metric_finish)


def metric_batch(
    observer: Observer,
    trials: Sequence[Trial],
    *,
    hold: Optional[str] = None,
    dtype=None,
    step_remat: bool = False,
    checkpoint=None,
    run_params: Optional[dict] = None,
):
    """(``fn(params, item) -> {metric: (B,) RMSE deg}``, item): the BROAD metric of ``observer`` over a batch item
    of padded trials (rows may be selected: ``item[i]`` for a minibatch), and the item of ``trials``. Pure JAX in
    the params. For gradients: ``checkpoint`` ("auto", a segment length in steps, None: off;
    :func:`jaxatt.engine.segment_length`) stores one state per segment and recomputes each segment in the reverse
    pass; ``step_remat`` rematerialises each step as well (least memory, slowest). ``run_params``: each trial's
    own values of some params fields (:func:`batch_item`). ``hold``: None, the observer's own, else "next"
    (:func:`jaxatt.engine.hold_for`)."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.result_type(float)
    hold = engine.hold_for(observer, hold, "next")
    padded = pad_trials(trials)
    n_steps = int(padded.samples.t.shape[1]) - 1
    fn = engine.compiled(
        observer,
        engine.Recorded(n_steps, padded.dt is not None),
        METRIC_REDUCER,
        hold=hold,
        obs_dtype=dtype,
        segment=engine.segment_length(n_steps, checkpoint),
        step_remat=step_remat,
    )
    return (lambda params, item: fn(None, params, item).summary), batch_item(padded, dtype, run_params)


def metric_fn(
    observer: Observer,
    trials: Sequence[Trial],
    *,
    hold: Optional[str] = None,
    dtype=None,
    step_remat: bool = False,
    checkpoint=None,
    run_params: Optional[dict] = None,
):
    """``fn(params) -> {metric: (B,) RMSE deg}``: the BROAD metric of ``observer`` on ``trials`` as a pure JAX
    function of the params (jit it, vmap it over a grid of gains, differentiate it), all trials in one scan
    (``checkpoint``, ``step_remat``, ``run_params``: :func:`metric_batch`)."""
    fn, item = metric_batch(
        observer, trials, hold=hold, dtype=dtype, step_remat=step_remat, checkpoint=checkpoint, run_params=run_params
    )
    return lambda params: fn(params, item)


def score(
    observer: Observer,
    params,
    trials: Sequence[Trial],
    *,
    hold: Optional[str] = None,
    dtype=None,
    run_params: Optional[dict] = None,
) -> Dict[str, Dict[str, float]]:
    """BROAD metric of ``observer`` on each trial: {trial name: {metric: RMSE deg}}, all trials in one vmapped scan.

    The observer's estimate k (T estimates for T samples: estimate 0 is ``init``'s from the first sample,
    :mod:`jaxatt.engine`) must be sensor-to-ENU (BROAD's frame) and is scored against ``opt_quat[k]``. ``hold``:
    the input of each step ("next": sample k updates the estimate to t_k, as ahrs, VQF and BROAD's filters do;
    None: the observer's own, else "next").
    ``dtype``: the filter's arithmetic (default jax's default float); the metric is computed in float64 when x64
    is enabled. ``run_params``: each trial's own values of some params fields, ``{field: (B, ...)}``
    (:func:`jaxatt.api.recording_defaults_per_trial`).
    """
    summary = jax.device_get(metric_fn(observer, trials, hold=hold, dtype=dtype, run_params=run_params)(params))
    return {tr.name: {m: float(summary[m][i]) for m in METRICS} for i, tr in enumerate(trials)}
