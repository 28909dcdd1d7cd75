"""Command line: ``jaxatt reproduce EXPERIMENT`` and ``jaxatt simulate --observer NAME``.

Every run enables float64 in JAX: the simulated truth and sensors are always computed in float64, and the
observer runs in float64 unless ``--float32`` is given.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import List, Optional

import numpy as np

__all__ = ["main"]


def _floats(n: int):
    def parse(s: str):
        try:
            v = [float(x) for x in s.replace(" ", "").split(",") if x != ""]
        except ValueError as e:
            raise argparse.ArgumentTypeError(f"expected {n} comma-separated numbers, got {s!r}") from e
        if len(v) != n:
            raise argparse.ArgumentTypeError(f"expected {n} comma-separated numbers, got {len(v)}: {s!r}")
        if not all(np.isfinite(v)):
            raise argparse.ArgumentTypeError(f"numbers must be finite, got {s!r}")
        return tuple(v)

    return parse


def _positive(s: str) -> float:
    v = float(s)
    if not np.isfinite(v) or v <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {s}")
    return v


def _nonneg(s: str) -> float:
    v = float(s)
    if not np.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"must be a non-negative number, got {s}")
    return v


def _runs(s: str) -> int:
    v = int(s)
    if v < 1:
        raise argparse.ArgumentTypeError(f"--runs must be >= 1, got {s}")
    return v


SIMULATED = ("batista-ges", "batista-so3")
SIMULATE_OBSERVERS = SIMULATED + ("complementary",)
NLIO_CASES = ("nlio-case1", "nlio-case2", "nlio-case3", "nlio-case4", "nlio-simb")


def _experiment(name: str):
    from .experiments import REGISTRY

    return REGISTRY[name]


def _common(p: argparse.ArgumentParser):
    p.add_argument("--runs", type=_runs, default=100, help="Monte Carlo runs (default 100)")
    p.add_argument("--duration", type=_positive, default=None, help="simulated time per run, s (default 3600)")
    p.add_argument("--seed", type=int, default=0, help="base seed; run k uses fold_in(PRNGKey(seed), k)")
    p.add_argument("--hold", choices=["zoh", "linear"], default="zoh",
                   help="sensor samples held over the RK4 step (zoh, default) or interpolated to the stage times")
    p.add_argument("--x1-init", choices=["first-sample", "zero"], default=None,
                   help="batista-ges: x1^(0) = first magnetometer sample (default; reproduces the paper) or zero "
                        "(literal)")
    p.add_argument("--m-init", choices=["rescaled", "first-sample"], default=None,
                   help="batista-so3: m^(0) = first sample rescaled to |I_m| (default; Theorem 1) or the raw first "
                        "sample (literal)")
    p.add_argument("--integrator", choices=["lie", "rk4"], default=None,
                   help="batista-so3: RKMK-4 on SO(3) (default) or plain RK4 on the 15 numbers (the paper's)")
    prec = p.add_mutually_exclusive_group()
    prec.add_argument("--float32", action="store_true", help="run the observer in float32")
    prec.add_argument("--float64", action="store_true", help="run the observer in float64 (default)")
    p.add_argument("--chunk", type=_runs, default=250, help="runs vmapped together (memory vs speed)")
    p.add_argument("--json", default=None, help="write results JSON here (updated after every chunk)")
    p.add_argument("--plot", default=None, help="write a PNG of the paper's convergence figures here")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="jaxatt", description="Batched, differentiable attitude observers in JAX.")
    sub = ap.add_subparsers(dest="command", required=True)

    rp = sub.add_parser("reproduce", help="run a paper's simulation study and compare with its published numbers")
    rp.add_argument("experiment", choices=list(SIMULATED) + list(NLIO_CASES))
    rp.add_argument("--aggressive", action="store_true", help="the 20x faster angular velocity (Section IV / 4)")
    _common(rp)

    sp = sub.add_parser("simulate", help="run an observer on a scenario you define with flags")
    sp.add_argument("--observer", choices=list(SIMULATE_OBSERVERS), required=True)
    sp.add_argument("--trajectory", choices=["slow", "aggressive"], default="slow")
    sp.add_argument("--rate-scale", type=float, default=1.0, help="multiplies the angular-velocity profile")
    sp.add_argument("--latitude", type=float, default=None, help="latitude in degrees (north positive)")
    sp.add_argument("--reference", type=_floats(3), default=None,
                    help="inertial vector measured by the vector sensor, X,Y,Z in nT, NED (default IGRF-11 Lisbon)")
    sp.add_argument("--gyro-arw", type=_nonneg, default=4.0, help="gyro angle random walk, deg/h/sqrt(Hz)")
    sp.add_argument("--gyro-bias", type=_floats(3), default=(0.0, 0.0, 0.0), help="gyro bias X,Y,Z rad/s")
    sp.add_argument("--mag-noise", type=_nonneg, default=150.0, help="vector-sensor noise std, nT")
    sp.add_argument("--noise-scale", type=_nonneg, default=1.0, help="multiplies all noise (0 = noise-free)")
    sp.add_argument("--dt", type=_positive, default=0.01, help="sample period, s")
    sp.add_argument("--window-start", type=_nonneg, default=None, help="start of the steady-state window, s")
    sp.add_argument("--r0", type=_floats(9), default=None, help="initial R^ (9 numbers, row-major)")
    sp.add_argument("--r0-euler", type=_floats(3), default=None, help="initial R^ as ZYX roll,pitch,yaw in degrees")
    sp.add_argument("--x2-0", type=_floats(3), default=None, help="batista-ges: initial x2^, nT/s")
    sp.add_argument("--v0", type=_floats(3), default=None, help="batista-so3: initial v^, nT^2 rad/s")
    sp.add_argument("--epsilon", type=float, default=None,
                    help="batista-ges: Theorem-3 threshold on ||R^T R - I||_F, in (0,1) (default 0.5)")
    g = sp.add_argument_group("complementary (Trumpf et al. 2012) observer")
    g.add_argument("--scenario", choices=["rotating", "switching", "constant", "two-constant", "body-fixed"],
                   default="rotating", help="vector-measurement scenario (default rotating)")
    g.add_argument("--form", choices=["matrix", "quaternion"], default="matrix", help="eq. (10) or eq. (18)")
    g.add_argument("--gain", type=_positive, default=0.6, help="gain k_i = l_j of every measurement, 1/s")
    g.add_argument("--k-i", type=_nonneg, default=0.0, help="gyro-bias integral gain, 1/s (0 = no bias estimate)")
    g.add_argument("--gyro-noise", type=_nonneg, default=0.0, help="gyro white noise per sample, rad/s")
    g.add_argument("--vector-noise", type=_nonneg, default=0.0, help="noise per component of the unit vectors")
    _common(sp)

    tp = sub.add_parser("tune", help="tune an experiment's gains by gradient descent through the Monte Carlo scan")
    tp.add_argument("--experiment", required=True, help="batista-ges, batista-so3, ... (see jaxatt.tune)")
    tp.add_argument("--steps", type=int, default=100, help="optimiser steps")
    tp.add_argument("--train-runs", type=int, default=32, help="training seeds (at most 64 in the acceptance study)")
    tp.add_argument("--duration", type=_positive, default=None, help="simulated time per run, s")
    tp.add_argument("--seed", type=int, default=0)
    tp.add_argument("--lr", type=_positive, default=0.05)
    tp.add_argument("--refine-schedule", type=float, nargs="+", default=(), metavar="T",
                    help="extra switch times (s) for the experiment's gain schedules, tuned from the paper's values")
    tp.add_argument("--out", default="gains.json", help="gains + history JSON, rewritten as the loop goes")
    tp.add_argument("--quiet", action="store_true")

    vp = sub.add_parser("evaluate", help="Monte Carlo of an experiment with a gains file (same JSON as reproduce)")
    vp.add_argument("--experiment", required=True)
    vp.add_argument("--gains", default=None, help="gains JSON from jaxatt tune (default: the paper's gains)")
    vp.add_argument("--runs", type=_runs, default=100)
    vp.add_argument("--seed", type=int, default=1)
    vp.add_argument("--duration", type=_positive, default=None)
    vp.add_argument("--json", default=None)
    vp.add_argument("--quiet", action="store_true")

    bp = sub.add_parser("broad", help="run an observer on BROAD trials and print the BROAD metric")
    bp.add_argument("--data-dir", required=True, help="folder of BROAD .hdf5 trials (needs jaxatt[data])")
    bp.add_argument("--observer", default="robust", help="robust, mahony, complementary, ...")
    bp.add_argument("--gains", default=None, help="gains JSON from jaxatt broad-tune (default: shipped gains)")
    bp.add_argument("--trials", nargs="*", default=None, help="trial names or numbers (default: all)")
    bp.add_argument("--json", default=None)
    bp.add_argument("--float32", action="store_true")

    bt = sub.add_parser("broad-tune", help="learn an observer's gains on BROAD trials")
    bt.add_argument("--data-dir", required=True)
    bt.add_argument("--observer", default="robust")
    bt.add_argument("--trials", nargs="*", default=None, help="training trials (default: all)")
    bt.add_argument("--steps", type=int, default=150)
    bt.add_argument("--lr", type=_positive, default=0.05, help="Adam learning rate on log-gains")
    bt.add_argument("--init-gains", default=None, help="start from this gains JSON (default: untuned defaults)")
    bt.add_argument("--out", default="gains.json")

    ep = sub.add_parser("excitation", help="excitation / observability measures (Trumpf et al. Defs 3.3, 4.1, "
                                           "Lemmas 3.4, 4.2, conditions 6, 13) of a scenario or a log")
    src = ep.add_mutually_exclusive_group(required=True)
    src.add_argument("--scenario", choices=["rotating", "switching", "constant", "two-constant", "body-fixed"])
    src.add_argument("--log", help="CSV or NPZ log (jaxatt.data.logs): acc and mag vs constant references")
    ep.add_argument("--duration", type=_positive, default=60.0, help="simulated duration of a scenario, s")
    ep.add_argument("--dt", type=_positive, default=0.01, help="sample period of a scenario, s")
    ep.add_argument("--window", type=_positive, default=5.0, help="sliding window length T, s")
    ep.add_argument("--mag-ref", type=_floats(3), default=None,
                    help="log: magnetic reference in the log's navigation frame (any unit; only its direction is used)")
    ep.add_argument("--frame", choices=["NED", "ENU"], default="NED", help="log: navigation frame of --mag-ref")
    ep.add_argument("--threshold", type=_nonneg, default=0.05,
                    help="a window is reported as not exciting when lambda2 / T falls below this (default 0.05)")
    ep.add_argument("--json", default=None, help="write the measures per window here")
    ep.add_argument("--plot", default=None, help="write a PNG of the measures over time here")
    return ap


def _environment() -> dict:
    from .report import environment

    return environment()


def _summarise(per_run: dict) -> dict:
    out = {}
    for k, v in per_run.items():
        v = np.asarray(v, float)
        out[k] = {"mean": float(np.mean(v)), "std": float(np.std(v)), "min": float(np.min(v)),
                  "max": float(np.max(v)), "per_run": v.tolist()}
    return out


def _write_json(path: Optional[str], payload: dict):
    if not path:
        return
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(payload, f, indent=1)
    os.replace(tmp, path)  # atomic: an interrupted write never leaves a broken file


def _table(rows, values: dict, paper: dict, units: dict) -> str:
    lines = [f"{'quantity':34s} {'paper':>10s} {'measured':>12s} {'(std over runs)':>16s} {'ratio':>7s}"]
    for key, label in rows:
        if key not in paper and key not in units:
            continue
        m = units.get(key, "")
        meas = values.get(key)
        pv = paper.get(key)
        ratio = f"{meas['mean'] / pv:7.2f}" if (pv and meas) else ""
        lines.append(f"{label + (' [' + m + ']' if m else ''):34s} {pv if pv is not None else '-':>10} "
                     f"{meas['mean']:12.4g} {meas['std']:16.3g} {ratio}")
    return "\n".join(lines)



def _run(args, E, cfg, paper: dict, title: str) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from . import montecarlo, plot

    dtype = jnp.float32 if args.float32 else jnp.float64
    scn, obs = E.scenario(cfg), E.observer(cfg)
    params = E.params(cfg, dtype=jnp.float64)
    E.check_params(params)
    config = {k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg._asdict().items()}
    config.update(runs=args.runs, seed=args.seed, dtype=str(np.dtype(dtype)), chunk=args.chunk)
    base = {"experiment": title, "config": config, "environment": _environment(), "notes": E.notes(cfg)}
    t0 = time.perf_counter()

    def on_chunk(res):
        if not args.quiet:
            print(f"  {len(res.run_indices)}/{args.runs} runs done, {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        _write_json(args.json, {**base, "complete": res.complete, "runs_done": len(res.run_indices),
                                "metrics": _summarise(res.per_run), "timing": {"wall_s": time.perf_counter() - t0}})

    res = montecarlo.monte_carlo(scn, obs, params, runs=args.runs, duration=cfg.duration, dt=cfg.dt, seed=args.seed,
                                 errors_fn=E.errors, window_start=cfg.window_start, hold=cfg.hold, chunk=args.chunk,
                                 dtype=dtype, on_chunk=on_chunk)
    wall = time.perf_counter() - t0
    summary = _summarise(res.per_run)
    n_steps = int(round(cfg.duration / cfg.dt))
    timing = {"wall_s": wall, "runs": len(res.run_indices), "steps_per_run": n_steps,
              "run_steps_per_s": len(res.run_indices) * n_steps / wall}
    units = dict(E.UNITS, final_angle_error_deg="deg", max_angle_error_deg="deg")
    print(f"{title}: {len(res.run_indices)} runs x {cfg.duration:g} s at {1 / cfg.dt:g} Hz, observer in "
          f"{np.dtype(dtype).name}, window t >= {cfg.window_start:g} s"
          + ("" if res.complete else "  [INTERRUPTED: partial results]"))
    for n in base["notes"][:3]:
        print(f"  {n}")
    print(_table(E.TABLE_ROWS, summary, paper, units))
    print(f"final angle error: max over runs {summary['final_angle_error_deg']['max']:.4g} deg")
    print(f"wall {wall:.1f} s, {timing['run_steps_per_s']:.3g} run-steps/s (compile included)")
    payload = {**base, "complete": res.complete, "runs_done": len(res.run_indices), "metrics": summary,
               "paper": paper, "timing": timing}
    if args.plot:
        summ, trace, _ = montecarlo.simulate(scn, obs, params, duration=cfg.duration, dt=cfg.dt, seed=args.seed,
                                             errors_fn=E.errors, window_start=cfg.window_start, hold=cfg.hold,
                                             trace_every=10, dtype=dtype)
        plot.convergence_figure(trace, args.plot, title=f"{title} (run 0)", panels=E.PLOT_PANELS,
                                steady_from_s=cfg.window_start)
        print(f"plot written to {args.plot}")
        payload["plot"] = args.plot
    _write_json(args.json, payload)
    if args.json:
        print(f"results written to {args.json}")
    return 0 if res.complete else 130


def _observer_settings(args, E, name: str) -> dict:
    """Observer-specific flags mapped onto the experiment's Config; a flag of another observer is an error."""
    given = {"x1_init": None if args.x1_init is None else args.x1_init.replace("-", "_"),
             "m_init": None if args.m_init is None else args.m_init.replace("-", "_"),
             "integrator": args.integrator,
             "x2_0": getattr(args, "x2_0", None), "v_hat_0": getattr(args, "v0", None),
             "epsilon": getattr(args, "epsilon", None)}
    flags = {"x1_init": "--x1-init", "m_init": "--m-init", "integrator": "--integrator", "x2_0": "--x2-0",
             "v_hat_0": "--v0", "epsilon": "--epsilon"}
    kw = {}
    for field, v in given.items():
        if v is None:
            continue
        if field not in E.Config._fields:
            raise ValueError(f"{flags[field]} does not apply to {name}")
        kw[field] = v
    return kw


def _complementary_config(args, E, dur):
    kw = dict(scenario=args.scenario.replace("-", "_"), form=args.form, gain=args.gain, k_i=args.k_i,
              gyro_bias_deg_s=tuple(np.rad2deg(args.gyro_bias)), gyro_noise_std=args.gyro_noise,
              meas_noise_std=args.vector_noise, noise_scale=args.noise_scale, hold=args.hold, duration=dur, dt=args.dt,
              window_start=args.window_start if args.window_start is not None else 2.0 * dur / 3.0)
    if args.r0_euler is not None:
        kw["r_hat_0_euler_deg"] = args.r0_euler
    if args.r0 is not None:
        raise ValueError("--r0 does not apply to complementary; use --r0-euler")
    return E.Config(**kw)


def _excitation(args) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    from . import analysis

    if args.scenario:
        from .sim import references

        scn = references.make_scenario(args.scenario.replace("-", "_"))
        res = analysis.excitation_of_scenario(scn, duration=args.duration, dt=args.dt, window=args.window)
        source = f"scenario {args.scenario}, {args.duration:g} s at {1 / args.dt:g} Hz"
    else:
        from .data import logs
        from .observers import complementary as comp

        samples = logs.load_log(args.log)
        if samples.acc is None and samples.mag is None:
            raise ValueError("the log has neither acc nor mag columns")
        fields = tuple(f for f in ("acc", "mag") if getattr(samples, f) is not None)
        if "mag" in fields and args.mag_ref is None:
            raise ValueError("--mag-ref X,Y,Z is needed to analyse a magnetometer log")
        up = comp.UP_NED if args.frame == "NED" else comp.UP_ENU
        refs_ = [np.asarray(up, float)] if "acc" in fields else []
        if "mag" in fields:
            refs_.append(np.asarray(args.mag_ref, float))
        p = comp.default_params(len(refs_), 0, ref_inertial=np.stack(refs_))
        res = analysis.excitation_from_samples(samples, window=args.window, params=p, imu_fields=fields)
        source = f"log {args.log} ({', '.join(fields)}; references in {args.frame})"
    T = args.window
    lam = np.asarray(res.lambda2) / T
    bad = lam < args.threshold
    print(f"excitation of {source}: {len(lam)} windows of T = {T:g} s")
    rows = [("lambda2 / T  (Def. 3.3/4.1)", lam), ("lambda_min projector / T (Lemma 3.4/4.2)",
                                                   np.asarray(res.lambda_min_projector) / T),
            ("condition (6)/(13) / T", np.asarray(res.condition) / T)]
    print(f"{'measure':42s} {'min':>10s} {'median':>10s} {'max':>10s}")
    for label, v in rows:
        print(f"{label:42s} {np.min(v):10.4g} {np.median(v):10.4g} {np.max(v):10.4g}")
    if bad.any():
        t0 = np.asarray(res.t_start)[bad]
        print(f"NOT exciting (lambda2/T < {args.threshold:g}) in {bad.mean() * 100:.1f} % of the windows, "
              f"first at t = {t0[0]:.2f} s, last at t = {t0[-1]:.2f} s")
    else:
        print(f"exciting in every window (lambda2/T >= {args.threshold:g})")
    if args.json:
        _write_json(args.json, {"source": source, "window_s": T, "threshold": args.threshold,
                                "measures": {k: np.asarray(v).tolist() for k, v in res._asdict().items()},
                                "environment": _environment()})
        print(f"results written to {args.json}")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 3.2), constrained_layout=True)
        analysis.plot_excitation(res, ax=ax, threshold=args.threshold, title=f"excitation: {source}")
        fig.savefig(args.plot, dpi=110)
        plt.close(fig)
        print(f"plot written to {args.plot}")
    return 0


def _reproduce_nlio(args, name: str) -> int:
    """Section 5 of sensors2020 (NLO, NLIO-FG, NLIO-TV, MEKF): tables laid out like the paper's Tables 1-7."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from .experiments import nlio

    if args.aggressive or args.x1_init or args.m_init or args.integrator:
        print("jaxatt: error: --aggressive/--x1-init/--m-init/--integrator do not apply to the NLIO cases",
              file=sys.stderr)
        return 2
    kw = {}
    if args.duration is not None:
        kw["duration"] = args.duration
    try:
        nlio.reproduce(name, runs=args.runs, seed=args.seed, chunk=args.chunk, json_path=args.json,
                       plot_path=args.plot, quiet=args.quiet, dtype=jnp.float32 if args.float32 else None, **kw)
    except KeyboardInterrupt:
        print("jaxatt: interrupted (finished observers are in the JSON)", file=sys.stderr)
        return 130
    except ValueError as e:
        print(f"jaxatt: error: {e}", file=sys.stderr)
        return 2
    return 0


def _tools(args) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    if args.command == "tune":
        from . import tune

        tune.tune(args.experiment, steps=args.steps, train_runs=args.train_runs, out_path=args.out, seed=args.seed,
                  lr=args.lr, duration=args.duration, refine_schedule=args.refine_schedule, quiet=args.quiet)
        print(f"gains written to {args.out}")
        return 0
    if args.command == "evaluate":
        from . import tune

        tune.evaluate(args.experiment, args.gains, runs=args.runs, seed=args.seed, json_path=args.json,
                      duration=args.duration, quiet=args.quiet)
        return 0
    from . import broad_tune

    if args.command == "broad":
        broad_tune.broad_eval(args.data_dir, args.observer, gains_path=args.gains, json_path=args.json,
                              trials=args.trials, dtype="float32" if args.float32 else "float64")
        return 0
    broad_tune.broad_tune(args.data_dir, args.observer, trials=args.trials, out_path=args.out, steps=args.steps,
                          lr=args.lr, init_gains=args.init_gains)
    print(f"gains written to {args.out}")
    return 0


def main(argv: Optional[List[str]] = None) -> int:
    args = _parser().parse_args(argv)
    if args.command in ("tune", "evaluate", "broad", "broad-tune"):
        try:
            return _tools(args)
        except ValueError as e:
            print(f"jaxatt: error: {e}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print("jaxatt: interrupted (what was found so far is saved)", file=sys.stderr)
            return 130
    if args.command == "excitation":
        try:
            return _excitation(args)
        except ValueError as e:
            print(f"jaxatt: error: {e}", file=sys.stderr)
            return 2
    name = args.experiment if args.command == "reproduce" else args.observer
    if name in NLIO_CASES:
        return _reproduce_nlio(args, name)
    E = _experiment(name)
    dur = args.duration if args.duration is not None else E.DURATION
    try:
        obs_kw = _observer_settings(args, E, name)
        if args.command == "reproduce":
            traj = "aggressive" if args.aggressive else "slow"
            cfg = E.Config(trajectory=traj, hold=args.hold, duration=dur,
                           window_start=min(E.WINDOW_START, 2.0 * dur / 3.0), **obs_kw)
            return _run(args, E, cfg, E.PAPER[traj], f"{name} reproduce ({traj})")
        # simulate
        if name == "complementary":
            return _run(args, E, _complementary_config(args, E, dur), {}, f"{name} simulate ({args.scenario})")
        r0 = args.r0
        if args.r0_euler is not None:
            from . import so3

            r0 = tuple(np.asarray(so3.euler_zyx_to_matrix(*np.deg2rad(args.r0_euler))).reshape(9))
        kw = dict(trajectory=args.trajectory, rate_scale=args.rate_scale, gyro_arw_deg_h_rthz=args.gyro_arw,
                  mag_noise_nT=args.mag_noise, noise_scale=args.noise_scale, gyro_bias=args.gyro_bias,
                  r_hat_0=r0, hold=args.hold, duration=dur, dt=args.dt,
                  window_start=args.window_start if args.window_start is not None else min(E.WINDOW_START, 2.0 * dur / 3.0),
                  **obs_kw)
        if args.latitude is not None:
            if not -90.0 <= args.latitude <= 90.0:
                raise ValueError(f"--latitude must be in [-90, 90] degrees, got {args.latitude}")
            kw["latitude_deg"] = args.latitude
        if args.reference is not None:
            kw["reference_nT"] = args.reference
        return _run(args, E, E.Config(**kw), {}, f"{name} simulate")
    except ValueError as e:
        print(f"jaxatt: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaxatt: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
