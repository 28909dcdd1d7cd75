"""The offline mode (jaxatt.smoothing): the fusion against a numpy/scipy reference, the time reversal, the
smoothed estimate against the truth of a simulated recording, a batch of padded recordings against each alone,
the gradient through both passes against finite differences, and the front door's checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from broad_data import DATA, need_data
from scipy.spatial.transform import Rotation, Slerp

import jaxatt
from jaxatt import montecarlo, so3
from jaxatt import smoothing as S
from jaxatt.fitting import parametrize as P
from jaxatt.observers import registry


def _rot(q):
    return Rotation.from_quat(np.asarray(q)[..., [1, 2, 3, 0]])


def _quat(r):
    q = r.as_quat()[..., [3, 0, 1, 2]]
    return np.where(q[..., :1] < 0, -q, q)


def _same_rotation(a, b, tol):
    """max over rows of 1 - |<a, b>| (0 for the same rotation, either sign)."""
    return float(np.max(1.0 - np.abs(np.sum(np.asarray(a) * np.asarray(b), axis=-1)))) <= tol


# ------------------------------------------------------------------------------------------------------------
# The fusion and the uncertainty against numpy
# ------------------------------------------------------------------------------------------------------------
def test_fusion_and_uncertainty_match_a_numpy_reference():
    rng = np.random.default_rng(0)
    n = 200
    qf = _quat(Rotation.random(n, random_state=1))
    # backward estimates a few degrees to ~120 deg away
    qb = _quat(Rotation.from_rotvec(rng.normal(size=(n, 3)) * np.linspace(0.01, 1.2, n)[:, None]) * _rot(qf))
    wi, wh = rng.uniform(size=n), rng.uniform(size=n)
    got = np.asarray(S.fuse(jnp.asarray(qf), jnp.asarray(qb), jnp.asarray(wi), jnp.asarray(wh)))
    # reference: delta = log(Rb Rf^T) in the nav frame, midpoint, anisotropic weights about it
    delta = (_rot(qb) * _rot(qf).inv()).as_rotvec()
    mid = Rotation.from_rotvec(delta / 2) * _rot(qf)
    w = np.stack([wi, wi, wh], axis=-1)
    ref = _quat(Rotation.from_rotvec((w - 0.5) * delta) * mid)
    assert _same_rotation(got, ref, 1e-13)
    # equal weights: slerp; 0 and 1: the estimates themselves; swapping estimates and weights: the same rotation
    for k in range(0, n, 37):
        s = Slerp([0, 1], Rotation.concatenate([_rot(qf[k]), _rot(qb[k])]))
        q = S.fuse(jnp.asarray(qf[k]), jnp.asarray(qb[k]), jnp.asarray(wi[k]), jnp.asarray(wi[k]))
        assert _same_rotation(q, _quat(s([wi[k]]))[0], 1e-13)
    zero, one = jnp.zeros(n), jnp.ones(n)
    assert _same_rotation(S.fuse(jnp.asarray(qf), jnp.asarray(qb), zero, zero), qf, 1e-13)
    assert _same_rotation(S.fuse(jnp.asarray(qf), jnp.asarray(qb), one, one), qb, 1e-13)
    swapped = S.fuse(jnp.asarray(qb), jnp.asarray(qf), jnp.asarray(1 - wi), jnp.asarray(1 - wh))
    assert _same_rotation(swapped, got, 1e-13)
    # inclination-only fusion keeps the forward heading: the fused and forward up-vectors in the body frame
    # follow the swing; the heading of q_f is untouched when q_b differs by a pure yaw
    yaw = _quat(Rotation.from_rotvec(np.array([0, 0, 0.7])) * _rot(qf))
    q6 = S.fuse_inclination(jnp.asarray(qf), jnp.asarray(yaw), jnp.asarray(wi))
    assert _same_rotation(q6, qf, 1e-13)

    # uncertainty: P_0 = start, P_k = (1 - g)^2 (P_{k-1} + dt), g = trust (1 - exp(-dt / tau))
    trust = rng.uniform(size=(3, 500)) * (rng.uniform(size=(3, 500)) > 0.3)
    dt = rng.uniform(0.005, 0.02, size=(3, 500))
    got = np.asarray(S.uncertainty(jnp.asarray(trust), jnp.asarray(dt), 2.0, 7.0))
    ref = np.empty_like(trust)
    ref[:, 0] = 7.0
    for k in range(1, 500):
        g = trust[:, k] * (1 - np.exp(-dt[:, k] / 2.0))
        ref[:, k] = (1 - g) ** 2 * (ref[:, k - 1] + dt[:, k])
    np.testing.assert_allclose(got, ref, rtol=1e-12)


def test_reverse_indices_align_the_gyro_with_the_interval_it_covers():
    n, length = 12, 9
    for hold in ("next", "zoh", "linear"):
        meas, gyr = (np.asarray(a) for a in S.reverse_indices(n, length, hold))
        assert list(meas[:length]) == list(range(length - 1, -1, -1)) and np.all(meas[length:] == 0)
        for j in range(1, length):  # reversed step j covers the forward interval [L-1-j, L-j]
            used = {"next": j, "zoh": j - 1, "linear": j}[hold]  # the reversed sample the step reads its gyro from
            want = {"next": length - j, "zoh": length - 1 - j, "linear": None}[hold]
            if want is not None:
                assert gyr[used] == want, (hold, j)
        if hold == "linear":
            assert np.array_equal(gyr, meas)


# ------------------------------------------------------------------------------------------------------------
# On a simulated recording
# ------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sim():
    """20 s at 100 Hz of the simulated AHRS (constant gyro bias, no rest at the start: the causal filters'
    start transient is long), gyro sample 0 = sample 1 (see the time-reversal test)."""
    scn = jaxatt.api.ahrs_scenario(gyro_noise_std=2e-3, acc_noise_std=0.1, mag_noise_std=0.5)
    s, truth = montecarlo.simulate_log(scn, duration=20.0, dt=0.01, seed=3)
    g, a, m = (np.array(x, np.float64) for x in (s.gyr, s.acc, s.mag))
    g[0] = g[1]
    return g, a, m, np.asarray(truth.r)


def _reversed(g, a, m):
    """The time-reversed recording, hold "next": gyro sample j of the reversed recording covers the forward
    interval ending at sample L - j, negated."""
    idx = np.concatenate([[len(g) - 1], np.arange(len(g) - 1, 0, -1)])
    return -g[idx], a[::-1].copy(), m[::-1].copy()


def _rms_deg(r_true, q):
    return float(np.sqrt(np.mean(np.rad2deg(np.asarray(so3.angle_error(r_true, so3.quat_to_matrix(q)))) ** 2)))


def test_smoothing_the_reversed_recording_gives_the_reversed_estimate(sim):
    g, a, m, _ = sim
    off = S.Offline(seed_bias=True)
    est = jaxatt.filter("mahony", g, a, m, dt=0.01, offline=off)
    rev = jaxatt.filter("mahony", *_reversed(g, a, m), dt=0.01, offline=off)
    assert est.quat.dtype == np.float64
    assert _same_rotation(rev.quat[::-1], est.quat, 1e-12)
    # the passes swap: the forward pass of the reversed recording is the backward pass of the recording
    assert _same_rotation(rev.outputs["q_forward"][::-1], est.outputs["q_backward"], 1e-12)
    np.testing.assert_allclose(rev.outputs["weight_heading"][::-1], 1 - est.outputs["weight_heading"], atol=1e-12)
    # biases: the backward pass's, in the forward gyro's sign, equals the reversed recording's forward pass's
    # negated (the reversed gyro is negated)
    np.testing.assert_allclose(-rev.outputs["bias"][::-1], est.outputs["backward_bias"], atol=1e-12)


@pytest.mark.parametrize("name", ["robust", "mahony"])
def test_smoothed_error_is_below_the_causal_filters_on_a_simulated_recording(sim, name):
    g, a, m, r_true = sim
    est = jaxatt.filter(name, g, a, m, dt=0.01, offline=True)
    fwd = _rms_deg(r_true, est.outputs["q_forward"])
    smooth = _rms_deg(r_true, est.quat)
    if name == "mahony":  # the forward pass is the causal filter itself
        causal = jaxatt.filter(name, g, a, m, dt=0.01)
        assert _same_rotation(causal.quat, est.outputs["q_forward"], 1e-14)
    assert smooth < 0.75 * fwd, (name, fwd, smooth)
    assert smooth < _rms_deg(r_true, est.outputs["q_backward"]), name


def test_a_missing_reading_at_the_end_starts_the_backward_pass_from_the_last_present_one(sim):
    """A last row without its magnetometer reading (a slower magnetometer, NaN-filled) smooths as a last row that
    repeats the previous reading turned by one step of the gyro: the backward pass starts from the last present
    reading carried to the end, as the forward pass does from the first. (Before, the robust AHRS's backward TRIAD
    read NaN, 27 deg off without a word, and the MEKF raised 'non-finite at sample 0'.)"""
    g, a, m, r_true = sim
    m_nan, m_rep = m.copy(), m.copy()
    m_nan[-1], m_rep[-1] = np.nan, m[-2]
    for name in ("robust", "mekf"):
        est = jaxatt.filter(name, g, a, m_nan, dt=0.01, offline=True)
        ref = jaxatt.filter(name, g, a, m_rep, dt=0.01, offline=True)
        step_deg = np.degrees(np.max(np.linalg.norm(g[-2:], axis=-1)) * 0.01)  # one step's turn
        assert _rms_deg(np.asarray(so3.quat_to_matrix(jnp.asarray(ref.outputs["q_backward"]))),
                        est.outputs["q_backward"]) < step_deg, name  # fmt: skip
        assert _rms_deg(r_true, est.quat) < _rms_deg(r_true, est.outputs["q_forward"]), name


def test_broad_score_offline_of_a_trial_ending_without_magnetometer_readings(sim):
    """The same start from the last present reading when a trial is scored offline (broad_score and `jaxatt broad
    --offline`): a trial whose last 3 magnetometer rows are missing scores as one whose last rows repeat the last
    present reading (it scored 26.7 deg against 1.0)."""
    from jaxatt.data import broad

    g, a, m, r_true = sim
    q_true = np.asarray(so3.matrix_to_quat(r_true))
    t = np.arange(len(g)) * 0.01

    def trial(mag):
        samples = jaxatt.ImuSample(t, g, a, mag)
        return broad.Trial("01_sim", samples, q_true, np.ones(len(g), bool), 100.0, "undisturbed")

    m_nan, m_rep = m.copy(), m.copy()
    m_nan[-3:], m_rep[-3:] = np.nan, m[-4]
    got, ref = (jaxatt.broad_score("robust", None, [trial(x)], offline=True) for x in (m_nan, m_rep))
    assert got.trials["01_sim"].total_rmse_deg == pytest.approx(ref.trials["01_sim"].total_rmse_deg, abs=0.02)
    assert got.trials["01_sim"].total_rmse_deg < 2.0


@pytest.mark.parametrize("mag", ["none", "all missing"])
def test_a_9d_observer_without_magnetometer_readings_is_smoothed_in_inclination_only(sim, mag):
    """Without any magnetometer reading neither pass has an absolute heading: the fused estimate keeps the forward
    pass's heading and moves its inclination only (smoothing.fuse_inclination), as for a 6D observer. (Before, a 9D
    observer blended two unrelated headings: 27 deg total error against 3.5 for the forward pass.)"""
    g, a, m, r_true = sim
    est = jaxatt.filter("robust", g, a, None if mag == "none" else np.full_like(m, np.nan), dt=0.01, offline=True)
    o = est.outputs
    inclination_only = S.fuse_inclination(o["q_forward"], o["q_backward"], o["weight_inclination"])
    assert _same_rotation(est.quat, np.asarray(inclination_only), 1e-13)
    assert _rms_deg(r_true, est.quat) <= _rms_deg(r_true, o["q_forward"]) + 0.1


def test_the_passes_estimates_are_in_the_asked_frame_and_the_backward_times_run_forward(sim):
    """q_forward / q_backward are converted to ``frame`` as the fused quat is, and backward_t holds the time each
    row's estimate refers to (the forward time, not the reversed pass's own clock)."""
    g, a, m, _ = sim
    enu = jaxatt.filter("mahony", g, a, m, dt=0.01, offline=True)
    ned = jaxatt.filter("mahony", g, a, m, dt=0.01, offline=True, frame="NED")
    assert _same_rotation(ned.quat, jaxatt.frames.change_frame(enu.quat, "NED"), 1e-14)
    for k in ("q_forward", "q_backward"):
        assert _same_rotation(ned.outputs[k], jaxatt.frames.change_frame(enu.outputs[k], "NED"), 1e-14), k
    np.testing.assert_array_equal(enu.outputs["backward_t"], enu.t)
    np.testing.assert_array_equal(enu.outputs["t"], enu.t)


def test_a_padded_batch_smooths_each_recording_as_alone(sim):
    g, a, m, _ = sim
    obs = registry.recorded_observer("mahony")
    p = registry.get("mahony").params(dtype=np.float64)
    n, short = len(g), len(g) - 157

    def item_of(arrs, length):
        pad = lambda x: np.concatenate([x[:length], np.repeat(x[length - 1 : length], n - length, 0)])  # noqa: E731
        return [pad(x) for x in arrs]

    rows = [item_of((g, a, m), n), item_of((g, a, m), short)]
    t = np.arange(n) * 0.01
    samples = jaxatt.ImuSample(*(jnp.asarray(np.stack(x)) for x in ([t, t], *zip(*rows))))
    fn = S.compiled(obs, n - 1, obs_dtype=np.dtype(np.float64), seed_bias=True)
    res = fn(p, S.default_fusion(), {"samples": samples, "dt": jnp.full((2,), 0.01)}, jnp.asarray([n, short]))
    alone = jaxatt.filter("mahony", g[:short], a[:short], m[:short], dt=0.01, offline=S.Offline(seed_bias=True))
    assert _same_rotation(np.asarray(res.q)[1, :short], alone.quat, 1e-12)
    full = jaxatt.filter("mahony", g, a, m, dt=0.01, offline=S.Offline(seed_bias=True))
    assert _same_rotation(np.asarray(res.q)[0], full.quat, 1e-12)


def test_gradient_through_both_passes_matches_finite_differences(sim):
    """d/d theta of the mean squared angle error of the smoothed estimate over 2 s, theta = the robust AHRS's
    tuned gains (log space) and the log fusion params, against a central difference along a random direction."""
    g, a, m, r_true = sim
    k = 200
    e = registry.get("robust")
    obs = registry.recorded_observer(e)
    bound = P.for_gains(e.gains).bind(e.default_params(dtype=jnp.float64))
    fn = S.smoother_fn(obs, k - 1, obs_dtype=jnp.float64)
    t = jnp.arange(k) * 0.01
    item = {
        "samples": jaxatt.ImuSample(t[None], *(jnp.asarray(x[None, :k]) for x in (g, a, m))),
        "dt": jnp.full(1, 0.01),
    }
    rt = jnp.asarray(r_true[:k])

    def loss(theta):
        gains, log_f = theta
        q = fn(bound.constrain(gains), S.FusionParams(*jnp.exp(log_f)), item, jnp.asarray([k])).q[0]
        return jnp.mean(jnp.rad2deg(so3.angle_error(rt, so3.quat_to_matrix(q))) ** 2)

    th0 = (bound.init(), jnp.log(jnp.asarray([2.0, 5.0, 3.0, 4.0])))  # fusion away from its defaults' corner
    vg = jax.jit(jax.value_and_grad(loss))
    value, grad = vg(th0)
    assert np.isfinite(float(value))
    leaves = jax.tree_util.tree_leaves(grad)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in leaves)
    assert float(jnp.max(jnp.abs(grad[1]))) > 0  # the fusion params reach the loss
    rng = np.random.default_rng(0)
    d = jax.tree_util.tree_map(lambda x: jnp.asarray(rng.standard_normal(np.shape(x))), th0)
    d = (bound.zero_frozen(d[0]), d[1])
    h = 1e-5
    fp = vg(jax.tree_util.tree_map(lambda x, y: x + h * y, th0, d))[0]
    fm = vg(jax.tree_util.tree_map(lambda x, y: x - h * y, th0, d))[0]
    fd = float(fp - fm) / (2 * h)
    ad = sum(float(jnp.vdot(x, y)) for x, y in zip(jax.tree_util.tree_leaves(grad), jax.tree_util.tree_leaves(d)))
    assert abs(fd) > 0
    assert abs(ad - fd) <= 1e-4 * abs(fd), (ad, fd)


# ------------------------------------------------------------------------------------------------------------
# The front door
# ------------------------------------------------------------------------------------------------------------
def test_bad_offline_settings_are_one_clear_line(sim):
    g, a, m, _ = sim
    with pytest.raises(ValueError, match="offline must be"):
        jaxatt.filter("mahony", g, a, m, dt=0.01, offline="yes")
    with pytest.raises(ValueError, match="fusion parameter tau_heading must be a finite positive"):
        jaxatt.filter("mahony", g, a, m, dt=0.01, offline={"tau_heading": -1.0})
    with pytest.raises(ValueError, match="unknown fusion parameters"):
        jaxatt.filter("mahony", g, a, m, dt=0.01, offline={"tau": 1.0})
    with pytest.raises(ValueError, match="seed_bias needs an output field bias"):
        jaxatt.filter("madgwick", g[:50], a[:50], m[:50], dt=0.01, offline=S.Offline(seed_bias=True))
    # a user's time_reversed that fails, or returns something else than its params: one line naming it
    mahony = registry.get("mahony")
    p = mahony.default_params()
    for reverse, match in (
        (lambda q: (1.0,), r"time_reversed\(params\) must return params of the same type and fields \(Params\), got"),
        (lambda q: 1 / 0, r"time_reversed\(params\) failed: ZeroDivisionError"),
    ):
        mine = registry.recorded_observer(mahony)._replace(name="mine", time_reversed=reverse)
        with pytest.raises(ValueError, match=match):
            jaxatt.filter(mine, g[:50], a[:50], m[:50], dt=0.01, params=p, offline=True)


def test_broad_score_offline_is_the_metric_of_the_smoothed_estimate():
    need_data()
    from jaxatt.data import broad

    trials = broad.load(DATA, ["24"])
    tr = trials[0]
    sc = jaxatt.broad_score("robust", None, trials, offline=True)
    est = jaxatt.filter("robust", tr.samples.gyr, tr.samples.acc, tr.samples.mag, dt=1 / tr.rate_hz, offline=True)
    ref = broad.broad_errors(est.quat, tr.quat_true, tr.movement)
    assert sc.observer == "robust+offline"
    np.testing.assert_allclose(sc.trials[tr.name].total_rmse_deg, ref["total_rmse_deg"], rtol=1e-6)
    causal = jaxatt.broad_score("robust", None, trials).trials[tr.name].total_rmse_deg
    assert sc.trials[tr.name].total_rmse_deg < causal
    # a second call (other gains, weakly typed) reuses the cached smoother: the trials are its arguments
    again = jaxatt.broad_score("robust", {"mag_delay": 0.001}, trials, offline=True)
    assert again.trials[tr.name].total_rmse_deg != sc.trials[tr.name].total_rmse_deg
    off = S.Offline()
    smoother = S.compiled(  # the program broad_score runs (S.compiled is cached on its arguments)
        registry.recorded_observer("robust"),
        broad.pad_trials(trials).samples.t.shape[1] - 1,  # the trial padded to whole blocks of steps
        per_step_dt=False,  # a BROAD trial: uniform steps
        hold="next",
        obs_dtype=np.dtype(np.float64),
        trust=off.trust,
        heading=True,
        seed_bias=off.seed_bias,
        segment=0,
        start_from_present=True,  # the robust AHRS sets itself up from its first sample
    )
    assert smoother._cache_size() == 1


def test_filter_command_offline_with_timestamps(sim, tmp_path):
    """``jaxatt filter --offline`` on a CSV log (timestamps: the per-step dt path) writes the fused estimate, the
    same as with the constant dt."""
    from jaxatt import cli
    from jaxatt.data import logs

    g, a, m, _ = sim
    t = np.arange(len(g)) * 0.01
    log, out = tmp_path / "log.csv", tmp_path / "est.csv"
    logs.save_log(log, jaxatt.ImuSample(t, g, a, m))
    assert cli.main(["filter", "--log", str(log), "--observer", "mahony", "--offline", "--out", str(out)]) == 0
    table = np.genfromtxt(out, delimiter=",", names=True)
    assert "weight_heading" in table.dtype.names and "backward_bias_x" in table.dtype.names
    q = np.column_stack([table[c] for c in ("qw", "qx", "qy", "qz")])
    const = jaxatt.filter("mahony", g, a, m, dt=0.01, offline=True)
    assert _same_rotation(q, const.quat, 1e-12)
    for name in ("q_forward", "q_backward"):  # (T, 4) outputs are written as <name>_w ... <name>_z
        written = np.column_stack([table[f"{name}_{c}"] for c in "wxyz"])
        assert _same_rotation(written, const.outputs[name], 1e-12), name


def test_a_pass_that_starts_without_a_reading_starts_from_the_next_one_carried_by_the_gyro():
    """A magnetometer missing over a recording's first or last 3 s: the pass starting there is set up from the
    nearest present reading carried back to its start by the gyro (so3.first_present_at_start), its start
    uncertainty 3 s larger. Both passes then agree, and the fused estimate over those seconds is as good as the
    other pass's. Before, the uncarried reading (a reading of another attitude) put that pass 45 deg off, and the
    fusion gave it the weight (40-50 deg off); the causal filter started 45 deg off as well."""
    s, truth = montecarlo.simulate_log(jaxatt.ahrs_scenario(), duration=20.0, dt=0.01, seed=3)
    q_true = np.asarray(so3.quat_canonical(so3.matrix_to_quat(truth.r)))

    def err(q):
        return np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(np.asarray(q) * q_true, -1)), 0, 1)))

    k = 300  # 3 s
    for part in (slice(0, k), slice(-k, None)):
        mag = np.array(s.mag)
        mag[part] = np.nan
        est = jaxatt.filter("robust", s.gyr, s.acc, mag, t=s.t, offline=True)
        for q in (est.quat, est.outputs["q_forward"], est.outputs["q_backward"]):
            assert err(q)[part].mean() < 5.0
    # VQF is not set up from its first sample: its backward pass has no heading before its first magnetometer
    # reading (40 deg off here), and has no weight there (smoothing.UNINFORMED_S)
    est = jaxatt.filter("vqf", s.gyr, s.acc, mag, t=s.t, offline=True)
    assert err(est.outputs["q_backward"])[-k:].mean() > 20.0 and err(est.quat)[-k:].mean() < 5.0
    causal = jaxatt.filter("robust", s.gyr, s.acc, mag, t=s.t)  # the causal filter's start alike
    assert err(causal.quat)[:k].mean() < 5.0


def test_a_pass_that_starts_in_motion_gives_the_other_pass_the_weight_there():
    """A recording that ends while the sensor is shaken (a linear acceleration: its last readings tilt a start taken
    from them, and the observer is still settling): the backward pass is far less sure there
    (smoothing.MOVING_START_S, decaying over SETTLE_S), so the forward pass, settled, has the weight. (The backward
    pass of BROAD trials cut mid-movement was tens of degrees off and weighted 0.98 in heading: offline 35.5 deg
    against 1.45 causal over their last second.) A turning sensor without linear acceleration, or one at rest, is
    not "in motion"."""
    samples, _ = montecarlo.simulate_log(jaxatt.api.ahrs_scenario(rate_scale=3.0), duration=20.0, dt=0.01, seed=4)
    n = len(samples.t)
    t = np.asarray(samples.t)
    shake = np.where(t > 17.0, 3.0 * np.sin(2 * np.pi * 2.0 * t), 0.0)[:, None] * [1.0, 0.0, 0.0]  # m/s^2, body
    shaken = samples._replace(acc=np.asarray(samples.acc) + shake)
    still = samples._replace(gyr=np.zeros_like(samples.gyr), acc=np.tile([0.0, 0.0, 9.81], (n, 1)))
    for rec, want in ((samples, [False, False]), (still, [False, False]), (shaken, [False, True])):
        batch = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], rec)
        assert np.asarray(S._start_in_motion(batch, jnp.asarray([n]))).tolist() == [want]
    w = [jaxatt.filter("robust", r, offline=True).outputs["weight_heading"][-1] for r in (samples, shaken)]
    assert w[0] > 0.5 and w[1] < 0.01, w  # at the end: the backward pass's start had the weight, now the forward
