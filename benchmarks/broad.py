"""jaxatt beside VQF, ahrs and imufusion on the BROAD trials: the same trials, the same metric, and samples per
second for each.

Install: ``pip install -e ".[compare,data]"`` (vqf, ahrs, imufusion, h5py). Run:
``python benchmarks/broad.py [--data-dir ../shared/data/broad] [--filters ...] [--trials ...] [--gains all]``.
Writes benchmarks/results/broad-<host>-<UTC>.json.

Filters and conventions:

* **jaxatt robust AHRS** (``jaxatt.observers.robust_ahrs.run``): every trial in one batched call (padded by
  repeating the last sample, dt per trial). Gains: the shipped ``--gains`` file (default ``all``, tuned on all 20
  trials, so in sample here; the out-of-fold numbers are ``benchmarks/broad_crossval.py``'s). Throughput: real
  (unpadded) samples of all trials / wall time of the warm batched call, median of ``--repeats``; float32 and
  float64. Also one trial at a time (unbatched, float32) for comparison.
* **jaxatt Mahony** (BROAD's implementation and gains, reproduces the published numbers): a sanity row.
* **VQF online 9D**: ``vqf.VQF(Ts).updateBatch(gyr, acc, mag)["quat9D"]``; **offline VQF 9D**:
  ``vqf.offlineVQF(gyr, acc, mag, Ts, None)["quat9D"]``. VQF's quaternions are sensor-to-ENU like BROAD's.
* **ahrs Madgwick** (beta = 0.12) and **ahrs Mahony** (BROAD's best gains k_P = 0.74, k_I = 0.0012): started
  from TRIAD of the first acc/mag sample, stepped with ``updateMARG`` from sample 0 on (BROAD's alignment: the
  estimate after sample k is compared with the truth at k). Madgwick's earth frame is NWU (reference field
  (b_x, 0, b_z), gravity up), converted with q_ENU = q_z(+90 deg) (x) q_NWU; ahrs's Mahony uses the reference
  field (0, |h_xy|, h_z), i.e. ENU directly.
* **imufusion** defaults (gain 0.5, no rejection), ``AhrsSettings.sample_rate`` set to the trial's rate, earth
  convention ENU; gyro in deg/s, acc in g.

Samples/s: total samples / wall time of the filter loop only (data loading and metric excluded).
"""
from __future__ import annotations

import argparse
import os
import pathlib
import statistics
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

import _common as C  # noqa: E402

G = 9.81
ALL_FILTERS = ("jaxatt-robust", "jaxatt-mahony", "vqf-online", "vqf-offline", "ahrs-madgwick", "ahrs-mahony",
               "imufusion")
ANCHOR_KEY = {"vqf-online": "VQF online 9D", "vqf-offline": "VQF offline 9D", "ahrs-madgwick": "ahrs Madgwick beta=0.12",
              "ahrs-mahony": "ahrs Mahony (BROAD best)", "imufusion": "imufusion defaults"}


def _qmul(a, b):
    import numpy as np

    aw, ax, ay, az = np.moveaxis(np.asarray(a), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b), -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def _nwu_to_enu(q):
    import numpy as np

    s = np.sqrt(0.5)
    return _qmul(np.array([s, 0.0, 0.0, s]), q)


def _triad(acc, mag, frame="NWU"):
    """Sensor-to-earth quaternion (w, x, y, z) from one acc (up) and mag sample; earth frame NWU or ENU."""
    import numpy as np

    up = acc / np.linalg.norm(acc)
    west = np.cross(up, mag)
    west /= np.linalg.norm(west)
    north = np.cross(west, up)
    # rows: earth axes in sensor coordinates -> R (sensor to earth)
    r = np.stack([north, west, up]) if frame == "NWU" else np.stack([-west, north, up])
    w = np.sqrt(max(1e-12, 1.0 + np.trace(r))) / 2.0
    if w > 1e-3:
        return np.array([w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)])
    from scipy.spatial.transform import Rotation  # noqa: PLC0415 - rare branch

    x, y, z, w = Rotation.from_matrix(r).as_quat()
    return np.array([w, x, y, z])


def run_vqf(tr, offline=False):
    import numpy as np
    import vqf

    g, a, m = (np.ascontiguousarray(x, dtype=np.float64) for x in (tr.samples.gyr, tr.samples.acc, tr.samples.mag))
    ts = 1.0 / tr.rate_hz
    t0 = time.perf_counter()
    q = vqf.offlineVQF(g, a, m, ts, None)["quat9D"] if offline else vqf.VQF(ts).updateBatch(g, a, m)["quat9D"]
    return q, time.perf_counter() - t0


def run_ahrs(tr, kind):
    import numpy as np
    from ahrs.filters import Madgwick, Mahony

    g, a, m = (np.asarray(x, dtype=np.float64) for x in (tr.samples.gyr, tr.samples.acc, tr.samples.mag))
    dt = 1.0 / tr.rate_hz
    f = Madgwick(frequency=tr.rate_hz, beta=0.12) if kind == "madgwick" else \
        Mahony(frequency=tr.rate_hz, k_P=0.74, k_I=0.0012)
    q = _triad(a[0], m[0], "NWU" if kind == "madgwick" else "ENU")
    out = np.empty((len(g), 4))
    t0 = time.perf_counter()
    for k in range(len(g)):
        q = f.updateMARG(q, g[k], a[k], m[k], dt=dt) if kind == "madgwick" else f.updateMARG(q, g[k], a[k], m[k])
        out[k] = q
    wall = time.perf_counter() - t0
    return (_nwu_to_enu(out) if kind == "madgwick" else out), wall


def run_imufusion(tr):
    import imufusion
    import numpy as np

    s = imufusion.AhrsSettings()
    s.sample_rate = float(tr.rate_hz)
    s.convention = imufusion.CONVENTION_ENU
    f = imufusion.Ahrs()
    f.set_settings(s)
    g = np.rad2deg(np.asarray(tr.samples.gyr, np.float64))
    a = np.asarray(tr.samples.acc, np.float64) / G
    m = np.asarray(tr.samples.mag, np.float64)
    out = np.empty((len(g), 4))
    t0 = time.perf_counter()
    for k in range(len(g)):
        f.update(g[k], a[k], m[k])
        out[k] = f.get_quaternion()
    return out, time.perf_counter() - t0


def run_jaxatt_robust(trials, gains, repeats):
    """Batched run of all trials; returns ({name: q}, timing dict)."""
    import jax
    import numpy as np

    from jaxatt.data import gains as shipped
    from jaxatt.observers import robust_ahrs as ra

    p = shipped.load_params(gains) if not str(gains).endswith(".json") or not os.path.exists(gains) else \
        ra.params_from_dict(__import__("json").load(open(gains))["gains"])
    n = np.array([len(tr.samples.t) for tr in trials])
    tmax = int(n.max())
    pad = lambda x, k: np.concatenate([x, np.repeat(x[-1:], tmax - k, 0)])  # noqa: E731
    gyr = np.stack([pad(np.asarray(tr.samples.gyr), k) for tr, k in zip(trials, n)])
    acc = np.stack([pad(np.asarray(tr.samples.acc), k) for tr, k in zip(trials, n)])
    mag = np.stack([pad(np.asarray(tr.samples.mag), k) for tr, k in zip(trials, n)])
    dts = np.array([1.0 / tr.rate_hz for tr in trials])
    timing = {"real_samples": int(n.sum()), "padded_samples": int(len(trials) * tmax)}
    qs = None
    for dtype in ("float32", "float64"):
        args = [jax.device_put(np.asarray(x, dtype)) for x in (gyr, acc, mag, dts)]
        t0 = time.perf_counter()
        q = jax.block_until_ready(ra.run(p, *args, dtype=dtype)["q"])
        first = time.perf_counter() - t0
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            q = jax.block_until_ready(ra.run(p, *args, dtype=dtype)["q"])
            times.append(time.perf_counter() - t0)
        med = statistics.median(times)
        timing[dtype] = {"first_call_s": first, "times_s": times, "median_s": med,
                         "samples_per_s": float(n.sum() / med)}
        if dtype == "float32":
            qs = {tr.name: np.asarray(q[i, : n[i]], np.float64) for i, tr in enumerate(trials)}
    # one trial at a time (float32, warm per length: each trial length compiles once, timed on a second call)
    tot = 0.0
    for tr in trials:
        args = [np.asarray(x, np.float32) for x in (tr.samples.gyr, tr.samples.acc, tr.samples.mag)]
        jax.block_until_ready(ra.run(p, *args, np.float32(1.0 / tr.rate_hz), dtype="float32")["q"])
        t0 = time.perf_counter()
        jax.block_until_ready(ra.run(p, *args, np.float32(1.0 / tr.rate_hz), dtype="float32")["q"])
        tot += time.perf_counter() - t0
    timing["unbatched_float32"] = {"total_s": tot, "samples_per_s": float(n.sum() / tot)}
    return qs, timing


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data-dir", default=str(C.REPO_ROOT.parent / "shared" / "data" / "broad"))
    ap.add_argument("--filters", nargs="+", default=list(ALL_FILTERS), choices=ALL_FILTERS)
    ap.add_argument("--trials", nargs="*", default=None)
    ap.add_argument("--gains", default="all", help="robust AHRS gains: shipped name (all, fold1, fold2) or a path")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=str(C.RESULTS_DIR))
    args = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from jaxatt import broad_tune as B
    from jaxatt.data import broad

    meta = C.metadata(sys.argv if argv is None else ["broad.py"] + list(argv))
    names = B.resolve_trials(args.data_dir, args.trials)
    info = broad.load_trial_info(args.data_dir)
    trials = [broad.load_trial(pathlib.Path(args.data_dir) / f"{n}.hdf5") for n in names]
    n_samples = int(sum(len(tr.samples.t) for tr in trials))
    results = {}
    for flt in args.filters:
        print(f"{flt} ...", flush=True)
        per, wall, extra = {}, 0.0, {}
        if flt == "jaxatt-robust":
            qs, extra = run_jaxatt_robust(trials, args.gains, args.repeats)
            wall = n_samples / extra["float32"]["samples_per_s"]
        elif flt == "jaxatt-mahony":
            ev = B.broad_eval(args.data_dir, "mahony", trials=names, verbose=False,
                              loaded={tr.name: tr for tr in trials})
            per = {n: {k: ev["trials"][n][k] for k in broad.METRICS} for n in names}
            qs, wall = None, ev["wall_s"]
            extra = {"note": "wall includes compile"}
        else:
            qs = {}
            for tr in trials:
                if flt.startswith("vqf"):
                    q, w = run_vqf(tr, offline=flt == "vqf-offline")
                elif flt.startswith("ahrs"):
                    q, w = run_ahrs(tr, flt.split("-")[1])
                else:
                    q, w = run_imufusion(tr)
                qs[tr.name], wall = q, wall + w
        if qs is not None:
            per = {tr.name: broad.broad_errors(qs[tr.name], tr.quat_true, tr.movement) for tr in trials}
        per = {n: {**per[n], "group": B._group_of(n, info)} for n in names}
        groups = B._summaries(per, info)
        results[flt] = {"trials": per, "groups": groups, "wall_s": wall, "samples_per_s": n_samples / wall, **extra}
        print("  " + ", ".join(f"{g} {v['total_rmse_deg']:.2f}" for g, v in groups.items())
              + f"  ({n_samples / wall:.3g} samples/s)", flush=True)

    print(f"\nBROAD, {len(names)} trials, {n_samples} samples: mean total RMSE (deg)")
    print(f"{'filter':16s} {'undisturbed':>12s} {'disturbed':>10s} {'anchor':>14s} {'samples/s':>11s}")
    for flt, r in results.items():
        a = B.ANCHORS.get(ANCHOR_KEY.get(flt, ""), None)
        anc = f"{a['undisturbed']:.2f} / {a['disturbed']:.2f}" if a else ""
        g = r["groups"]
        print(f"{flt:16s} {g.get('undisturbed', {}).get('total_rmse_deg', float('nan')):12.2f} "
              f"{g.get('disturbed', {}).get('total_rmse_deg', float('nan')):10.2f} {anc:>14s} {r['samples_per_s']:11.3g}")
    if "jaxatt-robust" in results:
        t = results["jaxatt-robust"]
        print(f"jaxatt robust, all trials batched: {t['float32']['samples_per_s']:.3g} samples/s float32, "
              f"{t['float64']['samples_per_s']:.3g} float64; one trial at a time {t['unbatched_float32']['samples_per_s']:.3g}"
              f" (load average {os.getloadavg()[0]:.1f})")
    path = C.write_results("broad", {"settings": vars(args), "n_samples": n_samples, "trials": names,
                                     "results": results, "anchors": B.ANCHORS, "data": broad.ATTRIBUTION,
                                     "load_avg_at_end": os.getloadavg()}, out_dir=args.out, meta=meta)
    print(f"results written to {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
