"""Angular-velocity profiles with exact omega(t), and the true attitude they generate.

A profile is any pytree with ``rate(t) -> omega`` (rad/s, body frame; the type :class:`RateProfile`);
:class:`SinusoidRates` covers the papers' profiles, :class:`FunctionRates` wraps a user function of t.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["RateProfile", "SinusoidRates", "FunctionRates", "batista_slow", "batista_aggressive"]


class RateProfile(Protocol):
    """An angular-velocity profile: any pytree with ``rate(t)``, the body angular velocity (rad/s) at ``t`` (s)."""

    def rate(self, t) -> Any: ...


class SinusoidRates(NamedTuple):
    """omega_i(t) = scale * amplitude_i * sin(2 pi t / period_i + phase_i) + offset_i (rad/s, body frame)."""

    amplitude: jax.Array  # (3,) rad/s
    period: jax.Array  # (3,) s
    phase: jax.Array  # (3,) rad
    offset: jax.Array  # (3,) rad/s
    scale: jax.Array  # () multiplies the whole profile (--rate-scale)

    def rate(self, t):
        """Body angular velocity (rad/s) at time ``t`` (s)."""
        t = jnp.asarray(t)[..., None]
        return self.scale * (self.amplitude * jnp.sin(2.0 * jnp.pi * t / self.period + self.phase) + self.offset)


@jax.tree_util.register_pytree_node_class
class FunctionRates:
    """A user-supplied ``fn(t) -> omega`` (rad/s, body frame, shape (3,)); ``fn`` must be traceable by JAX."""

    def __init__(self, fn: Callable[[jax.Array], jax.Array]):
        self.fn = fn

    def rate(self, t):
        return jnp.asarray(self.fn(t))

    def tree_flatten(self):
        return (), self.fn

    @classmethod
    def tree_unflatten(cls, fn, _):
        return cls(fn)


def _batista(amplitude_deg, scale: float = 1.0) -> SinusoidRates:
    return SinusoidRates(
        amplitude=jnp.asarray(np.deg2rad(amplitude_deg)),
        period=jnp.asarray([60.0, 180.0, 300.0]),
        phase=jnp.zeros(3),
        offset=jnp.zeros(3),
        scale=jnp.asarray(float(scale)),
    )


def batista_slow(scale: float = 1.0) -> SinusoidRates:
    """omega(t) of batista2019-ges Section IV (also batista2019-so3 Section 4): amplitudes [5, 1, -2] deg/s,
    periods [60, 180, 300] s."""
    return _batista([5.0, 1.0, -2.0], scale)


def batista_aggressive(scale: float = 1.0) -> SinusoidRates:
    """The 20x faster profile of batista2019-ges Section IV: amplitudes [100, 20, -40] deg/s."""
    return _batista([100.0, 20.0, -40.0], scale)
