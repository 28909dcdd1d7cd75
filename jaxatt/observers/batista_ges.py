"""GES cascade attitude observer with Earth-velocity estimation (Batista, Silvestre, Oliveira, Asian J.
Control 2019).

Inputs: high-grade gyro ``gyr`` = omega + omega_E (rad/s, body; eq. 4, sensitive to the Earth's rate) and ONE
body-frame vector measurement ``mag`` = R^T I_m of a constant, known inertial vector (eq. 6; any unit, e.g. nT).
Known constants: I_m and I_omega_E in the inertial frame (NED in the paper). R maps body to inertial.

Blocks (all cited by equation of that paper):

* Earth-rate block, eq. (15): x1 = m, x2 = m x omega_E, with A21, A22 of eq. (13); gains alpha1, alpha2 > 0,
  piecewise constant in time (Table 1). Error dynamics (16) are linear and GES (Theorem 1); V = z1^T P z1 with
  P = diag(I/2, I/(2 alpha2)) has dV/dt = -alpha1 ||x1~||^2 (Appendix B).
* Earth-rate estimate, eq. (17): omega_E^ = We1 x1^ + We2 x1^ x x2^ (Proposition 1).
* Attitude in R^9, eq. (21): z2 = rows of R stacked; y = C2 z2 with y = [x1; x2; x1 x x2] and C2 = M (x) I3,
  M = [I_m; I_m x I_wE; I_m x (I_m x I_wE)] (rows). GES for any Q > 0 (Theorem 2).
* Estimate on SO(3), Theorem 3: if ||R^T R - I||_F <= eps the projection of R^ onto SO(3), otherwise
  R_f propagated with dR_f/dt = R_f S(gyr - omega_E^).

Readings chosen where the paper is open (also in docs/observers/batista_ges.md):

* Q only enters (21) through C2^T Q^-1. We store the equivalent z-space gain G = C2^T Q^-1 C2 (9x9, SPD iff Q
  is) and inject G (C2^-1 y^ - z2^). C2^-1 = M^-1 (x) I3 is cheap because the rows of M are orthogonal, and this
  avoids inverting Q itself (condition number ~1e13 for the paper's Q). Section IV's Q = 1e5 C2 QD C2^T, read
  literally (QD in the z-space), gives G = 1e-5 QD^-1: rates 0.0225, 0.00164, 0.00147 1/s on the three rows
  of R. :func:`gain_from_q` converts any y-space Q.
* x1^(0): the paper sets it to zero; with Table 1's first gains that drives x2^ to ~4e3 nT/s and the attitude
  has not converged by t = 2400 s. Default ``x1_init="first_sample"`` (x1^(0) = m(0)) reproduces the paper's
  Monte Carlo; ``x1_init="params"`` uses ``params.x1_0`` (zeros = the literal reading).
* Theorem 3: eps and the norm are not given; we use the Frobenius norm and eps = 0.5, and project only when
  det(R^) > 0 too (a reflection cannot be projected continuously; near convergence det > 0 always, so the
  theorem's conclusions are unchanged). The propagation law uses omega(t), which is not measured; we use its
  implementable reading gyr - omega_E^. The projection is Newton's polar iteration, exact to rounding inside that
  region.
* The Table-1 schedule is evaluated at the start of each step (switch times are multiples of dt).

Missing samples (NaN in a log): a missing vector sample switches the corrections off for that step (x1^
stands in for m); a missing gyro sample holds the last valid gyro reading.
"""

from __future__ import annotations

import functools
from typing import NamedTuple, Sequence, Union

import jax
import jax.numpy as jnp
import numpy as np

from .. import schedule, so3
from ..integrate import rk4_step
from ..types import ArrayLike, ImuSample, Interval, Observer, shown, shown_for_shape
from . import registry

__all__ = [
    "Params",
    "State",
    "Out",
    "Coefficients",
    "make_observer",
    "default_params",
    "gain_from_q",
    "paper_gain",
    "coefficients",
    "check_params",
    "TABLE1_SWITCH_TIMES",
    "TABLE1_ALPHA1",
    "TABLE1_ALPHA2",
    "lyapunov_block1",
    "growing_memory_params",
    "GROWING_MEMORY_TIMES",
]

#: Table 1 of batista2019-ges: gains of (15) on [0,60), [60,120), [120,240), [240,300), [300,600), [600,720),
#: [720, inf) s.
TABLE1_SWITCH_TIMES = (60.0, 120.0, 240.0, 300.0, 600.0, 720.0)
TABLE1_ALPHA1 = (100.0, 10.0, 5.0, 5.0, 5.0, 2.5, 2.5)
TABLE1_ALPHA2 = (10.0, 1.0, 1e-1, 5e-2, 25e-3, 10e-3, 5e-3)


class Params(NamedTuple):
    """Observer parameters (a pytree of arrays).

    Fields:
        ref_nav: I_m, the measured vector in the inertial frame (3,), unit of the sensor (e.g. nT, NED).
        earth_rate_nav: I_omega_E, the Earth's rate in the inertial frame (3,), rad/s.
        switch_times: (n-1,) s, increasing; gains[i] hold on [switch_times[i-1], switch_times[i]).
        alpha1, alpha2: (n,) positive gains of (15) per interval (1/s and 1/s^2).
        gain_z: G = C2^T Q^-1 C2, (9, 9) symmetric positive definite (1/s), acting on z2 = rows of R.
        epsilon: Theorem-3 threshold on ||R^T R - I||_F, in (0, 1).
        x1_0, x2_0: initial x1^, x2^ (3,) (x1_0 used only with x1_init="params").
        r_hat_0: initial R^ (3, 3); need not be a rotation.
    """

    ref_nav: ArrayLike
    earth_rate_nav: ArrayLike
    switch_times: ArrayLike
    alpha1: ArrayLike
    alpha2: ArrayLike
    gain_z: ArrayLike
    epsilon: ArrayLike
    x1_0: ArrayLike
    x2_0: ArrayLike
    r_hat_0: ArrayLike


class Coefficients(NamedTuple):
    """Constants derived from ``ref_nav`` and ``earth_rate_nav`` (eqs. 13, 17 and C2)."""

    a21: jax.Array
    a22: jax.Array
    we1: jax.Array
    we2: jax.Array
    m_inv: jax.Array  # (3, 3): C2^-1 = m_inv (x) I3


class State(NamedTuple):
    """Observer state at time ``t`` (s): x1^ (3,), x2^ (3,), R^ (3,3) = z2^ as rows, R_f (3,3) on SO(3), the
    last valid gyro sample (3,), and the derived coefficients (constant over a run)."""

    t: jax.Array
    x1: jax.Array
    x2: jax.Array
    r_hat: jax.Array
    r_f: jax.Array
    gyr_last: jax.Array
    coef: Coefficients


class Out(NamedTuple):
    """Estimates at time ``t`` (s): x1^ (unit of m), x2^ (unit of m times rad/s), omega_E^ (rad/s, body),
    R^ in R^9 as (3,3), R (SO(3) estimate of Theorem 3, body to inertial), and whether R was projected."""

    t: jax.Array
    x1: jax.Array
    x2: jax.Array
    earth_rate: jax.Array
    r_hat: jax.Array
    r: jax.Array
    projected: jax.Array


def coefficients(ref_nav, earth_rate_nav) -> Coefficients:
    """A21, A22 (eq. 13), We1, We2 (eq. 17) and M^-1 (C2^-1 = M^-1 (x) I3)."""
    m, w = ref_nav, earth_rate_nav
    mm_, ww, mw = jnp.dot(m, m), jnp.dot(w, w), jnp.dot(m, w)
    mxw = so3.cross(m, w)
    mxmxw = so3.cross(m, mxw)
    n2, n3 = jnp.dot(mxw, mxw), jnp.dot(mxmxw, mxmxw)
    a21 = (ww * mm_ - mw**2) / mm_
    a22 = mw * n2 / n3
    we1 = mw / mm_
    we2 = (mw**2 - mm_ * ww) / n3
    rows = jnp.stack([m, mxw, mxmxw])
    m_inv = rows.T / jnp.stack([mm_, n2, n3])[None, :]  # rows are orthogonal
    return Coefficients(a21, a22, we1, we2, m_inv)


def c2_matrix(ref_nav, earth_rate_nav) -> jax.Array:
    """C2 of eq. (21), (9, 9)."""
    m, w = jnp.asarray(ref_nav), jnp.asarray(earth_rate_nav)
    rows = jnp.stack([m, so3.cross(m, w), so3.cross(m, so3.cross(m, w))])
    return jnp.kron(rows, jnp.eye(3, dtype=rows.dtype))


def gain_from_q(q, ref_nav, earth_rate_nav) -> jax.Array:
    """z-space gain G = C2^T Q^-1 C2 for a y-space Q (9x9 SPD) of eq. (21)."""
    c2 = c2_matrix(ref_nav, earth_rate_nav)
    return c2.T @ jnp.linalg.solve(q, c2)


def paper_gain(ref_nav, earth_rate_nav, scale: float = 1e5, qd_diag=(20.0, 2e-2, 1e3)) -> jax.Array:
    """G for Section IV's Q = scale C2 QD C2^T, QD = diag(20/|I_m| I, 2e-2/|I_wE x I_m| I,
    1e3/|I_m x (I_wE x I_m)| I), read literally (QD in the z-space): G = QD^-1 / scale."""
    m, w = np.asarray(ref_nav, float), np.asarray(earth_rate_nav, float)
    norms = np.array([np.linalg.norm(m), np.linalg.norm(np.cross(w, m)), np.linalg.norm(np.cross(m, np.cross(w, m)))])
    qd = np.asarray(qd_diag, float) / norms
    return jnp.asarray(np.kron(np.diag(1.0 / (scale * qd)), np.eye(3)))


def default_params(ref_nav, earth_rate_nav, *, r_hat_0=None, epsilon: float = 0.5, dtype=None) -> Params:
    """Section IV's parameters: Table 1 schedule, literal Q, R^(0) = diag(-1, -1, 1), x1^(0) = x2^(0) = 0.

    ref_nav: I_m in the inertial frame (e.g. nT, NED). earth_rate_nav: rad/s in the same frame.
    """
    dtype = dtype or jnp.result_type(float)
    ref_nav = np.asarray(ref_nav, float)
    earth_rate_nav = np.asarray(earth_rate_nav, float)
    check_references(ref_nav, earth_rate_nav)
    r0 = np.diag([-1.0, -1.0, 1.0]) if r_hat_0 is None else np.asarray(r_hat_0, float)
    p = Params(
        ref_nav=ref_nav,
        earth_rate_nav=earth_rate_nav,
        switch_times=np.asarray(TABLE1_SWITCH_TIMES),
        alpha1=np.asarray(TABLE1_ALPHA1),
        alpha2=np.asarray(TABLE1_ALPHA2),
        gain_z=np.asarray(paper_gain(ref_nav, earth_rate_nav)),
        epsilon=np.asarray(epsilon),
        x1_0=np.zeros(3),
        x2_0=np.zeros(3),
        r_hat_0=r0,
    )
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), p)


#: Switch times (s) added to Table 1 by :func:`growing_memory_params`.
GROWING_MEMORY_TIMES = (900.0, 1200.0, 1500.0, 1800.0, 2100.0, 2400.0, 2700.0, 3000.0, 3300.0)


def growing_memory_params(
    p: Params,
    *,
    k: float = 1.5,
    grow_from: float = 900.0,
    early_scale: float = 0.01,
    late_alpha1_scale: float = 0.1,
    gain_z_scale: float = 8.0,
    refine_times: Sequence[float] = GROWING_MEMORY_TIMES,
) -> Params:
    """``p`` with a growing-memory Earth-rate block: a gain schedule for long runs (an extension of Table 1,
    not the paper's; issue 6, docs/observers/batista_ges.md "Tuning the gains").

    After Table 1's last switch (720 s) the block of eq. (15) averages the gyro noise over a fixed memory of
    about alpha1 / alpha2 = 500 s (only that ratio sets it). Here the schedule is refined at ``refine_times``
    (s) and, on the intervals that start at t >= ``grow_from`` (s), alpha1 = alpha1_last * ``late_alpha1_scale``
    and alpha2 = alpha1 * min(alpha2_last / alpha1_last, ``k`` / t): the memory grows as t / k, never shorter
    than Table 1's last. The intervals before ``grow_from`` keep Table 1 with alpha1 and alpha2 both times
    ``early_scale`` (same ratio: Table 1's large early alpha1 passes magnetometer noise into x2^, which a long
    memory would keep); gain_z (eq. 21) is multiplied by ``gain_z_scale``. Every gain stays positive, so
    Theorems 1-3 hold on each interval. The defaults were chosen by ``research/ges_refined_start.py
    --search`` on 32 training runs of Section IV's 3600-s scenario; on 700 held-out runs they lower the
    steady-state (t >= 2400 s) mean angle error by 22.7 %. The memory stops growing at the last of
    ``refine_times``: for longer runs pass switch times that cover the horizon.
    """
    for name, v in (
        ("k", k),
        ("early_scale", early_scale),
        ("late_alpha1_scale", late_alpha1_scale),
        ("gain_z_scale", gain_z_scale),
    ):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"growing_memory_params: {name} must be finite and positive, got {shown(v)}")
    if not (np.isfinite(grow_from) and grow_from > 0):
        raise ValueError(f"growing_memory_params: grow_from must be a positive time in s, got {grow_from}")
    q = schedule.refine(p, refine_times, ["alpha1", "alpha2"])
    starts = np.concatenate([[0.0], np.asarray(q.switch_times, float)])
    a1 = np.array(q.alpha1, float)
    a2 = np.array(q.alpha2, float)
    last_a1, last_a2 = float(np.asarray(p.alpha1)[-1]), float(np.asarray(p.alpha2)[-1])
    grow = starts >= grow_from
    a1[~grow] *= early_scale
    a2[~grow] *= early_scale
    a1[grow] = last_a1 * late_alpha1_scale
    a2[grow] = a1[grow] * np.minimum(last_a2 / last_a1, k / starts[grow])
    dtype = jnp.asarray(q.alpha1).dtype
    return q._replace(
        alpha1=jnp.asarray(a1, dtype), alpha2=jnp.asarray(a2, dtype), gain_z=jnp.asarray(q.gain_z) * gain_z_scale
    )


# ------------------------------------------------------------------------------------------------------
# Validation at the API boundary (concrete arrays only; called by run/monte_carlo/CLI).
# ------------------------------------------------------------------------------------------------------
#: Largest-component range of ``ref_nav`` and ``earth_rate_nav`` (their units): :func:`paper_gain` takes norms of
#: products of up to four components, which must neither underflow nor overflow in float64.
VECTOR_MAGNITUDE = (1e-50, 1e50)


def check_references(
    ref_nav,
    earth_rate_nav,
    min_sin_angle: float = 1e-3,
    *,
    paper: str = "batista2019-ges",
    why: str = "the attitude is not observable from this vector and the Earth rate (C2 is singular)",
) -> None:
    """Assumption 1 of both Batista et al. (2019) papers: I_m not parallel to I_omega_E (|sin angle| >=
    ``min_sin_angle``); finite, shape (3,)."""
    m = np.asarray(ref_nav, float)
    w = np.asarray(earth_rate_nav, float)
    for name, v in (("ref_nav", m), ("earth_rate_nav", w)):
        if v.shape != (3,):
            raise ValueError(f"{name} must have shape (3,), got {v.shape}")
        if not np.all(np.isfinite(v)) or not VECTOR_MAGNITUDE[0] <= np.max(np.abs(v)) <= VECTOR_MAGNITUDE[1]:
            lo, hi = VECTOR_MAGNITUDE
            raise ValueError(
                f"{name} must be finite and non-zero, its largest component {lo:g} to {hi:g} in size, got {shown(v)}"
            )
    m, w = m / np.max(np.abs(m)), w / np.max(np.abs(w))  # directions only: no underflow or overflow below
    s = np.linalg.norm(np.cross(m, w)) / (np.linalg.norm(m) * np.linalg.norm(w))
    if s < min_sin_angle:
        raise ValueError(
            f"Assumption 1 of {paper} is violated: the reference vector is (nearly) parallel to the Earth's "
            f"rotation rate (sin of the angle between them = {s:.2e} < {min_sin_angle}); {why}."
        )


def check_params(p: Params) -> None:
    """Raise ValueError with a clear message for invalid parameters (shapes, finiteness, signs, Q > 0)."""
    check_references(p.ref_nav, p.earth_rate_nav)
    schedule.check(p.switch_times, {"alpha1": p.alpha1, "alpha2": p.alpha2}, "Theorem 1")
    g = np.asarray(p.gain_z, float)
    if g.shape != (9, 9) or not np.all(np.isfinite(g)):
        raise ValueError(f"gain_z must be a finite (9, 9) matrix, got {shown_for_shape(g, (9, 9))}")
    if not np.allclose(g, g.T, rtol=1e-6, atol=0) or np.min(np.linalg.eigvalsh(0.5 * (g + g.T))) <= 0:
        raise ValueError("gain_z = C2^T Q^-1 C2 must be symmetric positive definite (Q > 0, Theorem 2)")
    eps = float(np.asarray(p.epsilon))
    if not (0.0 < eps < 1.0):
        raise ValueError(f"epsilon must be in (0, 1) (Theorem 3), got {eps}")
    for name, v, shape in (("x1_0", p.x1_0, (3,)), ("x2_0", p.x2_0, (3,)), ("r_hat_0", p.r_hat_0, (3, 3))):
        v = np.asarray(v, float)
        if v.shape != shape or not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be a finite array of shape {shape}, got {v.shape}")
    sv = np.linalg.svd(np.asarray(p.r_hat_0, float), compute_uv=False)
    if sv[-1] <= 1e-9 * max(sv[0], 1e-300):  # R_f(t0), its nearest rotation (Theorem 3), is not defined
        raise ValueError(
            f"r_hat_0 must have rank 3 (its nearest rotation starts R_f, Theorem 3), got singular values {shown(sv)}"
        )


# ------------------------------------------------------------------------------------------------------
# Dynamics
# ------------------------------------------------------------------------------------------------------
def _schedule(p: Params, t):
    """alpha1, alpha2 of Table 1 at time t (s)."""
    return schedule.value_at(p.switch_times, t, p.alpha1, p.alpha2)


def earth_rate_estimate(coef: Coefficients, x1, x2):
    """omega_E^ = We1 x1^ + We2 x1^ x x2^ (eq. 17), rad/s, body frame."""
    return coef.we1 * x1 + coef.we2 * so3.cross(x1, x2)


def _dynamics(p: Params, coef: Coefficients, a1, a2, x, u: ImuSample):
    x1, x2, r = x
    wm, m = u.gyr, u.mag
    assert m is not None  # u is a sample checked by _sanitize
    dx1 = -so3.cross(wm, x1) - x2 + a1 * (m - x1)  # eq. (15), first line
    dx2 = coef.a21 * m - so3.cross(wm - coef.a22 * m, x2) - a2 * (m - x1)  # eq. (15), second line
    we = earth_rate_estimate(coef, x1, x2)
    y = jnp.stack([x1, x2, so3.cross(x1, x2)])  # y^ as rows
    z_meas = so3.mm(coef.m_inv, y)  # C2^-1 y^ as a 3x3 (rows of R)
    inj = so3.mv(p.gain_z, (z_meas - r).reshape(9)).reshape(3, 3)  # C2^T Q^-1 (y^ - C2 z2^), eq. (21)
    dr = so3.mm(r, so3.skew(wm - we)) + inj  # -S3(wm - wE^) z2^ <=> R^ S(wm - wE^)
    return dx1, dx2, dr


def _sanitize(u: ImuSample, gyr_last, x1) -> ImuSample:
    if u.mag is None:
        raise ValueError("batista-ges needs the vector measurement: samples with mag (or acc, with vector='acc')")
    gyr_ok = jnp.all(jnp.isfinite(u.gyr))
    mag_ok = jnp.all(jnp.isfinite(u.mag))
    return u._replace(gyr=jnp.where(gyr_ok, u.gyr, gyr_last), mag=jnp.where(mag_ok, u.mag, x1))


def vector_input(vector: str):
    """``u -> u`` with the chosen ImuSample field ("mag" or "acc") as the vector measurement ``u.mag``."""
    if vector not in ("mag", "acc"):
        raise ValueError(f"vector must be 'mag' or 'acc', got {vector!r}")
    return (lambda u: u) if vector == "mag" else (lambda u: u._replace(mag=u.acc))


def first_inputs(p, sample):
    """(t, gyr, vector) of the first sample in the params' dtype (``sample.mag`` is the measured vector)."""
    dtype = p.r_hat_0.dtype
    return jnp.asarray(sample.t, dtype), jnp.asarray(sample.gyr, dtype), jnp.asarray(sample.mag, dtype)


@functools.lru_cache(maxsize=None)
def make_observer(x1_init: str = "first_sample", vector: str = "mag") -> Observer:
    """Build the observer (cached: the same arguments give the same object, so jitted runners are reused).

    Args:
        x1_init: "first_sample" (x1^(0) = first vector sample; default, reproduces the paper's numbers) or
            "params" (x1^(0) = params.x1_0; zeros is the paper's literal set-up).
        vector: which ImuSample field carries the vector measurement ("mag" or "acc").
    """
    if x1_init not in ("first_sample", "params"):
        raise ValueError(f"x1_init must be 'first_sample' or 'params', got {x1_init!r}")
    _get = vector_input(vector)

    def init(p: Params, sample: ImuSample) -> State:
        t0, gyr, mag = first_inputs(p, _get(sample))
        coef = coefficients(p.ref_nav, p.earth_rate_nav)
        if x1_init == "first_sample":
            x1 = jnp.where(jnp.all(jnp.isfinite(mag)), mag, p.x1_0)
        else:
            x1 = p.x1_0
        r_hat = p.r_hat_0
        # R_f(t0) must be a rotation (Theorem 3); nearest rotation when R^(0) is not one.
        r_f = so3.nearest_rotation(r_hat)
        return State(t0, x1, p.x2_0, r_hat, r_f, jnp.where(jnp.isfinite(gyr), gyr, 0.0), coef)

    def step(p: Params, s: State, sample, dt):
        u: Union[Interval, ImuSample]
        if isinstance(sample, Interval):
            u = Interval(_sanitize(_get(sample.start), s.gyr_last, s.x1), _sanitize(_get(sample.end), s.gyr_last, s.x1))
            t0, gyr_mid = u.start.t, 0.5 * (u.start.gyr + u.end.gyr)
            gyr_new = u.end.gyr
        else:
            u = _sanitize(_get(sample), s.gyr_last, s.x1)
            t0, gyr_mid, gyr_new = u.t, u.gyr, u.gyr
        a1, a2 = _schedule(p, t0)
        f = lambda x, uu: _dynamics(p, s.coef, a1, a2, x, uu)  # noqa: E731
        x1, x2, r_hat = rk4_step(f, (s.x1, s.x2, s.r_hat), u, dt)
        # Theorem 3: propagate R_f with gyr - omega_E^ (averaged over the step), or project R^.
        we0 = earth_rate_estimate(s.coef, s.x1, s.x2)
        we1 = earth_rate_estimate(s.coef, x1, x2)
        r_prop = so3.mm(s.r_f, so3.exp(dt * (gyr_mid - 0.5 * (we0 + we1))))
        close = (so3.orthogonality_error(r_hat) <= p.epsilon) & (so3.det3(r_hat) > 0)
        r_proj = so3.polar_newton(jnp.where(close, r_hat, jnp.eye(3, dtype=r_hat.dtype)))
        r_f = jnp.where(close, r_proj, r_prop)
        t1 = t0 + dt
        new = State(t1, x1, x2, r_hat, r_f, gyr_new, s.coef)
        return new, Out(t1, x1, x2, we1, r_hat, r_f, close)

    def output(p: Params, s: State) -> Out:
        close = (so3.orthogonality_error(s.r_hat) <= p.epsilon) & (so3.det3(s.r_hat) > 0)
        return Out(s.t, s.x1, s.x2, earth_rate_estimate(s.coef, s.x1, s.x2), s.r_hat, s.r_f, close)

    return Observer(init=init, step=step, name="batista-ges", output=output, hold="zoh")


def lyapunov_block1(p: Params, t, x1_err, x2_err):
    """V = z1^T P z1 with P = diag(I/2, I/(2 alpha2(t))) (Appendix B), z1 = [x1~; x2~]."""
    _, a2 = _schedule(p, t)
    return 0.5 * jnp.sum(x1_err**2, -1) + 0.5 / a2 * jnp.sum(x2_err**2, -1)


# ------------------------------------------------------------------------------------------------------
# Registry
# ------------------------------------------------------------------------------------------------------
def _paper_params(dtype=None) -> Params:
    """Section IV: IGRF-11 field at Lisbon (nT, NED), the Earth's rate there, Table 1 and the paper's Q."""
    from ..sim import earth

    return default_params(
        earth.LISBON_FIELD_NED_NT, np.asarray(earth.earth_rate_ned(earth.LISBON_LATITUDE_DEG)), dtype=dtype
    )


ENTRIES = (
    registry.Entry(
        name="batista-ges",
        summary="attitude + Earth rate from a high-grade gyro and ONE vector (GES, R^9 + projection)",
        reference="Batista, Silvestre, Oliveira 2019 (GES), eqs. (15), (17), (21), Theorem 3",
        make=make_observer,
        default_params=_paper_params,
        gains=(
            registry.Gain(
                "alpha1",
                "1/s",
                "gain of the Earth-rate block, eq. (15), one value per Table-1 interval (switch_times fixed)",
                "schedule",
            ),
            registry.Gain(
                "alpha2",
                "1/s^2",
                "gain of the Earth-rate block, eq. (15), one value per Table-1 interval (switch_times fixed)",
                "schedule",
            ),
            registry.Gain(
                "gain_z",
                "1/s",
                "z-space attitude gain G = C2^T Q^-1 C2 of eq. (21), 9x9 SPD acting on z2 = rows of R stacked",
                "spd",
            ),
        ),
        frame="NED",
        needs=("mag",),
        module="batista_ges",
        check=check_params,
        recorded=False,
    ),
)
