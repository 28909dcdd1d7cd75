"""Multiplicative extended Kalman filter (MEKF) with gyro-bias states, the filtering baseline of Section 5.2 of
sensors2020-interconnected-observer-gyro-bias (its reference [35]; the standard filter of Markley & Crassidis,
"Fundamentals of Spacecraft Attitude Determination and Control", 2014, Sec. 6.2, and Lefferts, Markley &
Shuster 1982).

Inputs: gyro ``gyr`` = omega + b + eta_v (rad/s, body), accelerometer ``acc`` = R^T v_1^N + eta_1 and magnetometer
``mag`` = R^T v_2^N + eta_2 (body frame, raw units: no normalisation). R maps body to the navigation frame.

State: quaternion q^ (w, x, y, z), Hamilton, body to navigation (R(q^) = R^), bias b^ (rad/s), and the 6x6
covariance P of the error state x = [dtheta; db] with R = R^ exp(S(dtheta)) (body-frame attitude error) and
b = b^ + db.

* Propagation over dt with w^ = gyr - b^: q^ <- q^ (x) exp_q(w^ dt);  P <- Phi P Phi^T + Q_d with
  Phi = [[exp(-S(w^) dt), -dt (I - S(w^) dt / 2)], [0, I]] (exact to O(dt^3)) and Q_d of the continuous model
  dtheta' = -S(w^) dtheta - db - eta_v, db' = eta_u:
  Q_d = [[(sv^2 dt + su^2 dt^3/3) I, -(su^2 dt^2/2) I], [-(su^2 dt^2/2) I, su^2 dt I]], where
  sv^2 dt = gyro_noise_std^2 dt^2 (gyro_noise_std = std of one gyro sample, held over the step) and su = bias
  random walk (rad/s/sqrt(s)).
* Update, one sensor at a time (acc, then mag): h = R^T v^N, H = [S(h), 0], S = H P H^T + R_i,
  K = P H^T S^-1, x = K (y - h), Joseph-form covariance; reset q^ <- q^ (x) exp_q(dtheta), b^ <- b^ + db.
  Each update also gives the innovation's negative log-likelihood 0.5 (log det S + nu^T S^-1 nu + 3 log 2 pi),
  nu = y - h; ``Out.nll`` is the step's sum (the loss kind "innovation_nll" of :mod:`jaxatt.fitting.losses`).

Step order: with a held sample (``hold="zoh"``) the sample at t_k updates the state at t_k, then the gyro
propagates it to t_k+1 (Out is the prior at t_k+1); with an :class:`Interval` the mean gyro propagates first and
the sample at t_k+1 updates (Out is the posterior at t_k+1).

Not given in the paper, chosen here: R_i = the true noise covariance of the sensor (for mixed-Gaussian noise the
mixture's variance); the bias random walk su is a parameter (default 1e-6 rad/s/sqrt(s); the Section-5.2
experiment uses 1e-5). P_0 = blkdiag(1e-4 I, 1e-7 I) in Section 5.2.
Missing samples (NaN): a missing vector sensor skips its update, a missing gyro sample holds the last one.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import so3
from ..types import ArrayLike, ImuSample, Interval, Observer, shown, shown_for_shape
from . import registry

__all__ = [
    "Params",
    "State",
    "Out",
    "make_observer",
    "default_params",
    "check_params",
    "quat_exp",
    "propagate",
    "update",
    "innovation_nll",
]


class Params(NamedTuple):
    """MEKF parameters (a pytree of arrays).

    Fields:
        acc_ref_nav, mag_ref_nav: v_1^N, v_2^N (3,) in the sensors' units (e.g. m/s^2 and gauss; NED in the
            paper's simulations; on recorded data the set-up fills them from the first sample, in ENU).
        gyro_noise_std: std of one gyro sample (rad/s).
        bias_rw: bias random-walk density su (rad/s/sqrt(s)), >= 0.
        r_acc, r_mag: measurement covariances (3, 3) (sensor unit squared), SPD.
        r_hat_0: initial attitude estimate (3, 3), a rotation (body to navigation).
        b_hat_0: initial bias estimate (3,) rad/s.
        p0: initial covariance (6, 6) of [dtheta (rad); db (rad/s)], SPD.
    """

    acc_ref_nav: ArrayLike
    mag_ref_nav: ArrayLike
    gyro_noise_std: ArrayLike
    bias_rw: ArrayLike
    r_acc: ArrayLike
    r_mag: ArrayLike
    r_hat_0: ArrayLike
    b_hat_0: ArrayLike
    p0: ArrayLike


class State(NamedTuple):
    """t (s), q^ (4,) (w, x, y, z), b^ (3,) rad/s, P (6, 6), last valid gyro sample (3,), and the negative
    log-likelihood of the last step's innovations (nats, see :func:`innovation_nll`)."""

    t: jax.Array
    q: jax.Array
    b_hat: jax.Array
    p: jax.Array
    gyr_last: jax.Array
    nll: jax.Array


class Out(NamedTuple):
    """t (s), R (3, 3) body to navigation, q (4,), b^ (rad/s), sigma = sqrt(diag P) (6,) (rad, rad/s), and
    ``nll``: the negative log-likelihood (nats) of the innovations of the step that produced it (sum over its
    acc and mag updates, :func:`innovation_nll`; 0 before the first step and for missing samples)."""

    t: jax.Array
    r: jax.Array
    q: jax.Array
    bias: jax.Array
    sigma: jax.Array
    nll: jax.Array


def default_params(
    acc_ref_nav,
    mag_ref_nav,
    *,
    gyro_noise_std: float = 1e-3,
    bias_rw: float = 1e-6,
    acc_noise_std: float = 5e-3 * 9.81,
    mag_noise_std: float = 8e-3,
    r_acc=None,
    r_mag=None,
    r_hat_0=None,
    b_hat_0=(0.0, 0.0, 0.0),
    p0_att: float = 1e-4,
    p0_bias: float = 1e-7,
    p0=None,
    dtype=None,
) -> Params:
    """Section 5.2's MEKF: P_0 = blkdiag(1e-4 I, 1e-7 I); R_i = sigma_i^2 I unless given. Validated."""
    dtype = dtype or jnp.result_type(float)
    p = Params(
        acc_ref_nav=np.asarray(acc_ref_nav, float),
        mag_ref_nav=np.asarray(mag_ref_nav, float),
        gyro_noise_std=np.asarray(gyro_noise_std, float),
        bias_rw=np.asarray(bias_rw, float),
        r_acc=np.asarray(acc_noise_std**2 * np.eye(3) if r_acc is None else r_acc, float),
        r_mag=np.asarray(mag_noise_std**2 * np.eye(3) if r_mag is None else r_mag, float),
        r_hat_0=np.eye(3) if r_hat_0 is None else np.asarray(r_hat_0, float),
        b_hat_0=np.asarray(b_hat_0, float),
        p0=np.diag([p0_att] * 3 + [p0_bias] * 3) if p0 is None else np.asarray(p0, float),
    )
    check_params(p)
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), p)


def check_params(p: Params) -> None:
    """Raise ValueError with a clear message for invalid parameters."""
    for name in ("acc_ref_nav", "mag_ref_nav", "b_hat_0"):
        v = np.asarray(getattr(p, name), float)
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be a finite array of shape (3,), got {shown(v)}")
    a, m = np.asarray(p.acc_ref_nav, float), np.asarray(p.mag_ref_nav, float)
    if np.linalg.norm(np.cross(a, m)) < 1e-6 * np.linalg.norm(a) * np.linalg.norm(m) or not a.any() or not m.any():
        raise ValueError("acc_ref_nav and mag_ref_nav must be non-zero and not parallel (attitude unobservable)")
    for name in ("gyro_noise_std", "bias_rw"):
        v = np.asarray(getattr(p, name), float)
        if v.shape != () or not np.isfinite(v) or v < 0:
            raise ValueError(f"{name} must be a finite scalar >= 0, got {shown(v)}")
    for name, n in (("r_acc", 3), ("r_mag", 3), ("p0", 6)):
        v = np.asarray(getattr(p, name), float)
        if v.shape != (n, n) or not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be a finite ({n}, {n}) matrix, got {shown_for_shape(v, (n, n))}")
        if not np.allclose(v, v.T, rtol=1e-9, atol=1e-300) or np.linalg.eigvalsh(0.5 * (v + v.T)).min() <= 0:
            raise ValueError(f"{name} must be symmetric positive definite")
    r0 = np.asarray(p.r_hat_0, float)
    if r0.shape != (3, 3) or not np.all(np.isfinite(r0)):
        raise ValueError(f"r_hat_0 must be a finite (3, 3) matrix, got {shown_for_shape(r0, (3, 3))}")
    if np.linalg.norm(r0.T @ r0 - np.eye(3)) > 1e-6 or np.linalg.det(r0) <= 0:
        raise ValueError("r_hat_0 must be a rotation matrix (R^T R = I, det R = 1)")


# ------------------------------------------------------------------------------------------------------
#: :func:`jaxatt.so3.quat_exp` (rad -> (w, x, y, z)), under the name this module has always exported
quat_exp = so3.quat_exp


def _qnorm(q):
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def propagate(p: Params, q, b_hat, cov, gyr, dt):
    """Propagate (q^, P) over dt with the gyro sample ``gyr`` (see module docstring)."""
    w = gyr - b_hat
    q = _qnorm(so3.quat_multiply(q, quat_exp(w * dt)))
    eye = jnp.eye(3, dtype=cov.dtype)
    sw = so3.skew(w)
    phi11 = so3.exp(-w * dt)
    phi12 = -dt * (eye - 0.5 * dt * sw)
    z = jnp.zeros((3, 3), cov.dtype)
    phi = jnp.concatenate([jnp.concatenate([phi11, phi12], 1), jnp.concatenate([z, eye], 1)], 0)
    sv2dt = (p.gyro_noise_std * dt) ** 2
    su2 = p.bias_rw**2
    qd = jnp.concatenate(
        [
            jnp.concatenate([(sv2dt + su2 * dt**3 / 3.0) * eye, -(0.5 * su2 * dt**2) * eye], 1),
            jnp.concatenate([-(0.5 * su2 * dt**2) * eye, (su2 * dt) * eye], 1),
        ],
        0,
    )
    cov = so3.mm(so3.mm(phi, cov), phi.T) + qd
    return q, 0.5 * (cov + cov.T)


def innovation_nll(nu, s_inv, det_s):
    """Negative log-likelihood (nats) of an innovation ``nu`` (3,) ~ N(0, S) with S = H P H^T + R_i (the
    filter's own prediction): 0.5 (log det S + nu^T S^-1 nu + 3 log 2 pi). Summed over a run it is the
    prediction-error (innovations) form of the Gaussian likelihood of the samples (Schweppe 1965; Mehra 1970),
    whose minimiser is the maximum-likelihood estimate of the filter's noise parameters (Q, R).
    ``s_inv``, ``det_s``: S^-1 and det S."""
    quad = jnp.sum(nu * so3.mv(s_inv, nu), axis=-1)
    return 0.5 * (jnp.log(det_s) + quad + 3.0 * jnp.log(2.0 * jnp.pi))


def update(q, b_hat, cov, y, ref_nav, r_meas, ok):
    """One vector-measurement update (skipped where ``ok`` is False). Returns (q^, b^, P)."""
    return _update(q, b_hat, cov, y, ref_nav, r_meas, ok)[:3]


def _update(q, b_hat, cov, y, ref_nav, r_meas, ok):
    """:func:`update` and the innovation's negative log-likelihood (0 where ``ok`` is False)."""
    rot = so3.quat_to_matrix(q)
    h = so3.mv(rot.T, ref_nav)
    hm = jnp.concatenate([so3.skew(h), jnp.zeros((3, 3), cov.dtype)], axis=1)  # (3, 6)
    pht = so3.mm(cov, hm.T)  # (6, 3)
    s = so3.mm(hm, pht) + r_meas
    det_s = so3.det3(s)
    s_inv = jnp.swapaxes(so3.cofactor(s), -1, -2) / det_s
    k = so3.mm(pht, s_inv)  # (6, 3)
    nu = jnp.where(ok, y, h) - h
    dx = so3.mv(k, nu)
    ikh = jnp.eye(6, dtype=cov.dtype) - so3.mm(k, hm)
    cov_new = so3.mm(so3.mm(ikh, cov), ikh.T) + so3.mm(so3.mm(k, r_meas), k.T)
    cov_new = 0.5 * (cov_new + cov_new.T)
    q_new = _qnorm(so3.quat_multiply(q, quat_exp(dx[:3])))
    nll = jnp.where(ok, innovation_nll(nu, s_inv, det_s), 0.0)
    return (jnp.where(ok, q_new, q), jnp.where(ok, b_hat + dx[3:], b_hat), jnp.where(ok, cov_new, cov), nll)


def _finite(v):
    return jnp.all(jnp.isfinite(v), axis=-1)


@functools.lru_cache(maxsize=None)
def make_observer() -> Observer:
    """Build the MEKF (cached, so jitted runners are reused)."""

    def init(p: Params, sample: ImuSample) -> State:
        dtype = p.p0.dtype
        gyr = jnp.asarray(sample.gyr, dtype)
        q0 = so3.quat_canonical(so3.matrix_to_quat(p.r_hat_0))
        gyr0 = jnp.where(_finite(gyr), gyr, 0.0)
        return State(jnp.asarray(sample.t, dtype), _qnorm(q0), p.b_hat_0, p.p0, gyr0, jnp.zeros((), dtype))

    def measure(p, q, b, cov, u: ImuSample):
        if u.acc is None or u.mag is None:
            raise ValueError("mekf needs accelerometer and magnetometer samples (acc and mag)")
        ok_acc, ok_mag = so3.present(u.acc), so3.present(u.mag)  # NaN or zero rows: missing readings
        acc, mag = jnp.where(ok_acc[..., None], u.acc, 0.0), jnp.where(ok_mag[..., None], u.mag, 0.0)
        q, b, cov, l1 = _update(q, b, cov, acc, p.acc_ref_nav, p.r_acc, ok_acc)
        q, b, cov, l2 = _update(q, b, cov, mag, p.mag_ref_nav, p.r_mag, ok_mag)
        return q, b, cov, (l1 + l2).astype(cov.dtype)

    def step(p: Params, s: State, sample, dt):
        if isinstance(sample, Interval):
            g0 = jnp.where(_finite(sample.start.gyr), sample.start.gyr, s.gyr_last)
            g1 = jnp.where(_finite(sample.end.gyr), sample.end.gyr, g0)
            q, cov = propagate(p, s.q, s.b_hat, s.p, 0.5 * (g0 + g1), dt)
            q, b, cov, nll = measure(p, q, s.b_hat, cov, sample.end)
            t0, g_new = sample.start.t, g1
        else:
            g = jnp.where(_finite(sample.gyr), sample.gyr, s.gyr_last)
            q, b, cov, nll = measure(p, s.q, s.b_hat, s.p, sample)
            q, cov = propagate(p, q, b, cov, g, dt)
            t0, g_new = sample.t, g
        t1 = t0 + dt
        s1 = State(t1, q, b, cov, g_new, nll)
        return s1, output(p, s1)

    def output(p: Params, s: State) -> Out:
        sig = jnp.sqrt(jnp.maximum(jnp.diagonal(s.p), 0.0))
        return Out(s.t, so3.quat_to_matrix(s.q), s.q, s.b_hat, sig, s.nll)

    return Observer(init=init, step=step, name="mekf", output=output)  # its step reads "zoh" or "linear" samples


# ------------------------------------------------------------------------------------------------------
# Registry: the MEKF on recorded IMU data (ENU, acc "up" reference, first field as reference)
# ------------------------------------------------------------------------------------------------------
def _setup_recorded(p: Params, sample) -> Params:
    """TRIAD start; references: "up" times |a| of the first sample, the first magnetometer sample in ENU."""
    r0, m_nav, anorm = registry.first_sample_frame(sample)
    zero = jnp.zeros_like(anorm)
    return p._replace(r_hat_0=r0, mag_ref_nav=m_nav, acc_ref_nav=jnp.stack([zero, zero, anorm]))


def _recorded_defaults(dtype=None) -> Params:
    """Untuned defaults in recorded-data units: sigma_gyro = 0.002 rad/s, bias random walk 1e-5 rad/s/sqrt(s),
    R_acc = (1 m/s^2)^2 I, R_mag = (3 unit)^2 I for a 43.5-unit field (the front door scales it to the recording's
    field: 6.9 % of its norm; ``Entry.field_unit_gains``), P0 = blkdiag(1e-4 I, 1e-5 I)."""
    return default_params(
        (0.0, 0.0, 9.81),
        (0.0, 17.0, -40.0),
        gyro_noise_std=0.002,
        bias_rw=1e-5,
        acc_noise_std=1.0,
        mag_noise_std=3.0,
        p0_att=1e-4,
        p0_bias=1e-5,
        dtype=dtype,
    )


ENTRIES = (
    registry.Entry(
        name="mekf",
        summary="multiplicative extended Kalman filter, attitude + gyro bias",
        reference="Markley & Crassidis 2014, Sec. 6.2 (the MEKF of sensors2020 Section 5.2)",
        make=make_observer,
        default_params=_recorded_defaults,
        gains=(
            registry.Gain("gyro_noise_std", "rad/s", "std of one gyro sample (process noise)"),
            registry.Gain("bias_rw", "rad/s/sqrt(s)", "gyro-bias random walk"),
            registry.Gain("r_acc", "(m/s^2)^2", "accelerometer noise covariance, 3x3 SPD", "spd"),
            registry.Gain("r_mag", "unit^2", "magnetometer noise covariance, 3x3 SPD", "spd"),
            registry.Gain("p0", "rad^2, (rad/s)^2", "initial error covariance, 6x6 SPD", "spd", tuned=False),
        ),
        setup=_setup_recorded,
        setup_fields=("r_hat_0", "mag_ref_nav", "acc_ref_nav"),
        frame="ENU",
        hold="next",  # on recorded data (the filters' convention); the Observer declares none (see the module)
        module="mekf",
        check=check_params,
        field_unit_gains=("r_mag",),
    ),
)
