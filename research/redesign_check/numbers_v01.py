"""Reference numbers computed with the 0.1 API (before the redesign), to check the redesign moves nothing.

Run from the repository root: python research/redesign_check/numbers_v01.py OUT.json
"""

import json
import math
import sys

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np

from jaxatt import montecarlo, tune
from jaxatt.experiments import batista_ges, batista_so3, complementary
from jaxatt.experiments import nlio as X

out = {}


def lists(d):
    return {k: np.asarray(v, float).tolist() for k, v in d.items()}


for mod in (batista_ges, batista_so3):
    cfg = mod.Config(duration=300.0, window_start=200.0)
    for dt_name, dt in (("f64", jnp.float64), ("f32", jnp.float32)):
        res = montecarlo.monte_carlo(
            mod.scenario(cfg),
            mod.observer(cfg),
            mod.params(cfg, dtype=jnp.float64),
            runs=4,
            duration=cfg.duration,
            dt=cfg.dt,
            seed=3,
            errors_fn=mod.errors,
            window_start=cfg.window_start,
            chunk=2,
            dtype=dt,
        )
        out[f"mc/{mod.NAME}/{dt_name}"] = lists(res.per_run)

cfg = complementary.Config(
    scenario="rotating",
    duration=30.0,
    window_start=20.0,
    k_i=0.1,
    gyro_noise_std=0.01,
    meas_noise_std=0.01,
    gyro_bias_deg_s=(1.0, -1.0, 0.5),
)
res = montecarlo.monte_carlo(
    complementary.scenario(cfg),
    complementary.observer(cfg),
    complementary.params(cfg, dtype=jnp.float64),
    runs=3,
    duration=cfg.duration,
    dt=cfg.dt,
    seed=1,
    errors_fn=complementary.errors,
    window_start=cfg.window_start,
)
out["mc/complementary"] = lists(res.per_run)

cfg = X.config("nlio-case1", duration=60.0, windows=(("transient", 0.0, 20.0), ("steady", 40.0, 60.0)))
for name in ("NLO", "NLIO-FG", "NLIO-TV", "MEKF"):
    res = montecarlo.monte_carlo(
        X.scenario(cfg),
        X.observer(cfg, name),
        X.params(cfg, name, dtype=jnp.float64),
        runs=3,
        duration=cfg.duration,
        dt=cfg.dt,
        seed=0,
        errors_fn=X.errors,
        window_start=40.0,
        hold=cfg.hold,
        chunk=3,
        windows=cfg.windows,
        init_params=X.random_initial_attitude,
        trace_every=100,
        trace_fn=X.trace,
    )
    out[f"mc/nlio-case1/{name}"] = lists(res.per_run)
    out[f"mc/nlio-case1/{name}/trace_abs_euler_mean"] = np.asarray(res.traces["abs_euler"]).mean(axis=(0, 2)).tolist()

# simulated log + run
cfg = batista_ges.Config(duration=20.0)
samples, truth = montecarlo.simulate_log(batista_ges.scenario(cfg), duration=20.0, dt=0.01, seed=2)
o = montecarlo.run(batista_ges.observer(cfg), batista_ges.params(cfg), samples)
out["run/ges/r_last"] = np.asarray(o.r[-1]).tolist()
out["run/ges/r_first"] = np.asarray(o.r[0]).tolist()
out["run/ges/n"] = int(o.r.shape[0])

# tuning losses and gradients
for name, dur in (("batista-ges", 60.0), ("batista-so3", 60.0), ("nlio-case1", 30.0)):
    prob = tune.make_problem(name, duration=dur, transient_weight=0.5)
    keys = montecarlo.run_keys(0, range(4))
    th = prob.theta0()
    (loss, aux), g = jax.value_and_grad(prob.objective, has_aux=True)(th, keys)
    out[f"tune/{name}/loss"] = float(loss)
    out[f"tune/{name}/grad"] = {k: np.asarray(v).reshape(-1).tolist() for k, v in g.items()}

# BROAD
try:
    from pathlib import Path

    from jaxatt import broad_tune
    from jaxatt.data import broad

    DATA = Path.cwd().parent / "shared" / "data" / "broad"
    names = ["01_undisturbed_slow_rotation_A", "24_disturbed_tapping_A", "32_disturbed_attached_magnet_1cm"]
    trs = {n: broad.load_trial(DATA / f"{n}.hdf5") for n in names}
    for obs in ("robust", "mahony", "complementary", "nlio", "nlio-fg", "nlo", "mekf"):
        r = broad_tune.broad_eval(DATA, obs, trials=names, verbose=False, loaded=trs)
        out[f"broad/{obs}"] = {n: r["trials"][n] for n in names}
        r32 = broad_tune.broad_eval(DATA, obs, trials=names[:1], verbose=False, loaded=trs, dtype="float32")
        out[f"broad32/{obs}"] = {n: r32["trials"][n] for n in names[:1]}
    # differentiable BROAD loss of the robust AHRS (untuned start) and its gradient
    spec = broad_tune.get_spec("robust")
    batch, _ = broad_tune._make_batch([trs[n] for n in names[:2]], jnp.float64, broad.load_trial_info(DATA))
    loss_fn = broad_tune.make_loss(spec.observer, spec.prepare)
    g0 = {k: jnp.asarray(v, jnp.float64) for k, v in spec.start.items()}

    def obj(logs):
        g = dict(g0)
        for i, k in enumerate(spec.tunable):
            g[k] = jnp.exp(logs[i])
        return loss_fn(spec.build(g), batch)

    th = jnp.asarray([math.log(spec.start[k]) for k in spec.tunable])
    (l, rm), gr = jax.value_and_grad(obj, has_aux=True)(th)
    out["broad_loss/robust"] = {
        "loss": float(l),
        "rmse": np.asarray(rm).tolist(),
        "grad": np.asarray(gr).tolist(),
        "names": list(spec.tunable),
    }
except ImportError as e:
    print("BROAD skipped:", e)

json.dump(out, open(sys.argv[1], "w"), indent=1)
print("written", len(out), "entries")
