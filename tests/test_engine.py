"""The one scan (jaxatt.engine): T estimates for T samples with estimate 0 from init, the three holds, per-step
dt from timestamps, estimate 0 of an observer without ``output``, records decimated from estimate 0, and
checkpointed segments giving the same result as the plain scan. Checked against hand-written loops."""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxatt
from jaxatt import engine, montecarlo
from jaxatt.types import ImuSample, Interval, Observer


class P(NamedTuple):
    gain: jnp.ndarray


class S(NamedTuple):
    t: jnp.ndarray
    x: jnp.ndarray  # an integrator of the gyro's first component, with a decay


class O(NamedTuple):
    t: jnp.ndarray
    x: jnp.ndarray
    seen: jnp.ndarray  # the sample time the step used


def _init(p, s):
    return S(jnp.asarray(s.t), jnp.asarray(s.gyr[0]))


def _step(p, st, u, dt):
    if isinstance(u, Interval):
        g, seen = 0.5 * (u.start.gyr[0] + u.end.gyr[0]), u.start.t
    else:
        g, seen = u.gyr[0], u.t
    x = st.x + dt * (g - p.gain * st.x)
    return S(st.t + dt, x), O(st.t + dt, x, seen)


TOY = Observer(_init, _step, "toy")


def log(n=7, irregular=False):
    t = np.cumsum(np.r_[0.0, np.linspace(0.1, 0.3, n - 1)]) if irregular else np.arange(n) * 0.1
    gyr = np.stack([np.sin(np.arange(n)), np.zeros(n), np.zeros(n)], 1)
    return ImuSample(jnp.asarray(t), jnp.asarray(gyr))


def reference(samples, gain, hold):
    """The alignment written out: estimate 0 = init; estimate k = one step over [t_{k-1}, t_k]."""
    t, g = np.asarray(samples.t), np.asarray(samples.gyr)[:, 0]
    x = [g[0]]
    for k in range(1, len(t)):
        dt = t[k] - t[k - 1]
        u = {"zoh": g[k - 1], "next": g[k], "linear": 0.5 * (g[k - 1] + g[k])}[hold]
        x.append(x[-1] + dt * (u - gain * x[-1]))
    return np.asarray(x)


def _x_of(t, truth, out):
    return out.x


@pytest.mark.parametrize("hold", ["zoh", "next", "linear"])
@pytest.mark.parametrize("irregular", [False, True])
def test_t_estimates_for_t_samples_with_each_hold(hold, irregular):
    s = log(irregular=irregular)
    out = montecarlo.run(TOY, P(jnp.asarray(0.7)), s, hold=hold)
    assert out.x.shape == (7,)
    np.testing.assert_allclose(np.asarray(out.x), reference(s, 0.7, hold), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(out.t), np.asarray(s.t), atol=1e-12)
    # which sample each step used: k-1 (zoh, linear: interval start) or k (next)
    seen = np.asarray(out.seen)[1:]
    want = np.asarray(s.t)[1:] if hold == "next" else np.asarray(s.t)[:-1]
    np.testing.assert_allclose(seen, want, atol=1e-12)


@pytest.mark.parametrize("hold", ["zoh", "next", "linear"])
def test_a_log_longer_than_a_block_is_scanned_in_whole_blocks(hold):
    """montecarlo.run / log_runner scan a log of more than one block to the end of its last block
    (engine.whole_blocks: the compiled scan then holds one copy of the step) and return the log's own T estimates:
    those of the written-out loop, with irregular steps; the gradient in the gain equals central differences of
    the loop (the dropped estimates contribute nothing)."""
    b = engine.BLOCK
    assert [engine.whole_blocks(m) for m in (10, b, b + 1, 3 * b)] == [10, b, 2 * b, 3 * b]
    n = engine.BLOCK + 501
    s = log(n, irregular=True)
    out = montecarlo.run(TOY, P(jnp.asarray(0.7)), s, hold=hold)
    assert out.x.shape == (n,) and out.t.shape == (n,)
    np.testing.assert_allclose(np.asarray(out.x), reference(s, 0.7, hold), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(out.t), np.asarray(s.t), rtol=1e-12)
    run = montecarlo.log_runner(TOY, hold)
    g = jax.grad(lambda k: jnp.sum(run(P(k), s, jnp.diff(s.t)).x))(jnp.asarray(0.7))
    h = 1e-6
    fd = (reference(s, 0.7 + h, hold).sum() - reference(s, 0.7 - h, hold).sum()) / (2 * h)
    assert abs(float(g) - fd) <= 1e-6 * abs(fd), (float(g), fd)


def test_estimate_0_without_output_comes_from_the_state():
    """No ``output``: fields of the step's output that the state holds (t, x) are taken from it, the others are
    NaN until estimate 1."""
    s = log()
    out = montecarlo.run(TOY, P(jnp.asarray(0.7)), s)
    assert float(out.x[0]) == pytest.approx(float(s.gyr[0, 0]))
    assert float(out.t[0]) == 0.0 and np.isnan(float(out.seen[0]))
    with_output = TOY._replace(output=lambda p, st: O(st.t, st.x, st.t))
    out2 = montecarlo.run(with_output, P(jnp.asarray(0.7)), s)
    assert float(out2.seen[0]) == 0.0
    np.testing.assert_array_equal(np.asarray(out2.x), np.asarray(out.x))


def test_records_start_at_estimate_0_and_segments_change_nothing():
    """A recorded batch of two logs of different constant steps: records every 2nd estimate from estimate 0; a
    checkpointed scan (segments of 4 steps, with per-step remat) gives the same records and the same gradient."""
    n = 13
    s = log(n)
    items = {
        "samples": jax.tree_util.tree_map(lambda a: jnp.stack([a, a[::-1] if a.ndim == 1 else a]), s),
        "dt": jnp.asarray([0.1, 0.05]),
        "truth": None,
    }
    items["samples"] = items["samples"]._replace(t=jnp.stack([s.t, s.t]))
    pick = engine.records_of(_x_of, 2)
    plain = engine.batch_fn(TOY, engine.Recorded(n - 1), pick, hold="zoh")
    seg = engine.batch_fn(TOY, engine.Recorded(n - 1), pick, hold="zoh", segment=4, step_remat=True)
    p = P(jnp.asarray(0.4))
    r1 = plain(None, p, items).records
    r2 = seg(None, p, items).records
    assert r1.shape == (2, 1 + (n - 1) // 2)
    full0 = reference(s, 0.4, "zoh")
    np.testing.assert_allclose(np.asarray(r1[0]), full0[::2], rtol=1e-13)
    np.testing.assert_allclose(np.asarray(r2), np.asarray(r1), rtol=1e-14)
    f1 = jax.grad(lambda q: jnp.sum(plain(None, q, items).records ** 2))(p)
    f2 = jax.grad(lambda q: jnp.sum(seg(None, q, items).records ** 2))(p)
    assert float(f2.gain) == pytest.approx(float(f1.gain), rel=1e-12) and float(f1.gain) != 0.0


def test_bad_hold_and_record_interval_are_refused():
    with pytest.raises(ValueError, match="hold"):
        engine.check_hold("foh")
    with pytest.raises(ValueError, match="record interval"):
        engine.batch_fn(TOY, engine.Recorded(10), engine.records_of(lambda t, tr, o: o.x, 7))
    with pytest.raises(ValueError, match="checkpoint"):
        engine.segment_length(100, 300)


def test_estimate_r_and_q_read_either_field():
    from jaxatt import so3

    q = so3.quat_canonical(jnp.asarray([0.9, 0.1, -0.3, 0.2]) / jnp.linalg.norm(jnp.asarray([0.9, 0.1, -0.3, 0.2])))
    r = so3.quat_to_matrix(q)
    np.testing.assert_allclose(np.asarray(engine.estimate_r({"q": q})), np.asarray(r), atol=1e-15)
    np.testing.assert_allclose(np.asarray(engine.estimate_q({"r": r})), np.asarray(q), atol=1e-14)
    with pytest.raises(ValueError, match="neither a field"):
        engine.estimate_q({"x": 1.0})


def test_jit_shared_compiles_a_program_once_for_new_closures_of_it():
    """Two closures built the same way lower to the same program: the second is not compiled again and gives the
    same numbers; a different captured constant is a different program and is compiled."""

    def make(scale):
        c = jnp.asarray(scale)
        return lambda x: jnp.sum(jnp.sin(x) * c)

    x = jnp.linspace(0.0, 1.0, 7)
    before = dict(engine.program_cache_stats)
    a = engine.jit_shared(make(1.2345))(x)
    b = engine.jit_shared(make(1.2345))(x)
    after_same = dict(engine.program_cache_stats)
    c = engine.jit_shared(make(2.5))(x)
    after_other = dict(engine.program_cache_stats)
    assert after_same["compiled"] - before["compiled"] == 1 and after_same["reused"] - before["reused"] == 1
    assert after_other["compiled"] - after_same["compiled"] == 1
    assert float(a) == float(b) == pytest.approx(float(jnp.sum(jnp.sin(x)) * 1.2345), rel=1e-6)
    assert float(c) == pytest.approx(float(jnp.sum(jnp.sin(x)) * 2.5), rel=1e-6)


def test_microbatch_groups_give_the_same_runs_records_states_and_gradient():
    """A batch of 7 recorded runs split into groups of about 2 (4 groups of 2, one padding run dropped) gives
    every run's records, final state and summary of the unsplit batch exactly, and the same gradient."""
    n = 9
    s = log(n)
    gains = jnp.linspace(0.5, 1.1, 7)
    items = {
        "samples": jax.tree_util.tree_map(lambda a: jnp.stack([a * (1.0 + 0.1 * i) for i in range(7)]), s),
        "dt": jnp.full((7,), 0.1),
        "truth": None,
    }
    items["samples"] = items["samples"]._replace(t=jnp.stack([s.t] * 7))

    def init(t, truth, out):
        return out.x**2, out.x

    reducer = engine.Reducer(init, lambda acc, t, truth, out: (acc + out.x**2, out.x), lambda acc: {"ss": acc}, 1)
    kw = dict(hold="zoh", keep_state=True)
    whole = engine.batch_fn(TOY, engine.Recorded(n - 1), reducer, microbatch=0, **kw)
    split = engine.batch_fn(TOY, engine.Recorded(n - 1), reducer, microbatch=2, **kw)
    p = P(jnp.asarray(0.4))
    a, b = whole(None, p, items), split(None, p, items)
    assert a.records.shape == b.records.shape == (7, n) and b.summary["ss"].shape == (7,)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    ref = np.asarray(reference(jax.tree_util.tree_map(lambda v: v[3], items["samples"]), 0.4, "zoh"))
    np.testing.assert_allclose(np.asarray(b.records[3]), ref, rtol=1e-13)
    ga = jax.grad(lambda q: jnp.sum(whole(None, q, items).summary["ss"] * gains))(p)
    gb = jax.grad(lambda q: jnp.sum(split(None, q, items).summary["ss"] * gains))(p)
    assert float(gb.gain) == pytest.approx(float(ga.gain), rel=1e-13) and float(ga.gain) != 0.0
    assert engine.default_microbatch() == (engine.CPU_MICROBATCH if jax.default_backend() == "cpu" else 0)


def test_a_grid_of_gains_is_one_vmap_of_metrics_fn_and_equals_monte_carlo_per_gain():
    """montecarlo.metrics_fn is monte_carlo's program as a pure function: vmapped over a grid of gains (every gain
    on the same runs) it gives, per gain, the per-run metrics of monte_carlo with that gain."""
    from jaxatt import montecarlo, studies

    s = studies.get("complementary").setup(duration=2.0)
    kw = dict(duration=2.0, dt=s.dt, errors_fn=s.errors_fn)
    fn = montecarlo.metrics_fn(s.observer, **kw)
    gains = jnp.asarray([0.1, 0.3, 1.0])
    grid = jax.vmap(lambda k_i: s.params._replace(k_i=k_i))(gains)
    got = jax.jit(jax.vmap(fn, in_axes=(None, 0, None)))(s.scenario, grid, montecarlo.run_keys(3, range(2)))
    for i, k_i in enumerate(gains):
        one = montecarlo.monte_carlo(s.scenario, s.observer, s.params._replace(k_i=k_i), runs=2, seed=3, **kw)
        for k, v in one.per_run.items():
            np.testing.assert_allclose(got[k][i], v, rtol=1e-12, atol=1e-14, err_msg=k)
    assert not np.allclose(got["mean_angle_error_deg"][0], got["mean_angle_error_deg"][2])  # the gain matters


def test_running_stats_are_numpys_mean_and_std_and_a_single_sample_has_std_0():
    """metrics.stats_update (Welford, weights 0 / 1) gives numpy's mean and population std of the weighted-in
    values; one sample gives a std of exactly 0. A Monte Carlo window of one estimate gave NaN (float64) or
    1e-5 deg (float32) with runs=1 and 0 with runs=3: XLA rounded two reads of the same error differently and
    m2 went negative."""
    from jaxatt import metrics

    rng = np.random.default_rng(0)
    x = rng.normal(size=(500, 3)) * 10.0 + 3.0
    w = (rng.random(500) < 0.7).astype(float)
    s = metrics.stats_init((3,), jnp.float64)
    for xi, wi in zip(x, w):
        s = metrics.stats_update(s, jnp.asarray(xi), jnp.asarray(wi))
    np.testing.assert_allclose(np.asarray(s.mean), x[w > 0].mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(metrics.stats_std(s)), x[w > 0].std(axis=0), rtol=1e-10)
    res = jaxatt.monte_carlo("madgwick", None, runs=1, duration=0.02, dtype=jnp.float32)
    stds = {k: v for k, v in res.per_run.items() if k.startswith("std_")}
    assert stds and all(float(np.asarray(v)[0]) == 0.0 for v in stds.values()), stds
