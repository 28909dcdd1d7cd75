"""Order and accuracy of jaxatt.integrate against independent numpy references (float64, see conftest)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxatt import integrate, so3
from jaxatt.integrate import Interval, input_at

DEG = np.pi / 180.0
T_END = 60.0


# ----------------------------------------------------------------------------------------------------------
# The test problem: dR/dt = R S(omega(t)), R(0) = I
# ----------------------------------------------------------------------------------------------------------
def omega_np(t):
    t = np.asarray(t, float)
    return np.stack(
        [
            5 * DEG * np.sin(2 * np.pi * t / 60),
            1 * DEG * np.sin(2 * np.pi * t / 180),
            -2 * DEG * np.sin(2 * np.pi * t / 300),
        ],
        axis=-1,
    )


def omega_jax(t):
    return jnp.stack(
        [
            5 * DEG * jnp.sin(2 * jnp.pi * t / 60),
            1 * DEG * jnp.sin(2 * jnp.pi * t / 180),
            -2 * DEG * jnp.sin(2 * jnp.pi * t / 300),
        ],
        axis=-1,
    )


def skew_np(w):
    """Batched S(w) in numpy, shape (..., 3, 3)."""
    z = np.zeros(w.shape[:-1])
    return np.stack(
        [
            np.stack([z, -w[..., 2], w[..., 1]], -1),
            np.stack([w[..., 2], z, -w[..., 0]], -1),
            np.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        axis=-2,
    )


def _ordered_product(p):
    """P_0 @ P_1 @ ... @ P_{n-1} by pairwise reduction (keeps the order; vectorised)."""
    while p.shape[0] > 1:
        if p.shape[0] % 2:
            p = np.concatenate([p, np.eye(3)[None]], axis=0)
        p = np.einsum("nij,njk->nik", p[0::2], p[1::2])
    return p[0]


@functools.lru_cache(maxsize=None)
def reference_rk4(dt=1e-4, t_end=T_END):
    """Classical RK4 on the 9-dim linear ODE  R' = R A(t), A = S(omega(t)), with step ``dt``.

    For a linear right-hand side, one RK4 step is exactly R_{k+1} = R_k P_k with
        k1 = R A1, k2 = (R + h/2 k1) A2, k3 = (R + h/2 k2) A2, k4 = (R + h k3) A3,
        P = I + h/6 (K1 + 2 K2 + 2 K3 + K4),  K1 = A1, K2 = (I + h/2 K1) A2, K3 = (I + h/2 K2) A2, K4 = (I + h K3) A3,
    so all step matrices are built at once and multiplied in order.
    """
    n = int(round(t_end / dt))
    t = np.arange(n) * dt
    a1, a2, a3 = skew_np(omega_np(t)), skew_np(omega_np(t + 0.5 * dt)), skew_np(omega_np(t + dt))
    eye = np.eye(3)
    mul = lambda x, y: np.einsum("nij,njk->nik", x, y)  # noqa: E731
    k1 = a1
    k2 = mul(eye + 0.5 * dt * k1, a2)
    k3 = mul(eye + 0.5 * dt * k2, a2)
    k4 = mul(eye + dt * k3, a3)
    p = eye + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return _ordered_product(p)


def rk4_loop_np(dt, t_end):
    """Plain step-by-step classical RK4 in numpy (to validate the vectorised reference on a coarse grid)."""
    r = np.eye(3)
    f = lambda r, t: r @ skew_np(omega_np(t))  # noqa: E731
    for k in range(int(round(t_end / dt))):
        t = k * dt
        k1 = f(r, t)
        k2 = f(r + 0.5 * dt * k1, t + 0.5 * dt)
        k3 = f(r + 0.5 * dt * k2, t + 0.5 * dt)
        k4 = f(r + dt * k3, t + dt)
        r = r + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return r


# ----------------------------------------------------------------------------------------------------------
# jitted integrations (dt and the number of steps are traced: one compile for all step sizes)
# ----------------------------------------------------------------------------------------------------------
@jax.jit
def integrate_magnus(dt, n):
    def body(k, r):
        return integrate.magnus4_step(r, omega_jax, k * dt, dt)

    return jax.lax.fori_loop(0, n, body, jnp.eye(3))


@jax.jit
def integrate_lie_rk4(dt, n):
    def body(k, r):
        t = k * dt
        return integrate.lie_rk4_step(r, lambda _r, frac: omega_jax(t + frac * dt), dt)

    return jax.lax.fori_loop(0, n, body, jnp.eye(3))


def _err(r, ref):
    return float(np.max(np.abs(np.asarray(r) - ref)))


def _n(dt, t_end=T_END):
    n = int(round(t_end / dt))
    assert abs(n * dt - t_end) < 1e-9
    return n


# ----------------------------------------------------------------------------------------------------------
# Reference sanity
# ----------------------------------------------------------------------------------------------------------
def test_vectorised_reference_equals_stepwise_rk4():
    dt, t_end = 0.05, 6.0
    np.testing.assert_allclose(reference_rk4(dt, t_end), rk4_loop_np(dt, t_end), atol=1e-14)


def test_reference_is_converged():
    ref = reference_rk4()
    # a rotation, and unchanged (to well below the 1e-9 test tolerance) by doubling the RK4 step
    np.testing.assert_allclose(ref.T @ ref, np.eye(3), atol=1e-12)
    assert np.max(np.abs(reference_rk4(2e-4) - ref)) < 1e-12
    # the motion is not trivial: the attitude moved by several degrees
    assert np.linalg.norm(ref - np.eye(3)) > 0.05


# ----------------------------------------------------------------------------------------------------------
# magnus4_step
# ----------------------------------------------------------------------------------------------------------
def test_magnus4_matches_fine_rk4():
    r = integrate_magnus(0.01, _n(0.01))
    assert _err(r, reference_rk4()) < 1e-9
    assert float(so3.orthogonality_error(r)) < 1e-12


def test_magnus4_is_fourth_order():
    ref = reference_rk4()
    errs = [_err(integrate_magnus(dt, _n(dt)), ref) for dt in (2.0, 1.0, 0.5)]
    ratios = [errs[0] / errs[1], errs[1] / errs[2]]
    assert all(10.0 < q < 22.0 for q in ratios), (errs, ratios)


def test_magnus4_exact_for_constant_rate():
    w = jnp.array([0.3, -0.2, 0.7])
    r0 = so3.exp(jnp.array([0.1, 0.2, -0.3]))
    r = integrate.magnus4_step(r0, lambda t: w, 0.0, 0.5)
    np.testing.assert_allclose(np.asarray(r), np.asarray(r0 @ so3.exp(0.5 * w)), atol=1e-15)


# ----------------------------------------------------------------------------------------------------------
# lie_rk4_step
# ----------------------------------------------------------------------------------------------------------
def test_lie_rk4_stays_on_so3():
    r = integrate_lie_rk4(0.006, 10000)
    assert float(so3.orthogonality_error(r)) < 1e-12
    assert abs(float(so3.det3(r)) - 1.0) < 1e-12


def test_lie_rk4_stays_on_so3_large_rates():
    # far outside the asymptotic regime (|omega| dt ~ 1): still a rotation up to accumulated rounding
    # (10000 steps x ~1e-16), while classical RK4 on the 9 matrix entries leaves SO(3) completely.
    w = lambda _r, frac: jnp.array([3.0, -2.0, 4.0]) * (1.0 + frac)  # noqa: E731

    @jax.jit
    def run(r):
        return jax.lax.fori_loop(0, 10000, lambda k, r: integrate.lie_rk4_step(r, w, 0.2), r)

    @jax.jit
    def run_classical(r):
        f = lambda r, u: r @ so3.skew(jnp.array([3.0, -2.0, 4.0]) * (1.0 + u))  # noqa: E731
        u = Interval(0.0, 1.0)
        return jax.lax.fori_loop(0, 100, lambda k, r: integrate.rk4_step(f, r, u, 0.2), r)

    assert float(so3.orthogonality_error(run(jnp.eye(3)))) < 1e-11
    assert float(so3.orthogonality_error(run_classical(jnp.eye(3)))) > 1e-3


def test_lie_rk4_matches_fine_rk4_and_is_fourth_order():
    ref = reference_rk4()
    assert _err(integrate_lie_rk4(0.01, _n(0.01)), ref) < 1e-9
    errs = [_err(integrate_lie_rk4(dt, _n(dt)), ref) for dt in (2.0, 1.0, 0.5)]
    ratios = [errs[0] / errs[1], errs[1] / errs[2]]
    assert all(10.0 < q < 22.0 for q in ratios), (errs, ratios)


def test_lie_rk4_fourth_order_with_state_dependent_rate():
    """omega depending on R (observer-like feedback): Richardson differences shrink by ~16 per halving."""
    a = jnp.array([[0.3, 0.1, 0.0], [0.0, -0.2, 0.4], [0.1, 0.0, 0.5]])
    e3 = jnp.array([0.0, 0.0, 1.0])

    @jax.jit
    def run(dt, n):
        fn = lambda r, frac: a @ (r.T @ e3) + jnp.array([0.2, -0.1, 0.3])  # noqa: E731
        return jax.lax.fori_loop(0, n, lambda k, r: integrate.lie_rk4_step(r, fn, dt), jnp.eye(3))

    t_end = 6.0
    rs = [np.asarray(run(dt, _n(dt, t_end))) for dt in (0.4, 0.2, 0.1, 0.05)]
    d = [np.max(np.abs(rs[i] - rs[i + 1])) for i in range(3)]
    ratios = [d[0] / d[1], d[1] / d[2]]
    assert all(10.0 < q < 22.0 for q in ratios), (d, ratios)


# ----------------------------------------------------------------------------------------------------------
# rk4_step and input_at
# ----------------------------------------------------------------------------------------------------------
@functools.partial(jax.jit, static_argnames=("n", "linear"))
def _scalar_rk4(x0, dt, n, linear):
    """dx/dt = lam x + u(t), u(t) = c + d t; the input is given as samples at the step ends."""
    lam, c, d = -0.7, 0.5, 0.3
    u = lambda t: c + d * t  # noqa: E731
    f = lambda x, ui: lam * x + ui  # noqa: E731

    def body(k, x):
        t = k * dt
        ui = Interval(u(t), u(t + dt)) if linear else u(t)
        return integrate.rk4_step(f, x, ui, dt)

    return jax.lax.fori_loop(0, n, body, x0)


def _scalar_exact(x0, t):
    lam, c, d = -0.7, 0.5, 0.3
    # x' = lam x + c + d t:  particular solution p(t) = alpha + beta t with beta = -d/lam, alpha = (beta - c)/lam
    beta = -d / lam
    alpha = (beta - c) / lam
    return (x0 - alpha) * np.exp(lam * t) + alpha + beta * t


def test_rk4_fourth_order_scalar_linear():
    x0, t_end = 1.3, 4.0
    exact = _scalar_exact(x0, t_end)
    errs = [abs(float(_scalar_rk4(x0, t_end / n, n, True)) - exact) for n in (16, 32, 64)]
    ratios = [errs[0] / errs[1], errs[1] / errs[2]]
    assert all(14.5 < q < 18.0 for q in ratios), (errs, ratios)
    assert errs[-1] < 1e-6


def test_rk4_zero_order_hold_is_first_order_in_input():
    # with the sample held over the step the input is wrong by O(dt): the error only halves with dt
    x0, t_end = 1.3, 4.0
    exact = _scalar_exact(x0, t_end)
    errs = [abs(float(_scalar_rk4(x0, t_end / n, n, False)) - exact) for n in (16, 32, 64)]
    ratios = [errs[0] / errs[1], errs[1] / errs[2]]
    assert all(1.7 < q < 2.3 for q in ratios), (errs, ratios)


def test_rk4_on_pytree_state():
    # x = {"a": a, "b": (b1, b2)} with a' = b1, b1' = -a, b2' = 0 (harmonic oscillator + constant)
    f = lambda x, u: {"a": x["b"][0], "b": (-x["a"], jnp.zeros_like(x["b"][1]))}  # noqa: E731
    x = {"a": jnp.array(1.0), "b": (jnp.array(0.0), jnp.array([2.0, 3.0]))}
    step = jax.jit(lambda x: integrate.rk4_step(f, x, None, 0.01))
    for _ in range(100):
        x = step(x)
    np.testing.assert_allclose(float(x["a"]), np.cos(1.0), atol=1e-9)
    np.testing.assert_allclose(float(x["b"][0]), -np.sin(1.0), atol=1e-9)
    np.testing.assert_array_equal(np.asarray(x["b"][1]), [2.0, 3.0])


def test_input_at_interval_and_hold():
    start = {"g": jnp.array([1.0, -2.0, 4.0]), "s": jnp.array(3.0)}
    end = {"g": jnp.array([3.0, 2.0, 0.0]), "s": jnp.array(-1.0)}
    u = Interval(start, end)
    assert input_at(u, 0.0) is start
    assert input_at(u, 1.0) is end
    for frac in (0.25, 0.5, 0.8):
        got = input_at(u, frac)
        np.testing.assert_allclose(
            np.asarray(got["g"]), (1 - frac) * np.array([1.0, -2.0, 4.0]) + frac * np.array([3.0, 2.0, 0.0]), atol=1e-15
        )
        np.testing.assert_allclose(float(got["s"]), (1 - frac) * 3.0 + frac * -1.0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(input_at(u, 0.5)["g"]), [2.0, 0.0, 2.0], atol=0)
    # a plain sample is held whatever the fraction
    for frac in (0.0, 0.5, 1.0):
        assert input_at(start, frac) is start


def test_rkmk4_coupled_sphere_and_rotation_is_fourth_order_and_norm_preserving():
    """rkmk4_step on (x Euclidean, v on a sphere, R on SO(3)) with state-dependent rates: |v| and R^T R = I
    exactly, and the error against a fine classical RK4 falls ~16x when the step halves."""
    from jaxatt.integrate import rk4_step, rkmk4_step

    def rates(x, v, r, t):
        a = jnp.stack([jnp.sin(t) + 0.3 * x[0], 0.5 * jnp.cos(2 * t), 0.2 + 0.1 * v[2]])
        w = so3.mv(jnp.swapaxes(r, -1, -2), jnp.array([0.1, 0.4, -0.3])) + 0.2 * v
        return jnp.array([v[0] - 0.5 * x[0]]), a, w

    def f_lie(x, frames, t):
        v, r = frames
        dx, a, w = rates(x, v, r, t)
        return dx, (a, w)

    def f_flat(y, t):
        x, v, r = y
        dx, a, w = rates(x, v, r, t)
        return dx, so3.cross(a, v), so3.mm(r, so3.skew(w))

    x0, v0, r0 = jnp.array([0.3]), jnp.array([1.0, -2.0, 0.5]), so3.exp(jnp.array([0.3, -0.2, 0.9]))
    T = 2.0

    def solve(step, y0, n):  # n steps of ``step`` over [0, T], one compiled scan
        dt = T / n

        def body(y, k):
            t0 = k * dt
            return step(y, Interval(t0, t0 + dt), dt), None

        return jax.jit(lambda y: jax.lax.scan(body, y, jnp.arange(n, dtype=jnp.float64))[0])(y0)

    def solve_lie(n):
        return solve(lambda y, u, dt: rkmk4_step(f_lie, y[0], y[1], u, dt), (x0, (v0, r0)), n)

    ref = solve(lambda y, u, dt: rk4_step(f_flat, y, u, dt), (x0, v0, r0), 4000)
    errs = []
    for n in (20, 40):
        x, (v, r) = solve_lie(n)
        assert abs(float(jnp.linalg.norm(v) - jnp.linalg.norm(v0))) < 1e-13
        assert float(so3.orthogonality_error(r)) < 1e-13
        errs.append(float(jnp.linalg.norm(v - ref[1]) + jnp.linalg.norm(r - ref[2]) + jnp.linalg.norm(x - ref[0])))
    assert 12.0 < errs[0] / errs[1] < 20.0, errs
