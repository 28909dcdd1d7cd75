"""Madgwick's gradient-descent MARG filter, as implemented by the ``ahrs`` package (``ahrs.filters.Madgwick``).

References:

* S. O. H. Madgwick, "An efficient orientation filter for inertial and inertial/magnetic sensor arrays",
  report, University of Bristol, 2010. Equation numbers below are the report's, as the ``ahrs`` source cites them
  (not checked against the report's text here).
* M. Garcia, ``ahrs`` 0.4 (``ahrs/filters/madgwick.py``): ``Madgwick.updateMARG`` / ``updateIMU``. This module
  reproduces ``updateMARG`` in float64 (measured on BROAD trial 01: 20000 samples, max 7.2e-15 per quaternion
  component, ``tests/test_madgwick.py``).

What one step computes (time step dt, gain beta; gyro y, accelerometer a, magnetometer m, all body frame; q the
previous estimate):

1. q <- q / |q|; gyro quaternion derivative  q_dot_w = 1/2 q (x) (0, y)  (eq. 12).
2. a_bar = a / |a|, m_bar = m / |m|.
3. Magnetic distortion compensation: the measured field in the earth frame h = q (x) (0, m_bar) (x) q*
   (eq. 45), reference b = (sqrt(h_x^2 + h_y^2), 0, h_z) (eq. 46): the reference is re-estimated every step
   with the inclination of the measurement, so the field only acts on heading.
4. Objective function f_{g,b}(q, a_bar, b, m_bar) (eq. 31: the gravity rows f_g, eq. 25, with reference
   d = (0, 0, 1), stacked on the field rows f_b) and its Jacobian J_{g,b} (eq. 32: J_g, eq. 26, on J_b).
5. Gradient grad = J^T f (eq. 34), normalised; q_dot = q_dot_w - beta grad / |grad| (eq. 33).
6. Explicit Euler and renormalisation: q <- normalise(q + q_dot dt) (eq. 13).

The IMU-only update (``updateIMU``) is the same with the gravity rows only (f_g, J_g). ``ahrs`` skips the
correction when f = 0 exactly; here a zero gradient gives no correction (the same, without the 0/0 that ``ahrs``
would hit when f != 0 but J^T f = 0). No gyro-bias compensation (the report's second MARG gain zeta) - ``ahrs``
implements none either.

Frames and conventions:

* The filter's internal earth frame is **NWU** (x = horizontal magnetic north, y = west, z = up): that is what
  the gravity reference (0, 0, 1) (the specific force points up at rest) and the field reference (b_x, 0, b_z)
  imply. ``State.q`` is sensor-to-NWU (v_NWU = R(q) v_sensor), Hamilton, scalar first (w, x, y, z) - the same
  quaternion as ahrs' ``Q`` (``h = q m q*`` rotates a sensor vector into the earth frame).
* ``Out.q`` / ``Out.r`` are rotated into **ENU** (sensor-to-ENU) as the Mahony filter does:
  q_ENU = q_z(+90 deg) (x) q_NWU (:func:`jaxatt.observers.mahony.nwu_to_enu`); ``Out.q_nwu`` is the filter's own.
* Units: gyro rad/s, acc any unit (normalised), mag any unit (normalised), dt s, beta rad/s (the magnitude of the
  quaternion-derivative correction, 1/s; the report's beta = sqrt(3/4) times the mean gyro error per axis).
  Default beta = 0.041, ahrs' default for MARG (``gain_marg``; ``gain_imu`` is 0.033).

Initial orientation (``make_observer(init_mode="triad")``): sensor-to-NWU by TRIAD from the first acc and mag
sample (:func:`jaxatt.so3.triad`), w >= 0. ahrs' batch mode (``Madgwick(gyr=, acc=, mag=)``) starts from
``ecompass(acc[0], mag[0], frame='NED')``, whose rows are (a x m) x a, a x m, a: with the specific force pointing up
that is the same sensor-to-NWU matrix (agrees to ~1e-15), despite the 'NED' label. Note that ahrs 0.4 ignores
its ``q0=`` argument in MARG batch mode. A non-finite (or zero) first acc or mag gives the identity start.

Missing samples (NaN in a log; all-zero acc / mag vectors count as missing, as in ahrs and the C code):

* missing magnetometer -> the IMU-only update (ahrs' ``updateIMU``: gravity rows only);
* missing accelerometer -> pure gyro integration (ahrs skips the whole correction, magnetometer included,
  when |a| = 0);
* missing (non-finite) gyro -> the last valid gyro sample (``State.gyr_last``).
* Deliberate difference: an all-zero gyro sample is a zero rate here (the correction is still applied, as in
  Madgwick's C code); ahrs returns the quaternion unchanged then, skipping the correction. BROAD has no such
  sample.

Everything is pure JAX (jit / vmap / grad over ``Params``); normalisations are gradient-safe
(:func:`jaxatt.so3.unit`, guarded square roots), and missing readings are replaced before any arithmetic so no
NaN reaches a gradient. The step follows ahrs' operation order where reasonable (products written as ahrs'
``Quaternion.product``); sums of ``J^T f`` and the norms may round differently (ulps).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import so3
from ..types import ArrayLike, ImuSample, Observer, shown
from . import registry
from .mahony import nwu_to_enu, quat_from_acc_mag_triad, start_quaternion, step_inputs

__all__ = [
    "Params",
    "State",
    "Out",
    "make_observer",
    "default_params",
    "check_params",
    "BETA_MARG",
    "BETA_IMU",
    "quat_from_acc_mag_triad",
]

#: ahrs' default gains (``ahrs.filters.Madgwick``: ``gain_marg`` = 0.041, ``gain_imu`` = 0.033), rad/s.
BETA_MARG = 0.041
BETA_IMU = 0.033


class Params(NamedTuple):
    """Gains (a pytree of scalars; vmap over them for a grid).

    Fields:
        beta: gain of the normalised gradient step, eq. (33) (rad/s), > 0.
    """

    beta: ArrayLike


class State(NamedTuple):
    """Filter state at time ``t`` (s).

    Fields:
        t: time (s) of the estimate.
        q: (4,) sensor-to-NWU unit quaternion (w, x, y, z) (ahrs' ``Q[t]``).
        gyr_last: (3,) last finite gyro sample (rad/s), used when a gyro sample is missing.
    """

    t: jax.Array
    q: jax.Array
    gyr_last: jax.Array


class Out(NamedTuple):
    """Estimate at time ``t`` (s).

    Fields:
        t: time (s) the estimate refers to.
        q: (4,) sensor-to-ENU quaternion (w, x, y, z).
        r: (3, 3) sensor-to-ENU rotation matrix (v_ENU = r @ v_sensor).
        q_nwu: (4,) the filter's own sensor-to-NWU quaternion.
        acc_used, mag_used: whether the accelerometer / magnetometer sample entered this step (diagnostics;
            the magnetometer is used only together with the accelerometer).
    """

    t: jax.Array
    q: jax.Array
    r: jax.Array
    q_nwu: jax.Array
    acc_used: jax.Array
    mag_used: jax.Array


def default_params(beta: float = BETA_MARG, dtype=None) -> Params:
    """Params(beta) as an array; the default is ahrs' MARG gain 0.041 rad/s."""
    dtype = dtype or jnp.result_type(float)
    return Params(jnp.asarray(beta, dtype))


# ------------------------------------------------------------------------------------------------------------
# The update of ahrs' Madgwick.updateMARG / updateIMU
# ------------------------------------------------------------------------------------------------------------
def _update(q, g, a, m, acc_ok, mag_ok, beta, dt):
    """One ahrs ``updateMARG`` step (``updateIMU`` where the magnetometer is missing; gyro only where the
    accelerometer is missing). ``a`` and ``m`` are finite and non-zero (safe values substituted by the caller)."""
    dtype = q.dtype
    zero = jnp.zeros((), dtype)
    q = so3.unit(q)  # ahrs: Quaternion(q) normalises
    # Rate of change of the quaternion from the gyroscope (eq. 12).
    qdot = jnp.stack(so3.quat_multiply_parts(q, (zero, g[0], g[1], g[2])))
    qdot = 0.5 * qdot
    a = so3.unit(a)
    m = so3.unit(m)
    # Measured field in the earth frame (eq. 45) and its reference with the same inclination (eq. 46).
    qm = so3.unit(jnp.stack([zero, m[0], m[1], m[2]]))  # ahrs: Quaternion([0, *m]) normalises again
    qconj = (q[0], -q[1], -q[2], -q[3])
    h = so3.quat_multiply_parts(q, so3.quat_multiply_parts(qm, qconj))
    bxx = h[1] * h[1] + h[2] * h[2]
    bx_pos = bxx > 0
    bx = jnp.where(bx_pos, jnp.sqrt(jnp.where(bx_pos, bxx, 1.0)), 0.0)
    bz = h[3]
    qw, qx, qy, qz = so3.unit(q)  # ahrs: q / norm(q) once more
    # Objective function (eq. 25 for gravity, eq. 31 with the field rows).
    f = (
        2.0 * (qx * qz - qw * qy) - a[0],
        2.0 * (qw * qx + qy * qz) - a[1],
        2.0 * (0.5 - qx**2 - qy**2) - a[2],
        2.0 * bx * (0.5 - qy**2 - qz**2) + 2.0 * bz * (qx * qz - qw * qy) - m[0],
        2.0 * bx * (qx * qy - qw * qz) + 2.0 * bz * (qw * qx + qy * qz) - m[1],
        2.0 * bx * (qw * qy + qx * qz) + 2.0 * bz * (0.5 - qx**2 - qy**2) - m[2],
    )
    # Jacobian (eq. 26 for gravity, eq. 32 with the field rows).
    jac = (
        (-2.0 * qy, 2.0 * qz, -2.0 * qw, 2.0 * qx),
        (2.0 * qx, 2.0 * qw, 2.0 * qz, 2.0 * qy),
        (zero, -4.0 * qx, -4.0 * qy, zero),
        (-2.0 * bz * qy, 2.0 * bz * qz, -4.0 * bx * qy - 2.0 * bz * qw, -4.0 * bx * qz + 2.0 * bz * qx),
        (
            -2.0 * bx * qz + 2.0 * bz * qx,
            2.0 * bx * qy + 2.0 * bz * qw,
            2.0 * bx * qx + 2.0 * bz * qz,
            -2.0 * bx * qw + 2.0 * bz * qy,
        ),
        (2.0 * bx * qy, 2.0 * bx * qz - 4.0 * bz * qx, 2.0 * bx * qw - 4.0 * bz * qy, 2.0 * bx * qx),
    )
    # Gradient J^T f (eq. 34): gravity rows, then the field rows added (MARG) or not (IMU).
    grad_g = jnp.stack([jac[0][i] * f[0] + jac[1][i] * f[1] + jac[2][i] * f[2] for i in range(4)])
    grad_gb = jnp.stack(
        [
            jac[0][i] * f[0]
            + jac[1][i] * f[1]
            + jac[2][i] * f[2]
            + jac[3][i] * f[3]
            + jac[4][i] * f[4]
            + jac[5][i] * f[5]
            for i in range(4)
        ]
    )
    grad = jnp.where(mag_ok, grad_gb, grad_g)
    grad = so3.unit(grad)  # a zero gradient stays zero: no correction
    # Normalised gradient step with gain beta (eq. 33); none without a valid accelerometer sample.
    qdot = jnp.where(acc_ok, qdot - beta * grad, qdot)
    # Integrate (eq. 13) and renormalise.
    q_new = q + qdot * dt
    return so3.unit(q_new)


@functools.lru_cache(maxsize=None)
def make_observer(init_mode: str = "triad") -> Observer:
    """Madgwick's MARG filter (ahrs' ``Madgwick.updateMARG``). Cached: the same arguments give the same
    Observer (jitted runners are reused).

    Args:
        init_mode: "triad" (the only start: sensor-to-NWU from the first acc and mag samples, which is also
            ahrs' own batch start).

    Returns ``Observer(init, step, "madgwick", output)`` with ``init(params, first_sample) -> State`` and
    ``step(params, state, sample, dt) -> (State, Out)``: the step updates the estimate with ``sample`` (gyro,
    acc, mag) over ``dt`` seconds, as ``Q[t] = updateMARG(Q[t-1], gyr[t], acc[t], mag[t])`` (``hold="next"``). A
    :class:`jaxatt.types.Interval` input is processed with its start sample (the filter is an explicit-Euler,
    sample-and-hold filter by construction).
    """
    if init_mode != "triad":
        raise ValueError(f"init_mode must be 'triad', got {init_mode!r}")

    def init(p: Params, sample: ImuSample) -> State:
        gyr = jnp.asarray(sample.gyr)
        q0 = start_quaternion(sample)  # TRIAD in NWU; equals ahrs' ecompass(acc, mag, frame='NED') to rounding
        return State(t=jnp.asarray(sample.t, gyr.dtype), q=q0, gyr_last=jnp.where(jnp.isfinite(gyr), gyr, 0.0))

    def step(p: Params, s: State, sample, dt):
        dtype = s.q.dtype
        gyr, acc, mag, acc_ok, mag_ok = step_inputs(sample, s.gyr_last, dtype)
        acc_s = jnp.where(acc_ok, acc, jnp.array([0.0, 0.0, 1.0], dtype))
        mag_s = jnp.where(mag_ok, mag, jnp.array([1.0, 0.0, 0.0], dtype))
        dt = jnp.asarray(dt, dtype)
        q = _update(s.q, gyr, acc_s, mag_s, acc_ok, mag_ok, jnp.asarray(p.beta, dtype), dt)
        t = s.t + dt
        q_enu = nwu_to_enu(q)
        out = Out(t=t, q=q_enu, r=so3.quat_to_matrix(q_enu), q_nwu=q, acc_used=acc_ok, mag_used=acc_ok & mag_ok)
        return State(t=t, q=q, gyr_last=gyr), out

    def output(p: Params, s: State) -> Out:
        """The estimate held by ``s`` (no measurement used yet)."""
        q_enu = nwu_to_enu(s.q)
        no = jnp.zeros((), bool)
        return Out(t=s.t, q=q_enu, r=so3.quat_to_matrix(q_enu), q_nwu=s.q, acc_used=no, mag_used=no)

    return Observer(init, step, "madgwick", output, hold="next")


# ------------------------------------------------------------------------------------------------------------
# Registry
# ------------------------------------------------------------------------------------------------------------
def check_params(p: Params) -> None:
    """beta a finite scalar > 0 (ValueError otherwise)."""
    v = np.asarray(p.beta, float)
    if v.shape != () or not np.isfinite(v) or v <= 0:
        raise ValueError(f"Madgwick beta must be a finite number > 0 (rad/s), got {shown(v)}")


ENTRIES = (
    registry.Entry(
        name="madgwick",
        summary="Madgwick's gradient-descent MARG filter with magnetic distortion compensation (ahrs' updateMARG)",
        reference="Madgwick 2010 report, eqs. (12)-(13), (25)-(26), (31)-(34), (45)-(46); ahrs.filters.Madgwick",
        make=make_observer,
        default_params=lambda dtype=None: default_params(BETA_MARG, dtype=dtype),
        gains=(
            registry.Gain(
                "beta", "rad/s", "gain of the normalised gradient step, eq. (33)", "positive", True, (1e-4, 5.0)
            ),
        ),
        frame="ENU",
        module="madgwick",
        check=check_params,
        init_reads=("acc", "mag"),
    ),
)
