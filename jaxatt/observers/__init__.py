"""Observers, one module per paper/filter; each exposes Params, State, Out, make_observer, default_params.

The modules are imported on first use (``jaxatt.observers.mahony.Params`` works after ``import jaxatt``)."""

import importlib

#: the observer modules and the registry
MODULES = (
    "batista_ges",
    "batista_so3",
    "complementary",
    "madgwick",
    "mahony",
    "mekf",
    "nlio",
    "registry",
    "robust_ahrs",
    "vqf",
)
__all__ = list(MODULES)


def __getattr__(name: str):
    if name in MODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(MODULES))
