"""The filtering floor (jaxatt.fitting.floor): the Riccati recursion against Gaussian conditioning in numpy, the
Batista heading floor against its closed form, the floor below every observer's variance-free prediction, bad
input."""

import math

import jax
import numpy as np
import pytest
from scipy.linalg import expm

from jaxatt import so3, studies
from jaxatt.fitting import floor as F
from jaxatt.fitting import varfree as V


@pytest.fixture(autouse=True)
def _x64():
    prev = jax.config.values["jax_enable_x64"]
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", prev)


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _truth_numpy(rate, r0, dt, n, sub=40):
    """R(t) on the grid t = j dt / sub (j = 0 ... n sub) by RK4 on dR/dt = R S(omega(t)), re-orthonormalised."""
    h = dt / sub
    rate = jax.jit(rate)  # one program for the ~2000 calls below (eagerly, each jnp operation compiles)
    rs = [np.asarray(r0, float)]
    r = rs[0]
    for j in range(n * sub):
        t = j * h

        def f(rr, tt):
            return rr @ _skew(np.asarray(rate(tt), float))

        k1 = f(r, t)
        k2 = f(r + 0.5 * h * k1, t + 0.5 * h)
        k3 = f(r + 0.5 * h * k2, t + 0.5 * h)
        k4 = f(r + h * k3, t + h)
        r = r + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        u, _, vt = np.linalg.svd(r)
        r = u @ vt
        rs.append(r)
    return np.asarray(rs)


def _reference(rate, r0, earth_nav, refs_nav, sig_v, sig_g, dt, n, hold, prior_att, prior_bias, smooth=False):
    """tr Cov(eps_k | the samples estimate k uses), k = 0 ... n, by Gaussian conditioning on every random number
    at once (no recursion): eps_k and the measurements are linear maps of z = [eps_0, beta, g_0 .. g_n, v_0 .. v_n],
    built from the continuous-time perturbation eps' = -S(w_E) eps - R(s) (beta + g(s)) with a fine trapezoid
    rule. ``smooth``: conditioned on every sample (the RTS smoother's covariance)."""
    sub = 40
    rs = _truth_numpy(rate, r0, dt, n, sub)
    bias = prior_bias is not None
    nb = 3 if bias else 0
    m = 3 * len(refs_nav)
    nz = 3 + nb + 3 * (n + 1) + m * (n + 1)
    gi = lambda k: 3 + nb + 3 * k  # noqa: E731
    vi = lambda k: 3 + nb + 3 * (n + 1) + m * k  # noqa: E731
    var = np.concatenate(
        [np.full(3, prior_att**2), np.full(nb, (prior_bias or 0.0) ** 2), np.full(3 * (n + 1), sig_g**2)]
        + [np.full(m * (n + 1), 1.0)]
    )
    a = -_skew(earth_nav)
    e = np.zeros((3, nz))
    e[:, :3] = np.eye(3)
    eps = [e.copy()]
    s_grid = np.linspace(0.0, dt, sub + 1)
    wts = np.full(sub + 1, dt / sub)
    wts[[0, -1]] *= 0.5
    for k in range(n):
        nxt = expm(a * dt) @ e
        for j, s in enumerate(s_grid):
            tau = s / dt
            w0, w1 = {"zoh": (1.0, 0.0), "next": (0.0, 1.0), "linear": (1.0 - tau, tau)}[hold]
            kern = wts[j] * expm(a * (dt - s)) @ rs[k * sub + j]
            if bias:
                nxt[:, 3:6] -= kern
            nxt[:, gi(k) : gi(k) + 3] -= w0 * kern
            nxt[:, gi(k + 1) : gi(k + 1) + 3] -= w1 * kern
        e = nxt
        eps.append(e.copy())
    ys = []
    for k in range(n + 1):
        rk = rs[k * sub]
        h = np.vstack([rk.T @ _skew(r) for r in refs_nav])  # d(R^T r)/d eps, R = exp(S(eps)) R_bar
        y = h @ eps[k]
        y[:, vi(k) : vi(k) + m] += np.eye(m) * sig_v
        ys.append(y)
    cov = np.diag(var)
    out = []
    for k in range(n + 1):
        seen = range(0, n + 1) if smooth else range(0, max(k, 1)) if hold == "zoh" else range(0, k + 1)
        ymap = np.vstack([ys[j] for j in seen])
        s_ee = eps[k] @ cov @ eps[k].T
        s_ey = eps[k] @ cov @ ymap.T
        s_yy = ymap @ cov @ ymap.T
        out.append(np.trace(s_ee - s_ey @ np.linalg.solve(s_yy, s_ey.T)))
    return np.asarray(out)


@pytest.mark.parametrize("hold", ["zoh", "linear", "next"])
def test_riccati_matches_gaussian_conditioning(hold):
    """Two constant references with gyro bias (complementary study) and, for zoh, the Earth-rate coupling of the
    Batista problem: the Riccati recursion equals conditioning the joint Gaussian on the same samples."""
    cfg = dict(scenario="two_constant", gyro_noise_std=0.02, meas_noise_std=0.05, duration=1.0, dt=0.05)
    s = studies.get("complementary").setup(**cfg)
    scn = s.scenario
    refs_nav = np.asarray(scn.ref_inertial.at(0.0))
    n = 12
    prior = F.Prior(0.1, 0.01)
    got = F.floor(scn, duration=n * 0.05, dt=0.05, hold=hold, prior=prior, every=1)["records"]["mean_sq_deg2"]
    ref = _reference(scn.rates.rate, scn.r0, np.zeros(3), refs_nav, 0.05, 0.02, 0.05, n, hold, prior.attitude_rad, 0.01)
    np.testing.assert_allclose(got, ref * (180 / np.pi) ** 2, rtol=2e-6)
    sm = F.floor(scn, duration=n * 0.05, dt=0.05, hold=hold, prior=prior, smoother=True)["smoothed"]["all"]
    ref_s = _reference(
        scn.rates.rate, scn.r0, np.zeros(3), refs_nav, 0.05, 0.02, 0.05, n, hold, prior.attitude_rad, 0.01, True
    )
    np.testing.assert_allclose(sm["mean_sq_deg2"], np.mean(ref_s) * (180 / np.pi) ** 2, rtol=2e-6)
    if hold == "zoh":  # Earth rate coupling (x1e3 so that it shows over 12 steps), no bias, one vector
        g = studies.get("batista-ges").setup(duration=1.0, dt=0.05)
        sc = g.scenario._replace(earth_rate_nav=g.scenario.earth_rate_nav * 1e3)
        got = F.floor(sc, duration=n * 0.05, dt=0.05, prior=prior, every=1)["records"]["mean_sq_deg2"]
        sig_g = float(sc.gyro_arw) / math.sqrt(0.05)
        ref = _reference(
            sc.rates.rate,
            sc.r0,
            np.asarray(sc.earth_rate_nav),
            [np.asarray(sc.ref_nav)],
            float(sc.vec_noise_std),
            sig_g,
            0.05,
            n,
            "zoh",
            prior.attitude_rad,
            None,
        )
        np.testing.assert_allclose(got, ref * (180 / np.pi) ** 2, rtol=2e-6)


def test_batista_heading_floor_closed_form():
    """Heading variance about m_hat against (q / c) coth(c t) (heading_floor_closed_form): exact in the limit of a
    noise-free magnetometer (here its noise / 1000: tilt settling time sqrt(r / q) = 0.05 s), and with the paper's
    150 nT above it by the end effect of the tilt measurement only, less than 3 sqrt(r / q) / t."""
    dt = 0.1
    for scale, tol in ((1e-3, None), (1.0, "end")):
        s = studies.get("batista-ges").setup(dt=dt, mag_noise_nT=150.0 * scale)
        res = F.floor(s.scenario, duration=3600.0, dt=dt, every=100, windows=(("w", 600.0, math.inf),))
        rec = res["records"]
        m = np.asarray(s.scenario.ref_nav) / np.linalg.norm(np.asarray(s.scenario.ref_nav))
        sel = rec["t"] >= 600.0
        t = rec["t"][sel]
        ph = np.einsum("i,kij,j->k", m, rec["p_att"][sel], m)
        ratio = ph / F.heading_floor_closed_form(s.scenario, t)
        q = float(s.scenario.gyro_arw) ** 2
        r = (150.0 * scale / np.linalg.norm(np.asarray(s.scenario.ref_nav))) ** 2 * dt
        tau = math.sqrt(r / q)
        if tol is None:
            np.testing.assert_allclose(ratio, 1.0, atol=1e-3)
        else:
            assert np.all(ratio >= 1.0 - 1e-4) and np.all(ratio - 1.0 <= 3.0 * tau / t), (ratio, tau)
            assert np.all(ratio - 1.0 >= tau / t)  # the end effect is there: the limit is approached from above


GES_TRUTH = {"r_hat_0": (1, 0, 0, 0, 1, 0, 0, 0, 1)}


def _at_truth(study):
    """Config overrides that start each study's observer at the truth (nominal run), 6 s long."""
    base = {"duration": 6.0}
    if study == "batista-ges":
        s = studies.get(study).setup()
        x2 = np.cross(np.asarray(s.scenario.ref_nav), np.asarray(s.scenario.earth_rate_nav))
        return {**base, **GES_TRUTH, "x2_0": tuple(x2)}
    if study == "batista-so3":
        s = studies.get(study).setup()
        m, w = np.asarray(s.scenario.ref_nav), np.asarray(s.scenario.earth_rate_nav)
        return {**base, **GES_TRUTH, "v_hat_0": tuple(np.cross(m, np.cross(m, w)))}
    if study == "nlio-case1":
        return {**base, "random_init": False}
    return {
        **base,
        "scenario": "two_constant",
        "k_i": 0.1,
        "gyro_noise_std": 0.01,
        "meas_noise_std": 0.05,
        "r_hat_0_euler_deg": (20.0, -10.0, 30.0),
    }


@pytest.mark.parametrize("study", ["batista-ges", "batista-so3", "nlio-case1", "complementary"])
def test_floor_below_the_observer(study):
    """The Kalman filter of the linearised problem with a known start (Prior(0, 0)) is the best estimator of it:
    the noise-driven part of every observer's expected squared error (E[theta^2] - |mu|^2, varfree, started at
    the truth, paper gains) is at least the floor, window by window."""
    cfg = _at_truth(study)
    wins = (("a", 0.5, 2.0), ("b", 2.0, 4.0), ("c", 4.0, 6.0))
    pred = V.predict_study(study, windows=wins, errors=False, **cfg)["windows"]
    fl = F.floor_study(study, windows=wins, prior=F.Prior(0.0, 0.0), **cfg)["windows"]
    for w in ("a", "b", "c"):
        noise_part = pred[w]["mean_sq_deg2"] - pred[w]["bias_rms_deg"] ** 2
        assert fl[w]["count"] == pred[w]["count"]
        assert 0.0 < fl[w]["mean_sq_deg2"] <= noise_part * (1 + 1e-9), (study, w, fl[w], noise_part)


def test_bad_input():
    s = studies.get("batista-ges").setup(duration=1.0)
    with pytest.raises(ValueError, match="dt must be"):
        F.floor(s.scenario, duration=1.0, dt=0.0)
    with pytest.raises(ValueError, match="hold"):
        F.floor(s.scenario, duration=1.0, dt=0.1, hold="cubic")
    with pytest.raises(ValueError, match="prior"):
        F.floor(s.scenario, duration=1.0, dt=0.1, prior=F.Prior(-1.0, 0.0))
    with pytest.raises(ValueError, match="starts at"):
        F.floor(s.scenario, duration=1.0, dt=0.1, windows=(("late", 5.0, math.inf),))
    with pytest.raises(ValueError, match="without noise|no noise"):
        F.floor(s.scenario._replace(noise_scale=s.scenario.noise_scale * 0), duration=1.0, dt=0.1)
    with pytest.raises(ValueError, match="window"):
        F.floor(s.scenario, duration=1.0, dt=0.1, windows=())
    jax.config.update("jax_enable_x64", False)
    with pytest.raises(ValueError, match="float64"):
        F.floor(s.scenario, duration=1.0, dt=0.1)


def _mekf_initial(p, z):
    """The MEKF's initial estimate drawn from the floor's prior: attitude 0.1 rad, bias 0.05 rad/s per axis."""
    return p._replace(r_hat_0=p.r_hat_0 @ so3.exp(0.1 * z[:3]), b_hat_0=p.b_hat_0 + 0.05 * z[3:6])


def test_mekf_reaches_the_floor():
    """The floor is attained: the MEKF (Markley & Crassidis 2014, Sec. 6.2) given the scenario's own noise model,
    no bias random walk and an initial estimate drawn from the floor's prior about the truth
    (varfree.InitialNoise) is the Kalman filter of the same linearised problem, so the random part of its
    expected squared error (varfree) equals the floor (its nominal error, the lag of held samples, is the
    rest)."""
    from jaxatt.observers import mekf
    from jaxatt.studies import nlio

    cfg = nlio.config("nlio-case1", random_init=False)
    scn = nlio.scenario(cfg)
    va, vm = nlio.noise_variances(cfg)
    p = mekf.default_params(
        np.array([0.0, 0.0, cfg.gravity]),
        cfg.mag_ref_nav,
        gyro_noise_std=cfg.gyro_noise_std,
        bias_rw=0.0,
        r_acc=va * np.eye(3),
        r_mag=vm * np.eye(3),
        p0_att=0.1**2,
        p0_bias=0.05**2,
        b_hat_0=cfg.gyro_bias,  # started at the truth: the nominal run is the true one
        dtype=np.float64,
    )
    wins = (("a", 0.5, 3.0), ("b", 3.0, 8.0))
    kw = dict(duration=8.0, dt=cfg.dt, windows=wins, hold="zoh")
    fl = F.floor(scn, prior=F.Prior(0.1, 0.05), **kw)["windows"]
    pr = V.predict(mekf.make_observer(), scn, p, track="all", initial=V.InitialNoise(_mekf_initial, 6), **kw)
    pr = pr["windows"]
    for w in ("a", "b"):
        noise_part = pr[w]["mean_sq_deg2"] - pr[w]["bias_rms_deg"] ** 2
        np.testing.assert_allclose(noise_part, fl[w]["mean_sq_deg2"], rtol=1e-4)


@pytest.mark.parametrize(
    "change, match",
    [
        ({"duration": math.nan}, "duration must be a finite positive"),
        ({"duration": math.inf}, "duration must be a finite positive"),
        ({"duration": -1.0}, "duration must be a finite positive"),
        ({"dt": math.nan}, "dt must be a finite positive"),
        ({"dt": "0.1"}, "dt must be a number of seconds"),
        ({"duration": 1e12, "dt": 1e-3}, r"at most 2147483647 steps per run"),
        ({"every": -1}, "every must be >= 0"),
        ({"every": 1.5}, "every must be a whole number"),
        ({"prior": (1.0, "a")}, r"prior must be a Prior\(attitude_rad, bias_rad_s\)"),
        ({"prior": 0.1}, r"prior must be a Prior\(attitude_rad, bias_rad_s\)"),
        ({"bias": "no"}, "bias must be True, False or None"),
        ({"smoother": "yes"}, "smoother must be True or False"),
    ],
)
def test_floor_refuses_bad_times_every_and_options(change, match):
    """floor: NaN / inf / negative times, more steps than the engine counts (types.MAX_STEPS), a negative or
    fractional ``every`` and options of the wrong kind are one clear line, before anything runs."""
    s = studies.get("batista-ges").setup(duration=1.0)
    with pytest.raises(ValueError, match=match) as e:
        F.floor(s.scenario, **{"duration": 1.0, "dt": 0.1, **change})
    assert "\n" not in str(e.value)


def test_floor_study_refuses_bad_every_and_settings():
    for kw, match in (
        ({"every": -1}, "every must be >= 0"),
        ({"every": 0.5}, "every must be a whole number"),
        ({"duration": "x"}, "batista-ges setting 'duration' must be a finite number"),
        ({"gyro_bias": [1, 2]}, "batista-ges setting 'gyro_bias' must be a list of 3 finite numbers"),
    ):
        with pytest.raises(ValueError, match=match) as e:
            F.floor_study("batista-ges", **{"duration": 1.0, **kw})
        assert "\n" not in str(e.value)
