"""Cascade attitude observer on SO(3) with Earth-velocity estimation (Batista, Silvestre, Oliveira, Systems &
Control Letters 126 (2019) 33-39).

Inputs: high-grade gyro ``gyr`` = omega + omega_E (rad/s, body; eq. 2, sensitive to the Earth's rate) and ONE
body-frame vector measurement ``mag`` = m = R^T I_m of a constant, known inertial vector (eq. 3; any unit,
e.g. nT). Known constants: I_m and I_omega_E in the inertial frame (NED in the paper). R maps body to inertial.

Blocks (cited by equation of that paper):

* Decomposition (5): omega_E = c1 m - c2 v, c1 = I_wE . I_m / |I_m|^2, c2 = 1 / |I_m|^2, with the auxiliary
  vector v = m x (m x omega_E) = R^T I_v, I_v = I_m x (I_m x I_wE) (eq. 6).
* Auxiliary observer (9), gains alpha0, alpha1, alpha2 > 0 (alpha1, alpha2 piecewise constant, Table 1):
    m^' = -S[gyr + c2 v^ + alpha1 m x m^] m^
    v^' = -S[gyr - c1 m] v^ + alpha2 m x m^ - alpha0 (m . v^) m
  It preserves |m^| (Theorem 1 needs |m^(t0)| = |I_m|); V = |m~|^2/2 + c2 |v~|^2 / (2 alpha2) has
  dV/dt = -alpha1 |m x m^|^2 - c2 alpha0 / alpha2 (m . v~)^2 (proof of Theorem 1).
* Earth-rate estimate (after Theorem 1): omega_E^ = c1 m - c2 v^ (rad/s, body).
* Attitude observer (16), gains alpha3, alpha4 > 0: R^' = R^ S[omega_o],
    omega_o = gyr - c1 m + c2 v^ + alpha3 m x (R^T I_m) + alpha4 v^ x (R^T I_v).
  Almost-global (semi-global) convergence (Theorem 2), local exponential stability of the cascade with the
  linearisation matrix A of Theorem 3's proof (:func:`linearization`).

Integration (a choice of this library; the paper says "fourth-order Runge-Kutta"):

* ``integrator="lie"`` (default): one RKMK-4 step (:func:`jaxatt.integrate.rkmk4_step`) with m^ moved by
  rotations (so |m^| is preserved, as eq. 9 preserves it) and R^ moved through the exponential map (so R^ stays
  on SO(3)); v^ with the same RK4 stages. Rounding of consecutive, nearly equal increments still adds up
  linearly in float32, so each step ends with one Newton-Schulz step R <- R (3I - R^T R)/2 and |m^| <- |m^(0)|
  (identities in exact arithmetic); both hold at rounding level over 1e6 steps.
* ``integrator="rk4"``: classical RK4 on (m^, v^, R^) as 15 numbers (the paper's method); R^ and |m^| drift.

Readings chosen (also in docs/observers/batista_so3.md):

* Table 1's columns are alpha1 |I_m|^2 and alpha2 (then after 720 s the linearised first block is
  s^2 + 2.5 s + 0.005, the same as the GES paper's Table 1 after 720 s). alpha0 = 0.1/|I_m|^2,
  alpha3 = 0.02/|I_m|^2, alpha4 = 0.4/|I_v|^2 (Section 4).
* m^(0): the paper says "the first measurement", but Theorem 1 needs |m^(0)| = |I_m| and (9) keeps |m^|, so a
  noisy first sample keeps its norm error for ever (std of m~ ~5x larger). Default ``m_init="rescaled"``: the
  first sample rescaled to |I_m|; ``m_init="first_sample"`` is the literal reading; ``m_init="params"`` uses
  ``params.m_hat_0``. v^(0) = params.v_hat_0 (zeros in the paper).
* The gain schedule is evaluated at the start of each step.

Missing samples (NaN in a log): a missing vector sample is replaced by m^ for that step (the corrections that
compare m with m^ vanish); a missing gyro sample holds the last valid gyro reading.
"""

from __future__ import annotations

import functools
from typing import NamedTuple, Union

import jax
import jax.numpy as jnp
import numpy as np

from .. import schedule, so3
from ..integrate import rk4_step, rkmk4_step
from ..types import ArrayLike, ImuSample, Interval, Observer, shown
from . import registry

__all__ = [
    "Params",
    "State",
    "Out",
    "Coefficients",
    "make_observer",
    "default_params",
    "coefficients",
    "check_params",
    "check_references",
    "lyapunov",
    "linearization",
    "TABLE1_SWITCH_TIMES",
    "TABLE1_ALPHA1_NORMALISED",
    "TABLE1_ALPHA2",
]

#: Table 1 of batista2019-so3: alpha1 |I_m|^2 (1/s) and alpha2 (1/s) on [0,300), [300,420), [420,600),
#: [600,720), [720, inf) s.
TABLE1_SWITCH_TIMES = (300.0, 420.0, 600.0, 720.0)
TABLE1_ALPHA1_NORMALISED = (10.0, 10.0, 5.0, 2.5, 2.5)
TABLE1_ALPHA2 = (10e-2, 5e-2, 2.5e-2, 1e-2, 5e-3)


class Params(NamedTuple):
    """Observer parameters (a pytree of arrays).

    Fields:
        ref_nav: I_m, the measured vector in the inertial frame (3,), unit of the sensor (e.g. nT, NED).
        earth_rate_nav: I_omega_E in the inertial frame (3,), rad/s.
        switch_times: (n-1,) s, increasing; alpha1[i], alpha2[i] hold on [switch_times[i-1], switch_times[i]).
        alpha1: (n,) gains of (9), 1/(s unit^2) (alpha1 |I_m|^2 is a rate, 1/s).
        alpha2: (n,) gains of (9), 1/s.
        alpha0: gain of (9), 1/(s unit^2).
        alpha3: gain of (16), 1/(s unit^2).
        alpha4: gain of (16), 1/(s unit^4 (rad/s)^2) (alpha4 |I_v|^2 is a rate, 1/s).
        m_hat_0, v_hat_0: initial m^ (3,) (used with m_init="params") and v^ (3,) (unit^2 rad/s).
        r_hat_0: initial R^ (3, 3), a rotation (body to inertial).
    """

    ref_nav: ArrayLike
    earth_rate_nav: ArrayLike
    switch_times: ArrayLike
    alpha1: ArrayLike
    alpha2: ArrayLike
    alpha0: ArrayLike
    alpha3: ArrayLike
    alpha4: ArrayLike
    m_hat_0: ArrayLike
    v_hat_0: ArrayLike
    r_hat_0: ArrayLike


class Coefficients(NamedTuple):
    """Constants of eqs. (5)-(6): c1 (rad/s per unit), c2 (1/unit^2), I_v = I_m x (I_m x I_wE) (3,)."""

    c1: jax.Array
    c2: jax.Array
    iv: jax.Array


class State(NamedTuple):
    """Observer state at time ``t`` (s): m^ (3,), v^ (3,), R^ (3, 3), the last valid gyro sample (3,), |m^(0)|
    (kept by eq. 9) and the derived coefficients (constant over a run)."""

    t: jax.Array
    m_hat: jax.Array
    v_hat: jax.Array
    r: jax.Array
    gyr_last: jax.Array
    m_norm: jax.Array
    coef: Coefficients


class Out(NamedTuple):
    """Estimates at time ``t`` (s): m^ (unit of m), v^ (unit^2 rad/s), omega_E^ = c1 m - c2 v^ (rad/s, body),
    R^ (SO(3), body to inertial)."""

    t: jax.Array
    m_hat: jax.Array
    v_hat: jax.Array
    earth_rate: jax.Array
    r: jax.Array


def coefficients(ref_nav, earth_rate_nav) -> Coefficients:
    """c1, c2 of eq. (5) and I_v of eq. (6)."""
    m, w = ref_nav, earth_rate_nav
    mm_ = jnp.dot(m, m)
    return Coefficients(jnp.dot(w, m) / mm_, 1.0 / mm_, so3.cross(m, so3.cross(m, w)))


def default_params(ref_nav, earth_rate_nav, *, r_hat_0=None, v_hat_0=None, dtype=None) -> Params:
    """Section 4's gains (Table 1 read as alpha1 |I_m|^2 and alpha2; alpha0 = 0.1/|I_m|^2, alpha3 = 0.02/|I_m|^2,
    alpha4 = 0.4/|I_v|^2), v^(0) = 0, and R^(0) a rotation of 179 deg about the z axis (the paper: "initial
    rotation angle error very close to 180 degrees", with R(0) = I).

    ref_nav: I_m in the inertial frame (e.g. nT, NED). earth_rate_nav: rad/s in the same frame.
    """
    dtype = dtype or jnp.result_type(float)
    m = np.asarray(ref_nav, float)
    w = np.asarray(earth_rate_nav, float)
    check_references(m, w)
    mm_ = float(m @ m)
    iv = np.cross(m, np.cross(m, w))
    r0 = (
        np.asarray(so3.exp(jnp.asarray([0.0, 0.0, np.deg2rad(179.0)])), float)
        if r_hat_0 is None
        else np.asarray(r_hat_0, float)
    )
    p = Params(
        ref_nav=m,
        earth_rate_nav=w,
        switch_times=np.asarray(TABLE1_SWITCH_TIMES),
        alpha1=np.asarray(TABLE1_ALPHA1_NORMALISED) / mm_,
        alpha2=np.asarray(TABLE1_ALPHA2),
        alpha0=np.asarray(0.1 / mm_),
        alpha3=np.asarray(0.02 / mm_),
        alpha4=np.asarray(0.4 / float(iv @ iv)),
        m_hat_0=np.asarray(r0.T @ m),
        v_hat_0=np.zeros(3) if v_hat_0 is None else np.asarray(v_hat_0, float),
        r_hat_0=r0,
    )
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), p)


# ------------------------------------------------------------------------------------------------------
# Validation at the API boundary (concrete arrays only; called by run/monte_carlo/CLI).
# ------------------------------------------------------------------------------------------------------
def check_references(ref_nav, earth_rate_nav, min_sin_angle: float = 1e-3) -> None:
    """Assumption 1: I_m not parallel to I_omega_E (|sin angle| >= ``min_sin_angle``); finite, shape (3,)."""
    from .batista_ges import check_references as check

    check(
        ref_nav,
        earth_rate_nav,
        min_sin_angle,
        paper="batista2019-so3",
        why="I_v = I_m x (I_m x I_wE) vanishes and the attitude is not observable from this vector and the Earth rate",
    )


def check_params(p: Params) -> None:
    """Raise ValueError with a clear message for invalid parameters (shapes, finiteness, signs)."""
    check_references(p.ref_nav, p.earth_rate_nav)
    schedule.check(p.switch_times, {"alpha1": p.alpha1, "alpha2": p.alpha2}, "Theorems 1-3")
    for name in ("alpha0", "alpha3", "alpha4"):
        v = np.asarray(getattr(p, name), float)
        if not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise ValueError(f"{name} must be finite and positive (Theorems 1-3), got {shown(v)}")
    for name, shape in (("m_hat_0", (3,)), ("v_hat_0", (3,)), ("r_hat_0", (3, 3))):
        v = np.asarray(getattr(p, name), float)
        if v.shape != shape or not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be a finite array of shape {shape}, got {v.shape}")
    r0 = np.asarray(p.r_hat_0, float)
    if np.linalg.norm(r0.T @ r0 - np.eye(3)) > 1e-6 or np.linalg.det(r0) <= 0:
        raise ValueError(
            "r_hat_0 must be a rotation matrix (eq. 16 evolves on SO(3)); use "
            "jaxatt.so3.nearest_rotation to project one"
        )


# ------------------------------------------------------------------------------------------------------
# Dynamics
# ------------------------------------------------------------------------------------------------------
def _schedule(p: Params, t):
    """alpha1, alpha2 of Table 1 at time t (s)."""
    return schedule.value_at(p.switch_times, t, p.alpha1, p.alpha2)


def _rates(p: Params, coef: Coefficients, a1, a2, m_hat, v_hat, r, u: ImuSample):
    """(v^', rotation rate of m^, body rate of R^) of eqs. (9) and (16)."""
    wm, m = u.gyr, u.mag
    assert m is not None  # u is a sample checked by _sanitize
    mxmh = so3.cross(m, m_hat)
    rate_m = -(wm + coef.c2 * v_hat + a1 * mxmh)  # m^' = rate_m x m^  (eq. 9, first line)
    dv = -so3.cross(wm - coef.c1 * m, v_hat) + a2 * mxmh - p.alpha0 * jnp.dot(m, v_hat) * m  # eq. 9, 2nd line
    rt = jnp.swapaxes(r, -1, -2)
    omega_o = (
        wm
        - coef.c1 * m
        + coef.c2 * v_hat
        + p.alpha3 * so3.cross(m, so3.mv(rt, p.ref_nav))
        + p.alpha4 * so3.cross(v_hat, so3.mv(rt, coef.iv))
    )  # eq. (16)
    return dv, rate_m, omega_o


def _sanitize(u: ImuSample, gyr_last, m_hat) -> ImuSample:
    if u.mag is None:
        raise ValueError("batista-so3 needs the vector measurement: samples with mag (or acc, with vector='acc')")
    gyr_ok = jnp.all(jnp.isfinite(u.gyr))
    mag_ok = jnp.all(jnp.isfinite(u.mag))
    return u._replace(gyr=jnp.where(gyr_ok, u.gyr, gyr_last), mag=jnp.where(mag_ok, u.mag, m_hat))


@functools.lru_cache(maxsize=None)
def make_observer(m_init: str = "rescaled", integrator: str = "lie", vector: str = "mag") -> Observer:
    """Build the observer (cached: the same arguments give the same object, so jitted runners are reused).

    Args:
        m_init: "rescaled" (first vector sample scaled to |I_m|; default, satisfies Theorem 1),
            "first_sample" (the paper's literal reading) or "params" (params.m_hat_0).
        integrator: "lie" (RKMK-4: |m^| and R^ in SO(3) preserved to rounding; default) or "rk4" (classical RK4
            on all 15 numbers, the paper's method).
        vector: which ImuSample field carries the vector measurement ("mag" or "acc").
    """
    if m_init not in ("rescaled", "first_sample", "params"):
        raise ValueError(f"m_init must be 'rescaled', 'first_sample' or 'params', got {m_init!r}")
    if integrator not in ("lie", "rk4"):
        raise ValueError(f"integrator must be 'lie' or 'rk4', got {integrator!r}")
    from .batista_ges import first_inputs, vector_input

    _get = vector_input(vector)

    def init(p: Params, sample: ImuSample) -> State:
        t0, gyr, mag = first_inputs(p, _get(sample))
        coef = coefficients(p.ref_nav, p.earth_rate_nav)
        ok = jnp.all(jnp.isfinite(mag)) & (jnp.sum(mag**2) > 0)
        if m_init == "params":
            m_hat = p.m_hat_0
        elif m_init == "first_sample":
            m_hat = jnp.where(ok, mag, p.m_hat_0)
        else:
            safe = jnp.where(ok, mag, p.m_hat_0)
            m_hat = safe * (jnp.linalg.norm(p.ref_nav) / jnp.linalg.norm(safe))
        return State(
            t0, m_hat, p.v_hat_0, p.r_hat_0, jnp.where(jnp.isfinite(gyr), gyr, 0.0), jnp.linalg.norm(m_hat), coef
        )

    def step(p: Params, s: State, sample, dt):
        u: Union[Interval, ImuSample]
        if isinstance(sample, Interval):
            u = Interval(
                _sanitize(_get(sample.start), s.gyr_last, s.m_hat), _sanitize(_get(sample.end), s.gyr_last, s.m_hat)
            )
            t0, gyr_new, m_now = u.start.t, u.end.gyr, u.end.mag
        else:
            u = _sanitize(_get(sample), s.gyr_last, s.m_hat)
            t0, gyr_new, m_now = u.t, u.gyr, u.mag
        a1, a2 = _schedule(p, t0)
        if integrator == "lie":

            def f(v_hat, frames, uu):
                m_hat, r = frames
                dv, rate_m, omega_o = _rates(p, s.coef, a1, a2, m_hat, v_hat, r, uu)
                return dv, (rate_m, omega_o)

            v_hat, (m_hat, r) = rkmk4_step(f, s.v_hat, (s.m_hat, s.r), u, dt)
            # Exact in exact arithmetic; in float32 the rounding of consecutive, nearly equal exp(S(phi)) adds up
            # linearly (~1e-8 per step). One Newton-Schulz step and a rescale hold R^ and |m^| at rounding level.
            r = so3.reorthonormalize(r)
            m_hat = m_hat * (s.m_norm / jnp.linalg.norm(m_hat))
        else:

            def f_rk4(x, uu):
                m_hat, v_hat, r = x
                dv, rate_m, omega_o = _rates(p, s.coef, a1, a2, m_hat, v_hat, r, uu)
                return so3.cross(rate_m, m_hat), dv, so3.mm(r, so3.skew(omega_o))

            m_hat, v_hat, r = rk4_step(f_rk4, (s.m_hat, s.v_hat, s.r), u, dt)
        t1 = t0 + dt
        we = s.coef.c1 * m_now - s.coef.c2 * v_hat
        return State(t1, m_hat, v_hat, r, gyr_new, s.m_norm, s.coef), Out(t1, m_hat, v_hat, we, r)

    def output(p: Params, s: State) -> Out:
        """The estimate held by ``s`` (omega_E^ with m^ standing in for the measurement)."""
        return Out(s.t, s.m_hat, s.v_hat, s.coef.c1 * s.m_hat - s.coef.c2 * s.v_hat, s.r)

    return Observer(init=init, step=step, name="batista-so3", output=output, hold="zoh")


# ------------------------------------------------------------------------------------------------------
# Analysis (proofs of Theorems 1 and 3)
# ------------------------------------------------------------------------------------------------------
def lyapunov(p: Params, t, m_err, v_err):
    """V = |m~|^2 / 2 + c2 |v~|^2 / (2 alpha2(t)) of Theorem 1's proof."""
    _, a2 = _schedule(p, t)
    c2 = 1.0 / jnp.dot(p.ref_nav, p.ref_nav)
    return 0.5 * jnp.sum(m_err**2, -1) + 0.5 * c2 / a2 * jnp.sum(v_err**2, -1)


def linearization(ref_nav, earth_rate_nav, alpha0, alpha1, alpha2, alpha3, alpha4) -> np.ndarray:
    """The constant matrix A (9, 9) of Theorem 3's proof, z' = A z with z = [R x1; R x2; x3] (x1: increment of
    m x m^, x2: of v~, x3: of R~ ~ I + S(x3)), in the inertial frame:

        A = [[A1, 0], [A21, alpha3 S(I_m)^2 + alpha4 S(I_v)^2]],  A21 = [c2 I - alpha4 S(I_v)] (on z2),
        A1 = [[-alpha1 |I_m|^2 I - c1 S(I_m),  c2 |I_m|^2 I - c2 I_m I_m^T],
              [-alpha2 I,                      -alpha0 I_m I_m^T + c2 S(I_v)]].

    The garbled print of A1 was re-derived from the linearised x1, x2 dynamics stated in the proof (rotated
    into the inertial frame with the nominal rates). Exponentially stable for positive gains (Theorem 3).
    """
    m = np.asarray(ref_nav, float)
    w = np.asarray(earth_rate_nav, float)
    mm_ = m @ m
    c1, c2 = (w @ m) / mm_, 1.0 / mm_
    iv = np.cross(m, np.cross(m, w))
    sm, sv, eye = np.asarray(so3.skew(jnp.asarray(m))), np.asarray(so3.skew(jnp.asarray(iv))), np.eye(3)
    a1 = np.block(
        [
            [-alpha1 * mm_ * eye - c1 * sm, c2 * mm_ * eye - c2 * np.outer(m, m)],
            [-alpha2 * eye, -alpha0 * np.outer(m, m) + c2 * sv],
        ]
    )
    a21 = np.hstack([np.zeros((3, 3)), c2 * eye - alpha4 * sv])
    a3 = alpha3 * sm @ sm + alpha4 * sv @ sv
    return np.block([[a1, np.zeros((6, 3))], [a21, a3]])


# ------------------------------------------------------------------------------------------------------
# Registry
# ------------------------------------------------------------------------------------------------------
def _paper_params(dtype=None) -> Params:
    """Section 4: IGRF-11 field at Lisbon (nT, NED), the Earth's rate there, Table 1."""
    from ..sim import earth

    return default_params(
        earth.LISBON_FIELD_NED_NT, np.asarray(earth.earth_rate_ned(earth.LISBON_LATITUDE_DEG)), dtype=dtype
    )


def _norm2(v):
    v = np.asarray(v, float)
    return float(v @ v)


def _iv_norm2(p):
    m, w = np.asarray(p.ref_nav, float), np.asarray(p.earth_rate_nav, float)
    return _norm2(np.cross(m, np.cross(m, w)))


ENTRIES = (
    registry.Entry(
        name="batista-so3",
        summary="attitude + Earth rate from a high-grade gyro and ONE vector, observer on SO(3) (RKMK-4 step)",
        reference="Batista, Silvestre, Oliveira 2019 (SO(3)), eqs. (9), (16)",
        make=make_observer,
        default_params=_paper_params,
        gains=(
            registry.Gain(
                "alpha1",
                "1/(s unit^2)",
                "gain of eq. (9), one value per Table-1 interval",
                "schedule",
                rate=("alpha1 |I_m|^2 (1/s)", lambda p: _norm2(p.ref_nav)),
            ),
            registry.Gain("alpha2", "1/s", "gain of eq. (9), one value per Table-1 interval", "schedule"),
            registry.Gain(
                "alpha0",
                "1/(s unit^2)",
                "gain of eq. (9) (damping of v^ along m)",
                rate=("alpha0 |I_m|^2 (1/s)", lambda p: _norm2(p.ref_nav)),
            ),
            registry.Gain(
                "alpha3",
                "1/(s unit^2)",
                "attitude gain of eq. (16) on the vector I_m",
                rate=("alpha3 |I_m|^2 (1/s)", lambda p: _norm2(p.ref_nav)),
            ),
            registry.Gain(
                "alpha4",
                "1/(s unit^4 (rad/s)^2)",
                "attitude gain of eq. (16) on I_v",
                rate=("alpha4 |I_v|^2 (1/s)", _iv_norm2),
            ),
        ),
        frame="NED",
        needs=("mag",),
        module="batista_so3",
        check=check_params,
        recorded=False,
    ),
)
