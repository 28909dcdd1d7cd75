"""Scale-out (jaxatt.sharding): Monte Carlo and tuning losses with the runs split over 2 CPU devices
(XLA_FLAGS=--xla_force_host_platform_device_count=2, in a subprocess: the flag must be set before JAX starts)
equal the single-device results; the in-scan progress reports reach the injected reporter."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np

SCRIPT = textwrap.dedent(
    """
    import json, os, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    from jaxatt import montecarlo
    from jaxatt import studies
    from jaxatt.fitting import losses as tune

    assert len(jax.devices()) == 2, jax.devices()
    out = {}
    # Monte Carlo: the complementary observer with noisy gyro and vectors and the bias integrator (the splitting
    # does not depend on the observer, and this one compiles fast); 5 runs in chunks of 3 -> chunks rounded up to 4
    # (padding dropped), traces kept; 10 s: one noise block (a partial last block is a second copy of the step)
    s = studies.get("complementary").setup(duration=10.0, gyro_noise_std=0.01, meas_noise_std=0.05, k_i=0.1,
                                           scenario="two_constant", dt=0.01)
    scn, obs, p = s.scenario, s.observer, s.params
    kw = dict(runs=5, duration=10.0, dt=s.dt, seed=3, errors_fn=s.errors_fn, window_start=4.0, chunk=3,
              trace_every=250)
    reports = []
    sh = montecarlo.monte_carlo(scn, obs, p, progress=reports.append, **kw)
    one = montecarlo.monte_carlo(scn, obs, p, devices=1, **kw)
    out["mc_keys"] = sorted(sh.per_run)
    out["mc_runs"] = [sh.run_indices.tolist(), one.run_indices.tolist()]
    out["mc_rel"] = max(float(np.max(np.abs(sh.per_run[k] - one.per_run[k]) / (np.abs(one.per_run[k]) + 1e-300)))
                        for k in one.per_run)
    out["trace_rel"] = max(float(np.max(np.abs(sh.traces[k] - one.traces[k]))) for k in one.traces)
    out["trace_shape"] = list(sh.traces["angle_error_deg"].shape)
    out["reports"] = [[r["runs_done"], r["run_steps_done"], r["run_steps_total"]] for r in reports]
    # tuning loss and its gradient through the checkpointed scan, 4 runs over 2 devices vs one device (the same
    # complementary set-up: a tunable study whose gradient compiles in a fraction of the Batista observers' time)
    cfg = s
    spec = tune.loss_spec("angle_sq", steady_start=4.0)
    keys = montecarlo.run_keys(0, range(4))
    f2 = tune.make_loss_fn(obs, duration=12.0, dt=cfg.dt, spec=spec, checkpoint=200, devices=2)
    f1 = tune.make_loss_fn(obs, duration=12.0, dt=cfg.dt, spec=spec, checkpoint=200, devices=1)
    def vg(f):
        (l, aux), g = jax.value_and_grad(lambda q: f(scn, q, keys), has_aux=True)(p)
        return float(l), aux, g
    l2, a2, g2 = vg(f2)
    l1, a1, g1 = vg(f1)
    out["loss"] = [l2, l1]
    out["aux_rel"] = float(np.max(np.abs(np.asarray(a2["window_angle_deg"]) - np.asarray(a1["window_angle_deg"]))))
    gl2, gl1 = jax.tree_util.tree_leaves(g2), jax.tree_util.tree_leaves(g1)
    out["grad_rel"] = max(float(np.max(np.abs(np.asarray(a) - np.asarray(b)))
                                / (np.max(np.abs(np.asarray(b))) + 1e-300)) for a, b in zip(gl2, gl1) if np.size(b))
    out["grad_nonzero"] = sum(float(np.max(np.abs(np.asarray(b)))) > 0 for b in gl1 if np.size(b))
    # the front door passes devices= on: Mahony on the AHRS scenario, 4 runs over both devices and over one
    import jaxatt
    fd = [jaxatt.monte_carlo("mahony", runs=4, duration=0.5, chunk=4, devices=d) for d in (None, 1)]
    out["front_door_rel"] = max(float(np.max(np.abs(fd[0].per_run[k] - fd[1].per_run[k])
                                             / (np.abs(fd[1].per_run[k]) + 1e-300))) for k in fd[1].per_run)
    try:
        f2(scn, p, montecarlo.run_keys(0, range(3)))
        out["odd_batch"] = "accepted"
    except ValueError as e:
        out["odd_batch"] = str(e)
    print("RESULT" + json.dumps(out))
    """
)


def _run_two_devices():
    env = dict(os.environ)
    # XLA's backend optimisation off: the test is compile-bound and checks equality of two splits, not speed
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2 --xla_backend_optimization_level=0"
    ).strip()
    env["JAX_PLATFORMS"] = "cpu"
    r = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-4000:]
    line = next(l for l in r.stdout.splitlines() if l.startswith("RESULT"))
    return json.loads(line[len("RESULT") :])


def test_sharded_monte_carlo_and_gradient_equal_single_device():
    out = _run_two_devices()
    # Monte Carlo: same runs, same numbers to rounding, padding dropped
    assert out["mc_runs"][0] == out["mc_runs"][1] == [0, 1, 2, 3, 4]
    assert "mean_angle_error_deg" in out["mc_keys"]
    assert out["mc_rel"] < 1e-9, out["mc_rel"]
    assert out["trace_shape"] == [5, 1 + 1000 // 250] and out["trace_rel"] < 1e-9  # estimates 0, 250, ...
    # progress: reported from inside the scan, monotone, ends at the total
    rep = np.asarray(out["reports"])
    assert len(rep) >= 3 and np.all(np.diff(rep[:, 1]) >= 0)
    assert rep[-1, 0] == 5 and rep[-1, 1] == rep[-1, 2] == 5 * 1000
    # loss and gradient: the pmean over devices is the mean over all runs
    l2, l1 = out["loss"]
    assert abs(l2 - l1) <= 1e-10 * abs(l1) and out["aux_rel"] < 1e-9
    assert out["grad_nonzero"] >= 2 and out["grad_rel"] < 1e-8, out["grad_rel"]
    assert "multiple of 2" in out["odd_batch"]
    assert out["front_door_rel"] < 1e-9, out["front_door_rel"]


def test_progress_reporter_single_device():
    from jaxatt import montecarlo, studies

    s = studies.get("complementary").setup(duration=25.0, gyro_noise_std=0.01, meas_noise_std=0.05)
    seen = []
    res = montecarlo.monte_carlo(
        s.scenario,
        s.observer,
        s.params,
        runs=3,
        chunk=2,
        duration=25.0,
        dt=s.dt,
        errors_fn=s.errors_fn,
        progress=seen.append,
        devices=1,
    )
    assert res.complete and len(res.run_indices) == 3
    done = [s["run_steps_done"] for s in seen]
    # 3 blocks (1000, 1000, 500 steps) per chunk + one report per chunk end, two chunks
    assert done == sorted(done) and done[-1] == 3 * 2500 and len(seen) >= 6
    assert {s["chunk_steps_done"] for s in seen} >= {1000, 2000, 2500}
