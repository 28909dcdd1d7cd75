"""SO(3) algebra, written once for every observer.

Conventions (used across jaxatt):

* A rotation matrix ``R`` maps body/sensor coordinates to the reference frame: ``v_ref = R @ v_body``.
* Quaternions are Hamilton, scalar first ``(w, x, y, z)``, shape ``(..., 4)``, and describe the same
  body-to-reference rotation as ``R``.
* ``skew(x) @ y == cross(x, y)`` (the papers' ``S(x)``).
* Angles are in radians; only reports use degrees.

Every function broadcasts over leading axes and is safe under ``jit``, ``vmap`` and ``grad``: branches at
angle 0 and angle pi use the "double where" trick so that no NaN reaches a gradient (Euler angles excepted at
gimbal lock, where they are not defined).

Each public function checks the shapes of its arguments (ValueError naming the argument): a static check that
runs once when a jitted function is traced, so it costs nothing inside an observer's compiled step.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .types import check_shape

__all__ = [
    "skew",
    "vex",
    "mm",
    "mv",
    "exp",
    "log",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_multiply",
    "quat_conjugate",
    "quat_canonical",
    "quat_exp",
    "quat_log",
    "nearest_rotation",
    "polar_newton",
    "polar_tangent",
    "orthogonality_error",
    "angle_error",
    "angle_of",
    "EulerZYX",
    "matrix_to_euler_zyx",
    "euler_zyx_to_matrix",
    "cross",
    "det3",
    "cofactor",
    "wrap_angle",
    "euler_error_zyx",
    "triad",
    "unit",
    "quat_multiply_parts",
]


# --------------------------------------------------------------------------------------------------------
# Small helpers. Tiny 3x3 products written as broadcast multiply + sum: under vmap, XLA fuses them into one
# elementwise loop, which is much faster on CPU than a batch of 3x3 dot calls.
# --------------------------------------------------------------------------------------------------------
def present(v: jax.Array) -> jax.Array:
    """(...) True where a vector sensor's reading (..., 3) is present: finite and not all zero. A NaN or an
    all-zero row marks a missing accelerometer / magnetometer reading everywhere in jaxatt (loggers write zeros
    for a sensor they lack; the C filters BROAD runs read zero as missing). Not for the gyro, whose zero reading
    (no rotation) is real."""
    return jnp.all(jnp.isfinite(v), axis=-1) & jnp.any(v != 0, axis=-1)


def first_present_at_start(a, gyr, dt, length=None) -> jax.Array:
    """``a`` (T, 3), a vector sensor's readings in the body (sensor) frame, with a missing row 0 (:func:`present`)
    replaced by the first present reading j carried back to row 0's body frame by the gyro: R_0j a_j with
    R_0j = exp(S(gyr_1 dt_1)) ... exp(S(gyr_j dt_j)) (gyr (T, 3) rad/s, body; step k turns by gyr_k over dt_k,
    hold "next"; ``dt`` s, a number or (T,) with dt[0] unused; a non-finite gyro row turns by nothing). Zeros when
    no row within the first ``length`` is present; ``a`` unchanged when row 0 is. An observer set up from its first
    sample (TRIAD) then starts from a consistent pair of readings, off by the gyro's drift over t_j - t_0 (the
    reading itself, uncarried, is off by every turn in between)."""
    a = jnp.asarray(a)
    if not jnp.issubdtype(a.dtype, jnp.floating):  # raw counts
        a = a.astype(jnp.result_type(float))
    n = a.shape[0]
    ok = present(a) & (jnp.arange(n) < (n if length is None else length))
    j = jnp.where(jnp.any(ok), jnp.argmax(ok), 0)
    g = jnp.where(jnp.all(jnp.isfinite(gyr), axis=-1, keepdims=True), gyr, 0.0).astype(a.dtype)
    steps = jnp.broadcast_to(jnp.asarray(dt, a.dtype), (n,))

    def turn(kr):  # steps 1 ... j only: none when row 0 is present (a while loop, not a scan over the recording)
        k, r = kr
        return k + 1, mm(r, exp(g[k] * steps[k]))

    _, r0j = jax.lax.while_loop(lambda kr: kr[0] <= j, turn, (jnp.asarray(1, j.dtype), jnp.eye(3, dtype=a.dtype)))
    first = jnp.where(jnp.any(ok), mv(r0j, a[j]), jnp.zeros_like(a[0]))
    return a.at[0].set(jnp.where(ok[0], a[0], first))


def mm(a: jax.Array, b: jax.Array) -> jax.Array:
    """Matrix product of (..., n, k) and (..., k, m) arrays as a fused broadcast-sum (for tiny matrices)."""
    sa, sb = check_shape(a, "mm: a", (None, None)), check_shape(b, "mm: b", (None, None))
    if sa[-1] != sb[-2]:
        raise ValueError(f"mm: a (..., n, k) and b (..., k, m) must agree in k, got shapes {sa} and {sb}")
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def mv(a: jax.Array, v: jax.Array) -> jax.Array:
    """Matrix-vector product of (..., n, k) and (..., k) arrays as a fused broadcast-sum."""
    sa, sv = check_shape(a, "mv: a", (None, None)), check_shape(v, "mv: v", (None,))
    if sa[-1] != sv[-1]:
        raise ValueError(f"mv: a (..., n, k) and v (..., k) must agree in k, got shapes {sa} and {sv}")
    return jnp.sum(a * v[..., None, :], axis=-1)


def _as_float(x) -> jax.Array:
    """``x`` as a jax array of an inexact dtype: integers and bools become the default float (float32, or float64
    with x64 on), as ``jnp.asarray(x, float)``; float and complex dtypes are kept."""
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.inexact) else x.astype(jnp.result_type(float))


#: Levi-Civita symbol: (a x b)_i = eps_ijk a_j b_k and S(x)_ik = eps_ijk x_j.
_LEVI_CIVITA = np.zeros((3, 3, 3))
_LEVI_CIVITA[0, 1, 2] = _LEVI_CIVITA[1, 2, 0] = _LEVI_CIVITA[2, 0, 1] = 1.0
_LEVI_CIVITA[0, 2, 1] = _LEVI_CIVITA[2, 1, 0] = _LEVI_CIVITA[1, 0, 2] = -1.0


def cross(a: jax.Array, b: jax.Array) -> jax.Array:
    """Cross product a x b over the last axis, as a contraction with the Levi-Civita symbol: the component formula
    to one rounding per component (the other terms are exact zeros; XLA may fuse a product into the sum), and its
    derivative is a broadcast and a sum where the component formula's is slices, a stack and their pads: reverse
    mode through an observer's step compiles to about half the program (batista-so3's scan: 8.6 -> 3.6 s)."""
    check_shape(a, "cross: a", (3,))
    check_shape(b, "cross: b", (3,))
    e = jnp.asarray(_LEVI_CIVITA, jnp.result_type(a, b))
    return jnp.sum(e * a[..., None, :, None] * b[..., None, None, :], axis=(-2, -1))


def skew(x: jax.Array) -> jax.Array:
    """Skew-symmetric matrix S(x), shape (..., 3, 3), with S(x) y = x x y (a Levi-Civita contraction, like
    :func:`cross`)."""
    check_shape(x, "skew: x", (3,))
    x = jnp.asarray(x)
    return jnp.sum(jnp.asarray(_LEVI_CIVITA, x.dtype) * x[..., None, :, None], axis=-2)


def vex(m: jax.Array) -> jax.Array:
    """Inverse of :func:`skew` applied to the skew part of ``m``: vex((M - M^T)/2), shape (..., 3)."""
    check_shape(m, "vex: m", (3, 3))
    return 0.5 * jnp.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], axis=-1
    )


def _what(x) -> str:
    if isinstance(x, (tuple, list)):
        return f"{len(x)} items"
    return f"shape {tuple(x.shape)}" if hasattr(x, "shape") else type(x).__name__


def _safe_norm(x: jax.Array, eps: float) -> tuple[jax.Array, jax.Array]:
    """(norm, small) with a gradient-safe norm: where ``small`` the returned norm is 1 (caller branches)."""
    sq = jnp.sum(x * x, axis=-1)
    small = sq < eps * eps
    return jnp.sqrt(jnp.where(small, 1.0, sq)), small


def _tiny(dtype) -> float:
    return float(jnp.finfo(dtype).eps) ** 0.5


# --------------------------------------------------------------------------------------------------------
# Exponential and logarithm
# --------------------------------------------------------------------------------------------------------
def exp(phi: jax.Array) -> jax.Array:
    """Rotation matrix exp(S(phi)) for a rotation vector ``phi`` (rad, shape (..., 3)), Rodrigues' formula."""
    check_shape(phi, "exp: phi", (3,))
    phi = _as_float(phi)
    th2 = jnp.sum(phi * phi, axis=-1)
    small = th2 < _tiny(phi.dtype) ** 2 * 100
    th2_safe = jnp.where(small, 1.0, th2)
    th = jnp.sqrt(th2_safe)
    a = jnp.where(small, 1.0 - th2 / 6.0, jnp.sin(th) / th)
    # (1 - cos th) / th^2 written as 2 sin^2(th/2) / th^2: no cancellation (in float32, 1 - cos th loses ~2 % at
    # th ~ 2e-3 rad, which made R exp(S(phi)) drift off SO(3) by ~4e-8 per step).
    sh = jnp.sin(0.5 * th) / th
    b = jnp.where(small, 0.5 - th2 / 24.0, 2.0 * sh * sh)
    s = skew(phi)
    eye = jnp.eye(3, dtype=phi.dtype)
    return eye + a[..., None, None] * s + b[..., None, None] * mm(s, s)


def reorthonormalize(r: jax.Array) -> jax.Array:
    """One Newton-Schulz step R (3I - R^T R) / 2 towards the nearest rotation: an identity on SO(3), it removes
    the rounding drift that accumulates when a rotation is updated step after step (error e -> O(e^2))."""
    check_shape(r, "reorthonormalize: r", (3, 3))
    return mm(r, 1.5 * jnp.eye(3, dtype=r.dtype) - 0.5 * mm(jnp.swapaxes(r, -1, -2), r))


def log(r: jax.Array) -> jax.Array:
    """Rotation vector (rad, shape (..., 3)) of a rotation matrix (..., 3, 3), angle in [0, pi]; exact near 0 and
    pi."""
    check_shape(r, "log: r", (3, 3))
    return 2.0 * _quat_log_half(quat_canonical(matrix_to_quat(r)))


def _quat_log_half(q: jax.Array) -> jax.Array:
    """Half rotation vector of a unit quaternion with w >= 0: axis * angle / 2."""
    w, v = q[..., 0], q[..., 1:]
    n, small = _safe_norm(v, _tiny(q.dtype))
    # atan2(n, w)/n with the Taylor series 1/w (1 - n^2/(3 w^2)) near n = 0 (w ~ 1 there).
    ratio = jnp.where(small, (1.0 - jnp.sum(v * v, -1) / 3.0) / jnp.where(small, w, 1.0), jnp.arctan2(n, w) / n)
    return ratio[..., None] * v


# --------------------------------------------------------------------------------------------------------
# Quaternions (w, x, y, z), Hamilton product
# --------------------------------------------------------------------------------------------------------
def quat_to_matrix(q: jax.Array) -> jax.Array:
    """Rotation matrix (..., 3, 3) of a quaternion (..., 4) (w, x, y, z); the quaternion is normalised first."""
    check_shape(q, "quat_to_matrix: q", (4,))
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def matrix_to_quat(r: jax.Array) -> jax.Array:
    """Unit quaternion (..., 4) (w, x, y, z) of a rotation matrix (..., 3, 3) (Shepperd's method; sign is
    arbitrary)."""
    check_shape(r, "matrix_to_quat: r", (3, 3))
    m00, m01, m02 = r[..., 0, 0], r[..., 0, 1], r[..., 0, 2]
    m10, m11, m12 = r[..., 1, 0], r[..., 1, 1], r[..., 1, 2]
    m20, m21, m22 = r[..., 2, 0], r[..., 2, 1], r[..., 2, 2]
    tr = m00 + m11 + m22
    # Four candidate formulas; each is well-conditioned when its pivot is the largest.
    piv = jnp.stack([tr, m00, m11, m22], axis=-1)
    k = jnp.argmax(piv, axis=-1)
    s0 = 1.0 + tr
    s1 = 1.0 + m00 - m11 - m22
    s2 = 1.0 - m00 + m11 - m22
    s3 = 1.0 - m00 - m11 + m22
    cand = jnp.stack(
        [
            jnp.stack([s0, m21 - m12, m02 - m20, m10 - m01], -1),
            jnp.stack([m21 - m12, s1, m01 + m10, m02 + m20], -1),
            jnp.stack([m02 - m20, m01 + m10, s2, m12 + m21], -1),
            jnp.stack([m10 - m01, m02 + m20, m12 + m21, s3], -1),
        ],
        axis=-2,
    )  # (..., 4 candidates, 4)
    s = jnp.stack([s0, s1, s2, s3], axis=-1)
    s_safe = jnp.where(s > 0.1, s, 1.0)  # the chosen pivot always has s >= 1
    scaled = cand * (0.5 / jnp.sqrt(s_safe))[..., None]
    return jnp.take_along_axis(scaled, k[..., None, None], axis=-2)[..., 0, :]


def quat_multiply(p: jax.Array, q: jax.Array) -> jax.Array:
    """Hamilton product p * q of (..., 4) (w, x, y, z) quaternions (rotation p after... i.e. R(p) @ R(q))."""
    check_shape(p, "quat_multiply: p", (4,))
    check_shape(q, "quat_multiply: q", (4,))
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    w = pw * qw - jnp.sum(pv * qv, -1, keepdims=True)
    v = pw * qv + qw * pv + cross(pv, qv)
    return jnp.concatenate([w, v], axis=-1)


def quat_multiply_parts(p: tuple, q: tuple) -> tuple:
    """Hamilton product p (x) q of quaternions given as 4-tuples of component arrays (w, x, y, z): the form the
    elementwise filters use (a tuple of arrays fuses better on CPU than one stacked array). An array of shape
    (4, ...) is taken as its 4 rows."""
    for name, x in (("p", p), ("q", q)):
        n = len(x) if isinstance(x, (tuple, list)) else (getattr(x, "shape", ()) or (None,))[0]
        if n != 4:
            raise ValueError(f"quat_multiply_parts: {name} must be 4 arrays (w, x, y, z), got {_what(x)}")
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    )


def quat_conjugate(q: jax.Array) -> jax.Array:
    """Conjugate (inverse for unit quaternions) of (..., 4) (w, x, y, z) quaternions."""
    check_shape(q, "quat_conjugate: q", (4,))
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def quat_canonical(q: jax.Array) -> jax.Array:
    """The representative of +-q with w >= 0, for (..., 4) (w, x, y, z) quaternions."""
    check_shape(q, "quat_canonical: q", (4,))
    return jnp.where(q[..., :1] < 0, -q, q)


def quat_exp(v: jax.Array) -> jax.Array:
    """Unit quaternion (w, x, y, z) of a rotation vector v (..., 3) (rad): [cos(|v|/2), sin(|v|/2) v/|v|];
    gradient-safe at 0."""
    th2 = jnp.sum(v * v, axis=-1)
    small = th2 < 1e-12
    th = jnp.sqrt(jnp.where(small, 1.0, th2))
    half = 0.5 * th
    c = jnp.where(small, 1.0 - th2 / 8.0, jnp.cos(half))
    s = jnp.where(small, 0.5 - th2 / 48.0, jnp.sin(half) / th)
    return jnp.concatenate([c[..., None], s[..., None] * v], axis=-1)


def quat_log(q: jax.Array) -> jax.Array:
    """Rotation vector (..., 3) (rad, angle in [0, pi]) of a unit quaternion (w, x, y, z) (either sign)."""
    return 2.0 * _quat_log_half(quat_canonical(q))


# --------------------------------------------------------------------------------------------------------
# Projection onto SO(3)
# --------------------------------------------------------------------------------------------------------
@jax.custom_jvp
def nearest_rotation(m: jax.Array) -> jax.Array:
    """The rotation closest to ``m`` in the Frobenius norm: U diag(1, 1, det(U V^T)) V^T from the SVD.

    Works for any 3x3 matrix (also det(m) < 0, where the smallest singular direction is flipped). The
    derivative is the polar-decomposition derivative, finite at rotations (where the SVD's own derivative
    divides by zero between equal singular values).
    """
    check_shape(m, "nearest_rotation: m", (3, 3))
    u, _, vt = jnp.linalg.svd(m)
    d = jnp.sign(det3(mm(u, vt)))
    u = u.at[..., :, 2].multiply(d[..., None])
    return mm(u, vt)


@nearest_rotation.defjvp
def _nearest_rotation_jvp(primals, tangents):
    (m,), (dm,) = primals, tangents
    r = nearest_rotation(m)
    return r, polar_tangent(r, m, dm)


def polar_tangent(r: jax.Array, m: jax.Array, dm: jax.Array) -> jax.Array:
    """Derivative of the orthogonal polar factor ``r`` of ``m`` (m = r h, h symmetric positive definite) along
    ``dm``: d r = r S(w) with (tr(h) I - h) w = 2 vex(r^T dm). Finite at rotations, where the SVD's own
    derivative divides by zero between equal singular values; the 3x3 solve is written out (cofactors), so it
    fuses into the step of an observer."""
    for name, x in (("r", r), ("m", m), ("dm", dm)):
        check_shape(x, f"polar_tangent: {name}", (3, 3))
    h = mm(jnp.swapaxes(r, -1, -2), m)
    h = 0.5 * (h + jnp.swapaxes(h, -1, -2))
    a = jnp.trace(h, axis1=-2, axis2=-1)[..., None, None] * jnp.eye(3, dtype=m.dtype) - h
    rhs = 2.0 * vex(mm(jnp.swapaxes(r, -1, -2), dm))
    w = mv(cofactor(a), rhs) / det3(a)[..., None]  # a symmetric: a^-1 = cofactor(a) / det(a)
    return mm(r, skew(w))


def cofactor(m: jax.Array) -> jax.Array:
    """Cofactor matrix of (..., 3, 3) arrays: rows r2 x r3, r3 x r1, r1 x r2 (so m^-T = cofactor / det)."""
    check_shape(m, "cofactor: m", (3, 3))
    r1, r2, r3 = m[..., 0, :], m[..., 1, :], m[..., 2, :]
    return jnp.stack([cross(r2, r3), cross(r3, r1), cross(r1, r2)], axis=-2)


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def polar_newton(m: jax.Array, iterations: int = 5) -> jax.Array:
    """Orthogonal polar factor of a non-singular ``m`` by Newton's iteration X <- (X + X^-T) / 2.

    X^-T is the cofactor matrix over the determinant (three cross products), so an iteration costs about a
    third of a 3x3 product. Singular values map as s -> (s + 1/s)/2: quadratic convergence, five iterations
    reach float64 rounding for singular values in [0.7, 1.3] (||m^T m - I||_F <= 0.5, the projection region
    of Theorem 3 in batista2019-ges). Equals :func:`nearest_rotation` when det(m) > 0. Its derivative is the
    polar factor's (:func:`polar_tangent`), not the iteration's: the same where the iteration has converged,
    and a gradient then keeps no intermediate of the iterations.
    """
    check_shape(m, "polar_newton: m", (3, 3))
    x = m
    for _ in range(iterations):
        x = 0.5 * (x + cofactor(x) / det3(x)[..., None, None])
    return x


@polar_newton.defjvp
def _polar_newton_jvp(iterations, primals, tangents):
    (m,), (dm,) = primals, tangents
    r = polar_newton(m, iterations)
    return r, polar_tangent(r, m, dm)


def det3(r: jax.Array) -> jax.Array:
    """Determinant of (..., 3, 3) matrices as r0 . (r1 x r2) (fuses; no LU call)."""
    check_shape(r, "det3: r", (3, 3))
    return jnp.sum(r[..., 0, :] * cross(r[..., 1, :], r[..., 2, :]), axis=-1)


def orthogonality_error(r: jax.Array) -> jax.Array:
    """||R^T R - I||_F, shape (...), of (..., 3, 3) matrices."""
    check_shape(r, "orthogonality_error: r", (3, 3))
    e = mm(jnp.swapaxes(r, -1, -2), r) - jnp.eye(3, dtype=r.dtype)
    return jnp.sqrt(jnp.sum(e * e, axis=(-2, -1)))


# --------------------------------------------------------------------------------------------------------
# Errors and Euler angles
# --------------------------------------------------------------------------------------------------------
def angle_of(e: jax.Array) -> jax.Array:
    """Rotation angle (rad, in [0, pi]) of a rotation matrix ``e`` (eq. 23 of batista2019-ges).

    atan2(||vex(E)||, (tr E - 1)/2): accurate at small angles (unlike arccos) and gradient-safe at 0.
    """
    check_shape(e, "angle_of: e", (3, 3))
    e = _as_float(e)
    s, small = _safe_norm(vex(e), _tiny(e.dtype) ** 2)
    c = 0.5 * (jnp.trace(e, axis1=-2, axis2=-1) - 1.0)
    return jnp.where(small, jnp.where(c < 0, jnp.pi, 0.0), jnp.arctan2(s, c))


def angle_error(r_true: jax.Array, r_est: jax.Array) -> jax.Array:
    """Angle (rad) of the rotation error R_true^T R_est, shape (...), of (..., 3, 3) rotation matrices."""
    check_shape(r_true, "angle_error: r_true", (3, 3))
    check_shape(r_est, "angle_error: r_est", (3, 3))
    return angle_of(mm(jnp.swapaxes(r_true, -1, -2), r_est))


class EulerZYX(NamedTuple):
    """Roll, pitch, yaw (rad) of the ZYX convention: R = Rz(yaw) Ry(pitch) Rx(roll)."""

    roll: jax.Array
    pitch: jax.Array
    yaw: jax.Array


def matrix_to_euler_zyx(r: jax.Array) -> EulerZYX:
    """ZYX Euler angles (rad) of a body-to-reference rotation matrix; pitch in [-pi/2, pi/2].

    At pitch = +-90 deg (gimbal lock) roll and yaw are not defined and neither is their gradient.
    """
    check_shape(r, "matrix_to_euler_zyx: r", (3, 3))
    roll = jnp.arctan2(r[..., 2, 1], r[..., 2, 2])
    horiz = jnp.hypot(r[..., 2, 1], r[..., 2, 2])
    pitch = jnp.arctan2(-r[..., 2, 0], horiz)
    yaw = jnp.arctan2(r[..., 1, 0], r[..., 0, 0])
    return EulerZYX(roll, pitch, yaw)


def euler_zyx_to_matrix(roll: jax.Array, pitch: jax.Array, yaw: jax.Array) -> jax.Array:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (angles in rad), body-to-reference."""
    roll, pitch, yaw = jnp.broadcast_arrays(jnp.asarray(roll), jnp.asarray(pitch), jnp.asarray(yaw))
    cr, sr, cp, sp, cy, sy = jnp.cos(roll), jnp.sin(roll), jnp.cos(pitch), jnp.sin(pitch), jnp.cos(yaw), jnp.sin(yaw)
    return jnp.stack(
        [
            jnp.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
            jnp.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
            jnp.stack([-sp, cp * sr, cp * cr], -1),
        ],
        axis=-2,
    )


def wrap_angle(a: jax.Array) -> jax.Array:
    """Angle (rad) wrapped to (-pi, pi] (smooth: atan2(sin a, cos a))."""
    return jnp.arctan2(jnp.sin(a), jnp.cos(a))


def euler_error_zyx(r_true: jax.Array, r_est: jax.Array) -> EulerZYX:
    """Roll, pitch, yaw errors (rad): ZYX angles of the estimate minus the truth's, wrapped to (-pi, pi];
    (..., 3, 3) rotation matrices."""
    check_shape(r_true, "euler_error_zyx: r_true", (3, 3))
    check_shape(r_est, "euler_error_zyx: r_est", (3, 3))
    et, ee = matrix_to_euler_zyx(r_true), matrix_to_euler_zyx(r_est)
    return EulerZYX(*(wrap_angle(a - b) for a, b in zip(ee, et)))


# --------------------------------------------------------------------------------------------------------
# Attitude from two vectors
# --------------------------------------------------------------------------------------------------------
def unit(v: jax.Array) -> jax.Array:
    """v / |v| over the last axis (..., n), gradient-safe: vectors of norm 0 are returned unchanged."""
    check_shape(v, "unit: v", (None,))
    n2 = jnp.sum(v * v, axis=-1, keepdims=True)
    return v / jnp.sqrt(jnp.where(n2 > 0, n2, 1.0))


def triad(acc: jax.Array, mag: jax.Array, frame: str = "ENU") -> jax.Array:
    """Sensor-to-``frame`` rotation (..., 3, 3) from one accelerometer and one magnetometer sample (TRIAD).

    up = a / |a| (the specific force at rest points up), east = m x up / |m x up|, north = up x east: the rows of
    the sensor-to-ENU matrix are (east, north, up) in sensor coordinates; other frames (``"NED"``, ``"NWU"``,
    :mod:`jaxatt.frames`) by a fixed rotation. "North" is magnetic north (the field's horizontal direction).
    Degenerate samples still give a rotation: a zero accelerometer takes the sensor's z axis as up, and a
    magnetometer that is zero or parallel to up (no horizontal component) takes east from the sensor axis least
    aligned with up (the heading is then arbitrary).
    """
    from .frames import check_frame, frame_rotation

    check_shape(acc, "triad: acc", (3,))
    check_shape(mag, "triad: mag", (3,))
    frame = check_frame(frame)
    acc, mag = jnp.asarray(acc), jnp.asarray(mag)
    eye = jnp.eye(3, dtype=acc.dtype)
    a2 = jnp.sum(acc * acc, axis=-1, keepdims=True)
    u = jnp.where(a2 > 0, unit(acc), eye[2])
    e = cross(mag, u)
    e2, m2 = jnp.sum(e * e, axis=-1, keepdims=True), jnp.sum(mag * mag, axis=-1, keepdims=True)
    fallback = cross(eye[jnp.argmin(jnp.abs(u), axis=-1)], u)  # a horizontal vector from the least aligned axis
    east = unit(jnp.where(e2 > 1e-12 * m2, e, fallback))
    north = cross(u, east)
    r_enu = jnp.stack([east, north, u], axis=-2)
    if frame == "ENU":
        return r_enu
    return mm(jnp.asarray(frame_rotation(frame, "ENU"), r_enu.dtype), r_enu)
