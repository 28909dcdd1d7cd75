"""Acceptance study of gradient tuning (issue 6): tune a study's gains on at most 64 training seeds,
then compare tuned and paper gains on 100 held-out seeds.

Steps (one study per call):

1. ``jaxatt.fitting.fitter.fit(None, None, study, ...)``: Adam on the gains the registry tunes by default
   (batista-ges alpha1/alpha2 Table-1 schedules + the 9x9 SPD gain_z; batista-so3 alpha0 ... alpha4 with
   alpha1/alpha2 schedules; NLIO-FG Kp, kv, K1, K2), loss = mean squared rotation-angle error over the
   steady-state window t >= 2400 s of a 3600-s run (by default), averaged over a minibatch of training runs
   (seed ``--seed``, run indices 0 ... train_runs-1); early stopping on validation runs (the next ``--val-runs``
   indices of the same seed). The gains file (``jaxatt.fitting.gainsfile``) is written as the loop goes
   (``--gains-out``; an existing file is not replaced).
2. Held-out evaluation: ``jaxatt.montecarlo.monte_carlo`` of ``--eval-runs`` runs of another base seed
   (``--eval-seed``; disjoint from every training / validation key) with the paper's and the tuned gains, the
   same runs for both (paired), with a decimated angle-error trace.
3. Criteria, both reported: (A) steady-state mean angle error (per-run mean over t >= window start, averaged
   over runs) lowered by at least 20 %; (B) the tuned gains reach the paper gains' steady-state error at least
   twice as fast: settling time = first time after which the run-averaged angle error, smoothed over
   ``--smooth-s``, stays below (1 + tol) x the paper gains' steady-state mean error (tol = 10 %; 5/25/50 %
   also listed).

Writes ``research/results/tune_acceptance-<experiment>-<host>-<UTC>.json`` (settings, tuning history,
gains, both metric sets in the ``jaxatt reproduce`` layout, criteria) and prints a summary.

Usage:
  python research/tune_acceptance.py --experiment batista-ges            # full scale (hours on 2 CPU cores)
  python research/tune_acceptance.py --experiment batista-so3 --steps 20 --batch-runs 8
  python research/tune_acceptance.py --experiment batista-ges --gains G.json   # evaluation only
  python research/tune_acceptance.py --experiment batista-ges --gains jaxatt/data/gains/batista-ges-growing.json \
      --eval-seed 2 --eval-runs 300                                       # the shipped growing-memory gains
  python research/tune_acceptance.py --experiment batista-ges --refine-schedule 900 1200 ... 3300 \
      --schedule-from 720 --diagonal-spd --loss angle [--start G.json]   # tune a refined schedule (see
      research/ges_refined_start.py for the growing-memory start)
  python research/tune_acceptance.py --experiment batista-so3 --duration 900 ...  # reduced scale (labelled)
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "benchmarks"))

import _common as C  # noqa: E402

RESULTS_DIR = HERE / "results"
TOLERANCES = (0.05, 0.10, 0.25, 0.50)


def settling_time(t, curve, target, smooth_s):
    """First time after which the moving average (window ``smooth_s``) of ``curve`` stays <= target (None if
    never)."""
    import numpy as np

    t = np.asarray(t, float)
    curve = np.asarray(curve, float)
    dt = float(np.median(np.diff(t)))
    w = max(1, int(round(smooth_s / dt)))
    cs = np.concatenate([[0.0], np.cumsum(curve)])
    i = np.arange(len(curve))
    lo = np.maximum(0, i - w + 1)
    sm = (cs[i + 1] - cs[lo]) / (i + 1 - lo)  # trailing moving average
    above = np.nonzero(sm > target)[0]
    if len(above) == 0:
        return float(t[0])
    last = above[-1]
    return None if last == len(t) - 1 else float(t[last + 1])


def _trace(truth, out, errors, angle_deg):
    """Decimated trace: time and angle error (module level: the jitted runner is cached on it)."""
    return {"t": truth.t, "angle_deg": angle_deg}


def evaluate_pair(s, paper_params, tuned_params, runs, seed, chunk, trace_every):
    import numpy as np

    from jaxatt import montecarlo

    out = {}
    for label, p in (("paper", paper_params), ("tuned", tuned_params)):
        t0 = time.perf_counter()
        res = montecarlo.monte_carlo(
            s.scenario,
            s.observer,
            p,
            runs=runs,
            duration=s.duration,
            dt=s.dt,
            seed=seed,
            errors_fn=s.errors_fn,
            window_start=s.window_start,
            hold=s.hold,
            chunk=chunk,
            trace_every=trace_every,
            trace_fn=_trace,
            windows=s.windows,
            init_params=s.init_params,
        )
        wall = time.perf_counter() - t0
        print(
            f"  held-out {label}: {runs} runs in {wall:.0f} s, steady mean angle error "
            f"{np.mean(res.per_run['mean_angle_error_deg']):.4f} deg",
            flush=True,
        )
        out[label] = (res, wall)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument(
        "--experiment", required=True, choices=["batista-ges", "batista-so3", "nlio-case1", "nlio-case2", "nlio-case3"]
    )
    ap.add_argument("--duration", type=float, default=None, help="horizon, s (default the paper's 3600)")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--train-runs", type=int, default=64)
    ap.add_argument("--batch-runs", type=int, default=8)
    ap.add_argument("--val-runs", type=int, default=16)
    ap.add_argument("--val-every", type=int, default=5)
    ap.add_argument("--patience", type=int, default=3)
    ap.add_argument("--lr", type=float, default=0.1)
    ap.add_argument("--loss", default="angle_sq", choices=["angle_sq", "angle", "chordal"])
    ap.add_argument(
        "--diagonal-spd",
        action="store_true",
        help="tune only the diagonal of SPD gains (batista-ges gain_z: 9 numbers instead of 45)",
    )
    ap.add_argument(
        "--refine-schedule",
        type=float,
        nargs="+",
        default=(),
        metavar="T",
        help="extra switch times (s) inserted into the gain schedules before tuning (the start observer "
        "is the paper's; the tuner may vary the gains on the new intervals)",
    )
    ap.add_argument(
        "--start", default=None, metavar="G.json", help="start tuning from these gains (default: the paper's)"
    )
    ap.add_argument(
        "--schedule-from",
        type=float,
        default=None,
        metavar="T",
        help="tune only the schedule intervals that start at or after T s (earlier ones keep the paper's values)",
    )
    ap.add_argument(
        "--family-basis",
        action="store_true",
        help="batista-ges: tune 8 numbers that move the schedules and gain_z through fixed shapes "
        "(research/ges_refined_start.py family_transforms; use with --refine-schedule)",
    )
    ap.add_argument("--freeze", nargs="*", default=(), help="gains kept at the paper's values")
    ap.add_argument("--seed", type=int, default=0, help="base seed of the training and validation runs")
    ap.add_argument("--eval-runs", type=int, default=100)
    ap.add_argument("--eval-seed", type=int, default=1, help="base seed of the held-out runs")
    ap.add_argument("--eval-chunk", type=int, default=100)
    ap.add_argument("--trace-every", type=int, default=500, help="steps between trace samples (divides 1000)")
    ap.add_argument("--smooth-s", type=float, default=60.0)
    ap.add_argument("--gains", default=None, help="evaluate these gains (skip tuning)")
    ap.add_argument(
        "--gains-out",
        default=None,
        help="gains file written while tuning (default <--out>/gains-<experiment>.json; must not exist)",
    )
    ap.add_argument("--out", default=str(RESULTS_DIR))
    args = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from jaxatt import io, studies
    from jaxatt.fitting import fitter, gainsfile
    from jaxatt.fitting import parametrize as P
    from jaxatt.observers import registry

    meta = C.metadata(sys.argv if argv is None else ["tune_acceptance.py"] + list(argv))
    cfg = {} if args.duration is None else {"duration": args.duration}
    s = studies.get(args.experiment).setup(**cfg)
    gains_decl = registry.get(s.entry).gains
    reduced = s.duration != (3600.0 if args.experiment.startswith("batista") else 500.0)
    t_start = time.perf_counter()
    tuning = None
    if args.gains:
        payload = gainsfile.read(args.gains)
        if payload["observer"] != s.entry or payload.get("study") not in (None, args.experiment):
            ap.error(
                f"--gains {args.gains} holds gains of {payload['observer']} ({payload.get('study')}), not of "
                f"{args.experiment}"
            )
        tuned = gainsfile.apply(s.params, payload["gains"], source=args.gains)
        gains_path = args.gains
        # jaxatt 0.2's keys, or 0.1's (best_val_loss, start_val_loss, tuning)
        tuning = {
            "status": payload.get("status"),
            "best_step": payload.get("best_step"),
            "best_val_loss": payload.get("best_loss", payload.get("best_val_loss")),
            "start_val_loss": payload.get("start_loss", payload.get("start_val_loss")),
            "tuning": payload.get("settings", payload.get("tuning")),
            "history": payload.get("history"),
        }
    else:
        gains_path = args.gains_out or str(pathlib.Path(args.out) / f"gains-{args.experiment}.json")
        masks = {}
        if args.diagonal_spd:
            for g in gains_decl:
                if g.constraint == "spd" and g.field not in args.freeze:
                    masks[g.field] = P.SPD.diagonal_mask(int(np.shape(getattr(s.params, g.field))[0]))
        if (args.schedule_from is not None or args.family_basis) and not hasattr(s.params, "switch_times"):
            ap.error(f"--schedule-from / --family-basis: {s.entry} has no gain schedule")
        # switch times of the tuned schedules (the paper's plus --refine-schedule); NLIO-FG has none
        times = (
            np.unique(np.concatenate([np.asarray(s.params.switch_times, float), args.refine_schedule]))
            if hasattr(s.params, "switch_times")
            else None
        )
        if args.schedule_from is not None:
            for g in gains_decl:
                if g.constraint == "schedule" and g.field not in args.freeze:
                    masks[g.field] = P.schedule_mask_from(times, args.schedule_from)
        transforms = None
        if args.family_basis:
            if args.experiment != "batista-ges" or masks:
                ap.error("--family-basis is for batista-ges, without --diagonal-spd / --schedule-from")
            from ges_refined_start import family_transforms

            transforms = family_transforms(times)
        t0 = time.perf_counter()
        res = fitter.fit(
            None,
            None,
            args.experiment,
            steps=args.steps,
            train_runs=args.train_runs,
            out=gains_path,
            seed=args.seed,
            batch=args.batch_runs,
            val_runs=args.val_runs,
            val_every=args.val_every,
            patience=args.patience,
            lr=args.lr,
            loss=args.loss,
            config=cfg,
            freeze=tuple(args.freeze),
            masks=masks or None,
            refine_schedule=args.refine_schedule,
            start=args.start,
            transforms=transforms,
            quiet=False,
        )
        tuned = res.params
        tuning = {
            "status": res.status,
            "best_step": res.best_step,
            "best_val_loss": res.best_loss,
            "start_val_loss": res.start_loss,
            "history": res.history,
            "wall_s": time.perf_counter() - t0,
        }
    if args.eval_seed == args.seed:
        print("warning: --eval-seed equals --seed: held-out runs may overlap training runs", file=sys.stderr)

    print(f"held-out evaluation: {args.eval_runs} runs of seed {args.eval_seed}, {s.duration:g} s", flush=True)
    ev = evaluate_pair(s, s.params, tuned, args.eval_runs, args.eval_seed, args.eval_chunk, args.trace_every)
    (rp, wp), (rt, wt) = ev["paper"], ev["tuned"]
    ss_p = np.asarray(rp.per_run["mean_angle_error_deg"], float)
    ss_t = np.asarray(rt.per_run["mean_angle_error_deg"], float)
    diff = ss_t - ss_p
    improvement = 1.0 - ss_t.mean() / ss_p.mean()
    t = np.asarray(rp.traces["t"][0], float)
    curve_p = np.asarray(rp.traces["angle_deg"], float).mean(0)
    curve_t = np.asarray(rt.traces["angle_deg"], float).mean(0)
    settle = []
    for tol in TOLERANCES:
        target = (1 + tol) * ss_p.mean()
        tp = settling_time(t, curve_p, target, args.smooth_s)
        tt = settling_time(t, curve_t, target, args.smooth_s)
        settle.append(
            {
                "tolerance": tol,
                "target_deg": target,
                "paper_s": tp,
                "tuned_s": tt,
                "speedup": (tp / tt) if (tp and tt) else None,
            }
        )
    s10 = next(x for x in settle if x["tolerance"] == 0.10)
    crit_a = improvement >= 0.20
    crit_b = bool(s10["speedup"] is not None and s10["speedup"] >= 2.0)
    summary = {
        "experiment": args.experiment,
        "duration_s": s.duration,
        "window_start_s": s.window_start,
        "reduced_scale": reduced,
        "train_runs": args.train_runs,
        "eval_runs": args.eval_runs,
        "eval_seed": args.eval_seed,
        "steady_mean_angle_error_deg": {"paper_gains": float(ss_p.mean()), "tuned_gains": float(ss_t.mean())},
        "steady_improvement": float(improvement),
        "paired_difference_deg": {
            "mean": float(diff.mean()),
            "stderr": float(diff.std(ddof=1) / np.sqrt(len(diff))),
            "fraction_of_runs_better": float(np.mean(diff < 0)),
        },
        "settling_10pct": s10,
        "criterion_A_20pct_lower_steady_error": bool(crit_a),
        "criterion_B_twice_as_fast": crit_b,
    }
    print(
        f"\n{args.experiment}{' [REDUCED SCALE]' if reduced else ''}: steady-state mean angle error "
        f"(t >= {s.window_start:g} s, {args.eval_runs} held-out runs): paper gains {ss_p.mean():.4f} deg, tuned "
        f"{ss_t.mean():.4f} deg -> {100 * improvement:.1f} % lower (paired difference {diff.mean():.4f} +- "
        f"{summary['paired_difference_deg']['stderr']:.4f} deg; tuned better in {100 * np.mean(diff < 0):.0f} % "
        f"of runs)"
    )
    for x in settle:
        print(
            f"  time to stay within {100 * x['tolerance']:.0f} % of the paper's steady error "
            f"({x['target_deg']:.4f} deg): paper gains {x['paper_s']} s, tuned {x['tuned_s']} s"
            + (f", {x['speedup']:.2f}x faster" if x["speedup"] else "")
        )
    print(
        f"criterion A (>= 20 % lower steady error): {'MET' if crit_a else 'not met'}; criterion B (>= 2x faster "
        f"to the paper's steady error, 10 % band): {'MET' if crit_b else 'not met'}"
    )
    data = {
        "settings": vars(args),
        "summary": summary,
        "settling": settle,
        "tuning": tuning,
        "gains_path": gains_path,
        "gains": gainsfile.gains_to_dict(tuned, gains_decl),
        "paper_gains": gainsfile.gains_to_dict(s.params, gains_decl),
        "metrics": io.summarise(rt.per_run),
        "paper_gains_metrics": io.summarise(rp.per_run),
        "curves": {
            "t_s": t.tolist(),
            "paper_mean_angle_deg": curve_p.tolist(),
            "tuned_mean_angle_deg": curve_t.tolist(),
        },
        "timing": {"eval_paper_s": wp, "eval_tuned_s": wt, "total_s": time.perf_counter() - t_start},
        "notes": list(s.notes),
    }
    path = C.write_results(f"tune_acceptance-{args.experiment}", data, args.out, meta)
    print(f"results written to {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
