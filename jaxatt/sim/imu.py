"""IMU sensor models and the fused truth + sensor step used by the simulator.

Sensors (body frame, the papers' models):

* gyro  = omega + R^T earth_rate_nav + bias + n_g,  n_g ~ N(0, sigma_g^2) per sample, with
  sigma_g = ARW * sqrt(fs): an angle random walk ARW (rad/s/sqrt(Hz)) sampled at fs = 1/dt
  (e.g. 4 deg/h/sqrt(Hz) at 100 Hz gives 1.94e-4 rad/s, batista2019-ges Section IV).
* vector sensor (magnetometer) = R^T ref_nav + n_m,  n_m ~ N(0, sigma_m^2), sigma_m in the unit of ref_nav.

Noise comes from explicit PRNG keys. The stream of one run depends only on its key: sample s >= 1 uses row
(s - 1) % NOISE_BLOCK of ``normal(fold_in(key, (s - 1) // NOISE_BLOCK), (NOISE_BLOCK, channels))`` and sample 0
uses ``fold_in(key, INIT_BLOCK)``. Generating whole blocks vectorises well; the block length is part of the
stream's definition, so runs do not depend on batch size or on how a run is chunked.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import so3
from ..integrate import magnus4_step
from ..types import ImuSample
from .trajectories import RateProfile

__all__ = [
    "ImuScenario",
    "Truth",
    "NOISE_BLOCK",
    "arw_deg_per_hour_to_rad",
    "sample_sensors",
    "noise_block",
    "initial_noise",
    "truth_at",
    "N_CHANNELS",
]

NOISE_BLOCK = 1000
INIT_BLOCK = 2**31 - 1
N_CHANNELS = 6  # gyro (3) + vector sensor (3)


def arw_deg_per_hour_to_rad(arw_deg_h_rthz: float) -> float:
    """Angle random walk in deg/h/sqrt(Hz) -> rad/s/sqrt(Hz)."""
    return float(np.deg2rad(arw_deg_h_rthz) / 3600.0)


class ImuScenario(NamedTuple):
    """A simulated platform: trajectory, environment and sensor errors (all arrays, a pytree).

    Fields:
        rates: angular-velocity profile with ``rate(t)`` (rad/s, body frame).
        r0: initial attitude, body to navigation frame (3, 3).
        earth_rate_nav: Earth rate in the navigation frame (rad/s), zeros for a gyro blind to it.
        ref_nav: reference vector of the vector sensor in the navigation frame (e.g. field in nT, NED).
        gyro_arw: gyro angle random walk (rad/s/sqrt(Hz)).
        gyro_bias: constant gyro bias (rad/s, body).
        vec_noise_std: white-noise standard deviation of the vector sensor (unit of ref_nav).
        noise_scale: multiplies every noise (0 = noise-free).
    """

    rates: RateProfile
    r0: jax.Array
    earth_rate_nav: jax.Array
    ref_nav: jax.Array
    gyro_arw: jax.Array
    gyro_bias: jax.Array
    vec_noise_std: jax.Array
    noise_scale: jax.Array

    # The simulator interface used by jaxatt.montecarlo (any scenario type providing these plugs in):
    @property
    def n_channels(self) -> int:
        """Standard-normal numbers drawn per sample: gyro (3), then the vector sensor (3)."""
        return N_CHANNELS

    def truth_at(self, r, t) -> "Truth":
        """True quantities at time ``t`` (s) for the attitude ``r`` (body to nav)."""
        return truth_at(self, r, t)

    def propagate(self, r, t, dt):
        """True attitude at ``t + dt`` from ``r`` at ``t``."""
        return propagate_truth(self, r, t, dt)

    def sample(self, truth: "Truth", noise, dt) -> ImuSample:
        """Sensor sample at ``truth.t`` from ``n_channels`` standard-normal numbers."""
        return sample_sensors(self, truth, noise, dt)


class Truth(NamedTuple):
    """True quantities at one time: t (s), R (body to nav), omega (rad/s, body), earth rate and reference
    vector in body coordinates."""

    t: jax.Array
    r: jax.Array
    omega: jax.Array
    earth_rate_body: jax.Array
    ref_body: jax.Array


def truth_at(scn: ImuScenario, r, t) -> Truth:
    rt = jnp.swapaxes(r, -1, -2)
    return Truth(t, r, scn.rates.rate(t), so3.mv(rt, scn.earth_rate_nav), so3.mv(rt, scn.ref_nav))


def noise_block(key, block_index, dtype, channels: int = N_CHANNELS) -> jax.Array:
    """Standard-normal noise rows for samples 1 + block_index * NOISE_BLOCK ... (NOISE_BLOCK, channels)."""
    return jax.random.normal(jax.random.fold_in(key, block_index), (NOISE_BLOCK, channels), dtype)


def initial_noise(key, dtype, channels: int = N_CHANNELS) -> jax.Array:
    """Standard-normal noise of sample 0, (channels,)."""
    return jax.random.normal(jax.random.fold_in(key, INIT_BLOCK), (channels,), dtype)


def sample_sensors(scn: ImuScenario, truth: Truth, noise, dt) -> ImuSample:
    """Gyro and vector-sensor sample at ``truth.t`` from standard-normal ``noise`` (N_CHANNELS,)."""
    sigma_g = scn.gyro_arw / jnp.sqrt(dt)
    gyr = truth.omega + truth.earth_rate_body + scn.gyro_bias + scn.noise_scale * sigma_g * noise[..., 0:3]
    vec = truth.ref_body + scn.noise_scale * scn.vec_noise_std * noise[..., 3:6]
    return ImuSample(t=truth.t, gyr=gyr, mag=vec)


def propagate_truth(scn: ImuScenario, r, t, dt):
    """True attitude at t + dt (4th-order Magnus step with the exact omega(t))."""
    return magnus4_step(r, scn.rates.rate, t, dt)
