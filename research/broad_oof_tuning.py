"""Out-of-fold tuning of the classic filters on BROAD (issue 18, item 4): for each registered observer named,
2-fold cross-validation on the trials of ``--data-dir`` (``jaxatt.data.broad.stratified_folds``): its gains are
learnt with ``jaxatt.fit`` on one fold (from its untuned default gains, never from shipped ones, float32,
``--steps`` Adam steps, cosine decay) and every trial of the other fold is scored with them
(``jaxatt.broad_score``, float64), beside the same observer with its default gains. Gains files go to
``--folds-dir`` as ``<name>_broad_fold<k>.json`` (k = the fold tuned on); an existing file is reused
unless ``--retrain``.

Usage:
  python research/broad_oof_tuning.py --observers vqf madgwick mahony [--steps 40] [--folds-dir DIR] [--diagonal]
  python research/broad_oof_tuning.py --observers robust [--freeze mag_delay]

``--all`` also fits on every trial with the same recipe (``<tag>_broad_all.json``: what would ship).
``--diagonal`` learns the SPD gains (e.g. the MEKF's noise covariances) as diagonal matrices. ``--freeze`` keeps
the named gains at their defaults (gains files ``<name>_freeze-<gains>_broad_fold<k>``). ``--delay-start FILE``
(robust AHRS; FILE written by research/broad_sensor_delays.py) starts ``mag_delay`` of each fit at the median
measured delay of the magnetometer behind the gyro over that fit's *training* trials (files
``<tag>_delaystart_broad_fold<k>``).

Writes research/results/broad-oof-tuning-<host>-<UTC>.json (per trial and per group, default and tuned) and
prints the group means.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "benchmarks"))
sys.path.insert(0, str(HERE.parent))

import _common as C  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data-dir", default=str(C.REPO_ROOT.parent / "shared" / "data" / "broad"))
    ap.add_argument("--observers", nargs="+", default=["vqf", "madgwick", "mahony"])
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--lr", type=float, default=0.05)
    ap.add_argument("--folds-dir", default=str(HERE / "results" / "broad_folds"))
    ap.add_argument("--retrain", action="store_true", help="fit again even when the fold's gains file exists")
    ap.add_argument(
        "--diagonal",
        action="store_true",
        help="learn SPD gains (e.g. noise covariances) as diagonal matrices; gains files <name>_diag_broad_fold<k>",
    )
    ap.add_argument("--freeze", nargs="+", default=[], help="gains kept at their defaults")
    ap.add_argument(
        "--all", action="store_true", help="also fit on every trial (the same recipe): <tag>_broad_all.json, to ship"
    )
    ap.add_argument(
        "--delay-start",
        default=None,
        help="results of broad_sensor_delays.py: start mag_delay at the training trials' median measured delay",
    )
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import jaxatt
    from jaxatt.api import TrialScore, group_means
    from jaxatt.data import broad
    from jaxatt.fitting import gainsfile

    meta = C.metadata(sys.argv if argv is None else ["broad_oof_tuning.py"] + list(argv))
    names = broad.resolve_trials(args.data_dir)
    folds = broad.stratified_folds(names, broad.load_trial_info(args.data_dir))
    trials = {tr.name: tr for tr in broad.load(args.data_dir, names)}
    folds_dir = pathlib.Path(args.folds_dir)
    folds_dir.mkdir(parents=True, exist_ok=True)
    results = {}
    from jaxatt.fitting import parametrize
    from jaxatt.observers import registry

    delays = None
    if args.delay_start:
        measured = json.loads(pathlib.Path(args.delay_start).read_text())["trials"]
        delays = {n: float(v["mag_behind_gyr_ms"]) for n, v in measured.items()}
    for name in args.observers:
        entry = registry.get(name)
        diag = {
            g.field: parametrize.SPD(structure="diagonal") for g in entry.gains if g.constraint == "spd" and g.tuned
        }
        tag = f"{name}_diag" if args.diagonal else name
        if args.freeze:
            tag += "_freeze-" + "-".join(args.freeze)
        if args.delay_start:
            tag += "_delaystart"
        start = entry.default_params(jnp.float32)  # untuned: a shipped gains file may have seen every trial
        default = jaxatt.broad_score(name, entry.default_params(jnp.float64), list(trials.values()))
        tuned, fits = {}, []

        def fit_once(path, train, label, name=name, start=start, diag=diag):
            """Fit on ``train`` into ``path`` (unless it exists and --retrain is off); the wall time (s)."""
            t0 = time.perf_counter()
            if args.retrain or not path.exists():
                print(f"{name}: fitting on {label} ({len(train)} trials) -> {path}", flush=True)
                if delays is not None:  # the training trials' own measured delay: nothing from the test fold
                    start = start._replace(mag_delay=jnp.float32(np.median([delays[n] for n in train]) / 1e3))
                    print(f"  mag_delay starts at {1e3 * float(start.mag_delay):.2f} ms", flush=True)
                jaxatt.fit(
                    name,
                    start,
                    [trials[n] for n in train],
                    steps=args.steps,
                    lr=args.lr,
                    dtype="float32",
                    transforms=diag if args.diagonal else None,
                    freeze=tuple(args.freeze),
                    out=str(path),
                    overwrite=True,
                )
            return time.perf_counter() - t0

        for k, train in enumerate(folds, start=1):
            path = folds_dir / f"{tag}_broad_fold{k}.json"
            wall = fit_once(path, train, f"fold {k}")
            payload = gainsfile.read(path)
            fits.append(
                {
                    "fold": k,
                    "train": train,
                    "gains": str(path),
                    "fit_wall_s": wall,
                    "status": payload.get("status"),
                    "gains_values": payload.get("gains"),
                }
            )
            test = [trials[n] for n in names if n not in train]
            sc = jaxatt.broad_score(name, gainsfile.read_params(path, name, dtype=jnp.float64), test)
            tuned.update(sc.trials)
        if args.all:
            path = folds_dir / f"{tag}_broad_all.json"
            wall = fit_once(path, names, "all trials")
            fits.append({"fold": "all", "train": names, "gains": str(path), "fit_wall_s": wall})
        rows = {
            "default": {n: s._asdict() for n, s in default.trials.items()},
            "tuned_oof": {n: s._asdict() for n, s in tuned.items()},
        }
        groups = {
            "default": {g: s._asdict() for g, s in default.groups.items()},
            "tuned_oof": {
                g: s._asdict() for g, s in group_means({n: TrialScore(*s) for n, s in tuned.items()}).items()
            },
        }
        results[name] = {"trials": rows, "groups": groups, "fits": fits}
        d, t = groups["default"], groups["tuned_oof"]
        print(
            f"{name}: default {d['undisturbed']['total_rmse_deg']:.2f} / {d['disturbed']['total_rmse_deg']:.2f}, "
            f"tuned out of fold {t['undisturbed']['total_rmse_deg']:.2f} / {t['disturbed']['total_rmse_deg']:.2f} deg",
            flush=True,
        )
    path = C.write_results(
        "broad-oof-tuning",
        {"settings": vars(args), "folds": folds, "results": results, "data": broad.ATTRIBUTION},
        out_dir=args.out,
        meta=meta,
    )
    print(f"results written to {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
