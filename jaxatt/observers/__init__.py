"""Observers, one module per paper/filter; each exposes Params, State, Out, make_observer, default_params."""
from . import batista_ges  # noqa: F401
from .base import ImuSample, Observer  # noqa: F401
