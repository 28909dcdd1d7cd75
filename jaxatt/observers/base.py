"""The observer interface shared by every filter in jaxatt.

An observer is a NamedTuple of two pure functions (as optax's GradientTransformation):

* ``init(params, first_sample) -> State``: the state at the time of the first sample.
* ``step(params, state, sample, dt) -> (State, Out)``: advances the state from ``sample.t`` to
  ``sample.t + dt`` using the sample (or an :class:`jaxatt.integrate.Interval` of two samples), and returns
  the estimate at the end of the step; ``Out.t`` states the time the estimate refers to.

Gains live in a ``Params`` NamedTuple passed as an argument, never closed over, so ``jax.grad`` over gains,
``jax.vmap`` over a gain grid and ``jax.vmap`` over seeds need nothing more. Static choices (which reading of
a paper, which sensor field) are arguments of the factory that builds the observer.
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple, Optional

import jax

__all__ = ["Observer", "ImuSample"]


class ImuSample(NamedTuple):
    """One IMU sample. Absent sensors are None; a missing reading inside a log is NaN.

    Fields:
        t:   time (s).
        gyr: angular rate (rad/s), body frame, shape (3,).
        acc: specific force (m/s^2), body frame, shape (3,) or None.
        mag: magnetic field (unit of the scenario: nT, gauss or uT), body frame, shape (3,) or None.
    """

    t: jax.Array
    gyr: jax.Array
    acc: Optional[jax.Array] = None
    mag: Optional[jax.Array] = None


class Observer(NamedTuple):
    """A pair of pure functions ``init(params, sample) -> state`` and ``step(params, state, sample, dt)``."""

    init: Callable[[Any, Any], Any]
    step: Callable[[Any, Any, Any, Any], tuple]
    name: str = "observer"
