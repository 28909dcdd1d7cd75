"""VQF: Laidig and Seel's versatile quaternion-based filter, online version, 6D and 9D, as implemented by the
``vqf`` package (``vqf.VQF``, C++; ``vqf.PyVQF``, pure Python: the same update, ported here line by line).

References:

* D. Laidig and T. Seel, "VQF: Highly accurate IMU orientation estimation with bias estimation and magnetic
  disturbance rejection", Information Fusion 91 (2023) 187-204 (arXiv:2203.17024). Section numbers below are the
  paper's: Section 3.1 the strapdown integration, 3.2 the accelerometer update (inclination correction in an
  almost-inertial frame), 3.3 the magnetometer update (heading offset delta), Section 4 the gyroscope bias
  estimation (a Kalman filter on the bias, during motion from the low-pass filtered inclination correction, at rest
  from the low-pass filtered gyro), Section 5 the magnetic disturbance detection and rejection.
* D. Laidig, ``vqf`` 2.x: ``VQF::updateGyr``, ``VQF::updateAcc``, ``VQF::updateMag``, ``VQF::setup``,
  ``VQF::filterCoeffs`` / ``filterVec`` (C++) and their Python twin ``vqf.PyVQF``. This module reproduces the C++
  filter in float64 (``tests/test_vqf.py`` compares every BROAD trial; the numbers are in docs/observers/vqf.md).

What one step computes (time step Ts = dt; gyro y, accelerometer a, magnetometer m, sensor frame):

1. ``updateGyr`` (Section 3.1, 4.3): the rest-detection low-pass of the gyro (a second-order Butterworth filter,
   time constant ``rest_filter_tau``); rest is broken when |y - y_lp|^2 >= rest_th_gyr^2 or any |y_lp_i| >
   bias_clip. Strapdown integration of the bias-corrected rate: q_gyr <- q_gyr (x) exp((y - b) Ts / 2).
2. ``updateAcc`` (Section 3.2, 4): rest detection on the accelerometer (|a - a_lp|^2 < rest_th_acc^2 for
   rest_min_t seconds, with the gyro condition above); the specific force in the almost-inertial frame I_i,
   a_I = q_gyr a q_gyr*, low-pass filtered (Butterworth, ``tau_acc``); rotated into the 6D earth frame E_i with
   q_acc and normalised; the inclination correction q_acc <- q_corr (x) q_acc that turns it onto (0, 0, 1).
   Gyro-bias Kalman filter (Section 4): P <- P + V on the diagonal (below P0); at rest the measurement is
   y_lp - b (R = I, W = biasRestW); in motion the inclination correction rate e = (-a_E[1]/Ts, a_E[0]/Ts, 0)
   plus the low-pass filtered R b minus the low-pass filtered R times b (W = (biasMotionW, biasMotionW,
   biasVerticalW)); e clipped to +-bias_clip, K = P R^T (W + R P R^T)^-1, b <- clip(b + K e), P <- P - K R P.
3. ``updateMag`` (Section 3.3, 5; 9D only): the field in E_i, m_E = q_6D m q_6D*; its norm and dip angle, low-pass
   filtered (``mag_current_tau``); the disturbance detection against the accepted reference (norm within
   mag_norm_th relative, dip within mag_dip_th, for mag_min_undisturbed_time); the candidate of a new field
   (accepted after mag_new_time seconds of rotation faster than mag_new_min_gyr, mag_new_first_time for the
   first); the disagreement angle atan2(m_E[0], m_E[1]) - delta, wrapped to [-pi, pi]; the gain k = 1 - exp(-Ts /
   tau_mag), 0 while a disturbance is rejected (up to mag_max_rejection_time), k / mag_rejection_factor after
   that, at least 1/N during the first tau_mag seconds; delta <- wrap(delta + k angle).

Outputs: q_6D = q_acc (x) q_gyr (sensor to E_i), q_9D = (cos delta/2, 0, 0, sin delta/2) (x) q_6D (sensor to E).

Frames and conventions (from the package's quatRotate / getQuat9D and its documentation):

* Quaternions are Hamilton, scalar first (w, x, y, z), sensor-to-earth: v_E = q v_S q*. The package's
  ``getQuat6D`` / ``getQuat9D`` are exactly ``Out.q6d`` / ``Out.q9d`` here, no conjugation or frame change.
* The 9D earth frame E is **ENU**: z up (the specific force at rest is turned onto (0, 0, 1)), and the heading
  update drives atan2(m_E[0], m_E[1]) to 0, i.e. the horizontal field onto +y = (magnetic) north, so x = east.
  ``Out.q`` of "vqf" is q_9D, sensor-to-ENU, as every registered observer's.
* The 6D frame E_i is z up with an arbitrary heading (the sensor's at the start, drifting with the gyro):
  ``Out.q`` of "vqf-6d" is q_6D; its registry frame is "ENU" up to that unobserved heading.

Readings chosen here (documented differences, none on BROAD):

* Params booleans (``motion_bias_est_enabled``, ``rest_bias_est_enabled``, ``mag_dist_rejection_enabled``) are 0/1
  floats in the Params pytree and switch with ``jnp.where`` (every path is computed; one compiled scan serves every
  setting, vmap over them works). Every other VQF parameter is a float field in the package's units (degrees and
  degrees per second where the package uses them).
* The package computes its coefficients once from a fixed sampling time; here every step computes them from its
  own dt (equal for a constant dt). ``init`` performs the package's update with the first sample (so estimate 0 is
  the package's first output); it has no dt and uses ``Params.ts0`` (s, default 0.01) as the sampling time of that
  first update. Set it to the data's sampling time for a bit-for-bit match from the first sample (the tests do;
  :func:`jaxatt.filter` sets it to the recording's first step unless the params given name it).
* Missing samples: NaN or all-zero acc / mag skip that update (the package skips all-zero vectors); a NaN gyro
  sample is replaced by the last finite one. The next reading is processed over the time since the last one
  (``State.acc_gap`` / ``mag_gap``), so a magnetometer or accelerometer slower than the gyro, given as NaN rows
  between its readings, runs as the package set up with ``VQF(gyrTs, accTs, magTs)`` and ``updateMag`` at its
  readings (equal to rounding; a sensor's first reading is processed over ``ts0``, the package's over its Ts).
* ``smooth`` (default 0 = the exact VQF): a temperature for a differentiable relaxation of the discrete decisions
  (see :func:`_gate`): with smooth > 0, the rest / disturbance / candidate comparisons become sigmoids of
  the normalised margin, the flags become weights in [0, 1], the branches blend. It equals the exact filter for
  smooth <= 1e-7 on the BROAD trials; at 1e-3 the largest angle to it is 0.078 rad (tests/test_vqf.py and
  docs/observers/vqf.md). Use it for gradient-based tuning across thresholds; the registered gains are the
  continuous ones (time constants, bias sigmas).

Everything is pure JAX (jit / vmap / grad over ``Params``), guarded so no NaN reaches a gradient.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import so3
from ..types import ArrayLike, ImuSample, Interval, Observer, shown
from . import registry
from .mahony import valid_vector

__all__ = ["Params", "State", "Out", "Lp", "make_observer", "default_params", "check_params", "PACKAGE_NAMES"]

_EPS = float(np.finfo(float).eps)
_PI = math.pi
_DEG = _PI / 180.0
_SQRT2 = math.sqrt(2.0)


class Params(NamedTuple):
    """VQF's parameters (``vqf.VQF(Ts, **params)``; :data:`PACKAGE_NAMES` maps each field to the package's name).

    Fields (units as in the package):
        tau_acc: time constant of the accelerometer low-pass filter in the almost-inertial frame (s), Section 3.2.
        tau_mag: time constant of the heading (delta) update (s), Section 3.3.
        motion_bias_est_enabled: 1.0 / 0.0, gyro-bias estimation during motion (Section 4.2).
        rest_bias_est_enabled: 1.0 / 0.0, rest detection and bias estimation at rest (Section 4.3).
        mag_dist_rejection_enabled: 1.0 / 0.0, magnetic disturbance detection and rejection (Section 5).
        bias_sigma_init: initial bias standard deviation (deg/s).
        bias_forgetting_time: time in which the bias variance grows to (0.1 deg/s)^2 (s).
        bias_clip: clip of the bias estimate and of the Kalman innovation (deg/s).
        bias_sigma_motion: bias measurement sigma in motion (deg/s).
        bias_vertical_forgetting_factor: factor on the vertical bias measurement weight (-).
        bias_sigma_rest: bias measurement sigma at rest (deg/s).
        rest_min_t: time the rest conditions must hold (s).
        rest_filter_tau: time constant of the rest-detection low-pass filters (s).
        rest_th_gyr: gyro deviation threshold for rest (deg/s).
        rest_th_acc: accelerometer deviation threshold for rest (m/s^2).
        mag_current_tau: time constant of the norm/dip low-pass filter (s); <= 0 no filter.
        mag_ref_tau: time constant of the reference (and candidate) norm/dip update (s).
        mag_norm_th: relative norm threshold of the disturbance detection (-).
        mag_dip_th: dip threshold of the disturbance detection (deg).
        mag_new_time: rotation time after which a new field is accepted (s).
        mag_new_first_time: the same for the first field (s).
        mag_new_min_gyr: minimum (low-pass) angular rate that counts as rotation for a new field (deg/s).
        mag_min_undisturbed_time: undisturbed time before the field is used again (s).
        mag_max_rejection_time: longest time a disturbed field is ignored entirely (s).
        mag_rejection_factor: factor reducing the gain after that, and the rate the rejection time recovers (-).
        ts0: sampling time (s) of the update with the first sample, done by ``init`` (later steps use their dt).
        smooth: temperature of the smooth relaxation of the discrete decisions; 0 = the exact VQF.
    """

    tau_acc: ArrayLike
    tau_mag: ArrayLike
    motion_bias_est_enabled: ArrayLike
    rest_bias_est_enabled: ArrayLike
    mag_dist_rejection_enabled: ArrayLike
    bias_sigma_init: ArrayLike
    bias_forgetting_time: ArrayLike
    bias_clip: ArrayLike
    bias_sigma_motion: ArrayLike
    bias_vertical_forgetting_factor: ArrayLike
    bias_sigma_rest: ArrayLike
    rest_min_t: ArrayLike
    rest_filter_tau: ArrayLike
    rest_th_gyr: ArrayLike
    rest_th_acc: ArrayLike
    mag_current_tau: ArrayLike
    mag_ref_tau: ArrayLike
    mag_norm_th: ArrayLike
    mag_dip_th: ArrayLike
    mag_new_time: ArrayLike
    mag_new_first_time: ArrayLike
    mag_new_min_gyr: ArrayLike
    mag_min_undisturbed_time: ArrayLike
    mag_max_rejection_time: ArrayLike
    mag_rejection_factor: ArrayLike
    ts0: ArrayLike
    smooth: ArrayLike


#: Params field -> the ``vqf`` package's parameter name (``ts0`` and ``smooth`` are jaxatt's own).
PACKAGE_NAMES = {
    "tau_acc": "tauAcc",
    "tau_mag": "tauMag",
    "motion_bias_est_enabled": "motionBiasEstEnabled",
    "rest_bias_est_enabled": "restBiasEstEnabled",
    "mag_dist_rejection_enabled": "magDistRejectionEnabled",
    "bias_sigma_init": "biasSigmaInit",
    "bias_forgetting_time": "biasForgettingTime",
    "bias_clip": "biasClip",
    "bias_sigma_motion": "biasSigmaMotion",
    "bias_vertical_forgetting_factor": "biasVerticalForgettingFactor",
    "bias_sigma_rest": "biasSigmaRest",
    "rest_min_t": "restMinT",
    "rest_filter_tau": "restFilterTau",
    "rest_th_gyr": "restThGyr",
    "rest_th_acc": "restThAcc",
    "mag_current_tau": "magCurrentTau",
    "mag_ref_tau": "magRefTau",
    "mag_norm_th": "magNormTh",
    "mag_dip_th": "magDipTh",
    "mag_new_time": "magNewTime",
    "mag_new_first_time": "magNewFirstTime",
    "mag_new_min_gyr": "magNewMinGyr",
    "mag_min_undisturbed_time": "magMinUndisturbedTime",
    "mag_max_rejection_time": "magMaxRejectionTime",
    "mag_rejection_factor": "magRejectionFactor",
}

#: The package's defaults (``vqf.VQF(Ts).params``), booleans as 1.0.
DEFAULTS = dict(
    tau_acc=3.0,
    tau_mag=9.0,
    motion_bias_est_enabled=1.0,
    rest_bias_est_enabled=1.0,
    mag_dist_rejection_enabled=1.0,
    bias_sigma_init=0.5,
    bias_forgetting_time=100.0,
    bias_clip=2.0,
    bias_sigma_motion=0.1,
    bias_vertical_forgetting_factor=0.0001,
    bias_sigma_rest=0.03,
    rest_min_t=1.5,
    rest_filter_tau=0.5,
    rest_th_gyr=2.0,
    rest_th_acc=0.5,
    mag_current_tau=0.05,
    mag_ref_tau=20.0,
    mag_norm_th=0.1,
    mag_dip_th=10.0,
    mag_new_time=20.0,
    mag_new_first_time=5.0,
    mag_new_min_gyr=20.0,
    mag_min_undisturbed_time=0.5,
    mag_max_rejection_time=60.0,
    mag_rejection_factor=2.0,
    ts0=0.01,
    smooth=0.0,
)


def default_params(dtype=None, **overrides) -> Params:
    """The package's default parameters (``ts0`` = 0.01 s, ``smooth`` = 0: the exact filter), as arrays of
    ``dtype``; keyword arguments override fields (e.g. ``default_params(tau_acc=2.0, ts0=1 / 286)``)."""
    dtype = dtype or jnp.result_type(float)
    bad = set(overrides) - set(Params._fields)
    if bad:
        raise ValueError(f"unknown VQF params {sorted(bad)}; fields: {Params._fields}")
    vals = dict(DEFAULTS, **overrides)
    return Params(**{f: jnp.asarray(vals[f], dtype) for f in Params._fields})


class Lp(NamedTuple):
    """State of one vector low-pass filter with the package's averaging start (``filterVec``): during the first
    tau seconds the output is the running mean (``n`` samples, ``total`` their sum); then the second-order
    Butterworth filter (state ``z`` (2, N), direct form II transposed, as ``filterStep``) starts from it. ``y``:
    the last output; ``ts``: the step (s) of the last update (0 before the first); ``b`` (3,), ``a`` (2,): its
    coefficients."""

    n: jax.Array
    total: jax.Array
    z: jax.Array
    ready: jax.Array
    y: jax.Array
    ts: jax.Array
    b: jax.Array
    a: jax.Array


#: A step longer than this many times the last one, or shorter than the last one over it, the longer of the two
#: above a tenth of the filter's tau (a gap in a recording, a change of rate), restarts that Butterworth low-pass
#: at its last output (:func:`_filter_vec`); smaller changes (timestamp jitter, dropped samples) carry the state
#: over to the new coefficients. The package runs at one fixed Ts and meets neither.
GAP_RATIO = 3.0


class State(NamedTuple):
    """VQF's state (the package's ``VQFState``; flags as floats 0/1 or, with smooth > 0, weights in [0, 1]).

    Fields:
        t: time (s) of the estimate.
        gyr_quat: (4,) strapdown quaternion, sensor to the almost-inertial frame I_i (Section 3.1).
        acc_quat: (4,) inclination correction, I_i to the 6D earth frame E_i (Section 3.2).
        delta: heading offset (rad) from E_i to E (ENU), Section 3.3.
        rest_detected, mag_dist_detected: the flags (1.0 = rest / disturbed field).
        last_acc_lp: (3,) low-pass filtered specific force in I_i (m/s^2).
        acc_lp, rest_gyr_lp, rest_acc_lp, r_lp, bias_lp, mag_norm_dip_lp: the filters (:class:`Lp`).
        k_mag_init: 1/N gain of the first tau_mag seconds (0 once done).
        bias: (3,) gyro-bias estimate (rad/s, sensor frame); the rate used is gyr - bias.
        bias_p: (3, 3) its covariance (in (0.01 deg/s)^2, the package's scaling).
        rest_t: time the rest conditions have held (s).
        rest_last_gyr_lp, rest_last_acc_lp: (3,) last rest-detection filter outputs (rad/s, m/s^2).
        rest_last_sq_dev: (2,) last squared deviations (gyro, acc).
        mag_ref_norm, mag_ref_dip: accepted field norm (data unit) and dip (rad).
        mag_undisturbed_t, mag_reject_t: timers (s).
        mag_candidate_norm, mag_candidate_dip, mag_candidate_t: new field candidate and its timer.
        mag_norm_dip: (2,) last (filtered) norm and dip.
        last_mag_dis_angle: last heading disagreement (rad).
        gyr_last: (3,) last finite gyro sample (rad/s).
        acc_gap, mag_gap: time (s) since the last accelerometer / magnetometer reading, up to the previous step
            (0 when it had one): a reading is processed over this plus the step, the package's accTs / magTs.
    """

    t: jax.Array
    gyr_quat: jax.Array
    acc_quat: jax.Array
    delta: jax.Array
    rest_detected: jax.Array
    mag_dist_detected: jax.Array
    last_acc_lp: jax.Array
    acc_lp: Lp
    k_mag_init: jax.Array
    bias: jax.Array
    bias_p: jax.Array
    r_lp: Lp
    bias_lp: Lp
    rest_t: jax.Array
    rest_last_gyr_lp: jax.Array
    rest_gyr_lp: Lp
    rest_last_acc_lp: jax.Array
    rest_acc_lp: Lp
    rest_last_sq_dev: jax.Array
    mag_ref_norm: jax.Array
    mag_ref_dip: jax.Array
    mag_undisturbed_t: jax.Array
    mag_reject_t: jax.Array
    mag_candidate_norm: jax.Array
    mag_candidate_dip: jax.Array
    mag_candidate_t: jax.Array
    mag_norm_dip: jax.Array
    mag_norm_dip_lp: Lp
    last_mag_dis_angle: jax.Array
    gyr_last: jax.Array
    acc_gap: jax.Array
    mag_gap: jax.Array


class Out(NamedTuple):
    """Estimate at time ``t`` (s).

    Fields:
        t: time (s) the estimate refers to.
        q: (4,) sensor-to-ENU quaternion (w, x, y, z): q_9D for "vqf", q_6D for "vqf-6d" (heading arbitrary).
        r: (3, 3) the same as a rotation matrix (v_ENU = r @ v_sensor).
        q6d: (4,) the package's ``getQuat6D()`` (sensor to E_i).
        q9d: (4,) the package's ``getQuat9D()`` (sensor to E, ENU); equals q6d in 6D mode (delta = 0).
        delta: heading offset (rad) between E_i and E.
        bias: (3,) gyro-bias estimate (rad/s); bias_sigma: its standard deviation (rad/s), ``getBiasEstimate()``.
        rest_detected, mag_dist_detected: the flags (``getRestDetected()``, ``getMagDistDetected()``), floats.
        acc_used, mag_used: whether the accelerometer / magnetometer sample entered this step.
    """

    t: jax.Array
    q: jax.Array
    r: jax.Array
    q6d: jax.Array
    q9d: jax.Array
    delta: jax.Array
    bias: jax.Array
    bias_sigma: jax.Array
    rest_detected: jax.Array
    mag_dist_detected: jax.Array
    acc_used: jax.Array
    mag_used: jax.Array


# ------------------------------------------------------------------------------------------------------------
# Helpers, written in the C++ operation order
# ------------------------------------------------------------------------------------------------------------
def _tree_where(c, a, b):
    return jax.tree_util.tree_map(lambda x, y: jnp.where(c, x, y), a, b)


def _qmul(q1, q2):
    """Hamilton product (``VQF::quatMultiply``)."""
    w = q1[0] * q2[0] - q1[1] * q2[1] - q1[2] * q2[2] - q1[3] * q2[3]
    x = q1[0] * q2[1] + q1[1] * q2[0] + q1[2] * q2[3] - q1[3] * q2[2]
    y = q1[0] * q2[2] - q1[1] * q2[3] + q1[2] * q2[0] + q1[3] * q2[1]
    z = q1[0] * q2[3] + q1[1] * q2[2] - q1[2] * q2[1] + q1[3] * q2[0]
    return jnp.stack([w, x, y, z])


def _qrot(q, v):
    """q v q* (``VQF::quatRotate``)."""
    q0, q1, q2, q3 = q[0], q[1], q[2], q[3]
    x = (1 - 2 * q2 * q2 - 2 * q3 * q3) * v[0] + 2 * v[1] * (q2 * q1 - q0 * q3) + 2 * v[2] * (q0 * q2 + q3 * q1)
    y = 2 * v[0] * (q0 * q3 + q2 * q1) + v[1] * (1 - 2 * q1 * q1 - 2 * q3 * q3) + 2 * v[2] * (q2 * q3 - q1 * q0)
    z = 2 * v[0] * (q3 * q1 - q0 * q2) + 2 * v[1] * (q0 * q1 + q3 * q2) + v[2] * (1 - 2 * q1 * q1 - 2 * q2 * q2)
    return jnp.stack([x, y, z])


def _apply_delta(q, delta):
    """(cos delta/2, 0, 0, sin delta/2) (x) q (``VQF::quatApplyDelta``)."""
    c = jnp.cos(delta / 2)
    s = jnp.sin(delta / 2)
    return jnp.stack([c * q[0] - s * q[3], c * q[1] - s * q[2], c * q[2] + s * q[1], c * q[3] + s * q[0]])


def _sumsq(v):
    out = v[0] * v[0]
    for i in range(1, v.shape[0]):
        out = out + v[i] * v[i]
    return out


def _norm(v):
    """sqrt of the sum of squares, gradient-safe at 0 (``VQF::norm``)."""
    n2 = _sumsq(v)
    pos = n2 > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, n2, 1.0)), 0.0)


def _normalize(v):
    """v / |v| unless |v| < eps (``VQF::normalize``)."""
    n = _norm(v)
    ok = n >= _EPS
    return jnp.where(ok, v / jnp.where(ok, n, 1.0), v)


def _mm(a, b):
    """3x3 product, each entry summed in the C++ order."""
    return a[:, 0:1] * b[0:1, :] + a[:, 1:2] * b[1:2, :] + a[:, 2:3] * b[2:3, :]


def _inv3(m):
    """Adjugate inverse (``VQF::matrix3Inv``); zeros when |det| <= eps."""
    a, b, c, d, e, f, g, h, i = (m[0, 0], m[0, 1], m[0, 2], m[1, 0], m[1, 1], m[1, 2], m[2, 0], m[2, 1], m[2, 2])
    A = e * i - f * h
    D = c * h - b * i
    G = b * f - c * e
    B = f * g - d * i
    E = a * i - c * g
    H = c * d - a * f
    C = d * h - e * g
    F = b * g - a * h
    I_ = a * e - b * d
    det = a * A + b * B + c * C
    ok = jnp.abs(det) > _EPS
    det_s = jnp.where(ok, det, 1.0)
    out = jnp.stack([jnp.stack([A, D, G]), jnp.stack([B, E, H]), jnp.stack([C, F, I_])]) / det_s
    return jnp.where(ok, out, 0.0)


def _filter_coeffs(tau, ts):
    """Second-order Butterworth low-pass (``VQF::filterCoeffs``): (b (3,), a (2,)); a pass-through when
    tau < Ts/2 (or tau <= 0)."""
    through = (tau < ts / 2) | (tau <= 0)
    tau_s = jnp.where(through, 1.0, tau)
    fc = (_SQRT2 / (2.0 * _PI)) / tau_s
    c = jnp.tan(_PI * fc * ts)
    d = c * c + _SQRT2 * c + 1
    b0 = c * c / d
    b = jnp.stack([b0, 2 * b0, b0])
    a = jnp.stack([2 * (c * c - 1) / d, (1 - _SQRT2 * c + c * c) / d])
    one, zero = jnp.ones_like(b0), jnp.zeros_like(b0)
    b = jnp.where(through, jnp.stack([one, zero, zero]), b)
    a = jnp.where(through, jnp.stack([zero, zero]), a)
    return b, a


def _gain_from_tau(tau, ts):
    """k = 1 - exp(-Ts/tau); 0 for tau < 0, 1 for tau = 0 (``VQF::gainFromTau``)."""
    pos = tau > 0
    k = 1 - jnp.exp(-ts / jnp.where(pos, tau, 1.0))
    return jnp.where(pos, k, jnp.where(tau < 0, 0.0, 1.0))


def _lp_new(n_dim, dtype):
    return Lp(
        n=jnp.zeros((), dtype),
        total=jnp.zeros(n_dim, dtype),
        z=jnp.zeros((2, n_dim), dtype),
        ready=jnp.zeros((), bool),
        y=jnp.zeros(n_dim, dtype),
        ts=jnp.zeros((), dtype),
        b=jnp.zeros(3, dtype),
        a=jnp.zeros(2, dtype),
    )


def _filter_vec(x, tau, ts, b, a, st: Lp):
    """``VQF::filterVec``: the running mean for the first tau seconds, then the Butterworth filter started at
    the steady state of that mean (``filterInitialState``). Returns (y, new state).

    The package's coefficients are those of one fixed Ts; here each step has its own (b, a) from its dt, and the
    state ``z`` of one coefficient set is not that of another. Before each step the state is carried over to this
    step's coefficients: its steady state at the last output is exchanged for the new coefficients' one and its
    deviation from it is kept (``filterAdaptStateForCoeffChange``'s idea); with a constant step the change is
    exactly zero. Across a gap (0.01 s, then 1 s, then 0.01 s again; :data:`GAP_RATIO`) the deviation, which
    means something else under coefficients 100 times apart, is dropped: the filter restarts at the steady state
    of its last output (the old state driven through the new coefficients swung VQF's inclination by ~30 deg for
    ~20 s). A restart at every change of the step, jitter included, cost 20 deg on a jittered recording."""
    n1 = st.n + 1
    total1 = st.total + x
    mean = total1 / n1
    now_ready = n1 * ts >= tau
    z_init = jnp.stack([mean * (1 - b[0]), mean * (b[2] - a[1])])
    # steady state of the new coefficients minus that of the old, at the last output (0 for equal coefficients)
    carry = jnp.stack([st.y * (st.b[0] - b[0]), st.y * ((b[2] - a[1]) - (st.b[2] - st.a[1]))])
    gap = st.ready & ((ts > GAP_RATIO * st.ts) | (GAP_RATIO * ts < st.ts)) & (jnp.maximum(ts, st.ts) > 0.1 * tau)
    z_prev = jnp.where(gap, jnp.stack([st.y * (1 - b[0]), st.y * (b[2] - a[1])]), st.z + carry)
    y_run = b[0] * x + z_prev[0]
    z_run = jnp.stack([b[1] * x - a[0] * y_run + z_prev[1], b[2] * x - a[1] * y_run])
    y = jnp.where(st.ready, y_run, mean)
    z = jnp.where(st.ready, z_run, jnp.where(now_ready, z_init, st.z))
    new = Lp(
        n=jnp.where(st.ready, st.n, n1),
        total=jnp.where(st.ready, st.total, total1),
        z=z,
        ready=st.ready | now_ready,
        y=y,
        ts=jnp.asarray(ts, st.ts.dtype) * jnp.ones_like(st.ts),
        b=jnp.asarray(b, st.b.dtype),
        a=jnp.asarray(a, st.a.dtype),
    )
    return y, new


#: Offset (in temperatures) of the smooth gates, so that a tie (margin exactly 0, e.g. the rejection timer that
#: starts at its maximum) is decided as the exact filter decides it: ">" -> ~0, ">=" -> ~1 (e^-30 ~ 1e-13 off).
_TIE = 30.0


def _gate(margin, scale, smooth):
    """The decision ``margin > 0`` as 0/1 (smooth = 0) or sigmoid(margin / (smooth * scale) - 30) (smooth > 0):
    the smooth relaxation of the filter's comparisons; it tends to the exact decision as smooth -> 0, ties
    included. ``scale`` makes the margin dimensionless (the threshold)."""
    hard = (margin > 0).astype(margin.dtype)
    sm = smooth > 0
    soft = jax.nn.sigmoid(margin / jnp.where(sm, smooth * scale, 1.0) - _TIE)
    return jnp.where(sm, soft, hard)


def _gate_ge(margin, scale, smooth):
    """As :func:`_gate` for ``margin >= 0`` (sigmoid(margin / (smooth * scale) + 30): a tie counts as true)."""
    hard = (margin >= 0).astype(margin.dtype)
    sm = smooth > 0
    soft = jax.nn.sigmoid(margin / jnp.where(sm, smooth * scale, 1.0) + _TIE)
    return jnp.where(sm, soft, hard)


def _blend(w, a, b):
    """w a + (1 - w) b for a weight w in [0, 1]; exactly a or b where w is 0 or 1 (jnp.where keeps the exact
    filter bit-exact and NaN-free)."""
    return jax.tree_util.tree_map(lambda x, y: jnp.where(w >= 1, x, jnp.where(w <= 0, y, w * x + (1 - w) * y)), a, b)


# ------------------------------------------------------------------------------------------------------------
# The updates
# ------------------------------------------------------------------------------------------------------------
def _update_gyr(p: Params, s: State, gyr, ts) -> State:
    """``VQF::updateGyr``: rest detection on the gyro, strapdown integration (Section 3.1, 4.3)."""
    sm = p.smooth
    en = (p.rest_bias_est_enabled > 0.5) | (p.mag_dist_rejection_enabled > 0.5)
    b, a = _filter_coeffs(p.rest_filter_tau, ts)
    gyr_lp, lp = _filter_vec(gyr, p.rest_filter_tau, ts, b, a, s.rest_gyr_lp)
    sq_dev = _sumsq(gyr - gyr_lp)
    bias_clip = p.bias_clip * _DEG
    th2 = (p.rest_th_gyr * _DEG) ** 2
    # "rest is kept" weight: sq_dev < th^2 and every |gyr_lp_i| <= bias_clip
    keep = 1 - _gate_ge(sq_dev - th2, th2, sm)
    for i in range(3):
        keep = keep * (1 - _gate(jnp.abs(gyr_lp[i]) - bias_clip, bias_clip, sm))
    s_rest = s._replace(
        rest_gyr_lp=lp,
        rest_last_gyr_lp=gyr_lp,
        rest_last_sq_dev=s.rest_last_sq_dev.at[0].set(sq_dev),
        rest_t=keep * s.rest_t,
        rest_detected=keep * s.rest_detected,
    )
    s = _tree_where(en, s_rest, s)

    g = gyr - s.bias
    gn = _norm(g)
    angle = gn * ts
    moving = gn > _EPS
    gn_s = jnp.where(moving, gn, 1.0)
    c = jnp.cos(angle / 2)
    sn = jnp.sin(angle / 2) / gn_s
    dq = jnp.stack([c, sn * g[0], sn * g[1], sn * g[2]])
    q = _normalize(_qmul(s.gyr_quat, dq))
    return s._replace(gyr_quat=jnp.where(moving, q, s.gyr_quat))


def _quat_6d(s: State):
    return _qmul(s.acc_quat, s.gyr_quat)


def _update_acc(p: Params, s: State, acc, ts) -> State:
    """``VQF::updateAcc``: rest detection on the accelerometer, inclination correction (Section 3.2) and the
    gyro-bias Kalman filter (Section 4). ``acc`` is a valid sample (the caller skips missing ones)."""
    sm = p.smooth
    dtype = acc.dtype
    rest_en = p.rest_bias_est_enabled > 0.5
    motion_en = p.motion_bias_est_enabled > 0.5

    # rest detection
    rb, ra = _filter_coeffs(p.rest_filter_tau, ts)
    acc_lp_r, rlp = _filter_vec(acc, p.rest_filter_tau, ts, rb, ra, s.rest_acc_lp)
    sq_dev = _sumsq(acc - acc_lp_r)
    th2 = p.rest_th_acc * p.rest_th_acc
    still = 1 - _gate_ge(sq_dev - th2, th2, sm)  # deviation below the threshold
    rest_t_inc = s.rest_t + ts
    reached = _gate_ge(rest_t_inc - p.rest_min_t, p.rest_min_t, sm)
    rest_t = _blend(still, rest_t_inc, jnp.zeros_like(s.rest_t))
    rest_det = _blend(still, reached + (1 - reached) * s.rest_detected, jnp.zeros_like(s.rest_detected))
    s_rest = s._replace(
        rest_acc_lp=rlp,
        rest_last_acc_lp=acc_lp_r,
        rest_last_sq_dev=s.rest_last_sq_dev.at[1].set(sq_dev),
        rest_t=rest_t,
        rest_detected=rest_det,
    )
    s = _tree_where(rest_en, s_rest, s)

    # filter acc in the almost-inertial frame
    b, a = _filter_coeffs(p.tau_acc, ts)
    acc_i = _qrot(s.gyr_quat, acc)
    last_acc_lp, alp = _filter_vec(acc_i, p.tau_acc, ts, b, a, s.acc_lp)
    # to the 6D earth frame, normalised
    acc_e = _normalize(_qrot(s.acc_quat, last_acc_lp))
    # inclination correction
    qw2 = (acc_e[2] + 1) / 2
    qw_pos = qw2 > 0
    q_w = jnp.where(qw_pos, jnp.sqrt(jnp.where(qw_pos, qw2, 1.0)), 0.0)
    big = q_w > 1e-6
    q_ws = jnp.where(big, q_w, 1.0)
    zero = jnp.zeros((), dtype)
    corr = jnp.stack([q_w, 0.5 * acc_e[1] / q_ws, -0.5 * acc_e[0] / q_ws, zero])
    corr = jnp.where(big, corr, jnp.array([0.0, 1.0, 0.0, 0.0], dtype))
    acc_quat = _normalize(_qmul(corr, s.acc_quat))
    s = s._replace(acc_lp=alp, last_acc_lp=last_acc_lp, acc_quat=acc_quat)

    # bias estimation (Section 4)
    bias_clip = p.bias_clip * _DEG
    bias = s.bias
    q6 = _quat_6d(s)
    r = jnp.stack(
        [
            1 - 2 * q6[2] * q6[2] - 2 * q6[3] * q6[3],
            2 * (q6[2] * q6[1] - q6[0] * q6[3]),
            2 * (q6[0] * q6[2] + q6[3] * q6[1]),
            2 * (q6[0] * q6[3] + q6[2] * q6[1]),
            1 - 2 * q6[1] * q6[1] - 2 * q6[3] * q6[3],
            2 * (q6[2] * q6[3] - q6[1] * q6[0]),
            2 * (q6[3] * q6[1] - q6[0] * q6[2]),
            2 * (q6[0] * q6[1] + q6[3] * q6[2]),
            1 - 2 * q6[1] * q6[1] - 2 * q6[2] * q6[2],
        ]
    )
    bias_lp = jnp.stack(
        [r[0] * bias[0] + r[1] * bias[1] + r[2] * bias[2], r[3] * bias[0] + r[4] * bias[1] + r[5] * bias[2]]
    )
    r, r_lp = _filter_vec(r, p.tau_acc, ts, b, a, s.r_lp)
    bias_lp, b_lp = _filter_vec(bias_lp, p.tau_acc, ts, b, a, s.bias_lp)

    # coefficients (VQF::setup)
    p0 = (p.bias_sigma_init * 100.0) ** 2
    v = (0.1 * 100.0) ** 2 * ts / p.bias_forgetting_time
    p_motion = (p.bias_sigma_motion * 100.0) ** 2
    w_motion = p_motion * p_motion / v + p_motion
    w_vertical = w_motion / jnp.maximum(p.bias_vertical_forgetting_factor, 1e-10)
    p_rest = (p.bias_sigma_rest * 100.0) ** 2
    w_rest = p_rest * p_rest / v + p_rest

    # measurement: rest (R = I) or motion
    e_rest = s.rest_last_gyr_lp - bias
    e_motion = jnp.stack(
        [
            -acc_e[1] / ts + bias_lp[0] - r[0] * bias[0] - r[1] * bias[1] - r[2] * bias[2],
            acc_e[0] / ts + bias_lp[1] - r[3] * bias[0] - r[4] * bias[1] - r[5] * bias[2],
            -r[6] * bias[0] - r[7] * bias[1] - r[8] * bias[2],
        ]
    )
    r_motion = r.reshape(3, 3)
    w_m = jnp.stack([w_motion, w_motion, w_vertical])
    w_r = jnp.stack([w_rest, w_rest, w_rest])

    # step 1: P = P + V on the diagonal entries below P0
    pm = s.bias_p
    diag = jnp.diagonal(pm)
    pm = pm + jnp.diag(jnp.where(diag < p0, v, 0.0))

    # one Kalman update with the measurement of the branch taken (rest before motion; none if neither)
    w_at_rest = s.rest_detected * rest_en.astype(dtype)  # 1/0 in the exact filter, a weight with smooth > 0
    e, rm, w = _blend(w_at_rest, (e_rest, jnp.eye(3, dtype=dtype), w_r), (e_motion, r_motion, w_m))
    do_update = (w_at_rest > 0) | motion_en
    e = jnp.clip(e, -bias_clip, bias_clip)
    k = _mm(pm, rm.T)
    k = _mm(rm, k)
    k = k + jnp.diag(w)
    k = _inv3(k)
    k = _mm(rm.T, k)
    k = _mm(pm, k)
    bias_k = jnp.stack([k[i, 0] * e[0] + k[i, 1] * e[1] + k[i, 2] * e[2] for i in range(3)]) + bias
    bias_k = jnp.clip(bias_k, -bias_clip, bias_clip)
    p_k = pm - _mm(_mm(k, rm), pm)
    bias_new, p_new = _tree_where(do_update, (bias_k, p_k), (bias, pm))
    s_bias = s._replace(bias=bias_new, bias_p=p_new, r_lp=r_lp, bias_lp=b_lp)
    return _tree_where(motion_en | rest_en, s_bias, s)


def _wrap_pi(x):
    x = jnp.where(x > _PI, x - 2 * _PI, x)
    return jnp.where(x < -_PI, x + 2 * _PI, x)


def _update_mag(p: Params, s: State, mag, ts) -> State:
    """``VQF::updateMag``: magnetic disturbance detection and rejection (Section 5), heading update (Section
    3.3). ``mag`` is a valid sample (the caller skips missing ones)."""
    sm = p.smooth
    dtype = mag.dtype
    en = p.mag_dist_rejection_enabled > 0.5
    mag_e = _qrot(_quat_6d(s), mag)

    # disturbance detection and new-field acceptance
    nrm = _norm(mag_e)
    dip = -jnp.arcsin(jnp.clip(mag_e[2] / jnp.where(nrm > 0, nrm, 1.0), -1.0, 1.0))
    nd = jnp.stack([nrm, dip])
    b, a = _filter_coeffs(p.mag_current_tau, ts)
    nd_f, nd_lp = _filter_vec(nd, p.mag_current_tau, ts, b, a, s.mag_norm_dip_lp)
    use_f = p.mag_current_tau > 0
    nd = jnp.where(use_f, nd_f, nd)
    nd_lp = _tree_where(use_f, nd_lp, s.mag_norm_dip_lp)
    k_ref = _gain_from_tau(p.mag_ref_tau, ts)
    dip_th = p.mag_dip_th * _DEG

    def close(norm_ref, dip_ref):
        th_n = p.mag_norm_th * norm_ref
        g1 = _gate(th_n - jnp.abs(nd[0] - norm_ref), jnp.abs(th_n) + 1e-300, sm)
        g2 = _gate(dip_th - jnp.abs(nd[1] - dip_ref), dip_th, sm)
        return g1 * g2

    ok_ref = close(s.mag_ref_norm, s.mag_ref_dip)
    und_t = s.mag_undisturbed_t + ts
    long_enough = _gate_ge(und_t - p.mag_min_undisturbed_time, p.mag_min_undisturbed_time, sm)
    ref_norm_u = s.mag_ref_norm + k_ref * (nd[0] - s.mag_ref_norm)
    ref_dip_u = s.mag_ref_dip + k_ref * (nd[1] - s.mag_ref_dip)
    undisturbed = (
        und_t,
        _blend(long_enough, jnp.zeros_like(s.mag_dist_detected), s.mag_dist_detected),
        _blend(long_enough, ref_norm_u, s.mag_ref_norm),
        _blend(long_enough, ref_dip_u, s.mag_ref_dip),
    )
    disturbed = (jnp.zeros_like(und_t), jnp.ones_like(s.mag_dist_detected), s.mag_ref_norm, s.mag_ref_dip)
    und_t, dist, ref_norm, ref_dip = _blend(ok_ref, undisturbed, disturbed)

    ok_cand = close(s.mag_candidate_norm, s.mag_candidate_dip)
    rotating = _gate_ge(_norm(s.rest_last_gyr_lp) - p.mag_new_min_gyr * _DEG, p.mag_new_min_gyr * _DEG, sm)
    cand_t = s.mag_candidate_t + rotating * ts
    cand_norm = s.mag_candidate_norm + k_ref * (nd[0] - s.mag_candidate_norm)
    cand_dip = s.mag_candidate_dip + k_ref * (nd[1] - s.mag_candidate_dip)
    new_time = _gate_ge(cand_t - p.mag_new_time, p.mag_new_time, sm)
    first = (ref_norm == 0.0).astype(dtype) * _gate_ge(cand_t - p.mag_new_first_time, p.mag_new_first_time, sm)
    accept = dist * (new_time + first - new_time * first)  # disturbed and (new_time or first)
    detected = (ref_norm, ref_dip, dist, und_t)
    accepted = (cand_norm, cand_dip, jnp.zeros_like(dist), jnp.zeros_like(und_t) + p.mag_min_undisturbed_time)
    ref_norm, ref_dip, dist, und_t = _blend(ok_cand, _blend(accept, accepted, detected), detected)
    cand_t, cand_norm, cand_dip = _blend(ok_cand, (cand_t, cand_norm, cand_dip), (jnp.zeros_like(cand_t), nd[0], nd[1]))
    s_dist = s._replace(
        mag_norm_dip=nd,
        mag_norm_dip_lp=nd_lp,
        mag_undisturbed_t=und_t,
        mag_dist_detected=dist,
        mag_ref_norm=ref_norm,
        mag_ref_dip=ref_dip,
        mag_candidate_t=cand_t,
        mag_candidate_norm=cand_norm,
        mag_candidate_dip=cand_dip,
    )
    s = _tree_where(en, s_dist, s)

    # heading disagreement (Section 3.3), wrapped to [-pi, pi]
    angle = _wrap_pi(jnp.arctan2(mag_e[0], mag_e[1]) - s.delta)
    k = _gain_from_tau(p.tau_mag, ts)
    # disturbance rejection (Section 5)
    d = s.mag_dist_detected
    short = _gate_ge(p.mag_max_rejection_time - s.mag_reject_t, p.mag_max_rejection_time, sm)
    k_dist = _blend(short, jnp.zeros_like(k), k / p.mag_rejection_factor)
    rej_dist = _blend(short, s.mag_reject_t + ts, s.mag_reject_t)
    rej_ok = jnp.maximum(s.mag_reject_t - p.mag_rejection_factor * ts, 0.0)
    k_en, rej_en = _blend(d, (k_dist, rej_dist), (k, rej_ok))
    k = jnp.where(en, k_en, k)
    reject_t = jnp.where(en, rej_en, s.mag_reject_t)
    # fast initial convergence: k >= 1/N during the first tau_mag seconds (k_mag_init = 0 afterwards)
    k = jnp.maximum(k, s.k_mag_init)
    kmi = s.k_mag_init / (s.k_mag_init + 1)
    off = _gate(ts - kmi * p.tau_mag, ts, sm)
    kmi = (1 - off) * kmi
    delta = _wrap_pi(s.delta + k * angle)
    return s._replace(mag_reject_t=reject_t, k_mag_init=kmi, delta=delta, last_mag_dis_angle=angle)


# ------------------------------------------------------------------------------------------------------------
# The observer
# ------------------------------------------------------------------------------------------------------------
def _reset(p: Params, dtype) -> State:
    """``VQF::resetState``."""
    z = jnp.zeros((), dtype)
    p0 = (jnp.asarray(p.bias_sigma_init, dtype) * 100.0) ** 2
    return State(
        t=z,
        gyr_quat=jnp.array([1.0, 0.0, 0.0, 0.0], dtype),
        acc_quat=jnp.array([1.0, 0.0, 0.0, 0.0], dtype),
        delta=z,
        rest_detected=z,
        mag_dist_detected=z + 1,
        last_acc_lp=jnp.zeros(3, dtype),
        acc_lp=_lp_new(3, dtype),
        k_mag_init=z + 1,
        bias=jnp.zeros(3, dtype),
        bias_p=p0 * jnp.eye(3, dtype=dtype),
        r_lp=_lp_new(9, dtype),
        bias_lp=_lp_new(2, dtype),
        rest_t=z,
        rest_last_gyr_lp=jnp.zeros(3, dtype),
        rest_gyr_lp=_lp_new(3, dtype),
        rest_last_acc_lp=jnp.zeros(3, dtype),
        rest_acc_lp=_lp_new(3, dtype),
        rest_last_sq_dev=jnp.zeros(2, dtype),
        mag_ref_norm=z,
        mag_ref_dip=z,
        mag_undisturbed_t=z,
        mag_reject_t=z + jnp.asarray(p.mag_max_rejection_time, dtype),
        mag_candidate_norm=z - 1,
        mag_candidate_dip=z,
        mag_candidate_t=z,
        mag_norm_dip=jnp.zeros(2, dtype),
        mag_norm_dip_lp=_lp_new(2, dtype),
        last_mag_dis_angle=z,
        gyr_last=jnp.zeros(3, dtype),
        acc_gap=z,
        mag_gap=z,
    )


def _inputs(sample, gyr_last, dtype, use_mag: bool):
    gyr = jnp.asarray(sample.gyr, dtype)
    gyr = jnp.where(jnp.all(jnp.isfinite(gyr)), gyr, gyr_last)
    acc = jnp.asarray(sample.acc, dtype) if sample.acc is not None else jnp.full(3, jnp.nan, dtype)
    mag = jnp.asarray(sample.mag, dtype) if (use_mag and sample.mag is not None) else jnp.full(3, jnp.nan, dtype)
    acc_ok, mag_ok = valid_vector(acc), valid_vector(mag)
    acc = jnp.where(acc_ok, acc, jnp.array([0.0, 0.0, 1.0], dtype))
    mag = jnp.where(mag_ok, mag, jnp.array([0.0, 1.0, 0.0], dtype))
    return gyr, acc, mag, acc_ok, mag_ok


def _update(p: Params, s: State, sample, ts, use_mag: bool):
    """``VQF::update(gyr, acc[, mag])`` with one sample: (state, acc_ok, mag_ok).

    A missing acc / mag reading (NaN) skips that sensor's update, as calling only ``updateGyr`` does; the next
    reading is processed over the time since the last one (``State.acc_gap`` / ``mag_gap`` plus this step), as
    the package does with ``accTs`` / ``magTs`` for a sensor slower than the gyro. With a reading at every step
    that time is the step itself, bit for bit."""
    dtype = s.gyr_quat.dtype
    gyr, acc, mag, acc_ok, mag_ok = _inputs(sample, s.gyr_last, dtype, use_mag)
    acc_ts, mag_ts = s.acc_gap + ts, s.mag_gap + ts
    s = _update_gyr(p, s, gyr, ts)
    s = _tree_where(acc_ok, _update_acc(p, s, acc, acc_ts), s)
    if use_mag:
        s = _tree_where(mag_ok, _update_mag(p, s, mag, mag_ts), s)
    zero = jnp.zeros_like(acc_ts)
    return (
        s._replace(gyr_last=gyr, acc_gap=jnp.where(acc_ok, zero, acc_ts), mag_gap=jnp.where(mag_ok, zero, mag_ts)),
        acc_ok,
        mag_ok,
    )


def _out(s: State, use_mag: bool, acc_ok, mag_ok, bias_p0) -> Out:
    q6 = _quat_6d(s)
    q9 = _apply_delta(q6, s.delta)
    q = q9 if use_mag else q6
    pm = jnp.minimum(jnp.max(jnp.sum(jnp.abs(s.bias_p), axis=1)), bias_p0)
    sigma = jnp.sqrt(jnp.where(pm > 0, pm, 0.0)) * _PI / 100.0 / 180.0
    return Out(
        t=s.t,
        q=q,
        r=so3.quat_to_matrix(q),
        q6d=q6,
        q9d=q9,
        delta=s.delta,
        bias=s.bias,
        bias_sigma=sigma,
        rest_detected=s.rest_detected,
        mag_dist_detected=s.mag_dist_detected,
        acc_used=acc_ok,
        mag_used=mag_ok,
    )


@functools.lru_cache(maxsize=None)
def make_observer(mode: str = "9d") -> Observer:
    """VQF (the package's ``VQF.update``), ``mode`` "9d" (gyro, acc, mag; ``Out.q`` = q_9D, sensor-to-ENU) or "6d"
    (gyro, acc; ``Out.q`` = q_6D, heading arbitrary). Cached: the same arguments give the same Observer.

    ``init(params, first_sample)`` resets the state (``VQF::resetState``) and performs the update with the first
    sample over ``params.ts0`` seconds, so estimate 0 is the package's first output. ``step(params, state,
    sample, dt)`` performs ``update(gyr, acc, mag)`` with the next sample over dt (``hold="next"``); an
    :class:`jaxatt.types.Interval` is processed with its end sample.
    """
    if mode not in ("9d", "6d"):
        raise ValueError(f"mode must be '9d' or '6d', got {mode!r}")
    use_mag = mode == "9d"

    def bias_p0(p, dtype):
        return (jnp.asarray(p.bias_sigma_init, dtype) * 100.0) ** 2

    def init(p: Params, sample: ImuSample) -> State:
        dtype = jnp.asarray(sample.gyr).dtype
        s = _reset(p, dtype)
        s, _, _ = _update(p, s, sample, jnp.asarray(p.ts0, dtype), use_mag)
        return s._replace(t=jnp.asarray(sample.t, dtype))

    def step(p: Params, s: State, sample, dt):
        u = sample.end if isinstance(sample, Interval) else sample
        dtype = s.gyr_quat.dtype
        dt = jnp.asarray(dt, dtype)
        s, acc_ok, mag_ok = _update(p, s, u, dt, use_mag)
        s = s._replace(t=s.t + dt)
        return s, _out(s, use_mag, acc_ok, mag_ok, bias_p0(p, dtype))

    def output(p: Params, s: State) -> Out:
        yes = jnp.ones((), bool)
        return _out(s, use_mag, yes, yes if use_mag else ~yes, bias_p0(p, s.gyr_quat.dtype))

    return Observer(init, step, "vqf" if use_mag else "vqf-6d", output, hold="next")


# ------------------------------------------------------------------------------------------------------------
# Registry
# ------------------------------------------------------------------------------------------------------------
_POSITIVE = (
    "tau_acc",
    "tau_mag",
    "bias_sigma_init",
    "bias_forgetting_time",
    "bias_clip",
    "bias_sigma_motion",
    "bias_sigma_rest",
    "rest_filter_tau",
    "rest_th_gyr",
    "rest_th_acc",
    "mag_ref_tau",
    "mag_norm_th",
    "mag_dip_th",
    "mag_rejection_factor",
    "ts0",
)


def check_params(p: Params) -> None:
    """Every field a finite scalar; time constants, sigmas, thresholds and ts0 > 0; the switches 0 or 1; smooth >= 0
    (ValueError otherwise)."""
    for f in Params._fields:
        v = np.asarray(getattr(p, f), float)
        if v.shape != () or not np.isfinite(v):
            raise ValueError(f"VQF param {f} must be a finite scalar, got {shown(v)}")
        if f in _POSITIVE and v <= 0:
            raise ValueError(f"VQF param {f} must be > 0, got {shown(v)}")
        if f.endswith("_enabled") and v not in (0.0, 1.0):
            raise ValueError(f"VQF param {f} must be 0 or 1, got {shown(v)}")
        if f in ("smooth", "bias_vertical_forgetting_factor") and v < 0:
            raise ValueError(f"VQF param {f} must be >= 0, got {shown(v)}")


_GAINS_6D = (
    registry.Gain(
        "tau_acc",
        "s",
        "time constant of the accelerometer low-pass filter, Section 3.2",
        "positive",
        True,
        (0.05, 30.0),
    ),
    registry.Gain("bias_sigma_init", "deg/s", "initial bias sigma, Section 4.1", "positive", True, (1e-3, 10.0)),
    registry.Gain(
        "bias_sigma_motion", "deg/s", "bias measurement sigma in motion, Section 4.2", "positive", True, (1e-3, 10.0)
    ),
    registry.Gain(
        "bias_sigma_rest", "deg/s", "bias measurement sigma at rest, Section 4.3", "positive", True, (1e-4, 10.0)
    ),
    registry.Gain("bias_forgetting_time", "s", "bias variance growth time, Section 4.1", "positive", False, (1.0, 1e4)),
)

ENTRIES = (
    registry.Entry(
        name="vqf",
        summary="VQF 9D: inclination and heading with gyro-bias estimation, rest detection and magnetic "
        "disturbance rejection (vqf.VQF)",
        reference="Laidig & Seel 2023 (Information Fusion 91), Sections 3-5; vqf.VQF",
        make=lambda: make_observer("9d"),
        default_params=lambda dtype=None: default_params(dtype=dtype),
        gains=_GAINS_6D[:1]
        + (
            registry.Gain(
                "tau_mag", "s", "time constant of the heading update, Section 3.3", "positive", True, (0.05, 100.0)
            ),
        )
        + _GAINS_6D[1:],
        frame="ENU",
        module="vqf",
        check=check_params,
        first_step="ts0",
    ),
    registry.Entry(
        name="vqf-6d",
        summary="VQF 6D (no magnetometer): inclination with gyro-bias estimation and rest detection; heading "
        "unobserved (vqf.VQF without mag)",
        reference="Laidig & Seel 2023 (Information Fusion 91), Sections 3.1-3.2, 4; vqf.VQF",
        make=lambda: make_observer("6d"),
        default_params=lambda dtype=None: default_params(dtype=dtype),
        gains=_GAINS_6D,
        frame="ENU",
        needs=("acc",),
        module="vqf",
        check=check_params,
        first_step="ts0",
    ),
)
