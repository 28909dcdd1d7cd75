# %% [markdown]
# # Excitation: when can an attitude observer converge?
#
# Trumpf, Mahony, Hamel & Lageman (IEEE TAC 2012), *Analysis of non-linear attitude observers for time-varying
# reference measurements*, show that the complementary observer (their eq. 10) converges when the reference
# directions it sees are *persistently exciting* (Definition 4.1): over every window of length T the
# directions must span at least two dimensions,
#
#     lambda2( integral over [t, t+T] of sum_v v v^T ) >= c > 0,
#
# with equivalent forms in Lemma 4.2 (eq. 12) and a condition in terms of the inputs only (Theorem 4.3, eq. 13).
# One constant direction is never enough (the rotation about it is unobservable); a direction that moves in
# the inertial frame can be, and so can a body-fixed direction seen from a rotating body.
#
# `jaxatt.analysis` computes these measures over sliding windows for a scenario or a log, and
# `jaxatt.sim.references` has the four textbook cases:
#
# | scenario | measurements | exciting? |
# |---|---|---|
# | `rotating` | one inertial direction on a cone, turning at 30 deg/s | yes |
# | `constant` | one constant inertial direction (z) | no: the rotation about z is unobservable |
# | `two_constant` | two constant non-collinear directions | yes (the classical case) |
# | `body_fixed` | one body-fixed direction measured in the inertial frame, body turning | yes |
#
# **Reduced mode** (`JAXATT_NOTEBOOK_QUICK=1`): 60 s instead of 120 s per scenario.

# %%
import os
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib.pyplot as plt
import numpy as np

from jaxatt import analysis, montecarlo, plot, studies
from jaxatt.sim import references

QUICK = os.environ.get("JAXATT_NOTEBOOK_QUICK", "0") == "1"
FIG_DIR = Path(os.environ.get("JAXATT_FIGURE_DIR", "figures"))
RESULTS = {}

NAMES = ("rotating", "constant", "two_constant", "body_fixed")
DURATION = 60.0 if QUICK else 120.0  # s
DT = 0.01  # s
WINDOW = 5.0  # s, the window T of Definition 4.1
THRESHOLD = 0.05  # lambda2 / T below this: "not exciting" (the CLI's default)
TITLES = {
    "rotating": "rotating: one inertial direction on a cone",
    "constant": "constant: one inertial direction",
    "two_constant": "two_constant: two inertial directions",
    "body_fixed": "body_fixed: one body-fixed direction",
}


def show(fig, name):
    """Save ``fig`` as FIG_DIR/name.png, then show it."""
    print("figure saved to", plot.save(fig, FIG_DIR / f"{name}.png"))
    plt.show()


# %% [markdown]
# ## Excitation measures over sliding windows
#
# Each measure is divided by the window length, so it is a rate in [0, n]: `lambda2` of Definition 4.1 (the
# second largest eigenvalue of the integrated outer products), `lambda_min` of the projector form of Lemma 4.2,
# and the left side of condition (13) of Theorem 4.3. The measures come from the noise-free log of each scenario.

# %%
scenarios = {n: references.make_scenario(n) for n in NAMES}
exc = {
    n: analysis.excitation_of_scenario(s, duration=DURATION, dt=DT, window=WINDOW, stride=10)
    for n, s in scenarios.items()
}

top = 1.1 * max(
    float(np.max(getattr(e, f) / WINDOW))
    for e in exc.values()
    for f in ("lambda2", "lambda_min_projector", "condition")
)
fig, axes = plt.subplots(2, 2, figsize=(9, 6.0), sharex=True, constrained_layout=True)
for ax, n in zip(axes.ravel(), NAMES):
    analysis.plot_excitation(exc[n], ax=ax, threshold=THRESHOLD, title=TITLES[n])
    ax.set_ylim(-0.02 * top, top)
    ax.get_legend().remove()
    ax.grid(True, alpha=0.3)
for ax in axes[0]:
    ax.set_xlabel("")
handles, labels = axes[0, 0].get_legend_handles_labels()
fig.legend(
    handles + [axes[0, 0].lines[-1]],
    labels + [f"threshold {THRESHOLD:g}"],
    loc="outside lower center",
    ncol=4,
    fontsize=8,
)
fig.suptitle(f"persistent-excitation measures, windows of T = {WINDOW:g} s (per second of window)")
show(fig, "03_excitation_measures")

RESULTS["lambda2_min_per_s"] = {n: float(np.min(e.lambda2) / WINDOW) for n, e in exc.items()}
for n in NAMES:
    lam = RESULTS["lambda2_min_per_s"][n]
    print(f"{n:13s} min lambda2 / T = {lam:.4f}  -> {'exciting' if lam >= THRESHOLD else 'NOT exciting'}")

# %% [markdown]
# ## The observer on each scenario
#
# The complementary observer of eq. (10) (`jaxatt.observers.complementary`, gain 0.6 1/s per measurement)
# starts from roll, pitch, yaw = (150, 0, 0) deg while the truth starts at (20, -10, 30) deg; the gyro has white
# noise (1e-3 rad/s per sample) and the measured unit vectors 0.01 per component. Same seed for every scenario.
# The set-up is the `complementary` study (`jaxatt.studies.get("complementary")`); `montecarlo.simulate` runs
# one seed and records every 10th estimate from t = 0.

# %%
study = studies.get("complementary")
traces, summaries = {}, {}
for n in NAMES:
    s = study.setup(scenario=n, duration=DURATION, gyro_noise_std=1e-3, meas_noise_std=1e-2)  # window: last third
    summ, tr, _ = montecarlo.simulate(
        s.scenario,
        s.observer,
        s.params,
        duration=s.duration,
        dt=s.dt,
        errors_fn=s.errors_fn,
        window_start=s.window_start,
        hold=s.hold,
        trace_every=10,
        trace_fn=plot.euler_trace,
    )
    traces[n], summaries[n] = tr, summ
    print(
        f"{n:13s} final angle error {summ['final_angle_error_deg']:8.3f} deg, mean over the last third "
        f"{summ['mean_angle_error_deg']:8.3f} deg"
    )
RESULTS["final_angle_error_deg"] = {n: s["final_angle_error_deg"] for n, s in summaries.items()}

fig, ax = plt.subplots(figsize=(7, 3.6), constrained_layout=True)
for n, color in zip(NAMES, ("tab:blue", "tab:red", "tab:green", "tab:purple")):
    plot.angle_error_plot(traces[n], ax=ax, label=n, color=color)
ax.set_title("complementary observer (Trumpf et al. eq. 10): angle error")
show(fig, "03_angle_error_by_scenario")

# %% [markdown]
# With one constant reference (`constant`), the error converges to a rotation about that reference (the
# inertial z axis, i.e. the yaw): the tilt (roll, pitch) is corrected, the yaw error stays where the transient
# left it. The Euler-angle errors make this visible:

# %%
fig = plot.euler_error_plot(traces["constant"], title="constant reference: the yaw error is not observable")
for i, ax in enumerate(fig.axes):
    ax.lines[0].set_label("constant")
    ax.plot(
        traces["two_constant"]["t"],
        traces["two_constant"]["euler_error_deg"][:, i],
        color="0.35",
        ls="--",
        lw=0.9,
        label="two_constant",
    )
    ax.legend(fontsize=7, loc="upper right")
show(fig, "03_euler_constant_vs_two")

RESULTS["constant_final_yaw_error_deg"] = float(traces["constant"]["euler_error_deg"][-1, 2])
RESULTS["constant_final_tilt_error_deg"] = float(np.max(np.abs(traces["constant"]["euler_error_deg"][-1, :2])))
print(
    f"constant reference at t = {DURATION:g} s: roll/pitch error <= "
    f"{RESULTS['constant_final_tilt_error_deg']:.3f} deg, "
    f"yaw error {RESULTS['constant_final_yaw_error_deg']:.1f} deg"
)

# %% [markdown]
# ## From the shell
#
# `jaxatt excitation --scenario rotating --window 5 --plot exc.png` prints the same measures and their minimum;
# `jaxatt excitation --log mylog.csv --mag-ref X,Y,Z --frame NED` analyses a recorded accelerometer and
# magnetometer log against constant references.
