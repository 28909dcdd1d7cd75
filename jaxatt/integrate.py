"""Integrators shared by every continuous-time observer and by the simulator.

Observers are continuous-time ODEs driven by sampled sensor inputs. A step from t_k to t_k + dt needs the
input at the RK4 stage times t_k, t_k + dt/2, t_k + dt. Two readings exist (the papers do not say which they
used, see ../shared/papers/NOTES.md):

* ``hold="zoh"`` (default): the sample taken at t_k is held over the step. Causal; what a real-time
  implementation does.
* ``hold="linear"``: the input is interpolated linearly between the samples at t_k and t_k + dt, so stage
  inputs are (u_k, (u_k + u_k+1)/2, u_k+1). Needs one sample of look-ahead (offline processing).

A step receives a :class:`Interval` (start and end samples) in the linear mode and a plain sample otherwise;
:func:`input_at` hides the difference from the observer.
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from . import so3

__all__ = ["Interval", "input_at", "rk4_step", "lie_rk4_step", "magnus4_step"]


class Interval(NamedTuple):
    """Samples at both ends of a step, for linear interpolation of the input over the step."""

    start: Any
    end: Any


def input_at(u: Any, frac: float) -> Any:
    """The input at fraction ``frac`` in [0, 1] of the step: held sample, or linear interpolation."""
    if isinstance(u, Interval):
        if frac == 0.0:
            return u.start
        if frac == 1.0:
            return u.end
        return jax.tree_util.tree_map(lambda a, b: a + frac * (b - a), u.start, u.end)
    return u


def _axpy(a, x, y):
    return jax.tree_util.tree_map(lambda xi, yi: yi + a * xi, x, y)


def rk4_step(f: Callable[[Any, Any], Any], x: Any, u: Any, dt) -> Any:
    """Classical RK4 for dx/dt = f(x, u(t)) over one step of length ``dt`` (x any pytree of arrays)."""
    k1 = f(x, input_at(u, 0.0))
    k2 = f(_axpy(0.5 * dt, k1, x), input_at(u, 0.5))
    k3 = f(_axpy(0.5 * dt, k2, x), input_at(u, 0.5))
    k4 = f(_axpy(dt, k3, x), input_at(u, 1.0))
    incr = jax.tree_util.tree_map(lambda a, b, c, d: (a + 2.0 * (b + c) + d) / 6.0, k1, k2, k3, k4)
    return _axpy(dt, incr, x)


def lie_rk4_step(r: jax.Array, omega_fn: Callable[[jax.Array, float], jax.Array], dt) -> jax.Array:
    """RKMK-4 step for dR/dt = R S(omega(R, t)) that keeps R on SO(3) by construction.

    ``omega_fn(R, frac)`` is the body angular velocity (rad/s) at fraction ``frac`` of the step. The increment
    is integrated in the Lie algebra (Munthe-Kaas with the dexp^-1 correction to fourth order) and applied
    through the exponential map, so R stays a rotation to rounding error whatever the step.
    """

    def dexpinv(phi, w):
        # Right-trivialised form (R = R0 exp(S(phi)), phi' = dexp^{-1}_{-phi}(omega)):
        # dexp^{-1}_{-phi}(w) ~= w + 1/2 phi x w + 1/12 phi x (phi x w)  (enough for order 4)
        pw = so3.cross(phi, w)
        return w + 0.5 * pw + so3.cross(phi, pw) / 12.0

    k1 = omega_fn(r, 0.0)
    p = 0.5 * dt * k1
    k2 = dexpinv(p, omega_fn(so3.mm(r, so3.exp(p)), 0.5))
    p = 0.5 * dt * k2
    k3 = dexpinv(p, omega_fn(so3.mm(r, so3.exp(p)), 0.5))
    p = dt * k3
    k4 = dexpinv(p, omega_fn(so3.mm(r, so3.exp(p)), 1.0))
    phi = dt * (k1 + 2.0 * (k2 + k3) + k4) / 6.0
    return so3.mm(r, so3.exp(phi))


_GL = 3.0 ** 0.5 / 6.0


def magnus4_step(r: jax.Array, rate_fn: Callable[[jax.Array], jax.Array], t, dt) -> jax.Array:
    """Fourth-order Magnus step for dR/dt = R S(omega(t)) with a known rate function (true attitude).

    Uses the two Gauss-Legendre nodes t + (1/2 -+ sqrt(3)/6) dt. Stays on SO(3) by construction.
    """
    w1 = rate_fn(t + (0.5 - _GL) * dt)
    w2 = rate_fn(t + (0.5 + _GL) * dt)
    phi = 0.5 * dt * (w1 + w2) + (3.0 ** 0.5 / 12.0) * dt * dt * so3.cross(w1, w2)
    return so3.mm(r, so3.exp(phi))
