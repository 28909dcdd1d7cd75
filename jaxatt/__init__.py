"""jaxatt: fast, batched, differentiable attitude observers in JAX.

Conventions: quaternions (w, x, y, z); R maps body to the reference frame; SI units (rad/s, s); frames
named at every public function (the Batista papers simulate in NED, BROAD uses ENU).
"""
from . import integrate, metrics, montecarlo, observers, sim, so3  # noqa: F401
from .montecarlo import monte_carlo, run, simulate  # noqa: F401
from .observers.base import ImuSample, Observer  # noqa: F401

__version__ = "0.1.0"
