# %% [markdown]
# # Real data: the BROAD benchmark with Mahony's filter
#
# BROAD (Laidig, Caruso, Cereatti & Seel, "BROAD - A Benchmark for Robust Inertial Orientation Estimation",
# Data 6(7), 2021, doi:10.3390/data6070072, CC BY 4.0) holds IMU recordings at 285.7 Hz with optical ground
# truth: `imu_gyr` (rad/s), `imu_acc` (m/s^2), `imu_mag` (uT) in the sensor frame, and `opt_quat`, the true
# sensor-to-**ENU** orientation (w, x, y, z), NaN where the markers were lost. Errors are scored over the
# `movement` samples: RMSE of the total, heading and inclination angles of q_est (x) conj(q_true), with no
# offset fitted.
#
# `jaxatt.data.broad` loads the trials and computes the metric; `jaxatt.observers.mahony` is the explicit
# complementary filter with bias estimation as BROAD's example code runs it (Madgwick's MahonyAHRS.cpp, earth
# frame NWU, output rotated into ENU). Trials of different lengths are padded and run in one vmapped scan.
#
# **Data.** The trials are read from the folder in `JAXATT_BROAD_DIR` (default `../../shared/data/broad`
# relative to this notebook). Without it the notebook prints a message and skips the data cells.
# **Reduced mode** (`JAXATT_NOTEBOOK_QUICK=1`): 3 trials and a 4-point gain grid instead of every trial and
# 8 points.

# %%
import json
import os
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

from jaxatt import plot
from jaxatt.data import broad
from jaxatt.observers import mahony

QUICK = os.environ.get("JAXATT_NOTEBOOK_QUICK", "0") == "1"
FIG_DIR = Path(os.environ.get("JAXATT_FIGURE_DIR", "figures"))
DATA_DIR = Path(os.environ.get("JAXATT_BROAD_DIR", "../../shared/data/broad"))
RESULTS = {}


def show(fig, name):
    """Save ``fig`` as FIG_DIR/name.png, then show it."""
    print("figure saved to", plot.save(fig, FIG_DIR / f"{name}.png"))
    plt.show()


try:
    import h5py  # noqa: F401  (reading the HDF5 trials needs it: pip install "jaxatt[data]")

    HAVE_DATA = DATA_DIR.is_dir() and len(broad.list_trials(DATA_DIR)) > 0
except ImportError:
    HAVE_DATA = False
RESULTS["have_data"] = HAVE_DATA
if HAVE_DATA:
    print(f"BROAD trials in {DATA_DIR.resolve()}: {len(broad.list_trials(DATA_DIR))}")
    print(broad.ATTRIBUTION)
else:
    print(f"BROAD data not found in {DATA_DIR.resolve()} (or h5py missing): set JAXATT_BROAD_DIR to the folder "
          "of the .hdf5 trials (https://github.com/dlaidig/broad). The data cells below are skipped.")

# %% [markdown]
# ## Load a few trials and run the filter on all of them at once

# %%
if HAVE_DATA:
    names = broad.list_trials(DATA_DIR)
    if QUICK:
        names = [n for n in names if n.startswith(("01_", "06_", "28_"))] or names[:3]
    trials = broad.load_trials(DATA_DIR, names)
    for tr in trials:
        print(f"{tr.name:48s} {len(tr.samples.t):6d} samples ({len(tr.samples.t) / tr.rate_hz:5.1f} s), "
              f"{tr.movement.sum():6d} scored, groups {broad.trial_groups(tr.name)}")

    observer = mahony.make_observer()  # init_mode="broad": BROAD's start from the first acc/mag sample
    params = mahony.default_params()  # BROAD's TAGP gains Kp = 0.74 1/s, Ki = 0.0012 1/s^2
    padded = broad.pad_trials(trials)  # (B, T_max, ...), padding repeats the last sample; mask marks real ones
    q_est = broad.run_on_padded(observer, params, padded)  # (B, T_max, 4) sensor-to-ENU, one jit + vmap
    print("estimates:", q_est.shape)

# %% [markdown]
# ## The BROAD metric per trial, against the published numbers
#
# `published/results_mahony_average_rmse.json` holds the dataset authors' own numbers for the same filter and
# gains. The float64 filter here differs from their float32 C code by rounding only (up to ~1e-3 deg; the
# float32 run in `tests/test_broad.py` matches to 1e-12 deg).

# %%
if HAVE_DATA:
    pub_path = DATA_DIR / "published" / "results_mahony_average_rmse.json"
    published = json.loads(pub_path.read_text())["trials"] if pub_path.exists() else {}
    rows = {}
    print(f"{'trial':48s} {'total':>7s} {'heading':>8s} {'incl.':>7s}   published total (deg)")
    for i, tr in enumerate(trials):
        m = broad.broad_errors(q_est[i, : padded.lengths[i]], tr.quat_true, tr.movement)
        pub = published.get(tr.name, {}).get("tagp_parameters", {}).get("total_rmse_deg")
        rows[tr.name] = dict(m, published_total_rmse_deg=pub)
        print(f"{tr.name:48s} {m['total_rmse_deg']:7.3f} {m['heading_rmse_deg']:8.3f} "
              f"{m['inclination_rmse_deg']:7.3f}   {pub if pub is None else f'{pub:.3f}'}")
    RESULTS["per_trial"] = rows
    diffs = [abs(r["total_rmse_deg"] - r["published_total_rmse_deg"]) for r in rows.values()
             if r["published_total_rmse_deg"] is not None]
    RESULTS["max_abs_diff_to_published_deg"] = float(max(diffs)) if diffs else None
    print(f"largest difference to the published RMSE: {RESULTS['max_abs_diff_to_published_deg']:.2e} deg")

# %%
if HAVE_DATA:
    fig, ax = plt.subplots(figsize=(7.5, 0.42 * len(rows) + 1.9), constrained_layout=True)
    y = np.arange(len(rows))[::-1]
    for j, (key, label, color) in enumerate((("total_rmse_deg", "total", "tab:blue"),
                                             ("heading_rmse_deg", "heading", "tab:orange"),
                                             ("inclination_rmse_deg", "inclination", "tab:green"))):
        ax.barh(y + (1 - j) * 0.26, [r[key] for r in rows.values()], height=0.25, color=color, label=label)
    pub = [r["published_total_rmse_deg"] for r in rows.values()]
    ax.plot([np.nan if p is None else p for p in pub], y + 0.26, "k|", ms=12, mew=2, label="published total")
    ax.set_yticks(y)
    ax.set_yticklabels(list(rows), fontsize=8)
    ax.set_xlabel("RMSE over the movement phase (deg)")
    ax.set_title(f"Mahony (Kp = {float(params.kp):g}, Ki = {float(params.ki):g}) on BROAD")
    ax.grid(True, axis="x", alpha=0.3)
    fig.legend(loc="outside lower center", ncol=4, fontsize=8)
    show(fig, "04_broad_rmse_per_trial")

# %% [markdown]
# ## Error over time in one trial
#
# `broad.error_angles` gives the per-sample errors behind the metric. The grey band is the scored `movement`
# phase; the rest phases before and after it are not scored (during rest the heading error drifts: only the
# magnetometer corrects it, with a small gain).

# %%
if HAVE_DATA:
    i = 0
    tr = trials[i]
    n = padded.lengths[i]
    total, heading, incl = (np.rad2deg(e) for e in broad.error_angles(q_est[i, :n], tr.quat_true))
    t = tr.samples.t
    fig, ax = plt.subplots(figsize=(7.5, 3.4), constrained_layout=True)
    ax.fill_between(t, 0, 1, where=tr.movement, transform=ax.get_xaxis_transform(), color="0.9", lw=0,
                    label="movement (scored)")
    ax.plot(t, total, lw=0.7, label="total")
    ax.plot(t, heading, lw=0.7, label="heading")
    ax.plot(t, incl, lw=0.7, label="inclination")
    ax.set_yscale("log")
    ax.set_ylim(1e-2, 200)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("error (deg)")
    ax.set_title(f"{tr.name}: Mahony, TAGP gains")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, ncol=4, loc="upper right")
    show(fig, "04_broad_error_over_time")
    RESULTS["example_trial"] = tr.name

# %% [markdown]
# ## A gain grid in one call
#
# `broad.batch_errors_jax` is the metric as a pure JAX function of the gains (masks instead of NaN, so it is
# also differentiable); `jax.vmap` over a grid of Kp runs every gain on every trial in one compiled scan. The
# data go in as arguments of the jitted function (closed-over arrays would be baked into the program as
# constants).

# %%
if HAVE_DATA:
    kps = np.geomspace(0.1, 5.0, 4 if QUICK else 8)
    ki = float(params.ki)

    @jax.jit
    def grid(kps, samples, quat_true, movement, mask):
        data = padded._replace(samples=samples, quat_true=quat_true, movement=movement, mask=mask)
        one = lambda kp: broad.batch_errors_jax(observer, mahony.Params(kp, jnp.asarray(ki)), data)  # noqa: E731
        return jax.vmap(one)(kps)["total_rmse_deg"]

    rmse = np.asarray(grid(jnp.asarray(kps), padded.samples, padded.quat_true, padded.movement, padded.mask))
    fig, ax = plt.subplots(figsize=(6.5, 3.6), constrained_layout=True)
    for j, name in enumerate(padded.names):
        ax.plot(kps, rmse[:, j], "-o", ms=3, lw=0.9, label=name[:32])
    ax.plot(kps, rmse.mean(axis=1), "k-", lw=2, label="mean")
    ax.axvline(float(params.kp), color="0.5", ls="--", lw=0.8, label="TAGP Kp")
    ax.set_xscale("log")
    ax.set_xlabel("Kp (1/s)")
    ax.set_ylabel("total RMSE (deg)")
    ax.set_title(f"Mahony on BROAD: Kp grid (Ki = {ki:g})")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    show(fig, "04_broad_kp_grid")
    RESULTS["kp_grid"] = {"kp": kps.tolist(), "mean_total_rmse_deg": rmse.mean(axis=1).tolist()}
    print({f"{k:.3g}": f"{v:.2f} deg" for k, v in zip(kps, rmse.mean(axis=1))})
