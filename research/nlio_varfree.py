"""nlio-case1 tuned on the variance-free loss (issue 20 items 2 and 4): the NLIO-FG gains that
``jaxatt tune --experiment nlio-case1 --objective varfree --optimizer lbfgs`` finds from the paper's gains, against
the paper's gains, the shipped Monte Carlo-tuned gains (jaxatt/data/gains/nlio-case1.json) and the filtering floor.

* Predict: variance-free RMS and mean angle error over the steady window 300-500 s of each gain set
  (:func:`jaxatt.fitting.varfree.predict_study`, kind ``angle_sq``), as ratios to the floor of
  research/results/floor-*.json (the Kalman filter of the linearised problem, research/floor.py).
* Evaluate (held out): Monte Carlo of every gain set on the same ``--runs`` runs of seed ``--seed`` (never used in
  tuning: the variance-free loss draws no runs), the study's random initial attitudes included: per run the
  steady-state mean angle error and the transient (0-200 s) mean absolute roll / pitch / yaw errors; paired
  changes against the paper's gains with standard errors.

Tuning command (40 L-BFGS steps, 30-70 s each here):
  jaxatt tune --experiment nlio-case1 --objective varfree --optimizer lbfgs --steps 40 --out GAINS
Usage: python research/nlio_varfree.py --gains GAINS [--runs 300] [--seed 4000]
Writes research/results/nlio-varfree-<host>-<UTC>.json and prints the table.
"""

from __future__ import annotations

import argparse
import datetime
import math
import pathlib
import socket
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np

from jaxatt import io, montecarlo, studies
from jaxatt.fitting import gainsfile
from jaxatt.fitting import varfree as V

RESULTS = HERE / "results"
SHIPPED = HERE.parent / "jaxatt" / "data" / "gains" / "nlio-case1.json"
STEADY = (300.0, 500.0)


def floor_values() -> dict:
    """The newest research/results/floor-*.json's nlio-case1 causal floor (RMS and mean angle, deg)."""
    path = sorted(RESULTS.glob("floor-*.json"))[-1]
    f = io.read_json(path)["cases"]["nlio-case1"]["floor"]["filter"]
    return {"file": path.name, "rms_deg": f["rms_deg"], "mean_deg": f["mean_deg"]}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gains", required=True, help="gains file of the variance-free tuning")
    ap.add_argument("--runs", type=int, default=300)
    ap.add_argument("--seed", type=int, default=4000)
    args = ap.parse_args(argv)
    st = studies.get("nlio-case1")
    s = st.setup()
    sets = {
        "paper": s.params,
        "shipped (Monte Carlo)": gainsfile.read_params(str(SHIPPED), "nlio-fg", base=s.params),
        "varfree (L-BFGS)": gainsfile.read_params(args.gains, "nlio-fg", base=s.params),
    }
    floor = floor_values()
    out = {
        "what": "nlio-case1 NLIO-FG: paper, Monte Carlo-tuned and variance-free-tuned gains against the floor",
        "gains_file": args.gains,
        "tuning": {
            k: gainsfile.read(args.gains)["settings"].get(k) for k in ("objective", "optimizer", "steps", "loss")
        },
        "floor": floor,
        "environment": io.environment(),
        "predicted": {},
        "heldout": {"runs": args.runs, "seed": args.seed, "sets": {}},
    }
    path = RESULTS / f"nlio-varfree-{socket.gethostname()[:12]}-{datetime.datetime.utcnow():%Y%m%dT%H%M%SZ}.json"
    for label, p in sets.items():
        t0 = time.perf_counter()
        r = V.predict_study("nlio-case1", p, kind="angle_sq", windows=(("steady", *STEADY),), errors=False)
        w = r["windows"]["steady"]
        out["predicted"][label] = {
            "rms_deg": w["rms_deg"],
            "mean_deg": w["mean_deg"],
            "ratio_rms": w["rms_deg"] / floor["rms_deg"],
            "ratio_mean": w["mean_deg"] / floor["mean_deg"],
            "wall_s": time.perf_counter() - t0,
        }
        print(f"predicted {label}: {out['predicted'][label]}", flush=True)
    per_run = {}
    for label, p in sets.items():
        t0 = time.perf_counter()
        res = montecarlo.monte_carlo(
            s.scenario,
            s.observer,
            p,
            runs=args.runs,
            duration=s.duration,
            dt=s.dt,
            seed=args.seed,
            errors_fn=s.errors_fn,
            window_start=s.window_start,
            windows=st.windows(st.config()),
            hold=s.hold,
            init_params=st.init_params(st.config()),
        )
        per_run[label] = {k: np.asarray(v, float) for k, v in res.per_run.items()}
        print(f"{label}: {args.runs} runs in {time.perf_counter() - t0:.0f} s", flush=True)
    base = per_run["paper"]["mean_angle_error_deg"]
    for label, m in per_run.items():
        v = m["mean_angle_error_deg"]
        d = v - base
        e = {
            "mean_angle_error_deg": float(v.mean()),
            "se": float(v.std(ddof=1) / math.sqrt(len(v))),
            "ratio_mean_to_floor": float(v.mean() / floor["mean_deg"]),
            "paired_change_vs_paper": float(d.mean() / base.mean()),
            "paired_change_se": float(d.std(ddof=1) / math.sqrt(len(d)) / base.mean()),
            "share_of_runs_better_than_paper": float(np.mean(d < 0)),
        }
        for k in sorted(m):
            if k.startswith("mae_transient_") or k.startswith("max_angle"):
                e[k] = float(np.mean(m[k]))
        out["heldout"]["sets"][label] = e
    io.write_json(path, out)
    print(
        f"\nfloor (causal Kalman filter, {floor['file']}): RMS {floor['rms_deg']:.4f} mean {floor['mean_deg']:.4f} deg"
    )
    head = ("gains", "pred RMS", "x floor", "MC mean", "x floor", "vs paper", "transient MAE r/p/y")
    print(f"{head[0]:24s} " + " ".join(f"{h:>9s}" for h in head[1:-1]) + f" {head[-1]:>22s}")
    for label in sets:
        pr, h = out["predicted"][label], out["heldout"]["sets"][label]
        tr = "/".join(f"{h.get('mae_transient_' + a, float('nan')):.2f}" for a in ("roll", "pitch", "yaw"))
        print(
            f"{label:24s} {pr['rms_deg']:9.4f} {pr['ratio_rms']:8.3f} {h['mean_angle_error_deg']:9.4f} "
            f"{h['ratio_mean_to_floor']:8.3f} {100 * h['paired_change_vs_paper']:+8.1f}% {tr:>22s}"
        )
    print(f"written {path.relative_to(HERE.parent)}")


if __name__ == "__main__":
    main()
