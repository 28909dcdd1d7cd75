"""Noise parameters learnt by gradient (issue 20 item 3): the MEKF's gyro noise and measurement covariances by
maximum likelihood of its innovations (loss kind ``innovation_nll``, no truth used) and NLIO-TV's (the noise
model of its Riccati gains) by the study's Monte Carlo loss, on simulated seeds of nlio-case1 (seed 0), both
with ``jaxatt.fit``; scored on held-out runs of seed 1 (paired with the defaults, same runs) as the RMS angle
error over the steady window, and divided by the Kalman floor of the same set-up (``jaxatt.fitting.floor``).

Defaults: the study's MEKF (true R, sigma_g, bias random walk 1e-5 rad/s/sqrt(s), P0 bias 1e-7) and NLIO-TV
(paper gains, true R and sigma_g). Starts: the defaults with every noise std 10x off (gyro x10, R_acc / 100,
R_mag x 100). The MEKF is also given the floor's bias prior (P0 bias 0.05^2) and no bias random walk, the
"own noise model" MEKF that attains the floor.

Usage: python research/noise_learning.py [--duration 60] [--train-runs 4] [--eval-runs 8] [--steps 40]
Writes research/results/noise-learning-<host>-<UTC>.json. BROAD (out of fold, 2-fold):
``python research/broad_oof_tuning.py --observers mekf`` (the MEKF is registered for recorded data).
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "benchmarks"))
sys.path.insert(0, str(HERE.parent))

import _common as C  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=60.0, help="run length (s); the study's windows scale")
    ap.add_argument("--train-runs", type=int, default=4)
    ap.add_argument("--eval-runs", type=int, default=8)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import jaxatt
    from jaxatt import montecarlo, studies
    from jaxatt.fitting import floor as F
    from jaxatt.fitting import losses

    meta = C.metadata(sys.argv if argv is None else ["noise_learning.py"] + list(argv))
    base = dict(duration=args.duration, random_init=False)
    st = studies.get("nlio-case1")
    held_out = montecarlo.run_keys(1, list(range(args.eval_runs)))
    steady = st.setup(**base).loss_windows["steady"]
    fl = F.floor_study("nlio-case1", windows=(("steady", steady[0], args.duration),), **base)["windows"]["steady"]
    floor_rms = float(np.sqrt(fl["mean_sq_deg2"]))
    print(f"floor over {steady[0]:g}-{args.duration:g} s: RMS {floor_rms:.5f} deg", flush=True)

    def rms_deg(observer, params, cfg):
        s = st.setup(observer, **cfg)
        spec = losses.loss_spec("angle_sq", steady_start=steady[0])
        f = losses.make_loss_fn(s.observer, duration=s.duration, dt=s.dt, spec=spec, hold=s.hold)
        per_run = np.asarray(f(s.scenario, params, held_out)[1]["window_loss"][0])
        return np.sqrt(per_run)  # per-run RMS angle (deg) over the steady window

    def wrong(p):
        return p._replace(gyro_noise_std=p.gyro_noise_std * 10, r_acc=p.r_acc / 100, r_mag=p.r_mag * 100)

    def row(label, per_run, ref=None):
        m = float(np.sqrt(np.mean(per_run**2)))
        r = {"label": label, "rms_deg": m, "ratio_to_floor": m / floor_rms, "per_run_rms_deg": per_run.tolist()}
        if ref is not None:
            d = per_run - ref
            r["paired_diff_deg"] = float(d.mean())
            r["paired_diff_se_deg"] = float(d.std(ddof=1) / np.sqrt(len(d)))
        print(f"  {label:40s} RMS {m:.5f} deg  ratio to floor {m / floor_rms:.3f}", flush=True)
        return r

    noise = ["gyro_noise_std", "r_acc", "r_mag"]
    out: dict = {"floor_rms_deg": floor_rms, "window_s": [steady[0], args.duration], "observers": {}}
    # ---- MEKF: likelihood of the innovations
    cfg_m = dict(base, mekf_bias_rw=1e-9, mekf_p0_bias=0.05**2)
    kw = dict(config=cfg_m, train_runs=args.train_runs, batch=args.train_runs, val_runs=0, lr=0.1, dtype=np.float64)
    kw["loss"] = "innovation_nll"
    t0 = time.perf_counter()
    # R first (the gyro noise barely moves the likelihood until R is right), then all three
    r1 = jaxatt.fit("mekf", None, "nlio-case1", start=wrong, tune=noise[1:], steps=args.steps, **kw)
    r2 = jaxatt.fit("mekf", r1.params, "nlio-case1", tune=noise, steps=args.steps, **kw)
    fit_s = time.perf_counter() - t0
    own = st.setup("mekf", **cfg_m).params
    default = st.setup("mekf", **base).params
    e_def = rms_deg("mekf", default, base)
    print("MEKF (nlio-case1):", flush=True)
    rows = [
        row("default (study MEKF)", e_def),
        row("own noise model (true Q, R; bias prior)", rms_deg("mekf", own, cfg_m), e_def),
        row("start (noise 10x off)", rms_deg("mekf", wrong(own), cfg_m), e_def),
        row("learnt (innovation likelihood)", rms_deg("mekf", r2.params, cfg_m), e_def),
    ]
    out["observers"]["mekf"] = {
        "rows": rows,
        "fit_wall_s": fit_s,
        "learnt": {f: np.asarray(getattr(r2.params, f)).tolist() for f in noise},
        "true": {f: np.asarray(getattr(own, f)).tolist() for f in noise},
    }
    # ---- NLIO-TV: the study's Monte Carlo loss (euler_sq over the steady window)
    kw = dict(config=base, train_runs=args.train_runs, batch=args.train_runs, val_runs=0, lr=0.1, dtype=np.float64)
    t0 = time.perf_counter()
    rt = jaxatt.fit("nlio", None, "nlio-case1", start=wrong, tune=noise, steps=2 * args.steps, **kw)
    rd = jaxatt.fit("nlio", None, "nlio-case1", tune=noise, steps=2 * args.steps, **kw)
    fit_s = time.perf_counter() - t0
    default = st.setup("nlio", **base).params
    e_def = rms_deg("nlio", default, base)
    print("NLIO-TV (nlio-case1):", flush=True)
    rows = [
        row("default (paper gains, true Q, R)", e_def),
        row("start (noise 10x off)", rms_deg("nlio", wrong(default), base), e_def),
        row("learnt from the 10x-off start", rms_deg("nlio", rt.params, base), e_def),
        row("learnt from the defaults", rms_deg("nlio", rd.params, base), e_def),
    ]
    out["observers"]["nlio-tv"] = {
        "rows": rows,
        "fit_wall_s": fit_s,
        "learnt_from_start": {f: np.asarray(getattr(rt.params, f)).tolist() for f in noise},
        "learnt_from_defaults": {f: np.asarray(getattr(rd.params, f)).tolist() for f in noise},
        "default": {f: np.asarray(getattr(default, f)).tolist() for f in noise},
    }
    path = C.write_results("noise-learning", {"settings": vars(args), **out}, out_dir=args.out, meta=meta)
    print(f"results written to {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
