"""Mahony's explicit complementary filter with gyro-bias estimation, as run by the BROAD benchmark.

References:

* R. Mahony, T. Hamel, J.-M. Pflimlin, "Nonlinear complementary filters on the special orthogonal group",
  IEEE Trans. Automatic Control 53(5), 2008: the *explicit complementary filter with bias correction*,
  dR/dt = R (Omega_y - b + kP w_mes)x,  db/dt = -kI w_mes,  w_mes = sum_i k_i v_i x v^_i.
* J. Trumpf, R. Mahony, T. Hamel, C. Lageman, "Analysis of non-linear attitude observers for time-varying
  reference measurements", IEEE TAC 2012:
  the observer is their eq. (10) (the passive / explicit complementary filter) with n1 = 2 body-frame measurements
  a_1 = acc, a_2 = mag, n2 = 0, gains k_i = Kp and *constant* references a_1 = e_z, a_2 = b, plus Mahony's
  integral bias estimate (eq. 10 itself has no bias term).
* D. Laidig et al., "BROAD - A Benchmark for Robust Inertial Orientation Estimation", Data 6(7), 2021 and its
  public example code (dlaidig/broad, ``example_code/``), which runs S. Madgwick's C implementation of this
  filter (MahonyAHRS.cpp) in float32. This module reproduces that implementation operation by operation.

What one step computes (time step dt, sample = gyro y, accelerometer a, magnetometer m, all body frame):

1. a_bar = a / |a|, m_bar = m / |m|.
2. Estimated directions in the body frame: v^ = R^T e_z (gravity, "up"), and the magnetic reference is
   re-estimated every step from the measurement itself (Madgwick's variant):  h = R m_bar (field in the filter's
   earth frame), b = (sqrt(h_x^2 + h_y^2), 0, h_z), w^ = R^T b.  Its term m_bar x w^ = R^T (h x b) is mostly
   about the vertical (heading); it has a tilt component proportional to h_z when h is far from b (large
   heading errors), so the magnetometer is not fully decoupled from inclination.
3. w_mes = a_bar x v^ + m_bar x w^   (Mahony's omega_mes with k_1 = k_2 = 1).
4. Integral ("bias") term, updated *before* use:  xi <- xi + Ki w_mes dt   (xi = -b^, b^ the gyro-bias estimate).
5. Omega = y + xi + Kp w_mes.
6. q <- normalise(q + dt/2 q (x) (0, Omega))   (explicit Euler on the quaternion, then renormalisation).

(The C code stores 2 Kp, 2 Ki and half vectors v^/2, w^/2, e/2; the products are the same.) If Ki <= 0 the
integral is reset to zero, as in the C code.

Frames and conventions:

* The filter's internal earth frame is **NWU** (x = horizontal magnetic north, y = west, z = up): that is what
  the magnetic reference (b_x, 0, b_z) and gravity along +z imply. ``State.q`` is sensor-to-NWU.
  ``Out.q`` / ``Out.r`` are rotated into **ENU** (sensor-to-ENU), exactly as BROAD's example code does:
  q_ENU = q_z(+90 deg) (x) q_NWU.
* Quaternions Hamilton, scalar first (w, x, y, z); R maps sensor coordinates to the earth frame.
* Units: gyro rad/s, acc any unit (normalised), mag any unit (normalised), dt s, Kp 1/s, Ki 1/s^2.

Initial orientation (``make_observer(init_mode=...)``):

* ``"broad"``: exactly BROAD's ``quatFromAccMag(acc[0], mag[0])``: z = a, x = (z x -m) x z, y = z x x,
  R0 = [x/|x|, y/|y|, z/|z|] (as columns), q0 = BROAD's ``quatFromRotMat(R0)`` (w >= 0, signs of the other
  components from the off-diagonal differences). R0's columns are the axes of a south-east-up frame written in
  sensor coordinates (an earth-to-sensor matrix), which the filter reads as sensor-to-NWU: with R the true
  sensor-to-NWU rotation the start is R^T diag(-1, -1, 1). That is right only when R^2 = diag(-1, -1, 1), i.e. for
  a level sensor whose x axis points to magnetic east or west - roughly how the BROAD trials start (start errors
  1-9 deg against the optical truth); for a level sensor facing north it is 180 deg off, and from there the
  filter lingers for minutes near a tilted spurious equilibrium (the gravity term balancing the tilt part of
  the magnetometer term; measured: still 177 deg off after 60 s with Kp = 2 and gyro noise). On BROAD the filter
  converges in the rest phase before the scored ``movement`` samples, and the published numbers include this
  start, so it is kept for reproduction. Use "triad" on other data.
* ``"triad"`` (default; "broad" was the default before): the correct sensor-to-NWU orientation from
  the same two vectors (rows: north, west, up in sensor coordinates), so that the filter starts converged.

Missing samples (NaN in a log; also all-zero vectors, which the C code treats as missing):

* a missing accelerometer sample drops the gravity term of w_mes for that step;
* a missing magnetometer sample drops the magnetic term (the C code then runs its IMU-only update, which is the
  same thing);
* with both missing the step integrates the bias-corrected gyro (Omega = y + xi) and the integral is unchanged.
  (Deliberate differences from the C code, which skips its whole feedback block when the accelerometer is all
  zero: there a valid magnetometer sample is skipped too, and the bias estimate is not applied in that step.
  Neither case occurs in BROAD's data.)
* a missing (non-finite) gyro sample is replaced by the last valid one (``State.gyr_last``).

The first sample: a non-finite acc or mag there gives the identity quaternion (sensor = NWU) as start.

Everything is pure JAX (jit / vmap / grad over ``Params``); the normalisations use gradient-safe norms.
In float32 the step performs the same floating-point operations in the same order as MahonyAHRS.cpp.
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
    "make_observer",
    "default_params",
    "BROAD_TAGP",
    "quat_from_acc_mag_broad",
    "quat_from_acc_mag_triad",
    "Q_ENU_FROM_NWU",
    "nwu_to_enu",
]

#: (Kp, Ki) of BROAD's "TAGP" (lowest average total RMSE over all 39 trials on their grid).
BROAD_TAGP = (0.74, 0.0012)

#: q_z(+90 deg): rotation from the filter's NWU earth frame to ENU (BROAD's example code).
Q_ENU_FROM_NWU = (0.7071067811865475, 0.0, 0.0, 0.7071067811865475)


class Params(NamedTuple):
    """Gains (a pytree of scalars; vmap over them for a grid).

    Fields:
        kp: proportional gain Kp (1/s), > 0.
        ki: integral gain Ki (1/s^2), >= 0 (0 disables bias estimation).
    """

    kp: ArrayLike
    ki: ArrayLike


class State(NamedTuple):
    """Filter state at time ``t`` (s).

    Fields:
        t: time (s) of the estimate.
        q: (4,) sensor-to-NWU unit quaternion (w, x, y, z) (the C code's q0..q3).
        integral: (3,) integral feedback xi = Ki * int(w_mes) (rad/s, body); the gyro-bias estimate is -xi.
        gyr_last: (3,) last finite gyro sample (rad/s), used when a gyro sample is missing.
    """

    t: jax.Array
    q: jax.Array
    integral: jax.Array
    gyr_last: jax.Array


class Out(NamedTuple):
    """Estimate at time ``t`` (s).

    Fields:
        t: time (s) the estimate refers to (the end of the step).
        q: (4,) sensor-to-ENU quaternion (w, x, y, z).
        r: (3, 3) sensor-to-ENU rotation matrix (v_ENU = r @ v_sensor).
        q_nwu: (4,) the filter's own sensor-to-NWU quaternion.
        bias: (3,) gyro-bias estimate b^ = -xi (rad/s, sensor frame): the filter integrates gyr - bias + Kp w_mes.
        err: (3,) the correction w_mes = a_bar x v^ + m_bar x w^ used in this step (rad, sensor frame).
        acc_used, mag_used: whether the accelerometer / magnetometer sample entered this step (diagnostics).
    """

    t: jax.Array
    q: jax.Array
    r: jax.Array
    q_nwu: jax.Array
    bias: jax.Array
    err: jax.Array
    acc_used: jax.Array
    mag_used: jax.Array


def default_params(kp: float = BROAD_TAGP[0], ki: float = BROAD_TAGP[1], dtype=None) -> Params:
    """Params(kp, ki) as arrays; defaults are BROAD's TAGP gains (Kp = 0.74 1/s, Ki = 0.0012 1/s^2)."""
    dtype = dtype or jnp.result_type(float)
    return Params(jnp.asarray(kp, dtype), jnp.asarray(ki, dtype))


def nwu_to_enu(q_nwu: jax.Array) -> jax.Array:
    """Sensor-to-NWU quaternion(s) (..., 4) -> sensor-to-ENU: q_z(+90 deg) (x) q (as BROAD's example code)."""
    return so3.quat_multiply(jnp.asarray(Q_ENU_FROM_NWU, q_nwu.dtype), q_nwu)


# ------------------------------------------------------------------------------------------------------------
# Initial orientation
# ------------------------------------------------------------------------------------------------------------
def _quat_from_rotmat_broad(r: jax.Array) -> jax.Array:
    """BROAD's ``quatFromRotMat``: w = sqrt((1 + tr)/4) >= 0, |x|, |y|, |z| from the diagonal, signs from the
    off-diagonal differences (copysign). The square roots are clipped at 0 against rounding."""
    w_sq = (1 + r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]) / 4
    x_sq = (1 + r[..., 0, 0] - r[..., 1, 1] - r[..., 2, 2]) / 4
    y_sq = (1 - r[..., 0, 0] + r[..., 1, 1] - r[..., 2, 2]) / 4
    z_sq = (1 - r[..., 0, 0] - r[..., 1, 1] + r[..., 2, 2]) / 4
    s = lambda v: jnp.sqrt(jnp.maximum(v, 0.0))  # noqa: E731
    return jnp.stack(
        [
            s(w_sq),
            jnp.copysign(s(x_sq), r[..., 2, 1] - r[..., 1, 2]),
            jnp.copysign(s(y_sq), r[..., 0, 2] - r[..., 2, 0]),
            jnp.copysign(s(z_sq), r[..., 1, 0] - r[..., 0, 1]),
        ],
        axis=-1,
    )


def quat_from_acc_mag_broad(acc: jax.Array, mag: jax.Array) -> jax.Array:
    """BROAD's ``quatFromAccMag`` (example_code/broad_utils.py), used to start their filters.

    z = acc, x = (z x -mag) x z, y = z x x, R0 = columns [x/|x|, y/|y|, z/|z|], q = quatFromRotMat(R0).
    See the module docstring: the result is *not* the sensor-to-NWU orientation in general (R0 is the
    earth-to-sensor matrix of a south-east-up frame); it is what BROAD's published numbers start from.
    """
    z = acc
    x = so3.cross(so3.cross(z, -mag), z)
    y = so3.cross(z, x)
    r = jnp.stack([so3.unit(x), so3.unit(y), so3.unit(z)], axis=-1)
    return _quat_from_rotmat_broad(r)


def quat_from_acc_mag_triad(acc: jax.Array, mag: jax.Array) -> jax.Array:
    """Sensor-to-NWU quaternion from one accelerometer (specific force, "up" at rest) and magnetometer sample
    (:func:`jaxatt.so3.triad`)."""
    return so3.quat_canonical(so3.matrix_to_quat(so3.triad(acc, mag, "NWU")))


def valid_vector(v: jax.Array) -> jax.Array:
    """True where a sensor vector (..., 3) is usable: finite and not all zero (the C codes' "missing";
    :func:`jaxatt.so3.present`)."""
    return so3.present(v)


def start_quaternion(sample: ImuSample, fn=quat_from_acc_mag_triad) -> jax.Array:
    """The start of the NWU C filters (Mahony, Madgwick): ``fn(acc, mag)`` of the first sample, in the sample's
    precision; the identity (sensor = NWU) when either vector is missing."""
    if sample.acc is None or sample.mag is None:
        raise ValueError("this filter needs acc and mag samples")
    dtype = jnp.asarray(sample.gyr).dtype
    acc, mag = jnp.asarray(sample.acc, dtype), jnp.asarray(sample.mag, dtype)
    ok = valid_vector(acc) & valid_vector(mag)
    acc_s = jnp.where(ok, acc, jnp.array([0.0, 0.0, 1.0], dtype))
    mag_s = jnp.where(ok, mag, jnp.array([1.0, 0.0, 0.0], dtype))
    return jnp.where(ok, fn(acc_s, mag_s), jnp.array([1.0, 0.0, 0.0, 0.0], dtype))


def step_inputs(sample, gyr_last, dtype):
    """(gyr, acc, mag, acc_ok, mag_ok) of a step of the NWU C filters: an Interval is processed with its start
    sample; a non-finite gyro sample is replaced by ``gyr_last``; an absent acc / mag is NaN (missing)."""
    u = sample.start if isinstance(sample, Interval) else sample
    gyr = jnp.asarray(u.gyr, dtype)
    gyr = jnp.where(jnp.all(jnp.isfinite(gyr)), gyr, gyr_last)
    acc = jnp.asarray(u.acc, dtype) if u.acc is not None else jnp.full(3, jnp.nan, dtype)
    mag = jnp.asarray(u.mag, dtype) if u.mag is not None else jnp.full(3, jnp.nan, dtype)
    return gyr, acc, mag, valid_vector(acc), valid_vector(mag)


# ------------------------------------------------------------------------------------------------------------
# The update of MahonyAHRS.cpp, written in the same operation order
# ------------------------------------------------------------------------------------------------------------


def _normalize_c(v: jax.Array, ok: jax.Array) -> jax.Array:
    """v * (1/sqrt(vx*vx + vy*vy + vz*vz)) as in the C code; a safe unit vector where ``ok`` is False."""
    safe = jnp.where(ok, v, jnp.array([0.0, 0.0, 1.0], v.dtype))
    recip = 1.0 / jnp.sqrt(safe[0] * safe[0] + safe[1] * safe[1] + safe[2] * safe[2])
    return safe * recip


def _update(q, integral, g, a, m, acc_ok, mag_ok, kp, ki, dt):
    """One MahonyAHRS::update / updateIMU step. Returns (q, integral, w_mes)."""
    two_kp = 2 * kp
    two_ki = 2 * ki
    ax, ay, az = _normalize_c(a, acc_ok)
    mx, my, mz = _normalize_c(m, mag_ok)
    q0, q1, q2, q3 = q[0], q[1], q[2], q[3]

    q0q0 = q0 * q0
    q0q1 = q0 * q1
    q0q2 = q0 * q2
    q0q3 = q0 * q3
    q1q1 = q1 * q1
    q1q2 = q1 * q2
    q1q3 = q1 * q3
    q2q2 = q2 * q2
    q2q3 = q2 * q3
    q3q3 = q3 * q3

    # Reference direction of the earth's magnetic field (projected onto the x-z plane of NWU).
    hx = 2.0 * (mx * (0.5 - q2q2 - q3q3) + my * (q1q2 - q0q3) + mz * (q1q3 + q0q2))
    hy = 2.0 * (mx * (q1q2 + q0q3) + my * (0.5 - q1q1 - q3q3) + mz * (q2q3 - q0q1))
    bxx = hx * hx + hy * hy
    bx_pos = bxx > 0
    bx = jnp.where(bx_pos, jnp.sqrt(jnp.where(bx_pos, bxx, 1.0)), 0.0)
    bz = 2.0 * (mx * (q1q3 - q0q2) + my * (q2q3 + q0q1) + mz * (0.5 - q1q1 - q2q2))

    # Estimated directions of gravity and magnetic field (halved).
    halfvx = q1q3 - q0q2
    halfvy = q0q1 + q2q3
    halfvz = q0q0 - 0.5 + q3q3
    halfwx = bx * (0.5 - q2q2 - q3q3) + bz * (q1q3 - q0q2)
    halfwy = bx * (q1q2 - q0q3) + bz * (q0q1 + q2q3)
    halfwz = bx * (q0q2 + q1q3) + bz * (0.5 - q1q1 - q2q2)

    # Error: sum of cross products of measured and estimated directions (terms of missing sensors dropped).
    za = jnp.where(acc_ok, 1.0, 0.0).astype(q.dtype)
    zm = jnp.where(mag_ok, 1.0, 0.0).astype(q.dtype)
    acc_ex = (ay * halfvz - az * halfvy) * za
    acc_ey = (az * halfvx - ax * halfvz) * za
    acc_ez = (ax * halfvy - ay * halfvx) * za
    mag_ex = (my * halfwz - mz * halfwy) * zm
    mag_ey = (mz * halfwx - mx * halfwz) * zm
    mag_ez = (mx * halfwy - my * halfwx) * zm
    # x * 1 and x * 0 are exact, and x + 0 == x: with both sensors this is the C code's expression.
    halfex = jnp.where(mag_ok, acc_ex + mag_ex, acc_ex)
    halfey = jnp.where(mag_ok, acc_ey + mag_ey, acc_ey)
    halfez = jnp.where(mag_ok, acc_ez + mag_ez, acc_ez)
    any_ok = acc_ok | mag_ok

    gx, gy, gz = g[0], g[1], g[2]
    # Integral feedback (reset to zero when Ki <= 0, as in the C code).
    ix = integral[0] + two_ki * halfex * dt
    iy = integral[1] + two_ki * halfey * dt
    iz = integral[2] + two_ki * halfez * dt
    use_i = two_ki > 0.0
    ix = jnp.where(use_i, jnp.where(any_ok, ix, integral[0]), 0.0)
    iy = jnp.where(use_i, jnp.where(any_ok, iy, integral[1]), 0.0)
    iz = jnp.where(use_i, jnp.where(any_ok, iz, integral[2]), 0.0)
    gx = jnp.where(use_i, gx + ix, gx)
    gy = jnp.where(use_i, gy + iy, gy)
    gz = jnp.where(use_i, gz + iz, gz)
    # With no valid vector the proportional term is skipped (halfe is zero then anyway; the C code skips the
    # whole block, bias included - here the bias estimate keeps being applied).
    gx = jnp.where(any_ok, gx + two_kp * halfex, gx)
    gy = jnp.where(any_ok, gy + two_kp * halfey, gy)
    gz = jnp.where(any_ok, gz + two_kp * halfez, gz)

    # Integrate the rate of change of the quaternion.
    half_dt = 0.5 * dt
    gx = gx * half_dt
    gy = gy * half_dt
    gz = gz * half_dt
    qa, qb, qc = q0, q1, q2
    q0 = q0 + (-qb * gx - qc * gy - q3 * gz)
    q1 = q1 + (qa * gx + qc * gz - q3 * gy)
    q2 = q2 + (qa * gy - qb * gz + q3 * gx)
    q3 = q3 + (qa * gz + qb * gy - qc * gx)

    recip = 1.0 / jnp.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    q_new = jnp.stack([q0 * recip, q1 * recip, q2 * recip, q3 * recip])
    w_mes = 2.0 * jnp.stack([halfex, halfey, halfez]) * any_ok.astype(q.dtype)
    return q_new, jnp.stack([ix, iy, iz]), w_mes


def make_observer(init_mode: str = "triad") -> Observer:
    """Mahony's explicit complementary filter with bias (MahonyAHRS.cpp as run by BROAD).

    Args:
        init_mode: "triad" (default: the sensor-to-NWU orientation from the first acc and mag samples) or
            "broad" (BROAD's quatFromAccMag start, which reproduces their numbers: 180 deg off for a level
            sensor facing north, see the module docstring; the default before).

    Returns ``Observer(init, step, "mahony")`` with
    ``init(params, first_sample) -> State`` and ``step(params, state, sample, dt) -> (State, Out)``: the step
    updates the estimate with ``sample`` (gyro, acc and mag) over ``dt`` and returns it at ``state.t + dt`` (on
    recorded data the engine hands it the newest sample, hold "next", as BROAD's C code). A
    :class:`jaxatt.types.Interval` input is processed with its start sample (an explicit-Euler filter).
    """
    if init_mode not in ("broad", "triad"):
        raise ValueError(f"init_mode must be 'broad' or 'triad', got {init_mode!r}")

    def init(p: Params, sample: ImuSample) -> State:
        gyr = jnp.asarray(sample.gyr)
        q0 = start_quaternion(sample, quat_from_acc_mag_broad if init_mode == "broad" else quat_from_acc_mag_triad)
        return State(
            t=jnp.asarray(sample.t, gyr.dtype),
            q=q0,
            integral=jnp.zeros(3, gyr.dtype),
            gyr_last=jnp.where(jnp.isfinite(gyr), gyr, 0.0),
        )

    def step(p: Params, s: State, sample, dt):
        dtype = s.q.dtype
        gyr, acc, mag, acc_ok, mag_ok = step_inputs(sample, s.gyr_last, dtype)
        dt = jnp.asarray(dt, dtype)
        q, integral, w_mes = _update(
            s.q, s.integral, gyr, acc, mag, acc_ok, mag_ok, jnp.asarray(p.kp, dtype), jnp.asarray(p.ki, dtype), dt
        )
        t = s.t + dt
        q_enu = nwu_to_enu(q)
        out = Out(
            t=t,
            q=q_enu,
            r=so3.quat_to_matrix(q_enu),
            q_nwu=q,
            bias=-integral,
            err=w_mes,
            acc_used=acc_ok,
            mag_used=mag_ok,
        )
        return State(t=t, q=q, integral=integral, gyr_last=gyr), out

    def output(p: Params, s: State) -> Out:
        """The estimate held by ``s`` (no measurement used yet)."""
        q_enu = nwu_to_enu(s.q)
        no = jnp.zeros((), bool)
        return Out(
            t=s.t,
            q=q_enu,
            r=so3.quat_to_matrix(q_enu),
            q_nwu=s.q,
            bias=-s.integral,
            err=jnp.zeros_like(s.integral),
            acc_used=no,
            mag_used=no,
        )

    return Observer(init, step, "mahony", output, hold="next")


# ------------------------------------------------------------------------------------------------------------
# Registry
# ------------------------------------------------------------------------------------------------------------
def check_params(p: Params) -> None:
    """kp > 0 and ki >= 0, finite scalars (ValueError otherwise)."""
    for name, strict in (("kp", True), ("ki", False)):
        v = np.asarray(getattr(p, name), float)
        if v.shape != () or not np.isfinite(v) or (v <= 0 if strict else v < 0):
            raise ValueError(f"Mahony {name} must be a finite number {'> 0' if strict else '>= 0'}, got {shown(v)}")


def _registry_observer() -> Observer:
    return make_observer("triad")


ENTRIES = (
    registry.Entry(
        name="mahony",
        summary="Mahony's explicit complementary filter with gyro bias (MahonyAHRS.cpp as run by BROAD), TRIAD start",
        reference="Mahony, Hamel, Pflimlin 2008; Trumpf et al. 2012 eq. (10); BROAD's example code",
        make=_registry_observer,
        default_params=lambda dtype=None: default_params(*BROAD_TAGP, dtype=dtype),
        gains=(
            registry.Gain("kp", "1/s", "proportional gain Kp", "positive", True, (1e-3, 50.0)),
            registry.Gain("ki", "1/s^2", "integral (gyro-bias) gain Ki", "positive", True, (1e-7, 10.0)),
        ),
        frame="ENU",
        module="mahony",
        check=check_params,
        init_reads=("acc", "mag"),
    ),
)
