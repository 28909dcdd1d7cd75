"""How sensitive the robust AHRS is to the gyro's scale on BROAD, and whether a calibration from the truth helps
(issue 18: where the out-of-fold error of the undisturbed group comes from).

Two measurements, each out of fold (2-fold split of ``broad.stratified_folds``; the trials of one fold are filtered
with the shipped gains learnt on the other, ``jaxatt/data/gains/robust_broad_fold{1,2}.json``; float64):

* ``--scales``: every gyro sample multiplied by a common factor (1 = the recording) before filtering;
* calibration: the gyro regressed on the body rate differentiated from the optical attitude, gyr = S w + b_trial
  (one 3x3 S for the training fold's trials, one bias per trial, samples turning faster than 0.5 rad/s, the gyro
  one sample late as broad_sensor_delays.py measured), and the test fold's gyro corrected by S^-1 (full), by the
  inverse of its diagonal, or by the mean of its diagonal (common scale).

Writes research/results/broad-gyro-scale-<host>-<UTC>.json (per trial and group means) and prints one line per
variant.

Usage: python research/broad_gyro_scale.py [--data-dir DIR] [--scales 1 0.998 0.996 1.002]
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "benchmarks"))
sys.path.insert(0, str(HERE.parent))

import _common as C  # noqa: E402

GAINS = HERE.parent / "jaxatt" / "data" / "gains"
GYRO_LATE = 1  # samples (research/broad_sensor_delays.py)
MIN_RATE = 0.5  # rad/s: samples used by the regression


def _qmul(p, q):
    w1, x1, y1, z1 = np.moveaxis(p, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        -1,
    )


def rate_pairs(trial):
    """(body rate from the truth, gyro) (n, 3) each, rad/s, on the samples turning faster than MIN_RATE."""
    q, fs = np.asarray(trial.quat_true, float), float(trial.rate_hz)
    dq = _qmul(q[:-1] * np.array([1, -1, -1, -1]), q[1:])
    dq = dq * np.sign(dq[:, :1])
    w = 2.0 * dq[:, 1:] * fs  # body rate over [k, k+1] (small-angle quaternion)
    g = np.asarray(trial.samples.gyr, float)
    g = np.roll(0.5 * (g[:-1] + g[1:]), -GYRO_LATE, axis=0)
    ok = np.all(np.isfinite(w), 1) & np.all(np.isfinite(g), 1) & (np.linalg.norm(w, axis=1) > MIN_RATE)
    ok[-GYRO_LATE - 1 :] = False
    return w[ok], g[ok]


def calibration(trials) -> np.ndarray:
    """S (3, 3) of gyr = S w + b_trial, least squares over the trials' fast samples (one bias per trial)."""
    ws, gs, idx = [], [], []
    for i, tr in enumerate(trials):
        w, g = rate_pairs(tr)
        ws.append(w)
        gs.append(g)
        idx.append(np.full(len(w), i))
    w, g, k = np.concatenate(ws), np.concatenate(gs), np.concatenate(idx)
    x = np.column_stack([w, (k[:, None] == np.arange(len(trials))[None]).astype(float)])
    a, *_ = np.linalg.lstsq(x, g, rcond=None)
    return a[:3].T


def score_oof(by_name, folds, corrections) -> dict:
    """Total RMSE per trial (deg) with each fold's gyro multiplied by corrections[fold] (3x3) before filtering."""
    import jaxatt

    out = {}
    for k, test in enumerate((folds[1], folds[0])):  # fold-1 gains score fold 2 and the other way round
        c = corrections[k]
        tt = [
            by_name[n]._replace(samples=by_name[n].samples._replace(gyr=np.asarray(by_name[n].samples.gyr) @ c.T))
            for n in test
        ]
        s = jaxatt.broad_score("robust", str(GAINS / f"robust_broad_fold{k + 1}.json"), tt)
        out.update({n: {"total_rmse_deg": v.total_rmse_deg, "group": v.group} for n, v in s.trials.items()})
    return out


def summary(label, per_trial) -> dict:
    means = {
        g: float(np.mean([v["total_rmse_deg"] for v in per_trial.values() if v["group"] == g]))
        for g in ("undisturbed", "disturbed")
    }
    cells = " ".join(f"{n[:2]}:{v['total_rmse_deg']:.2f}" for n, v in sorted(per_trial.items()))
    print(
        f"{label:34s} undisturbed {means['undisturbed']:.3f} disturbed {means['disturbed']:.3f} | {cells}", flush=True
    )
    return {"label": label, "group_means_deg": means, "trials": per_trial}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data-dir", default=str(HERE.parent.parent / "shared" / "data" / "broad"))
    ap.add_argument("--scales", type=float, nargs="*", default=[1.0, 0.998, 0.996, 1.002])
    ap.add_argument("--out", default=str(HERE / "results"))
    a = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxatt.data import broad

    trials = broad.load(a.data_dir)
    by_name = {t.name: t for t in trials}
    folds = broad.stratified_folds(list(by_name))
    rows = [summary(f"common scale x{s:g}", score_oof(by_name, folds, [np.eye(3) * s] * 2)) for s in a.scales]
    s1, s2 = calibration([by_name[n] for n in folds[0]]), calibration([by_name[n] for n in folds[1]])
    print("S - I (%), fold 1:", np.round((s1 - np.eye(3)) * 100, 3).tolist())
    print("S - I (%), fold 2:", np.round((s2 - np.eye(3)) * 100, 3).tolist())
    variants = {
        "calibration: full S^-1": [np.linalg.inv(s1), np.linalg.inv(s2)],
        "calibration: diagonal": [np.diag(1 / np.diag(s1)), np.diag(1 / np.diag(s2))],
        "calibration: common scale": [np.eye(3) / np.mean(np.diag(s1)), np.eye(3) / np.mean(np.diag(s2))],
    }
    rows += [summary(label, score_oof(by_name, folds, c)) for label, c in variants.items()]
    path = C.write_results(
        "broad-gyro-scale",
        {
            "folds": folds,
            "calibration_S": {"fold1": s1.tolist(), "fold2": s2.tolist()},
            "settings": {"gyro_late_samples": GYRO_LATE, "min_rate_rad_s": MIN_RATE, "scales": a.scales},
            "rows": rows,
        },
        out_dir=a.out,
    )
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
