"""Differentiable tuning on simulated seeds (jaxatt.fit): the loss reproduces monte_carlo's runs, gradients
through the whole simulation match central finite differences (with and without checkpointing), stay finite
across gain switches and the Theorem-3 projection, and tuning from a poor gain lowers the loss on held-out seeds.

Cost control: every gradient here goes through the cached jitted loss of :func:`jaxatt.fitting.losses.make_loss_fn`
with the same static settings per observer, so each (observer, checkpoint) pair compiles once for the
whole module (three gradient programs, two forward programs); params (switch times, initial estimate, gains)
change freely without compiling again.
"""

import json
import math
import re
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxatt import montecarlo, so3, studies
from jaxatt.fitting import fitter, gainsfile
from jaxatt.fitting import losses as L
from jaxatt.fitting import parametrize as P
from jaxatt.observers import registry

DURATION = 6.0  # s at 100 Hz: 600 steps
CKPT = 100  # steps per checkpointed segment (6 segments)
KEYS = montecarlo.run_keys(0, [0, 1])
R40 = np.asarray(so3.exp(jnp.deg2rad(40.0) * jnp.asarray([1.0, 2.0, 2.0]) / 3.0))


class Problem(NamedTuple):
    setup: Any
    spec: Any
    loss_fn: Any
    checkpoint_segment: int


def problem(name, checkpoint=CKPT, duration=DURATION):
    """A study's tuned observer with its loss windows, the loss compiled once per (observer, checkpoint)."""
    s = studies.get(name).setup(duration=duration)
    (ss, se), (ts, te) = s.loss_windows["steady"], s.loss_windows["transient"]
    spec = L.loss_spec(s.loss_kind, steady_start=ss, steady_end=se, transient_start=ts, transient_end=te)
    f = L.make_loss_fn(
        s.observer,
        duration=s.duration,
        dt=s.dt,
        spec=spec,
        hold=s.hold,
        checkpoint=checkpoint,
        init_params=s.init_params,
    )
    return Problem(s, spec, f, L.segment_length(int(round(s.duration / s.dt)), checkpoint))


def gains_of(name):
    """The tunable gains the registry declares for a study's tuned observer."""
    return P.for_gains(registry.get(studies.get(name).entry).gains)


def ges_params(base, **kw):
    """batista-ges params with every Table-1 switch inside the 6-s horizon and a 40-degree initial error."""
    p = base._replace(switch_times=jnp.asarray([1.0, 2.0, 3.0, 4.0, 5.0, 5.5]), r_hat_0=jnp.asarray(R40))
    return p._replace(**{k: jnp.asarray(v) for k, v in kw.items()})


def so3_params(base):
    return base._replace(switch_times=jnp.asarray([1.5, 3.0, 4.5, 5.5]), r_hat_0=jnp.asarray(R40))


def value_and_grad(prob, bound, theta=None, keys=KEYS):
    """(loss, grads, aux) through the eagerly differentiated cached jitted loss (compiled once per problem)."""

    def obj(th):
        return prob.loss_fn(prob.setup.scenario, bound.constrain(th), keys)

    (loss, aux), g = jax.value_and_grad(obj, has_aux=True)(bound.init() if theta is None else theta)
    return float(loss), g, aux


def fd_check(prob, bound, grads, directions, h=1e-5):
    """Central finite differences of the loss along ``directions`` against grads . direction."""
    th0 = bound.init()

    def loss_at(th):  # the value of the same compiled value-and-grad program: no extra compile
        return value_and_grad(prob, bound, th)[0]

    errs = []
    for v in directions:
        ad = sum(float(jnp.vdot(grads[k], v[k])) for k in grads)
        fp = loss_at({k: th0[k] + h * v[k] for k in th0})
        fm = loss_at({k: th0[k] - h * v[k] for k in th0})
        fd = (fp - fm) / (2 * h)
        errs.append(abs(ad - fd) / max(abs(fd), 1e-300))
    return errs


def random_directions(theta, n, seed=0):
    rng = np.random.default_rng(seed)
    return [{k: jnp.asarray(rng.normal(size=np.shape(a))) for k, a in theta.items()} for _ in range(n)]


def unit_direction(theta, field, index):
    v = {k: jnp.zeros_like(a) for k, a in theta.items()}
    v[field] = v[field].at[index].set(1.0)
    return v


@pytest.fixture(scope="module")
def ges():
    prob = problem("batista-ges")
    bound = gains_of("batista-ges").bind(ges_params(prob.setup.params))
    loss, g, aux = value_and_grad(prob, bound)
    return prob, bound, loss, g, aux


def test_segment_length():
    assert L.segment_length(360_000) == 1000  # 360 stored carries + 1000 recomputed steps
    assert L.segment_length(4_000_000) == 2000
    assert L.segment_length(600) == 1000  # one block: a short horizon needs no finer segments
    assert L.segment_length(600, False) == 0 and L.segment_length(600, None) == 0
    assert L.segment_length(600, 200) == 200 and L.segment_length(10_000, 3000) == 3000
    with pytest.raises(ValueError):
        L.segment_length(600, 300)
    with pytest.raises(ValueError):
        L.segment_length(600, "sqrt")


def test_loss_spec_windows():
    spec = L.loss_spec("angle", steady_start=10.0, transient_end=5.0, w_transient=0.5)
    assert spec.windows == (("steady", 10.0, math.inf, 1.0), ("transient", 0.0, 5.0, 0.5))
    with pytest.raises(ValueError):
        L.loss_spec("nope")
    with pytest.raises(ValueError):
        L.loss_spec("angle", steady_start=3.0, steady_end=2.0)


def test_same_runs_as_monte_carlo(ges):
    """The loss's simulation is monte_carlo's: per-run mean angle error over the steady window agrees to
    rounding, and so does the final angle."""
    prob, bound, _, _, aux = ges  # aux of the value-and-grad program
    s = prob.setup
    params = bound.base
    res = montecarlo.monte_carlo(
        s.scenario,
        s.observer,
        params,
        runs=2,
        duration=s.duration,
        dt=s.dt,
        seed=0,
        errors_fn=s.errors_fn,
        window_start=s.window_start,
        hold=s.hold,
    )
    np.testing.assert_allclose(np.asarray(aux["window_angle_deg"][0]), res.per_run["mean_angle_error_deg"], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(aux["final_angle_deg"]), res.per_run["final_angle_error_deg"], rtol=1e-12)
    assert int(aux["window_count"][0]) == round((s.duration - s.window_start) / s.dt) + 1  # both ends


def test_ges_gradient_matches_finite_differences_across_switches(ges):
    prob, bound, loss, g, _ = ges
    assert math.isfinite(loss) and loss > 0
    for k, v in g.items():
        assert np.all(np.isfinite(np.asarray(v))), k
    # every Table-1 interval lies inside the horizon: each one's gain has a (finite, non-zero) gradient
    assert np.all(np.abs(np.asarray(g["alpha1"])) > 0) and np.all(np.abs(np.asarray(g["alpha2"])) > 0)
    th0 = bound.init()
    dirs = random_directions(th0, 1) + [unit_direction(th0, "alpha2", 5), unit_direction(th0, "gain_z", 0)]
    errs = fd_check(prob, bound, g, dirs)
    assert max(errs) < 1e-4, errs


def test_refined_schedule_same_loss_and_split_gradients_sum(ges):
    """Splitting Table-1 intervals (jaxatt.schedule.refine) changes nothing in the simulation, and
    the gradient with respect to the log-gain of a split interval is the sum of its parts' gradients (chain
    rule): two independent computations of the same derivative."""
    prob, bound, loss, g, _ = ges
    refined = P.refine_schedule(bound.base, [2.5, 4.5, 5.8], ["alpha1", "alpha2"])  # splits intervals 2, 4, 6
    rbound = gains_of("batista-ges").bind(refined)
    rloss, rg, _ = value_and_grad(prob, rbound)
    assert rloss == pytest.approx(loss, rel=1e-12)
    groups = [[0], [1], [2, 3], [4], [5, 6], [7], [8, 9]]  # refined interval indices of each old interval
    for field in ("alpha1", "alpha2"):
        summed = np.array([np.asarray(rg[field])[ix].sum() for ix in groups])
        np.testing.assert_allclose(summed, np.asarray(g[field]), rtol=1e-8, atol=1e-12 * np.abs(g[field]).max())
    np.testing.assert_allclose(np.asarray(rg["gain_z"]), np.asarray(g["gain_z"]), rtol=1e-8, atol=1e-14)


def test_checkpointing_gives_the_same_gradient(ges):
    prob, bound, loss, g, _ = ges
    plain = problem("batista-ges", checkpoint=False)
    assert plain.checkpoint_segment == 0 and prob.checkpoint_segment == CKPT
    loss2, g2, _ = value_and_grad(plain, bound)
    assert loss2 == pytest.approx(loss, rel=1e-13)
    for k in g:
        np.testing.assert_allclose(
            np.asarray(g2[k]), np.asarray(g[k]), rtol=1e-9, atol=1e-12 * float(jnp.max(jnp.abs(g[k])))
        )
    errs = fd_check(plain, bound, g2, random_directions(bound.init(), 1, seed=1))
    assert max(errs) < 1e-4, errs


def test_gradient_finite_through_theorem3_projection_switch(ges):
    """With G = 10 x the paper's, R^ (starting at the rotation R40, inside the projection region) is pulled
    towards the still unconverged measurement and leaves the region after about 0.7 s: R is the Newton polar
    projection of R^ until then, and R_f propagated from the last projection afterwards. The loss window
    (4-6 s) sees only the propagated R_f, whose gradient flows back through the projection; it stays finite.
    (The FD test runs the all-projected case: there ||R^T R^ - I||_F stays below 0.45.)"""
    prob, _, _, _, _ = ges
    base = ges_params(prob.setup.params, gain_z=10.0 * np.asarray(prob.setup.params.gain_z))
    bound = gains_of("batista-ges").bind(base)
    loss, g, aux = value_and_grad(prob, bound)
    eps = float(base.epsilon)
    assert float(so3.orthogonality_error(base.r_hat_0)) < eps  # projected at the start
    r_end = np.asarray(aux["final_state"].r_hat)
    assert all(float(so3.orthogonality_error(jnp.asarray(r))) > eps for r in r_end)  # propagated at the end
    assert math.isfinite(loss)
    for k, v in g.items():
        assert np.all(np.isfinite(np.asarray(v))), k
    assert float(jnp.linalg.norm(g["gain_z"])) > 0


@pytest.fixture(scope="module")
def so3_problem():
    return problem("batista-so3")


def test_so3_gradient_matches_finite_differences(so3_problem):
    prob = so3_problem
    bound = gains_of("batista-so3").bind(so3_params(prob.setup.params))
    loss, g, _ = value_and_grad(prob, bound)
    assert math.isfinite(loss)
    for k, v in g.items():
        assert np.all(np.isfinite(np.asarray(v))), k
    th0 = bound.init()
    dirs = random_directions(th0, 1, seed=2) + [unit_direction(th0, "alpha3", ()), unit_direction(th0, "alpha1", 4)]
    errs = fd_check(prob, bound, g, dirs)
    assert max(errs) < 1e-4, errs


def test_tuning_from_a_poor_gain_lowers_held_out_loss(so3_problem, tmp_path):
    """batista-so3 from alpha3 |I_m|^2 = 0.002 1/s (10 x below the paper's; alpha4 at 1 % so that the
    still unconverged v^ does not steer the attitude): 8 Adam steps on 2 training runs lower the loss of 2
    other seeds; the gains file is rewritten as the loop goes and loads back into the Params; an interrupted
    run keeps the best gains found so far. The other gains are frozen by masks; the three fits build the same
    objective program, so the later ones reuse it."""
    prob = so3_problem
    poor = lambda p: so3_params(p)._replace(alpha3=0.1 * p.alpha3, alpha4=0.01 * p.alpha4)  # noqa: E731
    frozen = {"alpha0": False, "alpha1": False, "alpha2": False, "alpha4": False}
    out = tmp_path / "gains.json"
    lines = []
    kw = dict(
        train_runs=2,
        batch=2,
        val_runs=2,
        lr=0.8,
        config={"duration": DURATION},
        start=poor,
        checkpoint=CKPT,
        masks=frozen,
        quiet=True,
    )
    res = fitter.fit(
        None, None, "batista-so3", steps=8, out=str(out), val_every=2, patience=None, callback=lines.append, **kw
    )
    assert res.status == "done" and len(lines) == 8
    assert float(res.params.alpha3) > 10 * float(res.start_params.alpha3)
    for f in ("alpha0", "alpha1", "alpha2", "alpha4"):  # frozen
        np.testing.assert_array_equal(np.asarray(getattr(res.params, f)), np.asarray(getattr(res.start_params, f)))
    held_out = montecarlo.run_keys(1, [0, 1])
    start_loss = float(prob.loss_fn(prob.setup.scenario, res.start_params, held_out)[0])
    tuned_loss = float(prob.loss_fn(prob.setup.scenario, res.params, held_out)[0])
    assert tuned_loss < 0.75 * start_loss, (start_loss, tuned_loss)
    assert res.best_loss < res.start_loss
    # the gains file: human-readable, loads back into the observer's Params
    payload = json.loads(out.read_text())
    assert payload["format"] == gainsfile.FORMAT and payload["status"] == "done"
    assert payload["observer"] == "batista-so3" and payload["study"] == "batista-so3"
    assert payload["gains"]["alpha2"]["unit"] == "1/s" and len(payload["history"]) == 9
    assert payload["gains"]["alpha1"]["switch_times_s"] == [1.5, 3.0, 4.5, 5.5]
    assert payload["settings"]["n_tunable"] == 1
    assert payload["gains"]["alpha3"]["as_rate"]["label"] == "alpha3 |I_m|^2 (1/s)"
    loaded = gainsfile.read_params(str(out), "batista-so3", base=prob.setup.params)
    for f in ("alpha0", "alpha1", "alpha2", "alpha3", "alpha4", "switch_times"):
        np.testing.assert_allclose(np.asarray(getattr(loaded, f)), np.asarray(getattr(res.params, f)), rtol=1e-12)

    # interrupted at step 3: the file holds the best gains found so far and says so
    def stop(info):
        if info["step"] == 3:
            raise KeyboardInterrupt

    out2 = tmp_path / "interrupted.json"
    res2 = fitter.fit(
        None, None, "batista-so3", steps=8, out=str(out2), val_every=2, patience=None, callback=stop, **kw
    )
    assert res2.status == "interrupted"
    p2 = json.loads(out2.read_text())
    assert p2["status"] == "interrupted" and p2["best_step"] == res2.best_step == 2
    assert p2["best_loss"] < p2["start_loss"]
    # resumed from the file, it ends where the uninterrupted run above ends, to rounding
    res3 = fitter.fit(None, None, "batista-so3", steps=8, out=str(out2), val_every=2, patience=None, resume=True, **kw)
    assert res3.status == "done" and res3.best_step == res.best_step
    np.testing.assert_allclose(float(res3.params.alpha3), float(res.params.alpha3), rtol=1e-12)
    vals = lambda r: [(h["step"], h["val_loss"]) for h in r.history if h.get("val_loss") is not None]  # noqa: E731
    assert [s for s, _ in vals(res3)] == [s for s, _ in vals(res)] == [0, 2, 4, 6, 8]
    np.testing.assert_allclose([v for _, v in vals(res3)], [v for _, v in vals(res)], rtol=1e-12)


def test_evaluate_writes_the_reproduce_metrics_layout(ges, tmp_path, capsys):
    """evaluate(): monte_carlo with the gains of a gains file; JSON metrics.<name>.mean/std/min/max/per_run as
    `jaxatt reproduce`, plus the paper gains on the same runs. (Reuses the runner compiled above.)"""
    prob, _, _, _, _ = ges
    p = prob.setup.params
    gains = tmp_path / "g.json"
    decl = registry.get("batista-ges").gains
    gainsfile.write(
        str(gains), observer="batista-ges", study="batista-ges", params=p._replace(alpha2=0.5 * p.alpha2), gains=decl
    )
    study = studies.get("batista-ges")
    tuned = gainsfile.read_params(str(gains), "batista-ges", base=p)
    out = tmp_path / "eval.json"
    payload = studies.evaluate(
        study,
        tuned,
        runs=2,
        seed=0,
        json_path=str(out),
        cfg=study.config(duration=DURATION),
        gains_source=str(gains),
        quiet=True,
    )
    saved = json.loads(out.read_text())
    assert saved["complete"] and saved["runs_done"] == 2 and saved["gains_path"] == str(gains)
    m = saved["metrics"]["mean_angle_error_deg"]
    assert set(m) == {"mean", "std", "min", "max", "per_run"} and len(m["per_run"]) == 2
    res = montecarlo.monte_carlo(
        prob.setup.scenario,
        prob.setup.observer,
        p._replace(alpha2=0.5 * p.alpha2),
        runs=2,
        duration=DURATION,
        dt=0.01,
        seed=0,
        errors_fn=prob.setup.errors_fn,
        window_start=prob.setup.window_start,
    )
    np.testing.assert_allclose(m["per_run"], res.per_run["mean_angle_error_deg"], rtol=1e-12)
    c = saved["comparison"]["mean_angle_error_deg"]
    assert c["ratio"] == pytest.approx(c["tuned"] / c["paper_gains"])
    assert saved["gains"]["alpha2"]["value"] == pytest.approx(list(0.5 * np.asarray(p.alpha2)))
    assert payload["metrics"]["mean_angle_error_deg"]["mean"] == pytest.approx(m["mean"])
    printed = capsys.readouterr().out
    assert "mean_angle_error_deg" in printed and printed.count(f"results written to {out}") == 1  # with the comparison


def test_evaluate_interrupted_in_the_paper_comparison_is_incomplete_and_resumes(ges, tmp_path, monkeypatch):
    """Ctrl-C while the paper's gains run (evaluate's second Monte Carlo) leaves ``complete: false`` and no
    comparison in the JSON; ``resume=True`` takes the saved tuned runs and finishes the comparison."""
    prob, _, _, _, _ = ges
    p = prob.setup.params
    tuned = p._replace(alpha2=0.5 * p.alpha2)
    study = studies.get("batista-ges")
    out = tmp_path / "eval.json"
    kw = dict(runs=2, seed=0, json_path=str(out), cfg=study.config(duration=DURATION), quiet=True)
    real, calls = montecarlo.monte_carlo, []

    def interrupted_second_call(*a, **k):
        calls.append(k.get("previous"))
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(montecarlo, "monte_carlo", interrupted_second_call)
    payload = studies.evaluate(study, tuned, **kw)
    saved = json.loads(out.read_text())
    assert not payload["complete"] and not saved["complete"] and "comparison" not in saved
    assert saved["runs_done"] == 2  # the tuned runs are kept
    calls.clear()
    monkeypatch.setattr(montecarlo, "monte_carlo", lambda *a, **k: calls.append(1) or real(*a, **k))
    payload = studies.evaluate(study, tuned, resume=True, **kw)
    saved = json.loads(out.read_text())
    assert saved["complete"] and "comparison" in saved
    assert len(calls) == 1  # only the paper's gains ran: the tuned runs came from the runs file
    # run again and interrupted in the comparison: the complete result stays (it was replaced, first by the tuned
    # runs alone marked complete, then by the partial result)
    finished = out.read_bytes()
    calls.clear()
    monkeypatch.setattr(montecarlo, "monte_carlo", interrupted_second_call)
    assert not studies.evaluate(study, tuned, **kw)["complete"]
    assert out.read_bytes() == finished


def test_nlio_case_gradient_matches_finite_differences():
    """nlio-case1 (NLIO-FG, random initial estimate, Euler-angle loss): the gradient along a direction in the
    unconstrained gains (Kp, kv, K1, K2 Cholesky / log) matches a central difference of the loss."""
    prob = problem("nlio-case1", checkpoint=100, duration=4.0)
    bound = gains_of("nlio-case1").bind(prob.setup.params)
    assert set(bound.transforms) == {"kp", "kv", "k1", "k2"}
    assert prob.spec.kind == "euler_sq" and prob.setup.init_params is not None
    th0 = bound.init()
    keys = montecarlo.run_keys(0, [0, 1])
    vg = jax.jit(jax.value_and_grad(lambda th: prob.loss_fn(prob.setup.scenario, bound.constrain(th), keys)[0]))
    g = vg(th0)[1]  # one compile: the finite differences below reuse its value
    leaves = jax.tree_util.tree_leaves(g)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in leaves)
    assert sum(float(np.max(np.abs(np.asarray(x)))) > 0 for x in leaves) == 4  # every gain moves the loss
    rng = np.random.default_rng(0)
    d = jax.tree_util.tree_map(lambda x: jnp.asarray(rng.standard_normal(np.shape(x))), th0)
    h = 1e-5
    fp = vg(jax.tree_util.tree_map(lambda a, b: a + h * b, th0, d))[0]
    fm = vg(jax.tree_util.tree_map(lambda a, b: a - h * b, th0, d))[0]
    fd = (fp - fm) / (2 * h)
    ad = sum(float(jnp.vdot(a, b)) for a, b in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(d)))
    assert abs(ad - float(fd)) <= 1e-4 * abs(float(fd)), (ad, float(fd))


def test_basis_gradients_are_the_chain_rule_of_the_interval_gradients(ges):
    """A schedule tuned through a few shapes (parametrize.LogBasis, log x = log x0 + B u) starts at the same
    loss, and its gradient is B^T times the per-interval gradient of the log-gains (two computations of the
    same derivative); ScaledSPD's gradient matches central finite differences."""
    prob, bound, loss, g, _ = ges
    base = bound.base
    starts = np.concatenate([[0.0], np.asarray(base.switch_times, float)])
    b1 = np.stack([np.ones_like(starts), starts / starts.max()], 1)
    b2 = np.stack([starts < 3.0, starts >= 3.0, np.log1p(starts)], 1).astype(float)
    tb = P.for_gains(
        registry.get("batista-ges").gains,
        transforms={
            "alpha1": P.LogBasis(b1),
            "alpha2": P.LogBasis(b2),
            "gain_z": P.ScaledSPD(np.kron(np.eye(3), np.ones((3, 1)))),
        },
    ).bind(base)
    assert tb.n_free() == 2 + 3 + 3
    loss2, g2, _ = value_and_grad(prob, tb)
    assert loss2 == pytest.approx(loss, rel=1e-12)
    for field, b in (("alpha1", b1), ("alpha2", b2)):
        np.testing.assert_allclose(
            np.asarray(g2[field]),
            b.T @ np.asarray(g[field]),
            rtol=1e-8,
            atol=1e-12 * np.abs(b.T @ np.asarray(g[field])).max(),
        )
    errs = fd_check(prob, tb, g2, [unit_direction(tb.init(), "gain_z", i) for i in range(3)])
    assert max(errs) < 1e-4, errs


def test_a_study_without_x64_says_so_once_and_labels_its_precision(tmp_path):
    """With JAX's x64 mode off (jaxatt never switches it), a study's paper gains are float32 with one jaxatt
    warning that says how to get float64 (not one JAX truncation warning per array), and the reproduce JSON
    records float32, the precision that ran."""
    import subprocess
    import sys

    code = f"""
import json, warnings
import jax
assert not jax.config.values["jax_enable_x64"]
from jaxatt import studies
st = studies.get("complementary")
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    s = st.setup(duration=0.5)
msgs = [str(w.message) for w in caught]
assert len(msgs) == 1 and "jax_enable_x64" in msgs[0] and "float32" in msgs[0], msgs
assert {{str(x.dtype) for x in jax.tree_util.tree_leaves(s.params) if x.dtype.kind == "f"}} == {{"float32"}}
studies.reproduce(st, st.config(duration=0.5), runs=1, json_path={str(tmp_path / "r.json")!r}, quiet=True)
print(json.load(open({str(tmp_path / "r.json")!r}))["config"]["dtype"])
"""
    env = {k: v for k, v in __import__("os").environ.items() if k != "JAX_ENABLE_X64"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().splitlines()[-1] == "float32"


def test_every_study_config_has_settings_of_its_declared_kind():
    """The check of study settings (jaxatt.studies.base.check_settings) accepts each study's own defaults and
    returns them unchanged in value (lists as tuples, numbers as floats)."""
    from jaxatt.studies import base, batista_ges, batista_so3, complementary, nlio

    for mod, name in ((batista_ges, "batista-ges"), (batista_so3, "batista-so3"), (complementary, "complementary")):
        d = mod.Config()._asdict()
        assert base.check_settings(mod.Config, d, name) == {k: v for k, v in d.items()}
    for key, cfg in nlio.CASES.items():
        d = cfg._asdict()
        assert base.check_settings(nlio.Config, d, f"nlio-{key}") == d
    # a 3x3 initial estimate is read as its 9 numbers, row-major
    s = studies.get("batista-ges").setup(duration=1.0, r_hat_0=np.eye(3))
    assert s.config.r_hat_0 == (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


@pytest.mark.parametrize(
    "flags", [["--train-runs", "32"], ["--val-runs", "4"], ["--train-runs", "2", "--val-runs", "0"]]
)
def test_tune_varfree_says_run_counts_do_not_apply(flags, tmp_path, capsys):
    """`jaxatt tune --objective varfree` draws no runs: --train-runs / --val-runs given (even at their defaults)
    are said to be ignored, before anything is computed, and not refused: 0.2.0 took them, and its commands keep
    working (here the run then stops at its bad --out, exit 2, so nothing is computed)."""
    from jaxatt import cli

    out = tmp_path / "g.txt"
    argv = ["tune", "--experiment", "batista-ges", "--objective", "varfree", *flags, "--out", str(out), "--quiet"]
    assert cli.main(argv) == 2
    warning, error = capsys.readouterr().err.strip().split("\n")
    assert re.match(r"jaxatt: warning: --.* not apply to --objective varfree .*: ignored", warning)
    assert error.startswith("jaxatt: error: --out") and not out.exists()


def test_fit_refuses_a_step_beyond_rk4s_stability_before_computing(tmp_path):
    """The fitter checks the study's step against the starting gains as `reproduce` does: batista-ges at dt = 0.03 s
    (Table 1's alpha1 = 100 1/s, alpha1 dt = 3 > 2.78) would go non-finite; refused with the longest step that
    works, before any program is compiled (no gains file written)."""
    out = tmp_path / "g.json"
    with pytest.raises(ValueError, match=r"dt = 0.03 s is too long for alpha1 = 100 .*dt < 0.0278"):
        fitter.fit(None, None, "batista-ges", steps=1, out=str(out), config={"dt": 0.03, "duration": 30.0})
    assert not out.exists()


@pytest.mark.parametrize("where", ["drawing the batch", "the last step's evaluation"])
def test_a_fit_resumed_after_an_interrupt_or_extended_ends_as_the_uninterrupted_one(where):
    """The saved data order is the one after the last recorded step: a step interrupted after drawing its batch
    (a Ctrl-C during its gradient), or a finished fit's evaluation of its last update, does not use up batches
    of the resumed run (before, the resumed steps trained on other minibatches than the uninterrupted fit)."""
    data = jnp.asarray(np.random.default_rng(0).normal(size=8))

    def objective(theta, idx):
        return jnp.mean((theta["x"] - data[idx]) ** 2), {}

    calls = []

    def take(idx, stop_at=None):
        calls.append(1)
        if len(calls) == stop_at:
            raise KeyboardInterrupt
        return jnp.asarray(idx)

    kw = dict(lr=0.1, clip=None)
    full = fitter.optimize(objective, {"x": jnp.asarray(3.0)}, steps=6, sampler=fitter.Sampler(8, 2), take=take, **kw)
    calls.clear()
    if where == "drawing the batch":  # interrupted in step 4, its batch drawn
        first = fitter.optimize(
            objective,
            {"x": jnp.asarray(3.0)},
            steps=6,
            sampler=fitter.Sampler(8, 2),
            take=lambda idx: take(idx, stop_at=4),
            **kw,
        )
        assert first.status == "interrupted" and len(first.history) == 3
    else:  # a finished 3-step fit (its last update evaluated on one more batch), extended to 6
        first = fitter.optimize(
            objective, {"x": jnp.asarray(3.0)}, steps=3, sampler=fitter.Sampler(8, 2), take=take, **kw
        )
        assert first.status == "done"
    rest = fitter.optimize(
        objective, {"x": jnp.asarray(3.0)}, steps=6, sampler=fitter.Sampler(8, 2), take=take, resume=first.resume, **kw
    )
    loss = lambda r: [h["train_loss"] for h in r.history]  # noqa: E731
    np.testing.assert_allclose(loss(rest), loss(full), rtol=1e-14)
    np.testing.assert_allclose(float(rest.last_theta["x"]), float(full.last_theta["x"]), rtol=1e-14)


def test_resume_on_a_gains_file_of_0_1_says_to_start_from_its_gains(tmp_path, capsys):
    """A gains file written by jaxatt 0.1 (format jaxatt-gains/1) holds no resume state: `tune --resume` on it
    says so and points to --init-gains, before computing (it said "setting 'data' differs (None vs 'study')")."""
    from jaxatt import cli

    old = {
        "format": "jaxatt-gains/1",
        "experiment": "batista-so3",
        "gains": {  # the values 0.1 wrote (a short tune of the paper's gains)
            "alpha1": {"value": [4.7e-09, 5.0e-09, 2.5e-09, 1.2e-09, 1.2e-09], "switch_times_s": [300, 420, 600, 720]},
            "alpha2": {"value": [0.105, 0.05, 0.025, 0.01, 0.005], "switch_times_s": [300, 420, 600, 720]},
            "alpha0": {"value": 4.7e-11},
            "alpha3": {"value": 1.0e-11},
            "alpha4": {"value": 1.9e-11},
        },
        "status": "done",
    }
    out = tmp_path / "g.json"
    out.write_text(json.dumps(old))
    argv = ["tune", "--experiment", "batista-so3", "--steps", "2", "--duration", "20", "--out", str(out), "--resume"]
    assert cli.main([*argv, "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert re.match(r"jaxatt: error: resume: .*g.json holds no resume state \(a gains file of another jaxatt "
                    r"version, e.g. 0.1.*--init-gains\)$", err), err  # fmt: skip
    assert json.loads(out.read_text()) == old  # untouched
