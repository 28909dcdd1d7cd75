"""``jaxatt.parametrize`` of version 0.1 is :mod:`jaxatt.fitting.parametrize` since 0.2: this alias keeps 0.1
code running, with a DeprecationWarning naming the new place."""

import warnings

from .fitting.parametrize import *  # noqa: F401,F403
from .fitting.parametrize import __all__  # noqa: F401

warnings.warn(
    "jaxatt.parametrize is jaxatt.fitting.parametrize since 0.2: import from there",
    DeprecationWarning,
    stacklevel=2,
)
