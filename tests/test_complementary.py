"""The observer of Trumpf et al. (2012), eq. (10) / (18), on the scenarios of Sections III-IV: agreement of the
matrix and quaternion implementations, the Lyapunov function of Proposition 4.6, convergence under persistent
excitation and its failure without, compatible measurements, Mahony's bias integrator, missing data, errors."""

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from jaxatt import analysis, montecarlo, so3  # noqa: E402
from jaxatt.observers import complementary as C  # noqa: E402
from jaxatt.sim import references as S  # noqa: E402
from jaxatt.types import ImuSample  # noqa: E402

DT = 0.02
DURATION = 40.0  # every log has 2001 samples, so the jitted scans compile once per (form, hold, n1, n2)
MIXED_BIAS_DEG = (1.0, -0.5, 0.8)


def rot(axis_angle):
    """exp(S(phi)) in numpy (Rodrigues), to keep test-side geometry out of JAX's op-by-op dispatch."""
    phi = np.asarray(axis_angle, float)
    th = np.linalg.norm(phi)
    if th == 0:
        return np.eye(3)
    k = np.array([[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]]) / th
    return np.eye(3) + np.sin(th) * k + (1 - np.cos(th)) * k @ k


def angle_between(r1, r2):
    """Angle (rad) of r1^T r2 for (..., 3, 3) arrays, numpy."""
    e = np.swapaxes(np.asarray(r1), -1, -2) @ np.asarray(r2)
    s = 0.5 * np.linalg.norm(
        np.stack([e[..., 2, 1] - e[..., 1, 2], e[..., 0, 2] - e[..., 2, 0], e[..., 1, 0] - e[..., 0, 1]], -1), axis=-1
    )
    return np.arctan2(s, 0.5 * (np.trace(e, axis1=-2, axis2=-1) - 1.0))


def lyap(r_hat, r):
    """V = tr(I - R^ R^T) in numpy."""
    return 3.0 - np.trace(np.asarray(r_hat) @ np.swapaxes(np.asarray(r), -1, -2), axis1=-2, axis2=-1)


def initial_estimates(r_true0, angles_deg, seed=0):
    """R^(0) = exp(angle * axis) R(0) for random axes: E_r(0) = R^ R^T has exactly that angle."""
    rng = np.random.default_rng(seed)
    out = []
    for a in angles_deg:
        ax = rng.normal(size=3)
        out.append(rot(ax / np.linalg.norm(ax) * np.deg2rad(a)) @ np.asarray(r_true0))
    return out


def angle_deg(out, truth_r):
    """Angle error (deg) of every estimate (T of them, estimate 0 being init's) against the truth at its time."""
    return np.rad2deg(angle_between(truth_r, out.r))


def run(params, samples, form="matrix", dt=DT, hold="zoh", **kw):
    return montecarlo.run(C.make_observer(form, **kw), params, samples, dt, hold=hold, validate=C.check_params)


def assert_converges(samples, truth_r, r0s, tol_deg=1e-3, floor_deg=0.5, **gains):
    """Runs from every R^(0) in r0s end on the run started at the truth (to tol_deg), whose error stays at the
    discretisation floor (zero-order-hold lag, ~|Omega| dt / 2) below floor_deg."""
    n1, n2 = np.shape(samples.body_meas)[1], np.shape(samples.inertial_meas)[1]
    ref = run(C.default_params(n1, n2, r_hat_0=np.asarray(truth_r[0]), **gains), samples)
    assert np.max(angle_deg(ref, truth_r)) < floor_deg
    for r0 in r0s:
        assert lyap(r0, truth_r[0]) < 4.0  # tr(I - E_r(0)) < 4: inside the basin of Thm 4.3
        out = run(C.default_params(n1, n2, r_hat_0=r0, **gains), samples)
        gap = np.rad2deg(angle_between(ref.r[-1], out.r[-1]))
        assert gap < tol_deg, (np.rad2deg(angle_between(truth_r[0], r0)), gap)


@pytest.fixture(scope="module")
def rotating():
    return S.simulate_vectors(S.rotating_reference(), DURATION, DT)


@pytest.fixture(scope="module")
def mixed():
    """One rotating inertial reference, one constant body-fixed reference, gyro bias 1 deg/s."""
    scn = S.rotating_reference(gyro_bias_deg_s=MIXED_BIAS_DEG)._replace(ref_body=S.constant_directions([0.0, 0.0, 1.0]))
    return S.simulate_vectors(scn, 8.0, 0.004)


# ---------------------------------------------------------------------------------------------------------
# Two independent implementations: eq. (10) on SO(3) with a Lie-group step, eq. (18) on quaternions
# ---------------------------------------------------------------------------------------------------------
def test_matrix_and_quaternion_forms_agree(mixed, hold="linear"):
    """Same trajectory to 1e-11 (the zero-order hold runs both forms in the bias test below)."""
    samples, truth_r = mixed
    r0 = initial_estimates(truth_r[0], [120.0], seed=3)[0]
    p = C.default_params(1, 1, k=0.7, l=0.9, k_i=0.3, r_hat_0=r0, bias_0=[0.01, 0.0, -0.02])
    om = run(p, samples, "matrix", dt=0.004, hold=hold)
    oq = run(p, samples, "quaternion", dt=0.004, hold=hold)
    np.testing.assert_allclose(om.r, oq.r, atol=1e-11)  # measured ~1e-14 at this dt
    np.testing.assert_allclose(om.bias, oq.bias, atol=1e-11)
    np.testing.assert_allclose(om.correction, oq.correction, atol=1e-11)
    # q up to sign: both outputs are sign-continuous, so one global sign suffices
    sign = np.sign(np.sum(np.asarray(om.q[0]) * np.asarray(oq.q[0])))
    np.testing.assert_allclose(om.q, sign * np.asarray(oq.q), atol=1e-11)
    np.testing.assert_allclose(np.asarray(so3.quat_to_matrix(om.q)), om.r, atol=1e-12)
    rtr = np.swapaxes(np.asarray(om.r), -1, -2) @ np.asarray(om.r)
    assert np.max(np.abs(rtr - np.eye(3))) < 1e-12  # stays on SO(3)
    assert np.min(np.abs(np.sum(np.asarray(om.q[1:]) * np.asarray(om.q[:-1]), -1))) > 0.9  # sign-continuous
    assert angle_deg(om, truth_r)[-1] < angle_deg(om, truth_r)[0]


def test_correction_terms_of_eq10_and_eq18_agree_and_vanish_at_truth():
    rng = np.random.default_rng(7)
    corr_m = jax.jit(C.correction_matrix)
    corr_q = jax.jit(C.correction_quaternion)
    for _ in range(5):
        r_hat, r = rot(rng.normal(size=3)), rot(rng.normal(size=3))
        ar, br = rng.normal(size=(3, 3)), rng.normal(size=(2, 3))
        u = C.StepInput(np.zeros(3), (r.T @ ar.T).T, ar, (r @ br.T).T, br)
        k, l = rng.uniform(0.1, 2, 3), rng.uniform(0.1, 2, 2)
        q_hat = so3.matrix_to_quat(r_hat)
        sm = corr_m(r_hat, u, k, l)
        np.testing.assert_allclose(sm, corr_q(q_hat, u, k, l), atol=1e-13)
        np.testing.assert_allclose(corr_q(2.5 * q_hat, u, k, l), sm, atol=1e-13)  # q^-1 exact off the sphere
        np.testing.assert_allclose(corr_m(r, u, k, l), 0.0, atol=1e-13)
        # small-error linearisation of Prop. 4.6: d z / dt = -P z with P = sum q (I - v v^T), E_r = exp(z)
        z = rng.normal(size=3) * 1e-6
        sig = np.asarray(corr_m(rot(z) @ r, u, k, l))
        v = np.concatenate(
            [ar / np.linalg.norm(ar, axis=1, keepdims=True), (r @ br.T).T / np.linalg.norm(br, axis=1, keepdims=True)]
        )
        P = sum(q * (np.eye(3) - np.outer(vi, vi)) for q, vi in zip(np.r_[k, l], v))
        np.testing.assert_allclose(r @ sig, -P @ z, atol=1e-11)  # inertial-frame rate of E_r = -P z


# ---------------------------------------------------------------------------------------------------------
# Proposition 4.6 / Theorem 4.3
# ---------------------------------------------------------------------------------------------------------
def test_lyapunov_never_increases(rotating, mixed):
    """V = tr(I - E_r) is non-increasing along noise-free runs (proof of Prop. 4.6), several initial errors."""
    for (samples, truth_r), n2, dt in ((rotating, 0, DT), (mixed, 1, 0.004)):
        bias = np.deg2rad(MIXED_BIAS_DEG) if n2 else None  # the mixed log has a gyro bias: give the true one
        for r0 in initial_estimates(truth_r[0], [20.0, 75.0, 130.0, 175.0], seed=1):
            p = C.default_params(1, n2, k=0.6, l=0.9, r_hat_0=r0, bias_0=bias)
            out = run(p, samples, dt=dt, hold="linear")
            v = lyap(out.r, truth_r)
            np.testing.assert_allclose(v[0], lyap(r0, truth_r[0]), atol=1e-12)  # estimate 0: R^(0)
            assert v[0] < 4.0
            assert np.max(np.diff(v)) < 1e-9, np.max(np.diff(v))
            assert v[-1] < v[0]


def test_persistently_exciting_single_reference_converges_from_almost_everywhere(rotating):
    samples, truth_r = rotating
    ex = analysis.excitation_from_samples(samples, window=12.0, stride=25)
    assert np.min(ex.lambda2 / (ex.t_end - ex.t_start)) > 0.3  # PE: bounded away from 0
    assert_converges(samples, truth_r, initial_estimates(truth_r[0], [30.0, 90.0, 150.0, 170.0], seed=2), k=0.6)


def test_single_constant_reference_is_not_enough():
    """The rotation about a constant reference is unobservable: it is never corrected (E_r å = å is an
    equilibrium set), and a generic error converges to a rotation about å, not to I."""
    scn = S.constant_reference((0.0, 0.0, 1.0))
    samples, truth_r = S.simulate_vectors(scn, DURATION, DT)
    ex = analysis.excitation_from_samples(samples, window=12.0, stride=25)
    assert np.max(np.abs(ex.lambda2)) < 1e-9 and np.max(ex.condition) < 1e-9
    # error purely about å: never corrected (exactly so in continuous time; the linear hold keeps the
    # discretisation drift of the gyro integration below 1e-3 deg, the zero-order hold ~0.1 deg)
    r0 = rot([0.0, 0.0, np.deg2rad(40.0)]) @ np.asarray(truth_r[0])
    out = run(C.default_params(1, 0, k=1.0, r_hat_0=r0), samples, hold="linear")
    np.testing.assert_allclose(angle_deg(out, truth_r), 40.0, atol=1e-3)
    np.testing.assert_allclose(out.correction, 0.0, atol=1e-5)
    # a generic error: the tilt is corrected, the rotation about å remains
    r0 = rot(np.deg2rad([30.0, -20.0, 50.0])) @ np.asarray(truth_r[0])
    out = run(C.default_params(1, 0, k=1.0, r_hat_0=r0), samples, hold="linear")
    e = np.asarray(C.right_error(out.r[-1], truth_r[-1]))
    np.testing.assert_allclose(C.lyapunov(out.r[-1], truth_r[-1]), 3.0 - np.trace(e), atol=1e-14)
    assert np.rad2deg(angle_between(np.eye(3), e)) > 10.0
    np.testing.assert_allclose(e @ [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], atol=1e-4)  # E_r å = å


def test_switching_reference_converges():
    samples, truth_r = S.simulate_vectors(S.switching_reference(half_period_s=3.0), DURATION, DT)
    assert_converges(samples, truth_r, initial_estimates(truth_r[0], [60.0, 150.0], seed=4), k=0.8)


def test_two_constant_references_converge():
    samples, truth_r = S.simulate_vectors(S.two_constant_references(60.0), DURATION, DT)
    assert_converges(samples, truth_r, initial_estimates(truth_r[0], [45.0, 170.0], seed=5), k=[1.0, 0.7])


def test_compatible_body_fixed_reference():
    """End of Section III / IV: one constant body-fixed b̊ suffices when the body turns about other axes,
    and does not when it turns only about b̊."""
    samples, truth_r = S.simulate_vectors(S.body_fixed_reference((0.0, 0.0, 1.0), rate_deg_s=30.0), DURATION, DT)
    ex = analysis.excitation_from_samples(samples, window=12.0, stride=25)
    assert np.min(ex.condition) > 1.0 and np.min(ex.lambda2 / (ex.t_end - ex.t_start)) > 0.1
    assert_converges(samples, truth_r, initial_estimates(truth_r[0], [60.0, 160.0], seed=6), l=0.8)
    spin = S.body_fixed_reference((0.0, 0.0, 1.0), rates=S.body_rates((0.0, 0.0, 0.0), offset_deg_s=(0.0, 0.0, 30.0)))
    samples, truth_r = S.simulate_vectors(spin, DURATION, DT)
    ex = analysis.excitation_from_samples(samples, window=12.0, stride=25)
    assert np.max(ex.condition) < 1e-9 and np.max(ex.lambda2) < 1e-9
    r0 = rot(np.deg2rad([0.0, 0.0, 50.0])) @ np.asarray(truth_r[0])
    ang = angle_deg(run(C.default_params(0, 1, l=0.8, r_hat_0=r0), samples), truth_r)
    assert ang[-1] > 45.0


def test_gyro_bias_converges_with_two_constant_references():
    """Mahony et al. 2008 passive complementary filter with bias (two constant non-collinear references)."""
    bias_deg = np.array([1.2, -0.7, 2.0])
    scn = S.two_constant_references(70.0, gyro_bias_deg_s=bias_deg)
    samples, truth_r = S.simulate_vectors(scn, DURATION, DT)
    r0 = initial_estimates(truth_r[0], [90.0], seed=8)[0]
    for form in C.FORMS:
        out = run(C.default_params(2, 0, k=1.0, k_i=0.3, r_hat_0=r0), samples, form)
        np.testing.assert_allclose(out.bias[-1], np.deg2rad(bias_deg), atol=1e-5)
        assert angle_deg(out, truth_r)[-1] < 0.1
    # without the integrator the bias leaves a standing error, the correction cancelling most of the bias
    out = run(C.default_params(2, 0, k=1.0, r_hat_0=r0), samples)
    assert angle_deg(out, truth_r)[-1] > 1.0
    np.testing.assert_allclose(out.correction[-1], -np.deg2rad(bias_deg), atol=5e-3)


# ---------------------------------------------------------------------------------------------------------
# ImuSample (accelerometer + magnetometer), missing data, noise
# ---------------------------------------------------------------------------------------------------------
def test_imu_sample_log_matches_vector_sample_log():
    """Accelerometer (m/s^2, NED: specific force = R^T (0, 0, -g)) + magnetometer (nT, NED) as ImuSample
    gives the same run as the equivalent VectorSample with constant references."""
    field = np.array([2.6338e4, 0.0851e4, 3.6359e4])
    up = np.array(C.UP_NED)
    scn = S.two_constant_references()._replace(ref_inertial=S.constant_directions(np.stack([up, field])))
    vs, truth_r = S.simulate_vectors(scn, DURATION, DT)
    rt = np.swapaxes(np.asarray(truth_r), -1, -2)
    imu = ImuSample(vs.t, vs.gyr, acc=rt @ (9.80665 * up), mag=rt @ field)
    r0 = initial_estimates(truth_r[0], [100.0], seed=9)[0]
    p_imu = C.imu_params(k_acc=2.0, k_mag=2.0, mag_ref=field, frame="NED", r_hat_0=r0)
    C.check_inputs(p_imu, imu)
    out_imu = run(p_imu, imu)
    out_vec = run(C.default_params(2, 0, k=2.0, r_hat_0=r0), vs)
    np.testing.assert_allclose(out_imu.r, out_vec.r, atol=1e-12)
    # the field is 54 deg from the vertical: slowest rate lambda_min(P) = 2 (1 - |cos 126 deg|) = 0.38 /s
    assert angle_deg(out_imu, truth_r)[-1] < 0.3
    # ENU frame: the up reference flips sign of z
    np.testing.assert_allclose(C.imu_params(mag_ref=field, frame="ENU").ref_inertial[0], C.UP_ENU)


def test_missing_measurements_are_skipped_and_gyro_held(rotating):
    samples, truth_r = rotating
    a = np.array(samples.body_meas)
    g = np.array(samples.gyr)
    a[100:400, 0, 1] = np.nan  # measurement lost for 6 s
    a[500, 0] = 0.0  # a zero vector is no direction either
    g[700] = np.nan
    bad = samples._replace(body_meas=jnp.asarray(a), gyr=jnp.asarray(g))
    r0 = initial_estimates(truth_r[0], [60.0], seed=10)[0]
    out = run(C.default_params(1, 0, k=0.6, r_hat_0=r0), bad)
    assert np.all(np.isfinite(np.asarray(out.r)))
    # estimate 0 is init's: no correction, nothing used, no gyro held
    assert not bool(out.used_body_meas[0, 0]) and not bool(out.gyr_held[0])
    np.testing.assert_array_equal(out.correction[0], 0.0)
    np.testing.assert_allclose(out.r[0], r0, atol=1e-12)
    # row k of the step outputs below (estimate k + 1) is the step over [t_k, t_{k+1}], which holds sample k
    ang = angle_deg(out, truth_r)[1:]
    out = jax.tree_util.tree_map(lambda a: a[1:], out)
    used = np.asarray(out.used_body_meas[:, 0])
    assert not used[100:400].any() and not used[500] and used[400:500].all()
    assert bool(out.gyr_held[700]) and int(np.sum(out.gyr_held)) == 1
    np.testing.assert_allclose(out.correction[100:400], 0.0)
    # while blind the estimate is pure gyro integration: the error stays (but for the zero-order-hold drift)
    assert ang[100] > 20.0 and abs(ang[399] - ang[100]) < 0.2
    assert ang[-1] < 0.2


def test_noise_needs_explicit_key_and_is_reproducible():
    scn = S.rotating_reference(gyro_noise_std=1e-3, meas_noise_std=1e-2)
    with pytest.raises(ValueError, match="PRNG key"):
        S.simulate_vectors(scn, 1.0, DT)
    s1, _ = S.simulate_vectors(scn, 1.0, DT, jax.random.PRNGKey(1))
    s2, _ = S.simulate_vectors(scn, 1.0, DT, jax.random.PRNGKey(1))
    s3, _ = S.simulate_vectors(scn, 1.0, DT, jax.random.PRNGKey(2))
    np.testing.assert_array_equal(s1.gyr, s2.gyr)
    assert np.max(np.abs(np.asarray(s1.body_meas) - np.asarray(s3.body_meas))) > 1e-4


def test_fused_simulation_runner_accepts_vector_scenarios():
    """A VectorScenario provides montecarlo's simulator interface: the fused simulate + observe scan gives the
    same run as simulate_vectors followed by montecarlo.run (noise-free, so both see the same samples)."""
    scn = S.two_constant_references(70.0, gyro_bias_deg_s=(1.2, -0.7, 2.0))
    samples, truth_r = S.simulate_vectors(scn, DURATION, DT)
    r0 = initial_estimates(truth_r[0], [90.0], seed=8)[0]
    p = C.default_params(2, 0, k=1.0, k_i=0.3, r_hat_0=r0)
    summary, trace, _ = montecarlo.simulate(
        scn._replace(r0=truth_r[0]),
        C.make_observer(),
        p,
        duration=DURATION,
        dt=DT,
        errors_fn=S.vector_errors,
        window_start=30.0,
        trace_every=1,
    )
    out = run(p, samples)
    np.testing.assert_allclose(trace["angle_error_deg"], angle_deg(out, truth_r), atol=1e-9)
    np.testing.assert_allclose(
        trace["norm_bias"], np.linalg.norm(np.asarray(out.bias) - np.deg2rad([1.2, -0.7, 2.0]), axis=-1), atol=1e-12
    )
    assert summary["final_norm_bias"] < 1e-5 and summary["mean_angle_error_deg"] < 0.2  # ZOH floor ~0.1 deg


# ---------------------------------------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------------------------------------
def test_bad_inputs_raise_clear_errors(rotating):
    samples, _ = rotating
    with pytest.raises(ValueError, match="non-negative"):
        C.default_params(1, 0, k=-1.0)
    with pytest.raises(ValueError, match="non-negative"):
        C.default_params(0, 1, l=np.nan)
    with pytest.raises(ValueError, match="k_i"):
        C.default_params(1, 0, k_i=-0.1)
    with pytest.raises(ValueError, match="n1 \\+ n2 >= 1"):
        C.default_params(0, 0)
    with pytest.raises(ValueError, match="shape \\(2,\\)"):
        C.default_params(2, 0, k=[1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="rotation matrix"):
        C.default_params(1, 0, r_hat_0=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="rotation matrix"):
        C.default_params(1, 0, r_hat_0=2 * np.eye(3))
    with pytest.raises(ValueError, match="r_hat_0 or q_hat_0"):
        C.default_params(1, 0, r_hat_0=np.eye(3), q_hat_0=[1.0, 0, 0, 0])
    with pytest.raises(ValueError, match="form"):
        C.make_observer("euler")
    with pytest.raises(ValueError, match="imu_fields"):
        C.make_observer(imu_fields=("gyr",))
    with pytest.raises(ValueError, match="frame"):
        C.imu_params(mag_ref=[1.0, 0, 0], frame="NWU")
    with pytest.raises(ValueError, match="mag_ref"):
        C.imu_params()
    p2 = C.default_params(2, 0)
    with pytest.raises(ValueError, match="body_meas"):
        C.check_inputs(p2, samples)  # the log has one body measurement, params two gains
    with pytest.raises(ValueError, match="body_meas"):
        run(p2, samples)  # the same mismatch caught while tracing the step
    with pytest.raises(ValueError, match="Params.ref_inertial"):
        C.check_inputs(C.default_params(1, 0), samples._replace(ref_inertial=None))
    with pytest.raises(ValueError, match="compatible"):
        C.check_inputs(C.default_params(1, 1), ImuSample(samples.t, samples.gyr, acc=samples.gyr))
    with pytest.raises(ValueError, match="dt"):
        run(C.default_params(1, 0), samples, dt=0.0)
    with pytest.raises(ValueError, match="unknown scenario"):
        S.make_scenario("spinning")
    with pytest.raises(ValueError, match="unknown scenario keyword"):
        S.make_scenario("rotating", rate=3.0)
    with pytest.raises(ValueError, match="dt"):
        S.simulate_vectors(S.constant_reference(), 1.0, -0.1)


def test_study_notes_say_the_scenario_whole_and_when_every_run_is_the_same():
    """The report's scenario line is the scenario's first sentence, not a line cut mid-sentence; a noise-free
    set-up (the default) says that every run is the same, a noisy one does not."""
    from jaxatt import studies

    study = studies.get("complementary")
    for name in S.SCENARIOS:
        line = study.notes(study.config(scenario=name))[0]
        assert line.endswith(".") and line.count("``") % 2 == 0 and line.count("(") == line.count(")"), line
    quiet = study.notes(study.config(scenario="rotating"))
    assert quiet[0].endswith("(sin tilt, 0, cos tilt).") and "rate_deg_s" in quiet[0]
    assert any(n.startswith("noise-free") for n in quiet)
    noisy = study.notes(study.config(scenario="rotating", gyro_noise_std=1e-3))
    assert not any(n.startswith("noise-free") for n in noisy)
