"""Excitation / observability measures of Trumpf, Mahony, Hamel, Lageman (IEEE TAC 2012), Sections III-IV, for a
scenario or a log.

For directions v: R -> S^2 and a window [t, t + T] (T = ``window``, s):

* ``lambda2``: λ2( ∫ Σ_v v v^T dτ ), the second largest eigenvalue (for a 3x3 matrix also the second
  smallest), over the collection the observer's error dynamics see (Proposition 4.6): the inertial
  references å_i of complementary measurements and the inertial-frame compatible measurements b_j.
  Persistent excitation, Definition 4.1 eq. (11): inf_t lambda2 > 0 for some window. Over [t0, t]
  (:func:`sufficient_excitation`) it is Definition 3.3 eq. (4).
* ``lambda_min_projector``: λmin( ∫ Σ_v q_v (I - v v^T) dτ ), eq. (12) of Lemma 4.2 (eq. (5) of Lemma 3.4
  over [t0, t]); q_v are the observer gains (k_i then l_j) or 1. With unit gains Lemma A.1 gives
  lambda_min_projector = n T - λ1 and lambda2 <= lambda_min_projector <= 2 lambda2.
* ``lambda2_complementary`` + ``compatible_term`` = ``condition``: condition (13) of Theorem 4.3 (condition
  (6) of Proposition 3.6 over [t0, t]): λ2( ∫ Σ_i å_i å_i^T ) + || ∫ Σ_j (Omega x b̊_j + d b̊_j/dτ) dτ ||,
  in terms of inputs only (references and angular velocity).

All values are integrals (units: s for the λ's; rad for the compatible term) and grow with the window;
divide by ``t_end - t_start`` for a rate in [0, n] (what :func:`plot_excitation` shows by default).

Numerics (readings): integrals over the samples by the trapezoid rule (``rule="left"``: rectangle rule,
exact for zero-order-hold signals), from cumulative sums in float64 numpy (offline post-processing; no loop
over time). ∫ d b̊/dτ is the telescoped difference of the sampled b̊ over the window (a sampled log cannot
tell a jump from a fast change, so jumps of a switching b̊ count, unlike the a.e. derivative in (6)).
Omega is the gyro sample (minus ``gyro_bias`` if given). Directions are normalised; a sample with a
non-finite or zero vector contributes nothing (a missing reading). On a log (:func:`excitation_from_samples`) a
constant reference counts only at the samples where its sensor's reading is valid (finite, non-zero). A gap in the
timestamps longer than ``max_gap`` (default 10 x the median sample interval) contributes nothing: no data is not
excitation.
"""

from __future__ import annotations

import math
from typing import Any, Dict, NamedTuple, Optional, Sequence

import numpy as np

__all__ = [
    "Excitation",
    "excitation",
    "sufficient_excitation",
    "excitation_from_samples",
    "excitation_of_scenario",
    "plot_excitation",
    "valid_readings",
    "gap_threshold",
]


class Excitation(NamedTuple):
    """Excitation measures over windows [t_start, t_end] (all numpy arrays of shape (W,), eigenvalues (W, 3)).

    Fields:
        t_start, t_end: window bounds (s) (t_end is the first sample at or after t_start + window).
        lambda2: λ2 of ∫ Σ v v^T over {å_i} ∪ {b_j} (eq. 11 / eq. 4), s.
        lambda_min_projector: λmin of ∫ Σ q (I - v v^T) (eq. 12 / eq. 5), s (times the gain unit).
        lambda2_complementary: λ2 of ∫ Σ_i å_i å_i^T, first term of (13) / (6), s.
        compatible_term: || ∫ Σ_j (Omega x b̊_j + d b̊_j/dτ) ||, second term of (13) / (6), rad.
        condition: lambda2_complementary + compatible_term, the left side of (13) / (6).
        eigenvalues: (W, 3) eigenvalues of ∫ Σ v v^T, descending (λ1 >= λ2 >= λ3), s.
    """

    t_start: np.ndarray
    t_end: np.ndarray
    lambda2: np.ndarray
    lambda_min_projector: np.ndarray
    lambda2_complementary: np.ndarray
    compatible_term: np.ndarray
    condition: np.ndarray
    eigenvalues: np.ndarray


# ------------------------------------------------------------------------------------------------------
# Inputs
# ------------------------------------------------------------------------------------------------------
def _time(t) -> np.ndarray:
    t_dtype = getattr(t, "dtype", None)
    t = np.asarray(t, float)
    if t.ndim != 1 or t.size < 2:
        raise ValueError(f"t must be a 1-D array of at least two sample times, got shape {t.shape}")
    from .data.logs import check_timestamps

    check_timestamps(t, "t", t_dtype)
    return t


def _directions(v, T: int, name: str):
    """(T, n, 3) unit directions and (T, n) validity; ``v`` (T, n, 3), constant (n, 3), one time-varying direction
    (T, 3) (one row per sample, T > 3: read as (T, 1, 3), not as T constant directions), or None (n = 0)."""
    if v is None:
        return np.zeros((T, 0, 3)), np.zeros((T, 0), bool)
    v = np.asarray(v, float)
    if v.ndim == 2 and v.shape == (T, 3) and T > 3:
        v = v[:, None, :]
    elif v.ndim == 2 and v.shape[-1] == 3:
        v = np.broadcast_to(v, (T,) + v.shape)
    if v.ndim != 3 or v.shape[0] != T or v.shape[2] != 3:
        raise ValueError(f"{name} must have shape (T, n, 3) with T = {T} (or (n, 3) if constant), got {v.shape}")
    with np.errstate(invalid="ignore"):
        n = np.linalg.norm(v, axis=-1)
    ok = np.isfinite(n) & (n > 0)
    u = np.where(ok[..., None], v / np.where(ok, n, 1.0)[..., None], 0.0)
    return u, ok


def valid_readings(reading) -> np.ndarray:
    """(T,) bool: the rows of a (T, 3) sensor reading that are finite and non-zero (the others are missing)."""
    r = np.asarray(reading, float)
    with np.errstate(invalid="ignore"):
        return np.all(np.isfinite(r), axis=-1) & (np.linalg.norm(np.nan_to_num(r), axis=-1) > 0)


def gap_threshold(t, max_gap: Optional[float] = None) -> float:
    """The longest sample interval (s) that counts as data: ``max_gap``, default 10 x the median interval."""
    if max_gap is None:
        return 10.0 * float(np.median(np.diff(np.asarray(t, float))))
    if not (math.isfinite(float(max_gap)) and max_gap > 0):
        raise ValueError(f"max_gap must be a finite positive number of seconds, got {max_gap}")
    return float(max_gap)


def _intervals(t: np.ndarray, max_gap: Optional[float]) -> np.ndarray:
    """(T-1,) sample intervals (s), zero for a gap longer than :func:`gap_threshold`."""
    d = np.diff(t)
    return np.where(d <= gap_threshold(t, max_gap), d, 0.0)


def _cumulative(f: np.ndarray, d: np.ndarray, rule: str) -> np.ndarray:
    """C[k] = ∫_{t0}^{t_k} f (trapezoid or left rectangle over the intervals ``d``), C[0] = 0; f (T, ...)."""
    dt = d.reshape((-1,) + (1,) * (f.ndim - 1))
    inc = 0.5 * (f[1:] + f[:-1]) * dt if rule == "trapezoid" else f[:-1] * dt
    return np.concatenate([np.zeros((1,) + f.shape[1:]), np.cumsum(inc, axis=0)], axis=0)


def _integrands(t, ref_inertial, inertial_meas, ref_body, gyr, gains, rule, max_gap=None):
    T = t.size
    d = _intervals(t, max_gap)
    a, ok_a = _directions(ref_inertial, T, "ref_inertial")
    b, ok_b = _directions(inertial_meas, T, "inertial_meas")
    n1, n2 = a.shape[1], b.shape[1]
    if n1 + n2 < 1:
        raise ValueError("at least one reference direction is needed (ref_inertial or inertial_meas)")
    q = np.ones(n1 + n2) if gains is None else np.asarray(gains, float).reshape(-1)
    if q.shape != (n1 + n2,) or not np.all(np.isfinite(q)) or np.any(q < 0):
        raise ValueError(f"gains must be {n1 + n2} finite non-negative numbers (k_i then l_j), got {gains}")
    v = np.concatenate([a, b], axis=1)  # (T, n, 3): the collection {å_i} ∪ {b_j}
    w = np.concatenate([ok_a, ok_b], axis=1).astype(float)
    vv = np.einsum("tni,tnj->tnij", v, v)
    S = np.einsum("tn,tnij->tij", w, vv)
    P = np.einsum("tn,n->t", w, q)[:, None, None] * np.eye(3) - np.einsum("tn,n,tnij->tij", w, q, vv)
    A = np.einsum("tn,tnij->tij", ok_a.astype(float), vv[:, :n1])
    # Compatible term of (13): Omega x b̊_j integrated, plus the telescoped increments of b̊_j.
    c = np.zeros((T, 3))
    D = np.zeros((T, 3))
    if n2:
        if ref_body is None or gyr is None:
            raise ValueError("condition (13) with compatible measurements needs ref_body (b̊_j) and gyr (Omega)")
        br, ok_br = _directions(ref_body, T, "ref_body")
        if br.shape[1] != n2:
            raise ValueError(f"ref_body must have {n2} directions like inertial_meas, got {br.shape[1]}")
        g = np.asarray(gyr, float)
        if g.shape != (T, 3):
            raise ValueError(f"gyr must have shape ({T}, 3), got {g.shape}")
        ok_g = np.all(np.isfinite(g), axis=-1)
        wc = (ok_br & ok_g[:, None]).astype(float)
        c = np.einsum("tn,tni->ti", wc, np.cross(np.where(ok_g[:, None], g, 0.0)[:, None, :], br))
        step_ok = (ok_br[1:] & ok_br[:-1]).astype(float)
        D = np.concatenate([np.zeros((1, 3)), np.cumsum(np.einsum("tn,tni->ti", step_ok, br[1:] - br[:-1]), 0)], 0)
    return _cumulative(S, d, rule), _cumulative(P, d, rule), _cumulative(A, d, rule), _cumulative(c, d, rule) + D


def _measures(t, starts, ends, CS, CP, CA, Cc) -> Excitation:
    def win(C):
        M = C[ends] - C[starts]
        return 0.5 * (M + np.swapaxes(M, -1, -2)) if M.ndim == 3 else M

    ev = np.linalg.eigvalsh(win(CS))[:, ::-1]  # descending
    lam_p = np.linalg.eigvalsh(win(CP))[:, 0]
    lam_a = np.linalg.eigvalsh(win(CA))[:, 1]
    comp = np.linalg.norm(win(Cc), axis=-1)
    return Excitation(t[starts], t[ends], ev[:, 1], lam_p, lam_a, comp, lam_a + comp, ev)


def _check_rule(rule):
    if rule not in ("trapezoid", "left"):
        raise ValueError(f"rule must be 'trapezoid' or 'left', got {rule!r}")


# ------------------------------------------------------------------------------------------------------
# Public API
# ------------------------------------------------------------------------------------------------------
def excitation(
    t,
    *,
    window: float,
    ref_inertial=None,
    inertial_meas=None,
    ref_body=None,
    gyr=None,
    gains=None,
    stride: int = 1,
    rule: str = "trapezoid",
    max_gap: Optional[float] = None,
) -> Excitation:
    """Persistent-excitation measures (Definition 4.1, Lemma 4.2, condition (13)) over sliding windows.

    Args:
        t: (T,) sample times (s), strictly increasing.
        window: window length δ (s); windows start at every ``stride``-th sample and end at the first sample
            at or after t + window; windows running past the log are dropped.
        ref_inertial: å_i, (T, n1, 3) or constant (n1, 3), inertial frame; None if n1 = 0. One time-varying
            direction may be given as (T, 3) (one row per sample).
        inertial_meas: compatible measurements b_j = R b̊_j, (T, n2, 3), inertial frame; None if n2 = 0.
        ref_body: b̊_j, (T, n2, 3) or constant (n2, 3), body frame (needed when n2 > 0); (T, 3) as above.
        gyr: (T, 3) angular velocity Omega (rad/s, body) (needed when n2 > 0).
        gains: (n1 + n2,) q of eq. (12) (k_i then l_j); default 1.
        max_gap: a sample interval longer than this (s) contributes nothing (default 10 x the median interval).
    Returns:
        :class:`Excitation` over the W window start times.
    """
    t = _time(t)
    w = float(window)
    if not (math.isfinite(w) and w > 0):
        raise ValueError(f"window must be a finite positive number of seconds, got {window}")
    step = float(np.median(np.diff(t)))
    if w < step:
        raise ValueError(f"window {w:g} s is shorter than the sample interval ({step:g} s)")
    stride = int(stride)
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    _check_rule(rule)
    starts = np.arange(0, t.size, stride)
    ends = np.searchsorted(t, t[starts] + w * (1.0 - 1e-9), side="left")
    keep = ends < t.size
    if not np.any(keep):
        raise ValueError(f"window {w} s is longer than the log ({t[-1] - t[0]} s)")
    C = _integrands(t, ref_inertial, inertial_meas, ref_body, gyr, gains, rule, max_gap)
    return _measures(t, starts[keep], ends[keep], *C)


def sufficient_excitation(
    t,
    *,
    ref_inertial=None,
    inertial_meas=None,
    ref_body=None,
    gyr=None,
    gains=None,
    rule: str = "trapezoid",
    max_gap: Optional[float] = None,
) -> Excitation:
    """Sufficient-excitation measures (Definition 3.3 eq. (4), Lemma 3.4 eq. (5), condition (6)) over the
    growing windows [t_0, t_k], k = 1..T-1; same arguments as :func:`excitation`."""
    t = _time(t)
    _check_rule(rule)
    ends = np.arange(1, t.size)
    C = _integrands(t, ref_inertial, inertial_meas, ref_body, gyr, gains, rule, max_gap)
    return _measures(t, np.zeros_like(ends), ends, *C)


def excitation_from_samples(
    samples,
    *,
    window: Optional[float] = None,
    params=None,
    imu_fields: Sequence[str] = ("acc", "mag"),
    gains=None,
    gyro_bias=None,
    stride: int = 1,
    rule: str = "trapezoid",
    max_gap: Optional[float] = None,
) -> Excitation:
    """Excitation of a log: a stacked :class:`jaxatt.types.VectorSample` or
    :class:`jaxatt.types.ImuSample` (constant references ``params.ref_inertial`` in the order of
    ``imu_fields``; reference i counts only at the samples where reading ``imu_fields[i]`` is finite and
    non-zero). References a VectorSample does not carry come from ``params``. ``window=None`` gives
    :func:`sufficient_excitation` (from the first sample); otherwise :func:`excitation`.
    ``gains="params"`` uses params.k, params.l as the q of eq. (12). ``max_gap``: see :func:`excitation`.
    """
    from .types import ImuSample, VectorSample

    if isinstance(gains, str):
        if gains != "params" or params is None:
            raise ValueError("gains must be None, an array, or 'params' (with params given)")
        gains = np.concatenate([np.asarray(params.k, float), np.asarray(params.l, float)])
    gyr = np.asarray(samples.gyr, float)
    if gyro_bias is not None:
        gyr = gyr - np.asarray(gyro_bias, float)
    if isinstance(samples, ImuSample):
        if params is None:
            raise ValueError("an ImuSample log needs params (its constant inertial references)")
        refs = np.asarray(params.ref_inertial, float)
        if refs.shape[0] != len(tuple(imu_fields)):
            raise ValueError(f"params.ref_inertial has {refs.shape[0]} rows but imu_fields is {tuple(imu_fields)}")
        fields = tuple(imu_fields)
        if len(set(fields)) != len(fields) or not set(fields) <= {"acc", "mag"}:
            raise ValueError(f"imu_fields must be distinct names among 'acc', 'mag', got {fields}")
        valid_rows = []
        for name in fields:
            reading = getattr(samples, name)
            if reading is None:
                raise ValueError(f"imu_fields names {name!r} but the samples have no {name} readings")
            valid_rows.append(valid_readings(reading))
        valid = np.stack(valid_rows, axis=1)  # (T, n)
        kw: Dict[str, Any] = dict(ref_inertial=np.where(valid[..., None], refs[None], np.nan))
    elif isinstance(samples, VectorSample):

        def ref(meas, carried, name):
            if carried is not None:
                return carried
            if meas is None:
                return None  # no measurement of this kind
            if params is None:
                raise ValueError(f"the samples carry no {name}: pass params with constant Params.{name}")
            return np.asarray(getattr(params, name), float)

        b = samples.inertial_meas
        kw = dict(
            ref_inertial=ref(samples.body_meas, samples.ref_inertial, "ref_inertial"),
            inertial_meas=b,
            ref_body=ref(b, samples.ref_body, "ref_body"),
            gyr=gyr,
        )
    else:
        raise ValueError(f"samples must be a VectorSample or ImuSample, got {type(samples).__name__}")
    if window is None:
        return sufficient_excitation(samples.t, gains=gains, rule=rule, max_gap=max_gap, **kw)
    return excitation(samples.t, window=window, gains=gains, stride=stride, rule=rule, max_gap=max_gap, **kw)


def excitation_of_scenario(
    scenario, *, duration: float, dt: float, window: float, gains=None, stride: int = 1, rule: str = "trapezoid"
) -> Excitation:
    """Excitation of a :class:`jaxatt.sim.references.VectorScenario` from its noise-free simulated log
    (Omega exact, no bias)."""
    from .montecarlo import check_dt, check_duration
    from .sim import references

    duration, dt = check_duration(duration), check_dt(dt)
    if dt >= duration:
        raise ValueError(f"dt ({dt:g} s) must be shorter than the duration ({duration:g} s)")
    clean = scenario._replace(
        gyro_bias=scenario.gyro_bias * 0,
        gyro_noise_std=scenario.gyro_noise_std * 0,
        meas_noise_std=scenario.meas_noise_std * 0,
    )
    samples, _ = references.simulate_vectors(clean, duration, dt)
    return excitation_from_samples(samples, window=window, gains=gains, stride=stride, rule=rule)


def plot_excitation(
    result: Excitation, ax=None, *, per_second: bool = True, threshold: Optional[float] = None, title: str = ""
):
    """Plot the excitation measures against the window start time; returns the matplotlib Axes.

    ``per_second`` divides by the window length (a rate: λ's in [0, n], compatible term in rad/s).
    ``threshold`` draws a horizontal line (e.g. a PE level c).
    """
    if ax is None:
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt

        _, ax = plt.subplots(figsize=(7, 3), constrained_layout=True)
    x = np.asarray(result.t_start)
    scale = 1.0 / (np.asarray(result.t_end) - x) if per_second else 1.0
    curves = [
        ("lambda2", r"$\lambda_2(\int \sum v v^\top)$ (11)", "-"),
        ("lambda_min_projector", r"$\lambda_{min}(\int \sum q(I - v v^\top))$ (12)", "--"),
        ("condition", "condition (13)", ":"),
    ]
    for field, label, ls in curves:
        ax.plot(x, np.asarray(getattr(result, field)) * scale, ls, label=label)
    if threshold is not None:
        ax.axhline(threshold, color="k", lw=0.8, alpha=0.6)
    ax.set_xlabel("window start (s)")
    ax.set_ylabel("per second of window" if per_second else "integral (s)")
    ax.set_ylim(bottom=min(0.0, ax.get_ylim()[0]))
    ax.legend(fontsize="small")
    if title:
        ax.set_title(title)
    return ax
