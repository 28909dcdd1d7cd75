"""Pool several held-out evaluations of the same gains (research/tune_acceptance.py JSONs with disjoint
``--eval-seed``) into one acceptance number (issue 6).

Each file holds the paper's and the tuned gains on the same runs (paired). Pooled over the N runs of all files:
steady-state mean angle error of both (run-weighted means), the paired difference with its standard error
(from each file's standard error: SE = sqrt(sum n_i^2 SE_i^2) / N), criterion A (>= 20 % lower), and criterion
B recomputed on the run-weighted mean error curves (settling into the 10 % band of the pooled paper steady
error, the same moving-average rule as tune_acceptance.py).

Usage: python research/pool_acceptance.py research/results/tune_acceptance-batista-ges-*.json ...
Writes research/results/pool-acceptance-<host>-<UTC>.json (``--out``).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "benchmarks"))

import _common as C  # noqa: E402
from tune_acceptance import RESULTS_DIR, settling_time  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+", help="tune_acceptance JSONs of the same gains, different --eval-seed")
    ap.add_argument("--smooth-s", type=float, default=60.0)
    ap.add_argument("--out", default=str(RESULTS_DIR))
    args = ap.parse_args(argv)
    import numpy as np

    rows, seeds, gains = [], set(), None
    for f in args.files:
        d = json.loads(pathlib.Path(f).read_text())
        sm, st = d["summary"], d["settings"]
        if sm["eval_seed"] in seeds:
            raise SystemExit(f"{f}: eval seed {sm['eval_seed']} appears twice; pool disjoint held-out sets only")
        seeds.add(sm["eval_seed"])
        g = json.dumps(d["gains"], sort_keys=True)
        if gains is not None and g != gains:
            raise SystemExit(f"{f}: different gains from the first file; pool evaluations of the same gains only")
        gains = g
        rows.append(
            {
                "file": f,
                "eval_seed": sm["eval_seed"],
                "runs": sm["eval_runs"],
                "paper": sm["steady_mean_angle_error_deg"]["paper_gains"],
                "tuned": sm["steady_mean_angle_error_deg"]["tuned_gains"],
                "diff": sm["paired_difference_deg"]["mean"],
                "diff_se": sm["paired_difference_deg"]["stderr"],
                "t": np.asarray(d["curves"]["t_s"], float),
                "curve_paper": np.asarray(d["curves"]["paper_mean_angle_deg"], float),
                "curve_tuned": np.asarray(d["curves"]["tuned_mean_angle_deg"], float),
                "gains_path": d.get("gains_path"),
                "smooth_s": st.get("smooth_s", args.smooth_s),
            }
        )
    n = np.array([r["runs"] for r in rows], float)
    big_n = n.sum()
    paper = float(np.sum(n * [r["paper"] for r in rows]) / big_n)
    tuned = float(np.sum(n * [r["tuned"] for r in rows]) / big_n)
    diff = float(np.sum(n * [r["diff"] for r in rows]) / big_n)
    diff_se = float(np.sqrt(np.sum((n * [r["diff_se"] for r in rows]) ** 2)) / big_n)
    improvement = 1.0 - tuned / paper
    t = rows[0]["t"]
    cp = np.sum([r["runs"] * r["curve_paper"] for r in rows], axis=0) / big_n
    ct = np.sum([r["runs"] * r["curve_tuned"] for r in rows], axis=0) / big_n
    target = 1.10 * paper
    tp, tt = settling_time(t, cp, target, args.smooth_s), settling_time(t, ct, target, args.smooth_s)
    speedup = (tp / tt) if (tp and tt) else None
    for r in rows:
        print(
            f"seed {r['eval_seed']}: {r['runs']} runs, paper {r['paper']:.4f} deg, tuned {r['tuned']:.4f} deg "
            f"({100 * (r['tuned'] / r['paper'] - 1):+.1f} %, paired {r['diff']:+.4f} +- {r['diff_se']:.4f})"
        )
    print(
        f"pooled over {int(big_n)} held-out runs: paper {paper:.4f} deg, tuned {tuned:.4f} deg -> "
        f"{100 * improvement:.1f} % lower (paired {diff:+.4f} +- {diff_se:.4f} deg, i.e. "
        f"{100 * -diff / paper:.1f} +- {100 * diff_se / paper:.1f} %)"
    )
    print(
        f"criterion A (>= 20 % lower): {'MET' if improvement >= 0.20 else 'not met'}; criterion B on the pooled "
        f"curves (10 % band, {target:.4f} deg): paper {tp} s, tuned {tt} s"
        + (f", {speedup:.2f}x" if speedup else "")
        + f" -> {'MET' if speedup and speedup >= 2 else 'not met'}"
    )
    meta = C.metadata(sys.argv if argv is None else ["pool_acceptance.py"] + list(argv))
    data = {
        "files": [r["file"] for r in rows],
        "per_file": [{k: v for k, v in r.items() if k not in ("t", "curve_paper", "curve_tuned")} for r in rows],
        "pooled": {
            "runs": int(big_n),
            "paper_steady_deg": paper,
            "tuned_steady_deg": tuned,
            "improvement": improvement,
            "paired_difference_deg": diff,
            "paired_stderr_deg": diff_se,
            "criterion_A": bool(improvement >= 0.20),
            "settling_10pct_paper_s": tp,
            "settling_10pct_tuned_s": tt,
            "speedup": speedup,
            "criterion_B": bool(speedup is not None and speedup >= 2.0),
        },
        "curves": {"t_s": t.tolist(), "paper_mean_angle_deg": cp.tolist(), "tuned_mean_angle_deg": ct.tolist()},
    }
    path = C.write_results("pool-acceptance", data, args.out, meta)
    print(f"results written to {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
