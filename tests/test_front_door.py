"""The front door with an observer written here, in a test file, not registered: jaxatt.filter, broad_score, fit and
monte_carlo take it like a registered one. Each result is checked against a second, independent computation
(the numpy BROAD metric of the stored estimates, the fused simulation against a recorded log of the same run, a
finite difference), and bad input gets one clear line."""

import dataclasses
import json
import re
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from broad_data import DATA, need_data

import jaxatt
from jaxatt import api, engine, frames, montecarlo, so3
from jaxatt.data import broad
from jaxatt.fitting import fitter
from jaxatt.observers import registry
from jaxatt.types import ImuSample, Observer


# ---------------------------------------------------------------------------------------------------------
# A user's observer: Mahony's explicit complementary filter with bias, sensor-to-ENU, written from scratch
# ---------------------------------------------------------------------------------------------------------
class MyParams(NamedTuple):
    kp: jnp.ndarray  # 1/s
    ki: jnp.ndarray  # 1/s^2


class MyState(NamedTuple):
    t: jnp.ndarray
    q: jnp.ndarray  # (4,) sensor-to-ENU, w x y z
    bias: jnp.ndarray  # (3,) rad/s


class MyOut(NamedTuple):
    t: jnp.ndarray
    q: jnp.ndarray
    bias: jnp.ndarray


def my_init(p, s):
    q = so3.quat_canonical(so3.matrix_to_quat(so3.triad(jnp.asarray(s.acc), jnp.asarray(s.mag), "ENU")))
    return MyState(jnp.asarray(s.t, q.dtype), q, jnp.zeros(3, q.dtype))


def my_step(p, st, s, dt):
    r = so3.quat_to_matrix(st.q)
    a = so3.unit(s.acc)
    m_nav = r @ so3.unit(s.mag)
    m_ref = so3.unit(jnp.stack([0.0 * m_nav[0], jnp.hypot(m_nav[0], m_nav[1]), m_nav[2]]))
    e = jnp.cross(a, r.T @ jnp.array([0.0, 0.0, 1.0], a.dtype)) + jnp.cross(so3.unit(s.mag), r.T @ m_ref)
    bias = st.bias - p.ki * e * dt
    w = s.gyr - bias + p.kp * e
    q = st.q + 0.5 * dt * so3.quat_multiply(st.q, jnp.concatenate([jnp.zeros(1, w.dtype), w]))
    q = q / jnp.linalg.norm(q)
    return MyState(st.t + dt, q, bias), MyOut(st.t + dt, q, bias)


MY_OBSERVER = Observer(my_init, my_step, "my_mahony")
MY_PARAMS = MyParams(jnp.asarray(1.0), jnp.asarray(0.3))


def short(trial, n):
    """The first n samples of a BROAD trial (its rest phase and the start of the movement)."""
    cut = lambda a: np.asarray(a)[:n]  # noqa: E731
    return broad.Trial(
        trial.name,
        jax.tree_util.tree_map(cut, trial.samples),
        cut(trial.quat_true),
        cut(trial.movement),
        trial.rate_hz,
        trial.group,
    )


@pytest.fixture(scope="module")
def trials():
    need_data()
    return [short(t, 14000) for t in broad.load(DATA, ["01", "24"])]


def test_filter_runs_your_observer_and_converges():
    """On a simulated noise-free AHRS log with a gyro bias, estimate 0 is the user's TRIAD start (exact), the
    bias (0.57 deg/s) pulls it away by < 1.5 deg until the integral has found it, then it stays within the one-sample
    lag of an explicit-Euler filter (|w| dt ~ 0.1 deg)."""
    scn = jaxatt.api.ahrs_scenario(gyro_noise_std=0.0, acc_noise_std=0.0, mag_noise_std=0.0, gyro_bias=(0.01, 0, 0))
    samples, truth = montecarlo.simulate_log(scn, duration=60.0, dt=0.01)
    est = jaxatt.filter(MY_OBSERVER, samples.gyr, samples.acc, samples.mag, dt=0.01, params=MY_PARAMS)
    assert est.quat.shape == (6001, 4) and est.quat.dtype == np.float64 and est.observer == "my_mahony"
    np.testing.assert_allclose(
        est.quat[0], np.asarray(my_init(MY_PARAMS, jax.tree_util.tree_map(lambda a: a[0], samples)).q), atol=1e-15
    )
    err = np.rad2deg(np.asarray(so3.angle_error(truth.r, so3.quat_to_matrix(jnp.asarray(est.quat)))))
    assert err[0] < 1e-6 and err.max() < 1.5 and err[-1000:].max() < 0.15, (err.max(), err[-1000:].max())
    np.testing.assert_allclose(est.outputs["bias"][-1], [0.01, 0.0, 0.0], atol=2e-3)


def test_your_observer_with_dict_params_is_the_same_filter():
    """Params are any pytree: an observer written over a dict of gains runs (a dict is not mistaken for a partial
    override, as it is for a registered observer) and equals the NamedTuple-params observer on the same log."""
    scn = jaxatt.api.ahrs_scenario(gyro_noise_std=1e-3, acc_noise_std=0.05, mag_noise_std=0.2)
    samples, _ = montecarlo.simulate_log(scn, duration=3.0, dt=0.01)
    dict_obs = Observer(my_init, lambda p, st, s, dt: my_step(MyParams(p["kp"], p["ki"]), st, s, dt), "my_dict")
    gains = {"kp": jnp.asarray(1.0), "ki": jnp.asarray(0.3)}
    got = jaxatt.filter(dict_obs, samples.gyr, samples.acc, samples.mag, dt=0.01, params=gains)
    ref = jaxatt.filter(MY_OBSERVER, samples.gyr, samples.acc, samples.mag, dt=0.01, params=MY_PARAMS)
    np.testing.assert_array_equal(got.quat, ref.quat)
    with pytest.raises(ValueError, match="a gains file needs them as the template"):
        jaxatt.filter(dict_obs, samples.gyr, samples.acc, samples.mag, dt=0.01, params="gains.json")


class _NoQState(NamedTuple):
    t: jnp.ndarray
    quat: jnp.ndarray  # not named q or r: estimate 0 cannot be read from it


def test_estimate_0_needs_q_or_r_in_the_state_or_an_output_function():
    """Without Observer(output=...), estimate 0 is read from init's state: a state without q or r is one clear line
    before anything runs (it was reported as a non-finite estimate at sample 0)."""
    scn = jaxatt.api.ahrs_scenario(gyro_noise_std=1e-3, acc_noise_std=0.05, mag_noise_std=0.2)
    samples, _ = montecarlo.simulate_log(scn, duration=1.0, dt=0.01)

    def init(p, s):
        st = my_init(p, s)
        return _NoQState(st.t, st.q)

    def step(p, st, s, dt):
        new, out = my_step(p, MyState(st.t, st.quat, jnp.zeros(3, st.quat.dtype)), s, dt)
        return _NoQState(new.t, new.q), {"q": new.q}

    with pytest.raises(
        ValueError, match=r"estimate 0 is read from init's state, which has no field q .*\['quat', 't'\]"
    ):
        jaxatt.filter(Observer(init, step, "noq"), samples.gyr, samples.acc, samples.mag, dt=0.01, params=MY_PARAMS)
    # with an output function it runs, and equals the observer that keeps q in its state (no bias: ki = 0)
    with_output = Observer(init, step, "noq", lambda p, st: {"q": st.quat})
    p0 = MY_PARAMS._replace(ki=jnp.asarray(0.0))
    got = jaxatt.filter(with_output, samples.gyr, samples.acc, samples.mag, dt=0.01, params=p0)
    ref = jaxatt.filter(MY_OBSERVER, samples.gyr, samples.acc, samples.mag, dt=0.01, params=p0)
    np.testing.assert_array_equal(got.quat, ref.quat)


def test_an_extra_output_is_nan_at_estimate_0_without_a_warning_and_warned_when_it_goes_bad_later():
    scn = jaxatt.api.ahrs_scenario(gyro_noise_std=1e-3, acc_noise_std=0.05, mag_noise_std=0.2)
    samples, _ = montecarlo.simulate_log(scn, duration=1.0, dt=0.01)

    def step(p, st, s, dt, bad=False):
        new, out = my_step(p, st, s, dt)
        err = jnp.where(bad & (new.t > 0.5), jnp.nan, 0.0) * jnp.ones(3, new.q.dtype)
        return new, {"q": out.q, "err": err}

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning at all
        est = jaxatt.filter(
            Observer(my_init, step, "extra"), samples.gyr, samples.acc, samples.mag, dt=0.01, params=MY_PARAMS
        )
    assert np.all(np.isnan(est.outputs["err"][0])) and np.all(est.outputs["err"][1:] == 0.0)
    bad = Observer(my_init, lambda p, st, s, dt: step(p, st, s, dt, bad=True), "extra_bad")
    with pytest.warns(UserWarning, match="the estimate is finite but the output err has non-finite values"):
        jaxatt.filter(bad, samples.gyr, samples.acc, samples.mag, dt=0.01, params=MY_PARAMS)


def test_broad_score_of_your_observer_equals_the_numpy_metric(trials):
    score = jaxatt.broad_score(MY_OBSERVER, MY_PARAMS, trials)
    assert set(score.trials) == {t.name for t in trials} and set(score.groups) == {"undisturbed", "disturbed", "all"}
    for tr in trials:
        est = jaxatt.filter(
            MY_OBSERVER, tr.samples.gyr, tr.samples.acc, tr.samples.mag, dt=1.0 / tr.rate_hz, params=MY_PARAMS
        )
        ref = broad.broad_errors(est.quat, tr.quat_true, tr.movement)
        s = score.trials[tr.name]
        for m in broad.METRICS:
            assert getattr(s, m) == pytest.approx(ref[m], rel=1e-9), m
        assert s.group == tr.group
    g = score.groups["all"]
    assert g.total_rmse_deg == pytest.approx(np.mean([s.total_rmse_deg for s in score.trials.values()]))
    assert json.loads(json.dumps(score.to_dict()))["observer"] == "my_mahony"


def test_a_recording_with_ground_truth_is_a_trial_scored_as_the_numpy_metric(tmp_path):
    """jaxatt.data.logs.load_trial: a logger's CSV (its own names, ms, deg/s, g) with its ground truth in NED
    becomes a Trial whose truth is the simulated sensor-to-ENU attitude, and broad_score on it is the numpy BROAD
    metric of jaxatt.filter's estimate; movement masks what is scored."""
    from jaxatt.data import logs

    samples, truth = montecarlo.simulate_log(jaxatt.api.ahrs_scenario(), duration=3.0, dt=0.01, seed=2)
    s = ImuSample(*(np.asarray(a) for a in samples))
    q_enu = np.asarray(so3.matrix_to_quat(truth.r))
    raw = s._replace(t=s.t * 1e3, gyr=np.rad2deg(s.gyr), acc=s.acc / 9.80665)
    path = tmp_path / "phone.csv"
    logs.save_log(path, raw, frames.change_frame(q_enu, "NED", "ENU"))
    text = path.read_text().splitlines()
    path.write_text("\n".join([text[0].replace("gyr_", "Gyro").replace("t,", "time_ms,", 1)] + text[1:]) + "\n")
    kw = dict(columns="t=time_ms,gyr_x=Gyrox,gyr_y=Gyroy,gyr_z=Gyroz", gyr_unit="deg/s", acc_unit="g", time_unit="ms")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the right frame: the truth's vertical is the accelerometer's
        trial = logs.load_trial(path, frame="NED", group="mine", **kw)
    with pytest.warns(UserWarning, match=r"the ground truth's vertical is 1[78]\d deg from the accelerometer's"):
        logs.load_trial(path, **kw)  # the NED truth read as ENU
    # a world-to-sensor truth (the conjugate): its vertical passes on this near-level run, its turning does not
    conj = tmp_path / "conj.csv"
    logs.save_log(conj, raw, frames.change_frame(q_enu * [1.0, -1.0, -1.0, -1.0], "NED", "ENU"))
    conj.write_text(
        "\n".join([text[0].replace("gyr_", "Gyro").replace("t,", "time_ms,", 1)] + conj.read_text().splitlines()[1:])
        + "\n"
    )
    with pytest.warns(UserWarning, match=r"the ground truth does not turn as the gyro does \(median cosine -[01]\."):
        logs.load_trial(conj, frame="NED", **kw)
    with pytest.warns(UserWarning, match=r"phone.csv: dt is not used: the log has timestamps"):
        logs.load_trial(path, frame="NED", dt=0.02, **kw)
    forgot = {k: v for k, v in kw.items() if k != "acc_unit"}  # the units check of jaxatt.filter, on the trial path
    with pytest.warns(
        UserWarning, match=r"log .*phone.csv: the median \|acc\| is 1: is it in g\? .*acc_unit='g' in load"
    ):
        logs.load_trial(path, frame="NED", **forgot)
    assert trial.name == "phone" and trial.group == "mine" and trial.rate_hz == pytest.approx(100.0)
    np.testing.assert_allclose(np.abs(np.sum(trial.quat_true * q_enu, axis=-1)), 1.0, atol=1e-12)  # q or -q
    np.testing.assert_allclose(trial.samples.gyr, s.gyr, rtol=1e-13)
    assert trial.movement.all()
    late = logs.load_trial(path, frame="NED", movement=np.asarray(s.t) >= 1.0, **kw)
    score = jaxatt.broad_score("mahony", None, [trial, late._replace(name="late")])
    est = jaxatt.filter("mahony", trial.samples)
    for tr in (trial, late):
        ref = broad.broad_errors(est.quat, tr.quat_true, tr.movement)
        got = score.trials["late" if tr is late else "phone"]
        assert got.total_rmse_deg == pytest.approx(ref["total_rmse_deg"], rel=1e-9)
    assert score.trials["late"].total_rmse_deg != pytest.approx(score.trials["phone"].total_rmse_deg, rel=1e-3)
    assert set(score.groups) == {"mine", "own", "all"} and score.groups["mine"].n_trials == 1
    # a recording whose rate changes half-way (the second half at 50 Hz) is scanned on its own timestamps: the
    # score is still the numpy metric of jaxatt.filter's estimate (it was the scan at a constant 1 / 100 Hz), with
    # a uniform trial beside it in the batch
    keep = np.ones(len(s.t), bool)
    keep[151::2] = False
    mixed = trial._replace(
        name="mixed",
        samples=ImuSample(*(np.asarray(a)[keep] for a in trial.samples)),
        quat_true=trial.quat_true[keep],
        movement=trial.movement[keep],
    )
    padded = broad.pad_trials([trial, mixed])
    assert (
        padded.dt is not None and padded.dt[1, 200] == pytest.approx(0.02) and padded.dt[0, 200] == pytest.approx(0.01)
    )
    assert broad.pad_trials([trial, late]).dt is None  # uniform trials: the constant step, as BROAD's filters
    score = jaxatt.broad_score("mahony", None, [trial, mixed])
    for tr in (trial, mixed):
        ref = broad.broad_errors(jaxatt.filter("mahony", tr.samples).quat, tr.quat_true, tr.movement)
        assert score.trials[tr.name].total_rmse_deg == pytest.approx(ref["total_rmse_deg"], rel=1e-9), tr.name
    with pytest.raises(ValueError, match=r"no ground truth \(columns quat_w"):
        logs.save_log(tmp_path / "no_truth.csv", s)
        logs.load_trial(tmp_path / "no_truth.csv")
    with pytest.raises(ValueError, match=r"movement must be a bool array of shape \(301,\)"):
        logs.load_trial(path, movement=np.ones(5, bool), **kw)
    # what a user hands over by mistake: one line each, saying what to pass
    with pytest.raises(ValueError, match=r"gyr is a trial \(Trial\): pass its recording, trial.samples"):
        jaxatt.filter("mahony", trial)
    with pytest.raises(ValueError, match=r"gyr is a tuple holding an ImuSample .*: pass the samples"):
        jaxatt.filter("mahony", logs.load_log(path, with_truth=True, **kw))
    with pytest.raises(ValueError, match=r"data must be a list of trials, got one Trial \(phone\): pass \[trial\]"):
        jaxatt.fit("mahony", None, trial, steps=1)
    with pytest.raises(ValueError, match=r"phone.csv: a CSV / NPZ log, not a BROAD .hdf5 trial: .*logs.load_trial"):
        broad.load_trial(path)
    # a recording without a magnetometer and without timestamps: dt times it, name= names it, and a 9D filter
    # scored on it says it runs without a magnetometer
    six = tmp_path / "six.csv"
    logs.save_log(six, s._replace(mag=None), q_enu)
    text = six.read_text().splitlines()
    six.write_text("\n".join(",".join(row.split(",")[1:]) for row in text) + "\n")  # no t column
    six_trial = logs.load_trial(six, dt=0.01, name="six-axis")
    assert six_trial.name == "six-axis" and np.isnan(six_trial.samples.mag).all()
    np.testing.assert_allclose(six_trial.samples.t, s.t, atol=1e-12)
    with pytest.warns(UserWarning, match=r"trial six-axis has no magnetometer reading: mahony runs on it without"):
        jaxatt.broad_score("mahony", None, [six_trial])
    unscored = trial._replace(name="none", movement=np.zeros_like(trial.movement))
    with pytest.warns(UserWarning, match=r"no scored sample .* in trial none: its metrics are NaN and the group"):
        score = jaxatt.broad_score("mahony", None, [unscored, trial])
    assert np.isnan(score.trials["none"].total_rmse_deg) and score.groups["all"].n_trials == 1


def test_fit_your_observer_on_trials_keeps_its_type_and_lowers_the_loss(trials, tmp_path, capsys):
    out = tmp_path / "my.json"
    res = jaxatt.fit(MY_OBSERVER, MY_PARAMS, trials, steps=4, lr=0.2, out=str(out), quiet=False)
    assert isinstance(res.params, MyParams) and res.status == "done"
    assert float(res.params.kp) > 0 and float(res.params.ki) > 0
    losses = [h["train_loss"] for h in res.history]
    assert res.best_loss < losses[0]
    # best_step counts updates; each history line's loss is of the gains going into that step, and the summary
    # says which gains it means
    assert 1 <= res.best_step <= 4
    if res.best_step < 4:
        assert losses[res.best_step] == res.best_loss
    summary = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"best loss {res.best_loss:.5g} (the gains after step {res.best_step})" in summary, summary
    # the best loss is the score of the returned params (group-weighted mean total RMSE)
    score = jaxatt.broad_score(MY_OBSERVER, res.params, trials)
    want = 0.5 * (score.groups["undisturbed"].total_rmse_deg + score.groups["disturbed"].total_rmse_deg)
    assert want == pytest.approx(res.best_loss, rel=1e-6)
    saved = json.loads(out.read_text())
    assert saved["observer"] == "my_mahony" and set(saved["gains"]) == {"kp", "ki"}
    assert saved["gains"]["kp"]["value"] == pytest.approx(float(res.params.kp))
    with pytest.raises(ValueError, match="exists"):
        jaxatt.fit(MY_OBSERVER, MY_PARAMS, trials, steps=4, out=str(out))
    other = Observer(my_init, my_step, "another")
    with pytest.raises(ValueError, match="resume: the saved fit is of observer 'my_mahony', not 'another'"):
        jaxatt.fit(other, MY_PARAMS, trials, steps=6, lr=0.2, out=str(out), resume=True)
    with pytest.raises(ValueError, match=r"'steps' differs .*\(4 vs 6\) \(the cosine schedule's length"):
        jaxatt.fit(MY_OBSERVER, MY_PARAMS, trials, steps=6, lr=0.2, out=str(out), resume=True)
    # the same fit again (a new objective closure, the same program) is not compiled again and gives the same gains
    compiled = engine.program_cache_stats["compiled"]
    again = jaxatt.fit(MY_OBSERVER, MY_PARAMS, trials, steps=4, lr=0.2)
    assert engine.program_cache_stats["compiled"] == compiled
    assert float(again.params.kp) == float(res.params.kp) and again.best_loss == res.best_loss


def test_monte_carlo_of_your_observer_is_the_same_run_as_a_recorded_log(tmp_path):
    """Run 0 of the fused Monte Carlo equals the filter on the recorded log of the same run (same key): two paths,
    one number. The result's summary and JSON are the per-run numbers' statistics (numpy)."""
    res = jaxatt.monte_carlo(MY_OBSERVER, MY_PARAMS, runs=2, duration=20.0, seed=5)
    res.save_json(tmp_path / "mc.json")
    saved = json.loads((tmp_path / "mc.json").read_text())
    assert saved["runs"] == 2 and saved["complete"] and saved["first_nonfinite"] is None
    for k, v in res.per_run.items():
        assert saved["metrics"][k]["per_run"] == np.asarray(v).tolist()
        assert saved["metrics"][k]["mean"] == pytest.approx(float(np.mean(v)), rel=1e-12)
        assert saved["metrics"][k]["std"] == pytest.approx(float(np.std(v)), rel=1e-12, abs=1e-300)
    assert res.summary() == saved["metrics"]
    with pytest.raises(ValueError, match=r"unknown extension '\.csv'"):
        res.save_json(tmp_path / "mc.csv")
    assert res.complete and set(res.per_run) >= {"mean_angle_error_deg", "std_yaw", "std_bias"}
    samples, truth = montecarlo.simulate_log(jaxatt.api.ahrs_scenario(), duration=20.0, dt=0.01, seed=5)
    est = jaxatt.filter(MY_OBSERVER, samples.gyr, samples.acc, samples.mag, dt=0.01, params=MY_PARAMS)
    err = np.rad2deg(np.asarray(so3.angle_error(truth.r, so3.quat_to_matrix(jnp.asarray(est.quat)))))
    assert res.per_run["final_angle_error_deg"][0] == pytest.approx(err[-1], rel=1e-9)
    t = np.asarray(samples.t)
    window = (t >= 20.0 * 2 / 3) & (np.arange(len(t)) >= 1)  # the window metrics count estimates 1 ... T-1
    assert res.per_run["mean_angle_error_deg"][0] == pytest.approx(err[window].mean(), rel=1e-9)


def test_a_param_the_recording_sets_up_is_said_not_to_be_used():
    """The MEKF's field reference given in a params dict was checked (a vertical one refused as 'parallel'), then
    replaced by the set-up from the first sample without a word: now a warning says so, and it is not checked."""
    samples, _ = montecarlo.simulate_log(jaxatt.api.ahrs_scenario(), duration=2.0, dt=0.01, seed=2)
    base = jaxatt.filter("mekf", samples.gyr, samples.acc, samples.mag, dt=0.01)
    for ref in ([20.0, 0.0, 44.0], [0.0, 0.0, 1.0]):
        with pytest.warns(UserWarning, match=r"param mag_ref_nav of mekf is set from each recording's first samples"):
            est = jaxatt.filter("mekf", samples.gyr, samples.acc, samples.mag, dt=0.01, params={"mag_ref_nav": ref})
        np.testing.assert_array_equal(est.quat, base.quat)


@pytest.mark.parametrize("name", ["madgwick", "mahony", "complementary", "mekf"])
def test_montecarlo_run_of_a_registered_filter_gives_jaxatt_filters_estimates(name):
    """An Observer carries the hold it is written for (``Observer.hold``) and every runner uses it: the low-level
    montecarlo.run of a registered filter's Observer gives jaxatt.filter's estimates. It used to hold each sample
    over the step after it ("zoh") where the filter updates with it ("next"): 0.45 deg apart on Madgwick. The
    observers that declare no hold of their own (complementary, MEKF) get their entry's from recorded_observer."""
    samples, _ = montecarlo.simulate_log(jaxatt.api.ahrs_scenario(), duration=5.0, dt=0.01, seed=2)
    e = registry.get(name)
    p = e.params(dtype=jnp.float64)
    est = jaxatt.filter(name, samples.gyr, samples.acc, samples.mag, dt=0.01, params=p)
    r_filter = so3.quat_to_matrix(jnp.asarray(est.quat))

    def gap_deg(out):
        return float(np.rad2deg(np.max(so3.angle_error(r_filter, so3.quat_to_matrix(engine.estimate_q(out))))))

    obs = registry.recorded_observer(name)
    assert obs.hold == "next" and e.make().hold in ("next", None)
    assert gap_deg(montecarlo.run(obs, p, samples, 0.01)) < 1e-9
    assert gap_deg(montecarlo.run(obs, p, samples, 0.01, hold="zoh")) > 1e-2  # a hold given still wins


def test_the_estimate_is_read_from_q_everywhere_when_an_output_also_has_r():
    """An output with a diagnostic ``r`` beside its estimate ``q`` (here a (3,) residual): the Monte Carlo scores
    ``q`` as jaxatt.filter does (it scored ``r``, or failed in the scan when ``r`` was not 3x3)."""

    def step_with_residual(p, st, s, dt):
        new, out = my_step(p, st, s, dt)
        return new, {"t": out.t, "q": out.q, "r": so3.unit(s.acc)}

    def output(p, st):
        return {"t": st.t, "q": st.q, "r": jnp.zeros(3, st.q.dtype)}

    with_r = Observer(my_init, step_with_residual, "my_mahony_r", output)
    kw = dict(runs=2, duration=2.0, seed=3)
    a, b = jaxatt.monte_carlo(MY_OBSERVER, MY_PARAMS, **kw), jaxatt.monte_carlo(with_r, MY_PARAMS, **kw)
    for k in ("final_angle_error_deg", "mean_angle_error_deg", "max_angle_error_deg"):
        np.testing.assert_allclose(b.per_run[k], a.per_run[k], rtol=1e-12, err_msg=k)


@pytest.fixture(scope="module")
def quiet_log():
    scn = jaxatt.api.ahrs_scenario(gyro_noise_std=1e-4, acc_noise_std=0.01, mag_noise_std=0.05, gyro_bias=(0, 0, 0))
    samples, truth = montecarlo.simulate_log(scn, duration=40.0, dt=0.01)
    return samples, np.asarray(truth.r)


# one test per observer: each compiles its own filter, and xdist spreads them over the workers
@pytest.mark.parametrize("name", jaxatt.observers.registry.names(recorded=True))
def test_registered_observers_through_the_front_door(name, quiet_log):
    """Every observer set up for recorded data runs through jaxatt.filter on a simulated log and converges near the
    truth; the frame argument rotates the estimate (NED = fixed rotation of ENU)."""
    samples, r_true = quiet_log
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        est = jaxatt.filter(name, samples.gyr, samples.acc, samples.mag, dt=0.01)
    assert not [str(w.message) for w in caught if "non-finite" in str(w.message)], name  # every output is finite
    # a 6D observer given a magnetometer says it ignores it (a user who wanted heading picked the wrong one)
    ignored = [str(w.message) for w in caught if "does not use the magnetometer" in str(w.message)]
    assert len(ignored) == int("mag" not in jaxatt.observers.registry.get(name).needs), (name, ignored)
    err = np.rad2deg(np.asarray(so3.angle_error(jnp.asarray(r_true), jnp.asarray(est.rotation))))
    assert np.all(np.isfinite(est.quat)), name
    assert err[-500:].mean() < 3.0, (name, err[-500:].mean())
    if name == "robust":
        ned = jaxatt.filter("robust", samples.gyr, samples.acc, samples.mag, dt=0.01, frame="NED")
        c = jaxatt.frames.frame_rotation("NED", "ENU")
        np.testing.assert_allclose(ned.rotation[-1], c @ est.rotation[-1], atol=1e-12)


@pytest.mark.parametrize(
    "name",
    [n for n in jaxatt.observers.registry.names(recorded=True) if jaxatt.observers.registry.get(n).field_unit_gains],
)
def test_default_noise_settings_hold_in_any_magnetometer_unit(name, quiet_log, trials):
    """The observers whose defaults hold magnetometer covariances (mekf: r_mag; the NLIO family: r_mag, p0_mag)
    give the same estimate for a field in uT, gauss or nT: the front door scales those defaults to the recording's
    field (Entry.field_unit_gains). Before, the MEKF's error went from 0.49 deg in uT to 70.7 deg in nT. A field
    the caller names keeps its value; broad_score scales as filter does."""
    samples, _ = quiet_log
    g, a, m = (np.asarray(x) for x in (samples.gyr, samples.acc, samples.mag))
    ut = jaxatt.filter(name, g, a, m, dt=0.01)
    for factor in (0.01, 1000.0):  # gauss, nT
        other = jaxatt.filter(name, g, a, m * factor, dt=0.01)
        assert np.abs(other.quat - ut.quat).max() < 1e-9, (name, factor)
    r_mag = 2.0 * np.eye(3)
    named = jaxatt.filter(name, g, a, m * 1000.0, dt=0.01, params={"r_mag": r_mag})
    np.testing.assert_array_equal(np.asarray(named.params.r_mag), r_mag)
    if name == "mekf":
        scaled = [t._replace(samples=t.samples._replace(mag=t.samples.mag * 1000.0)) for t in trials]
        a_ut, a_nt = (jaxatt.broad_score(name, None, tr).groups for tr in (trials, scaled))
        for grp in a_ut:
            assert a_nt[grp].total_rmse_deg == pytest.approx(a_ut[grp].total_rmse_deg, rel=1e-9)


@pytest.mark.parametrize("name", ["robust", "mahony", "madgwick"])
def test_a_missing_first_reading_starts_from_the_first_present_one(name, quiet_log):
    """Row 0 of mag (a blank cell, a slower magnetometer) missing: the filters that start from the first sample
    (their TRIAD; the robust AHRS's field norm and dip) start from the first present reading instead of a stand-in
    (the robust AHRS then rejected every real reading as disturbed: 16 deg instead of 3 on a simulated log),
    carried back to row 0 by the gyro (so3.first_present_at_start). The estimates are those of the log with that
    reading put in row 0, and as good as with every reading."""
    samples, r_true = quiet_log
    g, a, m = (np.asarray(x) for x in (samples.gyr, samples.acc, samples.mag))
    gap, moved = m.copy(), m.copy()
    gap[:3] = np.nan
    moved[:3] = np.nan
    moved[0] = np.asarray(so3.first_present_at_start(jnp.asarray(gap[:4]), jnp.asarray(g[:4]), 0.01))[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the missing rows are warned about
        est = jaxatt.filter(name, g, a, gap, dt=0.01)
        ref = jaxatt.filter(name, g, a, moved, dt=0.01)
    np.testing.assert_array_equal(est.quat, ref.quat)
    full = jaxatt.filter(name, g, a, m, dt=0.01)
    err = [np.rad2deg(np.asarray(so3.angle_error(jnp.asarray(r_true), jnp.asarray(e.rotation))))[-2000:].mean()
           for e in (est, full)]  # fmt: skip
    assert err[0] < err[1] + 0.2, (name, err)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda g, a, m: jaxatt.filter("robust", g, a, m), "dt"),
        (lambda g, a, m: jaxatt.filter("robust", g, a, m, dt=0.0), "dt"),
        (lambda g, a, m: jaxatt.filter("robust", g, a, m, dt=float("nan")), "dt"),
        (lambda g, a, m: jaxatt.filter("robust", g[:, :2], a, m, dt=0.01), "gyr"),
        (lambda g, a, m: jaxatt.filter("robust", g, a[:-1], m, dt=0.01), "acc"),
        (lambda g, a, m: jaxatt.filter("robust", g, None, m, dt=0.01), "needs acc"),
        (lambda g, a, m: jaxatt.filter(MY_OBSERVER, g, a, m, dt=0.01, params=1.0), "params is a float: pass the"),
        (lambda g, a, m: jaxatt.monte_carlo("batista-ges", runs=1, duration=1.0), "jaxatt reproduce batista-ges"),
        (lambda g, a, m: jaxatt.filter("nope", g, a, m, dt=0.01), "unknown observer"),
        (lambda g, a, m: jaxatt.filter(MY_OBSERVER, g, a, m, dt=0.01), "params are required"),
        (lambda g, a, m: jaxatt.filter(MY_OBSERVER, g, a, m, dt=0.01, params="g.json"), "read_params\\(path, base="),
        (lambda g, a, m: jaxatt.filter("robust", g, a, m, dt=0.01, frame="XYZ"), "frame"),
        (lambda g, a, m: jaxatt.filter("robust", g, a, m, dt=np.full(len(g), 0.01)), r"dt must be one number.*give t"),
        (lambda g, a, m: jaxatt.api.ahrs_scenario(mag_ref_enu="abc"), "mag_ref_enu must be 3 real numbers"),
        (lambda g, a, m: jaxatt.api.ahrs_scenario(mag_ref_enu=(0, 0, 5)), "mag_ref_enu must be non-zero and not vert"),
        (lambda g, a, m: jaxatt.api.ahrs_scenario(mag_noise_std="a"), "mag_noise_std must be a real number"),
        (lambda g, a, m: jaxatt.filter("robust", g, a, m, dt=0.01, hold="foh"), "hold"),
        (lambda g, a, m: jaxatt.filter("robust", g, a, m, t=np.zeros(len(g)), dt=None), "increasing"),
        (lambda g, a, m: jaxatt.filter("robust", np.full_like(g, np.inf), a, m, dt=0.01), "inf"),
        (lambda g, a, m: jaxatt.filter("robust", g, a, m, dt=True), "dt must be a number"),
        (lambda g, a, m: jaxatt.filter("robust", g, a, m, dt="0.01"), r"dt must be a number of seconds, got '0.01'"),
        (lambda g, a, m: jaxatt.filter("robust", g, a, m, t=["a"] * len(g)), "t must be an array of timestamps"),
        (lambda g, a, m: jaxatt.filter("robust", g, a, m, dt=0.01, dtype="float16"), "dtype must be float32"),
        (lambda g, a, m: jaxatt.filter("robust", g, a, m, dt=0.01, dtype="quad"), "dtype must be float32"),
        (
            lambda g, a, m: _mine(g, a, m, step=lambda p, st, s, dt: (st, {"q": st.q * p.missing})),
            "init or step failed",
        ),
        (
            lambda g, a, m: jaxatt.fit(MY_OBSERVER, MY_PARAMS, [_tiny_trial()], train_runs=4),
            "options of a fit on a study",
        ),
        (
            lambda g, a, m: jaxatt.filter(
                "mahony", g, a, m, dt=0.01, params=jaxatt.observers.mahony.Params(jnp.asarray(-1.0), jnp.asarray(0.0))
            ),
            "kp",
        ),
        (
            lambda g, a, m: jaxatt.filter(
                MY_OBSERVER, g, a, m, dt=0.01, params=MY_PARAMS._replace(kp=jnp.asarray(np.nan))
            ),
            "not finite",
        ),
        (lambda g, a, m: jaxatt.broad_score("robust", None, []), "empty"),
        (lambda g, a, m: jaxatt.fit("robust", None, [1, 2]), "Trial"),
        # another observer's params, a gain that is not a number
        (
            lambda g, a, m: jaxatt.filter("mahony", g, a, m, dt=0.01, params=jaxatt.observers.madgwick.Params(0.1)),
            r"params of mahony must be its Params \(kp, ki\).*got Params \(beta\)",
        ),
        (lambda g, a, m: jaxatt.filter("mahony", g, a, m, dt=0.01, params=3.0), "params of mahony must be"),
        (lambda g, a, m: jaxatt.filter("mahony", g, a, m, dt=0.01, params={"kp": "abc"}), "field 'kp' must be a"),
        # an observer of the user's that breaks the engine's contract: named before anything runs
        (lambda g, a, m: _mine(g, a, m, step=lambda p, st, s, dt: None), r"step must return a pair .*got None"),
        (lambda g, a, m: _mine(g, a, m, step=lambda p, st, s, dt: st), r"step must return a pair .*got MyState"),
        (
            lambda g, a, m: _mine(g, a, m, step=lambda p, st, s, dt: (st._replace(bias=jnp.zeros(5)), st)),
            r"state field \.bias is float\d\d\[3\] after init but float\d\d\[5\] after step",
        ),
        (  # a step written in float32 on float64 data: said as that, not as init's fault
            lambda g, a, m: _mine(
                g, a, m, step=lambda p, st, s, dt: (st._replace(bias=st.bias.astype(jnp.float32)), st)
            ),
            r"step returns the state field \.bias as float32\[3\], but the observer runs in float64 .*dtype='float32'",
        ),
        (
            lambda g, a, m: _mine(g, a, m, step=lambda p, st, s, dt: (st, st.q)),
            r"step must return its output as a NamedTuple or dict .*got an array",
        ),
        (lambda g, a, m: _mine(g, a, m, step=lambda p, st, s, dt: (st, {"x": st.q})), "neither a field q"),
        (
            lambda g, a, m: _mine(g, a, m, step=lambda p, st, s, dt: (st, {"q": st.q[:3]})),
            r"q of step must be a float array of shape \(4,\), got float\d\d\[3\]",
        ),
        (
            lambda g, a, m: _mine(g, a, m, step=lambda p, st, s, dt: (st, {"q": st.q.astype(jnp.int32)})),
            r"q of step must be a float array .*got int32\[4\]",
        ),
        (
            lambda g, a, m: _mine(g, a, m, step=lambda p, st, s, dt: (st, {"q": 2 * st.q})),
            r"sample 1 .* is not a unit quaternion \(norm 2\)",
        ),
        # an output function whose result is not what step outputs (estimate 0 is stacked with estimates 1...)
        (
            lambda g, a, m: _mine(g, a, m, step=my_step, output=lambda p, st: {"q": st.q, "extra": st.t}),
            r"output\(params, state\) must return what step returns .*output gave dict\(extra, q\), step gave MyOut",
        ),
        (
            lambda g, a, m: _mine(g, a, m, step=my_step, output=lambda p, st: MyOut(st.t, st.q, st.bias[:2])),
            r"output field \.bias is float\d\d\[2\] from output\(params, state\) but float\d\d\[3\] from step",
        ),
        (
            lambda g, a, m: _mine(g, a, m, step=my_step, output=lambda st: MyOut(st.t, st.q, st.bias)),
            r"'broken': init, step or output failed .*TypeError",
        ),
        # monte_carlo's arguments
        (lambda g, a, m: jaxatt.monte_carlo("mahony", duration=0.0), "duration must be a finite positive"),
        (lambda g, a, m: jaxatt.monte_carlo("mahony", duration=float("inf")), "duration must be a finite positive"),
        (lambda g, a, m: jaxatt.monte_carlo("mahony", runs=1.5), "runs must be a whole number"),
        (lambda g, a, m: jaxatt.monte_carlo("mahony", duration=2.0, dt=0.3), r"whole number of steps of dt = 0.3 s"),
        (
            lambda g, a, m: jaxatt.filter(MY_OBSERVER._replace(hold="cubic"), g, a, m, dt=0.01, params=MY_PARAMS),
            r"observer 'my_mahony': Observer.hold must be one of zoh, linear, next, got 'cubic'",
        ),
        (
            lambda g, a, m: montecarlo.run(MY_OBSERVER._replace(hold="x"), MY_PARAMS, ImuSample(None, g, a, m), 0.01),
            r"observer 'my_mahony': Observer.hold: hold must be one of zoh, linear, next, got 'x'",
        ),
        (lambda g, a, m: jaxatt.monte_carlo("mahony", dt="0.01"), r"dt must be a number of seconds"),
        (lambda g, a, m: jaxatt.monte_carlo("mahony", runs=2**33), "runs must be <= "),
        (lambda g, a, m: jaxatt.monte_carlo("mahony", chunk=0), "chunk must be >= 1"),
        (lambda g, a, m: jaxatt.monte_carlo("mahony", trace_every=-1), "trace_every must be >= 0"),
        (
            lambda g, a, m: jaxatt.monte_carlo("mahony", duration=1.0, trace_every=1000),
            r"trace_every = 1000 steps is longer than the run \(100 steps of 0.01 s\)",
        ),
        (lambda g, a, m: jaxatt.monte_carlo("mahony", seed=2**70), "seed must fit in 64 bits"),
        (lambda g, a, m: jaxatt.monte_carlo("mahony", seed=None), "seed must be an integer"),
        (lambda g, a, m: jaxatt.monte_carlo("mahony", scenario="x"), "scenario must be an AHRS scenario"),
        (lambda g, a, m: jaxatt.monte_carlo(MY_OBSERVER, MY_PARAMS, window_start="a"), "window_start must be"),
        (
            lambda g, a, m: jaxatt.filter("mahony", g, a, m, t=(1.7e9 + 0.01 * np.arange(50)).astype(np.float32)),
            "float32 timestamps near 1.7e.09 s cannot resolve the sample interval",
        ),
        # an estimate that is not a rotation: filter refuses it, and so do the batch runs before they score it
        (lambda g, a, m: jaxatt.monte_carlo(_SCALED_R, MY_PARAMS, runs=2, duration=1.0), "before the batch run"),
        (lambda g, a, m: jaxatt.broad_score(_SCALED_R, MY_PARAMS, [_tiny_trial()]), "not a unit quaternion .* batch"),
        (lambda g, a, m: jaxatt.fit(_SCALED_R, MY_PARAMS, [_tiny_trial()], steps=1), "must be a rotation matrix"),
        # params that are not a pytree of numbers (a plain dataclass, the Params class itself), one Trial not in a list
        (lambda g, a, m: jaxatt.filter(MY_OBSERVER, g, a, m, dt=0.01, params=_PlainParams()), "not an array of num"),
        (lambda g, a, m: jaxatt.monte_carlo(MY_OBSERVER, MyParams, runs=2), r"is type .*not an array of numbers"),
        (lambda g, a, m: jaxatt.fit(MY_OBSERVER, _PlainParams(), [_tiny_trial()], steps=1), "not an array of num"),
        (lambda g, a, m: jaxatt.broad_score("mahony", None, _tiny_trial()), r"a list of trials, got one Trial"),
        # units of the recording
        (
            lambda g, a, m: jaxatt.filter("mahony", g, a, m, dt=0.01, gyr_unit="rpm"),
            r"gyr_unit must be one of 'rad/s', ",
        ),
        (
            lambda g, a, m: jaxatt.filter("mahony", g, a, m, dt=0.01, acc_unit=9.81),
            r"acc_unit must be one of .*got 9.81",
        ),
        (lambda g, a, m: jaxatt.filter("mahony", g, a, m, dt=0.01, time_unit="min"), r"time_unit must be one of 's', "),
        (
            lambda g, a, m: jaxatt.filter(
                "mahony", g, a, m, t=np.arange(50) * np.timedelta64(10, "ms"), time_unit="ms"
            ),
            r"time_unit 'ms' applies to numeric t or dt: datetime64 / timedelta64 timestamps carry their own unit",
        ),
        # fit's optimiser arguments
        (lambda g, a, m: jaxatt.fit(MY_OBSERVER, MY_PARAMS, [_tiny_trial()], steps=1, clip=-1.0), "clip must be"),
        (lambda g, a, m: jaxatt.fit(MY_OBSERVER, MY_PARAMS, [_tiny_trial()], val_every=0), "val_every must be"),
    ],
)
def test_bad_input_is_one_clear_line(call, match):
    rng = np.random.default_rng(0)
    g, a, m = rng.normal(size=(50, 3)) * 0.1, np.tile([0, 0, 9.8], (50, 1)), np.tile([0, 20, -40.0], (50, 1))
    with pytest.raises(ValueError, match=match) as e:
        call(g, a, m)
    assert "\n" not in str(e.value)


def _scaled_r_step(p, st, s, dt):  # 3 R: a rotation matrix times 3 (an integrator that is not re-orthonormalised)
    st2, out = my_step(p, st, s, dt)
    return st2, {"r": 3.0 * so3.quat_to_matrix(out.q)}


_SCALED_R = Observer(my_init, _scaled_r_step, "scaled_r")


@dataclasses.dataclass
class _PlainParams:  # not registered as a pytree: JAX sees one opaque leaf
    kp: float = 1.0
    ki: float = 0.3


def _mine(g, a, m, *, step, output=None):
    """jaxatt.filter with MY_OBSERVER's init and another step (and an output function)."""
    return jaxatt.filter(Observer(my_init, step, "broken", output), g, a, m, dt=0.01, params=MY_PARAMS)


def test_a_study_fit_uses_the_devices_its_batches_split_over(monkeypatch):
    """16 runs on 3 devices used to stop ``jaxatt tune`` with its default flags; now the fit takes the most
    devices every batch splits over (2), all of them when they do (None), one when nothing else does, and says
    when it uses fewer than all."""
    from jaxatt.fitting import fitter

    monkeypatch.setattr(jax, "local_device_count", lambda: 3)
    monkeypatch.setattr(jax, "process_count", lambda: 1)
    assert fitter.devices_for_batches([16, 16]) == 2
    assert fitter.devices_for_batches([15, 6]) is None
    assert fitter.devices_for_batches([16, 3]) == 1
    # fewer devices than there are is said (the docs promised an error; the fit quietly ran on fewer)
    monkeypatch.setattr(jax, "local_device_count", lambda: 2)
    with pytest.warns(
        UserWarning, match=r"fit: 3 runs per batch split evenly over 1 of the 2 devices, so the fit runs"
    ):
        jaxatt.fit(None, None, "complementary", steps=0, train_runs=3, val_runs=0, config={"duration": 2.0})


def test_fit_takes_your_params_as_a_dict_a_dataclass_or_nested_and_returns_them_in_their_shape(tmp_path):
    """Params of any pytree shape are tuned leaf by leaf (they were refused, or a nested field crashed in the trace
    or was silently left fixed): the same gains as the NamedTuple fit of the same observer, returned in the
    caller's shape; the gains file names the leaves and is read back into that shape."""
    from jaxatt.fitting import gainsfile

    @jax.tree_util.register_dataclass
    @dataclasses.dataclass
    class Gains:
        kp: jax.Array
        ki: jax.Array

    as_named = {  # how each shape reads as MY_OBSERVER's MyParams
        "dict": ({"kp": MY_PARAMS.kp, "ki": MY_PARAMS.ki}, lambda p: MyParams(p["kp"], p["ki"])),
        "dataclass": (Gains(MY_PARAMS.kp, MY_PARAMS.ki), lambda p: MyParams(p.kp, p.ki)),
        "nested": (
            {"acc": {"kp": MY_PARAMS.kp}, "bias": (MY_PARAMS.ki,)},
            lambda p: MyParams(p["acc"]["kp"], p["bias"][0]),
        ),
    }
    trials = [_tiny_trial()]
    ref = jaxatt.fit(MY_OBSERVER, MY_PARAMS, trials, steps=3, lr=0.2)
    for shape, (params, named) in as_named.items():
        obs = Observer(
            lambda p, s, named=named: my_init(named(p), s),
            lambda p, st, s, dt, named=named: my_step(named(p), st, s, dt),
            shape,
        )
        out = tmp_path / f"{shape}.json"
        res = jaxatt.fit(obs, params, trials, steps=3, lr=0.2, out=str(out))
        assert jax.tree_util.tree_structure(res.params) == jax.tree_util.tree_structure(params), shape
        got = named(res.params)
        np.testing.assert_allclose([got.kp, got.ki], [ref.params.kp, ref.params.ki], rtol=1e-6, err_msg=shape)
        saved = json.loads(out.read_text())["gains"]
        back = named(gainsfile.apply(params, saved))
        np.testing.assert_allclose([back.kp, back.ki], [got.kp, got.ki], rtol=1e-12, err_msg=shape)
    assert set(json.loads((tmp_path / "nested.json").read_text())["gains"]) == {"acc_kp", "bias_0"}
    # a gain name says which leaf it is: two leaves that read as one name are refused, not renamed
    from jaxatt.fitting import flatparams

    with pytest.raises(ValueError, match=r"the leaves \['a'\]\['b'\] and \['a_b'\] both read as the gain name 'a_b'"):
        flatparams.leaf_names({"a_b": 1.0, "a": {"b": 2.0}})
    assert flatparams.leaf_names({"x²": 1.0})[0] == ["x_"]  # a name that is an identifier

    @jax.tree_util.register_pytree_node_class
    class Gain:  # a registered class of one leaf, as a field: tuned, not silently fixed
        def __init__(self, k):
            self.k = k

        def tree_flatten(self):
            return (self.k,), None

        @classmethod
        def tree_unflatten(cls, aux, children):
            return cls(*children)

    assert flatparams.needs_flat_view(MyParams(Gain(MY_PARAMS.kp), MY_PARAMS.ki))
    with pytest.raises(ValueError, match=r"start\(params\) must return params of the structure it was given"):
        jaxatt.fit(obs, params, trials, steps=1, start=lambda p: {"kp": 1.0})


def test_resume_without_out_and_resume_with_overwrite_are_refused(tmp_path):
    with pytest.raises(ValueError, match="resume=True needs out"):
        jaxatt.fit(MY_OBSERVER, MY_PARAMS, [_tiny_trial()], steps=1, resume=True)
    out = tmp_path / "g.json"
    jaxatt.fit(MY_OBSERVER, MY_PARAMS, [_tiny_trial()], steps=1, out=str(out), quiet=True)
    kept = out.read_bytes()
    with pytest.raises(ValueError, match="resume=True and overwrite=True: pass one"):  # used to resume silently
        jaxatt.fit(MY_OBSERVER, MY_PARAMS, [_tiny_trial()], steps=2, out=str(out), resume=True, overwrite=True)
    assert out.read_bytes() == kept
    # resumed from other start gains: refused (the file recorded them as the start it never had), down to the
    # 1e-9 gains of batista-so3 (an absolute tolerance let them all pass)
    with pytest.raises(ValueError, match="the start gains differ"):
        fitter._check_same_start({"alpha0": {"value": 1e-9}}, {"alpha0": {"value": 5e-9}})
    const = tmp_path / "const.json"
    jaxatt.fit(MY_OBSERVER, MY_PARAMS, [_tiny_trial()], steps=1, out=str(const), schedule="constant")
    with pytest.raises(ValueError, match=r"resume: the start gains differ from the saved fit's \(kp: 1.0 vs 2.0\)"):
        jaxatt.fit(
            MY_OBSERVER, MY_PARAMS, [_tiny_trial()], steps=2, out=str(const), schedule="constant", resume=True,
            start={"kp": 2.0},
        )  # fmt: skip
    more = jaxatt.fit(
        MY_OBSERVER, MY_PARAMS, [_tiny_trial()], steps=2, out=str(const), schedule="constant", resume=True
    )
    assert len(more.history) == 2


def test_a_non_finite_score_or_smoothed_estimate_says_where_it_first_appeared():
    """Your observer goes NaN after 0.2 s: broad_score names the sample and time (it said only "diverged (check
    the gains)"), and the offline mode says which pass went first (it named sample 0, the fused estimate's)."""

    def nan_step(p, st, s, dt):
        new, out = my_step(p, st, s, dt)
        q = jnp.where(new.t > 0.2, jnp.nan, new.q)
        return new._replace(q=q), out._replace(q=q)

    broken = Observer(my_init, nan_step, "nan_after_0.2s")
    trial = _tiny_trial()
    with pytest.raises(FloatingPointError, match=r"trial 00_tiny is not finite .*first non-finite .* at sample 2\d "
                       r"\(t = 0.2\d* s\)"):  # fmt: skip
        jaxatt.broad_score(broken, MY_PARAMS, [trial])
    with pytest.raises(FloatingPointError, match=r"at sample 0 .*\(the forward pass from sample 2\d, t = 0.2"):
        jaxatt.filter(broken, trial.samples, params=MY_PARAMS, offline=True)


def test_trials_whose_recording_defaults_differ_widely_are_warned_about():
    """The data-dependent defaults of a fit's batch (the MEKF's field covariances, VQF's first step: one set of
    gains for every trial) start from the median over its trials: a trial far from it (a magnetometer in nT beside
    ones in uT, another rate) is warned about, since its score then depends on the batch; trials alike, or params
    the caller gives, are not."""
    from jaxatt import api

    ut = _tiny_trial()
    nt = ut._replace(name="in_nT", samples=ut.samples._replace(mag=ut.samples.mag * 1e3))
    slow = ut._replace(name="slow", samples=ut.samples._replace(t=ut.samples.t * 3))
    for name, trials, match in (
        ("mekf", [ut, nt, ut._replace(name="b")], r"mekf: the sizes of the trials' first magnetometer readings differ "
         r"widely \(in_nT far from the median 44.72; a magnetometer in another unit\?\): the defaults of r_mag"),
        ("vqf", [ut, slow], r"vqf: the trials' sampling steps \(s\) differ widely .*the defaults of ts0"),
        # two trials: the median is one trial's value (the mean of uT and nT, 2.2e4, fitted neither)
        ("mekf", [ut, nt], r"mekf: the sizes .* differ widely \(in_nT far from the median 44.72; a magnetometer"),
    ):  # fmt: skip
        entry = registry.get(name)
        with pytest.warns(UserWarning, match=match):
            api.recording_defaults_for_trials(entry, None, entry.params(), trials)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            api.recording_defaults_for_trials(entry, None, entry.params(), [ut, ut._replace(name="b")])
            api.recording_defaults_for_trials(entry, entry.params(), entry.params(), trials)  # the caller's params


def test_a_trials_score_does_not_depend_on_the_trials_beside_it():
    """broad_score gives each trial its own data-dependent defaults (the MEKF's field covariances scale with its
    magnetometer's unit, VQF's ts0 is its first step), as filter does for one recording: a trial scored beside a
    magnetometer in nT, or beside a trial at another rate, scores as it does alone (they used to share the
    batch's median)."""
    ut = _tiny_trial()
    ut = ut._replace(samples=ut.samples._replace(mag=ut.samples.mag + np.random.default_rng(5).normal(size=(40, 3))))
    nt = ut._replace(name="in_nT", samples=ut.samples._replace(mag=ut.samples.mag * 1e3))
    slow = ut._replace(name="slow", samples=ut.samples._replace(t=ut.samples.t * 3), rate_hz=100.0 / 3)
    for name, beside in (("mekf", [nt, nt._replace(name="b")]), ("vqf", [slow, slow._replace(name="b")])):
        alone = jaxatt.broad_score(name, None, [ut]).trials[ut.name].total_rmse_deg
        together = jaxatt.broad_score(name, None, [ut, *beside])
        assert together.trials[ut.name].total_rmse_deg == pytest.approx(alone, rel=1e-9, abs=1e-12), name
        other = jaxatt.broad_score(name, None, [beside[0]]).trials[beside[0].name].total_rmse_deg
        assert together.trials[beside[0].name].total_rmse_deg == pytest.approx(other, rel=1e-9, abs=1e-12), name
    mekf = registry.get("mekf")
    p, run_params = api.recording_defaults_per_trial(mekf, None, mekf.params(), [ut, nt])
    assert set(run_params) == {"r_mag"}
    np.testing.assert_allclose(run_params["r_mag"][1], run_params["r_mag"][0] * 1e6, rtol=1e-12)
    assert api.recording_defaults_per_trial(mekf, None, mekf.params(), [ut, ut._replace(name="b")])[1] is None
    assert api.recording_defaults_per_trial(mekf, mekf.params(), mekf.params(), [ut, nt])[1] is None  # the caller's


def _tiny_trial():
    rng = np.random.default_rng(3)
    n = 40
    samples = ImuSample(
        np.arange(n) * 0.01,
        rng.normal(size=(n, 3)) * 0.01,
        np.tile([0, 0, 9.8], (n, 1)),
        np.tile([0, 20, -40.0], (n, 1)),
    )
    return broad.Trial("00_tiny", samples, np.tile([1.0, 0, 0, 0], (n, 1)), np.ones(n, bool), 100.0, "undisturbed")


@pytest.mark.parametrize(
    "change, warning",
    [
        ({"gyr": np.rad2deg}, r"gyr reaches .* is it in deg/s"),
        ({"acc": lambda a: a / 9.81}, r"median \|acc\| is 1: is it in g"),
        ({"t": lambda t: t * 1000}, r"sample interval is 10 s: are the timestamps in ms\? .*dt= / --dt"),
        ({"t": lambda t: t * 1e6}, r"sample interval is 1e\+04 s: are the timestamps in us"),
        ({"mag": lambda v: np.full_like(v, np.nan)}, r"mag has no present reading \(every row NaN or all zero\)"),
        ({"acc": np.zeros_like}, r"acc has no present reading"),  # a logger's zeros for a sensor it lacks
        (
            {"t": lambda t: np.where(t > 0.3, t + 100.0, t)},
            r"1 sample intervals are longer than 10x .*, the longest 100 s after t = 0.3 s \(sample 30\)",
        ),
        (
            {"t": lambda t: np.arange(len(t), dtype=float)},
            r"interval is 1 s: are the timestamps in ms \(or is t a "
            r"sample counter\? if the log truly runs at 1 Hz, ignore this\)",
        ),  # a step of exactly 1 (1 kHz in ms) was not warned about
        ({"acc": lambda a: a / 9.81 * 1000}, r"median \|acc\| is 1000, far from 9.81 .*is it in mg"),
        ({"acc": lambda a: a * 100}, r"median \|acc\| is 981, far from 9.81 .*is it in mg"),
        (
            {"gyr": lambda g: np.clip(g + np.sin(np.arange(len(g)) * 0.3)[:, None] * [6.0, 0, 0], -4.4, 4.4)},
            r"gyr stays at exactly 4.4 in \d+ samples: is the sensor saturated",
        ),
    ],
)
def test_data_in_the_wrong_units_is_warned_about(change, warning):
    """Recordings in deg/s, g or ms are common; the front door says so (and still runs: units are not proof)."""
    n = 60
    t = np.arange(n) * 0.01
    d = {"t": t, "gyr": np.tile([0.0, 0.0, 1.0], (n, 1)), "acc": np.tile([0, 0, 9.81], (n, 1))}
    d["mag"] = np.tile([0, 20, -40.0], (n, 1))
    d = {k: change.get(k, lambda v: v)(v) for k, v in d.items()}
    with pytest.warns(UserWarning, match=warning):
        try:
            jaxatt.filter(MY_OBSERVER, d["gyr"], d["acc"], d["mag"], t=d["t"], params=MY_PARAMS)
        except FloatingPointError:  # an all-NaN magnetometer gives NaN in this simple observer: fine here
            pass
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the unchanged recording: no warning
        jaxatt.filter(
            MY_OBSERVER,
            np.tile([0.0, 0.0, 1.0], (n, 1)),
            np.tile([0, 0, 9.81], (n, 1)),
            np.tile([0, 20, -40.0], (n, 1)),
            t=t,
            params=MY_PARAMS,
        )


def test_a_sample_period_in_ms_is_warned_about_as_dt_not_as_timestamps():
    """dt=10 (a period in ms given as s): the warning names dt, and does not tell the user to give dt."""
    n = 60
    gyr, acc, mag = np.tile([0.0, 0.0, 1.0], (n, 1)), np.tile([0, 0, 9.81], (n, 1)), np.tile([0, 20, -40.0], (n, 1))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        jaxatt.filter(MY_OBSERVER, gyr, acc, mag, dt=10.0, params=MY_PARAMS)
    said = [str(w.message) for w in caught if "10 s" in str(w.message)]
    assert said == [
        "the sample period dt is 10 s: is it in ms? jaxatt expects s (time_unit='ms' in jaxatt.filter converts it)"
    ], [str(w.message) for w in caught]


def test_unit_arguments_give_the_filter_of_the_same_recording_in_si_units():
    """A logger's deg/s, g and ms (timestamps or sample period) through gyr_unit / acc_unit / time_unit give the
    estimates of the same recording in rad/s, m/s^2 and s, t in s, without the wrong-unit warnings; a float32
    recording stays float32."""
    n = 60
    rng = np.random.default_rng(1)
    t = np.arange(n) * 0.01
    gyr = np.tile([0.1, -0.2, 1.0], (n, 1)) + 0.01 * rng.standard_normal((n, 3))
    acc, mag = np.tile([0.3, 0, 9.81], (n, 1)), np.tile([0, 20, -40.0], (n, 1))
    si = jaxatt.filter(MY_OBSERVER, gyr, acc, mag, t=t, params=MY_PARAMS)
    raw = {"gyr_unit": "deg/s", "acc_unit": "g", "time_unit": "ms"}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # deg/s, g and ms are no longer warned about
        by_t = jaxatt.filter(MY_OBSERVER, np.rad2deg(gyr), acc / 9.80665, mag, t=t * 1e3, params=MY_PARAMS, **raw)
        by_dt = jaxatt.filter(MY_OBSERVER, np.rad2deg(gyr), acc / 9.80665, mag, dt=10.0, params=MY_PARAMS, **raw)
    for est in (by_t, by_dt):
        np.testing.assert_allclose(est.t, si.t, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(est.quat, si.quat, atol=1e-12)
        assert not np.allclose(
            est.quat,
            jaxatt.filter(MY_OBSERVER, gyr, acc, mag, t=t, params=MY_PARAMS._replace(kp=jnp.asarray(2.0))).quat,
            atol=1e-6,
        )  # the comparison can fail: other gains give other estimates
    # the recording as one ImuSample (what jaxatt.data.logs.load_log returns) is the same recording
    log = ImuSample(t * 1e3, np.rad2deg(gyr), acc / 9.80665, mag)
    np.testing.assert_array_equal(jaxatt.filter(MY_OBSERVER, log, params=MY_PARAMS, **raw).quat, by_t.quat)
    with pytest.raises(ValueError, match=r"gyr is a whole recording .*: mag, dt cannot be given beside it"):
        jaxatt.filter(MY_OBSERVER, log, None, mag, dt=0.01, params=MY_PARAMS)
    f32 = [np.asarray(a, np.float32) for a in (np.rad2deg(gyr), acc / 9.80665, mag)]
    est32 = jaxatt.filter(MY_OBSERVER, *f32, dt=10.0, params=MY_PARAMS, **raw)
    assert est32.quat.dtype == np.float32
    np.testing.assert_allclose(est32.quat, si.quat, atol=1e-5)


def test_a_degenerate_first_sample_still_starts_on_so3():
    """NLO starts from TRIAD of the first sample; with a magnetometer reading zero (a dead sensor) the start was a
    rank-deficient matrix and the quaternions had norm 0.7 with exit 0. Now every estimate is a unit quaternion
    and the inclination (the only thing a dead magnetometer leaves observable) is right."""
    n = 50
    g, a = np.zeros((n, 3)), np.tile([0.0, 3.0, 9.3], (n, 1))
    with pytest.warns(UserWarning, match="mag has no present reading"):
        est = jaxatt.filter("nlo", g, a, np.zeros((n, 3)), dt=0.01)
    np.testing.assert_allclose(np.linalg.norm(est.quat, axis=-1), 1.0, atol=1e-9)
    np.testing.assert_allclose(est.rotation[:, 2], np.tile(a[0] / np.linalg.norm(a[0]), (n, 1)), atol=1e-6)


def test_a_slowly_turning_gyro_in_deg_per_s_is_warned_about():
    """At 0.2-1 rad/s a gyro in deg/s stays under 2000 "rad/s": the front door compares how far it turns with the
    acc-mag frame (about 1x in rad/s, 57x in deg/s) and says so; the same recording in rad/s gets no warning."""
    samples, _ = montecarlo.simulate_log(jaxatt.api.ahrs_scenario(), duration=20.0, dt=0.01)
    g, a, m = (np.asarray(x) for x in (samples.gyr, samples.acc, samples.mag))
    assert np.abs(np.rad2deg(g)).max() < 35.0  # the range check alone would not see it
    with pytest.warns(UserWarning, match=r"the gyro turns 5\d\.?\d*x as far as the accelerometer and magnetometer"):
        jaxatt.filter("madgwick", np.rad2deg(g), a, m, dt=0.01)
    assert 0.8 < jaxatt.api.gyro_rotation_ratio(g, a, m, np.arange(len(g)) * 0.01) < 1.25
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jaxatt.filter("madgwick", g, a, m, dt=0.01)


def _spin(rate: float, n: int = 3000, dt: float = 0.01):
    """gyr, acc, mag (body, rad/s, m/s^2, uT) of a constant spin at ``rate`` rad/s about a tilted axis (NED)."""
    axis = np.array([0.3, 0.5, 1.0]) / np.linalg.norm([0.3, 0.5, 1.0])
    rot = np.asarray(so3.exp(jnp.asarray(rate * dt * np.arange(n)[:, None] * axis)))  # body -> NED
    g, m = np.array([0.0, 0.0, -9.81]), np.array([20.0, 0.0, 40.0])
    acc, mag = np.einsum("tji,j->ti", rot, g), np.einsum("tji,j->ti", rot, m)
    return np.tile(rate * axis, (n, 1)), acc, mag


def test_the_gyro_units_check_sees_fast_spins_slow_sensors_and_dropouts_right():
    """A genuine spin at 3.5-30 rad/s turns the acc-mag frame past a half turn within a window (its net angle
    wraps): such windows are left out and no deg/s warning is given (it was, at 6-21x). A magnetometer at a
    tenth of the rate and one missing acc reading still let a slow deg/s gyro be told (57x). A sample step that
    underflows (1e-320 s) gives no answer instead of an OverflowError."""
    for rate in (3.5, 10.0, 30.0):
        g, a, m = _spin(rate)
        assert jaxatt.api.gyro_rotation_ratio(g, a, m, np.arange(len(g)) * 0.01) is None, rate
    g, a, m = _spin(0.5)
    t = np.arange(len(g)) * 0.01
    assert jaxatt.api.gyro_rotation_ratio(g, a, m, t) == pytest.approx(1.0, rel=0.02)
    m[np.arange(len(m)) % 10 != 0] = np.nan
    a[77] = np.nan
    assert jaxatt.api.gyro_rotation_ratio(np.rad2deg(g), a, m, t) == pytest.approx(np.rad2deg(1.0), rel=0.02)
    assert jaxatt.api.gyro_rotation_ratio(g, a, m, np.arange(len(g)) * 1e-320) is None
    g, a, m = _spin(10.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jaxatt.filter("madgwick", g, a, m, dt=0.01)
    # a gyro already in rad/s, declared in deg/s, is converted a second time (57x too small): said (was silent)
    g, a, m = _spin(0.5)
    with pytest.warns(UserWarning, match=r"the gyro turns 0.017\dx as far .*: is gyr converted twice"):
        jaxatt.filter("madgwick", g, a, m, dt=0.01, gyr_unit="deg/s")
    # but not a car that brakes and accelerates on a straight road (the acc-mag frame tilts, the gyro does not
    # turn, about no common axis) nor a sensor at rest in a swinging field: the gyro is right, and it was warned
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 60.0, 0.01)
    push = np.where(np.isin((np.arange(t.size) // 400) % 5, (0,)), 3.0, 0.0)
    push -= np.where(np.isin((np.arange(t.size) // 400) % 5, (2,)), 3.0, 0.0)
    acc = [0.0, 0.0, 9.81] + np.stack([0 * t, push, 0 * t], -1) + 0.05 * rng.standard_normal((t.size, 3))
    swing = np.deg2rad(25.0) * np.sin(2 * np.pi * t / 8.0)
    field = np.stack([-20.0 * np.sin(swing), 20.0 * np.cos(swing), np.full(t.size, -40.0)], -1)
    gyr = 0.003 * rng.standard_normal((t.size, 3))
    for a_, m_ in (
        (acc, [0.0, 20.0, -40.0] + 0.3 * rng.standard_normal((t.size, 3))),
        ([0.0, 0.0, 9.81] + 0 * acc, field),
    ):
        assert jaxatt.api.gyro_rotation_ratio(gyr, a_, m_, t) < jaxatt.api.LOW_ROTATION_RATIO
        assert not [n for n in jaxatt.api._implausible_notes(gyr, a_, m_, t, False, "f", "f") if "twice" in n]


@pytest.mark.parametrize("name", ["nlo", "madgwick"])
def test_a_recording_without_a_magnetometer_runs_inclination_only(name):
    """A 6-axis recording (no mag) through a 9D observer: the same run as a magnetometer that never reads (every
    row NaN), said in a warning, every estimate a unit quaternion with the inclination right. NLO takes its start
    from TRIAD of sample 0: with no magnetometer reading at all its estimates were NaN from sample 1."""
    samples, truth = montecarlo.simulate_log(jaxatt.api.ahrs_scenario(), duration=2.0, dt=0.01)
    g, a = np.asarray(samples.gyr), np.asarray(samples.acc)
    with pytest.warns(UserWarning, match=f"no magnetometer given: observer '{name}' runs without one"):
        est = jaxatt.filter(name, g, a, None, dt=0.01)
    with pytest.warns(UserWarning, match="mag has no present reading"):
        dead = jaxatt.filter(name, g, a, np.full_like(g, np.nan), dt=0.01)
    np.testing.assert_array_equal(est.quat, dead.quat)
    np.testing.assert_allclose(np.linalg.norm(est.quat, axis=-1), 1.0, atol=1e-9)
    z_true, z_est = np.asarray(truth.r)[:, 2, :], est.rotation[:, 2, :]
    assert np.degrees(np.arccos(np.clip(np.sum(z_true * z_est, -1), -1, 1)))[-50:].max() < 10.0


@pytest.mark.parametrize("name", ["mekf", "nlio"])
def test_observers_set_up_from_the_first_sample_take_the_first_present_reading(name):
    """mekf, nlo, nlio and complementary take their start and references (TRIAD, the field, |a|) from sample 0;
    with its mag (or acc) reading missing (NaN, a slower magnetometer) every estimate was NaN. Now a missing row-0
    reading is the sensor's first present one carried back by the gyro (so3.first_present_at_start): the estimate
    equals the run on the recording whose row 0 holds those readings (row 0 only feeds init on hold "next"), and
    it follows the truth of the simulated rotation."""
    samples, truth = montecarlo.simulate_log(jaxatt.api.ahrs_scenario(), duration=2.0, dt=0.01)
    g, a, m = (np.asarray(x, float) for x in (samples.gyr, samples.acc, samples.mag))
    gaps_a, gaps_m = a.copy(), m.copy()
    gaps_a[0] = np.nan
    gaps_m[:3] = np.nan
    est = jaxatt.filter(name, g, gaps_a, gaps_m, dt=0.01)
    filled_a, filled_m = gaps_a.copy(), gaps_m.copy()

    def carry(x, j):  # row j carried back to row 0 by the gyro
        return np.asarray(so3.first_present_at_start(jnp.asarray(x[: j + 1]), jnp.asarray(g[: j + 1]), 0.01))[0]

    filled_a[0], filled_m[0] = carry(gaps_a, 1), carry(gaps_m, 3)
    ref = jaxatt.filter(name, g, filled_a, filled_m, dt=0.01)
    np.testing.assert_array_equal(est.quat, ref.quat)
    r_err = np.asarray(truth.r, float)[1:] @ np.swapaxes(est.rotation[1:], -1, -2)  # sensor-to-ENU truth
    angle = np.degrees(np.arccos(np.clip((np.trace(r_err, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)))
    assert np.all(np.isfinite(angle)) and angle.max() < 3.0, angle.max()


def _filter_scan(name: str, n_run: int):
    """The compiled scan jaxatt.filter runs for registered observer ``name`` over ``n_run`` float64 samples at a
    constant dt (``engine.compiled`` is cached on its arguments, so this is the same jitted object)."""
    from jaxatt.observers import registry

    e = registry.get(name)
    return engine.compiled(
        registry.recorded_observer(e),
        engine.Recorded(n_run - 1, False),
        engine.records_of(jaxatt.api._pick_all, 1),
        obs_dtype=np.dtype(np.float64),
    )


def test_float32_data_with_epoch_timestamps_keeps_its_times():
    """float32 sensors stamped with Unix times (1.7e9 s): the filter runs in float32, but the times it returns, as
    ``t`` and as the ``t`` output, are the given float64 stamps (float32 rounds them to 128 s)."""
    n = 300
    t = 1.7e9 + 0.01 * np.arange(n)
    g = np.zeros((n, 3), np.float32)
    a, m = np.tile(np.float32([0, 0, 9.81]), (n, 1)), np.tile(np.float32([20, 0, -40]), (n, 1))
    est = jaxatt.filter("robust", g, a, m, t=t)
    assert est.quat.dtype == np.float32
    np.testing.assert_array_equal(est.t, t)
    np.testing.assert_array_equal(est.outputs["t"], t)
    # float32 stamps of a device clock at 1e5 s step by 0.0078 / 0.0156 s instead of 0.01 s: said (was silent);
    # the same stamps near 0 resolve the interval: nothing said
    t32 = (1e5 + 0.01 * np.arange(n)).astype(np.float32)
    with pytest.warns(UserWarning, match=r"t is float32: near 1e\+05 s it resolves 0.00781 s, against a sample"):
        jaxatt.filter("robust", g, a, m, t=t32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jaxatt.filter("robust", g, a, m, t=(0.01 * np.arange(n)).astype(np.float32))


def test_datetime64_timestamps_are_read_in_their_own_unit():
    """numpy datetime64 / timedelta64 stamps (1 ms apart, as a pandas column gives them) are seconds from their own
    unit: the same estimates as the float seconds 0, 0.001, ... (read as plain numbers, 1 ms would be 1 s)."""
    n = 200
    rng = np.random.default_rng(5)
    g = rng.normal(size=(n, 3)) * 0.3
    a, m = np.tile([0.0, 0.0, 9.81], (n, 1)), np.tile([20.0, 0.0, -40.0], (n, 1))
    ref = jaxatt.filter("madgwick", g, a, m, t=0.001 * np.arange(n))
    stamps = np.datetime64("2026-12-04T05:00:00.000") + np.arange(n) * np.timedelta64(1, "ms")
    for t in (stamps, np.arange(n) * np.timedelta64(1, "ms")):
        est = jaxatt.filter("madgwick", g, a, m, t=t)
        np.testing.assert_allclose(est.quat, ref.quat, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="t must be an array of timestamps"):
        jaxatt.filter("madgwick", g, a, m, t=np.ones(n, bool))


def test_weakly_typed_gains_reuse_the_compiled_filter():
    """Gains given as Python floats or weakly typed arrays (``jnp.asarray(0.1)``) run the program compiled for the
    same gains typed (no new entry in the compiled scan's cache), with the same estimates."""
    from jaxatt.observers import madgwick

    n = 120
    rng = np.random.default_rng(3)
    g = rng.normal(size=(n, 3)) * 0.01
    a, m = np.tile([0.0, 0.0, 9.81], (n, 1)), np.tile([20.0, 0.0, -40.0], (n, 1))
    scan = _filter_scan("madgwick", n)
    p = madgwick.default_params(dtype=jnp.float64)
    typed = jaxatt.filter("madgwick", g, a, m, dt=0.01, params=p._replace(beta=jnp.asarray(0.2, jnp.float64)))
    size = scan._cache_size()
    assert size >= 1
    for beta in (jnp.asarray(0.2), 0.2):
        est = jaxatt.filter("madgwick", g, a, m, dt=0.01, params=p._replace(beta=beta))
        np.testing.assert_array_equal(est.quat, typed.quat)
    assert scan._cache_size() == size  # without the cast: one more program per weak type


def test_seeds_beyond_32_bits_give_their_own_runs_with_float64_off():
    """Run k of seed s uses fold_in(PRNGKey(s), k) with PRNGKey(s) as JAX computes it in float64 mode, also with
    float64 off, where PRNGKey keeps the low 32 bits only (seed 2^32 silently repeated seed 0's runs)."""
    seeds = [0, 1, 2**31, 2**32, 2**40 + 5, 2**63 - 1, -1, -(2**63)]
    for s in seeds:  # the tests run with float64 on
        np.testing.assert_array_equal(montecarlo.seed_key(s), jax.random.PRNGKey(s))
    with jax.enable_x64(False):
        assert len({np.asarray(montecarlo.seed_key(s)).tobytes() for s in seeds}) == len(seeds)
        assert not np.array_equal(montecarlo.run_keys(2**32, [0, 1]), montecarlo.run_keys(0, [0, 1]))
        assert jaxatt.ahrs_scenario is jaxatt.api.ahrs_scenario  # the scenario is at the top level too


def test_the_monte_carlo_engine_refuses_an_empty_window_and_a_previous_result_it_cannot_continue():
    """montecarlo.monte_carlo (the engine under jaxatt.monte_carlo and the studies) checks what the front door
    checks: a window_start outside the run gave metrics of 0 over an empty window; a ``previous`` result with runs
    beyond ``runs``, a repeated run or other traces was merged without a word."""
    from jaxatt import studies

    s = studies.get("complementary").setup(duration=2.0)
    kw = dict(runs=2, duration=2.0, dt=s.dt, seed=3, errors_fn=s.errors_fn)
    for ws in (5.0, float("nan"), -1.0):
        with pytest.raises(ValueError, match=r"window_start \(.* s\) must lie inside the run \[0, 2.0\) s"):
            montecarlo.monte_carlo(s.scenario, s.observer, s.params, window_start=ws, **kw)
    done = montecarlo.monte_carlo(s.scenario, s.observer, s.params, **kw)
    assert done.complete and list(done.run_indices) == [0, 1]
    for previous, match in (
        ({}, "previous must be the MonteCarloResult of an interrupted call, got dict"),
        (done._replace(run_indices=np.array([0, 0])), "repeats a run"),
        (done._replace(run_indices=np.array([0, 3])), r"previous holds run 3, outside the runs 0 \.\.\. 1"),
    ):
        with pytest.raises(ValueError, match=match):
            montecarlo.monte_carlo(s.scenario, s.observer, s.params, previous=previous, **kw)
    with pytest.raises(ValueError, match=r"previous has no traces, and this call asks for traces"):
        montecarlo.monte_carlo(s.scenario, s.observer, s.params, previous=done, trace_every=100, **kw)
    # a finished result continued is itself
    again = montecarlo.monte_carlo(s.scenario, s.observer, s.params, previous=done, **kw)
    assert again.complete and {k: v.tolist() for k, v in again.per_run.items()} == {
        k: v.tolist() for k, v in done.per_run.items()
    }


def test_a_duration_of_whole_float32_steps_is_accepted_and_a_fit_refuses_a_fractional_one():
    """A float32 dt (np.float32(0.01) = 0.00999999977 s) divides 60 s to its rounding (it was refused as 'not a
    whole number of steps of dt = 0.01 s'); a fit on a study refuses 4 s of 0.3-s steps (it trained on 13 steps,
    3.9 s, and recorded 4 s)."""
    assert montecarlo.whole_steps(60.0, np.float32(0.01)) == 6000
    assert montecarlo.whole_steps(3600.0, np.float32(0.01)) == 360000
    with pytest.raises(ValueError, match=r"duration \(1 s\) must be a whole number of steps of dt = 0.3 s"):
        montecarlo.whole_steps(1.0, 0.3)
    with pytest.raises(ValueError, match=r"duration \(4 s\) must be a whole number of steps of dt = 0.3 s"):
        jaxatt.fit(None, None, "complementary", steps=1, config={"duration": 4.0, "dt": 0.3}, train_runs=2, val_runs=0)
    # the simulation loss is monte_carlo's simulation: the same steps, the same refusal (it rounded 4 s to 13 steps)
    from jaxatt.fitting import losses

    obs = registry.get("batista-so3").make()
    with pytest.raises(ValueError, match=r"duration \(4 s\) must be a whole number of steps of dt = 0.3 s"):
        losses.make_loss_fn(obs, duration=4.0, dt=0.3, spec=losses.LossSpec())
    # an observer whose own hold is "next" (Madgwick) is refused by the simulation loss saying that it is its own
    with pytest.raises(ValueError, match=r"got 'next' \(observer 'madgwick''s own hold: pass hold='zoh' or 'linear'\)"):
        losses.make_loss_fn(registry.get("madgwick").make(), duration=1.0, dt=0.01, spec=losses.LossSpec())


def test_an_interrupted_monte_carlo_warns_and_continues_from_its_result():
    """jaxatt.monte_carlo interrupted (here from on_chunk, or from the progress reporter at a chunk's end) returns
    the finished runs with a warning (it was silent), and ``previous=`` runs only the rest: the same numbers as
    one uninterrupted call. (An interrupt in the reporter dropped the chunk just finished.)"""
    kw = dict(runs=4, duration=0.5, chunk=2, seed=1)
    full = jaxatt.monte_carlo("mahony", **kw)

    def stop(_):
        raise KeyboardInterrupt

    def stop_after_two(info):
        if info["runs_done"] >= 2:
            raise KeyboardInterrupt

    for how in (dict(on_chunk=stop), dict(progress=stop_after_two)):
        with pytest.warns(UserWarning, match=r"interrupted after 2 of 4 runs .* previous="):
            part = jaxatt.monte_carlo("mahony", **kw, **how)
        assert not part.complete and list(part.run_indices) == [0, 1], how
        rest = jaxatt.monte_carlo("mahony", **kw, previous=part)
        assert rest.complete and list(rest.run_indices) == [0, 1, 2, 3]
        for k, v in full.per_run.items():
            np.testing.assert_array_equal(rest.per_run[k], v, err_msg=k)


def test_a_monte_carlo_saved_to_a_file_is_resumed_from_it(tmp_path):
    """``out=``: the runs are saved after every chunk, so a process that dies keeps them; ``resume=True`` runs the
    rest (the numbers of one uninterrupted call), returns a complete file without running, extends it to more
    runs, and refuses a file of another call; an existing file is not replaced without ``overwrite=True``."""
    from jaxatt import montecarlo

    kw = dict(duration=0.5, chunk=2, seed=1)
    full = jaxatt.monte_carlo("mahony", runs=4, **kw)
    out = tmp_path / "mc.npz"

    def die(_):  # the process is stopped after its first chunk: what was saved is what the file holds
        raise KeyboardInterrupt

    with pytest.warns(UserWarning, match="interrupted after 2 of 4 runs"):
        jaxatt.monte_carlo("mahony", runs=4, **kw, out=out, on_chunk=die)
    saved = montecarlo.load_result(out)
    assert list(saved.run_indices) == [0, 1] and not saved.complete
    seen = []
    rest = jaxatt.monte_carlo("mahony", runs=4, **kw, out=out, resume=True, on_chunk=seen.append)
    assert rest.complete and list(rest.run_indices) == [0, 1, 2, 3] and len(seen) == 1  # one chunk run, not two
    for k, v in full.per_run.items():
        np.testing.assert_array_equal(rest.per_run[k], v, err_msg=k)
        np.testing.assert_array_equal(montecarlo.load_result(out).per_run[k], v, err_msg=k)
    again = jaxatt.monte_carlo("mahony", runs=4, **kw, out=out, resume=True, on_chunk=seen.append)
    assert len(seen) == 1 and again.complete  # complete: nothing run
    more = jaxatt.monte_carlo("mahony", runs=6, **kw, out=out, resume=True)
    assert list(more.run_indices) == list(range(6))
    np.testing.assert_array_equal(more.per_run["mean_angle_error_deg"][:4], full.per_run["mean_angle_error_deg"])
    for call, match in (
        (dict(runs=6, **kw, out=out), r"out .*mc\.npz: exists; pass resume=True .* or overwrite=True"),
        (dict(runs=6, **{**kw, "seed": 2}, out=out, resume=True), r"holds runs of another call \(seed differs\)"),
        (dict(runs=3, **kw, out=out, resume=True), r"holds runs up to run 5: ask for runs >= 6"),
        (dict(runs=6, **kw, out=out, resume=True, overwrite=True), r"pass one"),
        (dict(runs=6, **kw, resume=True), r"resume=True needs out"),
        (dict(runs=6, **kw, out=tmp_path / "mc.json"), r"unknown extension"),
    ):
        with pytest.raises(ValueError, match=match):
            jaxatt.monte_carlo("mahony", **call)
    # your own observer is known by what it computes, not by its name: an edited step of the same name is refused
    own = tmp_path / "own.npz"
    jaxatt.monte_carlo(MY_OBSERVER, MY_PARAMS, runs=2, **kw, out=own)
    twice_the_gain = Observer(my_init, lambda p, st, s, dt: my_step(p._replace(kp=2 * p.kp), st, s, dt), "my_mahony")
    with pytest.raises(ValueError, match=r"another call \(the observer's code \(an edited function"):
        jaxatt.monte_carlo(twice_the_gain, MY_PARAMS, runs=4, **kw, out=own, resume=True)
    assert jaxatt.monte_carlo(MY_OBSERVER, MY_PARAMS, runs=3, **kw, out=own, resume=True).complete
    (tmp_path / "junk.npz").write_text("not an archive")
    with pytest.raises(ValueError, match="junk.npz is not a runs file of jaxatt"):
        jaxatt.monte_carlo("mahony", runs=2, **kw, out=tmp_path / "junk.npz", resume=True)
    replaced = jaxatt.monte_carlo("mahony", runs=2, **kw, out=out, overwrite=True)
    assert list(montecarlo.load_result(out).run_indices) == [0, 1] and replaced.complete
    assert jaxatt.monte_carlo("mahony", runs=2, **kw, out="/dev/null", resume=True).complete  # nothing kept there
    with pytest.raises(ValueError, match="seed must be"):  # checked before the file's spec is made of it
        jaxatt.monte_carlo("mahony", runs=2, **{**kw, "seed": None}, out=tmp_path / "s.npz")


def test_montecarlo_run_warns_of_float64_computed_in_float32_and_of_a_non_finite_estimate():
    """montecarlo.run (the README's lower-level runner) follows the front door's rules: float64 samples with x64
    off are said to run in float32, and a non-finite estimate is said with its sample and time (both were silent)."""
    entry = registry.get("madgwick")
    samples, _ = montecarlo.simulate_log(jaxatt.ahrs_scenario(), duration=1.0, dt=0.01)
    s64 = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), samples)
    with jax.enable_x64(False):
        with pytest.warns(UserWarning, match=r"float64 input \(samples\) is computed in float32"):
            montecarlo.run(registry.recorded_observer(entry), entry.default_params(), s64)

    def nan_step(p, st, s, dt):
        new, out = my_step(p, st, s, dt)
        q = jnp.where(new.t > 0.5, jnp.nan, new.q)
        return new._replace(q=q), out._replace(q=q)

    with pytest.warns(UserWarning, match=r"'nan_after': the estimate is first non-finite at sample 5\d \(t = 0.5"):
        montecarlo.run(Observer(my_init, nan_step, "nan_after"), MY_PARAMS, samples, hold="next")


def test_float64_gains_of_a_monte_carlo_without_x64_are_warned_about():
    """As jaxatt.filter warns for float64 data: float64 gains computed in float32 (x64 off) are said."""
    with jax.enable_x64(False):
        p64 = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), registry.get("mahony").default_params())
        with pytest.warns(UserWarning, match="float64 params is computed in float32 because JAX's x64 mode is off"):
            res = jaxatt.monte_carlo("mahony", p64, runs=2, duration=0.5)
        assert res.per_run["mean_angle_error_deg"].dtype == np.float32


def test_weakly_typed_gains_reuse_the_compiled_monte_carlo():
    """The same for a Monte Carlo: a weakly typed gain runs the program compiled for the typed one, same numbers."""
    from jaxatt import studies

    s = studies.get("complementary").setup(duration=2.0)
    kw = dict(runs=2, duration=2.0, dt=s.dt, seed=3, errors_fn=s.errors_fn)
    typed = montecarlo.monte_carlo(s.scenario, s.observer, s.params._replace(k_i=jnp.asarray(0.3, jnp.float64)), **kw)
    scan = montecarlo._simulation(  # the program monte_carlo runs (engine.compiled is cached on its arguments)
        s.observer,
        duration=2.0,
        dt=s.dt,
        errors_fn=s.errors_fn,
        window_start=0.0,
        hold="zoh",
        trace_every=0,
        trace_fn=None,
        dtype=None,
        windows=(),
        init_params=None,
    )[1]
    size = scan._cache_size()
    assert size >= 1
    weak = montecarlo.monte_carlo(s.scenario, s.observer, s.params._replace(k_i=jnp.asarray(0.3)), **kw)
    assert scan._cache_size() == size
    np.testing.assert_array_equal(weak.per_run["mean_angle_error_deg"], typed.per_run["mean_angle_error_deg"])


def test_padded_lengths_are_whole_blocks_few_per_octave_and_not_much_longer():
    """api._run_length: never shorter; beyond one noise block a whole number of blocks (the compiled scan then holds
    one copy of the step, not a second one for a partial block); at most 4 lengths per octave (+1 for the
    octave's first length, +1 where the block rounding starts) and at most 25 % longer than the recording
    rounded up by a block."""
    block = engine.BLOCK
    ns = np.arange(1, 70_000)
    lengths = np.array([jaxatt.api._run_length(int(n)) for n in ns])
    assert np.all(lengths >= ns)
    beyond = ns - 1 > block
    assert np.all((lengths[beyond] - 1) % block == 0)
    assert np.all(lengths <= 1.25 * (ns + block))
    for k in range(9, 16):
        octave = lengths[(ns >= 2**k) & (ns < 2 ** (k + 1))]
        assert len(np.unique(octave)) <= jaxatt.api.LENGTHS_PER_OCTAVE + 2, (k, np.unique(octave))


def test_recordings_of_nearby_lengths_share_one_compiled_filter():
    """jaxatt.filter scans a recording padded to a length shared with its neighbours (api._run_length): the
    estimates of the first 3900 samples alone equal the first 3900 of 4001 (a causal scan, the padding
    dropped), and nothing is compiled for the second length. (The offline estimate of a padded recording equals
    the smoother's on the recording alone: tests/test_smoothing.py, broad_score against filter.)"""
    scn = jaxatt.api.ahrs_scenario(gyro_noise_std=1e-3, acc_noise_std=0.05, mag_noise_std=0.3)
    samples, _ = montecarlo.simulate_log(scn, duration=40.0, dt=0.01, seed=4)  # the length of the test above
    g, a, m = (np.asarray(x) for x in (samples.gyr, samples.acc, samples.mag))
    n, short = 4001, 3900
    assert jaxatt.api._run_length(n) == jaxatt.api._run_length(short) == 4001
    scan = _filter_scan("robust", 4001)
    full = jaxatt.filter("robust", g[:n], a[:n], m[:n], dt=0.01)
    size = scan._cache_size()
    assert size >= 1
    part = jaxatt.filter("robust", g[:short], a[:short], m[:short], dt=0.01)
    assert scan._cache_size() == size
    assert part.quat.shape == (short, 4) and part.t.shape == (short,)
    np.testing.assert_array_equal(part.quat, full.quat[:short])
    np.testing.assert_array_equal(part.outputs["bias"], full.outputs["bias"][:short])


def test_non_finite_estimate_is_an_error_naming_the_sample():
    """Gains that make the user's filter diverge: FloatingPointError with the first bad sample and time."""
    rng = np.random.default_rng(1)
    n = 400
    g, a, m = rng.normal(size=(n, 3)), np.tile([0, 0, 9.8], (n, 1)), np.tile([0, 20, -40.0], (n, 1))
    bad = MyParams(jnp.asarray(1e200), jnp.asarray(1e200))
    with pytest.raises(FloatingPointError, match=r"first non-finite .*at sample \d+ \(t = "):
        jaxatt.filter(MY_OBSERVER, g, a, m, dt=0.01, params=bad)


def test_float64_input_without_x64_warns_and_runs_float32():
    """jaxatt never switches x64 on: float64 input with x64 off is computed in float32, with a warning; a fresh
    process checks that importing and running jaxatt leaves the flag off."""
    import subprocess
    import sys

    from jaxatt import api

    jax.config.update("jax_enable_x64", False)
    try:
        with pytest.warns(UserWarning, match="x64"):
            assert api.compute_dtype(np.zeros(3)) == np.float32
        assert api.compute_dtype(np.zeros(3, np.float32)) == np.float32
        with pytest.raises(ValueError, match="x64"):
            api.compute_dtype(np.zeros(3), dtype="float64")
        # integer readings (counts) are no float64 input: no warning (it said "float64 input" before)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            ints = api._vectors("gyr", np.zeros((5, 3), np.int32), 5, True)
            assert ints.dtype == np.float32 and api.compute_dtype(ints, np.zeros((5, 3), np.float32)) == np.float32
    finally:
        jax.config.update("jax_enable_x64", True)
    assert api.compute_dtype(np.zeros(3)) == np.float64
    code = (
        "import warnings, numpy as np, jax, jaxatt\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        "    est = jaxatt.filter('mahony', np.zeros((20, 3)), np.tile([0, 0, 9.8], (20, 1)),\n"
        "                        np.tile([0, 20, -40.0], (20, 1)), dt=0.01)\n"
        "print(est.quat.dtype, jax.config.jax_enable_x64, any('x64' in str(x.message) for x in w))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.stdout.split() == ["float32", "False", "True"], out.stderr[-2000:]


def test_imu_sample_is_the_users_input_type():
    """The user's observer sees jaxatt.ImuSample with t, gyr, acc, mag in its init and step."""
    seen = {}

    def init(p, s):
        seen["init"] = type(s)
        return MyState(jnp.asarray(s.t), jnp.asarray([1.0, 0, 0, 0]), jnp.zeros(3))

    def step(p, st, s, dt):
        seen["step"] = type(s)
        return st._replace(t=st.t + dt), MyOut(st.t + dt, st.q, st.bias)

    jaxatt.filter(
        Observer(init, step, "probe"),
        np.zeros((3, 3)),
        np.tile([0.0, 0.0, 9.81], (3, 1)),
        np.ones((3, 3)),
        dt=0.1,
        params=MY_PARAMS,
    )
    assert seen == {"init": ImuSample, "step": ImuSample}


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"seed": 1.5}, "seed must be an integer"),
        ({"callback": 5}, "callback must be a function"),
        ({"tune": "beta"}, r"tune must be a list of gain names, e.g. \['beta'\]"),
        ({"patience": -1}, "patience must be"),
        ({"steps": True}, "steps must be an integer"),
        ({"lr": True}, "lr must be a positive number, got True"),
        ({"batch": 1.5}, "batch must be a whole number, got 1.5"),
        ({"batch": True}, "batch must be a whole number, got True"),
        ({"batch": "2"}, "batch must be a whole number, got '2'"),
        ({"lr": np.float32(0.05), "val_every": 0}, "val_every must be"),  # a numpy lr passes (it was refused)
    ],
)
def test_fit_arguments_of_the_wrong_kind_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        jaxatt.fit("madgwick", None, [_tiny_trial()], **{"steps": 1, **kwargs})


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"freeze": ["kp", "ki"]}, r"no gain left to tune \(freeze names every tunable field: \['ki', 'kp'\]\)"),
        ({"masks": {"kp": [True, False]}}, r"masks\['kp'\] of shape \[2\] does not fit its \[\] learnt values"),
    ],
)
def test_fit_options_on_your_observer_are_named(kwargs, match):
    """Freezing every gain of a user's observer, or a mask of the wrong shape, is one line naming it (they were
    errors from inside JAX / numpy: 'at least one array or dtype is required', 'cannot broadcast')."""
    with pytest.raises(ValueError, match=match):
        jaxatt.fit(MY_OBSERVER, MY_PARAMS, [_tiny_trial()], **{"steps": 1, **kwargs})


def test_one_float64_trial_makes_the_batch_float64():
    """compute_dtype looks at every trial: a float32 trial beside a float64 one does not narrow the float64 one."""
    t64 = _tiny_trial()
    t32 = t64._replace(
        name="01_tiny32", samples=jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32), t64.samples)
    )
    # robust: Madgwick's normalised gradient step makes rounding matter on this noise-free trial
    alone = jaxatt.broad_score("robust", None, [t64]).trials["00_tiny"].total_rmse_deg
    mixed = jaxatt.broad_score("robust", None, [t32, t64]).trials["00_tiny"].total_rmse_deg
    assert mixed == pytest.approx(alone, rel=1e-12, abs=1e-12)
    res = jaxatt.fit("madgwick", None, [t32, t64], steps=0)
    assert np.asarray(res.params.beta).dtype == np.float64


def narrow_step(p, st, s, dt):
    """my_step returning a float32 q (whatever the arithmetic)."""
    new, out = my_step(p, st, s, dt)
    return new, out._replace(q=out.q.astype(jnp.float32))


def test_narrowed_or_non_finite_outputs_of_a_users_observer_are_said():
    """float64 input and a step that returns a float32 q: a warning (the estimates lose precision); a finite q with
    a NaN field beside it: a warning naming the field (not a silent success)."""
    samples, _ = _short_log()

    def nan_step(p, st, s, dt):
        new, out = my_step(p, st, s, dt)
        return new, out._replace(bias=out.bias * jnp.nan)

    for step, match in ((narrow_step, "output field q of step is float32"), (nan_step, "output bias has non-finite")):
        with pytest.warns(UserWarning, match=match):
            jaxatt.filter(
                Observer(my_init, step, "mine"), samples.gyr, samples.acc, samples.mag, dt=0.01, params=MY_PARAMS
            )


def test_a_registered_filter_that_overflows_is_a_non_finite_result():
    """acc of 1e200 m/s^2 overflows a registered filter's normalisation: FloatingPointError (the CLI exits 1), not
    a complaint about the observer's code."""
    samples, _ = _short_log()
    with pytest.raises(FloatingPointError, match="madgwick"):
        jaxatt.filter("madgwick", samples.gyr, samples.acc * 1e200, samples.mag, dt=0.01)


def _short_log():
    scn = jaxatt.api.ahrs_scenario(gyro_noise_std=1e-4, acc_noise_std=0.01, mag_noise_std=0.05, gyro_bias=(0, 0, 0))
    samples, truth = montecarlo.simulate_log(scn, duration=2.0, dt=0.01)
    return samples, truth


#: a short batista-ges set-up for study fits that stop at their arguments
_SHORT = {"duration": 1.0}


@pytest.mark.parametrize(
    "study, config, match",
    [
        ("batista-ges", {"duration": "abc"}, "batista-ges setting 'duration' must be a finite number, got 'abc'"),
        ("batista-ges", {"latitude_deg": [1, 2]}, "setting 'latitude_deg' must be a finite number, got \\[1, 2\\]"),
        ("batista-ges", {"reference_nT": 5}, "setting 'reference_nT' must be a list of 3 finite numbers, got 5"),
        ("batista-ges", {"gyro_bias": "x"}, "setting 'gyro_bias' must be a list of 3 finite numbers, got 'x'"),
        ("batista-ges", {"r_hat_0": [1, 0, 0]}, "setting 'r_hat_0' must be a list of 9 or 3x3 finite numbers or None"),
        ("batista-ges", {"nope": 1}, r"unknown batista-ges settings \['nope'\]"),
        ("batista-ges", [("duration", 1.0)], "config must be a dict of batista-ges settings"),
        ("batista-ges", {1: 2.0}, "setting names must be strings"),
        ("batista-so3", {"trajectory": 3}, "batista-so3 setting 'trajectory' must be a string, got 3"),
        ("complementary", {"gain": True}, "complementary setting 'gain' must be a finite number, got True"),
        ("nlio-case1", {"observers": "NLO"}, "nlio-case1 setting 'observers' must be a list of strings"),
        ("nlio-case1", {"random_init": 1}, "nlio-case1 setting 'random_init' must be True or False"),
        ("nlio-case1", {"duration": [500]}, "nlio-case1 setting 'duration' must be a finite number"),
        ("nlio-case1", {"windows": [("a", 0, "x")]}, r"setting 'windows' must be a list of \(string, number, number\)"),
    ],
)
def test_a_study_fit_names_the_setting_of_the_wrong_kind(study, config, match):
    """jaxatt.fit(data=<study>, config={...}): a setting of the wrong kind is one ValueError naming it (checked
    against the study's Config once, for every study, jaxatt.fit and the command line alike)."""
    with pytest.raises(ValueError, match=match) as e:
        jaxatt.fit(data=study, steps=0, config={**_SHORT, **config} if isinstance(config, dict) else config)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"params": 3.0}, r"params of batista-ges \(study batista-ges\) must be its Params \(ref_nav, .*got float"),
        ({"params": jaxatt.observers.madgwick.Params(0.1)}, r"must be its Params .*got Params"),
        ({"params": {"nope": 1.0}}, "params: 'nope' is not a field"),
        ({"params": {"epsilon": "abc"}}, "params: epsilon is not numeric"),
        ({"dtype": "float16"}, "dtype must be float32 or float64, got 'float16'"),
        ({"dtype": "int32"}, "dtype must be float32 or float64"),
        ({"hold": "next"}, "hold must be 'zoh' or 'linear', got 'next'"),
        ({"hold": "linear", "config": {**_SHORT, "hold": "zoh"}}, r"hold='linear' and config\['hold'\]='zoh' differ"),
        ({"train_runs": "4"}, "train_runs must be a whole number"),
        ({"val_runs": -1}, "val_runs must be >= 0"),
    ],
)
def test_a_study_fit_refuses_params_dtype_and_hold_it_cannot_use(kwargs, match):
    with pytest.raises(ValueError, match=match) as e:
        jaxatt.fit(data="batista-ges", **{"steps": 0, "config": _SHORT, **kwargs})
    assert "\n" not in str(e.value)


def test_a_study_fit_takes_a_dict_of_gains_and_honours_hold(tmp_path):
    """params={gain: value} is put into the paper's gains; hold= becomes the study's hold setting (recorded in
    the gains file's config), not silently dropped."""
    out = tmp_path / "g.json"
    res = jaxatt.fit(
        data="batista-ges",
        objective="varfree",
        steps=0,
        config=_SHORT,
        params={"epsilon": 0.4},
        hold="linear",
        dtype="float64",
        out=str(out),
    )
    assert float(res.start_params.epsilon) == 0.4
    assert json.loads(out.read_text())["settings"]["config"]["hold"] == "linear"


def test_a_study_gains_file_is_refused_on_recorded_data_with_one_line(tmp_path):
    """``jaxatt tune --experiment complementary`` learns the study's gains (one vector measurement); the same name's
    filter on a recording has two (acc, mag). The file is refused when read, naming it, not deep in the scan."""
    path = tmp_path / "tune.json"
    gains = {"k": {"value": [0.6]}, "k_i": {"value": 0.0}, "l": {"value": []}}
    path.write_text(json.dumps({"format": "jaxatt-gains/2", "observer": "complementary", "study": "complementary",
                                "gains": gains, "status": "done"}))  # fmt: skip
    g, a, m = np.zeros((50, 3)), np.tile([0, 0, 9.8], (50, 1)), np.tile([0, 20, -40.0], (50, 1))
    want = rf"gains file {re.escape(str(path))}: gains of complementary learnt on the 'complementary' study's .*\.k is"
    with pytest.raises(ValueError, match=want) as e:
        jaxatt.filter("complementary", g, a, m, dt=0.01, params=str(path))
    assert "\n" not in str(e.value)
    # the same file is the study's params where a study reads it
    params = jaxatt.fitting.gainsfile.read_params(path, "complementary")
    assert np.shape(params.k) == (1,)


def test_a_6d_filter_s_monte_carlo_says_its_heading_is_not_observable():
    """vqf-6d has no magnetometer: its angle errors include the heading's gyro drift. jaxatt.monte_carlo warns
    (before anything runs) and the CLI's notes say so; a 9D filter's notes do not."""
    from jaxatt import studies

    with pytest.warns(UserWarning, match="vqf-6d does not use the magnetometer: its heading is not observable"):
        with pytest.raises(ValueError, match="duration must be a finite positive"):
            jaxatt.monte_carlo("vqf-6d", duration=0.0)
    ahrs = studies.get("ahrs")
    assert any("compare std_roll and std_pitch" in n for n in ahrs.notes(ahrs.config(observer="vqf-6d")))
    assert not any("not observable" in n for n in ahrs.notes(ahrs.config(observer="vqf")))


def _my_entry(name, step=my_step, **kw):
    """The user's observer registered under ``name`` (as docs/concepts.md shows)."""
    gains = (registry.Gain("kp", "1/s", "proportional gain"), registry.Gain("ki", "1/s^2", "integral gain"))
    return registry.Entry(
        name, "mine", "-", lambda: Observer(my_init, step, name),
        lambda dtype=None: jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), MY_PARAMS), gains, **kw,
    )  # fmt: skip


def test_a_registered_users_observer_is_checked_as_one_passed_directly():
    """An observer a user registers goes through the checks of one passed as an Observer (before, only unregistered
    ones were checked): a float32 q from float64 input is warned about, a non-unit q is refused naming the fix (not
    called an overflow), and broad_score refuses it before the batch run instead of scoring it."""
    samples, _ = _short_log()

    def double_step(p, st, s, dt):
        new, out = my_step(p, st, s, dt)
        return new, out._replace(q=2 * out.q)

    try:
        registry.register(_my_entry("_narrow", narrow_step))
        registry.register(_my_entry("_double", double_step))
        with pytest.warns(UserWarning, match="output field q of step is float32"):
            jaxatt.filter("_narrow", samples.gyr, samples.acc, samples.mag, dt=0.01)
        with pytest.raises(ValueError, match=r"not a unit quaternion .*\(normalise it in step\)"):
            jaxatt.filter("_double", samples.gyr, samples.acc, samples.mag, dt=0.01)
        truth = np.asarray(so3.matrix_to_quat(_short_log()[1].r))
        trial = broad.Trial("sim", samples, truth, np.ones(len(samples.t), bool), 100.0, "mine")
        with pytest.raises(ValueError, match="not a unit quaternion .* before the batch run"):
            jaxatt.broad_score("_double", None, [trial])
        with pytest.raises(ValueError, match="not a unit quaternion .* before the batch run"):
            jaxatt.monte_carlo("_double", runs=2, duration=2.0)
    finally:
        registry._EXTRA.pop("_narrow", None)
        registry._EXTRA.pop("_double", None)


@pytest.mark.parametrize(
    "change, error, match",
    [
        ({"gains": (registry.Gain("kq", "1/s", "typo"),)}, ValueError, r"'kq' is not a field of its params MyParams"),
        ({"gains": ("kp",)}, TypeError, r"gains must be a tuple of registry.Gain"),
        ({"default_params": lambda: MY_PARAMS}, TypeError, r"default_params must take dtype="),
        (
            {"default_params": lambda dtype=None: MY_PARAMS._replace(kp=1.0 / 0)},
            TypeError,
            r"default_params\(dtype=None\) raised ZeroDivisionError: float division by zero",
        ),
        ({"make": MY_OBSERVER}, TypeError, r"make must be a function, got Observer"),
        ({"make": lambda: 3}, TypeError, r"make\(\) must return a jaxatt.Observer, got int"),
        ({"frame": "XYZ"}, ValueError, r"frame must be one of ENU, NED, NWU, got 'XYZ'"),
        ({"hold": "cubic"}, ValueError, r"hold must be one of"),
        ({"needs": ("gps",)}, ValueError, r"needs must be a tuple of 'acc' / 'mag'"),
        ({"gains": (registry.Gain("kp", "1/s", "", "odd"),)}, ValueError, r"gain 'kp' has constraint not in"),
        ({"first_step": "ts"}, ValueError, r"'ts' is not a field"),
        ({"name": ""}, ValueError, r"Entry.name must be a non-empty string"),
    ],
)
def test_register_refuses_an_unusable_entry_naming_the_field(change, error, match):
    """registry.register checks the entry (before, a typo in a gain's field surfaced as an AttributeError inside
    jaxatt.fit, an Observer in ``make`` as 'not callable' at the first filter)."""
    with pytest.raises(error, match=match) as info:
        registry.register(_my_entry("_bad")._replace(**change))
    assert len(str(info.value).splitlines()) == 1 and "_bad" not in registry.names()
    with pytest.raises(TypeError, match="register takes a jaxatt.observers.registry.Entry, got Observer"):
        registry.register(MY_OBSERVER)


def test_a_registered_observer_estimating_in_nwu_is_scored_in_its_own_frame():
    """Madgwick reporting its sensor-to-NWU quaternion, registered with frame="NWU", scores as the built-in (ENU)
    in jaxatt.monte_carlo (it scored 89 deg: the ENU truth against the NWU estimate), broad_score and fit (they
    refused it, though filter converts it)."""
    inner = registry.get("madgwick").make()

    def nwu(out):
        return out._replace(q=out.q_nwu, r=so3.quat_to_matrix(out.q_nwu))

    def step(p, s, u, dt):
        s, out = inner.step(p, s, u, dt)
        return s, nwu(out)

    obs = Observer(inner.init, step, "_madgwick_nwu", lambda p, s: nwu(inner.output(p, s)), None, inner.hold)
    entry = registry.get("madgwick")._replace(name="_madgwick_nwu", make=lambda: obs, frame="NWU", module="")
    samples, truth = montecarlo.simulate_log(jaxatt.api.ahrs_scenario(), duration=5.0, dt=0.01, seed=1)
    n = len(samples.t)
    q_true = np.asarray(so3.matrix_to_quat(truth.r))
    trial = broad.Trial("01_sim", ImuSample(*(np.asarray(x) for x in samples)), q_true, np.ones(n, bool), 100.0)
    try:
        registry.register(entry)
        for name in ("madgwick", "_madgwick_nwu"):
            assert registry.get(name).frame == ("NWU" if name != "madgwick" else "ENU")
        mc = [
            jaxatt.monte_carlo(m, runs=2, duration=5.0).per_run["mean_angle_error_deg"]
            for m in ("madgwick", "_madgwick_nwu")
        ]
        np.testing.assert_allclose(mc[1], mc[0], rtol=1e-9)
        assert np.all(mc[0] < 5.0)
        score = [jaxatt.broad_score(m, None, [trial]).trials["01_sim"] for m in ("madgwick", "_madgwick_nwu")]
        assert score[0].total_rmse_deg < 5.0
        np.testing.assert_allclose(score[1][:3], score[0][:3], rtol=1e-9)
        fits = [jaxatt.fit(m, None, [trial], val=[trial], steps=0).start_loss for m in ("madgwick", "_madgwick_nwu")]
        assert fits[1] == pytest.approx(fits[0], rel=1e-9)
    finally:
        registry._EXTRA.pop("_madgwick_nwu", None)


def test_a_fit_that_stops_on_non_finite_losses_warns():
    """A fit whose loss is NaN at every step returned status 'non-finite' and its starting gains without a word
    (the CLI exits 1 on the same): now a NonFiniteFit warning says so."""
    samples, truth = _short_log()

    def late_nan_step(p, st, s, dt):
        new, out = my_step(p, st, s, dt)
        q = jnp.where(s.t > 1.5, jnp.nan, new.q)
        return new._replace(q=q), out._replace(q=q)

    quat = np.asarray(so3.matrix_to_quat(truth.r))
    trial = broad.Trial("sim", samples, quat, np.ones(len(samples.t), bool), 100.0, "own")
    with pytest.warns(fitter.NonFiniteFit, match="stopped on a non-finite loss"):
        res = jaxatt.fit(Observer(my_init, late_nan_step, "late"), MY_PARAMS, [trial], steps=3)
    assert res.status == "non-finite"


def test_a_quiet_quantised_gyro_is_not_called_saturated():
    """A +-2000 deg/s gyro at rest repeats its largest quantisation step (0.001 rad/s) often; that is not its full
    scale, and no saturation is said (it was, for every seed at 0.8 LSB of noise)."""
    lsb = np.deg2rad(2000.0) / 32768
    for seed in range(5):
        quiet = np.round(np.random.default_rng(seed).normal(size=(10000, 3)) * 0.8) * lsb
        assert jaxatt.api._saturated(quiet, jaxatt.api.SATURATION_FLOOR["gyr"]) is None


def test_bad_timestamps_are_refused_naming_the_row():
    """Timestamps given to filter (and every loader, through data.logs.check_timestamps) name the first bad row;
    stamps rounded coarser than the sample period (0.01 s at 285 Hz) say so and point to dt."""
    n = 60
    gyr, acc, mag = np.zeros((n, 3)), np.tile([0, 0, 9.81], (n, 1)), np.tile([0, 20, -40.0], (n, 1))
    t = np.arange(n) * 0.01
    for bad, match in (
        (np.r_[t[:3], t[2:-1]], r"^t must be strictly increasing \(s\): t\[3\] = 0.02 after t\[2\] = 0.02$"),
        (np.where(np.arange(n) == 7, np.nan, t), r"^t must be finite \(s\): t\[7\] is nan$"),
        (np.round(np.arange(n) / 285.0, 2), r"steps repeat a timestamp .*coarser than the sample period\? give the "
         r"sample period \(dt\) instead"),
    ):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            jaxatt.filter(MY_OBSERVER, gyr, acc, mag, t=bad, params=MY_PARAMS)


def test_units_and_frames_are_read_whatever_their_case():
    """A logger writes "DEG/S", "G", "MS": the unit and frame arguments are read case-insensitively, in the API and
    on the command line (the API took frame="ned" but refused "G"; the CLI refused --frame ned)."""
    from jaxatt import cli, frames

    assert frames.unit_factor("gyr_unit", "DEG/S") == frames.unit_factor("gyr_unit", "deg/s")
    assert frames.unit_factor("acc_unit", " G ") == frames.unit_factor("acc_unit", "g")
    with pytest.raises(ValueError, match=r"time_unit must be one of 's', 'ms', 'us', 'ns', got 'minutes'"):
        frames.unit_factor("time_unit", "minutes")
    args = cli._parser().parse_args(
        ["filter", "--log", "x.csv", "--observer", "robust", "--frame", "ned", "--gyr-unit", "DEG/S", "--acc-unit", "G",
         "--time-unit", "MS", "--out", "o.csv"]
    )  # fmt: skip
    assert (args.frame, args.gyr_unit, args.acc_unit, args.time_unit) == ("NED", "deg/s", "g", "ms")
    # the spellings loggers and datasheets use: degree signs, "sec", superscripts, micro signs
    for arg, spellings, unit in (
        ("gyr_unit", ("°/s", "deg/sec", "Degrees/s", "°/sec", "deg/second"), "deg/s"),
        ("gyr_unit", ("rad/sec", "radians/s"), "rad/s"),
        ("acc_unit", ("m/s²", "m/s/s", "m/s**2", "M/S^2"), "m/s^2"),
        ("time_unit", ("µs", "μs", "usec"), "us"),
        ("time_unit", ("sec", "msec"), None),
    ):
        for s in spellings:
            want = frames.unit_factor(arg, unit or {"sec": "s", "msec": "ms"}[s])
            assert frames.unit_factor(arg, s) == want, (arg, s)
    args = cli._parser().parse_args(
        ["filter", "--log", "x.csv", "--observer", "robust", "--gyr-unit", "°/s", "--acc-unit", "m/s²", "--time-unit",
         "µs", "--out", "o.csv"]
    )  # fmt: skip
    assert (args.gyr_unit, args.acc_unit, args.time_unit) == ("deg/s", "m/s^2", "us")
    assert cli._parser().parse_args(["excitation", "--log", "x.csv", "--frame", "nwu"]).frame == "NWU"  # as elsewhere


def test_pandas_nullable_numbers_and_timezone_aware_times_are_read():
    """pandas' nullable Float64 columns (NA for a missing cell: numpy reads them as objects) and timezone-aware
    timestamps were refused as "got object"; they are read as floats with NaN and UTC times. pandas is not a
    dependency: a stand-in with its to_numpy / dt.tz_convert behaviour."""

    class Nullable:  # pd.array(..., dtype="Float64") in a DataFrame: to_numpy(dtype, na_value)
        def __init__(self, a):
            self.a = a

        def to_numpy(self, dtype=None, na_value=None):
            return np.where(np.isnan(self.a), na_value, self.a).astype(dtype)

        def __array__(self, dtype=None, copy=None):
            return np.asarray(self.a, object)

    class Zoned:  # a tz-aware DatetimeIndex: tz, tz_convert(None) -> naive UTC
        tz = "Europe/Berlin"

        def __init__(self, t):
            self.t = t

        def to_numpy(self, dtype=None, na_value=None):
            raise TypeError("cannot convert datetimes with a zone to float")

        def tz_convert(self, zone):
            assert zone is None
            return self.t

    n = 60
    gyr = np.tile([0.0, 0.0, 0.5], (n, 1))
    acc, mag = np.tile([0, 0, 9.81], (n, 1)), np.tile([0, 20, -40.0], (n, 1))
    t = np.datetime64("2026-01-01T00:00:00") + np.arange(n) * np.timedelta64(10, "ms")
    with_na = mag.copy()
    with_na[5] = np.nan
    ref = jaxatt.filter("mahony", gyr, acc, with_na, t=t)
    got = jaxatt.filter("mahony", gyr, acc, Nullable(with_na), t=Zoned(t))
    np.testing.assert_array_equal(got.quat, ref.quat)


def test_a_recording_without_timestamps_is_timed_by_dt_and_a_trial_without_a_group_is_refused_at_once():
    """An ImuSample with t=None was refused both without dt ('dt is required') and with it ('dt cannot be given
    beside it'): dt now times it. A hand-built Trial whose name has no BROAD number and no group ran the whole
    scan of broad_score before failing on its group with no hint: check_trials refuses it first, saying how."""
    n = 300
    rng = np.random.default_rng(5)
    g, a, m = rng.normal(size=(n, 3)) * 0.01, np.tile([0, 0, 9.81], (n, 1)), np.tile([0, 20, -40.0], (n, 1))
    est = jaxatt.filter("madgwick", ImuSample(None, g, a, m), dt=0.01)
    np.testing.assert_array_equal(est.quat, jaxatt.filter("madgwick", g, a, m, dt=0.01).quat)
    with pytest.raises(ValueError, match=r"dt cannot be given beside it \(to time it by dt instead"):
        jaxatt.filter("madgwick", ImuSample(np.arange(n) * 0.01, g, a, m), dt=0.01)
    walk = broad.Trial(
        "walk", ImuSample(np.arange(n) * 0.01, g, a, m), np.tile([1.0, 0, 0, 0], (n, 1)), np.ones(n, bool), 100.0
    )
    for call in (lambda: jaxatt.broad_score("madgwick", None, [walk]), lambda: broad.check_trials([walk])):
        with pytest.raises(
            ValueError, match=r"trial walk: cannot tell the group .* give its group, Trial\(\.\.\., group="
        ):
            call()
    assert jaxatt.broad_score("madgwick", None, [walk._replace(group="mine")]).groups["mine"].n_trials == 1
    six = walk._replace(group="mine", samples=walk.samples._replace(mag=None))  # a 6-axis IMU, built by hand
    with pytest.raises(ValueError, match=r"got None \(a trial without a magnetometer has NaN rows: mag=np.full"):
        broad.check_trials([six])
