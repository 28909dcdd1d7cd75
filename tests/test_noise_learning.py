"""Noise parameters of the MEKF learnt by maximum likelihood of its innovations (loss kind "innovation_nll")
through the one fitter, on the nlio-case1 scenario whose true noise levels are known (issue 20 item 3)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxatt
from jaxatt import montecarlo, so3, studies
from jaxatt.fitting import losses
from jaxatt.observers import mekf
from jaxatt.studies import nlio

# 20-s runs, true start (the floor's information pattern after the transient), bias learnt from a wide prior,
# no bias random walk (the scenario's bias is constant).
CFG = dict(duration=20.0, random_init=False, mekf_bias_rw=1e-9, mekf_p0_bias=0.05**2)


def test_innovation_nll_against_numpy():
    """The MEKF's per-update NLL is -log N(nu; 0, S) with S = H P H^T + R (numpy, independent of the filter)."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(6, 6))
    cov = a @ a.T * 1e-3 + 1e-4 * np.eye(6)
    r_meas = np.diag([0.2, 0.3, 0.25])
    q = np.array([0.9, 0.1, -0.3, 0.2])
    q /= np.linalg.norm(q)
    ref = np.array([0.0, 0.0, 9.81])
    y = rng.normal(size=3)
    *_, nll = mekf._update(jnp.asarray(q), jnp.zeros(3), jnp.asarray(cov), jnp.asarray(y), ref, r_meas, True)
    rot = np.asarray(so3.quat_to_matrix(jnp.asarray(q)))
    h = rot.T @ ref
    hm = np.concatenate([np.asarray(so3.skew(jnp.asarray(h))), np.zeros((3, 3))], axis=1)
    s = hm @ cov @ hm.T + r_meas
    nu = y - h
    expected = 0.5 * (np.linalg.slogdet(s)[1] + nu @ np.linalg.solve(s, nu) + 3 * np.log(2 * np.pi))
    np.testing.assert_allclose(float(nll), expected, rtol=1e-12)
    *_, nll_missing = mekf._update(jnp.asarray(q), jnp.zeros(3), jnp.asarray(cov), jnp.asarray(y), ref, r_meas, False)
    assert float(nll_missing) == 0.0


def _angle_deg(params, keys):
    """Mean angle error (deg) over the steady window of CFG, held-out runs ``keys``."""
    s = studies.get("nlio-case1").setup("mekf", **CFG)
    spec = losses.loss_spec("angle_sq", steady_start=s.loss_windows["steady"][0])
    f = losses.make_loss_fn(s.observer, duration=s.duration, dt=s.dt, spec=spec, hold=s.hold)
    return float(jnp.mean(f(s.scenario, params, keys)[1]["window_angle_deg"][0]))


def test_mekf_noise_levels_recovered_by_likelihood():
    """Started 10x off in every noise std (gyro 10x, R_acc / 100, R_mag x 100), maximum likelihood of the
    innovations on 4 simulated 20-s runs recovers the true levels: R_acc, R_mag per axis within 15 % (the
    estimate's spread from 4 x 2000 samples is ~2 %, the rest the not fully converged optimiser), the gyro noise
    within 40 % (the likelihood is flat in it: over 3e-4 ... 3e-3 rad/s it changes by < 1e-3 nats per step), and
    the learnt MEKF's error on held-out runs is within 5 % of the MEKF given the true noise model (which attains
    the Kalman floor, tests/test_floor.py), where the start is far above it."""
    cfg = nlio.config("nlio-case1", **CFG)
    va, vm = nlio.noise_variances(cfg)
    truth = studies.get("nlio-case1").setup("mekf", **CFG).params

    def wrong(p):
        return p._replace(gyro_noise_std=p.gyro_noise_std * 10, r_acc=p.r_acc / 100, r_mag=p.r_mag * 100)

    kw = dict(loss="innovation_nll", config=CFG, train_runs=4, batch=4, val_runs=0, lr=0.1, dtype=np.float64)
    # two stages of the same fitter: R first (the gyro noise barely moves the likelihood until R is right), then all
    r1 = jaxatt.fit("mekf", None, "nlio-case1", start=wrong, tune=["r_acc", "r_mag"], steps=30, **kw)
    r2 = jaxatt.fit("mekf", r1.params, "nlio-case1", tune=["gyro_noise_std", "r_acc", "r_mag"], steps=45, **kw)
    p = r2.params
    np.testing.assert_allclose(np.diag(np.asarray(p.r_acc)) / va, 1.0, atol=0.15)
    np.testing.assert_allclose(np.diag(np.asarray(p.r_mag)) / vm, 1.0, atol=0.15)
    assert 0.6 < float(p.gyro_noise_std) / cfg.gyro_noise_std < 1.4, float(p.gyro_noise_std)
    held_out = montecarlo.run_keys(1, list(range(4)))
    e_true, e_learnt, e_start = (_angle_deg(q, held_out) for q in (truth, p, wrong(truth)))
    assert e_learnt < 1.05 * e_true, (e_learnt, e_true)
    assert e_start > 1.2 * e_true, (e_start, e_true)


def test_bad_input():
    with pytest.raises(ValueError, match="not 'vqf'"):
        studies.get("nlio-case1").setup("vqf")
    s = studies.get("nlio-case1").setup(duration=1.0)  # NLIO-FG: its Out has no nll
    f = losses.make_loss_fn(s.observer, duration=0.05, dt=s.dt, spec=losses.loss_spec("innovation_nll"), hold=s.hold)
    with pytest.raises(ValueError, match="innovation_nll"):
        f(s.scenario, s.params, montecarlo.run_keys(0, [0]))
    jax.block_until_ready(0)
