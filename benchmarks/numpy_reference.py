"""Plain-numpy reference of the GES cascade observer of Batista, Silvestre and Oliveira (Asian J. Control 2019,
../shared/papers/batista2019-ges-attitude-earth-velocity.txt), for one run, plus a plain-numpy truth and sensor
simulator of Section IV.

Written from the paper, not from jaxatt's code; it follows the readings that jaxatt.observers.batista_ges
documents where the paper is open, so that both must agree to rounding error:

* the attitude injection of eq. (21), C2^T Q^-1 (y^ - C2 z2^), is taken as G (C2^-1 y^ - z2^) with the z-space
  gain G = C2^T Q^-1 C2 (``params.gain_z``); C2 is built element by element as printed in the paper (9 x 9) and
  inverted explicitly;
* x1^(0) is the first vector sample ("first_sample", default) or ``params.x1_0`` ("params");
* the sample at t_k is held (zero-order hold) over the RK4 step [t_k, t_k + dt]; x1^, x2^ and z2^ are one
  ODE of dimension 15 (the cascade integrated together, omega_E^ of eq. 17 evaluated at every RK4 stage);
* the Table-1 gains are those of the interval containing t_k;
* Theorem 3: R_f = projection of R^ on SO(3) when ||R^T R^ - I||_F <= eps and det(R^) > 0 (checked on R^ at
  the end of the step), else R_f <- R_f exp(dt S(gyr - (omega_E^(t_k) + omega_E^(t_k+1)) / 2));
  R_f(t_0) = nearest rotation to R^(0);
* NaN samples: a gyro sample with any NaN is replaced by the last valid one (initially the finite components
  of the first sample, zeros elsewhere); a vector sample with any NaN is replaced by x1^(t_k).

Everything is float64 numpy; nothing imports jax. Vectors are (3,), the attitude estimate z2^ is a 9-vector
of the rows of R^ (paper's z2), rotation matrices map body to inertial.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Dict, NamedTuple, Optional

import numpy as np

__all__ = [
    "NpParams",
    "NpState",
    "coefficients",
    "c2_matrix",
    "skew",
    "so3_exp",
    "project_so3",
    "make_reference",
    "run_numpy",
    "cross",
    "batista_rates",
    "simulate_numpy",
    "simulate_and_observe",
]


# ----------------------------------------------------------------------------------------------------------
# Small SO(3) helpers
# ----------------------------------------------------------------------------------------------------------
def cross(a, b) -> np.ndarray:
    """a x b for 3-vectors (np.cross is slow on tiny vectors)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def skew(v) -> np.ndarray:
    """S(v) with S(v) y = v x y."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def so3_exp(phi) -> np.ndarray:
    """exp(S(phi)) by Rodrigues' formula (Taylor series for tiny angles)."""
    phi = np.asarray(phi, float)
    th2 = float(phi @ phi)
    s = skew(phi)
    if th2 < 1e-14:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = math.sqrt(th2)
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    return np.eye(3) + a * s + b * (s @ s)


def project_so3(m) -> np.ndarray:
    """argmin_{X in SO(3)} ||X - m||_F = U diag(1, 1, det(U V^T)) V^T."""
    u, _, vt = np.linalg.svd(np.asarray(m, float))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


# ----------------------------------------------------------------------------------------------------------
# Constants of the observer
# ----------------------------------------------------------------------------------------------------------
class NpParams(NamedTuple):
    """The fields of jaxatt's ``batista_ges.Params``, as float64 numpy arrays."""

    ref_nav: np.ndarray
    earth_rate_nav: np.ndarray
    switch_times: np.ndarray
    alpha1: np.ndarray
    alpha2: np.ndarray
    gain_z: np.ndarray
    epsilon: float
    x1_0: np.ndarray
    x2_0: np.ndarray
    r_hat_0: np.ndarray

    @classmethod
    def from_any(cls, p: Any) -> "NpParams":
        """From any object with the same field names (e.g. jaxatt's Params of jax arrays)."""
        get = lambda name: np.array(getattr(p, name), dtype=np.float64)  # noqa: E731
        return cls(
            get("ref_nav"),
            get("earth_rate_nav"),
            np.atleast_1d(get("switch_times")),
            get("alpha1"),
            get("alpha2"),
            get("gain_z"),
            float(get("epsilon")),
            get("x1_0"),
            get("x2_0"),
            get("r_hat_0").reshape(3, 3),
        )


def coefficients(ref_nav, earth_rate_nav) -> Dict[str, float]:
    """A21, A22 (eq. 13) and We1, We2 (eq. 17), with the norms exactly as printed in the paper."""
    m = np.asarray(ref_nav, float)
    w = np.asarray(earth_rate_nav, float)
    mm, ww, mw = m @ m, w @ w, m @ w
    n_mxw2 = float(np.sum(np.cross(m, w) ** 2))  # ||I_m x I_wE||^2
    n_mxmxw2 = float(np.sum(np.cross(m, np.cross(m, w)) ** 2))  # ||I_m x (I_m x I_wE)||^2
    n_mxwxm2 = float(np.sum(np.cross(m, np.cross(w, m)) ** 2))  # ||I_m x (I_wE x I_m)||^2 (same number)
    return {
        "a21": (ww * mm - mw**2) / mm,
        "a22": mw * n_mxw2 / n_mxmxw2,
        "we1": mw / mm,
        "we2": (mw**2 - mm * ww) / n_mxwxm2,
    }


def c2_matrix(ref_nav, earth_rate_nav) -> np.ndarray:
    """C2 of eq. (21), built entry by entry: row 3(i-1)+k, column 3(j-1)+k holds I_x{ij}, k = 1, 2, 3."""
    m = np.asarray(ref_nav, float)
    w = np.asarray(earth_rate_nav, float)
    ix = np.array([m, np.cross(m, w), np.cross(m, np.cross(m, w))])  # ix[i-1, j-1] = I_x{ij}
    c2 = np.zeros((9, 9))
    for i in range(3):
        for j in range(3):
            for k in range(3):
                c2[3 * i + k, 3 * j + k] = ix[i, j]
    return c2


# ----------------------------------------------------------------------------------------------------------
# The observer
# ----------------------------------------------------------------------------------------------------------
class NpState(NamedTuple):
    t: float
    x1: np.ndarray  # (3,)
    x2: np.ndarray  # (3,)
    z2: np.ndarray  # (9,) rows of R^
    r_f: np.ndarray  # (3, 3) in SO(3)
    gyr_last: np.ndarray  # (3,)


class Reference(NamedTuple):
    init: Callable[[float, np.ndarray, np.ndarray], NpState]
    step: Callable[[NpState, float, np.ndarray, np.ndarray, float], tuple]


def make_reference(params: Any, x1_init: str = "first_sample") -> Reference:
    """Build ``init(t0, gyr0, mag0) -> state`` and ``step(state, t_k, gyr_k, mag_k, dt) -> (state, out)``.

    ``out`` is a dict with t (= t_k + dt), x1, x2, earth_rate (omega_E^ at t_k + dt), r_hat (3x3), r (R_f) and
    projected (bool), the fields of jaxatt's ``batista_ges.Out``.
    """
    if x1_init not in ("first_sample", "params"):
        raise ValueError(f"x1_init must be 'first_sample' or 'params', got {x1_init!r}")
    p = NpParams.from_any(params)
    k = coefficients(p.ref_nav, p.earth_rate_nav)
    a21, a22, we1, we2 = k["a21"], k["a22"], k["we1"], k["we2"]
    c2 = c2_matrix(p.ref_nav, p.earth_rate_nav)
    c2_inv = np.linalg.inv(c2)
    g = p.gain_z  # C2^T Q^-1 C2

    def earth_rate(x1, x2):  # eq. (17)
        return we1 * x1 + we2 * cross(x1, x2)

    def f(x, gyr, m, alpha1, alpha2):
        x1, x2, z2 = x[0:3], x[3:6], x[6:15]
        dx1 = -skew(gyr) @ x1 - x2 + alpha1 * (m - x1)  # eq. (15)
        dx2 = a21 * m - skew(gyr - a22 * m) @ x2 - alpha2 * (m - x1)
        y_hat = np.concatenate([x1, x2, cross(x1, x2)])
        s = skew(gyr - earth_rate(x1, x2))
        s3 = np.zeros((9, 9))  # S3(.) = diag(S, S, S)
        s3[0:3, 0:3] = s3[3:6, 3:6] = s3[6:9, 6:9] = s
        dz2 = -s3 @ z2 + g @ (c2_inv @ y_hat - z2)  # eq. (21) with C2^T Q^-1 (y - C2 z) = G (C2^-1 y - z)
        return np.concatenate([dx1, dx2, dz2])

    def gains(t):
        i = int(np.sum(t >= p.switch_times))
        return p.alpha1[i], p.alpha2[i]

    def init(t0, gyr0, mag0) -> NpState:
        gyr0 = np.asarray(gyr0, float)
        mag0 = np.asarray(mag0, float)
        if x1_init == "first_sample" and np.all(np.isfinite(mag0)):
            x1 = mag0.copy()
        else:
            x1 = p.x1_0.copy()
        return NpState(
            float(t0),
            x1,
            p.x2_0.copy(),
            p.r_hat_0.reshape(9).copy(),
            project_so3(p.r_hat_0),
            np.where(np.isfinite(gyr0), gyr0, 0.0),
        )

    def step(s: NpState, t_k, gyr, mag, dt):
        gyr = np.asarray(gyr, float)
        mag = np.asarray(mag, float)
        if not np.all(np.isfinite(gyr)):
            gyr = s.gyr_last
        if not np.all(np.isfinite(mag)):
            mag = s.x1
        alpha1, alpha2 = gains(t_k)
        x = np.concatenate([s.x1, s.x2, s.z2])
        k1 = f(x, gyr, mag, alpha1, alpha2)
        k2 = f(x + 0.5 * dt * k1, gyr, mag, alpha1, alpha2)
        k3 = f(x + 0.5 * dt * k2, gyr, mag, alpha1, alpha2)
        k4 = f(x + dt * k3, gyr, mag, alpha1, alpha2)
        x = x + dt * (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0
        x1, x2, z2 = x[0:3], x[3:6], x[6:15]
        r_hat = z2.reshape(3, 3)
        w_start, w_end = earth_rate(s.x1, s.x2), earth_rate(x1, x2)
        close = bool(np.linalg.norm(r_hat.T @ r_hat - np.eye(3), "fro") <= p.epsilon and np.linalg.det(r_hat) > 0)
        if close:
            r_f = project_so3(r_hat)
        else:
            r_f = s.r_f @ so3_exp(dt * (gyr - 0.5 * (w_start + w_end)))
        t1 = t_k + dt
        out = {"t": t1, "x1": x1, "x2": x2, "earth_rate": w_end, "r_hat": r_hat, "r": r_f, "projected": close}
        return NpState(t1, x1, x2, z2, r_f, gyr), out

    return Reference(init, step)


def run_numpy(samples: Any, params: Any, dt: Optional[float] = None, x1_init: str = "first_sample"):
    """Run the reference over a log; outputs stacked at t_1 ... t_{T-1} (as ``jaxatt.montecarlo.run``).

    samples: anything with ``t`` (T,), ``gyr`` (T, 3) and ``mag`` (T, 3) (e.g. jaxatt's ImuSample).
    dt: constant step (s), or None for dt_k = t_{k+1} - t_k.
    """
    t = np.asarray(samples.t, float)
    gyr = np.asarray(samples.gyr, float)
    mag = np.asarray(samples.mag, float)
    dts = np.diff(t) if dt is None else np.full(len(t) - 1, float(dt))
    ref = make_reference(params, x1_init)
    s = ref.init(t[0], gyr[0], mag[0])
    outs = []
    for k in range(len(t) - 1):
        s, out = ref.step(s, t[k], gyr[k], mag[k], dts[k])
        outs.append(out)
    return {key: np.array([o[key] for o in outs]) for key in outs[0]}


# ----------------------------------------------------------------------------------------------------------
# Truth and sensors of Section IV
# ----------------------------------------------------------------------------------------------------------
def batista_rates(amplitude_deg=(5.0, 1.0, -2.0), periods=(60.0, 180.0, 300.0)) -> Callable[[float], np.ndarray]:
    """omega(t) of Section IV: amplitude_i (deg/s) sin(2 pi t / period_i), rad/s (slow profile by default;
    (100, 20, -40) is the aggressive one)."""
    amp = np.deg2rad(np.asarray(amplitude_deg, float))
    per = np.asarray(periods, float)
    return lambda t: amp * np.sin(2.0 * np.pi * t / per)


def _magnus4(r, rate, t, dt):
    """One 4th-order Magnus step of dR/dt = R S(omega(t)) (Gauss-Legendre nodes)."""
    c = math.sqrt(3.0) / 6.0
    w1, w2 = rate(t + (0.5 - c) * dt), rate(t + (0.5 + c) * dt)
    return r @ so3_exp(0.5 * dt * (w1 + w2) + (math.sqrt(3.0) / 12.0) * dt * dt * cross(w1, w2))


class _Sensors(NamedTuple):
    rate: Callable[[float], np.ndarray]
    ref_nav: np.ndarray
    earth_rate_nav: np.ndarray
    sigma_g: float
    sigma_m: float
    gyro_bias: np.ndarray


def _sample(sn: _Sensors, r, t, noise6):
    gyr = sn.rate(t) + r.T @ sn.earth_rate_nav + sn.gyro_bias + sn.sigma_g * noise6[0:3]
    mag = r.T @ sn.ref_nav + sn.sigma_m * noise6[3:6]
    return gyr, mag


def _sensors(rate, ref_nav, earth_rate_nav, gyro_arw, mag_noise, dt, gyro_bias):
    return _Sensors(
        rate,
        np.asarray(ref_nav, float),
        np.asarray(earth_rate_nav, float),
        float(gyro_arw) / math.sqrt(dt),
        float(mag_noise),
        np.zeros(3) if gyro_bias is None else np.asarray(gyro_bias, float),
    )


def simulate_numpy(
    n_steps: int,
    dt: float,
    *,
    rate,
    ref_nav,
    earth_rate_nav,
    gyro_arw: float,
    mag_noise: float,
    r0=None,
    gyro_bias=None,
    noise: Optional[np.ndarray] = None,
    rng=None,
):
    """Truth and samples at t_k = k dt, k = 0 ... n_steps.

    gyro = omega + R^T I_wE + bias + (gyro_arw / sqrt(dt)) n_g; vector = R^T I_m + mag_noise n_m. ``noise`` is
    (n_steps + 1, 6) standard normal (gyro, vector), drawn from ``rng`` (np.random.Generator) when None.
    Returns (t, gyr, mag, r_true) with shapes (T,), (T, 3), (T, 3), (T, 3, 3).
    """
    sn = _sensors(rate, ref_nav, earth_rate_nav, gyro_arw, mag_noise, dt, gyro_bias)
    if noise is None:
        rng = np.random.default_rng(0) if rng is None else rng
        noise = rng.standard_normal((n_steps + 1, 6))
    r = np.eye(3) if r0 is None else np.asarray(r0, float)
    t = np.arange(n_steps + 1) * dt
    gyr, mag, rs = np.empty((n_steps + 1, 3)), np.empty((n_steps + 1, 3)), np.empty((n_steps + 1, 3, 3))
    for k in range(n_steps + 1):
        if k:
            r = _magnus4(r, sn.rate, t[k - 1], dt)
        rs[k] = r
        gyr[k], mag[k] = _sample(sn, r, t[k], noise[k])
    return t, gyr, mag, rs


def simulate_and_observe(
    n_steps: int,
    dt: float,
    params: Any,
    *,
    rate,
    ref_nav,
    earth_rate_nav,
    gyro_arw: float,
    mag_noise: float,
    r0=None,
    gyro_bias=None,
    rng=None,
    x1_init: str = "first_sample",
    record: bool = False,
):
    """Truth, sensors and observer fused in one loop (the numpy counterpart of jaxatt's fused Monte Carlo).

    Noise is drawn per step from ``rng``. Returns the final observer state, the final true attitude and, with
    ``record``, a list of (t, r_true, out) per step.
    """
    sn = _sensors(rate, ref_nav, earth_rate_nav, gyro_arw, mag_noise, dt, gyro_bias)
    rng = np.random.default_rng(0) if rng is None else rng
    ref = make_reference(params, x1_init)
    r = np.eye(3) if r0 is None else np.asarray(r0, float)
    gyr, mag = _sample(sn, r, 0.0, rng.standard_normal(6))
    s = ref.init(0.0, gyr, mag)
    rec = [] if record else None
    for k in range(n_steps):
        t_k = k * dt
        r = _magnus4(r, sn.rate, t_k, dt)
        s, out = ref.step(s, t_k, gyr, mag, dt)  # the sample at t_k, held over the step
        gyr, mag = _sample(sn, r, (k + 1) * dt, rng.standard_normal(6))
        if record:
            rec.append(((k + 1) * dt, r, out))
    return s, r, rec
