"""Integrators shared by every continuous-time observer and by the simulator.

Observers are continuous-time ODEs driven by sampled sensor inputs. A step from t_k to t_k + dt needs the
input at the RK4 stage times t_k, t_k + dt/2, t_k + dt. Two readings exist (the papers do not say which they
used; docs/observers/batista_ges.md discusses both):

* ``hold="zoh"`` (default): the sample taken at t_k is held over the step. Causal; what a real-time
  implementation does.
* ``hold="linear"``: the input is interpolated linearly between the samples at t_k and t_k + dt, so stage
  inputs are (u_k, (u_k + u_k+1)/2, u_k+1). Needs one sample of look-ahead (offline processing).

A step receives a :class:`Interval` (start and end samples) in the linear mode and a plain sample otherwise;
:func:`input_at` hides the difference from the observer.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp

from . import so3
from .types import Interval

__all__ = ["input_at", "rk4_step", "rkmk4_step", "lie_rk4_step", "magnus4_step"]


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


def _dexpinv(phi, w, side: float):
    """dexp^{-1}_{-side*phi}(w) to the order RKMK-4 needs: w + side/2 phi x w + 1/12 phi x (phi x w)
    (side = +1 for the right action R exp(S(phi)), -1 for the left action exp(S(phi)) v)."""
    pw = so3.cross(phi, w)
    return w + 0.5 * side * pw + so3.cross(phi, pw) / 12.0


def _act(g, phi):
    """Apply the group increment exp(S(phi)): right action R exp(S(phi)) on a rotation (3, 3), left action
    exp(S(phi)) v on a vector (3,)."""
    e = so3.exp(phi)
    return so3.mm(g, e) if g.shape[-2:] == (3, 3) else so3.mv(e, g)


def rkmk4_step(f: Callable[[Any, tuple, Any], tuple], x: Any, frames: tuple, u: Any, dt) -> tuple:
    """One RKMK-4 (Runge-Kutta-Munthe-Kaas) step of an ODE that couples Euclidean states with states moved by
    rotations, so the latter stay exactly on their manifold (SO(3), or a sphere) whatever the step.

    Args:
        f: ``f(x, frames, u) -> (dx, omegas)``; ``omegas[i]`` (3,) moves ``frames[i]``:
            a rotation (3, 3) with dR/dt = R S(omega) (body rate, right action), or a vector (3,) with
            dv/dt = omega x v (left action: the norm of v is preserved).
        x: Euclidean state (any pytree, may be ``()``), advanced by classical RK4 with the same stages.
        frames: tuple of rotations and/or vectors.
        u: the input (a held sample or an :class:`Interval`; see :func:`input_at`).
    Returns (x_next, frames_next).
    """
    sides = tuple(1.0 if g.shape[-2:] == (3, 3) else -1.0 for g in frames)

    def stage(k_prev, frac_x, frac_u):
        if k_prev is None:
            return f(x, frames, input_at(u, frac_u)), tuple(
                jnp.zeros_like(g[..., 0, :] if s > 0 else g) for g, s in zip(frames, sides)
            )
        dx, om = k_prev
        phis = tuple(frac_x * dt * w for w in om)
        xs = _axpy(frac_x * dt, dx, x)
        gs = tuple(_act(g, p) for g, p in zip(frames, phis))
        return f(xs, gs, input_at(u, frac_u)), phis

    def corrected(k, phis):
        dx, om = k
        return dx, tuple(_dexpinv(p, w, s) for p, w, s in zip(phis, om, sides))

    k1 = corrected(*stage(None, 0.0, 0.0))
    k2 = corrected(*stage(k1, 0.5, 0.5))
    k3 = corrected(*stage(k2, 0.5, 0.5))
    k4 = corrected(*stage(k3, 1.0, 1.0))
    dx = jax.tree_util.tree_map(lambda a, b, c, d: (a + 2.0 * (b + c) + d) / 6.0, k1[0], k2[0], k3[0], k4[0])
    phis = tuple((a + 2.0 * (b + c) + d) / 6.0 for a, b, c, d in zip(k1[1], k2[1], k3[1], k4[1]))
    return _axpy(dt, dx, x), tuple(_act(g, dt * p) for g, p in zip(frames, phis))


def lie_rk4_step(r: jax.Array, omega_fn: Callable[[jax.Array, float], jax.Array], dt) -> jax.Array:
    """RKMK-4 step for dR/dt = R S(omega(R, t)) that keeps R on SO(3) by construction.

    ``omega_fn(R, frac)`` is the body angular velocity (rad/s) at fraction ``frac`` of the step. The increment
    is integrated in the Lie algebra (Munthe-Kaas with the dexp^-1 correction to fourth order) and applied
    through the exponential map, so R stays a rotation to rounding error whatever the step.
    """
    f = lambda x, frames, frac: ((), (omega_fn(frames[0], frac),))  # noqa: E731
    return rkmk4_step(f, (), (r,), Interval(0.0, 1.0), dt)[1][0]


_GL = 3.0**0.5 / 6.0


def magnus4_step(r: jax.Array, rate_fn: Callable[[jax.Array], jax.Array], t, dt) -> jax.Array:
    """Fourth-order Magnus step for dR/dt = R S(omega(t)) with a known rate function (true attitude).

    Uses the two Gauss-Legendre nodes t + (1/2 -+ sqrt(3)/6) dt. Stays on SO(3) by construction.
    """
    w1 = rate_fn(t + (0.5 - _GL) * dt)
    w2 = rate_fn(t + (0.5 + _GL) * dt)
    phi = 0.5 * dt * (w1 + w2) + (3.0**0.5 / 12.0) * dt * dt * so3.cross(w1, w2)
    return so3.mm(r, so3.exp(phi))
