"""Scenarios of Trumpf et al. (IEEE TAC 2012, "Analysis of non-linear attitude observers for time-varying
reference measurements"): vector measurements of possibly time-varying reference directions, as pure-JAX
generators of the true attitude and :class:`jaxatt.types.VectorSample` logs.

Frames: an abstract inertial frame {A} and the body frame {B}; R (body to inertial) follows dR/dt = R S(Omega)
(eq. 1) from R(0) = ``r0`` with the exact Omega(t) of the profile (4th-order Magnus steps). Measurements:

* complementary, eq. (2): a_i(t) = R(t)^T å_i(t) (body frame) of inertial references å_i(t);
* compatible, eq. (3): b_j(t) = R(t) b̊_j(t) (inertial frame) of body-fixed references b̊_j(t).

Scenario constructors (plain floats in, a :class:`VectorScenario` out; degrees in names ending ``_deg``):

* :func:`rotating_reference` (a) one inertial direction moving on a cone about z: persistently exciting.
* :func:`switching_reference` (a') one inertial direction switching between two directions (Section III's
  switching example; piecewise continuous).
* :func:`constant_reference` (b) one constant inertial direction: the rotation about it is unobservable.
* :func:`two_constant_references` (c) two constant non-collinear directions (the classical case).
* :func:`body_fixed_reference` (d) one constant body-fixed direction seen in the inertial frame (compatible)
  while the body rotates about other axes (end of Section III: observable iff ||∫ Omega x b̊|| > 0).

:data:`SCENARIOS` maps names to constructors; :func:`make_scenario` builds one by name (for the CLI).
:func:`simulate_vectors` returns ``(samples, truth_r)``. Noise only through an explicit PRNG key.

A :class:`VectorScenario` also provides the simulator interface of :mod:`jaxatt.montecarlo` (``n_channels``,
``truth_at``, ``propagate``, ``sample``), so ``montecarlo.simulate`` / ``monte_carlo`` / ``simulate_log`` run
the complementary observer on it fused with the simulation (``errors_fn=vector_errors`` reports the bias
error). Both paths share :meth:`VectorScenario.sample`; their noise streams differ (explicit key here,
the runner's per-run block stream there).
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import so3
from ..integrate import magnus4_step
from ..types import ArrayLike, VectorSample, shown
from .trajectories import RateProfile, SinusoidRates

__all__ = [
    "Directions",
    "VectorScenario",
    "VectorTruth",
    "vector_errors",
    "rotating_reference",
    "switching_reference",
    "constant_reference",
    "two_constant_references",
    "body_fixed_reference",
    "SCENARIOS",
    "make_scenario",
    "simulate_vectors",
    "body_rates",
    "constant_directions",
]


class Directions(NamedTuple):
    """n time-varying directions (a pytree of arrays):

        v_i(t) = exp(S(rate_i * t * axis_i)) base_i(t),
        base_i(t) = v_a_i if floor(t / half_period_i) is even else v_b_i,

    so a constant direction has rate 0 and half_period inf; a rotating one rate != 0 (rad/s) about the unit
    ``axis``; a switching one a finite ``half_period`` (s, time spent on each of v_a, v_b).
    Shapes: v_a, v_b, axis (n, 3); rate, half_period (n,).
    """

    v_a: ArrayLike
    v_b: ArrayLike
    axis: ArrayLike
    rate: ArrayLike
    half_period: ArrayLike

    @property
    def n(self) -> int:
        return self.v_a.shape[0]

    def at(self, t):
        """Directions at time ``t`` (s), (n, 3)."""
        t = jnp.asarray(t)
        even = jnp.mod(jnp.floor(t / self.half_period), 2.0) == 0.0  # t / inf = 0 -> always v_a
        base = jnp.where(even[:, None], self.v_a, self.v_b)
        rot = so3.exp((self.rate * t)[:, None] * self.axis)  # (n, 3, 3)
        return so3.mv(rot, base)


def _unit_rows(v) -> np.ndarray:
    v = np.asarray(v, float).reshape(-1, 3)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    if np.any(n == 0) or not np.all(np.isfinite(v)):
        raise ValueError(f"reference directions must be finite and non-zero, got {shown(v)}")
    return v / n


def constant_directions(v) -> Directions:
    """Constant directions (rows of ``v``, normalised); ``v`` of shape (n, 3) or (3,); (0, 3) for none."""
    v = np.asarray(v, float).reshape(-1, 3)
    v = _unit_rows(v) if v.shape[0] else v
    n = v.shape[0]
    return Directions(v, v, np.tile([0.0, 0.0, 1.0], (n, 1)), np.zeros(n), np.full(n, np.inf))


class VectorTruth(NamedTuple):
    """True quantities at one time: t (s), R (3, 3) body to inertial, Omega (3,) rad/s body, gyro bias (3,)."""

    t: jax.Array
    r: jax.Array
    omega: jax.Array
    gyro_bias: jax.Array


def vector_errors(truth: VectorTruth, out) -> dict:
    """``errors_fn`` for :func:`jaxatt.montecarlo.simulate`: the gyro-bias estimation error (rad/s, body)."""
    return {"bias": out.bias - truth.gyro_bias.astype(out.bias.dtype)}


class VectorScenario(NamedTuple):
    """A simulated platform for vector measurements (all arrays; a pytree).

    Fields:
        rates: angular-velocity profile with ``rate(t)`` (rad/s, body), e.g. :class:`SinusoidRates`.
        r0: true initial attitude (3, 3), body to inertial.
        ref_inertial: :class:`Directions` å_i(t) of the n1 complementary measurements (inertial frame).
        ref_body: :class:`Directions` b̊_j(t) of the n2 compatible measurements (body frame).
        gyro_bias: constant gyro bias (rad/s, body), (3,).
        gyro_noise_std: white gyro noise per sample (rad/s), ().
        meas_noise_std: white noise added to each measured vector per sample (unit vectors, so ~rad), ().
    """

    rates: RateProfile
    r0: ArrayLike
    ref_inertial: Directions
    ref_body: Directions
    gyro_bias: ArrayLike
    gyro_noise_std: ArrayLike
    meas_noise_std: ArrayLike

    @property
    def n_body(self) -> int:
        """n1, the number of complementary (body-frame) measurements."""
        return self.ref_inertial.n

    @property
    def n_inertial(self) -> int:
        """n2, the number of compatible (inertial-frame) measurements."""
        return self.ref_body.n

    # The simulator interface of jaxatt.montecarlo.
    @property
    def n_channels(self) -> int:
        """Standard-normal numbers drawn per sample: gyro (3), then 3 per measurement (a_i, then b_j)."""
        return 3 + 3 * (self.n_body + self.n_inertial)

    def truth_at(self, r, t) -> VectorTruth:
        """True quantities at time ``t`` (s) for the attitude ``r``."""
        return VectorTruth(t, r, self.rates.rate(t), self.gyro_bias)

    def propagate(self, r, t, dt):
        """True attitude at ``t + dt`` from ``r`` at ``t`` (4th-order Magnus step, exact Omega(t))."""
        return magnus4_step(r, self.rates.rate, t, dt)

    def sample(self, truth: VectorTruth, noise, dt) -> VectorSample:
        """Sample at ``truth.t`` from ``n_channels`` standard-normal numbers ``noise``: gyr = Omega + bias +
        gyro_noise_std n; a_i = R^T å_i + meas_noise_std n; b_j = R b̊_j + meas_noise_std n."""
        n1, n2 = self.n_body, self.n_inertial
        ar = self.ref_inertial.at(truth.t)
        br = self.ref_body.at(truth.t)
        rt = jnp.swapaxes(truth.r, -1, -2)
        gyr = truth.omega + self.gyro_bias + self.gyro_noise_std * noise[..., 0:3]
        a = so3.mv(rt, ar) + self.meas_noise_std * noise[..., 3 : 3 + 3 * n1].reshape(n1, 3)
        b = so3.mv(truth.r, br) + self.meas_noise_std * noise[..., 3 + 3 * n1 :].reshape(n2, 3)
        return VectorSample(truth.t, gyr, a, ar, b, br)


# ------------------------------------------------------------------------------------------------------
# Constructors (plain floats in)
# ------------------------------------------------------------------------------------------------------
def body_rates(
    amplitude_deg_s=(10.0, 6.0, 8.0),
    period_s=(20.0, 30.0, 45.0),
    offset_deg_s=(0.0, 0.0, 0.0),
    phase_deg=(0.0, 0.0, 0.0),
) -> SinusoidRates:
    """omega_i(t) = A_i sin(2 pi t / P_i + phase_i) + offset_i (body frame), amplitudes in deg/s."""
    return SinusoidRates(
        amplitude=jnp.asarray(np.deg2rad(np.asarray(amplitude_deg_s, float))),
        period=jnp.asarray(np.asarray(period_s, float)),
        phase=jnp.asarray(np.deg2rad(np.asarray(phase_deg, float))),
        offset=jnp.asarray(np.deg2rad(np.asarray(offset_deg_s, float))),
        scale=jnp.asarray(1.0),
    )


def _triple(x, name) -> np.ndarray:
    v = np.asarray(x, float)
    v = np.full(3, float(v)) if v.ndim == 0 else v
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be a finite scalar or 3-vector, got {x}")
    return v


def _scenario(
    ref_inertial: Directions,
    ref_body: Directions,
    rates,
    *,
    r0_euler_deg,
    gyro_bias_deg_s,
    gyro_noise_std,
    meas_noise_std,
    dtype,
) -> VectorScenario:
    if ref_inertial.n + ref_body.n < 1:
        raise ValueError("a scenario needs at least one measurement")
    for name, v in (("gyro_noise_std", gyro_noise_std), ("meas_noise_std", meas_noise_std)):
        if not (math.isfinite(float(v)) and float(v) >= 0):
            raise ValueError(f"{name} must be finite and non-negative, got {shown(v)}")
    e = np.deg2rad(_triple(r0_euler_deg, "r0_euler_deg"))
    r0 = np.asarray(so3.euler_zyx_to_matrix(e[0], e[1], e[2]))
    scn = VectorScenario(
        rates,
        r0,
        ref_inertial,
        ref_body,
        np.deg2rad(_triple(gyro_bias_deg_s, "gyro_bias_deg_s")),
        np.asarray(float(gyro_noise_std)),
        np.asarray(float(meas_noise_std)),
    )
    dtype = dtype or jnp.result_type(float)
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), scn)


_NONE = constant_directions(np.zeros((0, 3)))


def _common(kw):
    return dict(
        r0_euler_deg=kw.pop("r0_euler_deg", (20.0, -10.0, 30.0)),
        gyro_bias_deg_s=kw.pop("gyro_bias_deg_s", 0.0),
        gyro_noise_std=kw.pop("gyro_noise_std", 0.0),
        meas_noise_std=kw.pop("meas_noise_std", 0.0),
        dtype=kw.pop("dtype", None),
    )


_DOC_COMMON = """
    Common keywords: ``rates`` (a profile; default :func:`body_rates`), ``r0_euler_deg`` (roll, pitch, yaw of
    R(0), ZYX), ``gyro_bias_deg_s`` (scalar or 3-vector), ``gyro_noise_std`` (rad/s per sample),
    ``meas_noise_std`` (per component, on unit vectors), ``dtype``."""


def _add_doc_common(fn) -> None:
    if fn.__doc__:  # None under python -OO
        fn.__doc__ += _DOC_COMMON


def rotating_reference(rate_deg_s: float = 30.0, tilt_deg: float = 60.0, **kw) -> VectorScenario:
    """(a) One inertial direction on a cone of half-angle ``tilt_deg`` about the inertial z axis, turning at
    ``rate_deg_s``: å(t) = Rz(rate t) (sin tilt, 0, cos tilt). Persistently exciting for tilt in (0, 180)
    and rate != 0 (over a period, ∫ å å^T = P diag(sin²/2, sin²/2, cos²))."""
    c = _common(kw)
    rates = kw.pop("rates", None) or body_rates()
    _no_extra(kw)
    th = np.deg2rad(float(tilt_deg))
    d = Directions(
        np.array([[np.sin(th), 0.0, np.cos(th)]]),
        np.array([[np.sin(th), 0.0, np.cos(th)]]),
        np.array([[0.0, 0.0, 1.0]]),
        np.array([np.deg2rad(float(rate_deg_s))]),
        np.array([np.inf]),
    )
    return _scenario(d, _NONE, rates, **c)


_add_doc_common(rotating_reference)


def switching_reference(half_period_s: float = 5.0, angle_deg: float = 90.0, **kw) -> VectorScenario:
    """(a') One inertial direction switching every ``half_period_s`` between e3 and e3 rotated by
    ``angle_deg`` about e1 (Section III: "takes on two different values over two time periods")."""
    c = _common(kw)
    rates = kw.pop("rates", None) or body_rates()
    _no_extra(kw)
    if not float(half_period_s) > 0:
        raise ValueError(f"half_period_s must be positive, got {half_period_s}")
    a = np.deg2rad(float(angle_deg))
    d = Directions(
        np.array([[0.0, 0.0, 1.0]]),
        np.array([[0.0, -np.sin(a), np.cos(a)]]),
        np.array([[0.0, 0.0, 1.0]]),
        np.zeros(1),
        np.array([float(half_period_s)]),
    )
    return _scenario(d, _NONE, rates, **c)


_add_doc_common(switching_reference)


def constant_reference(direction=(0.0, 0.0, 1.0), **kw) -> VectorScenario:
    """(b) One constant inertial direction: not sufficiently exciting (λ2 = 0); the rotation about it is
    unobservable (Section III, [9], [10])."""
    c = _common(kw)
    rates = kw.pop("rates", None) or body_rates()
    _no_extra(kw)
    return _scenario(constant_directions(direction), _NONE, rates, **c)


_add_doc_common(constant_reference)


def two_constant_references(angle_deg: float = 60.0, **kw) -> VectorScenario:
    """(c) Two constant inertial directions e3 and e3 rotated by ``angle_deg`` about e2 (non-collinear for
    angle not 0 or 180: Definition 4.8, Lemma 4.9)."""
    c = _common(kw)
    rates = kw.pop("rates", None) or body_rates()
    _no_extra(kw)
    a = np.deg2rad(float(angle_deg))
    return _scenario(constant_directions([[0.0, 0.0, 1.0], [np.sin(a), 0.0, np.cos(a)]]), _NONE, rates, **c)


_add_doc_common(two_constant_references)


def body_fixed_reference(
    direction=(0.0, 0.0, 1.0), rate_deg_s: float = 20.0, wobble_deg_s: float = 5.0, **kw
) -> VectorScenario:
    """(d) One constant body-fixed direction b̊ (compatible measurement b = R b̊, e.g. a GPS baseline), the
    body turning at ``rate_deg_s`` about body x plus a sinusoidal wobble of amplitude ``wobble_deg_s`` on
    each axis. With b̊ = e3 the condition of the end of Section III, ||∫ Omega x b̊|| > 0, holds."""
    c = _common(kw)
    rates = kw.pop("rates", None) or body_rates(
        amplitude_deg_s=(wobble_deg_s,) * 3, offset_deg_s=(rate_deg_s, 0.0, 0.0)
    )
    _no_extra(kw)
    return _scenario(_NONE, constant_directions(direction), rates, **c)


_add_doc_common(body_fixed_reference)


def _no_extra(kw):
    if kw:
        raise ValueError(f"unknown scenario keyword(s): {sorted(kw)}")


#: Scenario constructors by name (for the CLI).
SCENARIOS = {
    "rotating": rotating_reference,
    "switching": switching_reference,
    "constant": constant_reference,
    "two_constant": two_constant_references,
    "body_fixed": body_fixed_reference,
}


def make_scenario(name: str, **kwargs) -> VectorScenario:
    """Build the scenario ``name`` (a key of :data:`SCENARIOS`) with its keyword arguments."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; choose one of {sorted(SCENARIOS)}")
    return SCENARIOS[name](**kwargs)


# ------------------------------------------------------------------------------------------------------
# Simulation
# ------------------------------------------------------------------------------------------------------
def simulate_vectors(scenario: VectorScenario, duration: float, dt: float, key: Optional[jax.Array] = None):
    """Samples at t_k = k dt, k = 0..N (N = round(duration / dt)), and the true attitudes there.

    Returns ``(samples, truth_r)``: a :class:`VectorSample` of stacked arrays (t (N+1,), gyr (N+1, 3),
    body_meas / ref_inertial (N+1, n1, 3), inertial_meas / ref_body (N+1, n2, 3)) and R(t_k) (N+1, 3, 3).
    gyr = Omega + gyro_bias + noise; a_i = R^T a_ref_i + noise; b_j = R b_ref_j + noise (not renormalised).
    ``key`` (a jax PRNG key, used as a run key of :func:`jaxatt.montecarlo.simulate_log`) is required when the
    scenario has noise; None gives a noise-free log.
    """
    from ..montecarlo import simulate_log

    noisy = float(scenario.gyro_noise_std) > 0 or float(scenario.meas_noise_std) > 0
    if noisy and key is None:
        raise ValueError("the scenario has noise: pass an explicit PRNG key (jax.random.PRNGKey(seed))")
    samples, truth = simulate_log(scenario, duration=duration, dt=dt, key=jax.random.PRNGKey(0) if key is None else key)
    return samples, truth.r
