"""jaxatt: fast, batched, differentiable attitude observers in JAX.

Front door (:mod:`jaxatt.api`): ``jaxatt.filter(name_or_observer, gyr, acc, mag, dt=...)`` on your own arrays,
``jaxatt.broad_score`` / ``jaxatt.fit`` on BROAD trials (``jaxatt.data.broad.load``), ``jaxatt.monte_carlo`` on a
simulated AHRS scenario; the papers' studies in :mod:`jaxatt.studies`; observers in :mod:`jaxatt.observers`
(registry: :mod:`jaxatt.observers.registry`). ``filter`` and ``broad_score`` take ``offline=True``: forward-backward
smoothing over the whole recording (:mod:`jaxatt.smoothing`).

Conventions: quaternions (w, x, y, z); R maps sensor/body to the navigation frame; SI units (rad/s, m/s^2, s);
frames named at every public function (the Batista papers simulate in NED, BROAD uses ENU; :mod:`jaxatt.frames`).
jaxatt never switches JAX's float64 mode: enable it with ``jax.config.update("jax_enable_x64", True)``.

The names below are imported on first use, so ``import jaxatt`` (and ``jaxatt --help``) does not import JAX.
"""

import importlib

__version__ = "0.2.0"

#: public name -> (module, attribute) imported on first use
_NAMES = {
    "filter": ("api", "filter"),
    "broad_score": ("api", "broad_score"),
    "fit": ("fitting.fitter", "fit"),
    "monte_carlo": ("api", "monte_carlo"),
    "ahrs_scenario": ("api", "ahrs_scenario"),
    "Estimate": ("api", "Estimate"),
    "BroadScore": ("api", "BroadScore"),
    "FitResult": ("fitting.fitter", "FitResult"),
    "ImuSample": ("types", "ImuSample"),
    "VectorSample": ("types", "VectorSample"),
    "Interval": ("types", "Interval"),
    "Observer": ("types", "Observer"),
}
_SUBMODULES = (
    "analysis",
    "api",
    "data",
    "engine",
    "fitting",
    "frames",
    "integrate",
    "io",
    "metrics",
    "montecarlo",
    "observers",
    "plot",
    "progress",
    "schedule",
    "sharding",
    "sim",
    "smoothing",
    "so3",
    "studies",
    "types",
)

__all__ = list(_NAMES) + list(_SUBMODULES) + ["__version__"]


def __getattr__(name):
    if name in _NAMES:
        module, attr = _NAMES[name]
        value = getattr(importlib.import_module(f"{__name__}.{module}"), attr)
    elif name in _SUBMODULES:
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module 'jaxatt' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
