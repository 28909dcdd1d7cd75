"""MEKF with gyro-bias states (Markley & Crassidis): agreement with an independent plain-numpy implementation
on a noisy log, local convergence (noise-free, small initial errors), covariance sanity, bad input."""

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from jaxatt import montecarlo, so3  # noqa: E402
from jaxatt.observers import mekf  # noqa: E402
from jaxatt.sim import ahrs  # noqa: E402

DT = 0.01
ACC_REF = np.array([0.0, 0.0, ahrs.PAPER_GRAVITY])
MAG_REF = np.array(ahrs.PAPER_MAG_NED_G)
BIAS = np.array(ahrs.PAPER_GYRO_BIAS)


# ---------------------------------------------------------------------------------------------------------
# An independent numpy MEKF (written from the textbook equations, sharing no code with jaxatt)
# ---------------------------------------------------------------------------------------------------------
def _sk(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _qmul(p, q):
    pw, pv, qw, qv = p[0], p[1:], q[0], q[1:]
    return np.concatenate([[pw * qw - pv @ qv], pw * qv + qw * pv + np.cross(pv, qv)])


def _qrot(q):
    """Body-to-reference rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _qexp(phi):
    th = np.linalg.norm(phi)
    if th < 1e-12:
        return np.concatenate([[1.0], 0.5 * phi])
    return np.concatenate([[np.cos(th / 2)], np.sin(th / 2) * phi / th])


def _expm_skew(phi):
    th = np.linalg.norm(phi)
    s = _sk(phi)
    if th < 1e-12:
        return np.eye(3) + s
    return np.eye(3) + np.sin(th) / th * s + (1 - np.cos(th)) / th**2 * s @ s


def numpy_mekf(samples, p, hold):
    q = np.asarray(so3.quat_canonical(so3.matrix_to_quat(jnp.asarray(p.r_hat_0))))
    b = np.asarray(p.b_hat_0, float).copy()
    P = np.asarray(p.p0, float).copy()
    sg, su = float(p.gyro_noise_std), float(p.bias_rw)
    refs = ((np.asarray(p.acc_ref_nav), np.asarray(p.r_acc)), (np.asarray(p.mag_ref_nav), np.asarray(p.r_mag)))
    gyr, acc, mag = (np.asarray(a, float) for a in (samples.gyr, samples.acc, samples.mag))

    def measure(q, b, P, ys):
        for y, (ref, r) in zip(ys, refs):
            h = _qrot(q).T @ ref
            H = np.hstack([_sk(h), np.zeros((3, 3))])
            K = P @ H.T @ np.linalg.inv(H @ P @ H.T + r)
            dx = K @ (y - h)
            A = np.eye(6) - K @ H
            P = A @ P @ A.T + K @ r @ K.T
            q = _qmul(q, _qexp(dx[:3]))
            q /= np.linalg.norm(q)
            b = b + dx[3:]
        return q, b, P

    def propagate(q, b, P, g):
        w = g - b
        q = _qmul(q, _qexp(w * DT))
        q /= np.linalg.norm(q)
        Phi = np.eye(6)
        Phi[:3, :3] = _expm_skew(-w * DT)
        Phi[:3, 3:] = -DT * (np.eye(3) - 0.5 * DT * _sk(w))
        Q = np.zeros((6, 6))
        Q[:3, :3] = ((sg * DT) ** 2 + su**2 * DT**3 / 3) * np.eye(3)
        Q[:3, 3:] = Q[3:, :3] = -0.5 * su**2 * DT**2 * np.eye(3)
        Q[3:, 3:] = su**2 * DT * np.eye(3)
        return q, Phi @ P @ Phi.T + Q

    qs, bs, sig = [], [], []
    for k in range(len(gyr) - 1):
        if hold == "zoh":
            q, b, P = measure(q, b, P, (acc[k], mag[k]))
            q, P = propagate(q, b, P, gyr[k])
        else:
            q, P = propagate(q, b, P, 0.5 * (gyr[k] + gyr[k + 1]))
            q, b, P = measure(q, b, P, (acc[k + 1], mag[k + 1]))
        qs.append(q * np.sign(q[0]))
        bs.append(b.copy())
        sig.append(np.sqrt(np.diag(P)))
    return np.array(qs), np.array(bs), np.array(sig)


@pytest.fixture(scope="module")
def noisy_log():
    scn = ahrs.AhrsScenario.make(mix_prob=0.2, mix="sum")
    return montecarlo.simulate_log(scn, duration=20.0, dt=DT, seed=3)


@pytest.mark.parametrize("hold", ["zoh", "linear"])
def test_matches_independent_numpy_implementation(noisy_log, hold):
    samples, truth = noisy_log
    r0 = np.asarray(so3.exp(jnp.asarray([0.2, -0.3, 0.5])))
    p = mekf.default_params(
        ACC_REF,
        MAG_REF,
        acc_noise_std=0.1,
        mag_noise_std=0.02,
        bias_rw=1e-4,
        r_hat_0=r0,
        b_hat_0=(0.01, 0.0, -0.01),
        p0_att=1e-2,
        p0_bias=1e-5,
    )
    out = montecarlo.run(mekf.make_observer(), p, samples, DT, hold=hold, validate=mekf.check_params)
    q_np, b_np, sig_np = numpy_mekf(samples, p, hold)
    assert out.q.shape[0] == samples.t.shape[0]  # T estimates: row 0 is init's, rows 1... the steps
    q_j = np.asarray(out.q) * np.sign(np.asarray(out.q)[:, :1])
    np.testing.assert_allclose(q_j[1:], q_np, atol=1e-10)
    np.testing.assert_allclose(np.asarray(out.bias)[1:], b_np, atol=1e-11)
    np.testing.assert_allclose(np.asarray(out.sigma)[1:], sig_np, rtol=1e-8)
    np.testing.assert_allclose(np.asarray(out.r)[1:], np.array([_qrot(q) for q in q_np]), atol=1e-10)
    # estimate 0 is the initial state
    np.testing.assert_allclose(np.asarray(out.r)[0], r0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(out.bias)[0], np.asarray(p.b_hat_0), atol=0)
    np.testing.assert_allclose(np.asarray(out.sigma)[0], np.sqrt(np.diag(np.asarray(p.p0))), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(out.t), np.asarray(samples.t), atol=1e-9)
    # and it does estimate: the attitude error (33 deg at the start, ~17 deg after the first update) shrinks
    ang = np.rad2deg(np.asarray(so3.angle_error(truth.r, out.r)))
    assert ang[0] > 30.0 and ang[1] > 10.0 and ang[-1] < 1.0


def test_local_convergence_noise_free():
    """From small initial errors (<= 15 deg, 0.03 rad/s of bias) the MEKF converges on noise-free data (its
    model noise is kept: the gains are those of a real filter); the covariance stays symmetric positive."""
    samples, truth = montecarlo.simulate_log(ahrs.AhrsScenario.make(noise_scale=0.0), duration=150.0, dt=DT)
    rng = np.random.default_rng(0)
    base = mekf.default_params(ACC_REF, MAG_REF, bias_rw=1e-5)
    r0s = [
        np.asarray(so3.exp(jnp.asarray(a)))
        for a in (
            np.deg2rad(15.0) * np.array([1.0, 0, 0]),
            np.deg2rad(10.0) * rng.normal(size=3) / np.sqrt(3),
            np.deg2rad(15.0) * np.array([0, 0.6, 0.8]),
            np.zeros(3),
        )
    ]
    batch = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *[base._replace(r_hat_0=jnp.asarray(r)) for r in r0s])
    run = jax.jit(jax.vmap(montecarlo.log_runner(mekf.make_observer(), "linear"), in_axes=(0, None, None)))
    out = run(batch, samples, jnp.full(samples.t.shape[0] - 1, DT))
    ang = np.rad2deg(np.asarray(so3.angle_error(jnp.asarray(truth.r)[None], out.r)))
    assert np.max(ang[:, 1]) > 8.0  # (after the first update, from 15 deg)
    assert np.all(ang[:, -1] < 0.02), ang[:, -1]
    bias_err = np.linalg.norm(np.asarray(out.bias)[:, -1] - BIAS, axis=-1)
    assert np.all(bias_err < 1e-4), bias_err  # from 0.029 rad/s
    assert np.all(np.asarray(out.sigma) > 0) and np.all(np.isfinite(np.asarray(out.sigma)))
    sig_b = np.asarray(out.sigma)[..., 3:]
    assert np.all(sig_b[:, -1] < sig_b[:, 0] / 3)  # the bias becomes known


def test_missing_samples(noisy_log):
    samples, truth = noisy_log
    acc, mag, gyr = np.array(samples.acc), np.array(samples.mag), np.array(samples.gyr)
    acc[300:400] = np.nan
    mag[500:900] = np.nan
    gyr[1000:1003] = np.nan
    s = samples._replace(acc=jnp.asarray(acc), mag=jnp.asarray(mag), gyr=jnp.asarray(gyr))
    p = mekf.default_params(ACC_REF, MAG_REF, b_hat_0=BIAS, acc_noise_std=0.1, mag_noise_std=0.02)
    out = montecarlo.run(mekf.make_observer(), p, s, DT, hold="linear")
    for leaf in out:
        assert np.all(np.isfinite(np.asarray(leaf)))
    sig = np.asarray(out.sigma)
    assert sig[899, 2] > sig[499, 2]  # heading uncertainty grows while the magnetometer is missing
    assert float(so3.angle_error(truth.r[-1], out.r[-1])) < np.deg2rad(1.0)


def test_bad_input_gets_clear_errors():
    p = mekf.default_params(ACC_REF, MAG_REF)
    with pytest.raises(ValueError, match="parallel"):
        mekf.default_params(ACC_REF, -ACC_REF)
    with pytest.raises(ValueError, match="rotation"):
        mekf.check_params(p._replace(r_hat_0=2.0 * jnp.eye(3)))
    with pytest.raises(ValueError, match="p0"):
        mekf.check_params(p._replace(p0=-p.p0))
    with pytest.raises(ValueError, match="r_mag"):
        mekf.check_params(p._replace(r_mag=jnp.zeros((3, 3))))
    with pytest.raises(ValueError, match="bias_rw"):
        mekf.check_params(p._replace(bias_rw=jnp.asarray(-1.0)))
    with pytest.raises(ValueError, match="shape"):
        mekf.check_params(p._replace(b_hat_0=jnp.zeros(2)))
