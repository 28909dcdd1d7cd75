"""Complementary / compatible vector-measurement attitude observer on SO(3) with time-varying references
(Trumpf, Mahony, Hamel, Lageman, IEEE TAC 2012, "Analysis of non-linear attitude observers for time-varying
reference measurements"), with the optional
gyro-bias integrator of Mahony, Hamel, Pflimlin (IEEE TAC 2008, passive complementary filter).

Frames and conventions (as everywhere in jaxatt): R maps body coordinates to the inertial frame, v_A = R v_B;
quaternions are Hamilton (w, x, y, z) and describe the same body-to-inertial rotation; rates in rad/s (body),
gains in 1/s, time in s.

Measurements (Section II of the paper):

* n1 >= 0 *complementary* measurements, eq. (2): a_i = R^T å_i, made in the body frame of known inertial
  reference directions å_i(t) (e.g. accelerometer ~ "up", magnetometer ~ field direction).
* n2 >= 0 *compatible* measurements, eq. (3): b_j = R b̊_j, made in the inertial frame of known body-fixed
  reference directions b̊_j(t) (e.g. a GPS baseline), n1 + n2 >= 1.

References may vary in time, so the sample carries them (:class:`VectorSample`). The observer, eq. (10):

    dR^/dt = R^ ( Omega + sum_i k_i (a_i x â_i) + R^T sum_j l_j (b̂_j x b_j) )_x ,
    â_i = R^T å_i,  b̂_j = R^ b̊_j,  k_i, l_j > 0,

and, with the gyro bias integrator (Mahony et al. 2008 passive filter; our reading, see below),

    Omega = gyr - b^,   db^/dt = -k_I * sigma,   sigma := the correction sum above (rad/s, body frame).

Two independent implementations, selected by ``make_observer(form=...)``:

* ``"matrix"``: eq. (10) evaluated literally on R^ (3x3) and integrated with a Runge-Kutta-Munthe-Kaas step
  (:func:`jaxatt.integrate.rkmk4_step`), the bias carried by the same stages; R^ stays on SO(3) by
  construction (so3.exp), and one Newton-Schulz step per step holds the float32 rounding drift.
* ``"quaternion"``: eq. (18) evaluated literally with quaternion products (p(v) = (0, v), p† = vector part),
  dq^/dt = 1/2 q^ (x) p(Omega + sigma_q), integrated with classical RK4 in R^4 and renormalised each step.

Both give the same trajectory up to the sign of q: max |R^_matrix - R^_quaternion| ~2e-11 at dt = 0.02 s and
~4e-14 at dt = 0.004 s on a mixed run with bias estimation (tests/test_complementary.py).

Readings chosen where the paper is open or the text garbled:

* Eq. (10) as extracted reads "a_i × â_i" and "b̂_j × b_j" with hats lost in places; we use the reading that
  makes (10) coincide with the unified form (15) (v_i x v̂_i, v̂_i = R^T v̊_i, v̊ = å for complementary and
  v̊ = b (measured) for compatible measurements), i.e. sigma = sum k_i a_i x R^T å_i + sum l_j b̊_j x R^T b_j.
  A small-error check gives d vex(log E_r)/dt = -P(t) vex(log E_r) with P = sum q_i (I - v̊_i v̊_i^T), the
  linearisation in the proof of Proposition 4.6, so the signs are the stable ones.
* The paper assumes unit vectors (directions on S^2). With ``normalize=True`` (default) measurements and
  references are normalised at every RK stage, so raw accelerometer (m/s^2) and magnetometer (any unit)
  samples can be fed; ``normalize=False`` uses the raw vectors (the effective gain is then k_i |a_i| |å_i|).
* Gyro bias: the paper has no bias. Mahony et al. (2008) write dR^/dt = R^(Omega_y - b^ + k_P w)_x,
  db^/dt = -k_I w with w = sum k_i v_i x v̂_i. We fold k_P into the measurement gains (sigma = k_P w) and
  use db^/dt = -k_I sigma, so our k_I equals Mahony's k_I / k_P. k_I = 0 (default) is the paper's observer.
  The convergence guarantee of the bias integrator is Mahony's (constant, non-collinear references);
  for time-varying references it is not covered by either paper.
* The correction reported in :class:`Out` is sigma evaluated at the start of the step (R^_k, sample k).

Missing data (NaN in a log): a measurement whose vector or reference has a non-finite component, or is the
zero vector, gets weight zero for that step (its correction is skipped, others still act; with a linear
hold the measurement must be valid at both ends of the step). A non-finite gyro sample is replaced by the
last valid gyro reading. :class:`Out` reports which measurements were used and whether the gyro was held.
"""

from __future__ import annotations

import functools
from typing import List, NamedTuple, Sequence, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import frames, so3
from ..integrate import input_at, rk4_step, rkmk4_step
from ..types import ArrayLike, ImuSample, Interval, Observer, VectorSample, shown, shown_for_shape
from . import registry

__all__ = [
    "Params",
    "State",
    "Out",
    "StepInput",
    "make_observer",
    "default_params",
    "imu_params",
    "check_params",
    "check_inputs",
    "right_error",
    "lyapunov",
    "correction_matrix",
    "correction_quaternion",
    "FORMS",
    "UP_NED",
    "UP_ENU",
]

FORMS = ("matrix", "quaternion")
#: The "up" direction (unit), i.e. the direction of the specific force an accelerometer at rest measures
#: (minus gravity), in NED (z down) and ENU (z up) inertial frames.
UP_NED = tuple(frames.up("NED"))
UP_ENU = tuple(frames.up("ENU"))


# ------------------------------------------------------------------------------------------------------
# Data types
# ------------------------------------------------------------------------------------------------------
class Params(NamedTuple):
    """Observer parameters (a pytree of arrays).

    Fields:
        k:            (n1,) gains k_i >= 0 of the complementary measurements (1/s), eq. (10).
        l:            (n2,) gains l_j >= 0 of the compatible measurements (1/s), eq. (10).
        k_i:          () bias integral gain k_I >= 0 (1/s; Mahony's k_I / k_P, see module doc). 0 = no bias.
        r_hat_0:      (3, 3) initial estimate R^(t0), body to inertial, a rotation.
        bias_0:       (3,) initial gyro-bias estimate (rad/s, body).
        ref_inertial: (n1, 3) constant inertial references å_i, used when the sample carries none (always
                      for :class:`ImuSample`: rows in the order of ``imu_fields``).
        ref_body:     (n2, 3) constant body-fixed references b̊_j, used when the sample carries none.
    """

    k: ArrayLike
    l: ArrayLike
    k_i: ArrayLike
    r_hat_0: ArrayLike
    bias_0: ArrayLike
    ref_inertial: ArrayLike
    ref_body: ArrayLike


class State(NamedTuple):
    """Observer state at time ``t`` (s): R^ (3, 3) and q^ (4,) (the integrated one of the two depends on the
    form; the other is derived, q^ sign-continuous), bias estimate (3,) rad/s, last valid gyro (3,) rad/s."""

    t: jax.Array
    r: jax.Array
    q: jax.Array
    bias: jax.Array
    gyr_last: jax.Array


class Out(NamedTuple):
    """Estimate at time ``t`` (s, end of the step).

    Fields:
        t: (); r: (3, 3) R^, body to inertial; q: (4,) q^ (w, x, y, z), sign-continuous along a run;
        bias: (3,) gyro-bias estimate (rad/s, body);
        correction: (3,) sigma at the start of the step (rad/s, body): the innovation added to the gyro;
        used_body_meas: (n1,) bool, which complementary measurements acted in this step;
        used_inertial_meas: (n2,) bool, which compatible measurements acted;
        gyr_held: () bool, True when the gyro sample was missing and the last valid one was used.
    """

    t: jax.Array
    r: jax.Array
    q: jax.Array
    bias: jax.Array
    correction: jax.Array
    used_body_meas: jax.Array
    used_inertial_meas: jax.Array
    gyr_held: jax.Array


class StepInput(NamedTuple):
    """Input of the correction terms at one instant (all arrays finite; rows of missing measurements are
    replaced by a dummy unit vector and get gain 0): gyr (3,) rad/s body; a (n1, 3) body measurements;
    ar (n1, 3) their inertial references; b (n2, 3) inertial measurements; br (n2, 3) their body references."""

    gyr: jax.Array
    a: jax.Array  # (n1, 3) body measurements
    ar: jax.Array  # (n1, 3) inertial references
    b: jax.Array  # (n2, 3) inertial measurements
    br: jax.Array  # (n2, 3) body references


# ------------------------------------------------------------------------------------------------------
# Error and Lyapunov function of the paper
# ------------------------------------------------------------------------------------------------------
def right_error(r_hat, r):
    """Canonical right-invariant error E_r = R^ R^T (Section IV), (..., 3, 3); E_r = I means no error."""
    return so3.mm(r_hat, jnp.swapaxes(r, -1, -2))


def lyapunov(r_hat, r):
    """V = tr(I - E_r) in [0, 4] (proof of Proposition 4.6): V = 2 (1 - cos(angle error))."""
    return 3.0 - jnp.trace(right_error(r_hat, r), axis1=-2, axis2=-1)


# ------------------------------------------------------------------------------------------------------
# Parameters
# ------------------------------------------------------------------------------------------------------
def _gain_vector(g, n: int, name: str) -> np.ndarray:
    g = np.asarray(g, float)
    if g.ndim == 0:
        return np.full(n, float(g))
    if g.shape != (n,):
        raise ValueError(f"{name} must be a scalar or have shape ({n},), got {g.shape}")
    return g


def _initial_rotation(r_hat_0, q_hat_0) -> np.ndarray:
    if r_hat_0 is not None and q_hat_0 is not None:
        raise ValueError("give r_hat_0 or q_hat_0, not both")
    if q_hat_0 is not None:
        q = np.asarray(q_hat_0, float)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) == 0:
            raise ValueError(f"q_hat_0 must be a finite non-zero (w, x, y, z) quaternion, got {q}")
        return np.asarray(so3.quat_to_matrix(jnp.asarray(q)))
    return np.eye(3) if r_hat_0 is None else np.asarray(r_hat_0, float)


def default_params(
    n_body: int = 0,
    n_inertial: int = 0,
    *,
    k=1.0,
    l=1.0,
    k_i: float = 0.0,
    r_hat_0=None,
    q_hat_0=None,
    bias_0=None,
    ref_inertial=None,
    ref_body=None,
    dtype=None,
) -> Params:
    """Parameters for n_body complementary and n_inertial compatible measurements.

    Args:
        n_body, n_inertial: n1 and n2 (inferred from ``ref_inertial`` / ``ref_body`` when those are given).
        k, l: gains (1/s), scalars (same for every measurement) or sequences of length n1 / n2.
        k_i: bias integral gain (1/s); 0 disables bias estimation.
        r_hat_0 or q_hat_0: initial estimate (rotation matrix body->inertial or (w, x, y, z)); default I.
        bias_0: initial bias estimate (rad/s, body), default 0.
        ref_inertial, ref_body: constant references (inertial (n1, 3), body (n2, 3)) for samples that carry
            none; default zeros (then every sample must carry them; :func:`check_inputs` says so).
    """
    dtype = dtype or jnp.result_type(float)
    if ref_inertial is not None:
        ref_inertial = np.asarray(ref_inertial, float).reshape(-1, 3)
        n_body = n_body or ref_inertial.shape[0]
    if ref_body is not None:
        ref_body = np.asarray(ref_body, float).reshape(-1, 3)
        n_inertial = n_inertial or ref_body.shape[0]
    n_body, n_inertial = int(n_body), int(n_inertial)
    p = Params(
        k=_gain_vector(k, n_body, "k"),
        l=_gain_vector(l, n_inertial, "l"),
        k_i=np.asarray(float(k_i)),
        r_hat_0=_initial_rotation(r_hat_0, q_hat_0),
        bias_0=np.zeros(3) if bias_0 is None else np.asarray(bias_0, float),
        ref_inertial=np.zeros((n_body, 3)) if ref_inertial is None else ref_inertial,
        ref_body=np.zeros((n_inertial, 3)) if ref_body is None else ref_body,
    )
    check_params(p)
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), p)


def imu_params(
    k_acc: float = 1.0,
    k_mag: float = 1.0,
    *,
    mag_ref=None,
    frame: str = "NED",
    fields: Sequence[str] = ("acc", "mag"),
    k_i: float = 0.0,
    r_hat_0=None,
    q_hat_0=None,
    bias_0=None,
    dtype=None,
) -> Params:
    """Parameters for an accelerometer + magnetometer log (:class:`ImuSample`, constant references).

    The accelerometer reference is "up" (the specific force at rest is minus gravity): (0, 0, -1) in NED,
    (0, 0, 1) in ENU. ``mag_ref`` is the Earth's field in the same ``frame`` (any unit; only its direction
    matters with ``normalize=True``). ``fields`` must equal the observer's ``imu_fields``.
    """
    if frame not in ("NED", "ENU"):
        raise ValueError(f"frame must be 'NED' or 'ENU', got {frame!r}")
    fields = tuple(fields)
    refs: List[ArrayLike] = []
    gains: List[ArrayLike] = []
    for f in fields:
        if f == "acc":
            refs.append(UP_NED if frame == "NED" else UP_ENU)
            gains.append(k_acc)
        elif f == "mag":
            if mag_ref is None:
                raise ValueError("mag_ref (the magnetic field in the inertial frame) is needed for 'mag'")
            m = np.asarray(mag_ref, float)
            if m.shape != (3,) or not np.all(np.isfinite(m)) or np.linalg.norm(m) == 0:
                raise ValueError(f"mag_ref must be a finite non-zero (3,) vector in {frame}, got {m}")
            refs.append(m)
            gains.append(k_mag)
        else:
            raise ValueError(f"fields must name ImuSample vector fields 'acc'/'mag', got {f!r}")
    return default_params(
        len(fields),
        0,
        k=gains,
        k_i=k_i,
        r_hat_0=r_hat_0,
        q_hat_0=q_hat_0,
        bias_0=bias_0,
        ref_inertial=np.reshape(np.asarray(refs, float), (-1, 3)),
        dtype=dtype,
    )


def check_params(p: Params) -> None:
    """Raise ValueError with a clear message for invalid parameters (shapes, signs, finiteness, rotation)."""
    k, l, k_i = (np.asarray(x, float) for x in (p.k, p.l, p.k_i))
    if k.ndim != 1 or l.ndim != 1:
        raise ValueError(f"k and l must be 1-D gain vectors (n1,) and (n2,), got shapes {k.shape}, {l.shape}")
    if k.size + l.size < 1:
        raise ValueError("at least one measurement is needed (n1 + n2 >= 1, Section II)")
    for name, g in (("k", k), ("l", l)):
        if not np.all(np.isfinite(g)) or np.any(g < 0):
            raise ValueError(f"gains {name} must be finite and non-negative (k_i, l_j > 0 in eq. 10), got {shown(g)}")
    if k_i.shape != () or not np.isfinite(k_i) or k_i < 0:
        raise ValueError(f"k_i must be a finite non-negative scalar, got {k_i}")
    r = np.asarray(p.r_hat_0, float)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise ValueError(f"r_hat_0 must be a finite (3, 3) matrix, got {shown_for_shape(r, (3, 3))}")
    if np.linalg.norm(r.T @ r - np.eye(3)) > 1e-6 or np.linalg.det(r) <= 0:
        raise ValueError(
            "r_hat_0 must be a rotation matrix (R^T R = I, det R = +1); "
            "use so3.nearest_rotation to project an approximate one"
        )
    b = np.asarray(p.bias_0, float)
    if b.shape != (3,) or not np.all(np.isfinite(b)):
        raise ValueError(f"bias_0 must be a finite (3,) vector (rad/s), got {shown_for_shape(b, (3,))}")
    for name, v, n in (("ref_inertial", p.ref_inertial, k.size), ("ref_body", p.ref_body, l.size)):
        v = np.asarray(v, float)
        if v.shape != (n, 3) or not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be a finite ({n}, 3) array, got {shown_for_shape(v, (n, 3))}")


def check_inputs(p: Params, samples, imu_fields: Sequence[str] = ("acc", "mag")) -> None:
    """Check params and a stacked log (VectorSample or ImuSample, time-major) against each other."""
    check_params(p)
    n1, n2 = np.shape(p.k)[0], np.shape(p.l)[0]
    g = np.shape(samples.gyr)
    if len(g) != 2 or g[1] != 3:
        raise ValueError(f"samples.gyr must have shape (T, 3), got {shown(g)}")
    T = g[0]

    def need_const(name, arr):
        if np.any(np.linalg.norm(np.asarray(arr, float), axis=-1) == 0):
            raise ValueError(f"the samples carry no {name}, so Params.{name} must hold non-zero constant references")

    if isinstance(samples, ImuSample):
        if n2:
            raise ValueError("an ImuSample log has no inertial-frame (compatible) measurements: use n2 = 0")
        if len(tuple(imu_fields)) != n1:
            raise ValueError(f"imu_fields {tuple(imu_fields)} must match the {n1} gains in Params.k")
        for f in imu_fields:
            v = getattr(samples, f, None)
            if v is None or np.shape(v) != (T, 3):
                raise ValueError(f"samples.{f} must have shape ({T}, 3), got {None if v is None else np.shape(v)}")
        need_const("ref_inertial", p.ref_inertial)
        return
    if not isinstance(samples, VectorSample):
        raise ValueError(f"samples must be a VectorSample or ImuSample, got {type(samples).__name__}")
    for name, n, ref in (("body_meas", n1, "ref_inertial"), ("inertial_meas", n2, "ref_body")):
        v = getattr(samples, name)
        if v is None:
            if n:
                raise ValueError(f"samples.{name} is missing but Params has {n} gains for it")
            continue
        if np.shape(v) != (T, n, 3):
            raise ValueError(f"samples.{name} must have shape ({T}, {n}, 3) (T, gains, 3), got {np.shape(v)}")
        rv = getattr(samples, ref)
        if rv is None:
            need_const(ref, getattr(p, ref))
        elif np.shape(rv) != (T, n, 3):
            raise ValueError(f"samples.{ref} must have shape ({T}, {n}, 3), got {np.shape(rv)}")


# ------------------------------------------------------------------------------------------------------
# Correction terms: eq. (10) (matrix) and eq. (18) (quaternion), written independently
# ------------------------------------------------------------------------------------------------------
def _vectors(u: StepInput, normalize: bool):
    if normalize:
        return so3.unit(u.a), so3.unit(u.ar), so3.unit(u.b), so3.unit(u.br)
    return u.a, u.ar, u.b, u.br


def correction_matrix(r_hat, u: StepInput, k, l, normalize: bool = True):
    """sigma of eq. (10): sum_i k_i a_i x (R^T å_i) + R^T sum_j l_j (R^ b̊_j) x b_j (rad/s, body)."""
    a, ar, b, br = _vectors(u, normalize)
    rt = jnp.swapaxes(r_hat, -1, -2)
    a_hat = so3.mv(rt, ar)  # â_i = R^T å_i, (n1, 3)
    comp = jnp.sum(k[:, None] * so3.cross(a, a_hat), axis=0)
    b_hat = so3.mv(r_hat, br)  # b̂_j = R^ b̊_j, (n2, 3)
    compat = so3.mv(rt, jnp.sum(l[:, None] * so3.cross(b_hat, b), axis=0))
    return comp + compat


def _pure(v):
    return jnp.concatenate([jnp.zeros(v.shape[:-1] + (1,), v.dtype), v], axis=-1)


def _rotate_inverse_q(q, v):
    """p†(q^-1 (x) p(v) (x) q) = R(q)^T v, with q^-1 = conj(q) / |q|^2 (exact for non-unit RK stages)."""
    q_inv = so3.quat_conjugate(q) / jnp.sum(q * q)
    return so3.quat_multiply(so3.quat_multiply(q_inv, _pure(v)), q)[..., 1:]


def correction_quaternion(q_hat, u: StepInput, k, l, normalize: bool = True):
    """sigma of eq. (18): sum_i k_i a_i x p†(q^-1 p(å_i) q) + sum_j l_j b̊_j x p†(q^-1 p(b_j) q)."""
    a, ar, b, br = _vectors(u, normalize)
    comp = jnp.sum(k[:, None] * so3.cross(a, _rotate_inverse_q(q_hat, ar)), axis=0)
    compat = jnp.sum(l[:, None] * so3.cross(br, _rotate_inverse_q(q_hat, b)), axis=0)
    return comp + compat


# ------------------------------------------------------------------------------------------------------
# Input handling
# ------------------------------------------------------------------------------------------------------
def _as_vector_sample(u, p: Params, imu_fields: tuple) -> VectorSample:
    """VectorSample with every field an array (constant references from params where the sample has none)."""
    dtype = p.r_hat_0.dtype
    n1, n2 = p.k.shape[0], p.l.shape[0]
    if isinstance(u, ImuSample):
        if n2:
            raise ValueError("an ImuSample has no inertial-frame (compatible) measurements: Params.l must be empty")
        if len(imu_fields) != n1:
            raise ValueError(f"imu_fields {imu_fields} must match the {n1} gains in Params.k")
        vecs = []
        for f in imu_fields:
            v = getattr(u, f)
            if v is None:
                raise ValueError(f"the observer uses ImuSample.{f}, which is None in this sample")
            vecs.append(jnp.asarray(v, dtype))
        a = jnp.stack(vecs, axis=-2) if vecs else jnp.zeros((0, 3), dtype)
        return VectorSample(u.t, u.gyr, a, p.ref_inertial, jnp.zeros((0, 3), dtype), p.ref_body)
    if not isinstance(u, VectorSample):
        raise ValueError(f"samples must be VectorSample or ImuSample, got {type(u).__name__}")

    def field(v, n, name, default):
        if v is None:
            if name in ("body_meas", "inertial_meas") and n:
                raise ValueError(f"VectorSample.{name} is None but Params has {n} gains for it")
            return default
        v = jnp.asarray(v, dtype)
        if v.shape != (n, 3):
            raise ValueError(f"VectorSample.{name} must have shape ({n}, 3) per sample, got {v.shape}")
        return v

    zeros = lambda n: jnp.zeros((n, 3), dtype)  # noqa: E731
    return VectorSample(
        u.t,
        u.gyr,
        field(u.body_meas, n1, "body_meas", zeros(n1)),
        field(u.ref_inertial, n1, "ref_inertial", p.ref_inertial),
        field(u.inertial_meas, n2, "inertial_meas", zeros(n2)),
        field(u.ref_body, n2, "ref_body", p.ref_body),
    )


def _row_ok(*vs):
    """True where every one of ``vs`` (..., 3) is present (:func:`jaxatt.so3.present`)."""
    ok = so3.present(vs[0])
    for v in vs[1:]:
        ok = ok & so3.present(v)
    return ok


def _clean(v, ok):
    dummy = jnp.zeros_like(v).at[..., 0].set(1.0)
    return jnp.where(ok[..., None], v, dummy)


def _prepare(u, p: Params, gyr_last, imu_fields):
    """Cleaned step input (plain or Interval), effective gains, diagnostics, start time, new gyr_last."""
    ends: Tuple[VectorSample, ...]
    if isinstance(u, Interval):
        s, e = _as_vector_sample(u.start, p, imu_fields), _as_vector_sample(u.end, p, imu_fields)
        ok_a = _row_ok(s.body_meas, s.ref_inertial, e.body_meas, e.ref_inertial)
        ok_b = _row_ok(s.inertial_meas, s.ref_body, e.inertial_meas, e.ref_body)
        ends = (s, e)
    else:
        s = _as_vector_sample(u, p, imu_fields)
        ok_a = _row_ok(s.body_meas, s.ref_inertial)
        ok_b = _row_ok(s.inertial_meas, s.ref_body)
        ends = (s,)
    cleaned = []
    g_prev = gyr_last
    held = None
    for v in ends:
        gyr = jnp.asarray(v.gyr, gyr_last.dtype)
        g_ok = jnp.all(jnp.isfinite(gyr))
        held = ~g_ok if held is None else held
        g_prev = jnp.where(g_ok, gyr, g_prev)
        cleaned.append(
            StepInput(
                g_prev,
                _clean(v.body_meas, ok_a),
                _clean(v.ref_inertial, ok_a),
                _clean(v.inertial_meas, ok_b),
                _clean(v.ref_body, ok_b),
            )
        )
    x = Interval(*cleaned) if len(cleaned) == 2 else cleaned[0]
    k = jnp.where(ok_a, p.k, 0.0)
    l = jnp.where(ok_b, p.l, 0.0)
    return x, k, l, ok_a, ok_b, held, s.t, g_prev


# ------------------------------------------------------------------------------------------------------
# Observer
# ------------------------------------------------------------------------------------------------------
def make_observer(form: str = "matrix", imu_fields: Sequence[str] = ("acc", "mag"), normalize: bool = True) -> Observer:
    """Build the observer of eq. (10) (``form="matrix"``) or eq. (18) (``form="quaternion"``).

    Args:
        form: "matrix" (R^ on SO(3), Lie-group RK4 step) or "quaternion" (q^ in R^4, RK4 + renormalisation).
        imu_fields: for :class:`ImuSample` logs, the body-frame vector fields used as complementary
            measurements, in the order of ``Params.k`` / ``Params.ref_inertial`` (see :func:`imu_params`).
        normalize: normalise measurements and references to unit length (the paper's S^2 setting).

    Samples: :class:`VectorSample` (time-varying references) or :class:`ImuSample`, plain (held over the
    step) or an :class:`jaxatt.types.Interval` (linearly interpolated). The same arguments return the
    same Observer object, so :func:`jaxatt.montecarlo.run` reuses its compiled scan.
    """
    if form not in FORMS:
        raise ValueError(f"form must be one of {FORMS}, got {form!r}")
    fields = tuple(imu_fields)
    for f in fields:
        if f not in ("acc", "mag"):
            raise ValueError(f"imu_fields must name ImuSample vector fields 'acc'/'mag', got {f!r}")
    return _make_observer(form, fields, bool(normalize))


@functools.lru_cache(maxsize=None)
def _make_observer(form: str, imu_fields: tuple, normalize: bool) -> Observer:
    def init(p: Params, sample) -> State:
        dtype = p.r_hat_0.dtype
        gyr = jnp.asarray(sample.gyr, dtype)
        r0 = p.r_hat_0
        q0 = so3.quat_canonical(so3.matrix_to_quat(r0))
        return State(jnp.asarray(sample.t, dtype), r0, q0, p.bias_0, jnp.where(jnp.isfinite(gyr), gyr, 0.0))

    def step(p: Params, s: State, sample, dt):
        x, k, l, ok_a, ok_b, held, t0, gyr_new = _prepare(sample, p, s.gyr_last, imu_fields)
        dt = jnp.asarray(dt, s.r.dtype)
        if form == "matrix":

            def f(b, frames, u):
                sig = correction_matrix(frames[0], u, k, l, normalize)
                return -p.k_i * sig, (u.gyr - b + sig,)  # bias' and the body rate of R^ (eq. 10)

            bias, (r,) = rkmk4_step(f, s.bias, (s.r,), x, dt)
            r = so3.reorthonormalize(r)  # rounding drift (float32) held at rounding level
            q = so3.matrix_to_quat(r)
            q = jnp.where(jnp.dot(q, s.q) < 0, -q, q)
            sigma0 = correction_matrix(s.r, input_at(x, 0.0), k, l, normalize)
        else:

            def f_quat(y, u):
                qq, b = y
                sig = correction_quaternion(qq, u, k, l, normalize)
                return 0.5 * so3.quat_multiply(qq, _pure(u.gyr - b + sig)), -p.k_i * sig  # eq. (17)/(18)

            q, bias = rk4_step(f_quat, (s.q, s.bias), x, dt)
            q = q / jnp.linalg.norm(q)
            r = so3.quat_to_matrix(q)
            sigma0 = correction_quaternion(s.q, input_at(x, 0.0), k, l, normalize)
        t1 = jnp.asarray(t0, s.r.dtype) + dt
        new = State(t1, r, q, bias, gyr_new)
        return new, Out(t1, r, q, bias, sigma0, ok_a, ok_b, held)

    def output(p: Params, s: State) -> Out:
        """The estimate held by ``s``; no correction has been applied yet (zero, no measurement used)."""
        return Out(
            s.t,
            s.r,
            s.q,
            s.bias,
            jnp.zeros_like(s.bias),
            jnp.zeros(jnp.shape(p.k), bool),
            jnp.zeros(jnp.shape(p.l), bool),
            jnp.zeros((), bool),
        )

    return Observer(init, step, f"complementary-{form}", output)


# ------------------------------------------------------------------------------------------------------
# Registry: the observer on recorded IMU data (acc + mag, ENU)
# ------------------------------------------------------------------------------------------------------
def _setup_recorded(p: Params, sample) -> Params:
    """TRIAD start and the references of the recording: "up" for the accelerometer, the direction of the first
    magnetometer sample (in the TRIAD ENU frame) for the magnetometer."""
    r0, m_nav, _ = registry.first_sample_frame(sample)
    up = jnp.asarray(frames.up("ENU"), m_nav.dtype)
    return p._replace(r_hat_0=r0, ref_inertial=jnp.stack([up, so3.unit(m_nav)]))


def _recorded_defaults(dtype=None) -> Params:
    """k_acc = 0.5, k_mag = 0.2, k_I = 0.02 1/s (untuned); references and start from the data (``setup``)."""
    return imu_params(0.5, 0.2, mag_ref=(0.0, 1.0, -1.0), frame="ENU", k_i=0.02, dtype=dtype)


def _recorded_observer() -> Observer:
    return make_observer(form="quaternion", imu_fields=("acc", "mag"), normalize=True)


ENTRIES = (
    registry.Entry(
        name="complementary",
        summary="Trumpf et al.'s observer for complementary / compatible vector measurements with time-varying "
        "references (Mahony's passive filter as a special case), optional gyro bias",
        reference="Trumpf, Mahony, Hamel, Lageman 2012, eqs. (10), (18)",
        make=_recorded_observer,
        default_params=_recorded_defaults,
        gains=(
            registry.Gain("k", "1/s", "gains k_i of the complementary measurements (acc, mag), eq. (10)/(18)"),
            registry.Gain("k_i", "1/s", "gyro-bias integral gain"),
            registry.Gain("l", "1/s", "gains l_j of the compatible measurements, eq. (10)", tuned=False),
        ),
        setup=_setup_recorded,
        setup_fields=("r_hat_0", "ref_inertial"),
        frame="ENU",
        hold="next",
        module="complementary",
        check=check_params,
    ),
)
