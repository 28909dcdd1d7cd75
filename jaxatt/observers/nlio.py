"""Attitude and gyro-bias observers of the sensors2020 paper on a nonlinear interconnected observer with gyro-bias
estimation (Sensors 2020, 20, 6514): NLO, NLIO-FG and NLIO-TV.

Inputs: gyro ``gyr`` = omega + b (rad/s, body), two body-frame vector measurements ``acc`` = R^T v_1^N and
``mag`` = R^T v_2^N of constant, known, non-parallel references (Assumption 1), e.g. gravity in m/s^2 and the
magnetic field in gauss (NED in the paper). R maps body to NED. The attitude observer is written once:

* Attitude observer Sigma_1, eq. (8) (after Grip et al.), on a lifted R^ in R^{3x3}:
      dR^/dt = R^ S(gyr - b^) + theta Kp Gamma
      db^/dt = Proj(||b^|| <= l_b, -kv vex(Pa(R^s^T Kp Gamma))),   R^s = sat_1(R^) (element-wise)
  with the TRIAD-like injection, eqs. (9)-(11) and (13)-(14):
      Gamma = A_N A_B^T - A_N A_N^T R^,   A_N = [v1N, v2N, v1N x v2N],   A_B = [v1, v2, v1 x v2].
  Proj is the parameter projection of Grip et al. [9] (Krstic et al.): with L_b = ``bias_bound`` < l_b =
  ``bias_max`` and c = min(1, (|b^|^2 - L_b^2) / (l_b^2 - L_b^2)),
      Proj(b^, tau) = tau - c (b^ . tau) b^ / |b^|^2   if |b^| >= L_b and b^ . tau > 0,   tau otherwise.
* NLO: A_B is built from the raw measurements (the observer of Grip et al. [18] with this paper's Gamma).
* NLIO: A_B is built from the estimates v1^, v2^ of the auxiliary observer Sigma_2, eq. (17):
      dv^_i/dt = v^_i x (gyr - b^) + K_i (v_i - v^_i),   i = 1, 2,
  with fixed gains K1, K2 (NLIO-FG) or with the Kalman gains of the discrete Riccati recursion (28)-(30)
  (NLIO-TV) for the error system (27): per sensor, F_k = exp(-S(gyr - b^) dt),
  Q_k = int_0^dt e^{As} Q e^{A^T s} ds with Q_i = sigma_w^2 S(v^_i) S(v^_i)^T (gyro noise through S(v^_i), the
  paper's Q_i = E[S(v^_i) eta_w eta_w^T S^T(v^_i)]), R_i = E[eta_i eta_i^T] and C = I:
      K_k = P_k|k-1 (P_k|k-1 + R_i)^-1,  P_k|k = (I - K_k) P_k|k-1 (Joseph form),  P_k+1|k = F P_k|k F^T + Q_k.
  Sigma_1 and Sigma_2 are integrated together (one RK4 step of the joint ODE).

Readings chosen where the paper is open (also in docs/observers/nlio.md):

* A_B, A_N (``triad``, :func:`triad_matrix`). Eqs. (10)-(11) print [v1, v2, v1 x v2]; the text says "referencing
  the TRIAD algorithm [4]". In raw units (m/s^2, gauss) A_N A_N^T has eigenvalues up to ~96, so Kp = 15 puts a
  pole near -1450 1/s, unstable for RK4 at 100 Hz. On unit vectors ("unit") the rotational error modes decay
  at Kp (tr M - lambda_i)/2 = Kp x {1.0, 1.08, 0.27} (M = A_N A_N^T), the slow one about an axis close to the
  vertical, so the heading is filtered 4x harder than the tilt. With the orthonormal TRIAD frame
  ("orthonormal", default) A A^T = I, Gamma = R_TRIAD - R^ and every mode decays at Kp. The paper's tables
  decide: its steady-state yaw/pitch MAE ratio is 4.7 (Case 1) and 5.1 (Case 2), the ratio of the per-sample
  heading and tilt noise of TRIAD ((8e-3 / 0.3128) / 5e-3 = 5.1); "orthonormal" reproduces the NLO's yaw
  within 10 % where "unit" gives half of it. The auxiliary observer runs in raw units.
* Signs: Gamma and the bias law as printed; a small-error expansion gives db^/dt ~= kv (b - b^) (checked in
  tests/test_nlio.py), so the printed signs are the convergent ones.
* The bias bounds L_b and l_b are not given; defaults L_b = 0.05 rad/s, l_b = 0.06 rad/s (|b| = 0.029 rad/s in
  Section 5). Discrete time: the continuous projection keeps |b^| <= l_b only to O(dt^2), so after each step b^
  is also scaled back onto the ball |b^| <= l_b (inactive whenever the continuous flow respects the bound).
* The discrete Kalman gain K_k (dimensionless, per sample) enters eq. (17) as the continuous gain K_k / dt held
  over the step (the same correction per step to first order in K_k; K_k ~ 1e-3 - 1e-2 here).
  Q_k is evaluated by the trapezoidal rule (F Q F^T + Q) dt / 2; ``q_scale`` multiplies Q (the paper allows
  scaling Q and R but gives no numbers; default 1 = literal, sigma_w = std of one gyro sample).
* The Riccati recursion of a step uses the inputs at the start of the step: gyr (averaged over the step when
  samples are interpolated), b^ and v^; the gain K_k then multiplies the held (or interpolated) measurement
  over the step.
* v^_i(0) = the first measurement (the paper does not say).
* The output ``Out.r`` is the rotation nearest to the lifted R^ (Frobenius norm; Grip et al.'s R-bar); for
  det(R^) <= 0, which only happens during large transients, the Gram-Schmidt rotation of R^'s columns.

Missing samples (NaN in a log): a missing vector sample switches its correction off (NLIO: K_i = 0 and P only
propagates; NLO: the measurement is replaced by R^s^T v_i^N); a missing gyro sample holds the last valid one.
"""

from __future__ import annotations

import functools
from typing import Any, Dict, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import so3
from ..integrate import input_at, rk4_step
from ..types import ArrayLike, ImuSample, Interval, Observer, shown, shown_for_shape
from . import registry

__all__ = [
    "Params",
    "State",
    "Out",
    "VARIANTS",
    "make_observer",
    "default_params",
    "check_params",
    "injection",
    "projection",
    "rotation_of",
    "kalman_gain",
    "riccati_step",
    "auxiliary_rhs",
    "attitude_rhs",
    "triad_matrix",
    "TRIADS",
]

VARIANTS = ("nlo", "nlio-fg", "nlio-tv")


class Params(NamedTuple):
    """Observer parameters (a pytree of arrays).

    Fields:
        acc_ref_nav: v_1^N (3,), e.g. gravity reference in m/s^2 (NED: [0, 0, g] as in Section 5).
        mag_ref_nav: v_2^N (3,), e.g. magnetic field in gauss (NED; on recorded data the set-up fills both
            references from the first sample, in ENU).
        kp: Kp (3, 3), symmetric positive definite (1/s with unit vectors).
        kv: kv > 0, bias gain (scalar).
        theta: scaling theta >= 1 (scalar).
        bias_bound: L_b > 0, a known bound on |b| (rad/s; Assumption 3).
        bias_max: l_b > L_b, the projection keeps |b^| <= l_b (rad/s).
        r_hat_0: initial R^ (3, 3) (any matrix; the lifted observer needs no rotation).
        b_hat_0: initial b^ (3,) rad/s, |b^_0| <= l_b.
        k1, k2: fixed auxiliary gains K1, K2 (3, 3) of NLIO-FG (1/s).
        gyro_noise_std: sigma_w, std of the gyro noise used in Q (rad/s) (NLIO-TV).
        r_acc, r_mag: measurement covariances R_v1, R_v2 (3, 3) (unit of the sensor squared) (NLIO-TV).
        p0_acc, p0_mag: initial covariances P_0 (3, 3) of v~_1, v~_2 (NLIO-TV).
        q_scale: multiplies Q (NLIO-TV; 1 = literal).
    """

    acc_ref_nav: ArrayLike
    mag_ref_nav: ArrayLike
    kp: ArrayLike
    kv: ArrayLike
    theta: ArrayLike
    bias_bound: ArrayLike
    bias_max: ArrayLike
    r_hat_0: ArrayLike
    b_hat_0: ArrayLike
    k1: ArrayLike
    k2: ArrayLike
    gyro_noise_std: ArrayLike
    r_acc: ArrayLike
    r_mag: ArrayLike
    p0_acc: ArrayLike
    p0_mag: ArrayLike
    q_scale: ArrayLike


class State(NamedTuple):
    """Observer state at time ``t`` (s): lifted R^ (3, 3), b^ (3,) rad/s, v^_1, v^_2 (3,) (NLO: the last valid
    measurements), the prior covariances P_1, P_2 (3, 3) of NLIO-TV (None otherwise) and the last valid gyro
    sample (3,)."""

    t: jax.Array
    r_hat: jax.Array
    b_hat: jax.Array
    v1: jax.Array
    v2: jax.Array
    p1: Optional[jax.Array]
    p2: Optional[jax.Array]
    gyr_last: jax.Array


class Out(NamedTuple):
    """Estimates at time ``t`` (s): R (rotation nearest to R^, body to NED), the lifted R^, b^ (rad/s),
    v^_1, v^_2 (NLIO; None for NLO) and the auxiliary gains K1, K2 (3, 3) used over the step (1/s; None for
    NLO)."""

    t: jax.Array
    r: jax.Array
    r_hat: jax.Array
    bias: jax.Array
    v1: Optional[jax.Array]
    v2: Optional[jax.Array]
    k1: Optional[jax.Array]
    k2: Optional[jax.Array]


# ------------------------------------------------------------------------------------------------------
# Parameters
# ------------------------------------------------------------------------------------------------------
def _mat(x, name) -> np.ndarray:
    a = np.asarray(x, float)
    if a.ndim == 0:
        return a * np.eye(3)
    if a.shape == (3,):
        return np.diag(a)
    if a.shape != (3, 3):
        raise ValueError(f"{name} must be a scalar, a (3,) diagonal or a (3, 3) matrix, got shape {a.shape}")
    return a


def default_params(
    acc_ref_nav,
    mag_ref_nav,
    *,
    kp=15.0,
    kv: float = 0.2,
    theta: float = 1.0,
    bias_bound: float = 0.05,
    bias_max: float = 0.06,
    r_hat_0=None,
    b_hat_0=(0.0, 0.0, 0.0),
    k1=5.6,
    k2=3.3,
    gyro_noise_std: float = 1e-3,
    acc_noise_std: float = 5e-3 * 9.81,
    mag_noise_std: float = 8e-3,
    r_acc=None,
    r_mag=None,
    p0_acc=1e-5,
    p0_mag=5e-7,
    q_scale: float = 1.0,
    dtype=None,
) -> Params:
    """Parameters with Section 5's values (Case 1: Kp = 15 I, kv = 0.2, theta = 1, K1 = 5.6 I, K2 = 3.3 I,
    P0 = blkdiag(1e-5 I, 5e-7 I), sigma_w = 1e-3 rad/s, R_vi = sigma_i^2 I). Matrices may be given as scalars
    (times I) or diagonals; ``r_acc``/``r_mag`` default to acc_noise_std^2 I / mag_noise_std^2 I. Validated."""
    dtype = dtype or jnp.result_type(float)
    p = Params(
        acc_ref_nav=np.asarray(acc_ref_nav, float),
        mag_ref_nav=np.asarray(mag_ref_nav, float),
        kp=_mat(kp, "kp"),
        kv=np.asarray(kv, float),
        theta=np.asarray(theta, float),
        bias_bound=np.asarray(bias_bound, float),
        bias_max=np.asarray(bias_max, float),
        r_hat_0=np.eye(3) if r_hat_0 is None else np.asarray(r_hat_0, float),
        b_hat_0=np.asarray(b_hat_0, float),
        k1=_mat(k1, "k1"),
        k2=_mat(k2, "k2"),
        gyro_noise_std=np.asarray(gyro_noise_std, float),
        r_acc=_mat(acc_noise_std**2 if r_acc is None else r_acc, "r_acc"),
        r_mag=_mat(mag_noise_std**2 if r_mag is None else r_mag, "r_mag"),
        p0_acc=_mat(p0_acc, "p0_acc"),
        p0_mag=_mat(p0_mag, "p0_mag"),
        q_scale=np.asarray(q_scale, float),
    )
    check_params(p)
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), p)


def _spd(a, name, strict=True):
    a = np.asarray(a, float)
    if a.shape != (3, 3) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a finite (3, 3) matrix, got {shown_for_shape(a, (3, 3))}")
    if not np.allclose(a, a.T, rtol=1e-9, atol=1e-300):
        raise ValueError(f"{name} must be symmetric")
    ev = np.linalg.eigvalsh(a)
    if (ev.min() <= 0) if strict else (ev.min() < -1e-12 * max(1.0, ev.max())):
        raise ValueError(
            f"{name} must be symmetric positive {'definite' if strict else 'semi-definite'}, eigenvalues {ev}"
        )


def check_params(p: Params) -> None:
    """Raise ValueError with a clear message for invalid parameters (shapes, finiteness, signs, bounds)."""
    refs = []
    for name in ("acc_ref_nav", "mag_ref_nav", "b_hat_0"):
        v = np.asarray(getattr(p, name), float)
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be a finite array of shape (3,), got {shown(v)}")
        refs.append(v)
    a, m = refs[0], refs[1]
    na, nm = np.linalg.norm(a), np.linalg.norm(m)
    if na == 0 or nm == 0 or np.linalg.norm(np.cross(a, m)) < 1e-6 * na * nm:
        raise ValueError(
            "Assumption 1 of sensors2020-nlio is violated: acc_ref_nav and mag_ref_nav must be non-zero "
            "and not parallel (the attitude is not observable from parallel vectors)"
        )
    _spd(p.kp, "kp (Kp > 0, Lemma 1)")
    for name, low in (("kv", 0.0), ("bias_bound", 0.0)):
        v = np.asarray(getattr(p, name), float)
        if v.shape != () or not np.isfinite(v) or v <= low:
            raise ValueError(f"{name} must be a finite positive scalar, got {shown(v)}")
    th = np.asarray(p.theta, float)
    if th.shape != () or not np.isfinite(th) or th < 1.0:
        raise ValueError(f"theta must be a finite scalar >= 1 (Lemma 1), got {th}")
    lb, ub = float(np.asarray(p.bias_bound)), np.asarray(p.bias_max, float)
    if ub.shape != () or not np.isfinite(ub) or ub <= lb:
        raise ValueError(f"bias_max (l_b) must be a finite scalar > bias_bound (L_b) = {lb}, got {ub}")
    if np.linalg.norm(refs[2]) > float(ub):
        raise ValueError(f"|b_hat_0| = {np.linalg.norm(refs[2]):.4g} exceeds bias_max = {float(ub)}")
    r0 = np.asarray(p.r_hat_0, float)
    if r0.shape != (3, 3) or not np.all(np.isfinite(r0)):
        raise ValueError(f"r_hat_0 must be a finite (3, 3) matrix, got {shown_for_shape(r0, (3, 3))}")
    for name in ("k1", "k2"):
        _spd(getattr(p, name), f"{name} (K1, K2 > 0, Theorem 1)")
    for name in ("r_acc", "r_mag", "p0_acc", "p0_mag"):
        _spd(getattr(p, name), name, strict=name.startswith("r_"))
    for name in ("gyro_noise_std", "q_scale"):
        v = np.asarray(getattr(p, name), float)
        if v.shape != () or not np.isfinite(v) or v < 0:
            raise ValueError(f"{name} must be a finite scalar >= 0, got {shown(v)}")


# ------------------------------------------------------------------------------------------------------
# Building blocks (public: tests and other observers use them)
# ------------------------------------------------------------------------------------------------------
TRIADS = ("orthonormal", "unit", "raw")


def triad_matrix(v1, v2, triad: str = "orthonormal"):
    """The matrix A of eqs. (10)-(11) and (14) (columns), in one of three readings:

    * "unit": [u1, u2, u1 x u2] with u_i = v_i / |v_i| (eqs. 10-11 as printed, on unit vectors);
    * "orthonormal": the TRIAD frame [u1, n, u1 x n], n = unit(u1 x u2) (Shuster's TRIAD, the paper's
      reference [4]); then A A^T = I and Gamma = A_N A_B^T - R^ = R_TRIAD - R^;
    * "raw": [v1, v2, v1 x v2] in the sensors' units.
    """
    if triad == "raw":
        return jnp.stack([v1, v2, so3.cross(v1, v2)], axis=-1)
    u1, u2 = so3.unit(v1), so3.unit(v2)
    c = so3.cross(u1, u2)
    if triad == "unit":
        return jnp.stack([u1, u2, c], axis=-1)
    n = so3.unit(c)
    return jnp.stack([u1, n, so3.cross(u1, n)], axis=-1)


def injection(a_n, a_b, r_hat):
    """Gamma = A_N A_B^T - A_N A_N^T R^ (eqs. 9 and 13)."""
    at = lambda x: jnp.swapaxes(x, -1, -2)  # noqa: E731
    return so3.mm(a_n, at(a_b)) - so3.mm(so3.mm(a_n, at(a_n)), r_hat)


def projection(b_hat, tau, bias_bound, bias_max):
    """Grip et al.'s parameter projection Proj(b^, tau): keeps |b^| <= bias_max (continuous time)."""
    nb2 = jnp.sum(b_hat * b_hat, axis=-1, keepdims=True)
    bt = jnp.sum(b_hat * tau, axis=-1, keepdims=True)
    c = jnp.clip((nb2 - bias_bound**2) / (bias_max**2 - bias_bound**2), 0.0, 1.0)
    active = (nb2 >= bias_bound**2) & (bt > 0)
    return jnp.where(active, tau - c * bt * b_hat / jnp.where(active, nb2, 1.0), tau)


def attitude_rhs(p: Params, r_hat, b_hat, gyr, a_n, a_b):
    """(dR^/dt, db^/dt) of eq. (8) for TRIAD matrices A_N, A_B (eqs. 9-11 / 13-14)."""
    gamma = injection(a_n, a_b, r_hat)
    kg = so3.mm(p.kp, gamma)
    dr = so3.mm(r_hat, so3.skew(gyr - b_hat)) + p.theta * kg
    rs = jnp.clip(r_hat, -1.0, 1.0)
    tau = -p.kv * so3.vex(so3.mm(jnp.swapaxes(rs, -1, -2), kg))
    return dr, projection(b_hat, tau, p.bias_bound, p.bias_max)


def auxiliary_rhs(v_hat, w, v_meas, k):
    """dv^/dt = v^ x w + K (v - v^) of eq. (17), with w = gyr - b^."""
    return so3.cross(v_hat, w) + so3.mv(k, v_meas - v_hat)


def _inv3(m):
    return jnp.swapaxes(so3.cofactor(m), -1, -2) / so3.det3(m)[..., None, None]


def kalman_gain(p_prior, r_meas):
    """K = P (P + R)^-1 and the Joseph-form P+ = (I - K) P (I - K)^T + K R K^T (eqs. 29-30 with C = I)."""
    k = so3.mm(p_prior, _inv3(p_prior + r_meas))
    ik = jnp.eye(3, dtype=p_prior.dtype) - k
    p_post = so3.mm(so3.mm(ik, p_prior), jnp.swapaxes(ik, -1, -2)) + so3.mm(so3.mm(k, r_meas), jnp.swapaxes(k, -1, -2))
    return k, 0.5 * (p_post + jnp.swapaxes(p_post, -1, -2))


def riccati_step(p_post, v_hat, w, sigma_w, q_scale, dt):
    """P_k+1|k = F P F^T + Q_k (eq. 28) with F = exp(-S(w) dt) and Q_k = (F Q F^T + Q) dt / 2,
    Q = q_scale sigma_w^2 S(v^) S(v^)^T."""
    f = so3.exp(-w * dt)
    s = so3.skew(v_hat)
    q = (q_scale * sigma_w**2) * so3.mm(s, jnp.swapaxes(s, -1, -2))
    ft = jnp.swapaxes(f, -1, -2)
    p_next = so3.mm(so3.mm(f, p_post), ft) + 0.5 * dt * (so3.mm(so3.mm(f, q), ft) + q)
    return 0.5 * (p_next + jnp.swapaxes(p_next, -1, -2))


def _gram_schmidt(m):
    c1, c2 = m[..., :, 0], m[..., :, 1]
    e1 = so3.unit(c1)
    e2 = so3.unit(c2 - jnp.sum(e1 * c2, -1, keepdims=True) * e1)
    return jnp.stack([e1, e2, so3.cross(e1, e2)], axis=-1)


def _rotation_and_converged(m, iterations: int):
    eye = jnp.eye(3, dtype=m.dtype)
    scale = jnp.sqrt(jnp.sum(m * m, axis=(-2, -1)) / 3.0)[..., None, None]
    mn = m / jnp.where(scale > 0, scale, 1.0)
    ok = so3.det3(mn) > 1e-8
    x = jnp.where(ok[..., None, None], mn, eye)
    for _ in range(iterations):
        xit = so3.cofactor(x) / so3.det3(x)[..., None, None]
        g = jnp.sqrt(jnp.sqrt(jnp.sum(xit * xit, axis=(-2, -1)) / jnp.sum(x * x, axis=(-2, -1))))[..., None, None]
        x = 0.5 * (g * x + xit / g)
    tol = max(1e-8, 1e3 * float(jnp.finfo(m.dtype).eps))  # converged (float64: 1e-8; float32: 1.2e-4)
    ok = ok & (so3.orthogonality_error(x) < tol)
    return jnp.where(ok[..., None, None], x, _gram_schmidt(m)), ok


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def rotation_of(m, iterations: int = 10):
    """The rotation nearest to ``m`` (Frobenius) for det(m) > 0: Newton's polar iteration with Frobenius-norm
    scaling (X <- (g X + X^-T / g) / 2, g = sqrt(|X^-1| / |X|)), ~30x cheaper than an SVD on CPU. Where
    det(m) <= 0 or the iteration has not converged (nearly singular m: only during large transients of a lifted
    observer) the Gram-Schmidt rotation of m's columns is returned instead. The derivative is the polar
    factor's (:func:`jaxatt.so3.polar_tangent`) where the iteration converged, Gram-Schmidt's elsewhere: a
    gradient keeps no intermediate of the iterations."""
    return _rotation_and_converged(m, iterations)[0]


@rotation_of.defjvp
def _rotation_of_jvp(iterations, primals, tangents):
    (m,), (dm,) = primals, tangents
    r, ok = _rotation_and_converged(m, iterations)
    ok3 = ok[..., None, None]
    eye = jnp.eye(3, dtype=m.dtype)
    # each branch at a safe point where the other one is taken (no 0 * inf in a gradient)
    polar = so3.polar_tangent(jnp.where(ok3, r, eye), jnp.where(ok3, m, eye), dm)
    _, gram_schmidt = jax.jvp(_gram_schmidt, (jnp.where(ok3, eye, m),), (dm,))
    return r, jnp.where(ok3, polar, gram_schmidt)


# ------------------------------------------------------------------------------------------------------
# The observer
# ------------------------------------------------------------------------------------------------------
def _finite(v):
    return jnp.all(jnp.isfinite(v), axis=-1)


@functools.lru_cache(maxsize=None)
def make_observer(variant: str = "nlio-tv", triad: str = "orthonormal") -> Observer:
    """Build NLO, NLIO-FG or NLIO-TV (cached: same arguments, same object, so jitted runners are reused).

    Args:
        variant: "nlo" (raw measurements in Gamma), "nlio-fg" (auxiliary observer with Params.k1, k2) or
            "nlio-tv" (auxiliary observer with Riccati gains, eqs. 28-30).
        triad: how A_B, A_N are built from the two vectors (:func:`triad_matrix`): "orthonormal" (default, the
            TRIAD frame; reproduces the paper's tables), "unit" (eqs. 10-11 on unit vectors) or "raw" (eqs.
            10-11 in raw units; unstable at 100 Hz with Kp = 15 for Section 5's references).
    """
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    if triad not in TRIADS:
        raise ValueError(f"triad must be one of {TRIADS}, got {triad!r}")
    aux = variant != "nlo"
    tv = variant == "nlio-tv"

    def init(p: Params, sample: ImuSample) -> State:
        dtype = p.r_hat_0.dtype
        gyr = jnp.asarray(sample.gyr, dtype)
        acc, mag = jnp.asarray(sample.acc, dtype), jnp.asarray(sample.mag, dtype)
        rt = jnp.swapaxes(p.r_hat_0, -1, -2)
        v1 = jnp.where(so3.present(acc)[..., None], acc, so3.mv(rt, p.acc_ref_nav))
        v2 = jnp.where(so3.present(mag)[..., None], mag, so3.mv(rt, p.mag_ref_nav))
        return State(
            jnp.asarray(sample.t, dtype),
            p.r_hat_0,
            p.b_hat_0,
            v1,
            v2,
            p.p0_acc if tv else None,
            p.p0_mag if tv else None,
            jnp.where(_finite(gyr), gyr, 0.0),
        )

    def sanitize(u: ImuSample, gyr_last):
        if u.acc is None or u.mag is None:
            raise ValueError(f"{variant} needs accelerometer and magnetometer samples (acc and mag)")
        ok1, ok2 = so3.present(u.acc), so3.present(u.mag)  # NaN or zero rows: missing readings
        # NaN-free stand-ins; the masks switch the corresponding corrections off.
        return (
            u._replace(
                gyr=jnp.where(_finite(u.gyr), u.gyr, gyr_last),
                acc=jnp.where(ok1, u.acc, 0.0),
                mag=jnp.where(ok2, u.mag, 0.0),
            ),
            ok1,
            ok2,
        )

    def step(p: Params, s: State, sample, dt):
        if isinstance(sample, Interval):
            a, ok1a, ok2a = sanitize(sample.start, s.gyr_last)
            b, ok1b, ok2b = sanitize(sample.end, s.gyr_last)
            u = Interval(
                a._replace(acc=jnp.where(ok1a, a.acc, b.acc), mag=jnp.where(ok2a, a.mag, b.mag)),
                b._replace(acc=jnp.where(ok1b, b.acc, a.acc), mag=jnp.where(ok2b, b.mag, a.mag)),
            )
            ok1, ok2 = ok1a | ok1b, ok2a | ok2b
            t0, gyr_mid, gyr_new = a.t, 0.5 * (a.gyr + b.gyr), b.gyr
        else:
            u, ok1, ok2 = sanitize(sample, s.gyr_last)
            t0, gyr_mid, gyr_new = u.t, u.gyr, u.gyr
        a_n = triad_matrix(p.acc_ref_nav, p.mag_ref_nav, triad)
        dtype = s.r_hat.dtype
        zero = jnp.zeros((3, 3), dtype)
        k1 = k2 = p1 = p2 = None
        if tv:
            assert s.p1 is not None and s.p2 is not None  # init() sets P_1, P_2 for NLIO-TV
            k1d, p1 = kalman_gain(s.p1, p.r_acc)
            k2d, p2 = kalman_gain(s.p2, p.r_mag)
            k1d, p1 = jnp.where(ok1, k1d, zero), jnp.where(ok1, p1, s.p1)
            k2d, p2 = jnp.where(ok2, k2d, zero), jnp.where(ok2, p2, s.p2)
            k1, k2 = k1d / dt, k2d / dt
            w0 = gyr_mid - s.b_hat
            p1 = riccati_step(p1, s.v1, w0, p.gyro_noise_std, p.q_scale, dt)
            p2 = riccati_step(p2, s.v2, w0, p.gyro_noise_std, p.q_scale, dt)
        elif aux:
            k1, k2 = jnp.where(ok1, p.k1, zero), jnp.where(ok2, p.k2, zero)

        def f(x, uu: ImuSample):
            r_hat, b_hat, v1, v2 = x
            w = uu.gyr - b_hat
            if aux:
                dv1 = auxiliary_rhs(v1, w, uu.acc, k1)
                dv2 = auxiliary_rhs(v2, w, uu.mag, k2)
                y1, y2 = v1, v2
            else:
                dv1 = dv2 = jnp.zeros_like(v1)
                assert uu.acc is not None and uu.mag is not None  # u is a sample checked by sanitize()
                rst = jnp.swapaxes(jnp.clip(r_hat, -1.0, 1.0), -1, -2)
                y1 = jnp.where(ok1, uu.acc, so3.mv(rst, p.acc_ref_nav))
                y2 = jnp.where(ok2, uu.mag, so3.mv(rst, p.mag_ref_nav))
            dr, db = attitude_rhs(p, r_hat, b_hat, uu.gyr, a_n, triad_matrix(y1, y2, triad))
            return dr, db, dv1, dv2

        r_hat, b_hat, v1, v2 = rk4_step(f, (s.r_hat, s.b_hat, s.v1, s.v2), u, dt)
        # Discrete-time safeguard of the projection: |b^| <= l_b after every step.
        nb = jnp.sqrt(jnp.sum(b_hat * b_hat))
        b_hat = b_hat * jnp.minimum(1.0, p.bias_max / jnp.where(nb > 0, nb, 1.0))
        if not aux:
            u_end = input_at(u, 1.0)
            v1 = jnp.where(ok1, u_end.acc, s.v1)
            v2 = jnp.where(ok2, u_end.mag, s.v2)
        t1 = t0 + dt
        new = State(t1, r_hat, b_hat, v1, v2, p1, p2, gyr_new)
        out = Out(
            t1,
            rotation_of(r_hat),
            r_hat,
            b_hat,
            v1 if aux else None,
            v2 if aux else None,
            k1 if aux else None,
            k2 if aux else None,
        )
        return new, out

    def output(p: Params, s: State) -> Out:
        """The estimate held by ``s`` (auxiliary gains: NLIO-FG's K1, K2; zero for NLIO-TV before its first
        Kalman update)."""
        if not aux:
            return Out(s.t, rotation_of(s.r_hat), s.r_hat, s.b_hat, None, None, None, None)
        if tv:
            assert s.p1 is not None and s.p2 is not None  # init() sets P_1, P_2 for NLIO-TV
            k1, k2 = jnp.zeros_like(s.p1), jnp.zeros_like(s.p2)
        else:
            k1, k2 = p.k1, p.k2
        return Out(s.t, rotation_of(s.r_hat), s.r_hat, s.b_hat, s.v1, s.v2, k1, k2)

    return Observer(init=init, step=step, name=variant, output=output)


# ------------------------------------------------------------------------------------------------------
# Registry: NLO, NLIO-FG and NLIO-TV on recorded IMU data (ENU, acc "up" reference, first field as reference)
# ------------------------------------------------------------------------------------------------------
def _setup_recorded(p: Params, sample) -> Params:
    """TRIAD start; references: "up" times |a| of the first sample, the first magnetometer sample in ENU."""
    r0, m_nav, anorm = registry.first_sample_frame(sample)
    zero = jnp.zeros_like(anorm)
    return p._replace(r_hat_0=r0, mag_ref_nav=m_nav, acc_ref_nav=jnp.stack([zero, zero, anorm]))


def _recorded_defaults(dtype=None) -> Params:
    """Untuned defaults in recorded-data units (rad/s, m/s^2, the data's field unit): Kp = 0.3 I, kv = 0.02,
    K1 = I, K2 = 0.3 I, sigma_gyro = 0.002 rad/s, R_acc = P0_acc = 0.25 I, R_mag = P0_mag = I for a 43.5-unit field
    (scaled to the recording's field by the front door: ``Entry.field_unit_gains``), L_b = 0.02 rad/s."""
    return default_params(
        (0.0, 0.0, 9.81),
        (0.0, 17.0, -40.0),
        kp=0.3,
        kv=0.02,
        k1=1.0,
        k2=0.3,
        gyro_noise_std=0.002,
        r_acc=0.25,
        r_mag=1.0,
        p0_acc=0.25,
        p0_mag=1.0,
        bias_bound=0.02,
        bias_max=0.024,
        dtype=dtype,
    )


_G_KP = registry.Gain("kp", "1/s", "attitude gain Kp, eq. (10), 3x3 SPD", "spd")
_G_KV = registry.Gain("kv", "1/s", "gyro-bias gain k_v, eq. (10)")
_G_K1 = registry.Gain("k1", "1/s", "auxiliary-observer gain K1 of the accelerometer vector (NLIO-FG), 3x3 SPD", "spd")
_G_K2 = registry.Gain("k2", "1/s", "auxiliary-observer gain K2 of the magnetometer vector (NLIO-FG), 3x3 SPD", "spd")
_G_TV = (
    registry.Gain("gyro_noise_std", "rad/s", "gyro noise std of the Riccati recursion (NLIO-TV)"),
    registry.Gain("r_acc", "(m/s^2)^2", "accelerometer noise covariance R_1 (NLIO-TV), 3x3 SPD", "spd"),
    registry.Gain("r_mag", "unit^2", "magnetometer noise covariance R_2 (NLIO-TV), 3x3 SPD", "spd"),
)
_COMMON: Dict[str, Any] = dict(
    reference="sensors2020 (nonlinear interconnected observer with gyro-bias estimation), eqs. (10)-(14), "
    "(17), (28)-(30)",
    default_params=_recorded_defaults,
    setup=_setup_recorded,
    setup_fields=("r_hat_0", "mag_ref_nav", "acc_ref_nav"),
    frame="ENU",
    hold="next",
    module="nlio",
    check=check_params,
    field_unit_gains=("r_mag", "p0_mag"),
)

ENTRIES = (
    registry.Entry(
        name="nlo",
        summary="nonlinear observer with gyro bias on the raw vectors (NLO)",
        make=lambda: make_observer("nlo"),
        gains=(_G_KP, _G_KV),
        **_COMMON,
    ),
    registry.Entry(
        name="nlio-fg",
        summary="interconnected observer, auxiliary linear observer with fixed gains",
        make=lambda: make_observer("nlio-fg"),
        gains=(_G_KP, _G_KV, _G_K1, _G_K2),
        **_COMMON,
    ),
    registry.Entry(
        name="nlio",
        summary="interconnected observer, auxiliary Kalman (time-varying) gains (NLIO-TV)",
        make=lambda: make_observer("nlio-tv"),
        gains=(_G_KP, _G_KV) + _G_TV,
        **_COMMON,
    ),
)
