"""Starts in motion (2026-12-08): the robust AHRS started mid-movement, the offline mode on recordings that end
mid-movement, and the whole BROAD trials (shipped gains in sample, fold gains out of fold), online and offline.

    python research/start_in_motion.py start     # causal, each trial started 40 % into its movement: error (deg)
                                                 # at 0, 1, 3, 10, 30 s after the start
    python research/start_in_motion.py end       # each trial cut 60 % into its movement: total RMSE (deg) over
                                                 # its last second, causal and offline (mean, median, max)
    python research/start_in_motion.py broad     # group means of the per-trial total RMSE (deg), float32

Needs ../shared/data/broad (JAXATT_BROAD_DATA to point elsewhere). Results: research/README.md."""

import json
import os
import sys
import warnings

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
import jaxatt  # noqa: E402
from jaxatt.data import broad, gains  # noqa: E402

DATA = os.environ.get(
    "JAXATT_BROAD_DATA", os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "broad")
)


def _slice(tr, lo, hi):
    s = jaxatt.types.ImuSample(*(np.asarray(a)[lo:hi] for a in tr.samples))
    return s._replace(t=s.t - s.t[0]), tr.quat_true[lo:hi]


def start(trials, observer="robust"):
    for tr in trials:
        mv = np.flatnonzero(tr.movement)
        s, qt = _slice(tr, int(mv[0] + 0.4 * (mv[-1] - mv[0])), None)
        e = np.degrees(broad.error_angles(jaxatt.filter(observer, s).quat, qt)[0])
        r = int(tr.rate_hz)
        print(f"{tr.name[:28]:28s} " + " ".join(f"{e[min(k * r, len(e) - 1)]:6.1f}" for k in (0, 1, 3, 10, 30)))


def end(trials, observer="robust"):
    cuts = []
    for tr in trials:
        mv = np.flatnonzero(tr.movement)
        cut = int(mv[0] + 0.6 * (mv[-1] - mv[0]))
        s, qt = _slice(tr, 0, cut)
        m = np.zeros(cut, bool)
        m[cut - int(tr.rate_hz) :] = True
        cuts.append(tr._replace(samples=s._replace(t=tr.samples.t[:cut]), quat_true=qt, movement=m))
    for off in (False, True):
        v = [
            x.total_rmse_deg
            for x in jaxatt.broad_score(observer, None, cuts, offline=off, dtype="float32").trials.values()
        ]
        print(
            f"{'offline' if off else 'causal':8s} mean {np.mean(v):.2f} median {np.median(v):.2f} max {np.max(v):.2f}"
        )


def whole(trials):
    by = {t.name: t for t in trials}
    folds = broad.stratified_folds(list(by))
    out = {}
    for off in (False, True):
        kind = "offline" if off else "online"
        s = jaxatt.broad_score("robust", None, trials, offline=off, dtype="float32")
        out[f"shipped {kind}"] = {g: round(v.total_rmse_deg, 3) for g, v in s.groups.items()}
        per = {}
        for train, test in ((0, 1), (1, 0)):
            p = gains.load_params(f"fold{train + 1}")
            per.update(
                jaxatt.broad_score("robust", p, [by[n] for n in folds[test]], offline=off, dtype="float32").trials
            )
        grp = {}
        for v in per.values():
            grp.setdefault(v.group, []).append(v.total_rmse_deg)
        out[f"out of fold {kind}"] = {g: round(float(np.mean(v)), 3) for g, v in grp.items()}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    warnings.simplefilter("ignore")
    which = sys.argv[1] if len(sys.argv) > 1 else "broad"
    trials = broad.load(DATA)
    {"start": start, "end": end, "broad": whole}[which](trials)
