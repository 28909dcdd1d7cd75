"""AHRS scenario: gyro + accelerometer + magnetometer, constant gyro bias, mixed-Gaussian noise and noise bursts
(the set-up of Section 5 of sensors2020-interconnected-observer-gyro-bias; usable by any observer).

Sensors (body frame; R maps body to NED):

* gyro  = omega + b + sigma_g * n_g                       (rad/s), eq. (3) with constant bias b (eq. 4)
* acc   = R^T acc_ref_nav + eta_1                          (m/s^2), eq. (5)-(6) with v_1^N = acc_ref_nav
* mag   = R^T mag_ref_nav + eta_2                          (unit of mag_ref_nav; gauss in the paper)

``sigma_g`` is the standard deviation of one gyro sample at the simulation rate (the paper's
eta_omega ~ N(0, (1e-3 rad/s)^2) at 100 Hz), not an angle random walk.

The accelerometer reference follows the paper: v_1^N = g^N = [0, 0, g] (NED, "down"), i.e. the accelerometer is
modelled as measuring R^T g^N. A physical accelerometer at rest measures the specific force -R^T g^N; an
observer only needs the reference that matches the sensor, so use ``acc_ref_nav = [0, 0, -g]`` for real data.

Vector-sensor noise, per axis and per sample: with probability ``1 - mix_prob`` N(0, sigma^2), otherwise
N(0, (mix_scale * sigma)^2) (the paper's 0.8 N(0, s^2) + 0.2 N(0, (10 s)^2) is mix_prob = 0.2, mix_scale = 10;
mix_prob = 0 gives plain Gaussian noise). Inside the burst window burst_start < t < burst_end every
vector-sensor standard deviation is multiplied by ``burst_scale`` (Case 3: 5x for 110 s < t < 190 s).

Reading ``mix="sum"`` (``mix_sum = 1``): the printed 0.8 N(0, s^2) + 0.2 N(0, (10 s)^2) taken as a weighted sum of
two independent Gaussian variables, (1 - p) s n_a + p k s n_b: Gaussian with std s sqrt((1 - p)^2 + p^2 k^2)
(2.154 s for p = 0.2, k = 10) instead of the mixture's sqrt(1 - p + p k^2) s = 4.56 s.

Noise channels per sample (standard normals from jaxatt.sim.imu's block stream): gyro (3), acc (3), mag (3),
acc selectors (3), mag selectors (3). A selector z picks the wide component when z < ndtri(mix_prob), an exact
Bernoulli(mix_prob) draw, so switching the mixture on or off leaves the other channels' numbers unchanged.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import ndtri

from .. import so3
from ..integrate import magnus4_step
from ..types import ImuSample, shown
from .trajectories import RateProfile, SinusoidRates

__all__ = [
    "AhrsScenario",
    "AhrsTruth",
    "N_CHANNELS",
    "PAPER_GRAVITY",
    "PAPER_MAG_NED_G",
    "PAPER_GYRO_BIAS",
    "nlio_rates",
    "random_euler_rotation",
    "mixed_noise_variance",
    "MIX_MODES",
]

MIX_MODES = ("mixture", "sum")

N_CHANNELS = 15
#: g of Section 5 (m/s^2).
PAPER_GRAVITY = 9.81
#: mag_N of Section 5 (gauss, NED).
PAPER_MAG_NED_G = (0.3128, 0.0, 0.4282)
#: b_omega of Section 5 (rad/s).
PAPER_GYRO_BIAS = (-0.017, -0.017, 0.017)


def nlio_rates(scale: float = 1.0) -> SinusoidRates:
    """omega(t) = [0.1 sin(pi t/12), -0.2 cos(pi t/10), 0.1 sin(pi t/12)] rad/s (Section 5)."""
    return SinusoidRates(
        amplitude=jnp.asarray([0.1, -0.2, 0.1]),
        period=jnp.asarray([24.0, 20.0, 24.0]),
        phase=jnp.asarray([0.0, 0.5 * np.pi, 0.0]),  # -0.2 sin(x + pi/2) = -0.2 cos(x)
        offset=jnp.zeros(3),
        scale=jnp.asarray(float(scale)),
    )


def random_euler_rotation(key, low: float = -np.pi, high: float = np.pi, dtype=None) -> jax.Array:
    """Rotation (body to NED) with ZYX roll, pitch, yaw each uniform in [low, high] (rad), drawn from ``key``.

    Section 5's "initial attitude chosen randomly from a uniform distribution [-pi, pi]" (all three angles; a
    pitch outside [-pi/2, pi/2] is still a valid rotation, so the three draws are used as they come)."""
    dtype = dtype or jnp.result_type(float)
    e = jax.random.uniform(key, (3,), dtype, low, high)
    return so3.euler_zyx_to_matrix(e[0], e[1], e[2])


def mixed_noise_variance(sigma, mix_prob, mix_scale, mix: str = "mixture"):
    """Variance of (1 - p) N(0, s^2) + p N(0, (k s)^2): the mixture's s^2 (1 - p + p k^2) (20.8 s^2 in Case 2), or,
    for ``mix="sum"``, the weighted sum's s^2 ((1 - p)^2 + p^2 k^2) (4.64 s^2)."""
    if mix == "sum":
        return sigma**2 * ((1.0 - mix_prob) ** 2 + (mix_prob * mix_scale) ** 2)
    return sigma**2 * (1.0 - mix_prob + mix_prob * mix_scale**2)


class AhrsTruth(NamedTuple):
    """True quantities at one time: t (s), R (body to NED), omega (rad/s, body), the noise-free accelerometer
    and magnetometer vectors R^T v^N (body), and the gyro bias (rad/s)."""

    t: jax.Array
    r: jax.Array
    omega: jax.Array
    acc: jax.Array
    mag: jax.Array
    gyro_bias: jax.Array


class AhrsScenario(NamedTuple):
    """An AHRS platform (a pytree of arrays; plugs into jaxatt.montecarlo).

    Fields:
        rates: angular-velocity profile with ``rate(t)`` (rad/s, body), e.g. :func:`nlio_rates`.
        r0: true initial attitude, body to NED (3, 3).
        acc_ref_nav: v_1^N (m/s^2, NED); the paper's g^N = [0, 0, 9.81].
        mag_ref_nav: v_2^N (gauss in the paper, NED).
        gyro_bias: constant gyro bias (rad/s, body).
        gyro_noise_std: std of one gyro sample (rad/s).
        acc_noise_std, mag_noise_std: std sigma of the narrow noise component (m/s^2; unit of mag_ref_nav).
        mix_prob: probability of the wide component (0 = Gaussian).
        mix_scale: std ratio wide / narrow.
        mix_sum: 0 = mixture (default), 1 = weighted sum of the two Gaussians (see module docstring).
        burst_start, burst_end, burst_scale: vector-sensor stds x burst_scale for burst_start < t < burst_end.
        noise_scale: multiplies every noise (0 = noise-free).
    """

    rates: RateProfile
    r0: jax.Array
    acc_ref_nav: jax.Array
    mag_ref_nav: jax.Array
    gyro_bias: jax.Array
    gyro_noise_std: jax.Array
    acc_noise_std: jax.Array
    mag_noise_std: jax.Array
    mix_prob: jax.Array
    mix_scale: jax.Array
    mix_sum: jax.Array
    burst_start: jax.Array
    burst_end: jax.Array
    burst_scale: jax.Array
    noise_scale: jax.Array

    @property
    def n_channels(self) -> int:
        """Standard-normal numbers drawn per sample (simulator interface): :data:`N_CHANNELS`."""
        return N_CHANNELS

    @classmethod
    def make(
        cls,
        *,
        rates=None,
        r0=None,
        gravity: float = PAPER_GRAVITY,
        acc_ref_nav=None,
        mag_ref_nav=PAPER_MAG_NED_G,
        gyro_bias=PAPER_GYRO_BIAS,
        gyro_noise_std: float = 1e-3,
        acc_noise_std: float = 5e-3 * PAPER_GRAVITY,
        mag_noise_std: float = 8e-3,
        mix_prob: float = 0.0,
        mix_scale: float = 10.0,
        mix: str = "mixture",
        burst=None,
        noise_scale: float = 1.0,
        dtype=None,
    ) -> "AhrsScenario":
        """Build a scenario with Section 5's defaults (Case 1 noise); ``burst=(start, end, scale)`` or None;
        ``mix`` = "mixture" or "sum" (reading of the mixed-Gaussian noise).

        Raises ValueError on non-finite or negative settings."""
        dtype = dtype or jnp.result_type(float)

        def numbers(name, v):
            try:
                return np.asarray(v, float)
            except (TypeError, ValueError):
                raise ValueError(f"{name} must be numbers, got {v!r}") from None

        acc_ref = np.array([0.0, 0.0, gravity]) if acc_ref_nav is None else numbers("acc_ref_nav", acc_ref_nav)
        mag_ref_nav = numbers("mag_ref_nav", mag_ref_nav)
        b0, b1, bs = (0.0, 0.0, 1.0) if burst is None else tuple(numbers("burst", burst).reshape(-1))
        r0 = np.eye(3) if r0 is None else numbers("r0", r0)
        for name, v, shape in (
            ("acc_ref_nav", acc_ref, (3,)),
            ("mag_ref_nav", mag_ref_nav, (3,)),
            ("gyro_bias", numbers("gyro_bias", gyro_bias), (3,)),
            ("r0", r0, (3, 3)),
        ):
            if v.shape != shape or not np.all(np.isfinite(v)):
                raise ValueError(f"{name} must be a finite array of shape {shape}, got {shown(v)}")
        if np.linalg.norm(np.cross(acc_ref, np.asarray(mag_ref_nav, float))) <= 1e-9 * (
            np.linalg.norm(acc_ref) * np.linalg.norm(np.asarray(mag_ref_nav, float))
        ):
            raise ValueError("acc_ref_nav and mag_ref_nav must be non-zero and not parallel (Assumption 1)")
        for name, v in (
            ("gyro_noise_std", gyro_noise_std),
            ("acc_noise_std", acc_noise_std),
            ("mag_noise_std", mag_noise_std),
            ("mix_scale", mix_scale),
            ("burst scale", bs),
            ("noise_scale", noise_scale),
        ):
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {shown(v)}")
        if mix not in MIX_MODES:
            raise ValueError(f"mix must be one of {MIX_MODES}, got {mix!r}")
        if not 0.0 <= mix_prob <= 1.0:
            raise ValueError(f"mix_prob must be in [0, 1], got {mix_prob}")
        if not (np.isfinite(b0) and np.isfinite(b1)) or b1 < b0:
            raise ValueError(f"burst must be (start, end, scale) with start <= end, got {burst}")
        a = lambda x: jnp.asarray(x, dtype)  # noqa: E731
        return cls(
            rates=rates if rates is not None else nlio_rates(),
            r0=a(r0),
            acc_ref_nav=a(acc_ref),
            mag_ref_nav=a(mag_ref_nav),
            gyro_bias=a(gyro_bias),
            gyro_noise_std=a(gyro_noise_std),
            acc_noise_std=a(acc_noise_std),
            mag_noise_std=a(mag_noise_std),
            mix_prob=a(mix_prob),
            mix_scale=a(mix_scale),
            mix_sum=a(1.0 if mix == "sum" else 0.0),
            burst_start=a(b0),
            burst_end=a(b1),
            burst_scale=a(bs),
            noise_scale=a(noise_scale),
        )

    # ----------------------------------------------------------------------------------------------------
    # Simulator interface (jaxatt.montecarlo)
    # ----------------------------------------------------------------------------------------------------
    def truth_at(self, r, t) -> AhrsTruth:
        """True quantities at time ``t`` (s) for the attitude ``r`` (body to NED)."""
        rt = jnp.swapaxes(r, -1, -2)
        return AhrsTruth(
            t,
            r,
            self.rates.rate(t),
            so3.mv(rt, self.acc_ref_nav),
            so3.mv(rt, self.mag_ref_nav),
            jnp.broadcast_to(self.gyro_bias, jnp.shape(r)[:-2] + (3,)),
        )

    def propagate(self, r, t, dt):
        """True attitude at ``t + dt`` from ``r`` at ``t`` (4th-order Magnus step with the exact omega(t))."""
        return magnus4_step(r, self.rates.rate, t, dt)

    def vector_noise_std(self, t):
        """(acc std, mag std) of the narrow component at time ``t``, burst included."""
        in_burst = (t > self.burst_start) & (t < self.burst_end)
        k = jnp.where(in_burst, self.burst_scale, 1.0)
        return k * self.acc_noise_std, k * self.mag_noise_std

    def sample(self, truth: AhrsTruth, noise, dt) -> ImuSample:
        """Sensor sample at ``truth.t`` from ``N_CHANNELS`` standard-normal numbers."""
        del dt  # noise stds are per sample
        s_acc, s_mag = self.vector_noise_std(truth.t)
        thresh = ndtri(self.mix_prob)  # z < ndtri(p) has probability p (-inf for p = 0)
        p, k = self.mix_prob, self.mix_scale

        def vec_noise(n, z):
            mixture = jnp.where(z < thresh, k, 1.0) * n
            weighted_sum = (1.0 - p) * n + p * k * z
            return jnp.where(self.mix_sum > 0, weighted_sum, mixture)

        ns = self.noise_scale
        gyr = truth.omega + truth.gyro_bias + ns * self.gyro_noise_std * noise[..., 0:3]
        acc = truth.acc + ns * s_acc[..., None] * vec_noise(noise[..., 3:6], noise[..., 9:12])
        mag = truth.mag + ns * s_mag[..., None] * vec_noise(noise[..., 6:9], noise[..., 12:15])
        return ImuSample(t=truth.t, gyr=gyr, acc=acc, mag=mag)
