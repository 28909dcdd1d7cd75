"""Madgwick's MARG filter (jaxatt.observers.madgwick) against the ahrs package's ``Madgwick.updateMARG``.

Frames: ahrs' ``Q`` is the same quaternion as the observer's ``State.q`` / ``Out.q_nwu``: sensor-to-earth (ahrs
rotates the magnetometer into the earth frame as h = q m q*), Hamilton, (w, x, y, z), earth frame NWU (gravity
reference (0, 0, 1) for the specific force, field reference (b_x, 0, b_z)). No conjugation or frame change is
needed for the comparison; ``Out.q`` is the same estimate in ENU.

ahrs 0.4 ignores ``q0=`` in its MARG batch mode (it always starts from ``ecompass(acc[0], mag[0], 'NED')``), so
the reference runs ``Q[t] = updateMARG(Q[t-1], gyr[t], acc[t], mag[t])`` itself from the observer's start.

BROAD data (Laidig et al., Data 6(7), 2021, CC BY 4.0) in ../shared/data/broad: the tests that need it skip
without it, except under CI=true, where they fail.
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxatt
from jaxatt import frames, montecarlo
from jaxatt.data import broad
from jaxatt.observers import madgwick, registry
from jaxatt.types import ImuSample

try:
    import ahrs.filters as ahrs_filters
except ImportError:  # the comparison needs the test extra (pip install ".[test]")
    if os.environ.get("CI", "").lower() == "true":
        raise
    ahrs_filters = pytest.importorskip("ahrs.filters")

from broad_data import DATA, need_data  # noqa: E402

N_BROAD = 20000  # samples of trial 01 compared with ahrs


@pytest.fixture(scope="module")
def trial01():
    need_data()
    return broad.load(DATA, trials=["01"])[0]


def ahrs_run(q0, gyr, acc, mag, rate_hz, beta):
    """ahrs' Madgwick from q0: Q[0] = q0, Q[t] = updateMARG(Q[t-1], gyr[t], acc[t], mag[t]) (float64)."""
    f = ahrs_filters.Madgwick(frequency=rate_hz, gain=beta)
    q = np.zeros((len(gyr), 4))
    q[0] = q0
    for t in range(1, len(gyr)):
        q[t] = f.updateMARG(q[t - 1], gyr[t], acc[t], mag[t])
    return q


def max_diff(q1, q2):
    """Max abs difference per component, sign-aligned row by row. (np.asarray: ahrs returns its Quaternion class,
    an ndarray subclass whose ``*`` is the quaternion product.)"""
    q1, q2 = np.asarray(q1, np.float64), np.asarray(q2, np.float64)
    s = np.where(np.sum(q1 * q2, axis=-1, keepdims=True) < 0, -1.0, 1.0)
    return float(np.max(np.abs(q1 - s * q2)))


def qmul_np(a, b):
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    return np.concatenate([aw * bw - np.sum(av * bv, -1, keepdims=True), aw * bv + bw * av + np.cross(av, bv)], -1)


def rotate_np(q, v):
    """R(q) v (sensor to earth)."""
    qv = np.concatenate([np.zeros(v.shape[:-1] + (1,)), v], -1)
    conj = q * np.array([1.0, -1.0, -1.0, -1.0])
    return qmul_np(qmul_np(q, qv), conj)[..., 1:]


def synthetic_log(n=1500, dt=0.01, seed=0):
    """A smoothly rotating sensor in NWU: (truth q (n, 4) sensor-to-NWU, gyr, acc (m/s^2), mag (uT), dt)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    w = np.stack([0.6 * np.sin(0.7 * t), 0.4 * np.cos(1.3 * t), 0.9 * np.sin(0.3 * t + 1.0)], axis=1)
    q = np.zeros((n, 4))
    q[0] = [np.cos(0.4), 0.1, -0.2, np.sin(0.4)]
    q[0] /= np.linalg.norm(q[0])
    for k in range(n - 1):  # exact rotation over each step with the rate held from sample k+1 ("next")
        phi = w[k + 1] * dt
        th = np.linalg.norm(phi)
        dq = np.concatenate([[np.cos(th / 2)], np.sin(th / 2) * phi / th])
        q[k + 1] = qmul_np(q[k], dq)
    conj = q * np.array([1.0, -1.0, -1.0, -1.0])
    acc = rotate_np(conj, np.tile([0.0, 0.0, 9.81], (n, 1))) + 0.05 * rng.normal(size=(n, 3))
    mag = rotate_np(conj, np.tile([20.0, 0.0, -40.0], (n, 1))) + 0.3 * rng.normal(size=(n, 3))
    gyr = w + 0.003 * rng.normal(size=(n, 3))
    return q, gyr, acc, mag, dt


def angle_between(q1, q2):
    d = np.abs(np.sum(q1 * q2, axis=-1))
    return 2 * np.arccos(np.clip(d, 0.0, 1.0))


# ------------------------------------------------------------------------------------------------------------
# 1. ahrs on BROAD
# ------------------------------------------------------------------------------------------------------------
def test_matches_ahrs_update_marg_on_broad_trial_01(trial01):
    """jaxatt's observer vs ahrs' updateMARG on the first 20000 samples of BROAD trial 01 (float64, beta = 0.041,
    285.7 Hz, same start). Measured: max difference 7.2e-15 per quaternion component (tolerance 1e-9)."""
    s = trial01.samples
    gyr, acc, mag = (np.asarray(v[:N_BROAD], np.float64) for v in (s.gyr, s.acc, s.mag))
    samples = ImuSample(np.asarray(s.t[:N_BROAD], np.float64), gyr, acc, mag)
    dt = 1.0 / trial01.rate_hz
    p = madgwick.default_params()
    assert float(p.beta) == ahrs_filters.Madgwick().gain_marg == 0.041
    run = montecarlo.log_runner(madgwick.make_observer(), "next")
    out = run(p, samples, dt)
    q_jax = np.asarray(out.q_nwu)
    assert q_jax.dtype == np.float64 and q_jax.shape == (N_BROAD, 4)

    # The start: TRIAD in NWU, which is also what ahrs' own batch mode starts from (ecompass, 'NED' label).
    from ahrs.common.orientation import ecompass

    q_ecompass = ecompass(acc[0], mag[0], frame="NED", representation="quaternion")
    assert max_diff(q_ecompass[None], q_jax[:1]) < 1e-12

    q_ahrs = ahrs_run(q_jax[0], gyr, acc, mag, trial01.rate_hz, 0.041)
    d = max_diff(q_ahrs, q_jax)
    assert d < 1e-9, f"max |q_jaxatt - q_ahrs| = {d:.3g} over {N_BROAD} samples"
    # The comparison is sensitive: the estimate moves a lot, and a 10 % different gain is far outside tolerance.
    assert np.max(angle_between(q_jax[:1], q_jax)) > 1.0
    out_b = run(madgwick.default_params(0.041 * 1.1), samples, dt)
    assert max_diff(q_ahrs, np.asarray(out_b.q_nwu)) > 1e-5
    # And it tracks BROAD's optical truth in ENU (a loose sanity bound; about 2 deg on this trial).
    err = broad.broad_errors(np.asarray(out.q), trial01.quat_true[:N_BROAD], trial01.movement[:N_BROAD])
    assert err["total_rmse_deg"] < 5.0, err


# ------------------------------------------------------------------------------------------------------------
# 2. Through the registry and jaxatt.filter
# ------------------------------------------------------------------------------------------------------------
def test_registry_entry_and_filter_frames():
    e = registry.get("madgwick")
    assert "madgwick" in registry.names(recorded=True)
    assert e.module == "madgwick" and e.frame == "ENU" and registry.hold_of(e) == "next" and e.setup is None
    assert [g.field for g in e.gains] == ["beta"] and e.gain("beta").constraint == "positive"
    assert registry.recorded_observer("madgwick") is madgwick.make_observer()

    q_true, gyr, acc, mag, dt = synthetic_log()
    est = jaxatt.filter("madgwick", gyr, acc, mag, dt=dt)
    q_nwu = est.outputs["q_nwu"]
    assert est.frame == "ENU" and est.quat.shape == (len(gyr), 4)
    np.testing.assert_allclose(est.quat, frames.change_frame(q_nwu, "ENU", "NWU"), rtol=0, atol=1e-14)
    assert np.max(np.abs(est.quat - q_nwu)) > 0.1  # the rotation to ENU was applied
    np.testing.assert_allclose(
        jaxatt.filter("madgwick", gyr, acc, mag, dt=dt, frame="NWU").quat, q_nwu, rtol=0, atol=1e-14
    )
    # Same as the observer run directly with the default params.
    out = montecarlo.log_runner(madgwick.make_observer(), "next")(
        madgwick.default_params(), ImuSample(np.arange(len(gyr)) * dt, gyr, acc, mag), dt
    )
    np.testing.assert_allclose(np.asarray(out.q_nwu), q_nwu, rtol=0, atol=1e-14)
    # The estimate follows the synthetic truth (NWU) after the start.
    ang = np.rad2deg(angle_between(q_true, q_nwu))
    assert ang[0] < 3.0 and np.mean(ang[len(ang) // 2 :]) < 3.0, (ang[0], np.mean(ang[len(ang) // 2 :]))
    # ENU truth = q_z(90 deg) (x) NWU truth: est.quat is compared with it equally well.
    ang_enu = np.rad2deg(angle_between(frames.change_frame(q_true, "ENU", "NWU"), est.quat))
    np.testing.assert_allclose(ang_enu, ang, atol=1e-6)


def test_check_params():
    madgwick.check_params(madgwick.default_params())
    for bad in (0.0, -0.1, np.nan, np.inf):
        with pytest.raises(ValueError, match="beta"):
            madgwick.check_params(madgwick.Params(np.asarray(bad)))
    with pytest.raises(ValueError, match="beta"):
        madgwick.check_params(madgwick.Params(np.ones(2)))
    _, gyr, acc, mag, dt = synthetic_log(n=50)
    with pytest.raises(ValueError, match="beta"):
        jaxatt.filter("madgwick", gyr, acc, mag, dt=dt, params=madgwick.default_params(-1.0))


# ------------------------------------------------------------------------------------------------------------
# 3. Gradient with respect to beta
# ------------------------------------------------------------------------------------------------------------
def test_gradient_wrt_beta_matches_finite_differences(trial01):
    """d(BROAD total RMSE over samples 0..12000 of trial 01)/d(beta) by reverse mode vs central differences.
    Measured: relative difference 3.0e-8 at beta = 0.041 (grad 2.8015 deg/(rad/s)), 1.7e-9 at beta = 0.2."""
    n = 12000
    s = trial01.samples
    samples = ImuSample(*(jnp.asarray(np.asarray(v[:n], np.float64)) for v in (s.t, s.gyr, s.acc, s.mag)))
    qt = jnp.asarray(trial01.quat_true[:n])
    mov = jnp.asarray(trial01.movement[:n])
    assert int(mov.sum()) > 1000
    run = montecarlo.log_runner(madgwick.make_observer(), "next")
    dt = 1.0 / trial01.rate_hz

    def loss(beta):
        out = run(madgwick.Params(beta), samples, dt)
        return broad.broad_errors_jax(out.q, qt, mov)["total_rmse_deg"]

    vg = jax.jit(jax.value_and_grad(loss))  # one compile: the finite differences reuse its value
    for beta in (0.041, 0.2):
        b = jnp.asarray(beta, jnp.float64)
        g = float(vg(b)[1])
        h = 1e-5 * beta
        fd = float((vg(b + h)[0] - vg(b - h)[0]) / (2 * h))
        assert np.isfinite(g) and abs(g) > 1e-3, g
        assert abs(g - fd) <= 1e-4 * abs(fd), f"beta={beta}: grad {g:.10g}, finite differences {fd:.10g}"


# ------------------------------------------------------------------------------------------------------------
# 4. Missing samples
# ------------------------------------------------------------------------------------------------------------
def test_missing_samples_match_ahrs_semantics():
    """NaN mag -> ahrs' updateIMU; NaN acc -> pure gyro integration; NaN gyro -> last valid gyro; all-zero acc /
    mag vectors are missing too (ahrs' own semantics of zero vectors)."""
    _, gyr, acc, mag, dt = synthetic_log(n=600, seed=3)
    gyr, acc, mag = gyr.copy(), acc.copy(), mag.copy()
    mag[[5, 6, 100, 101, 102, 400]] = np.nan
    mag[200] = 0.0
    acc[[7, 50, 51, 300, 401]] = np.nan
    acc[250] = 0.0
    acc[[60, 61]] = np.nan
    mag[[60, 61]] = np.nan  # both missing
    gyr[[20, 21, 350]] = np.nan
    gyr[35, 1] = np.nan  # one component missing: the whole sample is missing
    n = len(gyr)
    samples = ImuSample(np.arange(n) * dt, gyr, acc, mag)
    out = montecarlo.log_runner(madgwick.make_observer(), "next")(madgwick.default_params(), samples, dt)
    q = np.asarray(out.q_nwu)
    assert np.all(np.isfinite(q))

    acc_ok = np.all(np.isfinite(acc), 1) & np.any(acc != 0, 1)
    mag_ok = np.all(np.isfinite(mag), 1) & np.any(mag != 0, 1)
    np.testing.assert_array_equal(np.asarray(out.acc_used)[1:], acc_ok[1:])
    np.testing.assert_array_equal(np.asarray(out.mag_used)[1:], (acc_ok & mag_ok)[1:])

    # ahrs, fed zeros for missing acc / mag (its own "missing") and the last valid gyro for a missing gyro.
    f = ahrs_filters.Madgwick(frequency=1.0 / dt, gain=madgwick.BETA_MARG)
    ref = np.zeros((n, 4))
    ref[0] = q[0]
    g_last = gyr[0]
    for t in range(1, n):
        if np.all(np.isfinite(gyr[t])):
            g_last = gyr[t]
        a_in = acc[t] if acc_ok[t] else np.zeros(3)
        m_in = mag[t] if mag_ok[t] else np.zeros(3)
        ref[t] = f.updateMARG(ref[t - 1], g_last, a_in, m_in)
    d = max_diff(ref, q)
    assert d < 1e-12, d

    # Step by step against the rules themselves, from the observer's own previous estimate.
    for t in (5, 100, 200, 400):  # mag missing: ahrs' updateIMU
        assert not mag_ok[t] and acc_ok[t]
        assert max_diff(f.updateIMU(q[t - 1], gyr[t], acc[t])[None], q[t : t + 1]) < 1e-14
        # ... which is a real difference from the MARG update.
        assert max_diff(f.updateMARG(q[t - 1], gyr[t], acc[t], mag[t - 1])[None], q[t : t + 1]) > 1e-8
    for t in (7, 50, 250, 60, 61):  # acc missing (with or without mag): gyro integration only
        assert not acc_ok[t]
        g = gyr[t] if np.all(np.isfinite(gyr[t])) else gyr[t - 1]
        qn = q[t - 1] + 0.5 * dt * qmul_np(q[t - 1], np.concatenate([[0.0], g]))
        np.testing.assert_allclose(q[t], qn / np.linalg.norm(qn), rtol=0, atol=1e-15)


def test_missing_gyro_uses_last_valid_and_zero_gyro_is_a_zero_rate():
    """A NaN gyro sample reuses the last valid one; an all-zero gyro sample is a zero rate with the correction
    applied (ahrs returns q unchanged then: the deliberate difference documented in the module)."""
    _, gyr, acc, mag, dt = synthetic_log(n=40, seed=5)
    obs = madgwick.make_observer()
    p = madgwick.default_params(0.5)
    s0 = obs.init(p, ImuSample(0.0, gyr[0], acc[0], mag[0]))
    s1, _ = obs.step(p, s0, ImuSample(dt, gyr[1], acc[1], mag[1]), dt)
    _, o_nan = obs.step(p, s1, ImuSample(2 * dt, jnp.full(3, jnp.nan), acc[2], mag[2]), dt)
    _, o_last = obs.step(p, s1, ImuSample(2 * dt, gyr[1], acc[2], mag[2]), dt)
    np.testing.assert_array_equal(np.asarray(o_nan.q_nwu), np.asarray(o_last.q_nwu))

    _, o_zero = obs.step(p, s1, ImuSample(2 * dt, jnp.zeros(3), acc[2], mag[2]), dt)
    f = ahrs_filters.Madgwick(frequency=1.0 / dt, gain=0.5)
    q1 = np.asarray(s1.q)
    # ahrs' update with a ~zero rate (1e-300 would underflow to a zero norm in ahrs' check)
    tiny = f.updateMARG(q1, np.array([1e-100, 0.0, 0.0]), acc[2], mag[2])
    assert max_diff(tiny[None], np.asarray(o_zero.q_nwu)[None]) < 1e-14
    assert max_diff(q1[None], np.asarray(o_zero.q_nwu)[None]) > 1e-6
    np.testing.assert_array_equal(f.updateMARG(q1, np.zeros(3), acc[2], mag[2]), q1 / np.linalg.norm(q1))


def test_missing_first_sample_starts_from_identity_and_vmap_over_beta():
    q_true, gyr, acc, mag, dt = synthetic_log(n=300, seed=7)
    acc = acc.copy()
    acc[0] = np.nan
    samples = ImuSample(np.arange(len(gyr)) * dt, gyr, acc, mag)
    run = montecarlo.log_runner(madgwick.make_observer(), "next")
    betas = jnp.asarray([0.02, 0.1, 1.0])
    outs = jax.vmap(lambda b: run(madgwick.Params(b), samples, dt))(betas)
    np.testing.assert_array_equal(np.asarray(outs.q_nwu[:, 0]), np.tile([1.0, 0.0, 0.0, 0.0], (3, 1)))
    for i, b in enumerate(np.asarray(betas)):
        single = np.asarray(run(madgwick.Params(jnp.asarray(b)), samples, dt).q_nwu)
        np.testing.assert_allclose(np.asarray(outs.q_nwu[i]), single, rtol=0, atol=1e-11)  # vmapped rounding
    # From the (wrong) identity start, a larger gain converges to the truth faster.
    err = [np.rad2deg(angle_between(np.asarray(outs.q_nwu[i, 100]), q_true[100])) for i in range(3)]
    assert err[0] > err[1] > err[2], err
