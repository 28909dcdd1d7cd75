"""BROAD loader and metric, the Mahony filter of BROAD's example code, and the published Mahony numbers.

Data: BROAD (Laidig et al., Data 6(7), 2021, CC BY 4.0), a 20-trial subset in ../shared/data/broad.
"""

import json
import os
import platform
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from broad_data import DATA, PUBLISHED, need_data  # noqa: E402

from jaxatt import engine, frames, montecarlo, so3
from jaxatt.data import broad
from jaxatt.observers import mahony
from jaxatt.types import ImuSample


def _q_nwu(t, truth, out):
    return out.q_nwu


def broad_protocol_quats(trials, kp, ki, dtype):
    """BROAD's example code: setState from sample 0 (start computed in float64), then the filter (its C code, in
    ``dtype``) updates with samples 0 ... N-1 (sample 0 a second time); its sensor-to-NWU output is rotated into
    ENU in float64. In jaxatt's alignment (T estimates, estimate 0 = init's, hold="next": estimate k uses sample k)
    that is the log with sample 0 duplicated, estimates 1 ... N. Every trial in one padded batch (one compile);
    returns the list of (N, 4) sensor-to-ENU estimates."""
    dup = [  # the first sample twice, at BROAD's constant rate (k / rate: a uniform trial, the constant step)
        tr._replace(
            samples=jax.tree_util.tree_map(lambda a: np.concatenate([a[:1], a]), tr.samples)._replace(
                t=np.arange(len(tr.samples.t) + 1) / tr.rate_hz
            ),
            quat_true=np.concatenate([tr.quat_true[:1], tr.quat_true]),
            movement=np.concatenate([[False], tr.movement]),
        )
        for tr in trials
    ]
    padded = broad.pad_trials(dup)
    item = {**broad.batch_item(padded, dtype), "truth": None}
    fn = engine.compiled(
        mahony.make_observer("broad"),
        engine.Recorded(padded.samples.t.shape[1] - 1),
        engine.records_of(_q_nwu, 1),
        hold="next",
        obs_dtype=jnp.dtype(dtype),
    )
    q_nwu = np.asarray(fn(None, mahony.default_params(kp, ki, dtype=dtype), item).records, np.float64)
    return [frames.change_frame(q_nwu[i, 1:n], "ENU", "NWU") for i, n in enumerate(padded.lengths)]


def random_quats(rng, n, scale=1.0):
    """Unit quaternions (w >= 0) of rotation vectors ~ N(0, scale^2 I) (numpy)."""
    phi = rng.normal(size=(n, 3)) * scale
    th = np.linalg.norm(phi, axis=1, keepdims=True)
    q = np.concatenate([np.cos(th / 2), np.sin(th / 2) * phi / th], axis=1)
    return np.where(q[:, :1] < 0, -q, q)


def quat_axis_angle(axis, angle_rad):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle_rad / 2)], np.sin(angle_rad / 2) * axis])


def qmul(a, b):
    """Hamilton product (numpy, broadcasting)."""
    a, b = np.broadcast_arrays(np.asarray(a, float), np.asarray(b, float))
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    return np.concatenate([aw * bw - np.sum(av * bv, -1, keepdims=True), aw * bv + bw * av + np.cross(av, bv)], -1)


def rot(q):
    """Rotation matrix of a (w, x, y, z) quaternion (numpy)."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def expm(phi):
    """Rodrigues (numpy)."""
    th = np.linalg.norm(phi)
    if th < 1e-15:
        return np.eye(3)
    k = np.asarray(phi) / th
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * kx + (1 - np.cos(th)) * kx @ kx


# ---------------------------------------------------------------------------------------------------------
# (a) The metric
# ---------------------------------------------------------------------------------------------------------
def errors_by_matrices(q_est, q_true):
    """Independent computation with rotation matrices: E = R_est R_true^T (error in ENU); total = angle of E;
    E = S Rz(psi) with S the smallest rotation taking e_z to E e_z (swing about a horizontal axis):
    inclination = angle(e_z, E e_z), heading = |psi|."""
    out = []
    for qe, qt in zip(q_est, q_true):
        e = rot(qe) @ rot(qt).T
        total = np.arccos(np.clip((np.trace(e) - 1) / 2, -1, 1))
        v = e[:, 2]
        beta = np.arccos(np.clip(v[2], -1, 1))
        axis = np.cross([0.0, 0.0, 1.0], v)
        s = np.eye(3)
        if np.linalg.norm(axis) > 1e-12:
            k = axis / np.linalg.norm(axis)
            kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
            s = np.eye(3) + np.sin(beta) * kx + (1 - np.cos(beta)) * kx @ kx
        m = s.T @ e
        assert abs(m[2, 2] - 1) < 1e-9  # a rotation about z is left
        out.append((total, abs(np.arctan2(m[1, 0], m[0, 0])), beta))
    return np.array(out).T


def test_metric_matches_matrix_computation():
    rng = np.random.default_rng(0)
    qt = random_quats(rng, 200, 2.0)
    qe = qmul(random_quats(rng, 200, 0.5), qt) * rng.choice([-1.0, 1.0], size=(200, 1))  # sign must not matter
    ref = errors_by_matrices(qe, qt)
    for got in (broad.error_angles(qe, qt), jax.jit(broad.error_angles_jax)(jnp.asarray(qe), jnp.asarray(qt))):
        np.testing.assert_allclose(np.stack([np.asarray(g) for g in got]), ref, atol=1e-7)
    # RMS over the movement samples, ignoring NaN truth
    mov = rng.random(200) < 0.7
    qt_nan = qt.copy()
    qt_nan[::9] = np.nan
    keep = mov & np.all(np.isfinite(qt_nan), axis=1)
    res = broad.broad_errors(qe, qt_nan, mov)
    res_j = jax.jit(broad.broad_errors_jax)(jnp.asarray(qe), jnp.asarray(qt_nan), jnp.asarray(mov))
    for name, e in zip(broad.METRICS, ref):
        want = np.rad2deg(np.sqrt(np.mean(e[keep] ** 2)))
        assert res[name] == pytest.approx(want, abs=1e-6)
        assert float(res_j[name]) == pytest.approx(res[name], abs=1e-9)


def test_metric_simple_properties():
    rng = np.random.default_rng(1)
    qt = random_quats(rng, 50, 2.0)
    mov = np.ones(50, bool)
    zero = broad.broad_errors(qt, qt, mov)
    assert all(v < 1e-6 for v in zero.values())
    # 10 deg about ENU z (in the earth frame: q_err = q_z), whatever the true orientation -> pure heading
    qe = qmul(quat_axis_angle([0, 0, 1], np.deg2rad(10.0)), qt)
    r = broad.broad_errors(qe, qt, mov)
    assert r["heading_rmse_deg"] == pytest.approx(10.0, abs=1e-9)
    assert r["total_rmse_deg"] == pytest.approx(10.0, abs=1e-9)
    assert r["inclination_rmse_deg"] < 1e-6
    rj = jax.jit(broad.broad_errors_jax)(jnp.asarray(qe), jnp.asarray(qt), jnp.asarray(mov))
    assert float(rj["heading_rmse_deg"]) == pytest.approx(10.0, abs=1e-9)
    assert float(rj["inclination_rmse_deg"]) < 1e-9
    # 7 deg about a horizontal earth axis -> pure inclination
    qe = qmul(quat_axis_angle([1, 2, 0], np.deg2rad(7.0)), qt)
    r = broad.broad_errors(qe, qt, mov)
    assert r["inclination_rmse_deg"] == pytest.approx(7.0, abs=1e-9)
    assert r["heading_rmse_deg"] < 1e-6
    # a rotation about the *sensor* z axis is not a heading error unless the sensor is level
    qe = qmul(qt, quat_axis_angle([0, 0, 1], np.deg2rad(10.0)))
    assert broad.broad_errors(qe, qt, mov)["inclination_rmse_deg"] > 1.0


def test_a_diverged_estimate_never_scores_zero():
    """NaN or infinite estimates on scored samples give a NaN metric (the numpy reference, broad_errors, agrees),
    never 0: a diverged filter (e.g. Madgwick with beta = 1e30 in float32) must not look perfect to
    jaxatt.broad_score or to the fitter's loss."""
    rng = np.random.default_rng(3)
    qt = random_quats(rng, 40, 2.0)
    mov = np.ones(40, bool)
    for bad in (np.nan, np.inf):
        qe = qt.copy()
        qe[5:] = bad
        ref = broad.broad_errors(qe, qt, mov)
        rj = jax.jit(broad.broad_errors_jax)(jnp.asarray(qe), jnp.asarray(qt), jnp.asarray(mov))
        for k in broad.METRICS:
            assert np.isnan(ref[k]) and np.isnan(float(rj[k])), (bad, k, ref[k], float(rj[k]))
    # a NaN estimate outside the movement mask is not scored
    qe = qt.copy()
    qe[:5] = np.nan
    mov[:5] = False
    rj = jax.jit(broad.broad_errors_jax)(jnp.asarray(qe), jnp.asarray(qt), jnp.asarray(mov))
    assert all(float(rj[k]) < 1e-6 for k in broad.METRICS)
    # no scored sample: NaN in both (nothing to score), as in the in-scan reducer; the jnp metric said 0.0
    none = np.zeros(40, bool)
    ref = broad.broad_errors(qt, qt, none)
    rj = jax.jit(broad.broad_errors_jax)(jnp.asarray(qt), jnp.asarray(qt), jnp.asarray(none))
    acc = broad.METRIC_REDUCER.init(
        0.0, {"q": jnp.asarray(qt[0]), "use": jnp.asarray(False)}, {"q": jnp.asarray(qt[0])}
    )[0]
    fin = broad.METRIC_REDUCER.finish(acc)
    for k in broad.METRICS:
        assert np.isnan(ref[k]) and np.isnan(float(rj[k])) and np.isnan(float(fin[k])), k


def test_metric_jax_gradient_safe_with_nan_truth():
    rng = np.random.default_rng(2)
    qt = random_quats(rng, 30)
    qt[3] = np.nan
    qe = qt.copy()
    qe[5:] = qmul(random_quats(rng, 25, 0.1), qt[5:])
    mov = np.ones(30, bool)

    def loss(q):
        return broad.broad_errors_jax(q, jnp.asarray(qt), jnp.asarray(mov))["total_rmse_deg"]

    grad = jax.jit(jax.grad(loss))
    g = grad(jnp.asarray(np.where(np.isfinite(qe), qe, 1.0)))
    assert np.all(np.isfinite(np.asarray(g)))
    g0 = grad(jnp.asarray(np.where(np.isfinite(qt), qt, 1.0)))  # zero error everywhere
    assert np.all(np.isfinite(np.asarray(g0)))


# ---------------------------------------------------------------------------------------------------------
# The Mahony filter: independent references
# ---------------------------------------------------------------------------------------------------------
def broad_quat_from_acc_mag(acc, mag):
    """Transcription of BROAD's example_code/broad_utils.py quatFromAccMag / quatFromRotMat (numpy)."""
    z = acc
    x = np.cross(np.cross(z, -mag), z)
    y = np.cross(z, x)
    r = np.column_stack([x / np.linalg.norm(x), y / np.linalg.norm(y), z / np.linalg.norm(z)])
    w_sq = (1 + r[0, 0] + r[1, 1] + r[2, 2]) / 4
    x_sq = (1 + r[0, 0] - r[1, 1] - r[2, 2]) / 4
    y_sq = (1 - r[0, 0] + r[1, 1] - r[2, 2]) / 4
    z_sq = (1 - r[0, 0] - r[1, 1] + r[2, 2]) / 4
    return np.array(
        [
            np.sqrt(w_sq),
            np.copysign(np.sqrt(x_sq), r[2, 1] - r[1, 2]),
            np.copysign(np.sqrt(y_sq), r[0, 2] - r[2, 0]),
            np.copysign(np.sqrt(z_sq), r[1, 0] - r[0, 1]),
        ]
    )


def mahony_step_matrices(q, xi, gyr, acc, mag, kp, ki, dt):
    """Mahony et al. 2008's explicit complementary filter with bias, written with matrices (float64):
    v^ = R^T e_z, h = R m, b = (|h_xy|, 0, h_z), w^ = R^T b, w_mes = a x v^ + m x w^ (unit a, m; missing terms
    dropped), xi += Ki w_mes dt, Omega = gyr + xi + Kp w_mes, q <- normalise(q + dt/2 q (x) (0, Omega))."""
    r = rot(q)
    w_mes = np.zeros(3)
    if acc is not None:
        w_mes += np.cross(acc / np.linalg.norm(acc), r.T @ np.array([0.0, 0.0, 1.0]))
    if mag is not None:
        m = mag / np.linalg.norm(mag)
        h = r @ m
        w_mes += np.cross(m, r.T @ np.array([np.hypot(h[0], h[1]), 0.0, h[2]]))
    if acc is not None or mag is not None:
        xi = xi + ki * w_mes * dt
    omega = gyr + xi + kp * w_mes
    qn = q + 0.5 * dt * qmul(q, np.concatenate([[0.0], omega]))
    return qn / np.linalg.norm(qn), xi


def sample(t, g, a, m):
    return ImuSample(
        jnp.asarray(t), jnp.asarray(g), None if a is None else jnp.asarray(a), None if m is None else jnp.asarray(m)
    )


def test_mahony_init_matches_broad_and_triad_is_correct():
    """BROAD's start reproduces quatFromAccMag; the default start ("triad") is the sensor-to-NWU rotation (the
    default was BROAD's, 180 deg off for a level sensor facing north)."""
    rng = np.random.default_rng(3)
    init_b, init_t = jax.jit(mahony.make_observer("broad").init), jax.jit(mahony.make_observer().init)
    p = mahony.default_params()
    ref_up, ref_field = np.array([0.0, 0.0, 9.81]), np.array([20.0, 0.0, -44.0])  # NWU: north and down
    for _ in range(20):
        r = expm(rng.normal(size=3) * 1.5)  # sensor -> NWU
        acc, mag = r.T @ ref_up, r.T @ ref_field
        s0 = sample(0.0, np.zeros(3), acc, mag)
        q_b = np.asarray(init_b(p, s0).q)
        np.testing.assert_allclose(q_b, broad_quat_from_acc_mag(acc, mag), atol=1e-12)
        np.testing.assert_allclose(rot(np.asarray(init_t(p, s0).q)), r, atol=1e-12)
        # the BROAD start is R^T diag(-1, -1, 1) (see the module docstring)
        np.testing.assert_allclose(rot(q_b), r.T @ np.diag([-1.0, -1.0, 1.0]), atol=1e-12)


def test_mahony_step_matches_matrix_reference_and_missing_samples():
    rng = np.random.default_rng(4)
    obs = mahony.make_observer()
    kp, ki, dt = 0.9, 0.05, 0.01
    p = mahony.default_params(kp, ki)
    step = jax.jit(obs.step)
    q = random_quats(rng, 1)[0]
    st = mahony.State(jnp.asarray(0.0), jnp.asarray(q), jnp.asarray(rng.normal(size=3) * 0.01), jnp.zeros(3))
    q_ref, xi_ref = q, np.asarray(st.integral)
    g_last = np.zeros(3)
    for k in range(40):
        g = rng.normal(size=3)
        a = rng.normal(size=3) * 5 + [0, 0, 9.8]
        m = rng.normal(size=3) * 10 + [20, 0, -40]
        case = k % 5
        a_in, m_in, g_in = a.copy(), m.copy(), g.copy()
        if case == 1:
            a_in[:] = np.nan
        elif case == 2:
            m_in[1] = np.nan
        elif case == 3:
            a_in[:], m_in[:] = np.nan, 0.0
        elif case == 4:
            g_in[2] = np.nan
        st, out = step(p, st, sample(k * dt, g_in, a_in, m_in), dt)
        g_used = g_last if case == 4 else g
        q_ref, xi_ref = mahony_step_matrices(
            q_ref, xi_ref, g_used, None if case in (1, 3) else a, None if case in (2, 3) else m, kp, ki, dt
        )
        g_last = g_used
        np.testing.assert_allclose(np.asarray(st.q), q_ref, atol=1e-13)
        np.testing.assert_allclose(np.asarray(out.bias), -xi_ref, atol=1e-13)
        assert bool(out.acc_used) == (case not in (1, 3)) and bool(out.mag_used) == (case not in (2, 3))
        np.testing.assert_allclose(np.asarray(out.q), np.asarray(mahony.nwu_to_enu(st.q)), atol=1e-15)
        np.testing.assert_allclose(np.asarray(out.r), rot(out.q), atol=1e-15)
        assert float(out.t) == pytest.approx((k + 1) * dt)


def static_log(n, dt, r_true, bias, ref_up=(0.0, 0.0, 9.81), ref_field=(20.0, 0.0, -44.0)):
    acc = np.tile(r_true.T @ np.asarray(ref_up), (n, 1))
    mag = np.tile(r_true.T @ np.asarray(ref_field), (n, 1))
    return ImuSample(np.arange(n) * dt, np.tile(bias, (n, 1)), acc, mag)


def test_mahony_converges_and_estimates_bias_through_montecarlo_run():
    """Static sensor, constant gyro bias: R^ -> R and b^ -> b (Mahony et al. 2008, explicit filter with bias);
    runs through jaxatt.montecarlo.run (the generic log runner)."""
    rng = np.random.default_rng(5)
    r_true = expm(rng.normal(size=3))
    bias = np.array([0.02, -0.01, 0.015])
    dt = 0.01
    log = static_log(6000, dt, r_true, bias)
    obs_t = mahony.make_observer("triad")
    outs = montecarlo.run(obs_t, mahony.default_params(4.0, 2.0), log, dt)
    r_enu_true = rot(mahony.Q_ENU_FROM_NWU) @ r_true
    assert np.rad2deg(float(so3.angle_error(jnp.asarray(r_enu_true), outs.r[-1]))) < 1e-3
    np.testing.assert_allclose(np.asarray(outs.bias[-1]), bias, atol=1e-5)
    # A level sensor facing magnetic north: BROAD's start is 180 deg off in heading, and the filter lingers
    # there (a tilted near-equilibrium where the gravity term balances the tilt part of the magnetometer term);
    # the correct (triad) start has no error at all.
    log = static_log(6000, dt, np.eye(3), np.zeros(3))  # same length: no recompile
    r_enu = jnp.asarray(rot(mahony.Q_ENU_FROM_NWU))
    out_b = montecarlo.run(mahony.make_observer("broad"), mahony.default_params(2.0, 0.0), log, dt)
    out_t = montecarlo.run(obs_t, mahony.default_params(2.0, 0.0), log, dt)
    assert np.rad2deg(float(so3.angle_error(r_enu, out_b.r[0]))) > 179
    assert np.rad2deg(float(so3.angle_error(r_enu, out_b.r[-1]))) > 170
    assert np.rad2deg(float(jnp.max(so3.angle_error(r_enu[None], out_t.r)))) < 1e-9


def synthetic_trial(name, n, rng, rate=100.0):
    """A short rotating trial with exact measurements and truth (sensor-to-ENU), built in numpy."""
    dt = 1.0 / rate
    w = rng.normal(size=3) * 0.5
    th = np.linalg.norm(w * dt)
    dq = np.concatenate([[np.cos(th / 2)], np.sin(th / 2) * w / np.linalg.norm(w)])
    q = random_quats(rng, 1, 0.3)[0]  # sensor -> NWU
    gyr, acc, mag, qs = [], [], [], []
    for _ in range(n):
        r = rot(q)
        gyr.append(w)
        acc.append(r.T @ [0, 0, 9.81])
        mag.append(r.T @ [20.0, 0, -44.0])
        qs.append(qmul(mahony.Q_ENU_FROM_NWU, q))
        q = qmul(q, dq)
    qs = np.array(qs)
    qs[n // 3] = np.nan
    s = ImuSample(np.arange(n) * dt, np.array(gyr) + 0.01, np.array(acc), np.array(mag))
    return broad.Trial(name, s, qs, np.arange(n) > n // 10, rate)


def test_a_batch_longer_than_a_block_is_padded_to_whole_blocks():
    """T_max - 1 becomes a multiple of engine.BLOCK (one copy of the step in the scan); the padding is masked."""
    rng = np.random.default_rng(3)
    trials = [synthetic_trial("97_c", 1500, rng), synthetic_trial("96_d", 700, rng)]
    pad = broad.pad_trials(trials)
    assert pad.samples.t.shape == (2, 1 + 2 * engine.BLOCK) and list(pad.lengths) == [1500, 700]
    assert pad.mask.sum() == 2200 and not pad.movement[:, 1500:].any()
    np.testing.assert_array_equal(pad.samples.gyr[0, :1500], trials[0].samples.gyr)
    assert broad.pad_trials(trials[1:]).samples.t.shape == (1, 700)  # up to one block: the longest trial


def test_padding_alignment_and_differentiable_batch_metric():
    rng = np.random.default_rng(7)
    trials = [synthetic_trial("99_a", 300, rng), synthetic_trial("98_b", 420, rng, rate=120.0)]
    pad = broad.pad_trials(trials)
    assert pad.samples.gyr.shape == (2, 420, 3) and pad.mask.sum() == 720 and list(pad.lengths) == [300, 420]
    np.testing.assert_array_equal(pad.samples.acc[0, 300:], np.repeat(trials[0].samples.acc[-1:], 120, 0))
    assert not pad.movement[0, 300:].any() and np.all(np.isfinite(pad.samples.gyr))
    obs, p = mahony.make_observer(), mahony.default_params(1.5, 0.1)
    step = jax.jit(obs.step)
    res = broad.score(obs, p, trials, hold="next")
    tr = trials[0]
    outs = montecarlo.log_runner(obs, "next")(p, tr.samples, 1.0 / tr.rate_hz)
    q = np.asarray(outs.q)
    assert q.shape == (len(tr.samples.t), 4)
    # estimate k is at t_k: init's at t_0, then one step per sample ("next": sample k updates the estimate to t_k)
    np.testing.assert_allclose(np.asarray(outs.t), tr.samples.t, atol=1e-12)
    sample = lambda k: jax.tree_util.tree_map(lambda a: jnp.asarray(a[k]), tr.samples)  # noqa: E731
    st = jax.jit(obs.init)(p, sample(0))
    np.testing.assert_allclose(q[0], np.asarray(obs.output(p, st).q), atol=1e-15)
    for k in range(1, 4):
        st, o = step(p, st, sample(k), 1.0 / tr.rate_hz)
        np.testing.assert_allclose(q[k], np.asarray(o.q), atol=1e-14)
    # the metric accumulated in the scan (atan2 form) equals BROAD's numpy formulas on the stored estimates
    np.testing.assert_allclose(
        [res[tr.name][m] for m in broad.METRICS],
        [broad.broad_errors(q, tr.quat_true, tr.movement)[m] for m in broad.METRICS],
        rtol=1e-9,
    )

    padded = broad.pad_trials(trials)
    fn = engine.compiled(
        obs, engine.Recorded(padded.samples.t.shape[1] - 1), broad.METRIC_REDUCER, hold="next", obs_dtype=jnp.float64
    )
    item = broad.batch_item(padded, jnp.float64)

    def loss(params):
        errs = fn(None, params, item).summary
        return jnp.mean(errs["total_rmse_deg"]), errs

    value_and_grad = jax.jit(jax.value_and_grad(loss, has_aux=True))
    (_, errs), g = value_and_grad(p)
    for i, tr in enumerate(trials):
        for name in broad.METRICS:
            assert float(errs[name][i]) == pytest.approx(res[tr.name][name], abs=1e-9)
    h = 1e-6
    fd = (value_and_grad(p._replace(kp=p.kp + h))[0][0] - value_and_grad(p._replace(kp=p.kp - h))[0][0]) / (2 * h)
    assert np.isfinite(float(g.kp)) and np.isfinite(float(g.ki))
    assert float(g.kp) == pytest.approx(float(fd), rel=1e-4, abs=1e-8)
    # checkpointed segments (the fitter's default on trials) and per-step remat: the same value and gradient
    for kw in ({"checkpoint": 100}, {"checkpoint": 100, "step_remat": True}):
        seg = broad.metric_fn(obs, trials, hold="next", dtype=jnp.float64, **kw)
        v2, g2 = jax.jit(jax.value_and_grad(lambda q, f=seg: jnp.mean(f(q)["total_rmse_deg"])))(p)
        assert float(v2) == pytest.approx(float(value_and_grad(p)[0][0]), rel=1e-13), kw
        np.testing.assert_allclose([float(g2.kp), float(g2.ki)], [float(g.kp), float(g.ki)], rtol=1e-11, err_msg=kw)


# ---------------------------------------------------------------------------------------------------------
# Loading the real files
# ---------------------------------------------------------------------------------------------------------
def test_load_trial_and_groups():
    need_data()
    names = broad.list_trials(DATA)
    tr = broad.load_trial(DATA / f"{names[0]}.hdf5")
    n = len(tr.samples.t)
    assert tr.name == names[0] and tr.rate_hz == pytest.approx(285.714, abs=1e-3)
    assert tr.samples.gyr.shape == tr.samples.acc.shape == tr.samples.mag.shape == (n, 3)
    np.testing.assert_allclose(np.diff(tr.samples.t), 1.0 / tr.rate_hz, rtol=1e-9)
    assert tr.movement.dtype == bool and tr.movement.shape == (n,) and tr.movement.any()
    ok = np.all(np.isfinite(tr.quat_true), axis=1)
    np.testing.assert_allclose(np.linalg.norm(tr.quat_true[ok], axis=1), 1.0, atol=1e-6)
    assert 9.0 < np.median(np.linalg.norm(tr.samples.acc, axis=1)) < 10.6  # m/s^2
    assert 10 < np.median(np.linalg.norm(tr.samples.mag, axis=1)) < 100  # uT
    info = broad.load_trial_info(DATA)
    for name in names:
        g = broad.trial_groups(name, info)
        num = int(name[:2])
        assert ("undisturbed" in g) == (num <= 23) and ("disturbed" in g) == (num >= 24)
        assert set(broad.trial_groups(name, None)) <= set(g)  # the number-based fallback agrees
    assert broad.group_trials(names, "disturbed", info) == [n_ for n_ in names if int(n_[:2]) >= 24]
    assert "rotation" in broad.trial_groups("01_undisturbed_slow_rotation_A", info)
    with pytest.raises(ValueError):
        broad.trial_groups("no_number", None)


def test_missing_h5py_message(monkeypatch):
    monkeypatch.setitem(sys.modules, "h5py", None)
    with pytest.raises(ImportError, match=r'pip install "jaxatt\[data\]"'):
        broad.load_trial(DATA / "01_undisturbed_slow_rotation_A.hdf5")


# ---------------------------------------------------------------------------------------------------------
# (b) The published Mahony numbers (Kp = 0.74, Ki = 0.0012)
# ---------------------------------------------------------------------------------------------------------
def published_trials():
    need_data()
    pub = json.loads(PUBLISHED.read_text())
    assert pub["tagp_parameters"] == {"Kp": 0.74, "Ki": 0.0012}
    names = [n for n in broad.list_trials(DATA) if n in pub["trials"]]
    assert len(names) >= 1
    return pub, names


def test_published_mahony_float64():
    """The float64 filter against BROAD's float32 C run: agreement up to the float32 rounding of the
    reference (measured max 5.6e-4 deg over 20 trials x 3 metrics; the errors themselves are 0.7-41 deg)."""
    pub, names = published_trials()
    diffs = []
    trials = broad.load_trials(DATA, names)
    for tr, q in zip(trials, broad_protocol_quats(trials, *mahony.BROAD_TAGP, "float64")):
        res = broad.broad_errors(q, tr.quat_true, tr.movement)
        diffs += [res[k] - pub["trials"][tr.name]["tagp_parameters"][k] for k in broad.METRICS]
    assert max(abs(d) for d in diffs) < 2e-3, max(abs(d) for d in diffs)


_EXACT_SCRIPT = textwrap.dedent("""
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, sys.argv[3])
    from test_broad import broad_protocol_quats
    from jaxatt.data import broad
    data, names = sys.argv[1], sys.argv[2].split(",")
    trials = broad.load_trials(data, names)
    res = {tr.name: broad.broad_errors(q, tr.quat_true, tr.movement)
           for tr, q in zip(trials, broad_protocol_quats(trials, 0.74, 0.0012, "float32"))}
    print("RESULT" + json.dumps(res))
""")


def test_published_mahony_float32_bit_exact():
    """In float32, with XLA kept from fusing multiply-adds, the filter repeats BROAD's C run operation by
    operation: the published per-trial RMSEs come out to ~1e-14 deg (runs in a fresh process because the
    XLA flag must be set before JAX starts)."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        pytest.skip("--xla_cpu_max_isa=SSE4_2 is an x86 flag")
    pub, names = published_trials()
    env = dict(os.environ, XLA_FLAGS="--xla_cpu_max_isa=SSE4_2", JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [sys.executable, "-c", _EXACT_SCRIPT, str(DATA), ",".join(names), str(Path(__file__).parent)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    if proc.returncode != 0 and "xla_cpu_max_isa" in proc.stderr:
        pytest.skip("this XLA does not know --xla_cpu_max_isa")
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT")][-1]
    res = json.loads(line[len("RESULT") :])
    diffs = [res[n][k] - pub["trials"][n]["tagp_parameters"][k] for n in names for k in broad.METRICS]
    assert max(abs(d) for d in diffs) < 1e-10, max(abs(d) for d in diffs)


def _synthetic_trial(name="01_x", n=50, rate=100.0):
    t = np.arange(n) / rate
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    samples = ImuSample(t, np.zeros((n, 3)), np.tile([0.0, 0.0, 9.81], (n, 1)), np.tile([0.0, 20.0, -40.0], (n, 1)))
    return broad.Trial(name, samples, q, np.ones(n, bool), rate, "undisturbed")


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda tr: [tr, tr], r"unique, '01_x' appears more than once"),
        (lambda tr: [tr._replace(quat_true=tr.quat_true[:, :3])], r"quat_true must be float \(N, 4\)"),
        (lambda tr: [tr._replace(quat_true=tr.quat_true * 3)], r"quat_true\[0\] has norm 3"),
        (lambda tr: [tr._replace(quat_true=tr.quat_true * 0)], r"quat_true\[0\] has norm 0"),
        (
            lambda tr: [tr._replace(quat_true=np.r_[tr.quat_true[:10], tr.quat_true[10:] * np.inf])],
            r"quat_true contains",
        ),
        (lambda tr: [tr._replace(movement=tr.movement[:10])], r"movement must be a bool array of shape \(50,\)"),
        (lambda tr: [tr._replace(movement=tr.movement.astype(float))], r"movement must be a bool array"),
        (lambda tr: [tr._replace(rate_hz=float("nan"))], r"rate_hz must be a positive number"),
        (lambda tr: [tr._replace(rate_hz="100")], r"rate_hz must be a number of Hz, got '100'"),
        (lambda tr: [tr._replace(rate_hz=285.714)], r"rate_hz = 285.714 Hz but samples.t steps by 0.01 s"),
        (lambda tr: [tr._replace(samples=tr.samples._replace(acc=None))], r"samples.acc must have shape"),
        (lambda tr: [tr._replace(samples=tr.samples._replace(t=None))], r"samples.t must have shape \(N,\) = \(50,\)"),
        (lambda tr: [tr._replace(samples=tr.samples._replace(t=tr.samples.t[:10]))], r"samples.t must have shape"),
        (
            lambda tr: [tr._replace(samples=tr.samples._replace(t=tr.samples.t * np.nan))],
            r"samples.t must be finite \(s\): samples.t\[0\] is nan",
        ),
        (
            lambda tr: [tr._replace(samples=tr.samples._replace(t=np.r_[tr.samples.t[:5], tr.samples.t[4:-1]]))],
            r"samples.t must be strictly increasing \(s\): samples.t\[5\] = 0.04 after samples.t\[4\] = 0.04",
        ),
        (lambda tr: [tr._replace(samples=tr.samples._replace(gyr=tr.samples.gyr + np.inf))], r"gyr contains \+-inf"),
        (lambda tr: [tr._replace(samples=tr.samples._replace(gyr=tr.samples.gyr * np.nan))], r"gyr has no finite"),
        (lambda tr: [tr._replace(samples=tr.samples._replace(acc=tr.samples.acc * np.nan))], r"acc has no finite"),
    ],
)
def test_trials_built_by_hand_are_checked_with_one_line(change, match):
    """Users with their own ground truth build Trials; broad_score names the trial and the field at fault instead
    of a broadcasting error, a silently dropped trial (duplicate names) or a blame on the gains."""
    import jaxatt

    with pytest.raises(ValueError, match=match) as e:
        jaxatt.broad_score("madgwick", None, change(_synthetic_trial()))
    assert "\n" not in str(e.value)


def test_a_fit_needs_a_scored_sample_in_every_trial():
    """A trial without a scored sample would add a zero error to the fit's loss (a loss of exactly 0 and the start
    gains returned as "best" for validation trials): refused, naming the trial."""
    import jaxatt

    good, idle = _synthetic_trial("01_a"), _synthetic_trial("02_b")
    idle = idle._replace(movement=np.zeros(50, bool))
    with pytest.raises(ValueError, match=r"trial 02_b: no scored sample .* leave it out of data"):
        jaxatt.fit("madgwick", None, [good, idle], steps=1)
    nan_truth = good._replace(name="03_c", quat_true=np.full((50, 4), np.nan))
    with pytest.raises(ValueError, match=r"trial 03_c: no scored sample .* leave it out of val"):
        jaxatt.fit("madgwick", None, [good], val=[nan_truth], steps=1)


def test_every_broad_trial_passes_the_trial_check():
    need_data()
    trials = broad.load(DATA)
    assert broad.check_trials(trials, need_scored=True) == trials


def test_the_gyro_units_check_tells_rad_from_deg_on_every_broad_trial():
    """api.gyro_rotation_ratio (the front door's deg/s warning, needing no filter) on real data: every trial's gyro
    as recorded (rad/s) turns well under 5x and well over api.LOW_ROTATION_RATIO (0.05) times as far as its acc-mag
    frame, the same gyro in deg/s well over 5x and in rad/s converted again (/57) under the low ratio."""
    from jaxatt import api

    need_data()
    for tr in broad.load(DATA):
        g, a, m, t = (np.asarray(x) for x in (tr.samples.gyr, tr.samples.acc, tr.samples.mag, tr.samples.t))
        rad, deg = api.gyro_rotation_ratio(g, a, m, t), api.gyro_rotation_ratio(np.rad2deg(g), a, m, t)
        assert rad is not None and deg is not None, tr.name
        assert 2 * api.LOW_ROTATION_RATIO < rad < 2.5 and deg > 12.0, (tr.name, rad, deg)
        assert rad / np.rad2deg(1.0) < api.LOW_ROTATION_RATIO, (tr.name, rad)
        np.testing.assert_allclose(deg / rad, np.rad2deg(1.0), rtol=1e-9)  # the same windows, scaled


def test_the_truth_turning_check_tells_a_conjugated_truth_on_every_broad_trial():
    """logs.truth_gyro_agreement (load_trial's check that the truth maps the sensor to the world) on real data:
    every trial's optical truth turns as its gyro does (cosine > 0.99), its conjugate (world to sensor) below
    the warning's 0.5."""
    from jaxatt.data import logs

    need_data()
    for tr in broad.load(DATA):
        q, g, t = tr.quat_true, tr.samples.gyr, tr.samples.t
        assert logs.truth_gyro_agreement(q, g, t) > 0.99, tr.name
        assert logs.truth_gyro_agreement(q * [1.0, -1.0, -1.0, -1.0], g, t) < 0.5, tr.name


def test_a_6d_observer_on_broad_is_warned_about_its_heading(monkeypatch):
    """vqf-6d does not read the magnetometer: its BROAD total and heading errors include an arbitrary heading, and
    broad_score says so (the filter run is replaced by a stub: this checks the boundary, not VQF)."""
    import warnings

    import jaxatt

    tr = _synthetic_trial()
    fake = {tr.name: {m: 1.0 for m in broad.METRICS}}
    monkeypatch.setattr(broad, "score", lambda *a, **k: fake)
    with pytest.warns(UserWarning, match=r"vqf-6d does not use the magnetometer.*inclination_rmse_deg"):
        jaxatt.broad_score("vqf-6d", None, [tr])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jaxatt.broad_score("vqf", None, [tr])


def test_broad_score_without_a_scored_sample_says_so():
    """Trials without a scored sample (no movement flagged) have NaN metrics and no group means; broad_score warns
    instead of returning an empty table silently."""
    import jaxatt

    idle = _synthetic_trial("01_a")._replace(movement=np.zeros(50, bool))
    with pytest.warns(UserWarning, match="no trial has a scored sample"):
        s = jaxatt.broad_score("madgwick", None, [idle])
    assert np.isnan(s.trials["01_a"].total_rmse_deg) and "undisturbed" not in s.groups
