"""jaxatt: fast, batched, differentiable attitude observers in JAX.

Front door (:mod:`jaxatt.api`): ``jaxatt.filter(name_or_observer, gyr, acc, mag, dt=...)`` on your own arrays,
``jaxatt.broad_score`` / ``jaxatt.fit`` on BROAD trials (``jaxatt.data.broad.load``), ``jaxatt.monte_carlo`` on a
simulated AHRS scenario; the papers' studies in :mod:`jaxatt.studies`; observers in :mod:`jaxatt.observers`
(registry: :mod:`jaxatt.observers.registry`).

Conventions: quaternions (w, x, y, z); R maps sensor/body to the navigation frame; SI units (rad/s, m/s^2, s);
frames named at every public function (the Batista papers simulate in NED, BROAD uses ENU; :mod:`jaxatt.frames`).
jaxatt never switches JAX's float64 mode: enable it with ``jax.config.update("jax_enable_x64", True)``.
"""

__version__ = "0.2.0"

from . import data, engine, frames, integrate, metrics, montecarlo, observers, sim, so3  # noqa: E402
from .api import BroadScore, Estimate, broad_score, filter, monte_carlo  # noqa: E402
from .fitting.fitter import FitResult, fit  # noqa: E402
from .types import ImuSample, Interval, Observer, VectorSample  # noqa: E402

__all__ = [
    "filter",
    "broad_score",
    "fit",
    "monte_carlo",
    "Estimate",
    "BroadScore",
    "FitResult",
    "ImuSample",
    "VectorSample",
    "Interval",
    "Observer",
    "data",
    "engine",
    "frames",
    "integrate",
    "metrics",
    "montecarlo",
    "observers",
    "sim",
    "so3",
    "__version__",
]
