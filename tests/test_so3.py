"""Properties of jaxatt.so3 checked against independent numpy references (float64, see conftest)."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxatt import frames, so3

PI = np.pi


class _Jitted:
    """so3.<name> wrapped in jax.jit (cached): one compile per shape instead of eager per-op dispatch."""

    def __init__(self):
        self._cache = {}

    def __getattr__(self, name):
        if name not in self._cache:
            self._cache[name] = jax.jit(getattr(so3, name))
        return self._cache[name]


J = _Jitted()


# ----------------------------------------------------------------------------------------------------------
# Independent numpy references (no jaxatt code involved)
# ----------------------------------------------------------------------------------------------------------
def np_skew(x):
    return np.array([[0.0, -x[2], x[1]], [x[2], 0.0, -x[0]], [-x[1], x[0], 0.0]])


def np_expm_series(a, terms=60):
    """exp(A) by the truncated power series sum A^k / k!, with scaling and squaring for accuracy."""
    s = max(0, int(np.ceil(np.log2(max(np.linalg.norm(a, 2), 1e-300)))) + 1)
    b = a / 2.0**s
    out = np.eye(3)
    term = np.eye(3)
    for k in range(1, terms):
        term = term @ b / k
        out = out + term
    for _ in range(s):
        out = out @ out
    return out


def np_rot_axis_angle(axis, angle):
    """Rodrigues' formula in numpy (unit axis)."""
    k = np_skew(np.asarray(axis, float) / np.linalg.norm(axis))
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def np_random_rotation(rng):
    """Uniform random rotation from the QR of a Gaussian matrix (sign fixed, det +1)."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def np_polar_rotation(m):
    """Nearest rotation (Frobenius) by numpy's SVD with the determinant fix."""
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def np_quat_to_matrix(q):
    """Rotation matrix of a unit (w,x,y,z) quaternion via v' = q v q* written with numpy Hamilton products."""

    def hprod(p, q):
        pw, pv, qw, qv = p[0], p[1:], q[0], q[1:]
        return np.concatenate([[pw * qw - pv @ qv], pw * qv + qw * pv + np.cross(pv, qv)])

    q = np.asarray(q, float) / np.linalg.norm(q)
    qc = q * np.array([1, -1, -1, -1])
    cols = [hprod(hprod(q, np.concatenate([[0.0], e])), qc)[1:] for e in np.eye(3)]
    return np.stack(cols, axis=1)


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def random_unit_vectors(rng, n):
    v = rng.standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


# Angles covering the special branches: exactly 0, tiny, small, generic, and near / at pi.
SPECIAL_ANGLES = [0.0, 1e-12, 1e-9, 1e-7, 1e-4, 0.3, 1.0, 2.5, 3.0, PI - 1e-3, PI - 1e-6, PI - 1e-9, PI]
AXES = [unit([1, 0, 0]), unit([0, 1, 0]), unit([0, 0, 1]), unit([1, 2, 3]), unit([-0.3, 0.8, -0.5])]


# ----------------------------------------------------------------------------------------------------------
# skew / vex
# ----------------------------------------------------------------------------------------------------------
def test_skew_cross_and_vex_inverse(rng):
    x = rng.standard_normal((50, 3))
    y = rng.standard_normal((50, 3))
    s = np.asarray(J.skew(jnp.asarray(x)))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", s, y), np.cross(x, y), atol=1e-14)
    np.testing.assert_allclose(s, -np.swapaxes(s, 1, 2), atol=0)
    np.testing.assert_allclose(np.asarray(J.vex(jnp.asarray(s))), x, atol=1e-15)
    np.testing.assert_allclose(np.asarray(J.cross(jnp.asarray(x), jnp.asarray(y))), np.cross(x, y), atol=1e-14)
    # the Levi-Civita contraction equals the component formula to one rounding of each component (the other
    # terms are exact zeros; XLA may fuse a product into the sum), in float64 and float32, jitted or not; S(x)
    # holds x's components exactly
    for dt in (np.float64, np.float32):
        a, b = x.astype(dt), y.astype(dt)
        terms = [(1, 2), (2, 0), (0, 1)]
        comp = np.stack([a[:, j] * b[:, k] - a[:, k] * b[:, j] for j, k in terms], axis=-1)
        scale = np.stack([np.abs(a[:, j] * b[:, k]) + np.abs(a[:, k] * b[:, j]) for j, k in terms], axis=-1)
        for f in (J.cross, jax.jit(J.cross)):
            c = np.asarray(f(jnp.asarray(a), jnp.asarray(b)))
            assert c.dtype == dt
            assert np.all(np.abs(c - comp) <= np.finfo(dt).eps * scale), np.max(np.abs(c - comp) / scale)
        sk = np.asarray(J.skew(jnp.asarray(a)))
        np.testing.assert_array_equal(sk[:, [2, 0, 1], [1, 2, 0]], a)
        np.testing.assert_array_equal(sk[:, [1, 2, 0], [2, 0, 1]], -a)
        np.testing.assert_array_equal(sk[:, [0, 1, 2], [0, 1, 2]], 0.0)
    # vex ignores the symmetric part
    sym = rng.standard_normal((50, 3, 3))
    sym = sym + np.swapaxes(sym, 1, 2)
    np.testing.assert_allclose(np.asarray(J.vex(jnp.asarray(s + sym))), x, atol=1e-14)


def test_mm_mv_det_cofactor(rng):
    a = rng.standard_normal((7, 3, 3))
    b = rng.standard_normal((7, 3, 3))
    v = rng.standard_normal((7, 3))
    np.testing.assert_allclose(np.asarray(J.mm(a, b)), a @ b, atol=1e-13)
    np.testing.assert_allclose(np.asarray(J.mv(a, v)), np.einsum("nij,nj->ni", a, v), atol=1e-13)
    np.testing.assert_allclose(np.asarray(J.det3(a)), np.linalg.det(a), rtol=1e-12, atol=1e-13)
    inv_t = np.swapaxes(np.linalg.inv(a), 1, 2)
    np.testing.assert_allclose(
        np.asarray(J.cofactor(a)) / np.linalg.det(a)[:, None, None], inv_t, rtol=1e-10, atol=1e-10
    )


# ----------------------------------------------------------------------------------------------------------
# exp / log
# ----------------------------------------------------------------------------------------------------------
def test_exp_matches_power_series(rng):
    phis = list(rng.standard_normal((20, 3)) * rng.uniform(0, 3.5, (20, 1)))
    phis += [th * ax for th, ax in itertools.product([0.0, 1e-9, 1e-7, 1e-3, PI - 1e-6, PI], AXES[:4])]
    for phi in phis:
        ref = np_expm_series(np_skew(phi))
        got = np.asarray(J.exp(jnp.asarray(phi)))
        np.testing.assert_allclose(got, ref, atol=2e-15 * max(1.0, np.linalg.norm(phi)) * 4, rtol=0)


def test_quat_exp_and_log_are_the_matrix_exp_and_log(rng):
    """so3.quat_exp (one copy: the MEKF and the smoother use it) is the quaternion of the power series' matrix
    exponential, and so3.quat_log its inverse with the angle in [0, pi], for either sign of q."""
    dirs = rng.standard_normal((20, 3))
    phis = list(dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * rng.uniform(0, PI - 1e-3, (20, 1)))
    phis += [th * ax for th, ax in itertools.product([0.0, 1e-9, 1e-7, 1e-3, PI - 1e-6], AXES[:4])]
    for phi in phis:
        q = J.quat_exp(jnp.asarray(phi))
        assert abs(float(jnp.linalg.norm(q)) - 1.0) < 1e-15
        ref = np_expm_series(np_skew(phi))
        np.testing.assert_allclose(np.asarray(J.quat_to_matrix(q)), ref, atol=1e-14, rtol=0)
        np.testing.assert_allclose(np.asarray(J.quat_log(q)), phi, atol=1e-13 * max(1.0, np.linalg.norm(phi)))
        np.testing.assert_allclose(np.asarray(J.quat_log(-q)), phi, atol=1e-13 * max(1.0, np.linalg.norm(phi)))
    g = jax.grad(lambda v: J.quat_exp(v)[1])(jnp.zeros(3))  # finite at 0: d(x)/dv = [1/2, 0, 0]
    np.testing.assert_allclose(np.asarray(g), [0.5, 0.0, 0.0], atol=1e-15)


def test_exp_is_rotation_about_axis(rng):
    for th, ax in itertools.product(SPECIAL_ANGLES, AXES):
        r = np.asarray(J.exp(jnp.asarray(th * ax)))
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-14)
        assert abs(np.linalg.det(r) - 1.0) < 1e-14
        np.testing.assert_allclose(r @ ax, ax, atol=1e-15)  # axis is fixed
        np.testing.assert_allclose(r, np_rot_axis_angle(ax, th), atol=1e-15)


def test_exp_log_roundtrip_special_angles():
    for th, ax in itertools.product(SPECIAL_ANGLES, AXES):
        r = np_rot_axis_angle(ax, th)
        phi = np.asarray(J.log(jnp.asarray(r)))
        assert np.all(np.isfinite(phi))
        assert np.linalg.norm(phi) <= PI + 1e-12
        np.testing.assert_allclose(np.asarray(J.exp(jnp.asarray(phi))), r, atol=1e-14)
        # log returns the expected vector (up to sign at exactly pi, where both are valid)
        expect = th * ax
        if th == PI:
            err = min(np.linalg.norm(phi - expect), np.linalg.norm(phi + expect))
        else:
            err = np.linalg.norm(phi - expect)
        # Near pi the axis is recovered from O(delta) data: allow the conditioning loss
        tol = 1e-14 if th < 3.0 else 1e-8
        assert err <= tol, (th, ax, phi, expect)


def test_exp_log_roundtrip_random(rng):
    rs = np.stack([np_random_rotation(rng) for _ in range(200)])
    phi = J.log(jnp.asarray(rs))
    assert phi.shape == (200, 3)
    np.testing.assert_allclose(np.asarray(J.exp(phi)), rs, atol=1e-14)


def test_log_exp_roundtrip_random(rng):
    ax = random_unit_vectors(rng, 300)
    th = rng.uniform(0, PI - 1e-3, (300, 1))
    th[:10] = np.array([0.0, 1e-12, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4, 3.1, 3.14])[:, None]
    phi = ax * th
    got = np.asarray(J.log(J.exp(jnp.asarray(phi))))
    np.testing.assert_allclose(got, phi, atol=2e-14, rtol=0)
    # relative accuracy at tiny angles
    small = th[:, 0] < 1e-4
    rel = np.linalg.norm(got[small] - phi[small], axis=1) / np.maximum(th[small, 0], 1e-300)
    assert np.all(rel[th[small, 0] > 0] < 1e-12)


# ----------------------------------------------------------------------------------------------------------
# Quaternions
# ----------------------------------------------------------------------------------------------------------
def test_quat_to_matrix_matches_reference(rng):
    q = rng.standard_normal((30, 4))
    got = np.asarray(J.quat_to_matrix(jnp.asarray(q)))
    for qi, ri in zip(q, got):
        np.testing.assert_allclose(ri, np_quat_to_matrix(qi), atol=1e-14)
    # quaternion of axis-angle (cos th/2, sin th/2 axis) gives Rodrigues' rotation
    for th, ax in itertools.product([0.0, 0.5, 2.0, PI], AXES):
        q = np.concatenate([[np.cos(th / 2)], np.sin(th / 2) * ax])
        np.testing.assert_allclose(np.asarray(J.quat_to_matrix(jnp.asarray(q))), np_rot_axis_angle(ax, th), atol=1e-15)


def _same_up_to_sign(a, b, atol):
    return min(np.max(np.abs(a - b)), np.max(np.abs(a + b))) <= atol


def test_matrix_quat_roundtrip(rng):
    q = rng.standard_normal((300, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    # rotations with very negative trace: angles near pi (w ~ 0), and exactly pi about each axis
    near_pi = []
    for delta, ax in itertools.product([0.0, 1e-12, 1e-8, 1e-4, 1e-2], list(AXES) + list(random_unit_vectors(rng, 5))):
        th = PI - delta
        near_pi.append(np.concatenate([[np.cos(th / 2)], np.sin(th / 2) * ax]))
    q = np.concatenate([q, np.array(near_pi), np.eye(4)])
    r = np.asarray(J.quat_to_matrix(jnp.asarray(q)))
    q2 = np.asarray(J.matrix_to_quat(jnp.asarray(r)))
    np.testing.assert_allclose(np.linalg.norm(q2, axis=1), 1.0, atol=1e-14)
    for a, b in zip(q, q2):
        assert _same_up_to_sign(a, b, 1e-14), (a, b)
    np.testing.assert_allclose(np.asarray(J.quat_to_matrix(jnp.asarray(q2))), r, atol=1e-14)
    # traces really were very negative for the near-pi group
    tr = np.trace(r[300 : 300 + len(near_pi)], axis1=1, axis2=2)
    assert np.all(tr < -0.99)


def test_quat_multiply_is_matrix_product(rng):
    p = rng.standard_normal((100, 4))
    q = rng.standard_normal((100, 4))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    pq = J.quat_multiply(jnp.asarray(p), jnp.asarray(q))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(pq), axis=1), 1.0, atol=1e-14)
    lhs = np.asarray(J.quat_to_matrix(pq))
    rhs = np.asarray(J.quat_to_matrix(jnp.asarray(p))) @ np.asarray(J.quat_to_matrix(jnp.asarray(q)))
    np.testing.assert_allclose(lhs, rhs, atol=1e-14)
    # Hamilton unit products: i*j = k, j*k = i, k*i = j, i*i = -1
    one, i, j, k = np.eye(4)
    qm = lambda a, b: np.asarray(J.quat_multiply(jnp.asarray(a), jnp.asarray(b)))  # noqa: E731
    np.testing.assert_array_equal(qm(i, j), k)
    np.testing.assert_array_equal(qm(j, k), i)
    np.testing.assert_array_equal(qm(k, i), j)
    np.testing.assert_array_equal(qm(i, i), -one)


def test_quat_conjugate_inverse(rng):
    q = rng.standard_normal((50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    qj = jnp.asarray(q)
    qc = J.quat_conjugate(qj)
    ident = np.tile([1.0, 0, 0, 0], (50, 1))
    np.testing.assert_allclose(np.asarray(J.quat_multiply(qj, qc)), ident, atol=1e-15)
    np.testing.assert_allclose(np.asarray(J.quat_multiply(qc, qj)), ident, atol=1e-15)
    r = np.asarray(J.quat_to_matrix(qj))
    np.testing.assert_allclose(np.asarray(J.quat_to_matrix(qc)), np.swapaxes(r, 1, 2), atol=1e-15)


def test_quat_canonical_and_xyzw(rng):
    q = rng.standard_normal((50, 4))
    qc = np.asarray(J.quat_canonical(jnp.asarray(q)))
    assert np.all(qc[:, 0] >= 0)
    assert np.all((qc == q).all(axis=1) | (qc == -q).all(axis=1))
    xyzw = np.asarray(frames.to_xyzw(jnp.asarray(q)))
    np.testing.assert_array_equal(xyzw, q[:, [1, 2, 3, 0]])
    np.testing.assert_array_equal(np.asarray(frames.from_xyzw(jnp.asarray(xyzw))), q)
    np.testing.assert_array_equal(np.asarray(frames.to_xyzw(frames.from_xyzw(jnp.asarray(q)))), q)


# ----------------------------------------------------------------------------------------------------------
# Projection onto SO(3)
# ----------------------------------------------------------------------------------------------------------
def _random_matrices(rng, n):
    m = rng.standard_normal((n, 3, 3))
    # force half of them to have det < 0
    neg = np.linalg.det(m) > 0
    m[neg[: n // 2].nonzero()[0], :, 0] *= -1
    return m


def test_nearest_rotation_in_so3_and_matches_svd(rng):
    m = _random_matrices(rng, 100)
    assert np.sum(np.linalg.det(m) < 0) >= 40
    r = np.asarray(J.nearest_rotation(jnp.asarray(m)))
    np.testing.assert_allclose(np.swapaxes(r, 1, 2) @ r, np.tile(np.eye(3), (100, 1, 1)), atol=1e-13)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-13)
    ref = np.stack([np_polar_rotation(mi) for mi in m])
    np.testing.assert_allclose(r, ref, atol=1e-11)
    np.testing.assert_allclose(np.asarray(J.orthogonality_error(jnp.asarray(r))), 0.0, atol=1e-14)


def test_nearest_rotation_of_rotation_is_identity_map(rng):
    rs = np.stack([np_random_rotation(rng) for _ in range(50)] + [np_rot_axis_angle(AXES[3], PI), np.eye(3)])
    np.testing.assert_allclose(np.asarray(J.nearest_rotation(jnp.asarray(rs))), rs, atol=1e-14)


def test_nearest_rotation_is_optimal(rng):
    m = _random_matrices(rng, 10)
    cands = np.stack([np_random_rotation(rng) for _ in range(200)])
    r = np.asarray(J.nearest_rotation(jnp.asarray(m)))
    for mi, ri in zip(m, r):
        d_opt = np.linalg.norm(mi - ri)
        d_cands = np.linalg.norm(cands - mi, axis=(1, 2))
        assert d_opt <= d_cands.min() + 1e-12
        # also no better than small perturbations of the optimum (local optimality)
        for w in random_unit_vectors(rng, 20) * 1e-3:
            assert d_opt <= np.linalg.norm(mi - ri @ np_rot_axis_angle(w, np.linalg.norm(w))) + 1e-12


def test_polar_newton_matches_nearest_rotation(rng):
    ms = []
    while len(ms) < 200:
        r = np_random_rotation(rng)
        # symmetric positive stretch with singular values in [0.7, 1.22], plus random shapes
        scale = rng.uniform(0.0, 1.0)
        m = r @ (np.eye(3) + scale * 0.3 * rng.standard_normal((3, 3)))
        if np.linalg.norm(m.T @ m - np.eye(3)) <= 0.5 and np.linalg.det(m) > 0:
            ms.append(m)
    # boundary cases: singular values exactly at the edge of the region
    for s in [(np.sqrt(1.5), 1.0, 1.0), (np.sqrt(0.5), 1.0, 1.0), (np.sqrt(1 - 0.5 / np.sqrt(3)),) * 3]:
        u, v = np_random_rotation(rng), np_random_rotation(rng)
        m = u @ np.diag(s) @ v
        assert np.linalg.norm(m.T @ m - np.eye(3)) <= 0.5 + 1e-12
        ms.append(m)
    ms = np.stack(ms)
    got = np.asarray(J.polar_newton(jnp.asarray(ms)))
    np.testing.assert_allclose(got, np.asarray(J.nearest_rotation(jnp.asarray(ms))), atol=1e-12)
    np.testing.assert_allclose(got, np.stack([np_polar_rotation(m) for m in ms]), atol=1e-12)


# ----------------------------------------------------------------------------------------------------------
# Angles
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("theta", [0.0, 1e-8, 1e-3, 1.0, 3.0, PI - 1e-6])
def test_angle_error_known_angle(rng, theta):
    base = np.stack([np_random_rotation(rng) for _ in range(5)] + [np.eye(3)])
    for ax in AXES + list(random_unit_vectors(rng, 3)):
        e = np.asarray(J.exp(jnp.asarray(theta * ax)))
        ang = np.asarray(J.angle_error(jnp.asarray(base), jnp.asarray(base @ e)))
        np.testing.assert_allclose(ang, theta, rtol=1e-7, atol=1e-15)
        np.testing.assert_allclose(np.asarray(J.angle_of(jnp.asarray(e))), theta, rtol=1e-10, atol=1e-15)
        # symmetric in its arguments
        np.testing.assert_allclose(np.asarray(J.angle_error(jnp.asarray(base @ e), jnp.asarray(base))), ang, atol=1e-15)


def test_angle_of_exactly_pi_and_zero():
    for ax in AXES:
        np.testing.assert_allclose(float(J.angle_of(jnp.asarray(np_rot_axis_angle(ax, PI)))), PI, atol=1e-15)
    assert float(J.angle_of(jnp.eye(3))) == 0.0
    assert float(J.angle_of(jnp.diag(jnp.array([1.0, -1.0, -1.0])))) == PI


def test_angle_error_small_angle_relative_accuracy(rng):
    th = 1e-7
    for _ in range(20):
        r = np_random_rotation(rng)
        ax = random_unit_vectors(rng, 1)[0]
        r2 = r @ np_rot_axis_angle(ax, th)
        ang = float(J.angle_error(jnp.asarray(r), jnp.asarray(r2)))
        assert abs(ang - th) / th < 1e-6


# ----------------------------------------------------------------------------------------------------------
# Euler ZYX
# ----------------------------------------------------------------------------------------------------------
def np_rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def np_ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def np_rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_euler_zyx_matches_hand_built(rng):
    roll = rng.uniform(-PI, PI, 50)
    pitch = rng.uniform(-PI / 2, PI / 2, 50)
    yaw = rng.uniform(-PI, PI, 50)
    got = np.asarray(J.euler_zyx_to_matrix(jnp.asarray(roll), jnp.asarray(pitch), jnp.asarray(yaw)))
    ref = np.stack([np_rz(y) @ np_ry(p) @ np_rx(r) for r, p, y in zip(roll, pitch, yaw)])
    np.testing.assert_allclose(got, ref, atol=1e-15)
    # and the angles come back (pitch strictly inside (-pi/2, pi/2) here, so they are unique)
    eul = J.matrix_to_euler_zyx(jnp.asarray(ref))
    np.testing.assert_allclose(np.asarray(eul.roll), roll, atol=1e-12)
    np.testing.assert_allclose(np.asarray(eul.pitch), pitch, atol=1e-12)
    np.testing.assert_allclose(np.asarray(eul.yaw), yaw, atol=1e-12)


def test_euler_zyx_roundtrip_random(rng):
    rs = np.stack([np_random_rotation(rng) for _ in range(200)] + [np.eye(3), np_rx(PI), np_ry(PI), np_rz(PI)])
    eul = J.matrix_to_euler_zyx(jnp.asarray(rs))
    assert np.all(np.abs(np.asarray(eul.pitch)) <= PI / 2)
    back = np.asarray(J.euler_zyx_to_matrix(*eul))
    np.testing.assert_allclose(back, rs, atol=1e-13)


# ----------------------------------------------------------------------------------------------------------
# Gradients
# ----------------------------------------------------------------------------------------------------------
_W = np.array([[0.3, -1.2, 0.7], [0.5, 0.9, -0.4], [-1.1, 0.2, 0.8]])  # fixed weights for scalar objectives

# Rotation vectors at angle 0 and at / near pi
GRAD_PHIS = [np.zeros(3), 1e-9 * AXES[3], PI * AXES[0], PI * AXES[3], (PI - 1e-7) * AXES[4], (PI - 1e-4) * AXES[2]]


def _scalar_fns():
    w = jnp.asarray(_W)
    ref = jnp.asarray(np_rot_axis_angle(unit([1, -1, 2]), 0.4))
    return {
        "exp": lambda phi: jnp.sum(w * J.exp(phi)),
        "log": lambda phi: jnp.sum(jnp.asarray(_W[0]) * J.log(J.exp(phi))),
        "angle_of": lambda phi: J.angle_of(J.exp(phi)),
        "angle_error": lambda phi: J.angle_error(ref, ref @ J.exp(phi)),
        "angle_error_sq": lambda phi: J.angle_error(ref, ref @ J.exp(phi)) ** 2,
        "nearest_rotation": lambda phi: jnp.sum(w * J.nearest_rotation(J.exp(phi) + 0.1 * phi[0] * w)),
        "euler": lambda phi: sum(jnp.sum(a) for a in J.matrix_to_euler_zyx(J.exp(phi))),
        "quat": lambda phi: jnp.sum(jnp.asarray(_W[1][:3]) * J.matrix_to_quat(J.exp(phi))[1:]),
    }


@pytest.mark.parametrize("name", list(_scalar_fns()))
def test_gradients_finite_at_special_angles(name):
    f = _scalar_fns()[name]
    g = jax.jit(jax.grad(f))
    for phi in GRAD_PHIS:
        gv = np.asarray(g(jnp.asarray(phi)))
        assert np.all(np.isfinite(gv)), (name, phi, gv)


def test_gradients_at_matrix_inputs_finite():
    """Differentiate w.r.t. the matrix itself at identity and at rotations by pi (no NaN)."""
    w = jnp.asarray(_W)
    fns = [
        lambda r: jnp.sum(jnp.asarray(_W[0]) * J.log(r)),
        lambda r: J.angle_of(r),
        lambda r: J.angle_error(jnp.eye(3), r),
        lambda r: jnp.sum(w * J.nearest_rotation(r)),
        lambda r: sum(jnp.sum(a) for a in J.matrix_to_euler_zyx(r)),
    ]
    mats = [
        np.eye(3),
        np_rot_axis_angle(AXES[0], PI),
        np_rot_axis_angle(AXES[3], PI),
        np_rot_axis_angle(AXES[4], PI - 1e-6),
    ]
    mats = jnp.asarray(np.stack(mats))
    for f in fns:
        gv = np.asarray(jax.jit(jax.vmap(jax.grad(f)))(mats))
        assert np.all(np.isfinite(gv))


def test_gradient_of_exp_at_zero_is_skew_generators():
    jac = np.asarray(jax.jit(jax.jacfwd(J.exp))(jnp.zeros(3)))  # (3, 3, 3): d exp / d phi_k = S(e_k)
    for k in range(3):
        np.testing.assert_allclose(jac[..., k], np_skew(np.eye(3)[k]), atol=1e-15)


def test_gradient_of_angle_matches_analytic():
    # d/dtheta angle_of(exp(theta * axis)) = 1 for 0 < theta < pi
    g = jax.jit(jax.grad(lambda t, ax: J.angle_of(J.exp(t * ax))))
    for th in [1e-6, 0.5, 2.0, 3.1, PI - 1e-5]:
        for ax in AXES:
            d = float(g(th, jnp.asarray(ax)))
            assert abs(d - 1.0) < 1e-6, (th, ax, d)


@pytest.mark.parametrize("fname", ["exp", "log", "nearest_rotation", "angle_error", "euler", "quat"])
def test_jacfwd_equals_jacrev(fname):
    ref = jnp.asarray(np_rot_axis_angle(unit([1, -1, 2]), 0.4))
    w = jnp.asarray(_W)
    vec_fns = {
        "exp": J.exp,
        "log": lambda phi: J.log(J.exp(phi)),
        "nearest_rotation": lambda phi: J.nearest_rotation(J.exp(phi) + 0.1 * phi[0] * w),
        "angle_error": lambda phi: J.angle_error(ref, ref @ J.exp(phi)),
        "euler": lambda phi: jnp.stack(J.matrix_to_euler_zyx(J.exp(phi))),
        "quat": lambda phi: J.quat_canonical(J.matrix_to_quat(J.exp(phi))),
    }
    f = vec_fns[fname]
    pts = [np.array([0.3, -0.2, 0.5]), (PI - 1e-3) * AXES[3], 2.0 * AXES[4]]
    if fname in ("exp", "nearest_rotation", "euler"):
        pts += [np.zeros(3), PI * AXES[3]]
    jacf, jacr = jax.jit(jax.jacfwd(f)), jax.jit(jax.jacrev(f))
    for phi in pts:
        jf = np.asarray(jacf(jnp.asarray(phi)))
        jr = np.asarray(jacr(jnp.asarray(phi)))
        assert np.all(np.isfinite(jf))
        np.testing.assert_allclose(jf, jr, atol=1e-12, rtol=1e-12)


def _central_fd(f, x, h=1e-6):
    x = np.asarray(x, float)
    cols = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e.flat[i] = h
        cols.append((np.asarray(f(jnp.asarray(x + e))) - np.asarray(f(jnp.asarray(x - e)))) / (2 * h))
    return np.stack(cols, axis=-1).reshape(np.shape(f(jnp.asarray(x))) + x.shape)


def test_nearest_rotation_derivative_matches_finite_differences(rng):
    mats = [np_random_rotation(rng) for _ in range(3)] + [np.eye(3), np_rot_axis_angle(AXES[3], PI)]
    # also a generic non-rotation with det > 0 and one with det < 0
    mats += [np_random_rotation(rng) @ np.diag([1.3, 0.9, 0.6]) @ np_random_rotation(rng)]
    mats += [np_random_rotation(rng) @ np.diag([1.3, 0.9, -0.6]) @ np_random_rotation(rng)]
    jacf = jax.jit(jax.jacfwd(J.nearest_rotation))
    jacr = jax.jit(jax.jacrev(J.nearest_rotation))
    nr = jax.jit(J.nearest_rotation)
    for m in mats:
        jac = np.asarray(jacf(jnp.asarray(m)))  # (3,3,3,3)
        fd = _central_fd(nr, m)
        np.testing.assert_allclose(jac, fd, atol=1e-8)
        jr = np.asarray(jacr(jnp.asarray(m)))
        np.testing.assert_allclose(jr, jac, atol=1e-12)
    # polar_newton's derivative (the polar factor's, so3.polar_tangent) against central differences of the
    # Newton iteration's own values, where it converges (det > 0): rotations and a generic matrix
    pn = jax.jit(so3.polar_newton)
    for m in mats[:4] + [mats[-2]]:
        jac = np.asarray(jax.jacfwd(so3.polar_newton)(jnp.asarray(m)))
        np.testing.assert_allclose(jac, _central_fd(pn, m), atol=1e-8)
        np.testing.assert_allclose(np.asarray(jax.jacrev(so3.polar_newton)(jnp.asarray(m))), jac, atol=1e-12)


def test_exp_log_derivatives_match_finite_differences():
    jexp = jax.jit(jax.jacfwd(J.exp))
    jlog = jax.jit(jax.jacfwd(lambda p: J.log(J.exp(p))))  # identity map: jacobian = I
    expj = jax.jit(J.exp)
    for phi in [np.array([0.3, -0.2, 0.5]), 2.5 * AXES[4], 1e-3 * AXES[3]]:
        np.testing.assert_allclose(np.asarray(jexp(jnp.asarray(phi))), _central_fd(expj, phi), atol=1e-8)
        np.testing.assert_allclose(np.asarray(jlog(jnp.asarray(phi))), np.eye(3), atol=1e-12)


# ----------------------------------------------------------------------------------------------------------
# vmap / jit / broadcasting
# ----------------------------------------------------------------------------------------------------------
_euler_stack = jax.jit(lambda x: jnp.stack(so3.matrix_to_euler_zyx(x), -1))
_euler_inv = jax.jit(lambda x: so3.euler_zyx_to_matrix(x[..., 0], x[..., 1], x[..., 2]))
_BATCH_FNS = {
    # name: (function, builder of its arguments from (phi, q, m, r))
    "exp": ("exp", lambda phi, q, m, r: (phi,)),
    "log": ("log", lambda phi, q, m, r: (r,)),
    "skew": ("skew", lambda phi, q, m, r: (phi,)),
    "vex": ("vex", lambda phi, q, m, r: (m,)),
    "quat_to_matrix": ("quat_to_matrix", lambda phi, q, m, r: (q,)),
    "matrix_to_quat": ("matrix_to_quat", lambda phi, q, m, r: (r,)),
    "quat_multiply": ("quat_multiply", lambda phi, q, m, r: (q, 2.0 * q[..., ::-1])),
    "nearest_rotation": ("nearest_rotation", lambda phi, q, m, r: (m,)),
    "angle_of": ("angle_of", lambda phi, q, m, r: (r,)),
    "angle_error": ("angle_error", lambda phi, q, m, r: (r, J.exp(0.5 * phi))),
    "orthogonality_error": ("orthogonality_error", lambda phi, q, m, r: (m,)),
    "det3": ("det3", lambda phi, q, m, r: (m,)),
    "euler": (_euler_stack, lambda phi, q, m, r: (r,)),
    "euler_inv": (_euler_inv, lambda phi, q, m, r: (phi,)),
}
_VMAPPED = {}


@pytest.mark.parametrize("shape", [(5,), (2, 3)])
def test_batched_shapes_equal_per_element(rng, shape):
    n = int(np.prod(shape))
    phi = rng.standard_normal(shape + (3,)) * 1.5
    phi.reshape(-1, 3)[0] = 0.0
    phi.reshape(-1, 3)[1] = PI * AXES[3]
    q = rng.standard_normal(shape + (4,))
    m = rng.standard_normal(shape + (3, 3))
    pj, qj, mj = jnp.asarray(phi), jnp.asarray(q), jnp.asarray(m)
    r = J.exp(pj)
    for name, (fn, build) in _BATCH_FNS.items():
        f = getattr(J, fn) if isinstance(fn, str) else fn  # jitted; shared compiles across tests
        args = build(pj, qj, mj, r)
        out = np.asarray(f(*args))  # broadcasting over leading axes
        assert out.shape[: len(shape)] == shape, name
        flat_args = [np.asarray(a).reshape((n,) + a.shape[len(shape) :]) for a in args]
        per = np.stack([np.asarray(f(*[jnp.asarray(a[i]) for a in flat_args])) for i in range(n)])
        np.testing.assert_allclose(out.reshape(per.shape), per, atol=1e-13, err_msg=name)
        # jax.vmap over the flattened batch gives the same as broadcasting
        if name not in _VMAPPED:
            _VMAPPED[name] = jax.jit(jax.vmap(f))
        vm = np.asarray(_VMAPPED[name](*[jnp.asarray(a) for a in flat_args]))
        np.testing.assert_allclose(vm, per, atol=1e-13, err_msg=name)


def test_vmap_of_grad(rng):
    phi = jnp.asarray(rng.standard_normal((5, 3)))
    g = jax.jit(jax.vmap(jax.grad(lambda p: J.angle_of(J.exp(p)))))(phi)
    # d|phi|/dphi = phi/|phi| for |phi| < pi
    phi_np = np.asarray(phi)
    norms = np.linalg.norm(phi_np, axis=1)
    wrapped = norms > PI
    expect = phi_np / norms[:, None] * np.where(wrapped, -1.0, 1.0)[:, None]
    np.testing.assert_allclose(np.asarray(g), expect, atol=1e-12)


def test_triad_recovers_the_rotation_and_stays_a_rotation_on_degenerate_samples(rng):
    """TRIAD gives back R (sensor to ENU) from a = R^T up, m = R^T m_enu; a zero accelerometer, or a magnetometer
    that is zero or parallel to up, still gives a rotation (det 1) whose up row is a / |a| (the heading is then
    arbitrary): the starts of the recorded-data observers never leave SO(3)."""
    up, field = np.array([0.0, 0.0, 9.81]), np.array([0.0, 20.0, -44.0])  # ENU: field north and down
    for _ in range(10):
        r = np.asarray(so3.exp(jnp.asarray(rng.normal(size=3) * 1.5)))
        np.testing.assert_allclose(
            np.asarray(so3.triad(jnp.asarray(r.T @ up), jnp.asarray(r.T @ field))), r, atol=1e-12
        )
    a = rng.normal(size=3) * 5
    cases = [(a, np.zeros(3)), (a, 3.0 * a), (a, -a), (np.zeros(3), field), (np.zeros(3), np.zeros(3))]
    for acc, mag in cases:
        for dtype in (jnp.float32, jnp.float64):
            m = np.asarray(so3.triad(jnp.asarray(acc, dtype), jnp.asarray(mag, dtype)), np.float64)
            tol = 1e-6 if dtype == jnp.float32 else 1e-12
            np.testing.assert_allclose(m @ m.T, np.eye(3), atol=tol)
            assert abs(np.linalg.det(m) - 1.0) < tol
            want_up = acc / np.linalg.norm(acc) if np.any(acc) else np.array([0.0, 0.0, 1.0])
            np.testing.assert_allclose(m[2], want_up, atol=tol)
    batch = so3.triad(jnp.asarray(np.stack([a, a])), jnp.asarray(np.stack([a, np.zeros(3)])))
    assert batch.shape == (2, 3, 3)


_Q3, _V4, _M23 = np.zeros(3), np.zeros(4), np.zeros((2, 3))
_EYE, _Q1 = np.eye(3), np.array([1.0, 0.0, 0.0, 0.0])


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda: so3.quat_to_matrix(_Q3), r"quat_to_matrix: q must have shape \(\.\.\., 4\), got \(3,\)"),
        (lambda: so3.quat_multiply(_Q1, _Q3), r"quat_multiply: q must have shape \(\.\.\., 4\), got \(3,\)"),
        (lambda: so3.quat_conjugate(np.zeros(5)), r"quat_conjugate: q must have shape \(\.\.\., 4\)"),
        (lambda: so3.quat_canonical(_Q3), r"quat_canonical: q must have shape \(\.\.\., 4\)"),
        (lambda: so3.matrix_to_quat(_M23), r"matrix_to_quat: r must have shape \(\.\.\., 3, 3\), got \(2, 3\)"),
        (lambda: so3.log(_M23), r"log: r must have shape \(\.\.\., 3, 3\), got \(2, 3\)"),
        (lambda: so3.exp(_V4), r"exp: phi must have shape \(\.\.\., 3\), got \(4,\)"),
        (lambda: so3.skew(_V4), r"skew: x must have shape \(\.\.\., 3\), got \(4,\)"),
        (lambda: so3.vex(_M23), r"vex: m must have shape \(\.\.\., 3, 3\)"),
        (lambda: so3.cross(_V4, _V4), r"cross: a must have shape \(\.\.\., 3\), got \(4,\)"),
        (lambda: so3.mm(_EYE, _M23), r"mm: a \(\.\.\., n, k\) and b \(\.\.\., k, m\) must agree in k"),
        (lambda: so3.mv(_EYE, _V4), r"mv: a \(\.\.\., n, k\) and v \(\.\.\., k\) must agree in k"),
        (lambda: so3.mv(_EYE, 1.0), r"mv: v must have shape \(\.\.\., n\), got \(\)"),
        (lambda: so3.nearest_rotation(_M23), r"nearest_rotation: m must have shape \(\.\.\., 3, 3\)"),
        (lambda: so3.polar_newton(_M23), r"polar_newton: m must have shape \(\.\.\., 3, 3\)"),
        (lambda: so3.det3(_M23), r"det3: r must have shape \(\.\.\., 3, 3\)"),
        (lambda: so3.cofactor(_M23), r"cofactor: m must have shape \(\.\.\., 3, 3\)"),
        (lambda: so3.orthogonality_error(_M23), r"orthogonality_error: r must have shape"),
        (lambda: so3.angle_of(_M23), r"angle_of: e must have shape"),
        (lambda: so3.angle_error(_EYE, _M23), r"angle_error: r_est must have shape"),
        (lambda: so3.matrix_to_euler_zyx(_M23), r"matrix_to_euler_zyx: r must have shape"),
        (lambda: so3.euler_error_zyx(_M23, _EYE), r"euler_error_zyx: r_true must have shape"),
        (lambda: so3.triad(_V4, _Q3), r"triad: acc must have shape \(\.\.\., 3\), got \(4,\)"),
        (lambda: so3.triad(_Q3, _Q3, frame="XYZ"), r"frame must be one of ENU, NED, NWU, got 'XYZ'"),
        (lambda: so3.unit(1.0), r"unit: v must have shape \(\.\.\., n\), got \(\)"),
        (lambda: so3.quat_multiply_parts((1.0, 0.0, 0.0), tuple(_Q1)), r"quat_multiply_parts: p must be 4 arrays"),
    ],
)
def test_wrong_shapes_are_refused_in_one_line(call, match):
    """A quaternion of length 3, a (2, 3) matrix, a 4-vector for a 3-vector: refused naming the argument (they
    gave a shape error deep in jax, or a silently wrong broadcast result: mv of a 3x3 and a length-1 vector)."""
    with pytest.raises(ValueError, match=match):
        call()


def test_shape_checks_under_jit_and_vmap_and_batches():
    """The checks read static shapes: they pass batched and traced inputs and refuse inside jit / vmap too."""
    q = jnp.asarray(np.tile(_Q1, (2, 5, 1)))
    assert jax.jit(so3.quat_to_matrix)(q).shape == (2, 5, 3, 3)
    assert jax.vmap(jax.vmap(so3.quat_to_matrix))(q).shape == (2, 5, 3, 3)
    assert jax.jit(jax.vmap(so3.log))(jnp.tile(jnp.eye(3), (4, 1, 1))).shape == (4, 3)
    assert so3.quat_multiply_parts(jnp.asarray(_Q1), tuple(_Q1))[0] == 1.0  # a (4,) array is 4 rows
    with pytest.raises(ValueError, match=r"exp: phi must have shape \(\.\.\., 3\), got \(4,\)"):
        jax.jit(so3.exp)(jnp.zeros(4))
    with pytest.raises(ValueError, match=r"quat_to_matrix: q must have shape \(\.\.\., 4\), got \(3,\)"):
        jax.vmap(so3.quat_to_matrix)(jnp.zeros((7, 3)))


def test_integer_inputs_are_promoted_to_float():
    """exp and angle_of of integer arrays failed deep in jnp.finfo ("not inexact"); they take the default float."""
    r = so3.exp(jnp.array([0, 0, 1]))
    assert jnp.issubdtype(r.dtype, jnp.floating)
    np.testing.assert_allclose(np.asarray(r), np.asarray(so3.exp(jnp.array([0.0, 0.0, 1.0]))), atol=1e-15)
    assert float(so3.angle_of(jnp.eye(3, dtype=int))) == 0.0
    assert float(so3.angle_error(jnp.eye(3, dtype=int), jnp.diag(jnp.array([1, -1, -1])))) == pytest.approx(PI)


def test_first_present_at_start_carries_the_reading_back_by_the_gyro():
    """A sensor turning at a constant rate (exact under the per-step exponentials): the first present reading j,
    carried back to row 0 by the gyro, is the reading row 0 would have had; a present row 0 is kept; no present
    reading gives zeros; NaN gyro rows turn by nothing."""
    n, j, dt = 50, 30, 0.01
    w = np.array([0.3, -0.7, 1.1])  # rad/s, body
    m_nav = np.array([0.2, 20.0, -40.0])
    r = [np.eye(3)]
    for _ in range(n - 1):
        r.append(r[-1] @ np.asarray(so3.exp(jnp.asarray(w * dt, jnp.float64))))
    body = np.stack([rk.T @ m_nav for rk in r])  # v_body(k) = R_nb(k)^T v_nav
    gyr = np.tile(w, (n, 1))
    a = body.copy()
    a[:j] = np.nan
    got = np.asarray(so3.first_present_at_start(jnp.asarray(a), jnp.asarray(gyr), dt))
    np.testing.assert_allclose(got[0], body[0], rtol=0, atol=1e-10)
    np.testing.assert_array_equal(got[1:], a[1:])
    np.testing.assert_array_equal(np.asarray(so3.first_present_at_start(jnp.asarray(body), jnp.asarray(gyr), dt)), body)
    none = np.asarray(so3.first_present_at_start(jnp.asarray(np.full((n, 3), np.nan)), jnp.asarray(gyr), dt))
    np.testing.assert_array_equal(none[0], 0.0)
    g3, g0 = gyr.copy(), gyr.copy()
    g3[5], g0[5] = np.nan, 0.0  # a NaN gyro row before j turns by nothing
    with_nan, with_zero = (np.asarray(so3.first_present_at_start(a, g, dt))[0] for g in (g3, g0))
    np.testing.assert_array_equal(with_nan, with_zero)
    counts = np.round(np.where(np.isnan(a), 0, a) * 100).astype(np.int32)  # raw counts (zero rows: missing)
    assert np.all(np.isfinite(np.asarray(so3.first_present_at_start(counts, gyr, dt))))
    g2 = gyr.copy()
    g2[j + 1 :] = np.nan  # after j: not used
    np.testing.assert_allclose(np.asarray(so3.first_present_at_start(jnp.asarray(a), jnp.asarray(g2), dt))[0],
                               body[0], atol=1e-10)  # fmt: skip
