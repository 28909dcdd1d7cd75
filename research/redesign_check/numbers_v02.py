"""The numbers of numbers_v01.py computed with the 0.2 API (after the redesign), same entries.

Run from the repository root: python research/redesign_check/numbers_v02.py OUT.json; then
python research/redesign_check/compare.py v01.json v02.json.
"""

import json
import sys

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np

from jaxatt import montecarlo, studies
from jaxatt.fitting import fitter, losses
from jaxatt.fitting import parametrize as P
from jaxatt.observers import registry
from jaxatt.studies import batista_ges, batista_so3, complementary
from jaxatt.studies import nlio as X

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
out["run/ges/r_first"] = np.asarray(o.r[1]).tolist()  # 0.2: estimate 0 is init's, the first step's is row 1
out["run/ges/n"] = int(o.r.shape[0]) - 1

# tuning losses and gradients
for name, dur in (("batista-ges", 60.0), ("batista-so3", 60.0), ("nlio-case1", 30.0)):
    st = studies.get(name).setup(duration=dur)
    (ss, se), (ts, te) = st.loss_windows["steady"], st.loss_windows["transient"]
    spec = losses.loss_spec(
        st.loss_kind, steady_start=ss, steady_end=se, transient_start=ts, transient_end=te, w_transient=0.5
    )
    bound = P.for_gains(registry.get(st.entry).gains).bind(st.params)
    obj = fitter.simulated_objective(st, bound, spec)
    keys = montecarlo.run_keys(0, range(4))
    (loss, aux), g = jax.value_and_grad(obj, has_aux=True)(bound.init(), keys)
    out[f"tune/{name}/loss"] = float(loss)
    out[f"tune/{name}/grad"] = {k: np.asarray(v).reshape(-1).tolist() for k, v in g.items()}

# BROAD (0.2: jaxatt.broad_score; estimate k uses samples 1 ... k after the start from sample 0, "next")
try:
    from pathlib import Path

    import jaxatt
    from jaxatt.data import broad

    DATA = Path.cwd().parent / "shared" / "data" / "broad"
    names = ["01_undisturbed_slow_rotation_A", "24_disturbed_tapping_A", "32_disturbed_attached_magnet_1cm"]
    trs = broad.load(DATA, names)
    for obs in ("robust", "mahony", "complementary", "nlio", "nlio-fg", "nlo", "mekf"):
        r = jaxatt.broad_score(obs, None, trs)
        out[f"broad/{obs}"] = {n: r.trials[n]._asdict() for n in names}
        r32 = jaxatt.broad_score(obs, None, trs[:1], dtype="float32")
        out[f"broad32/{obs}"] = {n: r32.trials[n]._asdict() for n in names[:1]}
    e = registry.get("robust")
    from jaxatt.observers import robust_ahrs as ra

    p0 = e.default_params(dtype=jnp.float64)
    bound = P.for_gains(e.gains).bind(p0)
    obj, n, take = fitter.recorded_objective(registry.recorded_observer(e), bound, trs[:2], dtype=jnp.float64)
    (l, aux), gr = jax.value_and_grad(obj, has_aux=True)(bound.init(), take(np.arange(2)))
    out["broad_loss/robust"] = {
        "loss": float(l),
        "rmse": np.asarray(aux["rmse_deg"]).tolist(),
        "grad": [float(gr[k]) for k in ra.TUNABLE],
        "names": list(ra.TUNABLE),
    }
except ImportError as e:
    print("BROAD skipped:", e)

json.dump(out, open(sys.argv[1], "w"), indent=1)
print("written", len(out), "entries")
