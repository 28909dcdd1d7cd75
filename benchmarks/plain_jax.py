"""Plain JAX Monte Carlos of four jaxatt studies: what a user would write without jaxatt (issue 19's reference).

Each study is written from its paper (and, for batista-ges, from benchmarks/numpy_reference.py), not from jaxatt's
code: truth, sensors and observer of one run in one ``jax.lax.scan``, ``jax.vmap`` over the runs' keys, ``jax.jit``.
Small matrices are ``jnp`` arrays multiplied with ``@``, rotations are projected with ``jnp.linalg.svd``, and the
noise of sample k of a run is ``jax.random.normal(jax.random.fold_in(key, k), (channels,))``. Nothing here imports
jaxatt. Per run the scan accumulates the rotation-angle error of the estimate (deg) over t >= ``window_start``:
mean, max and final value (estimates 1 ... n_steps; estimate 0 is init's and is not counted, as in jaxatt).

* :func:`batista_ges`: Batista, Silvestre, Oliveira 2019 (GES), Section IV: Magnus-4 truth with the slow
  sinusoidal rates, gyro (Earth rate, ARW 4 deg/h/rtHz) and magnetometer (150 nT) samples, the 15-state observer
  of eqs. (15), (17), (21) integrated by RK4 with the sample held over the step (9x9 S3 block matrix, C2^-1,
  z-space gain G = C2^T Q^-1 C2 of the paper's Q read literally, Table 1 schedule, x1^(0) = first sample), and
  Theorem 3's estimate on SO(3) (SVD projection when ||R^T R - I||_F <= 0.5 and det > 0, else propagation).
* :func:`batista_so3`: Batista, Silvestre, Oliveira 2019 (SO(3)), Section 4: the same platform, the auxiliary
  observer (9) and the attitude observer (16) with Table 1's gains, m^(0) = first sample rescaled to |I_m|,
  integrated by an RKMK-4 step (m^ and R^ moved by rotations, v^ by RK4 with the same stages), then one
  Newton-Schulz step on R^ and |m^| reset (what jaxatt's study runs: ``integrator="lie"``).
* :func:`nlio_case1`: sensors2020 (NLIO), Section 5, Case 1, NLIO with fixed gains (NLIO-FG): random initial
  estimate (ZYX angles uniform in [-pi, pi]), gyro with bias, accelerometer and magnetometer with Gaussian noise,
  eq. (8) with the orthonormal-TRIAD Gamma (eqs. 9-14), the bias projection, and the auxiliary observer (17),
  one RK4 step of the joint ODE with the samples interpolated over the step; the output is the SVD projection of
  the lifted R^.
* :func:`complementary`: Trumpf, Mahony, Hamel, Lageman 2012, eq. (10) with the bias integrator (k_I = 0 by
  default: the paper's observer) on one inertial direction rotating on a cone, RKMK-4 step on SO(3) and one
  Newton-Schulz step.

Every builder returns ``fn(items) -> dict`` (jitted, vmapped over the first axis of ``items``): ``items`` are PRNG
keys (``jax.random.PRNGKey`` arrays, (B, 2)) unless ``noise_at`` / ``init_at`` are given (the tests feed jaxatt's
noise stream that way). With ``record=True`` the result also holds every estimate and the true attitude
``r_true`` (runs, n_steps + 1, ...).

Usage (x64 enabled for float64)::

    fn = plain_jax.batista_ges(n_steps=2000)
    out = fn(jax.vmap(lambda k: jax.random.fold_in(jax.random.PRNGKey(0), k))(jnp.arange(1000)))
"""

from __future__ import annotations

import math
from typing import Callable, Dict, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "STUDIES",
    "batista_ges",
    "batista_so3",
    "nlio_case1",
    "complementary",
    "ges_constants",
    "so3_constants",
    "nlio_constants",
    "complementary_constants",
    "step_noise",
    "run_keys",
]

# ----------------------------------------------------------------------------------------------------------
# Small SO(3) helpers
# ----------------------------------------------------------------------------------------------------------
I3 = np.eye(3)


def skew(v):
    """S(v), S(v) y = v x y."""
    z = jnp.zeros_like(v[0])
    return jnp.array([[z, -v[2], v[1]], [v[2], z, -v[0]], [-v[1], v[0], z]])


def vex(m):
    """vex((M - M^T) / 2)."""
    return 0.5 * jnp.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])


def so3_exp(phi):
    """exp(S(phi)) by Rodrigues' formula (Taylor series for tiny angles)."""
    th2 = phi @ phi
    small = th2 < 1e-14
    th = jnp.sqrt(jnp.where(small, 1.0, th2))
    a = jnp.where(small, 1.0 - th2 / 6.0, jnp.sin(th) / th)
    b = jnp.where(small, 0.5 - th2 / 24.0, (1.0 - jnp.cos(th)) / jnp.where(small, 1.0, th2))
    s = skew(phi)
    return jnp.eye(3, dtype=phi.dtype) + a * s + b * (s @ s)


def project_so3(m):
    """argmin_{X in SO(3)} ||X - m||_F = U diag(1, 1, det(U V^T)) V^T."""
    u, _, vt = jnp.linalg.svd(m)
    d = jnp.sign(jnp.linalg.det(u @ vt))
    return u @ jnp.diag(jnp.array([1.0, 1.0, d], m.dtype)) @ vt


def unit(v):
    return v / jnp.linalg.norm(v)


def angle_deg(r_true, r_est):
    """Rotation angle of R_true^T R_est (deg)."""
    c = 0.5 * (jnp.trace(r_true.T @ r_est) - 1.0)
    return jnp.degrees(jnp.arccos(jnp.clip(c, -1.0, 1.0)))


def euler_zyx(roll, pitch, yaw):
    """R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr, cp, sp, cy, sy = jnp.cos(roll), jnp.sin(roll), jnp.cos(pitch), jnp.sin(pitch), jnp.cos(yaw), jnp.sin(yaw)
    rz = jnp.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = jnp.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = jnp.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def magnus4(r, rate, t, dt):
    """One 4th-order Magnus step of dR/dt = R S(omega(t)) (Gauss-Legendre nodes)."""
    c = math.sqrt(3.0) / 6.0
    w1, w2 = rate(t + (0.5 - c) * dt), rate(t + (0.5 + c) * dt)
    return r @ so3_exp(0.5 * dt * (w1 + w2) + (math.sqrt(3.0) / 12.0) * dt * dt * jnp.cross(w1, w2))


def newton_schulz(r):
    """One step R (3 I - R^T R) / 2 towards SO(3)."""
    return r @ (1.5 * jnp.eye(3, dtype=r.dtype) - 0.5 * r.T @ r)


def sinusoid_rates(amplitude, period, phase=(0.0, 0.0, 0.0), offset=(0.0, 0.0, 0.0)) -> Callable:
    """omega_i(t) = amplitude_i sin(2 pi t / period_i + phase_i) + offset_i (rad/s)."""
    amplitude, period, phase, offset = (np.asarray(x, float) for x in (amplitude, period, phase, offset))
    return lambda t: amplitude * jnp.sin(2.0 * jnp.pi * t / period + phase) + offset


def rkmk4(f, x, frames, sides, dt):
    """One Runge-Kutta-Munthe-Kaas step: ``f(x, frames) -> (dx, omegas)``; frame i is a rotation moved by
    R exp(S(phi)) (side +1) or a vector moved by exp(S(phi)) v (side -1); x (Euclidean) by RK4 with the same
    stages. dexp^-1 to fourth order: w + side/2 phi x w + phi x (phi x w) / 12."""

    def act(g, phi, side):
        return g @ so3_exp(phi) if side > 0 else so3_exp(phi) @ g

    def corrected(om, phis):
        return [
            w + 0.5 * s * jnp.cross(p, w) + jnp.cross(p, jnp.cross(p, w)) / 12.0 for w, p, s in zip(om, phis, sides)
        ]

    ks = []
    dx, om = f(x, frames)
    ks.append((dx, om))  # phi = 0: no correction
    for frac in (0.5, 0.5, 1.0):
        dx_prev, om_prev = ks[-1]
        phis = [frac * dt * w for w in om_prev]
        h = frac * dt
        xs = jax.tree_util.tree_map(lambda a, d, h=h: a + h * d, x, dx_prev)
        gs = [act(g, p, s) for g, p, s in zip(frames, phis, sides)]
        dx, om = f(xs, gs)
        ks.append((dx, corrected(om, phis)))
    avg = lambda a, b, c, d: (a + 2.0 * (b + c) + d) / 6.0  # noqa: E731
    dx = jax.tree_util.tree_map(avg, *[k[0] for k in ks])
    phis = [avg(*[k[1][i] for k in ks]) for i in range(len(frames))]
    x_new = jax.tree_util.tree_map(lambda a, d: a + dt * d, x, dx)
    return x_new, [act(g, dt * p, s) for g, p, s in zip(frames, phis, sides)]


def rk4(f, x, dt, inputs):
    """Classical RK4 of dx/dt = f(x, u) for a pytree x; ``inputs`` = (u at t, u at t + dt/2, u at t + dt)."""
    u0, uh, u1 = inputs
    add = lambda a, b, h: jax.tree_util.tree_map(lambda p, q: p + h * q, a, b)  # noqa: E731
    k1 = f(x, u0)
    k2 = f(add(x, k1, 0.5 * dt), uh)
    k3 = f(add(x, k2, 0.5 * dt), uh)
    k4 = f(add(x, k3, dt), u1)
    return jax.tree_util.tree_map(lambda p, a, b, c, d: p + dt * (a + 2.0 * (b + c) + d) / 6.0, x, k1, k2, k3, k4)


# ----------------------------------------------------------------------------------------------------------
# Noise and the per-run Monte Carlo loop
# ----------------------------------------------------------------------------------------------------------
def step_noise(channels: int) -> Callable:
    """``noise_at(key, k)``: the standard normals of sample k of the run of ``key``."""
    return lambda key, k: jax.random.normal(jax.random.fold_in(key, k), (channels,))


def run_keys(seed: int, runs: int):
    """(runs, 2) keys fold_in(PRNGKey(seed), k)."""
    base = jax.random.PRNGKey(seed)
    return jax.vmap(lambda k: jax.random.fold_in(base, k))(jnp.arange(runs, dtype=jnp.uint32))


def _monte_carlo(init, step, n_steps: int, dt: float, window_start: float, record: bool, prepare=None):
    """``jit(vmap(run))`` with run(item): init(item) -> (carry, r_true0, out0); step(item, carry, k) -> (carry,
    r_true, out) advancing from t_k to t_{k+1}; out["r"] is the estimate on SO(3). ``prepare(item)`` (once per
    run) turns the batch item into what init and step read."""

    def run(item):
        if prepare is not None:
            item = prepare(item)
        carry0, r_true0, out0 = init(item)
        z = jnp.zeros((), out0["r"].dtype)

        def body(c, k):
            carry, (total, count, worst, _) = c
            carry, r_true, out = step(item, carry, k)
            ang = angle_deg(r_true, out["r"])
            w = (k + 1) * dt >= window_start
            acc = (total + jnp.where(w, ang, 0.0), count + w, jnp.maximum(worst, jnp.where(w, ang, 0.0)), ang)
            return (carry, acc), (dict(out, r_true=r_true) if record else None)

        (_, (total, count, worst, last)), recs = jax.lax.scan(body, (carry0, (z, z, z, z)), jnp.arange(n_steps))
        res = {
            "mean_angle_error_deg": total / jnp.maximum(count, 1.0),
            "max_angle_error_deg": worst,
            "final_angle_error_deg": last,
        }
        if record:
            out0 = dict(out0, r_true=r_true0)
            res.update({k: jnp.concatenate([out0[k][None], v]) for k, v in recs.items()})
        return res

    return jax.jit(jax.vmap(run))


# ----------------------------------------------------------------------------------------------------------
# Batista et al. 2019 (GES), Section IV
# ----------------------------------------------------------------------------------------------------------
LISBON_LATITUDE_DEG = 38.7138
LISBON_FIELD_NED_NT = (2.6338e4, 0.0851e4, 3.6359e4)  # IGRF-11 (nT, NED)
EARTH_RATE = 7.2921150e-5  # rad/s


def earth_rate_ned(latitude_deg: float = LISBON_LATITUDE_DEG) -> np.ndarray:
    lat = math.radians(latitude_deg)
    return EARTH_RATE * np.array([math.cos(lat), 0.0, -math.sin(lat)])


def batista_rates() -> Callable:
    """Section IV's slow profile: (5, 1, -2) deg/s sin(2 pi t / (60, 180, 300) s)."""
    return sinusoid_rates(np.deg2rad([5.0, 1.0, -2.0]), [60.0, 180.0, 300.0])


class GesConstants(NamedTuple):
    m: np.ndarray  # I_m (nT, NED)
    w: np.ndarray  # I_wE (rad/s, NED)
    a21: float
    a22: float
    we1: float
    we2: float
    c2_inv: np.ndarray  # (9, 9)
    g: np.ndarray  # (9, 9) z-space gain C2^T Q^-1 C2
    switch_times: np.ndarray
    alpha1: np.ndarray
    alpha2: np.ndarray
    epsilon: float
    r_hat_0: np.ndarray
    x2_0: np.ndarray
    sigma_g: float  # gyro noise std per sample (rad/s)
    sigma_m: float  # magnetometer noise std (nT)


def ges_constants(dt: float = 0.01) -> GesConstants:
    """The paper's numbers: eqs. (13), (17), C2 of (21), Q = 1e5 C2 QD C2^T read literally (G = QD^-1 / 1e5),
    Table 1, R^(0) = diag(-1, -1, 1), eps = 0.5, gyro ARW 4 deg/h/rtHz, magnetometer 150 nT."""
    m, w = np.asarray(LISBON_FIELD_NED_NT, float), earth_rate_ned()
    mm, ww, mw = m @ m, w @ w, m @ w
    mxw, mxmxw = np.cross(m, w), np.cross(m, np.cross(m, w))
    ix = np.array([m, mxw, mxmxw])  # I_x{ij}
    c2 = np.zeros((9, 9))
    for i in range(3):
        for j in range(3):
            for k in range(3):
                c2[3 * i + k, 3 * j + k] = ix[i, j]
    norms = np.array([np.linalg.norm(m), np.linalg.norm(np.cross(w, m)), np.linalg.norm(np.cross(m, np.cross(w, m)))])
    qd = np.array([20.0, 2e-2, 1e3]) / norms
    return GesConstants(
        m=m,
        w=w,
        a21=float((ww * mm - mw**2) / mm),
        a22=float(mw * (mxw @ mxw) / (mxmxw @ mxmxw)),
        we1=float(mw / mm),
        we2=float((mw**2 - mm * ww) / (mxmxw @ mxmxw)),
        c2_inv=np.linalg.inv(c2),
        g=np.kron(np.diag(1.0 / (1e5 * qd)), np.eye(3)),
        switch_times=np.array([60.0, 120.0, 240.0, 300.0, 600.0, 720.0]),
        alpha1=np.array([100.0, 10.0, 5.0, 5.0, 5.0, 2.5, 2.5]),
        alpha2=np.array([10.0, 1.0, 1e-1, 5e-2, 25e-3, 10e-3, 5e-3]),
        epsilon=0.5,
        r_hat_0=np.diag([-1.0, -1.0, 1.0]),
        x2_0=np.zeros(3),
        sigma_g=math.radians(4.0) / 3600.0 / math.sqrt(dt),
        sigma_m=150.0,
    )


def batista_ges(
    n_steps: int,
    dt: float = 0.01,
    *,
    window_start: float = 0.0,
    noise_at: Optional[Callable] = None,
    record: bool = False,
    c: Optional[GesConstants] = None,
):
    """Truth + sensors + the GES observer of one run per item (a key, or what ``noise_at(item, k)`` reads)."""
    c = ges_constants(dt) if c is None else c
    noise_at = noise_at or step_noise(6)
    rate = batista_rates()
    m_ref, w_ref = jnp.asarray(c.m), jnp.asarray(c.w)
    c2_inv, g = jnp.asarray(c.c2_inv), jnp.asarray(c.g)

    def sample(r, t, n):
        gyr = rate(t) + r.T @ w_ref + c.sigma_g * n[0:3]
        mag = r.T @ m_ref + c.sigma_m * n[3:6]
        return gyr, mag

    def earth_rate(x1, x2):  # eq. (17)
        return c.we1 * x1 + c.we2 * jnp.cross(x1, x2)

    def f(x, u):
        gyr, m, a1, a2 = u
        x1, x2, z2 = x[0:3], x[3:6], x[6:15]
        dx1 = -skew(gyr) @ x1 - x2 + a1 * (m - x1)  # eq. (15)
        dx2 = c.a21 * m - skew(gyr - c.a22 * m) @ x2 - a2 * (m - x1)
        y_hat = jnp.concatenate([x1, x2, jnp.cross(x1, x2)])
        s3 = jnp.kron(jnp.eye(3), skew(gyr - earth_rate(x1, x2)))  # S3 = diag(S, S, S)
        dz2 = -s3 @ z2 + g @ (c2_inv @ y_hat - z2)  # eq. (21)
        return jnp.concatenate([dx1, dx2, dz2])

    def init(item):
        r = jnp.eye(3)
        gyr, mag = sample(r, 0.0, noise_at(item, 0))
        r_hat = jnp.asarray(c.r_hat_0)
        x = jnp.concatenate([mag, jnp.asarray(c.x2_0), r_hat.reshape(9)])
        r_f = project_so3(r_hat)
        return (r, x, r_f, gyr, mag), r, {"r": r_f, "x1": x[0:3], "x2": x[3:6], "r_hat": r_hat}

    def step(item, carry, k):
        r, x, r_f, gyr, mag = carry
        t = k * dt
        i = jnp.sum(t >= c.switch_times)  # Table 1
        u = (gyr, mag, jnp.asarray(c.alpha1)[i], jnp.asarray(c.alpha2)[i])
        x_new = rk4(f, x, dt, (u, u, u))
        r_hat = x_new[6:15].reshape(3, 3)
        w0, w1 = earth_rate(x[0:3], x[3:6]), earth_rate(x_new[0:3], x_new[3:6])
        orth = jnp.linalg.norm(r_hat.T @ r_hat - jnp.eye(3), "fro")
        close = (orth <= c.epsilon) & (jnp.linalg.det(r_hat) > 0)  # Theorem 3
        r_f = jnp.where(close, project_so3(r_hat), r_f @ so3_exp(dt * (gyr - 0.5 * (w0 + w1))))
        r = magnus4(r, rate, t, dt)
        gyr, mag = sample(r, (k + 1) * dt, noise_at(item, k + 1))
        return (r, x_new, r_f, gyr, mag), r, {"r": r_f, "x1": x_new[0:3], "x2": x_new[3:6], "r_hat": r_hat}

    return _monte_carlo(init, step, n_steps, dt, window_start, record)


# ----------------------------------------------------------------------------------------------------------
# Batista et al. 2019 (SO(3)), Section 4
# ----------------------------------------------------------------------------------------------------------
class So3Constants(NamedTuple):
    m: np.ndarray
    w: np.ndarray
    c1: float
    c2: float
    iv: np.ndarray  # I_m x (I_m x I_wE)
    switch_times: np.ndarray
    alpha1: np.ndarray
    alpha2: np.ndarray
    alpha0: float
    alpha3: float
    alpha4: float
    r_hat_0: np.ndarray
    v_hat_0: np.ndarray
    sigma_g: float
    sigma_m: float


def so3_constants(dt: float = 0.01) -> So3Constants:
    """Section 4: eqs. (5)-(6), Table 1 read as alpha1 |I_m|^2 and alpha2, alpha0 = 0.1 / |I_m|^2,
    alpha3 = 0.02 / |I_m|^2, alpha4 = 0.4 / |I_v|^2, R^(0) = 179 deg about z, v^(0) = 0; sensors as Section IV."""
    m, w = np.asarray(LISBON_FIELD_NED_NT, float), earth_rate_ned()
    mm = float(m @ m)
    iv = np.cross(m, np.cross(m, w))
    th = math.radians(179.0)
    r0 = np.array([[math.cos(th), -math.sin(th), 0.0], [math.sin(th), math.cos(th), 0.0], [0.0, 0.0, 1.0]])
    return So3Constants(
        m=m,
        w=w,
        c1=float(w @ m) / mm,
        c2=1.0 / mm,
        iv=iv,
        switch_times=np.array([300.0, 420.0, 600.0, 720.0]),
        alpha1=np.array([10.0, 10.0, 5.0, 2.5, 2.5]) / mm,
        alpha2=np.array([10e-2, 5e-2, 2.5e-2, 1e-2, 5e-3]),
        alpha0=0.1 / mm,
        alpha3=0.02 / mm,
        alpha4=0.4 / float(iv @ iv),
        r_hat_0=r0,
        v_hat_0=np.zeros(3),
        sigma_g=math.radians(4.0) / 3600.0 / math.sqrt(dt),
        sigma_m=150.0,
    )


def batista_so3(
    n_steps: int,
    dt: float = 0.01,
    *,
    window_start: float = 0.0,
    noise_at: Optional[Callable] = None,
    record: bool = False,
    c: Optional[So3Constants] = None,
):
    """Truth + sensors + the SO(3) observer (eqs. 9, 16) of one run per item."""
    c = so3_constants(dt) if c is None else c
    noise_at = noise_at or step_noise(6)
    rate = batista_rates()
    m_ref, w_ref, iv = jnp.asarray(c.m), jnp.asarray(c.w), jnp.asarray(c.iv)

    def sample(r, t, n):
        return rate(t) + r.T @ w_ref + c.sigma_g * n[0:3], r.T @ m_ref + c.sigma_m * n[3:6]

    def init(item):
        r = jnp.eye(3)
        gyr, mag = sample(r, 0.0, noise_at(item, 0))
        m_hat = mag * (jnp.linalg.norm(m_ref) / jnp.linalg.norm(mag))  # |m^(0)| = |I_m| (Theorem 1)
        r_hat = jnp.asarray(c.r_hat_0)
        v_hat = jnp.asarray(c.v_hat_0)
        carry = (r, m_hat, v_hat, r_hat, jnp.linalg.norm(m_hat), gyr, mag)
        return carry, r, {"r": r_hat, "m_hat": m_hat, "v_hat": v_hat}

    def step(item, carry, k):
        r, m_hat, v_hat, r_hat, m_norm, gyr, mag = carry
        t = k * dt
        i = jnp.sum(t >= c.switch_times)  # Table 1
        a1, a2 = jnp.asarray(c.alpha1)[i], jnp.asarray(c.alpha2)[i]

        def f(v, frames):
            mh, rh = frames
            mxmh = jnp.cross(mag, mh)
            rate_m = -(gyr + c.c2 * v + a1 * mxmh)  # eq. (9): m^' = rate_m x m^
            dv = -jnp.cross(gyr - c.c1 * mag, v) + a2 * mxmh - c.alpha0 * (mag @ v) * mag
            omega_o = (
                gyr
                - c.c1 * mag
                + c.c2 * v
                + c.alpha3 * jnp.cross(mag, rh.T @ m_ref)
                + c.alpha4 * jnp.cross(v, rh.T @ iv)
            )  # eq. (16)
            return dv, [rate_m, omega_o]

        v_hat, (m_hat, r_hat) = rkmk4(f, v_hat, [m_hat, r_hat], (-1.0, 1.0), dt)
        r_hat = newton_schulz(r_hat)
        m_hat = m_hat * (m_norm / jnp.linalg.norm(m_hat))
        r = magnus4(r, rate, t, dt)
        gyr, mag = sample(r, (k + 1) * dt, noise_at(item, k + 1))
        return (r, m_hat, v_hat, r_hat, m_norm, gyr, mag), r, {"r": r_hat, "m_hat": m_hat, "v_hat": v_hat}

    return _monte_carlo(init, step, n_steps, dt, window_start, record)


# ----------------------------------------------------------------------------------------------------------
# sensors2020 NLIO, Section 5, Case 1, NLIO-FG
# ----------------------------------------------------------------------------------------------------------
class NlioConstants(NamedTuple):
    acc_ref: np.ndarray  # v_1^N = g^N (m/s^2, NED)
    mag_ref: np.ndarray  # v_2^N (G, NED)
    kp: np.ndarray
    kv: float
    theta: float
    bias_bound: float  # L_b
    bias_max: float  # l_b
    k1: np.ndarray
    k2: np.ndarray
    gyro_bias: np.ndarray
    sigma_g: float
    sigma_a: float
    sigma_m: float


def nlio_constants() -> NlioConstants:
    """Section 5, Case 1: Kp = 15 I, kv = 0.2, theta = 1, K1 = 5.6 I, K2 = 3.3 I, bias [-0.017, -0.017, 0.017]
    rad/s, gyro noise 1e-3 rad/s, accelerometer 5e-3 g, magnetometer 8e-3 G; L_b = 0.05, l_b = 0.06 rad/s."""
    return NlioConstants(
        acc_ref=np.array([0.0, 0.0, 9.81]),
        mag_ref=np.array([0.3128, 0.0, 0.4282]),
        kp=15.0 * I3,
        kv=0.2,
        theta=1.0,
        bias_bound=0.05,
        bias_max=0.06,
        k1=5.6 * I3,
        k2=3.3 * I3,
        gyro_bias=np.array([-0.017, -0.017, 0.017]),
        sigma_g=1e-3,
        sigma_a=5e-3 * 9.81,
        sigma_m=8e-3,
    )


def nlio_rates(t):
    """omega(t) = [0.1 sin(pi t / 12), -0.2 cos(pi t / 10), 0.1 sin(pi t / 12)] rad/s."""
    return jnp.stack(
        [0.1 * jnp.sin(jnp.pi * t / 12.0), -0.2 * jnp.cos(jnp.pi * t / 10.0), 0.1 * jnp.sin(jnp.pi * t / 12.0)]
    )


def triad(v1, v2):
    """The orthonormal TRIAD frame [u1, n, u1 x n] (columns), n = unit(u1 x u2)."""
    u1 = unit(v1)
    n = unit(jnp.cross(u1, unit(v2)))
    return jnp.stack([u1, n, jnp.cross(u1, n)], axis=1)


def random_attitude_angles(key):
    """ZYX roll, pitch, yaw of the initial estimate, each uniform in [-pi, pi]."""
    return jax.random.uniform(key, (3,), minval=-jnp.pi, maxval=jnp.pi)


def nlio_case1(
    n_steps: int,
    dt: float = 0.01,
    *,
    window_start: float = 0.0,
    noise_at: Optional[Callable] = None,
    init_at: Optional[Callable] = None,
    record: bool = False,
    c: Optional[NlioConstants] = None,
):
    """Truth + sensors + NLIO-FG of one run per item. By default an item is a key split into an initial-attitude
    key and a noise key; ``init_at(item)`` (ZYX angles of R^(0)) and ``noise_at(item, k)`` replace the draws."""
    c = nlio_constants() if c is None else c
    prepare = None
    if noise_at is None and init_at is None:  # a run's key -> (initial-attitude key, noise key)
        prepare = jax.random.split
        draw = step_noise(9)
        noise_at = lambda keys, k: draw(keys[1], k)  # noqa: E731
        init_at = lambda keys: random_attitude_angles(keys[0])  # noqa: E731
    elif noise_at is None or init_at is None:
        raise ValueError("give both noise_at and init_at, or neither")
    acc_ref, mag_ref, bias = jnp.asarray(c.acc_ref), jnp.asarray(c.mag_ref), jnp.asarray(c.gyro_bias)
    kp, k1, k2 = jnp.asarray(c.kp), jnp.asarray(c.k1), jnp.asarray(c.k2)
    a_n = triad(acc_ref, mag_ref)

    def sample(r, t, n):
        gyr = nlio_rates(t) + bias + c.sigma_g * n[0:3]
        return gyr, r.T @ acc_ref + c.sigma_a * n[3:6], r.T @ mag_ref + c.sigma_m * n[6:9]

    def projection(b, tau):  # Grip et al.'s parameter projection
        nb2, bt = b @ b, b @ tau
        cc = jnp.clip((nb2 - c.bias_bound**2) / (c.bias_max**2 - c.bias_bound**2), 0.0, 1.0)
        active = (nb2 >= c.bias_bound**2) & (bt > 0)
        return jnp.where(active, tau - cc * bt * b / jnp.where(active, nb2, 1.0), tau)

    def f(x, u):
        r_hat, b, v1, v2 = x
        gyr, acc, mag = u
        w = gyr - b
        dv1 = jnp.cross(v1, w) + k1 @ (acc - v1)  # eq. (17)
        dv2 = jnp.cross(v2, w) + k2 @ (mag - v2)
        a_b = triad(v1, v2)
        gamma = a_n @ a_b.T - a_n @ a_n.T @ r_hat  # eqs. (9)-(14)
        kg = kp @ gamma
        dr = r_hat @ skew(gyr - b) + c.theta * kg  # eq. (8)
        tau = -c.kv * vex(jnp.clip(r_hat, -1.0, 1.0).T @ kg)
        return dr, projection(b, tau), dv1, dv2

    def init(item):
        e = init_at(item)
        r = jnp.eye(3)
        s0 = sample(r, 0.0, noise_at(item, 0))
        r_hat = euler_zyx(e[0], e[1], e[2])
        b = jnp.zeros(3)
        return (r, r_hat, b, s0[1], s0[2], s0), r, {"r": project_so3(r_hat), "r_hat": r_hat, "bias": b}

    def step(item, carry, k):
        r, r_hat, b, v1, v2, s0 = carry
        t = k * dt
        r = magnus4(r, nlio_rates, t, dt)
        s1 = sample(r, (k + 1) * dt, noise_at(item, k + 1))
        s_half = tuple(a + 0.5 * (b_ - a) for a, b_ in zip(s0, s1))  # samples interpolated over the step
        r_hat, b, v1, v2 = rk4(f, (r_hat, b, v1, v2), dt, (s0, s_half, s1))
        b = b * jnp.minimum(1.0, c.bias_max / jnp.linalg.norm(b))  # |b^| <= l_b after the step
        return (r, r_hat, b, v1, v2, s1), r, {"r": project_so3(r_hat), "r_hat": r_hat, "bias": b}

    return _monte_carlo(init, step, n_steps, dt, window_start, record, prepare)


# ----------------------------------------------------------------------------------------------------------
# Trumpf et al. 2012, eq. (10), rotating reference
# ----------------------------------------------------------------------------------------------------------
class ComplementaryConstants(NamedTuple):
    r0: np.ndarray  # true R(0)
    r_hat_0: np.ndarray
    k: float  # gain of the one complementary measurement (1/s)
    k_i: float  # bias integral gain (1/s), 0 = the paper's observer
    ref_rate: float  # rad/s of the reference about the inertial z axis
    ref_tilt: float  # rad, half-angle of its cone
    gyro_bias: np.ndarray
    sigma_g: float
    sigma_a: float


def _euler_np(roll_deg, pitch_deg, yaw_deg) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) in numpy (angles in deg)."""
    r, p, y = np.deg2rad([roll_deg, pitch_deg, yaw_deg])
    rz = np.array([[np.cos(y), -np.sin(y), 0.0], [np.sin(y), np.cos(y), 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[np.cos(p), 0.0, np.sin(p)], [0.0, 1.0, 0.0], [-np.sin(p), 0.0, np.cos(p)]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(r), -np.sin(r)], [0.0, np.sin(r), np.cos(r)]])
    return rz @ ry @ rx


def complementary_constants() -> ComplementaryConstants:
    """The "rotating" scenario: å(t) = Rz(30 deg/s t) (sin 60 deg, 0, cos 60 deg); R(0) = ZYX (20, -10, 30) deg,
    R^(0) = ZYX (150, 0, 0) deg, k = 0.6 1/s, no bias, no noise (jaxatt's study defaults)."""
    return ComplementaryConstants(
        r0=_euler_np(20.0, -10.0, 30.0),
        r_hat_0=_euler_np(150.0, 0.0, 0.0),
        k=0.6,
        k_i=0.0,
        ref_rate=math.radians(30.0),
        ref_tilt=math.radians(60.0),
        gyro_bias=np.zeros(3),
        sigma_g=0.0,
        sigma_a=0.0,
    )


def complementary(
    n_steps: int,
    dt: float = 0.01,
    *,
    window_start: float = 0.0,
    noise_at: Optional[Callable] = None,
    record: bool = False,
    c: Optional[ComplementaryConstants] = None,
):
    """Truth + one complementary measurement + the observer of eq. (10) (with k_I bias integrator)."""
    c = complementary_constants() if c is None else c
    noise_at = noise_at or step_noise(6)
    rate = sinusoid_rates(np.deg2rad([10.0, 6.0, 8.0]), [20.0, 30.0, 45.0])
    bias = jnp.asarray(c.gyro_bias)

    def reference(t):
        a = c.ref_rate * t
        st, ct = math.sin(c.ref_tilt), math.cos(c.ref_tilt)
        return jnp.stack([jnp.cos(a) * st, jnp.sin(a) * st, jnp.full_like(a, ct)])

    def sample(r, t, n):
        ar = reference(t)
        return rate(t) + bias + c.sigma_g * n[0:3], r.T @ ar + c.sigma_a * n[3:6], ar

    def init(item):
        r = jnp.asarray(c.r0)
        s0 = sample(r, 0.0, noise_at(item, 0))
        r_hat = jnp.asarray(c.r_hat_0)
        return (r, r_hat, jnp.zeros(3), s0), r, {"r": r_hat}

    def step(item, carry, k):
        r, r_hat, b, (gyr, a, ar) = carry
        t = k * dt
        a_u, ar_u = unit(a), unit(ar)

        def f(b_, frames):
            sigma = c.k * jnp.cross(a_u, frames[0].T @ ar_u)  # k a x (R^T å), eq. (10)
            return -c.k_i * sigma, [gyr - b_ + sigma]

        b, (r_hat,) = rkmk4(f, b, [r_hat], (1.0,), dt)
        r_hat = newton_schulz(r_hat)
        r = magnus4(r, rate, t, dt)
        s1 = sample(r, (k + 1) * dt, noise_at(item, k + 1))
        return (r, r_hat, b, s1), r, {"r": r_hat}

    return _monte_carlo(init, step, n_steps, dt, window_start, record)


#: jaxatt study name -> builder.
STUDIES: Dict[str, Callable] = {
    "batista-ges": batista_ges,
    "batista-so3": batista_so3,
    "nlio-case1": nlio_case1,
    "complementary": complementary,
}
