"""Offline mode: forward-backward smoothing of any causal observer on a whole recording.

Use it through the front door: ``jaxatt.filter(name_or_observer, gyr, acc, mag, dt=..., offline=True)`` and
``jaxatt.broad_score(..., offline=True)`` (settings: :class:`Offline`); :func:`smoother_fn` is the batched, pure
function underneath (docs: ``docs/offline.md``).

The causal observer runs twice over the recording, unchanged: forward, and over the time-reversed recording
(:func:`reverse_item`: samples in reverse order, gyro negated and re-aligned to the intervals it covers; the
params as the observer declares them for reversed time, :func:`reversed_params`); the two
estimates of each sample are fused by a weighted geodesic average whose weights come from an uncertainty model
driven by the observer's own gates (:func:`uncertainty`, :func:`fuse`). Every part is pure JAX: ``jit``, ``vmap``
over padded trials, ``grad`` through both passes with respect to the observer's params and the fusion params.

Why it helps. A causal filter's error is largest where it has had the least information: after its start (bias
and references not yet learnt) and while a sensor is gated out (during a magnetic disturbance the heading only
follows the gyro, and its error grows with the time since the disturbance began). The backward pass has the mirror
image of that error: large before the end, and during a disturbance growing with the time *until* it ends. The
weights follow these two uncertainties, so a disturbance is bridged from both sides (the gyro-only stretch is
interpolated between the good headings before and after it), a start transient is replaced by the converged
backward estimate, and elsewhere the two estimates are averaged (their noise partly cancels).

Offline VQF (Laidig & Seel 2023, ``vqf.offlineVQF``) is a different, VQF-specific design: the forward and
backward bias estimates are fused by their covariances, the gyro is integrated open loop with that bias, the
accelerometer is low-passed forward and backward (zero phase) in that strapdown frame, and the heading offset is
filtered forward then backward, with rejection where both directions detect a disturbance. Here the whole
filter runs in each direction and only its estimates are fused, so any registered observer (or your own) gets an
offline mode; the gates of the observer (robust AHRS, VQF) give separate heading and inclination weights, and with
``seed_bias`` (:class:`Offline`) a second round of passes starts each pass from the gyro bias the other pass of
the first round ended with (offline VQF's use of the bias of both directions, for any observer with an output
``bias``).

Uncertainty model (per direction, per channel c in {inclination, heading}; in seconds of gyro-only coasting, so
the fusion params are all time constants): ``P_0 = start_c``, then per step k over dt_k

    P_k = (1 - g_k)^2 (P_{k-1} + dt_k),    g_k = trust_c,k (1 - exp(-dt_k / tau_c)),

i.e. the error variance of a first-order correction of time constant ``tau_c`` that grows while coasting
(trust 0) and settles at ~tau_c / 2 while the sensor is trusted. The trust of each step is read from the
observer's output (:func:`trust_of`). The backward weight of a channel is w = P_fwd / (P_fwd + P_bwd).

Fusion (:func:`fuse`): delta = log(q_b (x) conj(q_f)), the rotation vector (ENU, rad) from the forward to the
backward estimate; W = diag(w_incl, w_incl, w_head) acts on it about the geodesic midpoint
q_m = exp(delta / 2) (x) q_f: q = exp((W - I / 2) delta) (x) q_m. It is the slerp of q_f towards q_b by w when
the weights are equal, it is exactly symmetric (swapping the estimates and the weights gives the same q), so
smoothing the time-reversed recording gives the time-reversed estimate.

Conventions: quaternions Hamilton (w, x, y, z), sensor to the observer's navigation frame (ENU for every registered
observer); the navigation frame must be fixed by the measurements (gravity and the magnetic field), so that the
forward and backward passes estimate the same rotation. Observers without an absolute heading (6D, ``heading``
False) are fused in inclination only (the heading is the forward pass's). Time in s, angles in rad.
"""

from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from . import engine, so3
from .types import ImuSample

__all__ = [
    "FusionParams",
    "default_fusion",
    "check_fusion",
    "trust_of",
    "reverse_indices",
    "reverse_item",
    "reversed_params",
    "uncertainty",
    "fuse",
    "fuse_inclination",
    "quat_exp",
    "quat_log",
    "Offline",
    "resolve_offline",
    "Smoothed",
    "Passes",
    "passes_fn",
    "fuse_passes",
    "smoother_fn",
    "compiled",
    "compiled_passes",
    "broad_metric_fn",
]


class FusionParams(NamedTuple):
    """Parameters of the uncertainty model that weights the forward and backward estimates (all in s, > 0).

    Fields:
        tau_inclination: time constant (s) of the observer's inclination correction while the accelerometer is
            trusted (the error variance settles at about tau / 2 s of coasting).
        tau_heading: time constant (s) of its heading correction while the magnetometer is trusted.
        start_inclination: inclination uncertainty at the start of a pass, in s of gyro-only coasting.
        start_heading: heading uncertainty at the start of a pass (s of coasting).
    """

    tau_inclination: Any
    tau_heading: Any
    start_inclination: Any
    start_heading: Any


_FUSION_DEFAULTS = dict(tau_inclination=3.0, tau_heading=100.0, start_inclination=10.0, start_heading=1.0)


def default_fusion(dtype=None, **overrides) -> FusionParams:
    """Default :class:`FusionParams` (s): tau_inclination 3, tau_heading 100, start_inclination 10,
    start_heading 1; ``overrides`` by field name (ValueError for another name).

    The heading numbers are those that each fold of BROAD's 2-fold split picked on its own from a grid
    (``benchmarks/broad.py``, rows ``*-offline-oof``): a magnetometer's heading is often off by a few degrees in
    one place and right in another, so after coasting the heading uncertainty decays slowly (100 s), and a start
    at rest with an undisturbed field is as good as a converged estimate (1 s). The inclination numbers barely
    matter on BROAD."""
    unknown = sorted(set(overrides) - set(FusionParams._fields))
    if unknown:
        raise ValueError(f"unknown fusion parameters {unknown}; fields: {', '.join(FusionParams._fields)}")
    dtype = dtype or jnp.result_type(float)
    vals = {**_FUSION_DEFAULTS, **overrides}
    return FusionParams(**{k: jnp.asarray(vals[k], dtype) for k in FusionParams._fields})


def check_fusion(f) -> FusionParams:
    """``f`` as :class:`FusionParams` (a dict replaces fields of the defaults); ValueError naming the first field
    that is not a finite positive scalar (skipped for traced values)."""
    if f is None:
        return default_fusion()
    if isinstance(f, dict):
        f = default_fusion(**f)
    if not isinstance(f, FusionParams):
        raise ValueError(f"fusion must be jaxatt.smoothing.FusionParams or a dict, got {type(f).__name__}")
    for name, v in zip(f._fields, f):
        if isinstance(v, jax.core.Tracer):
            continue
        a = np.asarray(v)
        if a.shape != () or not np.isfinite(a) or a <= 0:
            raise ValueError(f"fusion parameter {name} must be a finite positive number of seconds, got {a}")
    return f


# ------------------------------------------------------------------------------------------------------------
# Trust of each step, read from the observer's output
# ------------------------------------------------------------------------------------------------------------
def _get(out, name):
    return out.get(name) if isinstance(out, dict) else getattr(out, name, None)


def _scalar(v, like):
    v = jnp.asarray(v)
    return v.astype(like.dtype) if v.shape == () else None


def trust_of(out):
    """(acc_trust, mag_trust) of one step, each () in [0, 1], from the fields of an observer's output:

    * accelerometer: ``acc_weight`` (a smooth gate, robust AHRS), else 1 - ``acc_rejected``, times ``acc_used``
      when present (VQF, Mahony, Madgwick); 1 without any of them;
    * magnetometer: ``mag_weight``, else 1 - ``mag_disturbed`` or 1 - ``mag_dist_detected`` (VQF), times
      ``mag_used`` when present; 1 without any of them.

    Your own observer gets disturbance-aware weights by naming its output fields the same way."""
    q = engine.estimate_q(out)
    one = jnp.ones(q.shape[:-1], q.dtype)

    def pick(weight, flags, used):
        w = _get(out, weight)
        if w is not None and (v := _scalar(w, one)) is not None:
            return v
        t = one
        for f in flags:
            x = _get(out, f)
            if x is not None and (v := _scalar(x, one)) is not None:
                t = one - v
                break
        u = _get(out, used)
        if u is not None and (v := _scalar(u, one)) is not None:
            t = t * v
        return t

    return (
        pick("acc_weight", ("acc_rejected",), "acc_used"),
        pick("mag_weight", ("mag_disturbed", "mag_dist_detected"), "mag_used"),
    )


# ------------------------------------------------------------------------------------------------------------
# Time reversal
# ------------------------------------------------------------------------------------------------------------
def reverse_indices(n: int, length, hold: str = "next"):
    """(meas, gyr): (n,) int index arrays that read a recording of ``length`` real samples (padded to n) in
    reverse time: reversed sample j takes acc / mag / t from sample ``meas[j]`` = L - 1 - j and its gyro
    (negated) from ``gyr[j]``, chosen so that each step integrates the rotation rate the forward pass integrated
    over the same interval:

    * hold "next" (step over [t_{k-1}, t_k] uses sample k): ``gyr[j]`` = L - j (the sample at the interval's
      later end, as forward); j = 0 (the start, before any step) takes L - 1;
    * "zoh" (step over [t_k, t_{k+1}] uses sample k): ``gyr[j]`` = L - 2 - j (the interval's earlier end);
    * "linear" (both ends, interpolated): ``gyr[j]`` = ``meas[j]`` (the interpolation is the same backwards).

    Indices past the real samples repeat the reversed last sample (padding), so ``meas`` maps reversed estimates
    back to forward time as well: forward sample k is reversed sample ``meas[k]`` for k < L."""
    engine.check_hold(hold)
    j = jnp.arange(n)
    length = jnp.asarray(length)
    meas = jnp.clip(length - 1 - j, 0, length - 1)
    if hold == "next":
        gyr = jnp.clip(length - j, 1, length - 1)
    elif hold == "zoh":
        gyr = jnp.clip(length - 2 - j, 0, length - 1)
    else:
        gyr = meas
    return meas, gyr


def _present(a, length):
    """(T,) True where a (T, 3) reading is present within the first ``length`` rows: finite and not all zero (NaN
    or zero rows mark a missing reading, as on the forward pass)."""
    return so3.present(a) & (jnp.arange(a.shape[0]) < length)


def _start_from_present(a, gyr, dt, length):
    """``a`` (T, 3) with a missing row 0 replaced by its first present reading carried back to row 0 by the gyro
    (:func:`jaxatt.so3.first_present_at_start`; zeros when none is present): the start of an observer that sets
    itself up from its first sample (TRIAD, field references) never reads NaN, nor a reading of another attitude."""
    return so3.first_present_at_start(a, gyr, dt, length)


def reverse_item(item: dict, lengths, hold: str = "next", bias=None, start_from_present: bool = False) -> dict:
    """The engine's batch item (:class:`jaxatt.engine.Recorded`: ``samples`` (B, T, ...) ImuSample, ``dt`` (B,)
    or (B, T)) of the time-reversed recordings, each reversed within its ``lengths`` (B,) real samples
    (:func:`reverse_indices`): acc and mag in reverse order, gyro negated (rad/s, sensor frame: the sensor turns
    the other way in reverse time) and re-aligned to the interval it covers; timestamps t'_j = t_0 + t_{L-1} -
    t_{L-1-j} for per-step dt (``dt`` (B, T), dt'_j = dt_{L-j}), unchanged for a constant dt. ``truth`` is dropped.

    ``bias``: optional (B, 3) gyro bias (rad/s, sensor frame) subtracted from the gyro before it is reversed
    (e.g. the forward pass's final estimate: the backward pass then starts with it instead of zero).
    ``start_from_present``: a missing acc / mag reading at the recording's end (the backward pass's start) is
    replaced by that sensor's last present one, as :func:`jaxatt.api.start_from_valid` does for the forward
    pass's start (for observers set up from their first sample)."""
    samples = item["samples"]
    if not isinstance(samples, ImuSample):
        raise ValueError("the offline mode needs ImuSample recordings (t, gyr, acc, mag)")
    n = samples.gyr.shape[1]

    def one(s, dt, length, b):
        meas, gidx = reverse_indices(n, length, hold)
        take = lambda a: None if a is None else jnp.take(a, meas, axis=0)  # noqa: E731
        g = s.gyr if b is None else s.gyr - b.astype(s.gyr.dtype)
        gyr = -jnp.take(g, gidx, axis=0)
        if jnp.ndim(dt) == 1:  # per-step dt: dt[k] = t_k - t_{k-1}
            t = s.t[0] + s.t[length - 1] - jnp.take(s.t, meas, axis=0)
            dt = jnp.take(dt, jnp.clip(length - jnp.arange(n), 1, length - 1), axis=0)
        else:
            t = s.t
        acc, mag = take(s.acc), take(s.mag)
        if start_from_present:
            acc, mag = (None if a is None else _start_from_present(a, gyr, dt, length) for a in (acc, mag))
        return ImuSample(t, gyr, acc, mag), dt

    bs = None if bias is None else jnp.asarray(bias)
    rev, dt = jax.vmap(one, in_axes=(0, 0, 0, None if bs is None else 0))(samples, item["dt"], jnp.asarray(lengths), bs)
    return {"samples": rev, "dt": dt, "truth": None}


def _take_time(a, idx):
    """a (B, T, ...) read at per-trial time indices idx (B, T)."""
    return jax.vmap(lambda x, i: jnp.take(x, i, axis=0))(a, idx)


# ------------------------------------------------------------------------------------------------------------
# Uncertainty and fusion
# ------------------------------------------------------------------------------------------------------------
def uncertainty(trust, dt, tau, start):
    """Error variance of one channel along a pass, in s of gyro-only coasting, (..., T):
    P_0 = start, P_k = (1 - g_k)^2 (P_{k-1} + dt_k) with g_k = trust_k (1 - exp(-dt_k / tau)).

    Args:
        trust: (..., T) in [0, 1], the trust of each step (entry 0, the start, is not used).
        dt: (..., T) or broadcastable step lengths (s); entry 0 not used.
        tau, start: the channel's time constant and start uncertainty (s).
    Differentiable in everything; a linear recursion scanned over the last axis."""
    dt = jnp.broadcast_to(jnp.asarray(dt, trust.dtype), trust.shape)
    g = trust * -jnp.expm1(-dt / tau)
    a = (1.0 - g) ** 2
    p0 = jnp.broadcast_to(jnp.asarray(start, trust.dtype), trust.shape[:-1])

    def step(p, x):
        ak, dk = x
        p = ak * (p + dk)
        return p, p

    _, ps = jax.lax.scan(step, p0, (jnp.moveaxis(a[..., 1:], -1, 0), jnp.moveaxis(dt[..., 1:], -1, 0)))
    return jnp.concatenate([p0[..., None], jnp.moveaxis(ps, 0, -1)], axis=-1)


#: :func:`jaxatt.so3.quat_exp` and :func:`jaxatt.so3.quat_log`, under the names this module has always exported
quat_exp = so3.quat_exp
quat_log = so3.quat_log


def fuse(q_f, q_b, w_incl, w_head):
    """Weighted geodesic average of two sensor-to-nav quaternions (..., 4), (w, x, y, z), with separate weights
    (...) of ``q_b`` about horizontal axes (``w_incl``, the inclination) and about the vertical nav z axis
    (``w_head``, the heading): delta = log(q_b (x) conj(q_f)) (nav frame), q_m = exp(delta / 2) (x) q_f,
    q = exp((diag(w_incl, w_incl, w_head) - I / 2) delta) (x) q_m. Equals slerp(q_f, q_b, w) for equal weights;
    fuse(q_f, q_b, wi, wh) = fuse(q_b, q_f, 1 - wi, 1 - wh) exactly (up to sign)."""
    delta = quat_log(so3.quat_multiply(q_b, so3.quat_conjugate(q_f)))
    w = jnp.stack([w_incl, w_incl, w_head], axis=-1).astype(delta.dtype)
    q_m = so3.quat_multiply(quat_exp(0.5 * delta), q_f)
    q = so3.quat_multiply(quat_exp((w - 0.5) * delta), q_m)
    return so3.quat_canonical(q / jnp.linalg.norm(q, axis=-1, keepdims=True))


def fuse_inclination(q_f, q_b, w_incl):
    """Fusion for observers without an absolute heading (6D): the heading is ``q_f``'s, the inclination moves
    towards ``q_b``'s by ``w_incl``. d = q_b (x) conj(q_f) = swing (x) twist (twist about nav z);
    q = exp(w_incl log(swing)) (x) q_f."""
    d = so3.quat_canonical(so3.quat_multiply(q_b, so3.quat_conjugate(q_f)))
    tw = d * jnp.array([1.0, 0.0, 0.0, 1.0], d.dtype)
    n, small = so3._safe_norm(tw, 1e-12)
    tw = jnp.where(small[..., None], jnp.array([1.0, 0.0, 0.0, 0.0], d.dtype), tw / n[..., None])
    swing = so3.quat_multiply(d, so3.quat_conjugate(tw))
    q = so3.quat_multiply(quat_exp(w_incl[..., None] * quat_log(swing)), q_f)
    return so3.quat_canonical(q / jnp.linalg.norm(q, axis=-1, keepdims=True))


# ------------------------------------------------------------------------------------------------------------
# The smoother: the passes through the engine, then the fusion
# ------------------------------------------------------------------------------------------------------------
class Offline(NamedTuple):
    """The offline mode's settings (``jaxatt.filter(..., offline=Offline(...))``; ``offline=True`` is
    ``Offline()``).

    Fields:
        fusion: :class:`FusionParams` (or a dict of its fields replacing the defaults); None: the defaults.
        seed_bias: two rounds of passes: the first (forward and backward from zero bias) learns the gyro bias at
            each end; in the second, each pass starts from the bias the other pass of the first round ended with
            (the gyro is corrected by it before the observer sees it; the observer's own estimate then tracks the
            rest). Twice the cost; helps where the bias takes long to converge (no rest at the start). Needs an
            output field ``bias`` (3,), rad/s, sensor frame. Keeps the time-reversal symmetry.
        trust: ``trust(out) -> (acc_trust, mag_trust)`` of one step (:func:`trust_of`).
    """

    fusion: Any = None
    seed_bias: bool = False
    trust: Callable = trust_of


def resolve_offline(offline) -> Optional[Offline]:
    """None for ``offline`` False / None; :class:`Offline` with checked fusion params for True, an
    :class:`Offline`, a :class:`FusionParams` or a dict of fusion fields. ValueError otherwise."""
    if offline is None or offline is False:
        return None
    if offline is True:
        spec = Offline()
    elif isinstance(offline, Offline):
        spec = offline
    elif isinstance(offline, (FusionParams, dict)):
        spec = Offline(fusion=offline)
    else:
        raise ValueError(
            "offline must be True/False, jaxatt.smoothing.Offline, FusionParams or a dict, got "
            f"{type(offline).__name__}"
        )
    if not callable(spec.trust):
        raise ValueError("Offline.trust must be a function trust(out) -> (acc_trust, mag_trust)")
    return spec._replace(fusion=check_fusion(spec.fusion), seed_bias=bool(spec.seed_bias))


class Smoothed(NamedTuple):
    """Result of :func:`smoother_fn`; every array (B, T, ...) in forward time (row k at t_k).

    Fields:
        q: (B, T, 4) the fused sensor-to-nav quaternion (w, x, y, z), w >= 0.
        q_forward, q_backward: (B, T, 4) the estimates of the forward and backward passes (of the second round
            with ``seed_bias``).
        weight_inclination, weight_heading: (B, T) the backward estimate's weights in [0, 1].
        var_forward, var_backward: (B, T, 2) the uncertainties (inclination, heading), in s of coasting.
        forward, backward: every output field of both passes (``keep_outputs``) or None; the backward pass's
            read in forward time, its ``bias`` turned back to the forward gyro's sign (and, with ``seed_bias``,
            both passes' ``bias`` include the bias they were started with).
    """

    q: Any
    q_forward: Any
    q_backward: Any
    weight_inclination: Any
    weight_heading: Any
    var_forward: Any
    var_backward: Any
    forward: Any = None
    backward: Any = None


@functools.lru_cache(maxsize=None)
def _picker(trust: Callable, keep_outputs: bool):
    def pick(t, truth, out):
        acc_t, mag_t = trust(out)
        q = engine.estimate_q(out)
        rec = {"q": q, "trust": jnp.stack([jnp.asarray(acc_t, q.dtype), jnp.asarray(mag_t, q.dtype)], axis=-1)}
        b = _get(out, "bias")
        if b is not None and jnp.shape(b) == (3,):
            rec["bias"] = b
        if keep_outputs:
            rec["out"] = out
        return rec

    return pick


def _last(a, lengths):
    """a (B, T, ...) at row lengths - 1 of each recording."""
    return jax.vmap(lambda x, n: jnp.take(x, n - 1, axis=0))(a, lengths)


def _with_bias(out, b):
    """``out`` with its ``bias`` field replaced by ``b``."""
    return out._replace(bias=b) if hasattr(out, "_replace") else {**out, "bias": b}


class Passes(NamedTuple):
    """The records of both passes (:func:`passes_fn`), before the fusion (:func:`fuse_passes`).

    Fields:
        forward: dict of (B, T, ...) records in forward time: ``q`` (w, x, y, z), ``trust`` (B, T, 2), ``bias``
            when the observer outputs one, ``out`` (every output) with ``keep_outputs``.
        backward: the same for the backward pass, in ITS time (row j at t_{L-1-j}), its bias of the negated gyro.
        dt_forward, dt_backward: the step lengths (s), (B, 1) for a constant dt or (B, T).
        meas: (B, T) the row of the backward records that holds each forward time (:func:`reverse_indices`).
        seed_forward, seed_backward: (B, 3) the biases (rad/s, forward gyro's sign) the passes were started with
            (``seed_bias``), else None.
        mag_present: (B,) whether each recording has a magnetometer reading (a present one: finite, not all zero),
            or None for recordings without a mag field: without one neither pass has an absolute heading, and
            :func:`fuse_passes` fuses that recording in inclination only.
        start_age: (B, 2, 2) s, for each pass (forward, backward) and channel (acc: inclination, mag: heading),
            how far in time the reading its start was set from, carried back by the gyro (:func:`_start_from_present`:
            as good as coasting that long), lies from its first sample (0 when that sample has it), or None.
        no_reading_until: (B, 2, 2) s, the same time for observers that are not set up from a carried reading but
            wait for one (VQF's heading): the pass has no weight in that channel before it (:data:`UNINFORMED_S`).
        start_moving: (B, 2) bool, whether each pass starts in motion (:func:`_start_in_motion`), or None: its
            uncertainty then has :data:`MOVING_START_S` exp(-t / :data:`SETTLE_S`) more, t the time into the pass.
    """

    forward: Any
    backward: Any
    dt_forward: Any
    dt_backward: Any
    meas: Any
    seed_forward: Any = None
    seed_backward: Any = None
    mag_present: Any = None
    start_age: Any = None
    no_reading_until: Any = None
    start_moving: Any = None


def reversed_params(observer, params):
    """The params of the backward pass: ``observer.time_reversed(params)`` where the observer declares how its
    params change when time runs backwards (the robust AHRS: its magnetometer delay changes sign, since in
    reversed time the field arrives that much *before* the rate), else ``params`` unchanged."""
    return params if observer.time_reversed is None else observer.time_reversed(params)


def check_time_reversed(observer, params, name: str) -> None:
    """ValueError (one line) unless ``observer.time_reversed(params)`` (when declared) runs and gives params of the
    same type and structure: checked on concrete params before an offline run compiles (a user's function failing
    inside the trace was a bare AttributeError / ZeroDivisionError)."""
    if observer.time_reversed is None:
        return
    try:
        back = observer.time_reversed(params)
    except Exception as e:
        first = (str(e).splitlines() or [""])[0]
        raise ValueError(f"observer {name!r}: time_reversed(params) failed: {type(e).__name__}: {first}") from e
    structure = jax.tree_util.tree_structure
    same = type(back) is type(params) and str(structure(back)) == str(structure(params))
    if not same:
        raise ValueError(
            f"observer {name!r}: time_reversed(params) must return params of the same type and fields "
            f"({type(params).__name__}), got {type(back).__name__}"
        )


def passes_fn(
    observer,
    n_steps: int,
    *,
    per_step_dt: bool = False,
    hold: Optional[str] = None,
    obs_dtype=None,
    trust: Callable = trust_of,
    seed_bias: bool = False,
    keep_outputs: bool = False,
    segment: int = 0,
    start_from_present: bool = False,
):
    """``fn(params, item, lengths) -> Passes``: the forward and backward passes of ``observer`` over a batch of
    recordings (each pass one :func:`jaxatt.engine.batch_fn` scan over the whole batch), before the fusion.
    Arguments as :func:`smoother_fn`."""
    hold = engine.hold_for(observer, hold, "next")
    run = engine.batch_fn(
        observer,
        engine.Recorded(int(n_steps), per_step_dt),
        engine.records_of(_picker(trust, keep_outputs), 1),
        hold=hold,
        obs_dtype=obs_dtype,
        segment=segment,
    )

    def fn(params, item, lengths):
        lengths = jnp.asarray(lengths)
        per_run = {engine.RUN_PARAMS: item[engine.RUN_PARAMS]} if engine.RUN_PARAMS in item else {}
        item = {"samples": item["samples"], "dt": item["dt"], "truth": None, **per_run}
        age = _start_age(item["samples"], lengths)
        given = item["samples"]  # as recorded: the seeded passes below reverse these, not the filled ones
        rev = {**reverse_item(item, lengths, hold, start_from_present=start_from_present), **per_run}
        if start_from_present:  # the forward pass's start, as the backward pass's (idempotent)
            item = {**item, "samples": _samples_start_from_present(given, item["dt"], lengths)}
        fwd = run(None, params, item).records
        bwd = run(None, reversed_params(observer, params), rev).records
        b_fwd = b_bwd = None
        if seed_bias:
            if "bias" not in fwd:
                raise ValueError(f"{observer.name}: seed_bias needs an output field bias of shape (3,)")
            b_fwd = -_last(bwd["bias"], lengths)  # the backward pass ends at t_0; its bias is of the negated gyro
            b_bwd = _last(fwd["bias"], lengths)
            s = item["samples"]
            item = {**item, "samples": s._replace(gyr=s.gyr - b_fwd[:, None, :].astype(s.gyr.dtype))}
            back = reverse_item({**item, "samples": given}, lengths, hold, b_bwd, start_from_present)
            rev = {**back, **per_run}
            fwd = run(None, params, item).records
            bwd = run(None, reversed_params(observer, params), rev).records
        n = fwd["q"].shape[1]
        meas = jax.vmap(lambda length: reverse_indices(n, length, hold)[0])(lengths)
        dtype = fwd["q"].dtype
        dt_f = jnp.asarray(item["dt"], dtype)
        dt_b = jnp.asarray(rev["dt"], dtype)
        if not per_step_dt:
            dt_f, dt_b = dt_f[:, None], dt_b[:, None]
        mag = item["samples"].mag
        mag_present = None if mag is None else jax.vmap(lambda m, n: jnp.any(_present(m, n)))(mag, lengths)
        zero = jnp.zeros_like(age)
        carried, waited = (age, zero) if start_from_present else (zero, age)
        moving = _start_in_motion(given, lengths)
        return Passes(fwd, bwd, dt_f, dt_b, meas, b_fwd, b_bwd, mag_present, carried, waited, moving)

    return fn


#: Uncertainty (s of coasting) of a pass in a channel before its first reading of it, for observers that wait
#: for one (VQF's heading before its first magnetometer reading is arbitrary): large against any start or settled
#: variance (tau / 2), so the other pass has the weight there.
UNINFORMED_S = 1e4


def _samples_start_from_present(samples, dt, lengths):
    """(B, T) samples with :func:`_start_from_present` on each recording's acc and mag (``dt`` (B,) or (B, T))."""
    fix = jax.vmap(_start_from_present)
    return samples._replace(
        acc=None if samples.acc is None else fix(samples.acc, samples.gyr, dt, lengths),
        mag=None if samples.mag is None else fix(samples.mag, samples.gyr, dt, lengths),
    )


def _start_age(samples, lengths):
    """(B, 2, 2) s: for the forward pass (row 0) and the backward pass (row length - 1) of each recording, the time
    to the nearest present acc (inclination) / mag (heading) reading; 0 for a sensor the recordings lack or one
    with no present reading (no heading in either pass: :func:`fuse_passes` fuses the inclination only)."""

    def one(t, acc, mag, length):
        rows = []
        for a in (acc, mag):
            if a is None:
                rows.append(jnp.zeros(2, t.dtype))
                continue
            ok = _present(a, length)
            first, last = jnp.argmax(ok), a.shape[0] - 1 - jnp.argmax(ok[::-1])  # padding rows are not present
            age = jnp.stack([t[first] - t[0], t[length - 1] - t[last]])
            rows.append(jnp.where(jnp.any(ok), age, 0.0))
        return jnp.stack(rows, axis=-1)  # (pass, channel)

    acc, mag = samples.acc, samples.mag
    return jax.vmap(one, in_axes=(0, None if acc is None else 0, None if mag is None else 0, 0))(
        samples.t, acc, mag, jnp.asarray(lengths)
    )


#: Uncertainty (s of coasting) added at its start to a pass that starts in motion (:func:`_start_in_motion`),
#: decaying as exp(-t / :data:`SETTLE_S`) into the pass: its start comes from readings tilted by linear
#: accelerations while the observer is still settling (tens of degrees off at the end of BROAD trials cut
#: mid-movement, against ~1 deg at rest), so the other pass, settled there, has the weight.
MOVING_START_S = 1e4
#: Time constant (s) of that extra uncertainty: the robust AHRS started in motion is within a few degrees after
#: 30 s (research/start_in_motion.py), where exp(-30 / 5) leaves 25 s of coasting (a settled pass's heading
#: uncertainty is ~50 s, its inclination's ~1.5 s: the other pass leads for ~27 s in heading, ~44 s in inclination).
SETTLE_S = 5.0
#: A pass starts "in motion" when, over its first :data:`START_WINDOW_S` s, the mean of | |acc| / median |acc| - 1 |
#: exceeds :data:`START_ACC` (a linear acceleration, which tilts a start taken from the accelerometer) or that of
#: | |mag| / median |mag| - 1 | exceeds :data:`START_MAG` (a disturbed field). A rotation alone does not count (an
#: observer starts well from readings of a turning sensor). On the 20 BROAD trials cut 60 % into their movement the
#: acc deviation over their last 0.5 s is 0.031-0.94 (0.005-0.008 for the two at rest there), the field's 0.6 on
#: the attached magnet; 0.004 on a simulated turning IMU without linear acceleration.
START_WINDOW_S, START_ACC, START_MAG = 0.5, 0.02, 0.1
#: The norms are averaged over this many seconds before they are compared (white noise of 0.2 m/s^2 read as a
#: linear acceleration sample by sample).
NORM_MEAN_S = 0.05


def _start_in_motion(samples, lengths):
    """(B, 2) bool: whether the forward pass (the first :data:`START_WINDOW_S` s of each recording) and the
    backward pass (its last ones, within its length) start with a linear acceleration or a disturbed field
    (:data:`START_ACC`, :data:`START_MAG`)."""

    def deviation(t, v, length):
        """| |v| / median |v| - 1 | of the norm averaged over :data:`NORM_MEAN_S` (white noise averages out, a
        linear acceleration of a hand or a vehicle does not), NaN where missing; and the present rows."""
        ok = _present(v, length)
        n = jnp.where(ok, jnp.linalg.norm(jnp.where(ok[:, None], v, 0.0), axis=-1), 0.0)
        d = jnp.diff(t)
        step = jnp.nanmedian(jnp.where(jnp.arange(d.shape[0]) < length - 1, d, jnp.nan))
        k = jnp.clip(jnp.round(NORM_MEAN_S / jnp.where(step > 0, step, 1.0)), 1, t.shape[0]).astype(jnp.int32)
        idx = jnp.arange(t.shape[0])
        cs = jnp.cumsum(jnp.concatenate([jnp.zeros(1, n.dtype), n]))  # running sums: a centred moving mean
        cn = jnp.cumsum(jnp.concatenate([jnp.zeros(1, n.dtype), ok.astype(n.dtype)]))
        lo = jnp.clip(idx - k // 2, 0, t.shape[0])
        hi = jnp.clip(idx + k - k // 2, 0, t.shape[0])
        count = cn[hi] - cn[lo]
        mean = jnp.where(ok & (count > 0), (cs[hi] - cs[lo]) / jnp.maximum(count, 1), jnp.nan)
        return jnp.abs(mean / jnp.nanmedian(mean) - 1.0), ok

    def one(t, acc, mag, length):
        real = jnp.arange(t.shape[0]) < length
        moving = jnp.zeros(2, bool)
        if t.shape[0] < 2:  # one sample: nothing to compare
            return moving
        for v, most in ((acc, START_ACC), (mag, START_MAG)):
            if v is None:
                continue
            dev, ok = deviation(t, v, length)
            # from the first / to the last present reading: the one a pass's start is set from
            first, last = jnp.argmax(ok), t.shape[0] - 1 - jnp.argmax(ok[::-1])
            windows = (real & (t <= t[first] + START_WINDOW_S), real & (t >= t[last] - START_WINDOW_S))
            moving = moving | jnp.stack([jnp.nanmean(jnp.where(w, dev, jnp.nan)) > most for w in windows])
        return moving

    acc, mag = samples.acc, samples.mag
    return jax.vmap(one, in_axes=(0, None if acc is None else 0, None if mag is None else 0, 0))(
        samples.t, acc, mag, jnp.asarray(lengths)
    )


def fuse_passes(passes: Passes, fusion, heading: bool = True) -> Smoothed:
    """The fused estimate of :func:`passes_fn`'s records with the :class:`FusionParams` ``fusion`` (pure JAX,
    differentiable in both); ``heading`` as in :func:`smoother_fn`."""
    fusion = FusionParams(*fusion)
    fwd, bwd, meas = passes.forward, passes.backward, passes.meas
    dtype = fwd["q"].dtype
    taus = (fusion.tau_inclination, fusion.tau_heading)
    starts = (fusion.start_inclination, fusion.start_heading)

    age, wait, moving = passes.start_age, passes.no_reading_until, passes.start_moving

    def variances(trust_, dt, k):
        def start(c):  # a start set from a reading carried by the gyro: as good as coasting that long
            s0 = jnp.asarray(starts[c], dtype)
            return s0 if age is None else s0 + age[:, k, c].astype(dtype)

        var = jnp.stack(
            [uncertainty(trust_[..., c], dt, jnp.asarray(taus[c], dtype), start(c)) for c in (0, 1)], axis=-1
        )
        if wait is None and moving is None:
            return var
        t = jnp.cumsum(jnp.broadcast_to(jnp.asarray(dt, dtype), trust_.shape[:-1]).at[:, 0].set(0.0), axis=-1)
        if moving is not None:  # a start in motion: far less sure while the observer settles
            settling = MOVING_START_S * jnp.exp(-t / SETTLE_S)
            var = var + jnp.where(moving[:, k, None], settling, 0.0)[..., None].astype(dtype)
        if wait is None:
            return var
        # an observer that had no reading of a channel yet: no weight in it before its first one
        before = t[..., None] < wait[:, None, k, :].astype(dtype)
        return jnp.where(before, jnp.maximum(var, UNINFORMED_S), var)

    var_f = variances(fwd["trust"], passes.dt_forward, 0)
    var_b = _take_time(variances(bwd["trust"], passes.dt_backward, 1), meas)
    q_f = fwd["q"]
    q_b = _take_time(bwd["q"], meas)
    w = var_f / (var_f + var_b)
    q = fuse_inclination(q_f, q_b, w[..., 0])
    if heading:  # a recording without a magnetometer reading has no absolute heading in either pass
        q9 = fuse(q_f, q_b, w[..., 0], w[..., 1])
        q = q9 if passes.mag_present is None else jnp.where(passes.mag_present[:, None, None], q9, q)
    out_f = out_b = None
    if "out" in fwd:
        b_fwd, b_bwd = passes.seed_forward, passes.seed_backward
        out_f = fwd["out"]
        out_b = jax.tree_util.tree_map(lambda a: _take_time(a, meas), bwd["out"])
        bf, bb = _get(out_f, "bias"), _get(out_b, "bias")
        if bb is not None and jnp.shape(bb)[-1:] == (3,):
            bb = -bb
            if b_bwd is not None:
                bb = bb + b_bwd[:, None, :].astype(bb.dtype)
            out_b = _with_bias(out_b, bb)
        if bf is not None and b_fwd is not None and jnp.shape(bf)[-1:] == (3,):
            out_f = _with_bias(out_f, bf + b_fwd[:, None, :].astype(bf.dtype))
    return Smoothed(q, q_f, q_b, w[..., 0], w[..., 1], var_f, var_b, out_f, out_b)


def smoother_fn(
    observer,
    n_steps: int,
    *,
    per_step_dt: bool = False,
    hold: Optional[str] = None,
    obs_dtype=None,
    trust: Callable = trust_of,
    heading: bool = True,
    seed_bias: bool = False,
    keep_outputs: bool = False,
    segment: int = 0,
    start_from_present: bool = False,
):
    """``fn(params, fusion, item, lengths) -> Smoothed``: the forward and backward passes of ``observer``
    (:func:`passes_fn`) and their fusion per sample (:func:`fuse_passes`). Pure JAX: jit it, differentiate it in
    ``params`` and ``fusion`` (:class:`FusionParams`).

    Args:
        observer: the :class:`jaxatt.types.Observer` as run on recorded data (a registered one through
            :func:`jaxatt.observers.registry.recorded_observer`); its estimate must be in a nav frame fixed by the
            measurements (gravity and the magnetic field: ENU for every registered observer), since both passes
            must estimate the same rotation.
        n_steps: T - 1 (T the padded length).
        per_step_dt: ``item["dt"]`` is (B, T) (dt[k] = t_k - t_{k-1}, s) rather than a constant (B,).
        hold: the observer's input per step (:data:`jaxatt.types.HOLDS`); None: the observer's own, else "next".
        obs_dtype: the observer's arithmetic (and that of the fusion).
        trust: ``trust(out) -> (acc_trust, mag_trust)`` (:func:`trust_of`).
        heading: the estimate has an absolute heading (9D); False: fuse the inclination only
            (:func:`fuse_inclination`, 6D).
        seed_bias: see :class:`Offline` (needs an output ``bias``).
        keep_outputs: also return every output field of both passes.
        segment: checkpointed segment length of the scans (:func:`jaxatt.engine.segment_length`; 0 = none):
            reverse mode then stores one state per segment.
        start_from_present: each pass starts from its nearest present acc / mag reading, carried to its first row
            by the gyro, when that row misses one (:func:`_start_from_present`; for observers set up from their
            first sample).
    ``item`` is :class:`jaxatt.engine.Recorded`'s batch (``samples``: :class:`jaxatt.types.ImuSample` of
    (B, T, ...) arrays in the sensor frame, rad/s, m/s^2, any field unit; ``dt``; ``truth`` ignored);
    ``lengths`` (B,) the real samples of each recording, the rest padding that repeats the last sample
    (:func:`jaxatt.data.broad.pad_trials`): each recording is reversed within its own length, so a recording
    smooths the same alone or in any batch."""
    passes = passes_fn(
        observer,
        n_steps,
        per_step_dt=per_step_dt,
        hold=hold,
        obs_dtype=obs_dtype,
        trust=trust,
        seed_bias=seed_bias,
        keep_outputs=keep_outputs,
        segment=segment,
        start_from_present=start_from_present,
    )

    def fn(params, fusion, item, lengths):
        return fuse_passes(passes(params, item, lengths), fusion, heading)

    return fn


def _static(observer, static: dict) -> dict:
    """The keywords of a cached program: the hold resolved (:func:`jaxatt.engine.hold_for`), in one order."""
    return dict(sorted({**static, "hold": engine.hold_for(observer, static.get("hold"), "next")}.items()))


def compiled_passes(observer, n_steps: int, **static):
    """``jax.jit`` of :func:`passes_fn` (cached like :func:`compiled`): the records of both passes, to fuse with
    many fusion params (:func:`fuse_passes`)."""
    return _compiled_passes(observer, int(n_steps), **_static(observer, static))


@functools.lru_cache(maxsize=32)
def _compiled_passes(observer, n_steps: int, **static):
    return jax.jit(passes_fn(observer, n_steps, **static))


def compiled(observer, n_steps: int, **static):
    """``jax.jit`` of :func:`smoother_fn` (cached on every argument, the hold resolved: new params, fusion params
    or recordings of the same shapes reuse the compiled program)."""
    return _compiled(observer, int(n_steps), **_static(observer, static))


@functools.lru_cache(maxsize=32)
def _compiled(observer, n_steps: int, **static):
    return jax.jit(smoother_fn(observer, n_steps, **static))


# ------------------------------------------------------------------------------------------------------------
# BROAD
# ------------------------------------------------------------------------------------------------------------
def broad_metric_fn(
    observer,
    trials,
    *,
    hold: Optional[str] = None,
    dtype=None,
    offline=True,
    heading: bool = True,
    segment: int = 0,
    start_from_present: bool = False,
    run_params: Optional[dict] = None,
):
    """``fn(params, fusion) -> {metric: (B,) RMSE deg}``: the BROAD metric (:data:`jaxatt.data.broad.METRICS`) of
    the offline estimate of ``observer`` on ``trials`` (padded, all in one batch), as a pure JAX function of the
    observer's params and the :class:`FusionParams` (jit it, differentiate it: gains and fusion can be tuned
    through the smoother). ``offline``: :class:`Offline` settings (its ``fusion`` is not used: pass it to ``fn``).
    Estimate k is scored against ``opt_quat[k]`` (sensor to ENU) over the movement samples with finite truth,
    computed in the truth's precision (float64 when x64 is on). ``segment``: checkpointed segment length of the
    scans (:func:`jaxatt.engine.segment_length`), to bound the memory of a gradient over long trials.
    ``run_params``: each trial's own values of some params fields (:func:`jaxatt.data.broad.batch_item`)."""
    from .data import broad

    spec = resolve_offline(offline) or Offline()
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.result_type(float)
    hold = engine.hold_for(observer, hold, "next")
    padded = broad.pad_trials(trials)
    item = broad.batch_item(padded, dtype, run_params)
    lengths = jnp.asarray(padded.lengths)
    # the cached, jitted smoother with the trials as its arguments: called as it is (not under an outer jit, which
    # would make the trials constants of a new program), a second call with trials of the same shapes compiles
    # nothing
    fn = compiled(
        observer,
        int(padded.samples.t.shape[1]) - 1,
        per_step_dt=padded.dt is not None,
        hold=hold,
        obs_dtype=dtype,
        trust=spec.trust,
        heading=heading,
        seed_bias=spec.seed_bias,
        segment=segment,
        start_from_present=start_from_present,
    )
    truth = item["truth"]

    def metric(params, fusion):
        q = fn(params, fusion, item, lengths).q
        return broad.broad_errors_jax(q.astype(truth["q"].dtype), truth["q"], truth["use"])

    return metric
