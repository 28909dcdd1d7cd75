"""Robust 9D AHRS: a complementary filter on SO(3) with gyro-bias estimation, inclination from the accelerometer
low-passed in a quasi-inertial frame, heading from the magnetometer's horizontal projection only, rest detection
and magnetic-disturbance / acceleration gating - every gate a smooth (sigmoid) function of learnable thresholds,
so the whole filter is differentiable in its parameters.

Structure. The attitude follows the explicit complementary filter of Mahony, Hamel, Pflimlin (IEEE TAC 2008,
"Nonlinear complementary filters on the special orthogonal group") written, as in Trumpf, Mahony, Hamel, Lageman
(IEEE TAC 2012, eq. (10)), as gyro propagation plus a sum of vector-measurement corrections,

    dR^/dt = R^ (gyr - b^ + sigma_acc + sigma_mag)_x ,   db^/dt = -k_I sigma,

with three changes that make it robust on real data (after VQF: D. Laidig, T. Seel, "VQF: Highly accurate IMU
orientation estimation with bias estimation and magnetic disturbance rejection", Information Fusion 91, 2023):

1. Inclination. The accelerometer is rotated into the estimated earth frame, a_E = R^ a, and low-passed there by
   two first-order stages (time constants ``tau_acc`` and ``tau_acc_2``). The filter states are rotated with
   every correction, so they live in the quasi-inertial frame of the gyro integration: linear accelerations
   (which integrate to velocity, bounded) average out while gravity stays put. The inclination is then corrected
   fully about a horizontal axis so that the low-passed vector points up; sigma_acc is that rotation. A
   first-order filter (``tau_acc_2`` -> 0) makes this exactly Mahony's acc term with k_P = 1 / tau_acc.
2. Heading. Only the horizontal projection of m_E = R^ m is used: the heading error psi = atan2(m_E,x, m_E,y)
   (angle of the measured field east of north) is removed at the rate 1 / ``tau_mag`` by a rotation about the
   vertical (ENU z). The magnetometer never changes roll or pitch.
3. Gyro bias. (a) At rest: b^ follows the low-passed gyro with time constant ``tau_bias_rest``, weighted by a
   smooth rest detector (gyro and acc deviations from their ``tau_rest`` low-pass below ``rest_th_gyr`` /
   ``rest_th_acc`` and the low-passed gyro a plausible bias, below ``bias_max``, held for ``rest_hold`` s).
   (b) In motion: Mahony's integral of the corrections, b^ <- b^ - phi_B / ``tau_bias``, phi_B the inclination
   correction of the step (rotation vector, body frame), saturated at 0.01 rad against wind-up (steady operation
   stays far below). |b^_i| <= ``bias_max``. The heading corrections do not feed the bias (a bias change along
   the current vertical would tilt the estimate once the sensor turns), so the magnetometer never acts on the
   inclination, not even through the bias.

4. Magnetometer delay. Many IMUs sample or filter the magnetometer later than the gyro (about 10 ms on BROAD's
   sensor: during fast rotations the field then points several degrees off). Each mag sample is turned forward
   by ``mag_delay`` s with the current gyro rate, m <- exp(-(w x) mag_delay) m (to second order), before any use.
   0 (the default) leaves it as it is; :func:`jaxatt.fit` learns it with the rest.

Gates (smooth, learnable). Each uses a normalised squared deviation e >= 0, clipped at 2 and held with a linear
decay ("e_h = max(min(e, 2), e_h - dt / hold)", so a deviation keeps the gate shut for ``hold`` s after it
ends), and the weight w = sigmoid(``gate_sharpness`` (1 - e_h)), rescaled to be exactly 1 at e_h = 0 and exactly 0
at e_h = 2 (w = 0.5 at the threshold):

* accelerometer: e = ((|a| - ``gravity``) / ``acc_th``)^2 scales the low-pass input (tapping, impacts);
* magnetometer: e = ((|m| - n_ref) / (``mag_norm_th`` n_ref))^2 + ((dip - dip_ref) / ``mag_dip_th``)^2 scales the
  heading correction; the references n_ref and dip_ref (dip = elevation of m_E, negative when the field points
  down) start from the first sample and follow the field with time constant ``tau_mag_ref`` while undisturbed.
  Limitation: a field that is disturbed from the first sample on and never returns is rejected for good. The
  front door (``jaxatt.filter``, ``broad_score``, ``fit`` on recordings) starts a recording whose first acc / mag
  reading is missing from that sensor's first present one (``Entry.init_reads``).

Frames and units. R^ (and q^, Hamilton (w, x, y, z)) maps sensor coordinates to ENU (x East, y North - the
horizontal direction of the local magnetic field -, z Up): v_ENU = R^ v_sensor, as BROAD and VQF. Gyro rad/s,
acc (specific force; "up" at rest) m/s^2, mag in any unit (only ratios and directions are used), time s.
Parameters are sample-rate independent (time constants in s); coefficients k = 1 - exp(-dt / tau) are derived
from them and dt inside ``step``.

Start (``init``): TRIAD from the first accelerometer and magnetometer samples (up = a / |a|, east = m x up /
|.|, north = up x east; rows of R^ = east, north, up), zero bias, low-pass states at the first samples, the
rest detector "not at rest" (it needs ``rest_hold`` s of quiet first).
Start-up: a start taken in motion is only as good as that one sample (a linear acceleration tilts it, and the
magnetic reference's dip is read in that tilted frame); with a dip reference that far off the magnetic gate used
to shut for good. So for a start-up of weight ``start`` = exp(-t / (``tau_acc`` + ``tau_acc_2``)) the acc gate is
opened (w <- w + start (1 - w)), the dip does not gate the magnetometer (its term scaled by (1 - start)^2) and
the dip reference follows the field as read in the settling estimate (its step k <- k + start (1 - k)). The norm,
which does not depend on the estimate, gates and is learnt as always, so a disturbance that arrives during the
start-up is still rejected. On the 20 BROAD trials started 40 % into their movement, the error 30 s later falls
from 87 / 41 / 28 deg (the fast translations and the combined trial) to 3.0 / 2.6 / 2.2 deg; the magnet trials
are unchanged (a start beside a magnet, or in a disturbed field, learns it: the limitation below).

Missing data: a non-finite (or zero) acc / mag sample gets weight 0 (its gate state is held); a non-finite gyro
sample is replaced by the gyro low-pass. Padded trials (last sample repeated) need no special care. The time
constants hold for a sensor slower than the gyro or with gaps (a magnetometer at a quarter of the gyro rate, given
as NaN rows between its readings): the next present reading takes the step that the steps without one owed,
1 - prod(1 - k) over them (``State.acc_gain``, ``State.mag_gain``; the tau_acc low-pass and the tau_mag heading
correction), so a correction per reading does not slow down with the reading rate. With a reading at every step
this is k itself, bit for bit.

Everything is pure JAX: jit, vmap over trials (padded, masked) and over parameter sets, grad through long scans
(:func:`jaxatt.fit` learns the parameters from BROAD trials). Shipped tuned parameters: the registry entry
"robust" (``jaxatt.filter("robust", ...)``) and :func:`jaxatt.data.gains.load_params`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import so3
from ..types import ArrayLike, ImuSample, Interval, Observer, shown
from . import registry

__all__ = [
    "Params",
    "State",
    "Out",
    "Coeffs",
    "make_observer",
    "default_params",
    "params_from_dict",
    "params_to_dict",
    "coefficients",
    "PARAM_NAMES",
    "TUNABLE",
    "ENTRIES",
    "check_params",
    "quat_from_acc_mag_enu",
    "gain_from_tau",
]

_DEG = float(np.pi / 180.0)


class Params(NamedTuple):
    """User-facing parameters (each a scalar array): time constants (s) and gating thresholds.

    Fields:
        tau_acc: first low-pass stage of the acc in the quasi-inertial frame (s), > 0.
        tau_acc_2: second low-pass stage (s), > 0 (small: first-order, i.e. Mahony with k_P = 1 / tau_acc).
        tau_mag: heading correction time constant (s), > 0.
        tau_bias: motion bias integral from the inclination corrections (s), > 0 (large: off).
        tau_bias_rest: bias low-pass while at rest (s), > 0.
        tau_rest: low-pass of gyro and acc for rest detection (s), > 0.
        rest_hold: time the rest condition must hold before the sensor counts as at rest (s), > 0.
        rest_th_gyr: rest threshold on |gyr - lp(gyr)| (rad/s), > 0.
        rest_th_acc: rest threshold on |acc - lp(acc)| (m/s^2), > 0.
        acc_th: acceleration rejection threshold on ||a| - gravity| (m/s^2), > 0.
        acc_hold: acc rejection hold time (s), > 0.
        mag_norm_th: magnetic disturbance threshold on the relative norm deviation (1), > 0.
        mag_dip_th: magnetic disturbance threshold on the dip deviation (rad), > 0.
        mag_hold: magnetic disturbance hold time (s), > 0.
        tau_mag_ref: time constant of the magnetic reference (norm, dip) while undisturbed (s), > 0.
        gravity: |g| (m/s^2) for the acc gate.
        gate_sharpness: slope of the sigmoid gates (1); large -> hard thresholds.
        bias_max: bound on each bias component (rad/s).
        mag_delay: delay of the magnetometer behind the gyro (s; 0: none, may be negative). Each mag sample is
            turned forward by it with the gyro rate before use: m <- exp(-(w x) mag_delay) m, to second order.
        tau_mag_gate: low-pass time constant (s) of the field norm and dip that the magnetic gate compares with
            its references (<= 0, as the default and the shipped gains: each reading as it is). For a magnetometer
            noisier than the gate's thresholds: 2 uT of noise on a 45-uT field shuts the shipped gate in 97 % of the
            samples (3.0 deg RMS on a simulated log), 0.1 s opens it (0.23 deg). Not learnt by default (on BROAD
            out of fold, 0.05 s with the shipped gains costs 1.82 -> 1.93 deg undisturbed; learnt unconstrained,
            a value <= 0 is "off").
    """

    tau_acc: ArrayLike
    tau_acc_2: ArrayLike
    tau_mag: ArrayLike
    tau_bias: ArrayLike
    tau_bias_rest: ArrayLike
    tau_rest: ArrayLike
    rest_hold: ArrayLike
    rest_th_gyr: ArrayLike
    rest_th_acc: ArrayLike
    acc_th: ArrayLike
    acc_hold: ArrayLike
    mag_norm_th: ArrayLike
    mag_dip_th: ArrayLike
    mag_hold: ArrayLike
    tau_mag_ref: ArrayLike
    gravity: ArrayLike
    gate_sharpness: ArrayLike
    bias_max: ArrayLike
    mag_delay: ArrayLike = 0.0
    tau_mag_gate: ArrayLike = 0.0


PARAM_NAMES = Params._fields
#: Parameters :func:`jaxatt.fit` learns by default (all positive and learnt in log space within bounds, but the
#: real ``mag_delay``).
TUNABLE = (
    "tau_acc",
    "tau_acc_2",
    "tau_mag",
    "tau_bias",
    "tau_bias_rest",
    "tau_rest",
    "rest_hold",
    "rest_th_gyr",
    "rest_th_acc",
    "acc_th",
    "acc_hold",
    "mag_norm_th",
    "mag_dip_th",
    "mag_hold",
    "tau_mag_ref",
    "mag_delay",
)

_DEFAULTS = dict(
    tau_acc=2.0,
    tau_acc_2=1.0,
    tau_mag=9.0,
    tau_bias=60.0,
    tau_bias_rest=3.0,
    tau_rest=0.5,
    rest_hold=1.5,
    rest_th_gyr=2.0 * _DEG,
    rest_th_acc=0.5,
    acc_th=5.0,
    acc_hold=0.1,
    mag_norm_th=0.1,
    mag_dip_th=10.0 * _DEG,
    mag_hold=0.5,
    tau_mag_ref=30.0,
    gravity=9.81,
    gate_sharpness=6.0,
    bias_max=2.0 * _DEG,
    mag_delay=0.0,
    tau_mag_gate=0.0,
)


class State(NamedTuple):
    """Filter state at time ``t`` (s).

    Fields:
        t: time (s).
        q: (4,) sensor-to-ENU unit quaternion (w, x, y, z).
        bias: (3,) gyro-bias estimate (rad/s, sensor frame).
        acc_lp: (3,) first acc low-pass stage, quasi-inertial (ENU-aligned) frame (m/s^2).
        acc_lp2: (3,) second acc low-pass stage (m/s^2), quasi-inertial frame; points up after a full correction.
        gyr_lp: (3,) gyro low-pass (rad/s, sensor frame): rest detection, stand-in for a missing gyro sample.
        acc_lp_body: (3,) acc low-pass (m/s^2, sensor frame): rest detection, stand-in for a missing acc sample.
        rest_e: () held rest deviation (normalised, in [0, 2]).
        acc_e: () held acc deviation.
        mag_e: () held magnetic deviation.
        mag_norm_ref: () reference |m| (unit of mag).
        mag_sin_dip_ref: () sine of the reference dip (negative when the field points down).
        acc_gain: () fraction 1 - prod(1 - k_acc) of the acc low-pass step over the steps since the last present
            acc reading, this one included (k_acc there when every step has one; see "Missing data").
        mag_gain: () the same for the heading correction (k_mag).
        mag_norm_lp, mag_sin_dip_lp: () the field norm and sin(dip) low-passed with ``tau_mag_gate`` (the magnetic
            gate's input).
        start: () weight of the start-up in [0, 1]: 1 at ``init``, decaying with the time constant
            ``tau_acc + tau_acc_2`` (see "Start").
    """

    t: jax.Array
    q: jax.Array
    bias: jax.Array
    acc_lp: jax.Array
    acc_lp2: jax.Array
    gyr_lp: jax.Array
    acc_lp_body: jax.Array
    rest_e: jax.Array
    acc_e: jax.Array
    mag_e: jax.Array
    mag_norm_ref: jax.Array
    mag_sin_dip_ref: jax.Array
    acc_gain: jax.Array
    mag_gain: jax.Array
    mag_norm_lp: jax.Array
    mag_sin_dip_lp: jax.Array
    start: jax.Array


class Out(NamedTuple):
    """Estimate at time ``t`` (s, end of the step) and per-step diagnostics.

    Fields:
        t: ().
        q: (4,) sensor-to-ENU quaternion (w, x, y, z).
        r: (3, 3) sensor-to-ENU rotation matrix (v_ENU = r @ v_sensor).
        bias: (3,) gyro-bias estimate (rad/s, sensor frame).
        mag_disturbed: () bool, magnetometer gated out (weight < 0.5) in this step (or missing).
        acc_rejected: () bool, accelerometer gated out (weight < 0.5) in this step (or missing); not during
            the start-up, which opens the acc gate (``State.start``).
        rest: () bool, rest detected (weight > 0.5).
        mag_weight, acc_weight, rest_weight: () the smooth gate values in [0, 1].
        heading_error: () psi, heading of the measured field east of north in the estimated frame (rad), before
            this step's heading correction.
    """

    t: jax.Array
    q: jax.Array
    r: jax.Array
    bias: jax.Array
    mag_disturbed: jax.Array
    acc_rejected: jax.Array
    rest: jax.Array
    mag_weight: jax.Array
    acc_weight: jax.Array
    rest_weight: jax.Array
    heading_error: jax.Array


def default_params(dtype=None, **overrides) -> Params:
    """Params with VQF-like defaults (time constants in s, thresholds in SI / relative units); ``overrides`` by
    field name. These defaults are untuned; the tuned ones ship as :func:`jaxatt.data.gains.load_params`."""
    unknown = set(overrides) - set(PARAM_NAMES)
    if unknown:
        raise ValueError(f"unknown robust_ahrs parameters: {sorted(unknown)}")
    dtype = dtype or jnp.result_type(float)
    vals = {**_DEFAULTS, **overrides}
    return Params(**{k: jnp.asarray(vals[k], dtype) for k in PARAM_NAMES})


def params_from_dict(d: dict, dtype=None) -> Params:
    """Params from a {name: value} mapping (missing names take the defaults)."""
    return default_params(dtype, **{k: float(v) for k, v in d.items() if k in PARAM_NAMES})


def params_to_dict(p: Params) -> dict:
    return {k: float(np.asarray(v)) for k, v in zip(PARAM_NAMES, p)}


def gain_from_tau(tau, dt):
    """Discrete first-order low-pass coefficient 1 - exp(-dt / tau) (the step response reaches 63 % at tau)."""
    return -jnp.expm1(-dt / tau)


# ------------------------------------------------------------------------------------------------------------
# Coefficients derived from the parameters and dt (VQF's split: params -> coefficients -> state)
# ------------------------------------------------------------------------------------------------------------
class Coeffs(NamedTuple):
    """Per-step coefficients from :class:`Params` and dt (broadcastable arrays)."""

    dt: jax.Array
    k_rest: jax.Array
    k_bias_rest: jax.Array
    k_acc: jax.Array
    k_acc_2: jax.Array
    k_mag: jax.Array
    k_mag_ref: jax.Array
    inv_bias: jax.Array
    inv_rest_gyr2: jax.Array
    inv_rest_acc2: jax.Array
    inv_acc_th: jax.Array
    inv_mag_norm_th: jax.Array
    inv_mag_dip_th: jax.Array
    dec_rest: jax.Array
    dec_acc: jax.Array
    dec_mag: jax.Array
    gravity: jax.Array
    sharpness: jax.Array
    gate_lo: jax.Array
    gate_scale: jax.Array
    bias_max: jax.Array
    mag_delay: jax.Array
    k_mag_gate: jax.Array
    k_start: jax.Array


def coefficients(p: Params, dt) -> Coeffs:
    """Discrete coefficients for time step ``dt`` (s): k = 1 - exp(-dt / tau) for the low-passes, dt / hold for
    the linear decay of the held deviations, reciprocals of the thresholds."""
    lo = jax.nn.sigmoid(-p.gate_sharpness)
    return Coeffs(
        dt=dt,
        k_rest=gain_from_tau(p.tau_rest, dt),
        k_bias_rest=gain_from_tau(p.tau_bias_rest, dt),
        k_acc=gain_from_tau(p.tau_acc, dt),
        k_acc_2=gain_from_tau(p.tau_acc_2, dt),
        k_mag=gain_from_tau(p.tau_mag, dt),
        k_mag_ref=gain_from_tau(p.tau_mag_ref, dt),
        inv_bias=1.0 / p.tau_bias,
        inv_rest_gyr2=1.0 / (p.rest_th_gyr * p.rest_th_gyr),
        inv_rest_acc2=1.0 / (p.rest_th_acc * p.rest_th_acc),
        inv_acc_th=1.0 / p.acc_th,
        inv_mag_norm_th=1.0 / p.mag_norm_th,
        inv_mag_dip_th=1.0 / p.mag_dip_th,
        dec_rest=dt / p.rest_hold,
        dec_acc=dt / p.acc_hold,
        dec_mag=dt / p.mag_hold,
        gravity=p.gravity,
        sharpness=p.gate_sharpness,
        gate_lo=lo,
        gate_scale=1.0 / (1.0 - 2.0 * lo),
        bias_max=p.bias_max,
        mag_delay=p.mag_delay,
        k_mag_gate=jnp.where(
            p.tau_mag_gate > 0, gain_from_tau(jnp.where(p.tau_mag_gate > 0, p.tau_mag_gate, 1.0), dt), 1.0
        ),
        k_start=gain_from_tau(p.tau_acc + p.tau_acc_2, dt),
    )


# ------------------------------------------------------------------------------------------------------------
# The elementwise core, written on scalar components (each an array of the batch shape, so the same code serves
# one trial or a broadcast batch), with no transcendental function but one atan2 (XLA's CPU backend fuses cheap
# arithmetic freely). ``step`` unpacks the public State into components and packs the result back.
# ------------------------------------------------------------------------------------------------------------
#: Components of the tuple ``_core`` returns: the new state, then the diagnostics of the step.
_ROWS = (
    "qw",
    "qx",
    "qy",
    "qz",
    "bx",
    "by",
    "bz",
    "l1x",
    "l1y",
    "l1z",
    "l2x",
    "l2y",
    "l2z",
    "glx",
    "gly",
    "glz",
    "abx",
    "aby",
    "abz",
    "rest_e",
    "acc_e",
    "mag_e",
    "mag_norm_ref",
    "mag_sin_dip_ref",
    "acc_gain",
    "mag_gain",
    "mag_norm_lp",
    "mag_sin_dip_lp",
    "start",
    "w_mag",
    "w_acc",
    "w_rest",
    "psi",
)
_N_STATE = 29
#: Anti-windup of the motion-bias integrator: saturation of a step's acc correction (rad) it integrates (far
#: above its values in steady operation, ~1e-4 rad per step).
_PHI_SAT = 0.01


def _gate(e_held, c: Coeffs):
    """Smooth gate of a held deviation e in [0, 2]: sigmoid(s (1 - e)) rescaled so that w(0) = 1 and w(2) = 0
    exactly (a rejected sensor leaks nothing); w(1) = 0.5."""
    return (1.0 / (1.0 + jnp.exp(c.sharpness * (e_held - 1.0))) - c.gate_lo) * c.gate_scale


def _hold(e_prev, e_now, dec):
    """Held deviation: jumps up to min(e, 2) at once, decays linearly by ``dec`` = dt / hold per step."""
    return jnp.maximum(jnp.minimum(e_now, 2.0), e_prev - dec)


def _rot_c(q, v):
    """R(q) v for a unit quaternion q = (w, x, y, z): v + 2 w (u x v) + 2 u x (u x v)."""
    w, x, y, z = q
    vx, vy, vz = v
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    return (vx + w * tx + (y * tz - z * ty), vy + w * ty + (z * tx - x * tz), vz + w * tz + (x * ty - y * tx))


def _rot_inv_c(q, v):
    w, x, y, z = q
    return _rot_c((w, -x, -y, -z), v)


def _finite3(x, y, z):
    return jnp.isfinite(x) & jnp.isfinite(y) & jnp.isfinite(z)


def _core(c: Coeffs, s: tuple, g: tuple, a: tuple, m: tuple):
    """One step. ``s``: the state as a tuple of component arrays (_ROWS[:_N_STATE]); g, a, m: 3-tuples of arrays (gyro,
    acc, mag; NaN = missing). Returns the tuple of _ROWS: the new state, then this step's diagnostics. (Tuples of
    components, never one packed array: slicing a packed array turns into pads in the reverse pass, which XLA
    computes very slowly.)"""
    (
        qw,
        qx,
        qy,
        qz,
        bx,
        by,
        bz,
        l1x,
        l1y,
        l1z,
        l2x,
        l2y,
        l2z,
        glx,
        gly,
        glz,
        abx,
        aby,
        abz,
        rest_e,
        acc_e,
        mag_e,
        mref,
        sref,
        acc_gain,
        mag_gain,
        mnl,
        sdl,
        start,
    ) = s
    gx, gy, gz = g
    ax, ay, az = a
    mx, my, mz = m
    gyr_ok = _finite3(gx, gy, gz)
    acc_ok = _finite3(ax, ay, az) & ((ax != 0) | (ay != 0) | (az != 0))
    mag_ok = _finite3(mx, my, mz) & ((mx != 0) | (my != 0) | (mz != 0))
    gx, gy, gz = jnp.where(gyr_ok, gx, glx), jnp.where(gyr_ok, gy, gly), jnp.where(gyr_ok, gz, glz)
    ax, ay, az = jnp.where(acc_ok, ax, abx), jnp.where(acc_ok, ay, aby), jnp.where(acc_ok, az, abz)
    one, zero = jnp.ones_like(qw), jnp.zeros_like(qw)
    mx, my, mz = jnp.where(mag_ok, mx, zero), jnp.where(mag_ok, my, one), jnp.where(mag_ok, mz, zero)
    fa, fm = acc_ok.astype(qw.dtype), mag_ok.astype(qw.dtype)
    # magnetometer delay: a sample measured mag_delay s ago is turned by the rotation since then,
    # m(t) = exp(-(w x) tau) m(t - tau) for a constant body rate w (m fixed in the earth frame), to second order
    tau = c.mag_delay
    ux, uy, uz = gx - bx, gy - by, gz - bz
    cx1, cy1, cz1 = uy * mz - uz * my, uz * mx - ux * mz, ux * my - uy * mx  # w x m
    cx2, cy2, cz2 = uy * cz1 - uz * cy1, uz * cx1 - ux * cz1, ux * cy1 - uy * cx1  # w x (w x m)
    half_tau2 = 0.5 * tau * tau
    mx, my, mz = mx - tau * cx1 + half_tau2 * cx2, my - tau * cy1 + half_tau2 * cy2, mz - tau * cz1 + half_tau2 * cz2

    # --- rest detection (sensor frame) ---
    kr = c.k_rest
    glx, gly, glz = glx + kr * (gx - glx), gly + kr * (gy - gly), glz + kr * (gz - glz)
    kra = kr * fa
    abx, aby, abz = abx + kra * (ax - abx), aby + kra * (ay - aby), abz + kra * (az - abz)
    dgx, dgy, dgz = gx - glx, gy - gly, gz - glz
    dax, day, daz = ax - abx, ay - aby, az - abz
    # a steady rotation is not rest however quiet the gyro is: the low-passed rate must also be a plausible bias
    # (VQF's bias-clip test; (|lp(gyr)| / bias_max)^4: 0.06 at half of bias_max, 1 at it)
    r_bias = (glx * glx + gly * gly + glz * glz) / (c.bias_max * c.bias_max)
    e_rest = (
        (dgx * dgx + dgy * dgy + dgz * dgz) * c.inv_rest_gyr2
        + (dax * dax + day * day + daz * daz) * c.inv_rest_acc2
        + r_bias * r_bias
    )
    rest_e = _hold(rest_e, e_rest, c.dec_rest)
    w_rest = _gate(rest_e, c)
    anorm = jnp.sqrt(ax * ax + ay * ay + az * az)
    da = (anorm - c.gravity) * c.inv_acc_th
    acc_e = jnp.where(acc_ok, _hold(acc_e, da * da, c.dec_acc), acc_e)
    # the start-up (weight ``start``) opens the acc gate: a start from one sample is only as good as that sample
    w_acc = _gate(acc_e, c)
    w_acc = (w_acc + start * (1.0 - w_acc)) * fa

    # --- bias at rest, then gyro propagation: q <- q (x) exp((g - b) dt / 2) (series to th^4: error below
    # th^6 / 46080 for the rotation angle th of one step, < 1e-10 up to 0.12 rad per step = 2000 deg/s at 285 Hz)
    kb = w_rest * c.k_bias_rest
    bx, by, bz = bx + kb * (glx - bx), by + kb * (gly - by), bz + kb * (glz - bz)
    wx, wy, wz = gx - bx, gy - by, gz - bz
    dt = c.dt
    th2 = (wx * wx + wy * wy + wz * wz) * (dt * dt)
    cos_h = 1.0 + th2 * (-1.0 / 8.0 + th2 * (1.0 / 384.0))
    sinc_h = (0.5 + th2 * (-1.0 / 48.0 + th2 * (1.0 / 3840.0))) * dt  # sin(th / 2) / |w|
    q = so3.quat_multiply_parts((qw, qx, qy, qz), (cos_h, sinc_h * wx, sinc_h * wy, sinc_h * wz))

    # --- inclination: acc low-passed in the quasi-inertial frame (every valid sample, so that linear accelerations
    # average out), then the rotation that brings the low-passed vector up, applied to the fraction w_acc ---
    aex, aey, aez = _rot_c(q, (ax, ay, az))
    # the low-pass step owed since the last present reading: 1 - prod(1 - k_acc) over those steps (k_acc itself,
    # bit for bit, when every step has a reading), so the time constant holds for a slower or gappy accelerometer
    acc_gain = acc_gain + c.k_acc * (1.0 - acc_gain)
    k1 = acc_gain * fa
    l1x, l1y, l1z = l1x + k1 * (aex - l1x), l1y + k1 * (aey - l1y), l1z + k1 * (aez - l1z)
    k2 = c.k_acc_2
    l2x, l2y, l2z = l2x + k2 * (l1x - l2x), l2y + k2 * (l1y - l2y), l2z + k2 * (l1z - l2z)
    n2 = jnp.sqrt(jnp.maximum(l2x * l2x + l2y * l2y + l2z * l2z, 1e-30))
    nx, ny, nz = l2x / n2, l2y / n2, l2z / n2
    cw = jnp.sqrt(jnp.maximum(0.5 * (1.0 + nz), 1e-12))
    cx, cy = 0.5 * ny / cw, -0.5 * nx / cw  # (cw, cx, cy, 0) rotates lp2 onto +z
    # the fraction w_acc of it (normalised linear interpolation from the identity; exact at 0 and 1)
    cw, cx, cy = 1.0 - w_acc + w_acc * cw, w_acc * cx, w_acc * cy
    inv_c = 1.0 / jnp.sqrt(cw * cw + cx * cx + cy * cy)
    cw, cx, cy = cw * inv_c, cx * inv_c, cy * inv_c
    corr = (cw, cx, cy, zero)
    qa = qaw, qax, qay, qaz = so3.quat_multiply_parts(corr, q)
    l1x, l1y, l1z = _rot_c(corr, (l1x, l1y, l1z))
    l2x, l2y, l2z = _rot_c(corr, (l2x, l2y, l2z))

    # --- heading: horizontal projection of the magnetometer only, rotation about ENU z ---
    mex, mey, mez = _rot_c(qa, (mx, my, mz))
    mnorm = jnp.sqrt(mx * mx + my * my + mz * mz)
    sdip = mez / mnorm  # sin(dip)
    # the gate's input: norm and sin(dip) low-passed over tau_mag_gate (k = 1 exactly when it is 0: as read)
    kg = c.k_mag_gate * fm
    mnl = jnp.where(kg >= 1.0, mnorm, mnl + kg * (mnorm - mnl))
    sdl = jnp.where(kg >= 1.0, sdip, sdl + kg * (sdip - sdl))
    dn = (mnl - mref) * c.inv_mag_norm_th / mref
    # dip deviation (rad) to first order: d sin(dip) / cos(dip_ref)
    dd = (sdl - sref) * c.inv_mag_dip_th / jnp.sqrt(jnp.maximum(1.0 - sref * sref, 1e-6))
    # the dip is read in the estimated frame: during the start-up (weight ``start``) the inclination is still
    # settling, so the dip term does not gate and the dip reference follows the field as read; the norm, which
    # does not depend on the estimate, gates and is learnt as always (a disturbance then is still rejected)
    mag_e = jnp.where(mag_ok, _hold(mag_e, dn * dn + (1.0 - start) ** 2 * dd * dd, c.dec_mag), mag_e)
    w_mag = _gate(mag_e, c) * fm
    psi = jnp.arctan2(mex, mey)
    mag_gain = mag_gain + c.k_mag * (1.0 - mag_gain)  # as acc_gain: the heading step owed since the last reading
    theta = w_mag * mag_gain * psi  # |theta| <= pi (1 - exp(-gap / tau_mag)), gap = time since the last reading
    # the reference's time constant likewise, to first order in gap / tau_mag_ref (exact when every step has one)
    kref = w_mag * c.k_mag_ref * (mag_gain / jnp.where(c.k_mag > 0, c.k_mag, 1.0))
    kref_dip = kref + w_mag * start * (1.0 - kref)
    mref, sref = mref + kref * (mnorm - mref), sref + kref_dip * (sdip - sref)
    qw, qx, qy, qz = so3.quat_multiply_parts(
        (one, zero, zero, 0.5 * theta), qa
    )  # small rotation about z, to first order
    inv_n = 1.0 / jnp.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    # the same rotation for the low-pass states: (1, 0, 0, theta / 2) / |.| turns by phi with
    # cos(phi) = (1 - theta^2 / 4) / (1 + theta^2 / 4), sin(phi) = theta / (1 + theta^2 / 4)
    d = 1.0 / (1.0 + 0.25 * theta * theta)
    ct, st = (1.0 - 0.25 * theta * theta) * d, theta * d

    # --- motion bias: integral of the inclination corrections (Mahony et al. 2008), sensor frame. Anti-windup: the
    # integrator sees a step's correction saturated at _PHI_SAT rad (x / sqrt(1 + (x / x_max)^2)), so that
    # converging from a large error does not wind the bias up. The heading corrections do not feed the bias: a
    # bias change along today's vertical would tilt the estimate once the sensor turns. ---
    sx, sy = 2.0 * cx, 2.0 * cy  # acc correction rotation vector (ENU, horizontal)
    fa_b = c.inv_bias / jnp.sqrt(1.0 + (sx * sx + sy * sy) * (1.0 / (_PHI_SAT * _PHI_SAT)))
    pbx, pby, pbz = _rot_inv_c(qa, (sx * fa_b, sy * fa_b, zero))
    bx = jnp.clip(bx - pbx, -c.bias_max, c.bias_max)
    by = jnp.clip(by - pby, -c.bias_max, c.bias_max)
    bz = jnp.clip(bz - pbz, -c.bias_max, c.bias_max)

    return (
        qw * inv_n,
        qx * inv_n,
        qy * inv_n,
        qz * inv_n,
        bx,
        by,
        bz,
        ct * l1x - st * l1y,
        st * l1x + ct * l1y,
        l1z,
        ct * l2x - st * l2y,
        st * l2x + ct * l2y,
        l2z,
        glx,
        gly,
        glz,
        abx,
        aby,
        abz,
        rest_e,
        acc_e,
        mag_e,
        mref,
        sref,
        acc_gain * (1.0 - fa),
        mag_gain * (1.0 - fm),
        mnl,
        sdl,
        start * (1.0 - c.k_start),
        w_mag,
        w_acc,
        w_rest,
        psi,
    )


def _flatten_state(s: State) -> tuple:
    sp = lambda v: tuple(v[..., i] for i in range(v.shape[-1]))  # noqa: E731
    return (
        *sp(s.q),
        *sp(s.bias),
        *sp(s.acc_lp),
        *sp(s.acc_lp2),
        *sp(s.gyr_lp),
        *sp(s.acc_lp_body),
        s.rest_e,
        s.acc_e,
        s.mag_e,
        s.mag_norm_ref,
        s.mag_sin_dip_ref,
        s.acc_gain,
        s.mag_gain,
        s.mag_norm_lp,
        s.mag_sin_dip_lp,
        s.start,
    )


def _unflatten_state(t, f) -> State:
    st = lambda i, j: jnp.stack(f[i:j], axis=-1)  # noqa: E731
    return State(
        t=t,
        q=st(0, 4),
        bias=st(4, 7),
        acc_lp=st(7, 10),
        acc_lp2=st(10, 13),
        gyr_lp=st(13, 16),
        acc_lp_body=st(16, 19),
        rest_e=f[19],
        acc_e=f[20],
        mag_e=f[21],
        mag_norm_ref=f[22],
        mag_sin_dip_ref=f[23],
        acc_gain=f[24],
        mag_gain=f[25],
        mag_norm_lp=f[26],
        mag_sin_dip_lp=f[27],
        start=f[28],
    )


def _split3(v):
    return v[..., 0], v[..., 1], v[..., 2]


# ------------------------------------------------------------------------------------------------------------
# Observer interface
# ------------------------------------------------------------------------------------------------------------
def quat_from_acc_mag_enu(acc, mag):
    """Sensor-to-ENU quaternion(s) (..., 4), (w, x, y, z), from accelerometer ("up" at rest) and magnetometer
    samples (..., 3) (TRIAD: up = a / |a|, east = m x up / |.|, north = up x east; rows of R: east, north, up)."""
    return so3.quat_canonical(so3.matrix_to_quat(so3.triad(acc, mag, "ENU")))


def _init(p: Params, sample: ImuSample) -> State:
    """State at the first sample (broadcasts over leading batch axes of the sample)."""
    if sample.acc is None or sample.mag is None:
        raise ValueError("robust_ahrs needs acc and mag samples")
    dtype = jnp.result_type(p.tau_acc)
    gyr = jnp.asarray(sample.gyr, dtype)
    acc, mag = jnp.asarray(sample.acc, dtype), jnp.asarray(sample.mag, dtype)
    acc_ok, mag_ok = so3.present(acc)[..., None], so3.present(mag)[..., None]
    acc_s = jnp.where(acc_ok, acc, jnp.array([0.0, 0.0, 1.0], dtype) * p.gravity)
    # a stand-in field, not parallel to acc_s, when a sample is missing
    mag_s = jnp.where(mag_ok & acc_ok, mag, jnp.array([0.0, 1.0, -1.0], dtype))
    q0 = quat_from_acc_mag_enu(acc_s, mag_s)
    mnorm = jnp.sqrt(jnp.sum(mag_s * mag_s, axis=-1))
    sdip = jnp.sum(mag_s * so3.unit(acc_s), axis=-1) / mnorm  # sin(dip) = m . up / |m|
    anorm = jnp.sqrt(jnp.sum(acc_s * acc_s, axis=-1))
    zero = jnp.zeros_like(anorm)
    return State(
        t=jnp.asarray(sample.t, dtype),
        q=q0,
        bias=jnp.zeros_like(acc_s),
        acc_lp=jnp.stack([zero, zero, anorm], axis=-1),
        acc_lp2=jnp.stack([zero, zero, anorm], axis=-1),
        gyr_lp=jnp.where(jnp.isfinite(gyr), gyr, 0.0),
        acc_lp_body=acc_s,
        rest_e=jnp.full_like(anorm, 2.0),
        acc_e=zero,
        mag_e=zero,
        mag_norm_ref=mnorm,
        mag_sin_dip_ref=sdip,
        acc_gain=zero,
        mag_gain=zero,
        mag_norm_lp=mnorm,
        mag_sin_dip_lp=sdip,
        start=jnp.ones_like(anorm),
    )


def _step(p: Params, s: State, sample, dt):
    u = sample.start if isinstance(sample, Interval) else sample
    dtype = s.q.dtype
    if isinstance(p, Coeffs):  # precomputed (e.g. hoisted out of a scan); its dt is used
        c = Coeffs(*(jnp.asarray(v, dtype) for v in p))
    else:
        c = coefficients(Params(*(jnp.asarray(v, dtype) for v in p)), jnp.asarray(dt, dtype))
    nan3 = jnp.full(s.q.shape[:-1] + (3,), jnp.nan, dtype)
    acc = jnp.asarray(u.acc, dtype) if u.acc is not None else nan3
    mag = jnp.asarray(u.mag, dtype) if u.mag is not None else nan3
    f = _core(c, _flatten_state(s), _split3(jnp.asarray(u.gyr, dtype)), _split3(acc), _split3(mag))
    t = s.t + c.dt
    new = _unflatten_state(t, f)
    w_mag, w_acc, w_rest, psi = f[_N_STATE:]
    out = Out(
        t=t,
        q=new.q,
        r=so3.quat_to_matrix(new.q),
        bias=new.bias,
        mag_disturbed=w_mag < 0.5,
        acc_rejected=w_acc < 0.5,
        rest=w_rest > 0.5,
        mag_weight=w_mag,
        acc_weight=w_acc,
        rest_weight=w_rest,
        heading_error=psi,
    )
    return new, out


def _output(p: Params, s: State) -> Out:
    """The estimate held by ``s``: the gates from its held deviations, no heading correction yet."""
    dtype = s.q.dtype
    lo = jax.nn.sigmoid(-jnp.asarray(p.gate_sharpness, dtype))
    c = Coeffs(*([jnp.zeros((), dtype)] * len(Coeffs._fields)))._replace(
        sharpness=jnp.asarray(p.gate_sharpness, dtype), gate_lo=lo, gate_scale=1.0 / (1.0 - 2.0 * lo)
    )
    w_mag, w_acc, w_rest = _gate(s.mag_e, c), _gate(s.acc_e, c), _gate(s.rest_e, c)
    return Out(
        t=s.t,
        q=s.q,
        r=so3.quat_to_matrix(s.q),
        bias=s.bias,
        mag_disturbed=w_mag < 0.5,
        acc_rejected=w_acc < 0.5,
        rest=w_rest > 0.5,
        mag_weight=w_mag,
        acc_weight=w_acc,
        rest_weight=w_rest,
        heading_error=jnp.zeros_like(s.mag_e),
    )


def _time_reversed(p: Params) -> Params:
    """The params on the time-reversed recording (offline mode's backward pass): the magnetometer, ``mag_delay``
    s behind the gyro, is that much *ahead* of it when time runs backwards."""
    return p._replace(mag_delay=-p.mag_delay)


_OBSERVER = Observer(_init, _step, "robust_ahrs", _output, _time_reversed, hold="next")


def make_observer() -> Observer:
    """The robust AHRS as ``Observer(init, step, "robust_ahrs")`` (see the module docstring).

    ``init(params, first_sample) -> State`` (TRIAD start); ``step(params, state, sample, dt) -> (State, Out)``
    processes ``sample`` (gyro over the step, then acc, then mag) and returns the estimate at ``state.t + dt`` (on
    recorded data the engine hands it the newest sample, hold "next"). An :class:`jaxatt.types.Interval` input is
    processed with its start sample. Both
    broadcast over leading batch axes (the step is elementwise), and both vmap.
    """
    return _OBSERVER


# ------------------------------------------------------------------------------------------------------------
# Registry
# ------------------------------------------------------------------------------------------------------------
def check_params(p: Params) -> None:
    """Raise ValueError naming the first parameter that is not a finite positive scalar (``mag_delay``: a finite
    scalar of at most 1 s either way; ``tau_mag_gate``: any finite scalar, <= 0 meaning off)."""
    for name in PARAM_NAMES:
        v = np.asarray(getattr(p, name), float)
        if name == "tau_mag_gate":
            if v.shape != () or not np.isfinite(v):
                raise ValueError(
                    f"robust AHRS parameter tau_mag_gate must be a finite number of seconds, got {shown(v)}"
                )
        elif name == "mag_delay":
            if v.shape != () or not np.isfinite(v) or abs(v) > 1.0:
                raise ValueError(
                    f"robust AHRS parameter mag_delay must be a finite number of seconds in [-1, 1], got {shown(v)}"
                )
        elif v.shape != () or not np.isfinite(v) or v <= 0:
            raise ValueError(f"robust AHRS parameter {name} must be a finite positive number, got {shown(v)}")


_UNITS = dict(
    tau_acc="s",
    tau_acc_2="s",
    tau_mag="s",
    tau_bias="s",
    tau_bias_rest="s",
    tau_rest="s",
    rest_hold="s",
    rest_th_gyr="rad/s",
    rest_th_acc="m/s^2",
    acc_th="m/s^2",
    acc_hold="s",
    mag_norm_th="1",
    mag_dip_th="rad",
    mag_hold="s",
    tau_mag_ref="s",
    gravity="m/s^2",
    gate_sharpness="1",
    bias_max="rad/s",
    mag_delay="s",
    tau_mag_gate="s",
)
_BOUNDS = dict(
    tau_acc=(0.05, 30.0),
    tau_acc_2=(1e-3, 30.0),
    tau_mag=(0.5, 200.0),
    tau_bias=(1.0, 1e4),
    tau_bias_rest=(0.1, 100.0),
    tau_rest=(0.05, 10.0),
    rest_hold=(0.05, 20.0),
    rest_th_gyr=(0.1 * _DEG, 20 * _DEG),
    rest_th_acc=(0.02, 5.0),
    acc_th=(0.5, 200.0),
    acc_hold=(0.005, 5.0),
    mag_norm_th=(0.01, 2.0),
    mag_dip_th=(0.5 * _DEG, 90 * _DEG),
    mag_hold=(0.01, 20.0),
    tau_mag_ref=(1.0, 1e4),
)


def _param_docs() -> dict:
    doc = Params.__doc__ or ""
    if "Fields:" not in doc:  # docstrings stripped (python -OO)
        return dict.fromkeys(PARAM_NAMES, "")
    lines = doc.split("Fields:")[1].strip().splitlines()
    docs, name = {}, None
    for ln in lines:
        head = ln.strip().split(":", 1)
        if len(head) == 2 and head[0] in PARAM_NAMES:
            name = head[0]
            docs[name] = head[1].strip()
        elif name:
            docs[name] += " " + ln.strip()
    return docs


_DOCS = _param_docs()

#: Share of a recording's samples above which :func:`_advise` says the magnetic gate was shut.
GATE_SHUT_WARNING = 0.5


def _advise(p: Params, outputs: dict, samples):
    """The registry entry's ``advise``: when the gate, without ``tau_mag_gate``, rejected the magnetometer in more than
    :data:`GATE_SHUT_WARNING` of the samples with a field reading (a disturbed place, or a magnetometer noisier than
    the thresholds: 2 uT of noise on a 45-uT field shuts the shipped gate in 97 % of them), a line naming
    ``tau_mag_gate``; else None. Samples without a reading (NaN rows: a slower magnetometer, or none) are not
    counted: the gate has nothing to accept there."""
    shut = outputs.get("mag_disturbed")
    if shut is None or len(shut) < 2 or float(np.asarray(p.tau_mag_gate)) > 0 or samples.mag is None:
        return None
    from ..api import _valid_rows  # the front door's "a reading is present" (imported when it runs: no cycle)

    read = _valid_rows(np.asarray(samples.mag, float))[1:]
    if not read.any():
        return None
    frac = float(np.mean(np.asarray(shut[1:])[read] > 0.5))
    if frac <= GATE_SHUT_WARNING:
        return None
    return (
        f"the magnetometer was rejected as disturbed in {100 * frac:.0f} % of its readings (heading from the gyro "
        "alone there). If the field is not disturbed but the magnetometer is noisy, low-pass what the gate sees: "
        "params={'tau_mag_gate': 0.1} (s)"
    )


ENTRIES = (
    registry.Entry(
        name="robust",
        summary="real-data 9D AHRS: inclination from low-passed acc, heading from mag only, rest-based bias, learnable "
        "magnetic-disturbance and acceleration gates; ships gains tuned on BROAD",
        reference="Mahony et al. 2008 / Trumpf et al. 2012 structure, VQF-style gating (Laidig & Seel 2023)",
        make=make_observer,
        default_params=default_params,
        gains=tuple(
            registry.Gain(f, _UNITS[f], _DOCS[f], "positive", f in TUNABLE, _BOUNDS.get(f))
            if f not in ("mag_delay", "tau_mag_gate")
            else registry.Gain(f, _UNITS[f], _DOCS[f], "real", f in TUNABLE, scale=0.01 if f == "mag_delay" else 0.1)
            for f in PARAM_NAMES
        ),
        frame="ENU",
        shipped="robust_broad_all.json",
        module="robust_ahrs",
        check=check_params,
        init_reads=("acc", "mag"),
        advise=_advise,
    ),
)
