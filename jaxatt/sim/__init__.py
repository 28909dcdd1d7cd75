"""Simulation: trajectories with exact omega(t), Earth models and IMU sensor models."""

from . import earth, imu, trajectories  # noqa: F401
from .earth import EARTH_RATE, earth_rate_ned, ned_to_enu  # noqa: F401
from .imu import ImuScenario, Truth, arw_deg_per_hour_to_rad  # noqa: F401
from .trajectories import FunctionRates, SinusoidRates, batista_aggressive, batista_slow  # noqa: F401
