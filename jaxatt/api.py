"""The front door: a registered observer or your own ``Observer(init, step)`` on your own arrays, on BROAD trials,
tuned on them, or in Monte Carlo on a simulated AHRS scenario.

    import jaxatt
    est = jaxatt.filter("robust", gyr, acc, mag, dt=1 / 285.714)        # numpy (T, 3) in, est.quat (T, 4) out
    est = jaxatt.filter("mekf", gyr, acc, mag, dt=0.01, frame="NED")    # any registered observer
    est = jaxatt.filter(my_observer, gyr, acc, mag, dt=0.01, params=my_params)
    est = jaxatt.filter("robust", gyr, acc, mag, dt=0.0035, offline=True)  # forward-backward smoothing
    trials = jaxatt.data.broad.load("path/to/broad", trials=["01", "02"])
    score = jaxatt.broad_score("robust", None, trials)   # .trials[name].total_rmse_deg, .groups["disturbed"]...
    score = jaxatt.broad_score("robust", None, trials, offline=True)      # the smoothed estimate's metric
    fit = jaxatt.fit(my_observer, my_params, trials, steps=20)            # .params (same type), .history

Conventions: inputs in the sensor (body) frame, gyro rad/s, accelerometer m/s^2 (specific force, "up" at rest),
magnetometer in any unit; quaternions (w, x, y, z) mapping sensor to the navigation frame (``frame``: ENU, NED or
NWU, :mod:`jaxatt.frames`). T samples give T estimates, estimate 0 being the observer's start from the first
sample (:mod:`jaxatt.engine`). ``offline=True`` (``filter``, ``broad_score``) uses the whole recording: the observer
runs forward and over the time-reversed recording and the two estimates are fused per sample
(:mod:`jaxatt.smoothing`). Arithmetic: float64 for float64 input when JAX's x64 is on (jaxatt never switches
it: ``jax.config.update("jax_enable_x64", True)``); otherwise float32, with a warning for float64 input.
"""

from __future__ import annotations

import functools
import time
import warnings
from typing import Any, Dict, List, NamedTuple, Optional, Sequence, Union

import jax
import jax.numpy as jnp
import numpy as np

from . import engine, frames, so3
from .observers import registry
from .types import HOLDS, ImuSample, Observer, check_seed, check_window_start

__all__ = [
    "filter",
    "Estimate",
    "broad_score",
    "BroadScore",
    "TrialScore",
    "GroupScore",
    "monte_carlo",
    "ahrs_scenario",
    "ahrs_errors",
    "resolve_observer",
    "compute_dtype",
]

ObserverLike = Union[str, Observer, registry.Entry]


# ------------------------------------------------------------------------------------------------------------
# Boundary helpers
# ------------------------------------------------------------------------------------------------------------
def trial_arrays(trials):
    """Every sensor array of ``trials`` (what :func:`compute_dtype` looks at: one float64 trial makes it float64)."""
    return [a for t in trials for a in (t.samples.gyr, t.samples.acc, t.samples.mag)]


def _dtype_of(a) -> np.dtype:
    """An array's dtype without copying it to the host (a JAX array's own), or numpy's reading of a list."""
    try:
        return np.dtype(a.dtype)
    except (AttributeError, TypeError):  # a list, a number, another library's dtype
        return np.asarray(a).dtype


def compute_dtype(*arrays, dtype=None, what: str = "input"):
    """The arithmetic for arrays of the given dtypes: ``dtype`` if given; float64 when any input is float64 and x64
    is on; float32 otherwise (with a warning when float64 input is computed in float32)."""
    x64 = bool(jax.config.values["jax_enable_x64"])
    if dtype is not None:
        try:
            dt = np.dtype(dtype.lower() if isinstance(dtype, str) else dtype)
        except TypeError:
            raise ValueError(f"dtype must be float32 or float64, got {dtype!r}") from None
        if dt not in (np.float32, np.float64):
            raise ValueError(f"dtype must be float32 or float64, got {dtype!r}")
        if dt == np.float64 and not x64:
            raise ValueError("dtype float64 needs JAX's x64 mode: call jax.config.update('jax_enable_x64', True) first")
        return dt
    wide = any(_dtype_of(a) == np.float64 for a in arrays if a is not None)
    if wide and not x64:
        warnings.warn(
            f"float64 {what} is computed in float32 because JAX's x64 mode is off; call "
            "jax.config.update('jax_enable_x64', True) for float64 results, or pass float32 arrays",
            stacklevel=3,
        )
    return np.dtype(np.float64) if (wide and x64) else np.dtype(np.float32)


def _from_table(v):
    """``v`` as numpy can read it when it is a pandas object: nullable numbers (``Float64`` with ``NA``, which
    numpy reads as objects) as floats with NaN, timezone-aware times as UTC datetime64; anything else as is."""
    if isinstance(v, np.ndarray) or not hasattr(v, "to_numpy"):
        return v
    times = getattr(v, "dt", v)  # a Series' datetime accessor, or a DatetimeIndex itself
    if getattr(times, "tz", None) is not None and hasattr(times, "tz_convert"):
        return np.asarray(times.tz_convert(None))  # UTC, without the zone
    try:
        return v.to_numpy(dtype=float, na_value=np.nan)
    except (TypeError, ValueError):
        return v


def _vectors(name: str, v, n: Optional[int], required: bool) -> Optional[np.ndarray]:
    if v is None:
        if required:
            raise ValueError(f"{name} is required (an array of shape (T, 3))")
        return None
    try:
        a = np.asarray(_from_table(v))
    except Exception as e:  # noqa: BLE001 - anything numpy cannot read
        raise ValueError(f"{name} must be an array of shape (T, 3), got {type(v).__name__}: {e}") from None
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise ValueError(f"{name} must be numeric, got dtype {a.dtype}")
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (T, 3), got {a.shape}")
    if n is not None and a.shape[0] != n:
        raise ValueError(f"{name} has {a.shape[0]} samples, gyr has {n}")
    if np.any(np.isinf(a)):
        raise ValueError(f"{name} contains +-inf (mark a missing reading with NaN)")
    if np.issubdtype(a.dtype, np.floating):
        return a
    # integer counts: float64 where JAX computes in it, else float32 (not a "float64 input" narrowed with a warning)
    return a.astype(np.float64 if jax.config.values["jax_enable_x64"] else np.float32)


def _valid_rows(a: np.ndarray) -> np.ndarray:
    """(T,) True where a (T, 3) reading is present: finite and not all zero (NaN / zero rows mark a missing one)."""
    with np.errstate(invalid="ignore"):
        return np.all(np.isfinite(a), axis=-1) & np.any(a != 0, axis=-1)


def _starts_from_first_sample(entry) -> bool:
    return entry is not None and (entry.setup is not None or bool(entry.init_reads))


def start_from_valid(entry, acc: Optional[np.ndarray], mag: Optional[np.ndarray], gyr, ts):
    """(acc, mag) for a registered observer that sets its start and references up from the first sample (an
    entry with ``setup``: TRIAD and the field and gravity references; or one whose ``init_reads`` names the
    sensors, e.g. the robust AHRS's TRIAD and field norm and dip): a missing acc / mag reading in row 0 is
    replaced by that sensor's first present reading, carried back to row 0's sensor frame by the gyro
    (:func:`jaxatt.so3.first_present_at_start`; ``gyr`` (T, 3) rad/s, ``ts`` (T,) s; row 0 only feeds ``init`` on
    hold "next"; other rows stay missing). A sensor with no present reading at all gets a zero row 0 (missing by
    the same convention, and no NaN in the set-up: its degenerate TRIAD keeps the inclination, the observer's own
    handling of a dead magnetometer)."""
    if not _starts_from_first_sample(entry):
        return acc, mag
    out: List[Optional[np.ndarray]] = []
    for a in (acc, mag):
        if a is not None and not _valid_rows(a[:1])[0]:
            ok = _valid_rows(a)
            j = int(np.argmax(ok)) + 1  # only the rows up to the first present one matter
            a = a.copy()
            dt = np.diff(np.asarray(ts[:j], np.float64), prepend=0.0)
            row0 = so3.first_present_at_start(np.asarray(a[:j], np.float64), np.asarray(gyr[:j], np.float64), dt)[0]
            a[0] = np.asarray(row0) if ok.any() else 0.0
        out.append(a)
    return out[0], out[1]


def truth_in_frame_of(entry, trials: list) -> list:
    """``trials`` with their sensor-to-ENU truth re-expressed in the navigation frame of ``entry``'s estimate (a
    registered NED or NWU observer: the frames share the vertical, so the BROAD metric's heading / inclination
    split is the same); unchanged for an ENU observer or one of your own (``entry`` None)."""
    if entry is None or entry.frame == "ENU":
        return trials
    return [tr._replace(quat_true=frames.change_frame(tr.quat_true, entry.frame, "ENU")) for tr in trials]


def trials_start_from_valid(entry, trials: list) -> list:
    """:func:`start_from_valid` on each trial's samples (a trial whose row 0 has all its readings is kept as is)."""
    if not _starts_from_first_sample(entry):
        return trials
    out = []
    for tr in trials:
        s = tr.samples
        acc = None if s.acc is None else np.asarray(s.acc)
        mag = None if s.mag is None else np.asarray(s.mag)
        acc2, mag2 = start_from_valid(entry, acc, mag, np.asarray(s.gyr), np.asarray(s.t))
        out.append(tr if acc2 is acc and mag2 is mag else tr._replace(samples=s._replace(acc=acc2, mag=mag2)))
    return out


def _moving_mean(x: np.ndarray, k: int) -> np.ndarray:
    """Mean of the present rows (finite, not all zero) among each k consecutive rows (the last k - 1 rows repeat
    the last mean); NaN where a window has no present row (a sensor at a lower rate, a dropout)."""
    ok = _valid_rows(x)
    if k <= 1 or len(x) < k:
        return np.where(ok[:, None], x, np.nan)
    c = np.cumsum(np.concatenate([np.zeros((1,) + x.shape[1:]), np.where(ok[:, None], x, 0.0)]), axis=0)
    n = np.cumsum(np.concatenate([[0], ok.astype(np.int64)]))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (c[k:] - c[:-k]) / (n[k:] - n[:-k])[:, None]
    return np.concatenate([out, np.repeat(out[-1:], k - 1, axis=0)])


def _rows_in(seconds: float, step: float, length: int) -> Optional[int]:
    """How many sample intervals of ``step`` s make ``seconds`` (at least 1); None when that is not under
    ``length`` (or the step is not a positive finite number)."""
    rows = seconds / step if np.isfinite(step) and step > 0 else np.inf
    return max(1, int(round(rows))) if rows < length else None


def _present_spacing(x: np.ndarray) -> int:
    """Median number of rows between present readings of x (1 at the full rate; 10 for a sensor at a tenth)."""
    rows = np.flatnonzero(_valid_rows(x))
    return int(np.median(np.diff(rows))) if len(rows) > 1 else 1


def _frame_angle(frame: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) between the body-frame bases frame[i] and frame[j] (each (3, 3))."""
    rel = np.einsum("nki,nkj->nij", frame[i], frame[j])
    return np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1))


#: Windows (s) over which :func:`gyro_rotation_ratio` compares the gyro's rotation with the acc-mag frame's.
RATIO_WINDOWS = (0.5, 1.0, 2.0)
#: Sub-windows per window whose chained frame angles must stay under 180 deg (no spin through a half turn).
RATIO_SUBWINDOWS = 8


def gyro_rotation_ratio(gyr, acc, mag, ts, max_windows: int = 2000) -> Optional[float]:
    """How far the gyro turns against the accelerometer-magnetometer frame (:func:`_gyro_rotation`)."""
    return _gyro_rotation(gyr, acc, mag, ts, max_windows)[0]


def _frame_turn_axis(frame: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Unit axis (body frame) of the body's rotation from sample i to j that the bases frame[i], frame[j] (the nav
    basis in body coordinates) imply: R = F_i F_j^T."""
    rel = np.einsum("nik,njk->nij", frame[i], frame[j])
    v = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], axis=-1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _gyro_rotation(gyr, acc, mag, ts, max_windows: int = 2000):
    """How far the gyro turns against the accelerometer-magnetometer frame (a units check needing no filter):
    the median over windows of :data:`RATIO_WINDOWS` of |sum of gyr dt| / the rotation angle between the frames
    (gravity, gravity x field; from 50-ms means of the present acc and mag readings, longer for a sensor at a
    lower rate, in the body) at the window's ends. Windows whose ends are near rest (|acc| within 10 % of its
    median, |mag| within 10 %) and turn 10-90 deg count, unless the frame's path through
    :data:`RATIO_SUBWINDOWS` sub-windows reaches 180 deg (a fast spin, whose net angle wraps); None with fewer
    than 5. About 1 for gyr in rad/s (0.23-1.0 on the 20 BROAD trials), 57 for deg/s given as rad/s (13-57 on
    BROAD: fast translation makes the frame turn with the linear acceleration). ``ts``: sample times (T,), s;
    gyr, acc, mag: (T, 3) in the body frame. Returns (ratio, cos): cos the median cosine between the gyro's turn
    and the frame's over the windows whose ratio is at most twice the median (1 when they turn the same way: a
    gyro in the wrong unit; near 0 when the frame turns with a linear acceleration or a field change the gyro
    does not see); (None, None) with fewer than 5 windows."""
    if acc is None or mag is None or len(ts) < 3:
        return None, None
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN sensor: no window counts
        dt = np.diff(ts)
        step = float(np.median(dt))
        k = _rows_in(0.05, step, len(ts))
        if k is None:
            return None, None
        a_s, m_s = (_moving_mean(x, max(k, _present_spacing(x))) for x in (acc, mag))
        a_n, m_n = np.linalg.norm(a_s, axis=-1), np.linalg.norm(m_s, axis=-1)
        e1 = a_s / a_n[:, None]
        e2 = np.cross(a_s, m_s)
        e2 = e2 / np.linalg.norm(e2, axis=-1, keepdims=True)
        frame = np.stack([e1, e2, np.cross(e1, e2)], axis=-1)  # (T, 3, 3): the nav basis in body coordinates
        near_rest = (np.abs(a_n - np.nanmedian(a_n)) < 0.1 * np.nanmedian(a_n)) & (
            np.abs(m_n - np.nanmedian(m_n)) < 0.1 * np.nanmedian(m_n)
        )
        near_rest &= np.all(np.isfinite(frame), axis=(-1, -2))
        turned = np.concatenate(
            [np.zeros((1, 3)), np.cumsum(np.where(np.isfinite(gyr[:-1]), gyr[:-1], 0.0) * dt[:, None], 0)]
        )
        ratios, cosines = [], []
        for w in RATIO_WINDOWS:
            n = _rows_in(w, step, len(ts))
            if n is None:
                continue
            i = np.arange(0, len(ts) - n, max(1, (len(ts) - n) // max_windows))
            i = i[near_rest[i] & near_rest[i + n]]
            seen = _frame_angle(frame, i, i + n)
            cuts = [i + (n * c) // RATIO_SUBWINDOWS for c in range(RATIO_SUBWINDOWS + 1)]
            path = sum(_frame_angle(frame, u, v) for u, v in zip(cuts[:-1], cuts[1:]))  # NaN: not counted
            use = (seen > np.deg2rad(10)) & (seen < np.deg2rad(90)) & (path < np.pi)
            g = (turned[i + n] - turned[i])[use]
            g_norm = np.linalg.norm(g, axis=-1)
            ratios.append(g_norm / seen[use])
            cosines.append(np.sum(g * _frame_turn_axis(frame, i[use], (i + n)[use]), axis=-1) / g_norm)
        r = np.concatenate(ratios) if ratios else np.zeros(0)
        c = np.concatenate(cosines) if cosines else np.zeros(0)
    if len(r) < 5:
        return None, None
    typical = r <= 2.0 * np.median(r)  # the windows that make the median ratio
    return float(np.median(r)), float(np.nanmedian(c[typical]))


def _warn_implausible(
    gyr: np.ndarray,
    acc: Optional[np.ndarray],
    mag: Optional[np.ndarray],
    ts: np.ndarray,
    from_dt: bool = False,
    where: str = "",
    api: str = "jaxatt.filter",
    cli: str = "jaxatt filter",
    stacklevel: int = 3,
):
    """Warn (never refuse) about data that looks like the wrong units: gyro beyond 35 rad/s (2000 deg/s, the
    widest common range: deg/s given as rad/s?), specific force near 1 instead of 9.81 (g units?), a median sample
    interval above 1 s (ms timestamps?), gaps longer than 10 median intervals, a sensor with no present reading
    (acc / mag: every row NaN or zero), a gyro that turns over 5x as far as acc and mag do
    (:func:`gyro_rotation_ratio`: deg/s during slow motion). ``where`` starts each warning (e.g. "log walk.csv: ");
    ``api`` / ``cli`` name the function and the command whose unit arguments convert the data."""
    notes = _implausible_notes(gyr, acc, mag, ts, from_dt, api, cli)
    for note in notes:
        warnings.warn(where + note, stacklevel=stacklevel)


def _implausible_notes(gyr, acc, mag, ts, from_dt: bool, api: str, cli: str) -> List[str]:
    on_filter = api == "jaxatt.filter"  # filter's dt replaces a log's timestamps; load_trial's times a log without
    with np.errstate(invalid="ignore", over="ignore"):  # |acc| of huge readings: inf, said later
        notes = []
        if not np.isfinite(gyr).any():
            notes.append("gyr has no finite reading (every row NaN)")
        for name, a in (("acc", acc), ("mag", mag)):
            if a is not None and not _valid_rows(a).any():  # a zero row marks a missing reading, as NaN does
                notes.append(f"{name} has no present reading (every row NaN or all zero): the filter runs without it")
        g = np.nanmax(np.abs(gyr)) if np.isfinite(gyr).any() else 0.0
        d = np.diff(ts)
        step = float(np.median(d))
        time_suspect = step >= 1.0  # the gyro's integral is then off by the time unit, not by the gyro's
        ratio, agree = (None, None) if time_suspect else _gyro_rotation(gyr, acc, mag, ts)
        if g > 35.0:
            notes.append(
                f"gyr reaches {g:.4g} rad/s (more than 2000 deg/s): is it in deg/s? jaxatt expects rad/s "
                f"(gyr_unit='deg/s' in {api}, --gyr-unit deg/s in {cli}, converts it)"
            )
        elif ratio is not None and ratio > 5.0:
            notes.append(
                f"the gyro turns {ratio:.3g}x as far as the accelerometer and magnetometer do: is gyr in deg/s "
                f"(57x)? jaxatt expects rad/s (gyr_unit='deg/s' in {api}, --gyr-unit deg/s in {cli}, "
                "converts it)"
            )
        elif ratio is not None and ratio < LOW_ROTATION_RATIO and agree is not None and agree > 0.5:
            # the same way round, 57x less (a tilt from a linear acceleration or a field swinging at rest turns
            # the acc-mag frame too, but not about the gyro's axis)
            notes.append(
                f"the gyro turns {ratio:.3g}x as far as the accelerometer and magnetometer do: is gyr converted "
                f"twice (already in rad/s and given as deg/s: 57x too small) or in a smaller unit than said? "
                "jaxatt expects rad/s"
            )
        if acc is not None and np.isfinite(acc).any():
            acc_norm = float(np.nanmedian(np.linalg.norm(acc, axis=-1)))
            if 0.5 < acc_norm < 2.0:
                notes.append(
                    f"the median |acc| is {acc_norm:.3g}: is it in g? jaxatt expects m/s^2 (9.81 at rest; "
                    f"acc_unit='g' in {api}, --acc-unit g in {cli}, converts it)"
                )
            elif not 4.0 < acc_norm < 30.0:
                if 500 < acc_norm < 2000:
                    unit = f"mg? jaxatt expects m/s^2 (acc_unit='mg' in {api}, --acc-unit mg in {cli}, converts it)"
                else:
                    unit = "raw counts? jaxatt expects m/s^2"
                notes.append(
                    f"the median |acc| is {acc_norm:.4g}, far from 9.81 m/s^2 (gravity, what an accelerometer "
                    f"measures at rest): is it in {unit}"
                )
        for name, a in (("gyr", gyr), ("acc", acc)):
            at = _saturated(a, SATURATION_FLOOR[name])
            if at:
                notes.append(
                    f"{name} stays at exactly {at[1]:.6g} in {at[0]} samples: is the sensor saturated (clipped at "
                    "its range)? the estimate drifts while it is"
                )
        if step >= 1.0:
            unit = "ms" if step < 1e3 else ("us" if step < 1e6 else "ns")
            if step == 1.0 and not from_dt and np.all(ts == np.round(ts)):
                unit += " (or is t a sample counter? if the log truly runs at 1 Hz, ignore this)"
            if from_dt:  # the user's own sample period, not timestamps
                notes.append(
                    f"the sample period dt is {step:.4g} s: is it in {unit}? jaxatt expects s "
                    + (f"(time_unit='{unit}' in {api} converts it)" if on_filter else "(give dt in seconds)")
                )
            else:
                notes.append(
                    f"the median sample interval is {step:.4g} s: are the timestamps in {unit}? jaxatt expects s "
                    f"(time_unit='{unit}' in {api}, --time-unit {unit} in {cli}, converts them"
                    + ("; or give the sample period: dt= / --dt)" if on_filter else ")")
                )
        gaps = d > 10.0 * step
        if gaps.any():
            k = int(np.argmax(d))
            notes.append(
                f"{int(gaps.sum())} sample intervals are longer than 10x the median ({step:.3g} s), the longest "
                f"{d[k]:.4g} s after t = {ts[k]:.6g} s (sample {k}): the gyro is integrated across each gap"
            )
    return notes


#: A gyro turning less than this fraction of what the accelerometer and magnetometer turn is warned about
#: (:func:`gyro_rotation_ratio`): a gyro converted twice reads 1/57 (0.017); the 20 BROAD trials, magnetic
#: disturbances included, read 0.23-1.0.
LOW_ROTATION_RATIO = 0.05

#: Smallest |reading| a clipped sensor is taken to sit at (:func:`_saturated`): gyro ranges start at 125 deg/s
#: (2.2 rad/s), accelerometer ranges at 2 g; a quiet signal's repeated quantisation step is far below.
SATURATION_FLOOR = {"gyr": 2.0, "acc": 15.0}


def _saturated(a, floor: float) -> Optional[tuple]:
    """(count, value) when some axis of a noisy ``a`` (T, 3) sits at exactly its largest |value| (at least
    ``floor``: a sensor's full scale, not a quiet signal's quantisation step) in at least 10 samples and 0.1 % of
    them, but under half, at least 3 of them in a row (a clipped sensor: the genuine peaks of a noisy signal rarely
    repeat one reading), else None. Noisy: most of the other samples differ from the one before (noise-free
    simulated data holds constant stretches; a constant signal is not clipped)."""
    if a is None:
        return None
    a = np.asarray(a, float)
    with np.errstate(invalid="ignore"):
        for axis in range(a.shape[-1]):
            x = np.abs(a[:, axis])
            x = x[np.isfinite(x)]
            if x.size < 3 or not x.max() >= floor:
                continue
            top = x == x.max()
            count = int(top.sum())
            if not max(10, 1e-3 * x.size) <= count < 0.5 * x.size or not np.any(top[2:] & top[1:-1] & top[:-2]):
                continue
            others = ~top[1:] & ~top[:-1]
            if np.mean(np.diff(x)[others] != 0) > 0.5:
                return count, float(x.max())
    return None


def _times(t, dt, n: int):
    """(t (T,), per_step) from timestamps or a constant dt; ValueError naming the argument."""
    if t is not None and dt is not None:
        raise ValueError("give either t (timestamps, s) or dt (constant step, s), not both")
    if t is None and dt is None:
        raise ValueError("dt (the sample period, s) or t (timestamps, s) is required")
    if t is not None:
        try:
            t = np.asarray(_from_table(t))
            if t.dtype.kind in "mM":  # datetime64 / timedelta64: seconds from their own unit
                from .data.logs import timestamp_seconds

                t = timestamp_seconds(t)
            elif t.dtype.kind not in "iuf":
                raise TypeError
            t_dtype = t.dtype
            t = np.asarray(t, np.float64)
        except (TypeError, ValueError):
            raise ValueError(
                "t must be an array of timestamps in seconds (numbers) or numpy datetime64 / timedelta64, got "
                f"{getattr(t, 'dtype', type(t).__name__)}"
            ) from None
        if t.shape != (n,):
            raise ValueError(f"t must have shape ({n},) like gyr, got {t.shape}")
        from .data.logs import check_timestamps

        check_timestamps(t, "t", t_dtype)
        return t, True
    try:
        if isinstance(dt, (bool, np.bool_, str, bytes)):
            raise TypeError
        dt = float(dt)
    except (TypeError, ValueError):
        if np.ndim(dt) > 0:
            raise ValueError(
                f"dt must be one number of seconds, got an array of shape {np.shape(dt)} (for a varying step give "
                "t, the timestamps)"
            ) from None
        raise ValueError(f"dt must be a number of seconds, got {dt!r}") from None
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a finite positive number of seconds, got {dt}")
    return np.arange(n, dtype=np.float64) * dt, False


#: Lengths per octave (a power of two) that :func:`filter` pads a recording to (one compiled program each). A
#: compile (~1-2 s) costs as much as scanning ~1e6 samples, so the padding (at most 1/LENGTHS_PER_OCTAVE more
#: samples, or up to one noise block of :data:`jaxatt.engine.BLOCK` steps on recordings of a few blocks) is
#: cheap: 10 recordings of 3,000-6,000 samples (robust, float32) took 19.2 s with no padding, 11.6 s with 4
#: (2: 8.0 s).
LENGTHS_PER_OCTAVE = 4


def _per_octave(m: int) -> int:
    """``m`` rounded up to the next of :data:`LENGTHS_PER_OCTAVE` evenly spaced integers per octave."""
    if m <= LENGTHS_PER_OCTAVE:
        return m
    q = 1 << (m.bit_length() - LENGTHS_PER_OCTAVE.bit_length())  # (2^(bits - 1) <= m) / LENGTHS_PER_OCTAVE
    return -(-m // q) * q


def _run_length(n: int) -> int:
    """The number of samples :func:`filter` scans for a recording of ``n`` (``n - 1`` steps after the first
    sample): 256 samples or fewer, ``n`` itself; up to one block of :data:`jaxatt.engine.BLOCK` steps, the next of
    :data:`LENGTHS_PER_OCTAVE` lengths per octave (at most one block); longer, a whole number of blocks, that
    number on the same per-octave grid. Whole blocks keep one copy of the step in the compiled scan: a partial
    last block is a second scan of its own (the 9D VQF filter of 4,096 samples compiles in 8.9 s, of 4,001 in
    6.2 s)."""
    if n <= 256:
        return n
    if n - 1 <= engine.BLOCK:
        return min(_per_octave(n), engine.BLOCK + 1)
    return 1 + engine.BLOCK * _per_octave(-(-(n - 1) // engine.BLOCK))


def _check_recorded_gains(path, params, default, name: str) -> None:
    """One line unless the params read from a gains file have the fields and shapes of ``name``'s params on
    recorded data (a study's gains, e.g. the complementary observer tuned on its simulated vector measurements,
    can hold other shapes)."""
    got, want = engine.tree_shapes(params), engine.tree_shapes(default)
    if got == want:
        return
    from .fitting import gainsfile

    study = gainsfile.read(path).get("study")
    where = f"the {study!r} study's scenario" if study else "another set-up"
    diff = next((f"{k} is {got.get(k)} there, {want.get(k)} here" for k in sorted(set(got) | set(want))
                 if got.get(k) != want.get(k)), "")  # fmt: skip
    raise ValueError(
        f"gains file {path}: gains of {name} learnt on {where}, not for recorded data ({diff}); "
        "learn gains on recordings with jaxatt.fit / jaxatt broad-tune"
    )


def recording_defaults(entry, given, p, *, first_step: float, field_norm: float):
    """``p`` with the entry's data-dependent defaults set from the recording, where they come from the defaults
    (``given``: the params the caller passed, None, a dict or a gains-file path; a field the dict or file names is
    kept, and a Params of the caller's own is theirs, unchanged):

    * :attr:`~jaxatt.observers.registry.Entry.first_step`: that field <- ``first_step`` (s, the recording's first
      sampling time; VQF's ``ts0``);
    * :attr:`~jaxatt.observers.registry.Entry.field_unit_gains` (covariances in the magnetometer's unit squared)
      scaled by (``field_norm`` / |default mag_ref_nav|)^2, ``field_norm`` being |m| of the first field reading in
      the recording's unit.

    A NaN / non-positive ``first_step`` or ``field_norm`` (no such reading) leaves that default alone."""
    if entry is None or not (given is None or isinstance(given, (dict, str))):
        return p
    named = _named_fields(given)
    new = {}
    if entry.first_step and entry.first_step not in named and np.isfinite(first_step) and first_step > 0:
        new[entry.first_step] = jnp.asarray(first_step, jnp.result_type(getattr(p, entry.first_step)))
    if entry.field_unit_gains and np.isfinite(field_norm) and field_norm > 0:
        ref = float(np.linalg.norm(np.asarray(entry.default_params().mag_ref_nav, float)))
        k = (field_norm / ref) ** 2
        new.update({f: getattr(p, f) * k for f in entry.field_unit_gains if f not in named})
    return p._replace(**new) if new else p


def _first_field_norm(mag) -> float:
    """|m| of the first complete magnetometer reading (NaN when there is none)."""
    if mag is None:
        return float("nan")
    m = np.asarray(mag, float)
    ok = _valid_rows(m)
    return float(np.linalg.norm(m[np.argmax(ok)])) if ok.any() else float("nan")


def _median_finite(x) -> float:
    """The median trial's value among the finite ones (the lower middle one of an even count: a value of some
    trial, where the mean of two trials in different units, uT and nT, would fit neither); NaN when none."""
    x = np.sort(np.asarray(x, float)[np.isfinite(np.asarray(x, float))])
    return float(x[(x.size - 1) // 2]) if x.size else float("nan")


def recording_defaults_for_trials(entry, given, p, trials, warn: bool = True):
    """:func:`recording_defaults` for a batch of trials sharing one params: the median over the trials of their
    first step (s) and of their first field readings' norms. Trials far from the median (a field in another unit,
    another sampling rate, compared by their median steps) are warned about unless ``warn`` is False: the defaults
    fit them poorly, and their scores depend on the batch (a fit, whose one params serve every trial)."""
    steps = [float(np.asarray(tr.samples.t[1]) - np.asarray(tr.samples.t[0])) for tr in trials]
    norms = [_first_field_norm(tr.samples.mag) for tr in trials]
    step, norm = _median_finite(steps), _median_finite(norms)
    if warn and entry is not None and (given is None or isinstance(given, (dict, str))):
        named = _named_fields(given)
        cases = (
            ("sizes of the trials' first magnetometer readings", norms, norm, entry.field_unit_gains, 3.0, 2.0,
             "a magnetometer in another unit?"),
            ("trials' sampling steps (s)", [float(np.median(np.diff(np.asarray(tr.samples.t)))) for tr in trials], step,
             (entry.first_step,) if entry.first_step else (), 1.1, 1.1, "another sampling rate"),
        )  # fmt: skip
        for what, values, value, fields, most, far_from, why in cases:
            if not [f for f in fields if f not in named] or _spread(values) <= most:
                continue
            far = [tr.name for tr, v in zip(trials, values) if _spread([v, value]) >= far_from]
            warnings.warn(
                f"{entry.name}: the {what} differ widely ({', '.join(far[:3]) or 'some'}"
                f"{', ...' if len(far) > 3 else ''} far from the median {value:.4g}; {why}): the defaults of "
                f"{', '.join(fields)} follow the median for every trial, so those trials run with defaults that do "
                "not fit them and their scores depend on the batch; score them apart, or give those params",
                stacklevel=3,
            )
    return recording_defaults(entry, given, p, first_step=step, field_norm=norm)


def recording_defaults_per_trial(entry, given, p, trials):
    """(``p``, ``run_params``): :func:`recording_defaults` of each trial, for a batch whose runs may each have
    their own params (:data:`jaxatt.engine.RUN_PARAMS`): ``run_params`` is ``{field: (B, ...)}`` for the
    data-dependent fields whose defaults differ between the trials (their sampling steps, s; their magnetometers'
    units), None when none does; ``p`` holds the median's (:func:`recording_defaults_for_trials`). A trial's score
    then does not depend on the trials beside it."""
    p_shared = recording_defaults_for_trials(entry, given, p, trials, warn=False)
    if entry is None or len(trials) < 2 or not (given is None or isinstance(given, (dict, str))):
        return p_shared, None
    own = [
        recording_defaults(
            entry,
            given,
            p,
            first_step=float(np.asarray(tr.samples.t[1]) - np.asarray(tr.samples.t[0])),
            field_norm=_first_field_norm(tr.samples.mag),
        )
        for tr in trials
    ]
    fields = [f for f in ((entry.first_step,) if entry.first_step else ()) + tuple(entry.field_unit_gains or ())]
    differ = [f for f in fields if any(not np.array_equal(np.asarray(getattr(o, f)), np.asarray(getattr(own[0], f)))
                                       for o in own[1:])]  # fmt: skip
    if not differ:
        return own[0], None
    return p_shared, {f: np.stack([np.asarray(getattr(o, f)) for o in own]) for f in differ}


def _spread(values) -> float:
    """max / min of the finite positive values (1 when fewer than two)."""
    v = np.asarray([x for x in values if np.isfinite(x) and x > 0], float)
    return float(v.max() / v.min()) if v.size > 1 else 1.0


def _named_fields(given) -> set:
    """The Params fields the caller's params name (a dict's keys, a gains file's gains; none for None)."""
    if isinstance(given, dict):
        return set(given)
    if isinstance(given, str):  # the gains a file holds are the caller's
        from .fitting import gainsfile

        return set(gainsfile.read(given).get("gains", {}))
    return set()


def resolve_observer(observer: ObserverLike, params=None, *, dtype=None, recorded: bool = True):
    """(observer, params, entry or None, name) for a registered name / :class:`~jaxatt.observers.registry.Entry`
    (set up for recorded data, params None -> its shipped or default gains) or a user's :class:`Observer`
    (``params`` required)."""
    if isinstance(observer, (str, registry.Entry)):
        entry = registry.get(observer)
        obs = registry.recorded_observer(entry) if recorded else registry.with_hold(entry, entry.make())
        if params is None:
            params = entry.params(dtype=dtype)
        elif isinstance(params, str):
            from .fitting import gainsfile

            path, params = params, gainsfile.read_params(params, entry, dtype=dtype)
            if recorded:
                _check_recorded_gains(path, params, entry.params(dtype=dtype), entry.name)
        elif isinstance(params, dict):
            set_up = [k for k in params if recorded and entry.setup is not None and k in entry.setup_fields]
            if set_up:  # they were checked, then replaced by the set-up without a word
                warnings.warn(
                    f"{'params' if len(set_up) > 1 else 'param'} {', '.join(set_up)} of {entry.name} "
                    f"{'are' if len(set_up) > 1 else 'is'} set from each recording's first samples "
                    f"(sensor to {entry.frame}): the values given are not used (to fix them, run the observer "
                    f"jaxatt.observers.registry.get({entry.name!r}).make() as your own, with its full params)",
                    stacklevel=3,
                )
                params = {k: v for k, v in params.items() if k not in set_up}
            params = _override(entry.params(dtype=dtype), params, entry.name)
        else:
            default = entry.params(dtype=dtype)
            if type(params) is not type(default):
                raise ValueError(
                    f"params of {entry.name} must be its {type(default).__name__} "
                    f"({', '.join(getattr(default, '_fields', ()))}), "
                    f"a dict of some of those fields or a gains-file path, got {type(params).__name__}"
                    + (f" ({', '.join(params._fields)})" if hasattr(params, "_fields") else "")
                )
        if entry.check is not None:
            _check_concrete(entry.check, params)
        return obs, params, entry, entry.name
    if isinstance(observer, Observer):
        if params is None:
            raise ValueError(
                f"params are required for your own observer {observer.name!r} (registered observers have defaults)"
            )
        if isinstance(params, str):  # a dict is taken as the params themselves (a pytree like any other)
            raise ValueError(
                f"params of your own observer {observer.name!r} must be its params pytree: a gains file needs them "
                "as the template, e.g. jaxatt.fitting.gainsfile.read_params(path, base=my_params)"
            )
        engine.check_finite_params(params, observer.name)  # a pytree of numbers, or one line naming the leaf
        if observer.hold is not None and observer.hold not in HOLDS:
            raise ValueError(
                f"observer {observer.name!r}: Observer.hold must be one of {', '.join(HOLDS)}, got {observer.hold!r}"
            )
        return observer, params, None, observer.name
    if hasattr(observer, "init") and hasattr(observer, "step"):
        return resolve_observer(
            Observer(
                observer.init,
                observer.step,
                getattr(observer, "name", "observer"),
                getattr(observer, "output", None),
                getattr(observer, "time_reversed", None),
                getattr(observer, "hold", None),
            ),
            params,
            dtype=dtype,
        )
    raise ValueError(
        f"observer must be a registered name ({', '.join(registry.names())}) or an "
        f"Observer(init, step), got {type(observer).__name__}"
    )


def check_own_observer(observer: Observer, params, entry, dtype, hold: str, acc: bool = True, mag: bool = True):
    """For an observer written by a user (``entry`` None, or one they registered): ValueError (one line) unless it
    keeps the engine's contract (:func:`jaxatt.engine.check_observer`, shapes only), checked on a sample with the
    given sensors."""
    if entry is not None and registry.builtin(entry):
        return
    z = jnp.zeros((3,), dtype)
    sample0 = ImuSample(jnp.zeros((), dtype), z, z if acc else None, z if mag else None)
    engine.check_observer(observer, params, sample0, 1.0, dtype, hold)


#: how many samples the front door runs a user's observer over before a batch run, to check its estimate
CHECK_SAMPLES = 200


def check_own_estimate(observer: Observer, params, entry, samples: ImuSample, dt: float, dtype, hold: str) -> None:
    """For an observer written by a user (``entry`` None, or one they registered): ValueError (one line) unless its
    estimate is a rotation (unit ``q``, or ``r`` a rotation matrix, to 1e-3) over the first :data:`CHECK_SAMPLES`
    ``samples`` (sample period ``dt`` s), as :func:`filter` requires: the batch runs (:func:`monte_carlo`,
    :func:`broad_score`, :func:`jaxatt.fit`) would otherwise score a non-rotation silently."""
    if entry is not None and registry.builtin(entry):
        return
    n = min(CHECK_SAMPLES, int(np.shape(samples.gyr)[0]))
    cut = lambda a: None if a is None else np.asarray(a)[:n]  # noqa: E731
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            filter(
                observer,
                cut(samples.gyr),
                cut(samples.acc),
                cut(samples.mag),
                dt=dt,
                params=params,
                hold=hold,
                dtype=dtype,
            )
    except FloatingPointError:
        return  # a non-finite estimate: the batch run names it where it happens
    except ValueError as e:
        raise ValueError(f"{e} (checked on the first {n} samples before the batch run)") from None


def _override(base, gains: dict, name: str):
    """``base`` (a Params NamedTuple) with the fields named in ``gains`` replaced (ValueError for other names)."""
    unknown = sorted(set(gains) - set(base._fields))
    if unknown:
        raise ValueError(
            f"params of {name}: no field {', '.join(map(repr, unknown))}; fields: {', '.join(base._fields)}"
        )
    values = {}
    for k, v in gains.items():
        try:
            values[k] = np.asarray(v, dtype=np.asarray(getattr(base, k)).dtype)
        except (TypeError, ValueError):
            raise ValueError(f"params of {name}: field {k!r} must be a number, got {v!r}") from None
    return base._replace(**values)


def _check_concrete(check, params):
    try:
        leaves = jax.tree_util.tree_leaves(params)
        concrete = all(not isinstance(x, jax.core.Tracer) for x in leaves)
    except Exception:  # noqa: BLE001
        concrete = False
    if concrete:
        check(params)


# ------------------------------------------------------------------------------------------------------------
# filter
# ------------------------------------------------------------------------------------------------------------
class Estimate(NamedTuple):
    """The estimates of :func:`filter` (numpy), one per sample.

    Fields:
        t: (T,) s.
        quat: (T, 4) (w, x, y, z), sensor to ``frame``.
        frame: the navigation frame of ``quat`` ("ENU", "NED", "NWU"; as given for your own observer).
        outputs: every field of the observer's output, (T, ...) numpy arrays (bias, diagnostics, ...), in the
            observer's own frame; row 0 is the start (``init``); a ``t`` output is ``t`` (float64 s) as given.
        observer: its name.
        params: the params used.
    """

    t: np.ndarray
    quat: np.ndarray
    frame: str
    outputs: Dict[str, np.ndarray]
    observer: str
    params: Any

    @property
    def rotation(self) -> np.ndarray:
        """(T, 3, 3) rotation matrices of ``quat`` (v_frame = R v_sensor)."""
        from . import so3

        return np.asarray(so3.quat_to_matrix(jnp.asarray(self.quat)))


def _pick_all(t, truth, out):
    return out


def _as_dict(out) -> Dict[str, Any]:
    if hasattr(out, "_asdict"):
        return {k: v for k, v in out._asdict().items() if v is not None}
    if isinstance(out, dict):
        return {k: v for k, v in out.items() if v is not None}
    return {"out": out}


def filter(
    observer: ObserverLike,
    gyr,
    acc=None,
    mag=None,
    *,
    dt=None,
    t=None,
    params=None,
    frame: str = "ENU",
    hold: Optional[str] = None,
    dtype=None,
    offline=False,
    gyr_unit: str = "rad/s",
    acc_unit: str = "m/s^2",
    time_unit: str = "s",
) -> Estimate:
    """Run an observer over one recording; T estimates for T samples (numpy).

    Args:
        observer: a registered name (:func:`jaxatt.observers.registry.names`, e.g. "robust", "mekf", "mahony"), set
            up from the first samples (start, references), or your own :class:`jaxatt.Observer`: it gets
            :class:`jaxatt.ImuSample` (t, gyr, acc, mag) in the sensor frame in ``init(params, first)`` and
            ``step(params, state, sample, dt)``, and its output carries the estimate as ``q`` (w, x, y, z) or
            ``r`` (3x3).
        gyr, acc, mag: (T, 3) sensor frame; rad/s, m/s^2 (specific force), any field unit. NaN marks a missing
            reading; acc / mag may be None when the observer does not need them, and mag None (a 6-axis
            recording) runs a registered 9D observer without a magnetometer (inclination only, with a warning),
            as a magnetometer whose every row is NaN. A registered observer set up
            from the first sample (start and references: mekf, nlo, nlio, complementary, ...) takes a sensor's
            first present reading when row 0 lacks it.
            Or the whole recording as one :class:`jaxatt.ImuSample` in place of ``gyr`` (what
            :func:`jaxatt.data.logs.load_log` returns): its ``t`` times it, so acc, mag, t and dt are not given
            (the unit arguments still describe it: load_log's is in rad/s, m/s^2 and s already).
        dt: constant sample period (s), or ``t``: (T,) timestamps (s), strictly increasing, or numpy
            datetime64 / timedelta64 (read in their own unit).
        params: gains (default for a registered observer: its shipped gains or defaults; a gains-file path is
            read; a dict such as ``{"beta": 0.05}`` replaces those fields of the defaults); required for your own
            observer.
        frame: navigation frame of the returned quaternions ("ENU", "NED", "NWU"; north is magnetic north, no
            declination applied): registered observers are converted to it; for your own observer it only labels
            the estimate (no conversion).
        hold: the input of each step (:data:`jaxatt.types.HOLDS`; default the observer's, "next" for your own:
            sample k updates the estimate to t_k, as ahrs and VQF do).
        dtype: "float32" / "float64" (default: from the input, see the module docstring).
        offline: False (default): the causal filter, estimate k from samples 0 ... k. True (or a
            :class:`jaxatt.smoothing.Offline`, or fusion params as a dict / :class:`jaxatt.smoothing.FusionParams`):
            forward-backward smoothing, estimate k from the whole recording: the observer also runs over the
            time-reversed recording (gyro negated) and both estimates of each sample are fused, heading and
            inclination weighted by the observer's gates (:mod:`jaxatt.smoothing`). ``quat`` is the fused
            estimate; ``outputs`` holds the forward pass's fields as without it, the backward pass's as
            ``backward_<field>`` (in forward time, bias in the forward gyro's sign), ``q_forward``, ``q_backward``
            (in ``frame``, as ``quat``) and the backward weights ``weight_inclination``, ``weight_heading``. The
            observer's navigation frame must be fixed by gravity and the magnetic field (every registered 9D
            observer); a 6D observer, or a recording without a magnetometer reading, is smoothed in inclination
            only (the heading is the forward pass's).
        gyr_unit, acc_unit, time_unit: the units ``gyr``, ``acc`` and ``t`` / ``dt`` come in
            (:data:`jaxatt.frames.GYR_UNITS` "rad/s", "deg/s", "dps", "mdps"; :data:`~jaxatt.frames.ACC_UNITS`
            "m/s^2", "g", "mg"; :data:`~jaxatt.frames.TIME_UNITS` "s", "ms", "us", "ns"), converted to rad/s,
            m/s^2 and s before anything else (:func:`jaxatt.frames.to_si`); the estimate's ``t`` is in s.
    Raises ValueError (one line naming the argument) on bad input, FloatingPointError when an estimate is not
    finite (the first row and time are named).
    """
    frame = frames.check_frame(frame)
    if isinstance(getattr(gyr, "samples", None), ImuSample):  # a Trial
        raise ValueError(f"gyr is a trial ({type(gyr).__name__}): pass its recording, trial.samples")
    if isinstance(gyr, tuple) and not isinstance(gyr, ImuSample) and any(isinstance(g, ImuSample) for g in gyr):
        raise ValueError(
            "gyr is a tuple holding an ImuSample (load_log(..., with_truth=True) returns (samples, truth)): pass the "
            "samples"
        )
    whole = isinstance(gyr, ImuSample)
    if whole:  # one recording (jaxatt.data.logs.load_log)
        timed = gyr.t is not None  # without timestamps, dt times it
        given = [k for k, v in (("acc", acc), ("mag", mag), ("t", t), ("dt", dt if timed else None)) if v is not None]
        if given:
            raise ValueError(
                f"gyr is a whole recording (an ImuSample with its own t, acc and mag): {', '.join(given)} cannot be "
                "given beside it" + (" (to time it by dt instead: samples._replace(t=None))" if "dt" in given else "")
            )
        gyr, acc, mag, t = gyr.gyr, gyr.acc, gyr.mag, gyr.t
    from . import smoothing

    spec = smoothing.resolve_offline(offline)
    time_factor = frames.unit_factor("time_unit", time_unit)
    gyr_a = frames.to_si(_vectors("gyr", gyr, None, True), "gyr_unit", gyr_unit)
    assert gyr_a is not None  # required: _vectors raised on None
    n = gyr_a.shape[0]
    if n < 2:
        raise ValueError(f"gyr must have at least 2 samples, got {n}")
    acc_a = frames.to_si(_vectors("acc", acc, n, False), "acc_unit", acc_unit)
    mag_a = _vectors("mag", mag, n, False)
    if time_factor != 1.0 and t is not None and np.asarray(t).dtype.kind in "mM":
        raise ValueError(
            f"time_unit {time_unit!r} applies to numeric t or dt: datetime64 / timedelta64 timestamps carry their own "
            "unit (leave time_unit 's')"
        )
    ts, per_step = _times(t, dt, n)
    ts = ts * time_factor if time_factor != 1.0 else ts
    _warn_implausible(gyr_a, acc_a, mag_a, ts, from_dt=t is None)
    dt_ = compute_dtype(gyr_a, acc_a, mag_a, dtype=dtype)
    obs, p, entry, name = resolve_observer(observer, params, dtype=dt_)
    p = recording_defaults(entry, params, p, first_step=float(ts[1] - ts[0]), field_norm=_first_field_norm(mag_a))
    if entry is not None:
        if "acc" in entry.needs and acc_a is None:
            if whole:
                raise ValueError(
                    f"observer {name!r} needs acc, and the recording has no accelerometer (its acc is None)"
                )
            raise ValueError(f"observer {name!r} needs acc (an array of shape (T, 3), m/s^2)")
        if "mag" in entry.needs and mag_a is None:  # as a magnetometer with no reading: inclination only
            warnings.warn(
                f"no magnetometer given: observer {name!r} runs without one (inclination only: its heading is not "
                "observable and drifts with the gyro)",
                stacklevel=2,
            )
            mag_a = np.full(gyr_a.shape, np.nan, gyr_a.dtype)
        if mag_a is not None and "mag" not in entry.needs:
            warnings.warn(
                f"observer {name!r} does not use the magnetometer: mag is ignored (its heading drifts; a 9D "
                "observer such as 'vqf' or 'robust' uses mag)",
                stacklevel=2,
            )
    engine.check_finite_params(p, name)
    hold = engine.hold_for(obs, hold, "next")
    check_own_observer(obs, p, entry, dt_, hold, acc=acc_a is not None, mag=mag_a is not None)
    if spec is None:  # the smoother sets both passes' starts itself (and knows which were missing)
        acc_a, mag_a = start_from_valid(entry, acc_a, mag_a, gyr_a, ts)
    # the scan runs over a few more samples (the last one repeated, the extra estimates dropped): recordings of
    # nearby lengths share one compiled program (estimate k of a causal scan depends on samples 0..k only)
    n_run = _run_length(n)
    t_run = np.concatenate([ts, ts[-1] + (ts[-1] - ts[-2]) * np.arange(1, n_run - n + 1)])

    def run_input(a):
        return None if a is None else jnp.asarray(np.concatenate([a, np.repeat(a[-1:], n_run - n, axis=0)]), dt_)

    samples = ImuSample(jnp.asarray(t_run, dt_), run_input(gyr_a), run_input(acc_a), run_input(mag_a))
    steps = np.diff(t_run)
    cast = np.asarray(steps, np.dtype(dt_))
    if not (np.all(np.isfinite(cast)) and np.all(cast > 0)):
        raise ValueError(
            f"the sample period ({float(np.min(steps)):.3g} s) is not a positive number in "
            f"{np.dtype(dt_).name} (it rounds to 0 or overflows): check dt / t, or run in float64"
        )
    item = {
        "samples": jax.tree_util.tree_map(lambda a: a[None], samples),
        "dt": jnp.asarray(np.concatenate([steps[:1], steps]) if per_step else steps[0], dt_)[None],
        "truth": None,
    }
    # the gains in the arithmetic's type, as the scan uses them: a weakly typed gain (jnp.asarray(0.1), a float)
    # then reuses the compiled program instead of compiling another
    p_run = engine.cast_floats(p, dt_)
    if spec is None:
        fn = engine.compiled(
            obs, engine.Recorded(n_run - 1, per_step), engine.records_of(_pick_all, 1), hold=hold, obs_dtype=dt_
        )
        out = jax.device_get(jax.tree_util.tree_map(lambda a: a[0, :n], fn(None, p_run, item).records))
        q = np.asarray(engine.estimate_q(out))
        extra: Dict[str, Any] = {}
    else:
        smoothing.check_time_reversed(obs, p_run, name)
        heading = ("mag" in entry.needs) if entry is not None else mag_a is not None
        sm = smoothing.compiled(
            obs,
            n_run - 1,
            per_step_dt=per_step,
            hold=hold,
            obs_dtype=dt_,
            trust=spec.trust,
            heading=heading,
            seed_bias=spec.seed_bias,
            keep_outputs=True,
            start_from_present=_starts_from_first_sample(entry),
        )
        fusion = engine.cast_floats(spec.fusion, dt_)
        # the backward pass starts at sample n - 1 (the recording's end), not at the padding's
        res = jax.device_get(jax.tree_util.tree_map(lambda a: a[0, :n], sm(p_run, fusion, item, np.array([n]))))
        out, q = res.forward, np.asarray(res.q)
        extra = {f"backward_{k}": np.asarray(v) for k, v in _as_dict(res.backward).items()}
        extra.update(
            q_forward=np.asarray(res.q_forward),
            q_backward=np.asarray(res.q_backward),
            weight_inclination=np.asarray(res.weight_inclination),
            weight_heading=np.asarray(res.weight_heading),
        )
    with np.errstate(invalid="ignore"):
        bad = ~(np.linalg.norm(q, axis=-1) > 1e-6)  # NaN / inf, or a quaternion collapsed to zero
    if bad.any():
        k = int(np.argmax(bad))
        raise FloatingPointError(
            f"{name}: the estimate is first non-finite (or a zero quaternion) at sample {k} (t = {ts[k]:.6g} s), "
            f"{int(bad.sum())} of {len(bad)} estimates{_pass_at_fault(extra, ts)}; check the inputs and gains"
        )
    from .data.logs import non_unit_row

    off = non_unit_row(q)  # | |q| - 1 | > logs.UNIT_TOLERANCE
    if off is not None:
        k = off[0]
        if entry is not None and registry.builtin(entry):  # jaxatt's observers normalise: overflow, not a bug of step
            raise FloatingPointError(
                f"{name}: the estimate at sample {k} (t = {ts[k]:.6g} s) is not a unit quaternion (norm "
                f"{off[1]:.6g}): the filter overflowed; check the inputs (units) and gains"
            )
        raise ValueError(
            f"{name}: the estimate at sample {k} (t = {ts[k]:.6g} s) is not a unit quaternion (norm {off[1]:.6g}); "
            "an observer's q must have norm 1 (normalise it in step) and its r must be a rotation matrix"
        )
    if entry is not None and entry.frame != frame:
        q = frames.change_frame(q, frame, entry.frame)
        for pass_q in ("q_forward", "q_backward"):  # the passes' estimates, in the frame of the fused one
            if pass_q in extra:
                extra[pass_q] = frames.change_frame(extra[pass_q], frame, entry.frame)
    if "backward_t" in extra and extra["backward_t"].shape == ts.shape:
        extra["backward_t"] = ts  # row k of the backward pass is its estimate at t_k (its own clock runs backwards)
    outputs = {k: np.asarray(v) for k, v in _as_dict(out).items()}
    # from estimate 1 on: estimate 0's fields that init's state does not hold are NaN by design (initial_output)
    nonfinite = [
        k for k, v in outputs.items() if np.issubdtype(v.dtype, np.floating) and not np.all(np.isfinite(v[1:]))
    ]
    if nonfinite:
        warnings.warn(
            f"{name}: the estimate is finite but the output {', '.join(nonfinite)} "
            f"{'has' if len(nonfinite) == 1 else 'have'} non-finite values",
            stacklevel=2,
        )
    if entry is not None and entry.advise is not None:
        advice = entry.advise(p, outputs, ImuSample(ts, gyr_a, acc_a, mag_a))
    else:
        advice = None
    if advice:
        warnings.warn(f"{name}: {advice}", stacklevel=2)
    # the sample times, exact (float32 rounds Unix times to 128 s)
    if "t" in outputs and outputs["t"].shape == ts.shape:
        outputs["t"] = ts
    outputs.update(extra)
    return Estimate(ts, q, frame, outputs, name, p)


# ------------------------------------------------------------------------------------------------------------
# BROAD
# ------------------------------------------------------------------------------------------------------------
class TrialScore(NamedTuple):
    """BROAD metric of one trial: RMSE (deg) of the total, heading and inclination errors over its scored samples."""

    total_rmse_deg: float
    heading_rmse_deg: float
    inclination_rmse_deg: float
    group: str


class GroupScore(NamedTuple):
    """Means over the trials of a group of the per-trial RMSEs (deg), and how many trials."""

    total_rmse_deg: float
    heading_rmse_deg: float
    inclination_rmse_deg: float
    n_trials: int


class BroadScore(NamedTuple):
    """:func:`broad_score`'s result: ``trials[name]`` (:class:`TrialScore`), ``groups[g]`` (:class:`GroupScore`,
    g in "undisturbed", "disturbed", "all"), the observer's name and the wall time (s)."""

    trials: Dict[str, TrialScore]
    groups: Dict[str, GroupScore]
    observer: str
    wall_s: float

    def to_dict(self) -> dict:
        return {
            "observer": self.observer,
            "wall_s": self.wall_s,
            "trials": {n: s._asdict() for n, s in self.trials.items()},
            "groups": {g: s._asdict() for g, s in self.groups.items()},
        }


def group_means(per_trial: Dict[str, TrialScore]) -> Dict[str, GroupScore]:
    """Mean per-trial metrics per group (BROAD's "undisturbed", "disturbed", then any other label of your own
    trials, :func:`jaxatt.data.logs.load_trial`) and over all trials ("all")."""
    from .data.broad import GROUPS, METRICS

    out = {}
    own = sorted({s.group for s in per_trial.values()} - set(GROUPS) - {"all"})
    for g in GROUPS + tuple(own) + ("all",):
        rows = [
            s for s in per_trial.values() if (g == "all" or s.group == g) and np.isfinite(s.total_rmse_deg)
        ]  # trials without ground truth (NaN) are not in the means
        if rows:
            total, heading, inclination = (float(np.mean([getattr(r, m) for r in rows])) for m in METRICS)
            out[g] = GroupScore(total, heading, inclination, len(rows))
    return out


def broad_score(
    observer: ObserverLike, params, trials: Sequence, *, hold: Optional[str] = None, dtype=None, offline=False
) -> BroadScore:
    """The BROAD metric of an observer on trials (all at once: padded, vmapped, one scan).

    Args:
        observer: a registered name (set up from each trial's first samples) or your own Observer (its estimate
            must be sensor-to-ENU, BROAD's frame).
        params: gains; None for a registered observer's shipped or default gains; a gains-file path is read; a
            dict replaces those fields of the defaults.
        trials: :class:`jaxatt.data.broad.Trial` s (:func:`jaxatt.data.broad.load`).
        hold: as in :func:`filter`.
        dtype: the filter's arithmetic ("float32" is the fast choice; default from the data).
        offline: score the offline (forward-backward smoothed) estimate instead of the causal one: True, a
            :class:`jaxatt.smoothing.Offline` or fusion params (as in :func:`filter`); the observer's name gets
            the suffix "+offline".
    Returns :class:`BroadScore`. Estimate k is scored against ``opt_quat[k]`` over the movement samples with
    finite truth (BROAD's metric, no offset fitted). A trial with no such sample has NaN metrics (no ground truth:
    nothing to score) and is left out of the group means; FloatingPointError when a scored trial's metric is not
    finite (the estimate diverged).
    """
    from .data import broad as B

    trials = B.check_trials(trials)
    unscored = [tr.name for tr in trials if not B.scored_samples(tr).any()]
    if 0 < len(unscored) < len(trials):  # none scored: said below
        warnings.warn(
            f"no scored sample (movement and a finite quat_true) in trial{'s' if len(unscored) > 1 else ''} "
            f"{', '.join(unscored)}: its metrics are NaN and the group means leave it out",
            stacklevel=2,
        )
    dt_ = compute_dtype(*trial_arrays(trials), dtype=dtype, what="trial data")
    obs, p, entry, name = resolve_observer(observer, params, dtype=dt_)
    engine.check_finite_params(p, name)
    trials = truth_in_frame_of(entry, trials)  # a registered NED / NWU observer: its estimate's frame
    as_given, trials = trials, trials_start_from_valid(entry, trials)  # the smoother sets its starts itself
    p, run_params = recording_defaults_per_trial(entry, params, p, trials)  # each trial its own, as filter does
    hold = engine.hold_for(obs, hold, "next")
    check_own_observer(obs, p, entry, dt_, hold)
    check_own_estimate(obs, p, entry, trials[0].samples, 1.0 / float(trials[0].rate_hz), dt_, hold)
    if entry is not None and "mag" not in entry.needs:
        warnings.warn(
            f"{name} does not use the magnetometer: its heading is not observable, so its total and heading errors "
            "include an arbitrary heading; compare inclination_rmse_deg",
            stacklevel=2,
        )
    elif entry is not None:
        six = [tr.name for tr in trials if not _valid_rows(np.asarray(tr.samples.mag)).any()]  # zero = missing
        if six:
            warnings.warn(
                f"trial{'s' if len(six) > 1 else ''} {', '.join(six)} ha{'ve' if len(six) > 1 else 's'} no "
                f"magnetometer reading: {name} runs on {'them' if len(six) > 1 else 'it'} without one (inclination "
                "only: the heading drifts with the gyro, and so do the total and heading errors)",
                stacklevel=2,
            )
    from . import smoothing

    spec = smoothing.resolve_offline(offline)
    p_run = engine.cast_floats(p, dt_)  # as in filter: weakly typed gains reuse the compiled program
    t0 = time.perf_counter()
    if spec is None:
        res = B.score(obs, p_run, trials, hold=hold, dtype=dt_, run_params=run_params)
    else:
        smoothing.check_time_reversed(obs, p_run, name)
        heading = ("mag" in entry.needs) if entry is not None else True
        metric = smoothing.broad_metric_fn(
            obs,
            as_given,
            hold=hold,
            dtype=dt_,
            offline=spec,
            heading=heading,
            start_from_present=_starts_from_first_sample(entry),
            run_params=run_params,
        )
        summary = jax.device_get(metric(p_run, engine.cast_floats(spec.fusion, dt_)))  # not jitted: see there
        res = {tr.name: {m: float(summary[m][i]) for m in B.METRICS} for i, tr in enumerate(trials)}
        name = f"{name}+offline"
    wall = time.perf_counter() - t0
    per = {}
    for i, tr in enumerate(trials):
        m = res[tr.name]
        if not np.any(B.scored_samples(tr)):  # documented: no ground truth to score against -> NaN, not in the means
            m = {k: float("nan") for k in m}
        elif not all(np.isfinite(v) for v in m.values()):
            own = engine.with_run_params(p_run, {k: v[i] for k, v in (run_params or {}).items()}, dt_)
            where = _where_nonfinite(obs, own, tr, hold, dt_, spec)
            raise FloatingPointError(
                f"{name}: the BROAD metric of trial {tr.name} is not finite ({m}); "
                + (where or "the estimate diverged (check the gains)")
            )
        per[tr.name] = TrialScore(
            m["total_rmse_deg"], m["heading_rmse_deg"], m["inclination_rmse_deg"], tr.group or B.group_of(tr.name)
        )
    if all(np.isnan(v.total_rmse_deg) for v in per.values()):
        warnings.warn(
            f"{name}: no trial has a scored sample (movement with finite ground truth): every metric is NaN and "
            "there are no group means",
            stacklevel=2,
        )
    return BroadScore(per, group_means(per), name, wall)


def _pass_at_fault(passes: dict, ts) -> str:
    """For a non-finite smoothed estimate: which pass went first, and where (the backward pass runs from the
    recording's end: its first non-finite estimate is the last bad row in forward time)."""
    if "q_forward" not in passes:
        return ""
    with np.errstate(invalid="ignore"):
        fwd, bwd = (~(np.linalg.norm(passes[k], axis=-1) > 1e-6) for k in ("q_forward", "q_backward"))
    if fwd.any():
        k = int(np.argmax(fwd))
        return f" (the forward pass from sample {k}, t = {ts[k]:.6g} s)"
    if bwd.any():
        k = len(bwd) - 1 - int(np.argmax(bwd[::-1]))
        return (
            f" (the backward pass, run from the recording's end, from sample {k}, t = {ts[k]:.6g} s; the forward "
            "pass is finite)"
        )
    return ""


def _where_nonfinite(obs, params, trial, hold: str, dtype, offline) -> str:
    """Where :func:`filter` finds the first non-finite estimate of ``trial`` ("the estimate is first non-finite ...
    at sample k (t = ... s) ..."), or "" (only run once a score was not finite: it compiles the one-recording
    program)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # said already, by the batch
            filter(obs, trial.samples, params=params, hold=hold, dtype=dtype, offline=offline or False)
    except FloatingPointError as e:
        return str(e).split(": ", 1)[-1]
    except Exception:  # noqa: BLE001 - a second opinion only: the score's own message stands without it
        return ""
    return ""


# ------------------------------------------------------------------------------------------------------------
# Monte Carlo on a simulated AHRS scenario
# ------------------------------------------------------------------------------------------------------------
def ahrs_scenario(
    *,
    gyro_noise_std: float = 1e-3,
    acc_noise_std: float = 0.05,
    mag_noise_std: float = 0.3,
    gyro_bias=(0.01, -0.01, 0.005),
    mag_ref_enu=(0.0, 20.0, -40.0),
    rate_scale: float = 1.0,
    mix_prob: float = 0.0,
):
    """A simulated IMU in ENU for observers made for recorded data: gyro (rad/s, constant bias + white noise per
    sample), accelerometer measuring the specific force (+9.81 m/s^2 "up" at rest, white noise m/s^2),
    magnetometer (uT; default 44.7 uT field pointing north and down, white noise uT), the rotation rates of the
    NLIO paper's Section 5 (``rate_scale`` times them), true start = identity (sensor axes = ENU). North is the
    field's horizontal direction, as in every recorded-data set-up (TRIAD)."""
    from .sim import ahrs

    given = dict(gyro_noise_std=gyro_noise_std, acc_noise_std=acc_noise_std, mag_noise_std=mag_noise_std)
    given.update(mix_prob=mix_prob, rate_scale=rate_scale)
    for name, v in given.items():  # numbers (a string or a complex one failed deep inside numpy)
        if isinstance(v, (str, bytes, bool, complex, np.complexfloating)) or not isinstance(v, (int, float, np.number)):
            raise ValueError(f"{name} must be a real number, got {v!r}")
    for name, v in (("gyro_bias", gyro_bias), ("mag_ref_enu", mag_ref_enu)):
        if v is None or np.asarray(v).dtype.kind not in "iuf":
            raise ValueError(f"{name} must be 3 real numbers, got {v!r}")
    try:
        return ahrs.AhrsScenario.make(
            rates=ahrs.nlio_rates(rate_scale),
            acc_ref_nav=(0.0, 0.0, 9.81),
            mag_ref_nav=mag_ref_enu,
            gyro_bias=gyro_bias,
            gyro_noise_std=gyro_noise_std,
            acc_noise_std=acc_noise_std,
            mag_noise_std=mag_noise_std,
            mix_prob=mix_prob,
        )
    except ValueError as e:  # the scenario's check names its own fields: say the arguments given here
        msg = str(e).replace(
            "acc_ref_nav and mag_ref_nav must be non-zero and not parallel",
            "mag_ref_enu must be non-zero and not vertical (parallel to gravity)",
        )
        raise ValueError(msg.replace("mag_ref_nav", "mag_ref_enu")) from None


def ahrs_errors(truth, out):
    """Errors of an AHRS estimate against the simulated truth: roll, pitch, yaw (deg, ZYX, wrapped) and, when the
    output has ``bias``, the gyro-bias error (deg/s)."""
    from . import so3

    r = engine.estimate_r(out)
    roll, pitch, yaw = (jnp.rad2deg(e) for e in so3.euler_error_zyx(truth.r.astype(r.dtype), r))
    e = {"roll": roll, "pitch": pitch, "yaw": yaw}
    b = getattr(out, "bias", None) if not isinstance(out, dict) else out.get("bias")
    if b is not None and jnp.shape(b) == (3,):
        e["bias"] = jnp.rad2deg(truth.gyro_bias.astype(r.dtype) - b)
    return e


@functools.lru_cache(maxsize=32)
def _estimating_in_enu(obs: Observer, frame: str, name: str) -> Observer:
    """``obs`` with its estimate (the ``q`` / ``r`` of its outputs) re-expressed from the navigation frame
    ``frame`` in ENU, the frame of the simulated truth of :func:`ahrs_scenario` (cached: one program per frame)."""
    if obs.output is None:
        raise ValueError(
            f"observer {name!r} estimates in {frame} and has no output(params, state): the simulated IMU of "
            "jaxatt.monte_carlo is in ENU; give its Observer an output function to have its estimate converted"
        )
    c = frames.frame_rotation("ENU", frame)

    def in_enu(out):
        new = {}
        for field, fn in (
            ("q", lambda q: so3.quat_multiply(so3.matrix_to_quat(jnp.asarray(c, q.dtype)), q)),
            ("r", lambda r: jnp.asarray(c, r.dtype) @ r),
        ):
            v = out.get(field) if isinstance(out, dict) else getattr(out, field, None)
            if v is not None:
                new[field] = fn(v)
        return {**out, **new} if isinstance(out, dict) else out._replace(**new)

    def step(p, s, u, dt):
        s, out = obs.step(p, s, u, dt)
        return s, in_enu(out)

    output = obs.output
    return obs._replace(step=step, output=lambda p, s: in_enu(output(p, s)))


def monte_carlo(
    observer: ObserverLike,
    params=None,
    *,
    runs: int = 100,
    duration: float = 60.0,
    dt: float = 0.01,
    seed: int = 0,
    scenario=None,
    window_start: Optional[float] = None,
    hold: Optional[str] = None,
    dtype=None,
    chunk: int = 250,
    trace_every: int = 0,
    progress=None,
    devices=None,
    previous=None,
    on_chunk=None,
    out=None,
    resume: bool = False,
    overwrite: bool = False,
):
    """Monte Carlo of an observer (registered or your own) on a simulated AHRS (:func:`ahrs_scenario` by default,
    ENU): ``runs`` runs of ``duration`` s at 1/``dt`` Hz, run k from key fold_in(PRNGKey(seed), k), metrics reduced
    as the scan runs (:func:`jaxatt.montecarlo.monte_carlo`): per run the mean / max / final angle error (deg)
    over t >= ``window_start`` (default: the last third) and the std of every error of :func:`ahrs_errors`.
    ``devices``: None (default) splits the runs of each chunk over every visible device, an int over that many
    (1: one device); the result does not depend on it beyond rounding (:func:`jaxatt.montecarlo.monte_carlo`).
    Returns a :class:`jaxatt.montecarlo.MonteCarloResult`; FloatingPointError names the first run whose metrics
    are not finite. Interrupted (KeyboardInterrupt), it returns the runs finished so far with ``complete=False``
    and a warning: pass that result as ``previous`` to a call with the same arguments to run only the rest.
    ``on_chunk(result_so_far)`` is called after each chunk of runs.

    ``out`` (a ``.npz`` path): the runs are saved there after every chunk, so a killed process loses at most one
    chunk. ``resume=True`` continues the runs saved in ``out`` (a call with the same observer, params, scenario,
    duration, dt, seed, window, hold, precision and trace_every; more ``runs`` extend them) and runs only the
    rest: a complete file is returned without running. Without a file it starts afresh. An existing ``out`` is
    otherwise refused unless ``overwrite=True``. :func:`jaxatt.montecarlo.load_result` reads the file back."""
    from . import montecarlo as mc

    if resume and overwrite:
        raise ValueError(
            "resume=True and overwrite=True: pass one (resume continues the runs in out, overwrite replaces them)"
        )
    if (resume or overwrite) and out is None:
        raise ValueError(f"{'resume' if resume else 'overwrite'}=True needs out (the .npz file of the runs)")
    if resume and previous is not None:
        raise ValueError("previous and resume=True both give the runs done: pass one")

    if dtype is None and not jax.config.values["jax_enable_x64"] and params is not None and not isinstance(params, str):
        compute_dtype(*(a for a in jax.tree_util.tree_leaves(params) if hasattr(a, "dtype")), what="params")

    dt_ = compute_dtype(dtype=dtype) if dtype is not None else np.dtype(jnp.result_type(float))
    if isinstance(observer, (str, registry.Entry)) and not registry.get(observer).recorded:
        study = registry.get(observer).name
        raise ValueError(
            f"observer {study!r} runs on its paper's scenario, not the AHRS one: `jaxatt reproduce {study}` / "
            f"`jaxatt simulate --observer {study}`, or jaxatt.studies.get({study!r}) from Python"
        )
    obs, p, entry, name = resolve_observer(observer, params, dtype=dt_)
    engine.check_finite_params(p, name)
    if entry is not None and entry.frame != "ENU":  # a registered NED / NWU observer: scored in the truth's ENU
        obs = _estimating_in_enu(obs, entry.frame, name)
    hold = engine.hold_for(obs, hold, "next")
    check_own_observer(obs, p, entry, dt_, hold)
    if entry is not None and "mag" not in entry.needs:
        from .studies.ahrs import SIX_D_NOTE

        warnings.warn(SIX_D_NOTE.format(name=name), stacklevel=2)
    from .sim.ahrs import AhrsScenario

    scn = scenario if scenario is not None else ahrs_scenario()
    if not isinstance(scn, AhrsScenario):
        raise ValueError(f"scenario must be an AHRS scenario (jaxatt.api.ahrs_scenario(...)), got {type(scn).__name__}")
    duration = mc.check_duration(duration)
    ws = check_window_start(2.0 * duration / 3.0 if window_start is None else window_start, duration)
    if entry is None or not registry.builtin(entry):
        step = mc.check_dt(dt)
        n_check = max(1, min(CHECK_SAMPLES - 1, int(round(duration / step))))
        log, _ = mc.simulate_log(scn, duration=n_check * step, dt=step, seed=int(seed) if isinstance(seed, int) else 0)
        check_own_estimate(obs, p, entry, log, step, dt_, hold)
    if out is not None:
        from . import io

        out = io.check_output_path(out, "out", suffixes=(".npz",))
        spec = _runs_spec(
            name,
            p,
            scn,
            duration,
            mc.check_dt(dt),
            check_seed(seed),
            ws,
            hold,
            dt_,
            mc.check_count("trace_every", trace_every),
            programs=_programs(obs, p, scn, mc.check_dt(dt), dt_),
        )
        if resume:
            previous = _saved_runs(out, spec, name, runs)
        # several processes: process 0 writes the file, and the others must not find its first chunk and stop
        elif io.is_main_process() and out.exists() and not io.is_special(out) and not overwrite:
            raise ValueError(
                f"out {out}: exists; pass resume=True to continue its runs or overwrite=True to replace them"
            )
        user_on_chunk = on_chunk
        if user_on_chunk is not None and not callable(user_on_chunk):
            raise ValueError(f"on_chunk must be a function or None, got {user_on_chunk!r}")

        def on_chunk(result):
            if io.is_main_process():  # several processes: process 0 writes the file
                mc.save_runs(out, spec, {name: result})
            if user_on_chunk is not None:
                user_on_chunk(result)

    res = mc.monte_carlo(
        scn,
        obs,
        p,
        runs=runs,
        duration=duration,
        dt=dt,
        seed=seed,
        errors_fn=ahrs_errors,
        window_start=ws,
        hold=hold,
        chunk=chunk,
        trace_every=trace_every,
        dtype=dt_,
        progress=progress,
        devices=devices,
        previous=previous,
        on_chunk=on_chunk,
    )
    bad = res.first_nonfinite()
    if bad:
        raise FloatingPointError(f"{name}: {bad} (seed {seed})")
    if not res.complete:
        warnings.warn(
            f"{name}: interrupted after {len(res.run_indices)} of {runs} runs (result.complete is False): pass this "
            "result as previous= to the same call to run the rest",
            stacklevel=2,
        )
    return res


def program_fingerprint(fn, *args) -> str:
    """A short hash of what ``fn(*args)`` computes: its jaxpr (the traced program, so the code of every function
    it calls and the numbers it closes over, whatever their names) and the values of its constants. Two calls that
    compute the same agree; an edited function, or another JAX version, gives another."""
    import hashlib
    import re

    closed = jax.make_jaxpr(fn)(*args)
    h = hashlib.sha256(re.sub(r" at 0x[0-9a-fA-F]+", "", str(closed.jaxpr)).encode())
    for c in closed.consts:
        c = np.asarray(c)
        h.update(f"{c.dtype}{c.shape}".encode() + c.tobytes())
    return h.hexdigest()[:16]


def _programs(obs, params, scenario, dt: float, dtype) -> dict:
    """Fingerprints (:func:`program_fingerprint`) of the scenario's first simulated step (truth and sensors) and
    of the observer's init and step on its samples: a resumed Monte Carlo refuses runs of edited functions (a
    user's step or trajectory of the same name)."""
    noise = jnp.zeros((scenario.n_channels,), dtype)

    def first_samples(scn):
        r1 = scn.propagate(scn.r0, 0.0, dt)
        return scn.sample(scn.truth_at(scn.r0, 0.0), noise, dt), scn.sample(scn.truth_at(r1, dt), noise, dt)

    s0, s1 = jax.eval_shape(first_samples, scenario)
    p, step = engine.cast_floats(params, dtype), jnp.asarray(dt, dtype)
    s0, s1 = (jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape, dtype), s) for s in (s0, s1))
    return {
        "scenario": program_fingerprint(first_samples, scenario),
        "observer": program_fingerprint(lambda p, a, b: obs.step(p, obs.init(p, a), b, step), p, s0, s1),
    }


def _runs_spec(
    name, params, scenario, duration, dt, seed, window_start, hold, dtype, trace_every, programs=None
) -> str:
    """What must match for the runs saved by :func:`monte_carlo` (``out``) to be continued (runs aside)."""
    import json
    import re

    def tree(x):
        leaves, treedef = jax.tree_util.tree_flatten(x)
        # an object's repr in the structure holds its address, another in every process: not part of the call
        return {
            "tree": re.sub(r" at 0x[0-9a-fA-F]+", "", str(treedef)),
            "leaves": [np.asarray(v).tolist() for v in leaves],
        }

    spec = {
        "observer": name,
        "params": tree(params),
        "scenario": tree(scenario),
        "duration": float(duration),
        "dt": float(dt),
        "seed": int(seed),
        "window_start": float(window_start),
        "hold": hold,
        "dtype": str(np.dtype(dtype)),
        "trace_every": int(trace_every),
        "programs": programs,
    }
    return json.dumps(spec, sort_keys=True, default=str)


def _saved_runs(out, spec: str, name: str, runs: int):
    """The runs saved in ``out`` by an earlier call with the same ``spec`` (None when there is no file)."""
    from . import io
    from . import montecarlo as mc

    if io.is_special(out):  # /dev/null: nothing was kept
        return None
    saved_spec, saved = mc.load_runs(out, "resume", again="pass overwrite=True instead of resume to replace it")
    if not saved:
        return None
    differ = mc.spec_differences(saved_spec, spec, {"programs": mc.ANY})  # files of 0.2.0 hold no programs
    if differ or list(saved) != [name]:
        said = [
            f"the {k.split('.', 1)[1]}'s code (an edited function, or another jax version)"
            if k.startswith("programs.")
            else k
            for k in differ
        ]
        raise ValueError(
            f"resume: {out} holds runs of another call ({', '.join(said) or 'the observer'} "
            f"{'differ' if len(said) > 1 else 'differs'}); call "
            "with the same arguments, or pass overwrite=True instead"
        )
    res = saved[name]
    idx = np.asarray(res.run_indices)
    if idx.size and idx.max() >= runs:
        raise ValueError(f"resume: {out} holds runs up to run {int(idx.max())}: ask for runs >= {int(idx.max()) + 1}")
    return res._replace(complete=len(idx) == runs)
