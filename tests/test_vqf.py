"""VQF (jaxatt.observers.vqf) against the ``vqf`` package's C++ filter ``vqf.VQF`` on every BROAD trial.

What is compared: the whole of every trial in the BROAD folder (20 trials, 47639-60861 samples each at 285.7 Hz,
1.09 M samples), default parameters, float64, jaxatt's first update made over the data's sampling time
(``ts0 = 1/rate``; the package's first ``update`` uses its Ts). Per sample: the quaternion (9D: ``getQuat9D``
vs the "vqf" observer's ``Out.q``; 6D: ``getQuat6D`` vs "vqf-6d"'s), the rest flag, the magnetic disturbance
flag (9D) and the gyro-bias estimate (``updateBatch``'s ``quat9D`` / ``quat6D`` / ``restDetected`` /
``magDistDetected`` / ``bias``, the per-sample values of ``getQuat*``, ``getRestDetected``,
``getMagDistDetected`` and ``getBiasEstimate``). Measured: largest angle of q_jax^-1 q_vqf over all samples
2.7e-12 rad (9D) and 2.2e-12 rad (6D); per-trial RMS <= 1e-12 rad; the flags agree on every sample; the bias
within 1e-14 rad/s. The trials run as one vmapped batch (zero-padded to the longest; a zero acc / mag sample is
skipped, as in the package, and nothing after a trial's end is compared), one compilation per mode.

The package is in the test extra (``pip install ".[test]"``): without it these tests skip, except under CI=true.
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxatt
from jaxatt import montecarlo
from jaxatt.data import broad
from jaxatt.observers import registry, vqf
from jaxatt.types import ImuSample

try:
    import vqf as vqf_package
except ImportError:  # the comparison needs the test extra (pip install ".[test]")
    if os.environ.get("CI", "").lower() == "true":
        raise
    vqf_package = pytest.importorskip("vqf")

from broad_data import DATA, need_data  # noqa: E402


def qangle(a, b):
    """Angle (rad) of a^-1 (x) b, accurate near 0 (atan2 of the vector part's norm and |w|)."""
    aw, av, bw, bv = a[..., 0], a[..., 1:], b[..., 0], b[..., 1:]
    w = aw * bw + np.sum(av * bv, -1)
    v = aw[..., None] * bv - bw[..., None] * av - np.cross(av, bv)
    return 2 * np.arctan2(np.linalg.norm(v, axis=-1), np.abs(w))


@pytest.fixture(scope="module")
def batch():
    """Every BROAD trial, zero-padded to the longest: (names, lengths, dt, ImuSample (B, L, ...))."""
    need_data()
    trials = broad.load(DATA)
    assert len(trials) == len(list(DATA.glob("*.hdf5"))) and len(trials) >= 20
    rates = {float(tr.rate_hz) for tr in trials}
    assert len(rates) == 1, rates
    dt = 1.0 / rates.pop()
    lens = [len(tr.samples.gyr) for tr in trials]
    n = max(lens)

    def pad(x):
        x = np.asarray(x, np.float64)
        return np.concatenate([x, np.zeros((n - len(x),) + x.shape[1:])])

    s = ImuSample(
        np.tile(np.arange(n) * dt, (len(trials), 1)),
        *(np.stack([pad(getattr(tr.samples, f)) for tr in trials]) for f in ("gyr", "acc", "mag")),
    )
    return [tr.name for tr in trials], lens, dt, s


def run_batch(mode, params, s, dt):
    run = montecarlo.log_runner(vqf.make_observer(mode), "next")
    return jax.vmap(run, in_axes=(None, 0, None))(params, s, dt)


def package_run(gyr, acc, mag, dt):
    f = vqf_package.VQF(dt)
    return f.updateBatch(*(None if x is None else np.ascontiguousarray(x) for x in (gyr, acc, mag)))


@pytest.mark.parametrize("mode", ["9d", "6d"])
def test_matches_vqf_package_on_every_broad_trial(batch, mode):
    names, lens, dt, s = batch
    p = vqf.default_params(ts0=dt)
    out = jax.tree_util.tree_map(np.asarray, run_batch(mode, p, s, dt))  # host arrays: slicing compiles nothing
    q = out.q
    assert q.dtype == np.float64
    worst = 0.0
    for i, (name, n) in enumerate(zip(names, lens)):
        ref = package_run(s.gyr[i, :n], s.acc[i, :n], s.mag[i, :n] if mode == "9d" else None, dt)
        qr = ref["quat9D"] if mode == "9d" else ref["quat6D"]
        a = qangle(q[i, :n], qr)
        rms = float(np.sqrt(np.mean(a**2)))
        worst = max(worst, float(a.max()))
        assert rms <= 1e-6 and a.max() <= 1e-6, (name, mode, rms, a.max())
        np.testing.assert_array_equal(np.asarray(out.rest_detected[i, :n]) > 0.5, ref["restDetected"], err_msg=name)
        assert 0.2 < ref["restDetected"].mean() < 0.6  # both states occur
        np.testing.assert_allclose(np.asarray(out.bias[i, :n]), ref["bias"], rtol=0, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(np.asarray(out.bias_sigma[i, :n]), ref["biasSigma"], rtol=1e-9, err_msg=name)
        if mode == "9d":
            np.testing.assert_array_equal(
                np.asarray(out.mag_dist_detected[i, :n]) > 0.5, ref["magDistDetected"], err_msg=name
            )
            np.testing.assert_allclose(np.asarray(out.q6d[i, :n]), ref["quat6D"], rtol=0, atol=1e-9, err_msg=name)
    assert worst < 1e-10, worst  # measured 2.7e-12 rad
    if mode == "9d":
        # The smooth relaxation (smooth > 0) tends to the exact filter: close at 1e-3, equal at 1e-7.
        for temp, bound in SMOOTH_BOUNDS:
            # the default's type (a weakly typed temperature would compile the 9D scan again)
            q_s = np.asarray(run_batch(mode, p._replace(smooth=jnp.asarray(temp, p.smooth.dtype)), s, dt).q)
            d = max(float(qangle(q_s[i, :n], q[i, :n]).max()) for i, n in enumerate(lens))
            print(f"smooth={temp}: max angle to the exact filter {d:.3g} rad")
            assert d <= bound, (temp, d)


#: (smooth temperature, bound on the largest angle (rad) between the smooth and the exact filter over all trials):
#: measured 0.0777 rad at 1e-3 (near-threshold decisions switch a sample later, the heading difference persists)
#: and 0 at 1e-7 (every decision saturated: the exact filter, bit for bit).
SMOOTH_BOUNDS = ((1e-3, 0.1), (1e-7, 1e-12))


def test_registry_entries_and_filter_frames(batch):
    names, lens, dt, s = batch
    for name, mode in (("vqf", "9d"), ("vqf-6d", "6d")):
        e = registry.get(name)
        assert e.module == "vqf" and e.frame == "ENU" and registry.hold_of(e) == "next" and e.setup is None
        assert registry.recorded_observer(name) is vqf.make_observer(mode)
        assert e.gain("tau_acc").tuned
    assert registry.get("vqf").gain("tau_mag").tuned and registry.get("vqf-6d").needs == ("acc",)
    # jaxatt.filter gives the package's sensor-to-ENU quaternion (the first 4000 samples of trial 0: padded to
    # 4001, the length of tests/test_front_door.py's 40-s log, so the two tests share one compiled 9D filter)
    n = 4000
    gyr, acc, mag = (np.asarray(x[0, :n]) for x in (s.gyr, s.acc, s.mag))
    est = jaxatt.filter("vqf", gyr, acc, mag, dt=dt, params=vqf.default_params(ts0=dt))
    assert est.frame == "ENU"
    ref = package_run(gyr, acc, mag, dt)
    assert qangle(np.asarray(est.quat), ref["quat9D"]).max() < 1e-10
    # ENU: the horizontal field points north (+y) after the estimate's rotation.
    m_enu = np.einsum("nij,nj->ni", np.asarray(jaxatt.so3.quat_to_matrix(jnp.asarray(est.quat))), mag)
    assert np.median(np.abs(np.arctan2(m_enu[n // 2 :, 0], m_enu[n // 2 :, 1]))) < 0.05


def test_check_params():
    vqf.check_params(vqf.default_params())
    for field, bad in (("tau_acc", 0.0), ("tau_mag", np.nan), ("rest_bias_est_enabled", 0.5), ("smooth", -1.0)):
        with pytest.raises(ValueError, match=field):
            vqf.check_params(vqf.default_params(**{field: bad}))
    with pytest.raises(ValueError, match="unknown"):
        vqf.default_params(tauAcc=1.0)
    assert set(vqf.PACKAGE_NAMES.values()) == set(vqf_package.VQF(0.01).params)
    assert {k: float(v) for k, v in vqf_package.VQF(0.01).params.items()} == {
        vqf.PACKAGE_NAMES[f]: float(getattr(vqf.default_params(), f)) for f in vqf.PACKAGE_NAMES
    }


def test_a_gap_in_the_timestamps_costs_the_gyro_integration_not_a_filter_transient():
    """A 1-s gap in a 100-Hz recording: each Butterworth low-pass restarts from its last output when the step
    jumps (vqf.GAP_RATIO; carrying its state over to the new coefficients instead gave 7.4 deg). Its state,
    driven through the 1-s step's coefficients and then the 0.01-s ones again, swung the inclination by ~30 deg
    for ~20 s. Now the error after the gap stays at the error before it plus what
    the gyro integrates across the gap, and a constant step is untouched (the BROAD tests above)."""
    from jaxatt import so3

    scn = jaxatt.api.ahrs_scenario(gyro_noise_std=1e-3, acc_noise_std=0.02, mag_noise_std=0.5, gyro_bias=(0, 0, 0))
    samples, truth = montecarlo.simulate_log(scn, duration=40.0, dt=0.01, seed=4)
    keep = np.ones(len(samples.t), bool)
    keep[2000:2100] = False  # 20.00 ... 20.99 s missing
    cut = ImuSample(*(np.asarray(a)[keep] for a in samples))
    est = jaxatt.filter("vqf", cut)
    err = np.rad2deg(np.asarray(so3.angle_error(jnp.asarray(np.asarray(truth.r)[keep]), jnp.asarray(est.rotation))))
    before, after = err[1500:2000].max(), err[2000:3900].max()
    assert after < before + 1.0, (before, after)


def test_timestamp_jitter_and_dropped_samples_cost_what_the_gyro_integration_does():
    """Recordings whose steps vary: each step's low-pass coefficients differ from the last one's, and the state is
    carried over to them (a restart at every change of more than 50 % took the error to 20-24 deg here). With the
    timestamps jittered by +-2 ms at 100 Hz, or a fifth of the samples dropped, the error after the first 20 s
    stays within 0.3 deg of the regular recording's (measured 2.74 deg regular, 2.80 with either)."""
    from jaxatt import so3

    # 75 s simulated: the log with samples dropped keeps its first 6001, as many as the others (one program)
    samples, truth = montecarlo.simulate_log(jaxatt.api.ahrs_scenario(), duration=75.0, dt=0.01, seed=3)
    t, g, a, m = (np.asarray(x) for x in samples)
    r_true = np.asarray(truth.r)
    n = 6001

    def rms_after_20s(keep, times):
        est = jaxatt.filter("vqf", g[keep], a[keep], m[keep], t=times)
        err = np.rad2deg(np.asarray(so3.angle_error(jnp.asarray(r_true[keep]), jnp.asarray(est.rotation))))
        return float(np.sqrt(np.mean(err[np.searchsorted(times, 20.0) :] ** 2)))

    rng = np.random.default_rng(0)
    first = np.arange(len(t)) < n
    regular = rms_after_20s(first, t[:n])
    jittered = rms_after_20s(first, t[:n] + rng.uniform(-0.002, 0.002, n))
    kept = rng.random(len(t)) >= 0.2
    kept[0] = True
    kept &= np.cumsum(kept) <= n
    dropped = rms_after_20s(kept, t[kept])
    assert jittered < regular + 0.3 and dropped < regular + 0.3, (regular, jittered, dropped)


def test_the_front_door_starts_vqf_over_the_recordings_first_step():
    """``jaxatt.filter("vqf", ...)`` on a 50-Hz recording equals the package's ``VQF(0.02).updateBatch`` from the
    first sample: the front door sets ``ts0`` to the first step (Entry.first_step). With the default ts0 = 0.01 s
    the two were up to 1.7e-4 rad apart; a ts0 the caller names is kept."""
    samples, _ = montecarlo.simulate_log(jaxatt.api.ahrs_scenario(), duration=20.0, dt=0.02, seed=5)
    g, a, m = (np.ascontiguousarray(np.asarray(x, np.float64)) for x in (samples.gyr, samples.acc, samples.mag))
    ref = package_run(g, a, m, 0.02)["quat9D"]
    est = jaxatt.filter("vqf", g, a, m, dt=0.02)
    assert float(est.params.ts0) == 0.02
    assert qangle(est.quat, ref).max() < 1e-9
    kept = jaxatt.filter("vqf", g, a, m, dt=0.02, params={"ts0": 0.01})
    assert float(kept.params.ts0) == 0.01 and qangle(kept.quat, ref).max() > 1e-6
    # broad_score and fit (one params for a batch of trials) take the median of the trials' first steps
    e = jaxatt.observers.registry.get("vqf")
    trial = jaxatt.data.broad.Trial("t", samples, np.zeros((len(g), 4)), np.ones(len(g), bool), 50.0)
    at_100 = trial._replace(samples=samples._replace(t=np.asarray(samples.t) / 2))
    with pytest.warns(UserWarning, match=r"vqf: the trials' sampling steps \(s\) differ widely"):
        p = jaxatt.api.recording_defaults_for_trials(e, None, e.default_params(), [trial, trial, at_100])
    assert float(p.ts0) == pytest.approx(0.02, rel=1e-12)
    p = jaxatt.api.recording_defaults_for_trials(e, {"ts0": 0.01}, e.default_params(), [trial])
    assert float(p.ts0) == 0.01


def test_a_slower_magnetometer_or_accelerometer_matches_the_package_run_at_its_rate():
    """Readings at 1/n of the gyro rate (NaN rows between) against the package set up for them, ``VQF(gyrTs,
    accTs, magTs)`` with ``updateGyr`` every sample and ``updateAcc`` / ``updateMag`` at the readings: a reading
    is processed over the time since the last one. Magnetometer at 1/4: equal to rounding (measured 1.0e-13 rad;
    taken over one gyro step, as before, 0.043 rad apart). Accelerometer at 1/2 as well: within 1e-3 rad
    (measured 2.9e-4; before, 0.061), because the first reading, at the start, is processed over ts0 = the gyro's
    step and the package's over accTs."""
    scn = jaxatt.api.ahrs_scenario()
    samples, _ = montecarlo.simulate_log(scn, duration=60.0, dt=0.01, seed=3)
    g, a, m = (np.ascontiguousarray(np.asarray(x, np.float64)) for x in (samples.gyr, samples.acc, samples.mag))
    dt = 0.01
    run = montecarlo.log_runner(vqf.make_observer("9d"), "next")
    k = np.arange(len(g))
    for every_acc, every_mag, bound in ((1, 4, 1e-10), (2, 4, 1e-3)):
        f = vqf_package.VQF(dt, every_acc * dt, every_mag * dt)
        q_ref = []
        for i in range(len(g)):
            f.updateGyr(g[i])
            if i % every_acc == 0:
                f.updateAcc(a[i])
            if i % every_mag == 0:
                f.updateMag(m[i])
            q_ref.append(f.getQuat9D())
        acc = np.where((k % every_acc == 0)[:, None], a, np.nan)
        mag = np.where((k % every_mag == 0)[:, None], m, np.nan)
        out = run(vqf.default_params(ts0=dt), ImuSample(np.asarray(samples.t), g, acc, mag), dt)
        worst = float(qangle(np.asarray(out.q), np.array(q_ref)).max())
        assert worst < bound, (every_acc, every_mag, worst)
