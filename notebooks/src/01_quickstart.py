# %% [markdown]
# # jaxatt quick start: simulate, run an observer, plot
#
# This notebook simulates the set-up of Section IV of Batista, Silvestre & Oliveira (2019), *Globally
# exponentially stable attitude observer with Earth velocity estimation*: a platform in Lisbon turning slowly,
# a high-grade gyro that senses the Earth's rotation, and a magnetometer. It runs the paper's observer
# (`jaxatt.observers.batista_ges`) over the simulated log, plots the attitude error, and then runs a small
# Monte Carlo study with `montecarlo.monte_carlo`, drawn as an envelope (median and percentile bands).
#
# Conventions (see `docs/concepts.md`): `R` maps body coordinates to the reference frame (here NED);
# quaternions are `(w, x, y, z)`; SI units, magnetic field in nT; degrees only in reports (`_deg`).
#
# **Reduced mode.** With `JAXATT_NOTEBOOK_QUICK=1` (CI) the notebook samples at 50 Hz instead of 100 Hz and
# runs 8 Monte Carlo runs instead of 100. Figures are saved to `JAXATT_FIGURE_DIR` (default: `figures/` next
# to this notebook) as well as shown.

# %%
import os
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)  # float64, as for the paper reproductions (float32: dtype=jnp.float32)

import matplotlib.pyplot as plt
import numpy as np

from jaxatt import montecarlo, plot, so3
from jaxatt.studies import batista_ges as E

QUICK = os.environ.get("JAXATT_NOTEBOOK_QUICK", "0") == "1"
FIG_DIR = Path(os.environ.get("JAXATT_FIGURE_DIR", "figures"))
RESULTS = {}  # key numbers, checked by tests/test_notebooks.py


def show(fig, name):
    """Save ``fig`` as FIG_DIR/name.png, then show it."""
    print("figure saved to", plot.save(fig, FIG_DIR / f"{name}.png"))
    plt.show()


print(f"quick mode: {QUICK}; figures in {FIG_DIR.resolve()}; JAX backend: {jax.default_backend()}")

# %% [markdown]
# ## The study: scenario, observer, parameters
#
# `jaxatt.studies.batista_ges` bundles the paper's set-up (the same study as an object:
# `jaxatt.studies.get("batista-ges")`). Every setting is a field of `Config` (and a flag of `jaxatt simulate`).
# The observer is a pair of pure functions `init(params, first_sample)` and `step(params, state, sample, dt)`
# (plus `output(params, state)`, the estimate a state holds); the gains live in `params`, a NamedTuple of
# arrays, so they can be changed, vmapped over or differentiated without rebuilding anything.

# %%
cfg = E.Config(dt=0.02 if QUICK else 0.01)  # 3600 s; Section IV samples at 100 Hz
scenario = E.scenario(cfg)  # exact omega(t), Earth rate and IGRF field in NED, gyro ARW, magnetometer noise
observer = E.observer(cfg)  # Observer(init, step, name, output)
params = E.params(cfg)  # Params NamedTuple: Table-1 gain schedule, attitude gain, initial estimate

print(observer.name, "- Params fields:", ", ".join(params._fields))
print("Table 1: switch times (s)", np.asarray(params.switch_times))
print("         alpha1 (1/s)    ", np.asarray(params.alpha1))
print("initial estimate R^(0) =\n", np.asarray(params.r_hat_0), "(true R(0) = I: a 180 deg error)")

# %% [markdown]
# ## Simulate a log and run the observer over it
#
# `simulate_log` returns the sensor samples (an `ImuSample` of time-major arrays) and the truth, both at
# t_0 ... t_{T-1}; `run` scans the observer over any log, simulated or recorded. T samples give T estimates:
# row 0 is `init`'s estimate at t_0, row k the estimate at t_k, so row k is compared with `truth[k]`.

# %%
samples, truth = montecarlo.simulate_log(scenario, duration=cfg.duration, dt=cfg.dt, seed=0)
print("samples:", {k: np.shape(v) for k, v in samples._asdict().items() if v is not None})

out = montecarlo.run(observer, params, samples, cfg.dt)  # one jitted lax.scan, T estimates
assert out.r.shape[0] == samples.gyr.shape[0]
t = np.asarray(out.t)
angle = np.rad2deg(np.asarray(so3.angle_error(truth.r, out.r)))  # eq. (23), deg
steady = t >= cfg.window_start
RESULTS["n_samples"], RESULTS["n_estimates"] = int(samples.gyr.shape[0]), int(out.r.shape[0])
RESULTS["final_angle_error_deg"] = float(angle[-1])
RESULTS["mean_angle_error_deg"] = float(angle[steady].mean())
print(
    f"angle error: {angle[0]:.1f} deg at t = {t[0]:g} s, {angle[-1]:.3f} deg at t = {t[-1]:g} s; "
    f"mean over t >= {cfg.window_start:g} s: {RESULTS['mean_angle_error_deg']:.3f} deg "
    f"(paper, single run: {E.PAPER['slow']['single_run_mean_angle_error_deg']} deg)"
)

# %%
fig, ax = plt.subplots(figsize=(7, 3.2), constrained_layout=True)
plot.angle_error_plot(
    {"t": t, "angle_error_deg": angle},
    ax=ax,
    label="run 0 (seed 0)",
    title="batista-ges: attitude error from a 180 deg initial error",
)
for ts in np.asarray(params.switch_times):
    ax.axvline(ts, color="0.6", lw=0.6, ls=":")
ax.axvline(cfg.window_start, color="tab:red", lw=0.8, ls="--", label="steady-state window")
ax.legend(fontsize=8)
show(fig, "01_angle_error")

# %% [markdown]
# The dotted lines are the switches of the Table-1 gain schedule of the Earth-rate block. The attitude block
# converges slowly (time constants of about 44, 611 and 681 s with the paper's gain, see
# `docs/observers/batista_ges.md`). Over the steady-state window the error is a fraction of a degree; here it
# is split into ZYX Euler angles (roll, pitch, yaw):

# %%
euler = plot.euler_error_deg(truth.r, out.r)  # (T, 3): roll, pitch, yaw errors, deg
fig = plot.euler_error_plot(
    {"t": t, "euler_error_deg": euler},
    t_range=(cfg.window_start, cfg.duration),
    title="Euler-angle errors over the steady-state window (run 0)",
)
show(fig, "01_euler_errors")

# %% [markdown]
# The short spikes where the roll and yaw errors jump together are not attitude errors: the trajectory passes
# within 4 deg of pitch = +90 deg there (gimbal lock), where only roll - yaw is defined for ZYX angles, so equal
# errors in both cancel. The rotation-angle error above has no such artefact.

# %% [markdown]
# ## Streaming: `init` and `step` one sample at a time
#
# `run` is just a `lax.scan` of `step`. For real-time use, call `init` and `step` yourself (jit `step` once).
# `init` takes the first sample; `output(params, state)` is the estimate at t_0 (row 0 of `run`). With this
# observer's input hold (`"zoh"`, the default of `run`) the step from t_k to t_{k+1} uses sample k, and its
# output is row k + 1 of `run`:

# %%
step = jax.jit(observer.step)
state = observer.init(params, jax.tree_util.tree_map(lambda a: a[0], samples))
o = observer.output(params, state)
for k in range(4):
    if k > 0:
        state, o = step(params, state, jax.tree_util.tree_map(lambda a, k=k: a[k - 1], samples), cfg.dt)
    same = np.allclose(np.asarray(o.r), np.asarray(out.r[k]), rtol=0, atol=1e-12)
    print(
        f"t = {float(o.t):.2f} s, projected onto SO(3): {bool(o.projected)}, "
        f"angle error {float(np.rad2deg(so3.angle_error(truth.r[k], o.r))):.2f} deg, equals run row {k}: {same}"
    )
    assert same

# %% [markdown]
# ## A small Monte Carlo study
#
# `monte_carlo` fuses truth, sensors and observer in one scan, vmaps it over seeds in chunks and reduces the
# metrics on the fly; with `trace_every=n` it also keeps every n-th estimate, from estimate 0 (t = 0). Run k of
# seed s always sees the same noise (`fold_in(PRNGKey(s), k)`), whatever the chunk size, so run 0 here is the
# log above. `plot.euler_trace` records the Euler-angle errors too.

# %%
RUNS = 8 if QUICK else 100
mc = montecarlo.monte_carlo(
    scenario,
    observer,
    params,
    runs=RUNS,
    duration=cfg.duration,
    dt=cfg.dt,
    seed=0,
    errors_fn=E.errors,
    window_start=cfg.window_start,
    chunk=min(RUNS, 50),
    trace_every=100,
    trace_fn=plot.euler_trace,
    validate=E.check_params,
)
mean_angle = mc.per_run["mean_angle_error_deg"]
RESULTS["mc_runs"] = int(len(mean_angle))
RESULTS["mc_mean_angle_error_deg"] = float(np.mean(mean_angle))
RESULTS["mc_run0_final_angle_error_deg"] = float(mc.per_run["final_angle_error_deg"][0])
RESULTS["mc_trace_start_s"] = float(mc.traces["t"][0, 0])  # traces start at estimate 0, t = 0
RESULTS["mc_trace_start_angle_error_deg"] = float(mc.traces["angle_error_deg"][0, 0])  # the 180 deg start
print(
    f"{len(mean_angle)} runs in {mc.wall_s:.1f} s (compile included); traces: "
    f"{ {k: v.shape for k, v in mc.traces.items()} }"
)
print(
    f"mean angle error over t >= {cfg.window_start:g} s: {np.mean(mean_angle):.3f} deg "
    f"(std over runs {np.std(mean_angle):.3f}; paper, 1000 runs: {E.PAPER['slow']['mean_angle_error_deg']} deg)"
)
print(
    f"run 0 final error: Monte Carlo {RESULTS['mc_run0_final_angle_error_deg']:.6f} deg, "
    f"log + run above {RESULTS['final_angle_error_deg']:.6f} deg"
)

# %%
fig, axes = plt.subplots(2, 1, figsize=(7, 5.6), constrained_layout=True)
plot.angle_error_plot(mc_traces=mc.traces, ax=axes[0], title="Monte Carlo: angle error, whole run")
plot.angle_error_plot(
    mc_traces=mc.traces,
    ax=axes[1],
    logy=False,
    t_range=(cfg.window_start, cfg.duration),
    title=f"steady state (t >= {cfg.window_start:g} s)",
)
show(fig, "01_mc_envelope")

# %%
fig = plot.euler_error_plot(
    mc_traces=mc.traces,
    t_range=(cfg.window_start, cfg.duration),
    title="Monte Carlo Euler-angle errors: mean and 5-95 % band",
)
show(fig, "01_mc_euler_envelope")

# %% [markdown]
# ## Next
#
# * `02_paper_figures.ipynb`: the papers' convergence figures and Table 2 against the published numbers.
# * `03_excitation.ipynb`: when can an observer converge at all (Trumpf et al. 2012)?
# * `04_broad_real_data.ipynb`: a real IMU data set with optical ground truth.
# * `05_tuning.ipynb`: gains learnt by gradient descent through the simulation (`jaxatt.fit`).
# * From a shell: `jaxatt reproduce batista-ges --runs 20 --plot figs.png`.
