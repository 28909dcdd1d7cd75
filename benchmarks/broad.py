"""jaxatt beside VQF, ahrs and imufusion on the BROAD trials: the same trials, the same metric, and samples per
second for each: every observer registered for recorded data, and the robust AHRS out of fold (2-fold
cross-validation), its fair number to compare.

Install: ``pip install -e ".[compare,data]"`` (vqf, ahrs, imufusion, h5py). Run:
``python benchmarks/broad.py [--data-dir ../shared/data/broad] [--filters ...] [--trials ...] [--gains all]
[--retrain-folds --steps 40 --folds-dir DIR] [--oof-gains-dir DIR]``. Writes benchmarks/results/broad-<host>-<UTC>.json
and beside it the per-trial figure (.png: total RMSE of every trial, one series per row, trials grouped
undisturbed | disturbed, group means in the legend). ``python benchmarks/broad.py --figure-from RESULTS.json
[--figure-out PNG]`` only draws the figure of an existing results file.

Filters and conventions:

* **jaxatt robust AHRS** (``jaxatt-robust``): every trial in one batched call: ``jaxatt.engine.compiled`` of the
  registry's recorded robust AHRS over the trials padded by repeating the last sample (dt per trial), keeping the
  quaternion of every estimate. Gains: the shipped ``--gains`` file (default ``all``, tuned on all 20 trials, so
  in sample here). Throughput: real (unpadded) samples of all trials / wall time of the warm batched call on
  arrays already on the device, median of ``--repeats``; float32 (its estimates are the row's) and float64. Also
  one trial at a time through ``jaxatt.filter`` (float32, warm: each trial's length compiles once, timed on a
  second call; includes the front door's checks and the copy of every output to numpy).
* **jaxatt robust AHRS out of fold** (``jaxatt-robust-oof``): the folds are :func:`jaxatt.data.broad.stratified_folds`
  of all trials in ``--data-dir``; each selected trial is scored (``jaxatt.broad_score``, float64) with the gains
  tuned on the OTHER fold: the shipped ``robust_broad_fold{1,2}.json`` (each file must name the fold it was tuned
  on), or with ``--retrain-folds`` gains re-learnt first by ``jaxatt.fit("robust", defaults, fold, steps=--steps,
  lr=--lr, dtype=float32, out=--folds-dir/robust_broad_fold{k}.json)`` from the untuned defaults (about 3-5 min
  per fold on 2 CPU cores; ``XLA_FLAGS=--xla_cpu_use_fusion_emitters=false`` roughly halves a gradient on CPU).
  Its wall time includes compiling.
* **every other registered observer** (``jaxatt-<name>`` for each name of
  ``jaxatt.observers.registry.names(recorded=True)``: complementary, madgwick, mahony, mekf, nlo, nlio-fg, nlio,
  vqf, vqf-6d): ``jaxatt.broad_score(name, None, trials)`` with its default (or shipped) gains, float64, all trials
  in one batched scan; samples/s from a second, warm call (it includes padding the trials and the metric reduced
  in the scan). The registered madgwick and mahony start from TRIAD as the ahrs rows do; madgwick equals ahrs's
  Madgwick with the same beta (``tests/test_broad_benchmark.py``; the ahrs row's beta is 0.12, jaxatt's default
  0.041), mahony is BROAD's implementation (not ahrs's) with BROAD's best gains.
* **out-of-fold tuned VQF, Madgwick, Mahony** (``jaxatt-vqf-oof``, ``jaxatt-madgwick-oof``, ``jaxatt-mahony-oof``;
  :data:`TUNED_OOF`): as the robust AHRS's out-of-fold row, with the fold gains ``<name>_broad_fold{1,2}.json``
  that ``research/broad_oof_tuning.py`` learnt (``jaxatt.fit`` from the default gains, 40 Adam steps, float32) in
  ``--oof-gains-dir`` (default research/results/broad_folds; not shipped with the package). Each file must name
  fold k of ``broad.stratified_folds`` as its training trials; each trial is scored with the other fold's file.
  The out-of-fold rows' samples/s come from a second, warm ``jaxatt.broad_score`` call per fold (their ``wall_s``
  includes compiling).
* **jaxatt Mahony, BROAD's protocol** (``jaxatt-mahony-broad``: BROAD's implementation, start and gains;
  reproduces the published numbers): a sanity row replaying BROAD's protocol as ``tests/test_broad.py`` does:
  ``mahony.make_observer("broad")`` (BROAD's ``quatFromAccMag`` start; the registered "mahony" starts from TRIAD
  instead) over each trial with sample 0 processed twice (``setState`` from sample 0, then samples 0 ... N-1),
  ``montecarlo.log_runner``, float64, its sensor-to-NWU output rotated into ENU; wall includes compiling (one
  per trial length), samples/s from a second, warm call per trial.
* **offline mode** (``jaxatt-robust-offline``, ``jaxatt-vqf-offline``; :mod:`jaxatt.smoothing`): the registered
  observer run forward and over the time-reversed trials (gyro negated), the two estimates fused per sample with
  the default fusion params (``jaxatt.smoothing.default_fusion``, whose heading numbers are what each training fold
  picks below, so in sample for those two numbers); every trial in one batched call of ``passes_fn`` (float64),
  then ``fuse_passes``. The robust AHRS with the ``--gains`` file (in sample for ``all``), VQF with its defaults.
  Each row also keeps the forward pass's metrics (``forward``: the causal filter), and its samples/s are those of
  a warm call of both passes and the fusion.
* **offline mode out of fold** (``jaxatt-robust-offline-oof``, ``jaxatt-vqf-offline-oof``): the 2 folds of the
  out-of-fold row; on each training fold the fusion params are chosen from :data:`FUSION_GRID` (the lowest mean of
  the two group means of the total RMSE there), with the gains tuned on that fold (robust: the shipped
  ``robust_broad_fold{k}.json``; VQF: its defaults, tuned on nothing), and the trials of the other fold are
  scored with both. Wall includes compiling; samples/s from a warm call of both passes and the fusion over all
  trials of ``--data-dir`` with each fold's gains and fusion (mean of the two folds).
* **VQF online 9D**: ``vqf.VQF(Ts).updateBatch(gyr, acc, mag)["quat9D"]``; **offline VQF 9D**:
  ``vqf.offlineVQF(gyr, acc, mag, Ts, None)["quat9D"]``. VQF's quaternions are sensor-to-ENU like BROAD's.
* **ahrs Madgwick** (beta = 0.12) and **ahrs Mahony** (BROAD's best gains k_P = 0.74, k_I = 0.0012): started
  from TRIAD of the first acc/mag sample (``jaxatt.so3.triad``), stepped with ``updateMARG`` from sample 0 on
  (BROAD's alignment: the estimate after sample k is compared with the truth at k). Madgwick's earth frame is NWU
  (reference field (b_x, 0, b_z), gravity up), converted with ``jaxatt.frames.change_frame(q, "ENU", "NWU")``;
  ahrs's Mahony uses the reference field (0, |h_xy|, h_z), i.e. ENU directly.
* **imufusion** defaults (gain 0.5, no rejection), ``AhrsSettings.sample_rate`` set to the trial's rate, earth
  convention ENU; gyro in deg/s, acc in g.

The external filters' estimates are scored with :func:`jaxatt.data.broad.broad_errors` (numpy); group means as in
``jaxatt.broad_score`` (mean of the per-trial RMSEs over the trials of each group).
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
#: Where research/broad_oof_tuning.py leaves the fold gains of the jaxatt-<name>-oof rows (not shipped).
OOF_GAINS_DIR = C.REPO_ROOT / "research" / "results" / "broad_folds"
#: Rows besides one ``jaxatt-<name>`` per registered recorded observer (:func:`filter_names`).
SPECIAL = ("jaxatt-robust", "jaxatt-robust-oof", "jaxatt-mahony-broad")
#: Registered observers with out-of-fold tuned gains (research/broad_oof_tuning.py, ``--oof-gains-dir``): one
#: ``jaxatt-<name>-oof`` row each, scored as the robust AHRS's out-of-fold row.
TUNED_OOF = ("vqf", "madgwick", "mahony")
EXTERNAL = ("vqf-online", "vqf-offline", "ahrs-madgwick", "ahrs-mahony", "imufusion")
#: The offline mode of jaxatt (forward-backward smoothing, jaxatt.smoothing): in sample / out of fold.
OFFLINE = ("jaxatt-robust-offline", "jaxatt-robust-offline-oof", "jaxatt-vqf-offline", "jaxatt-vqf-offline-oof")
#: Fusion params (tau_inclination, tau_heading, start_inclination, start_heading), s, that the out-of-fold offline
#: rows choose from on each training fold (the inclination numbers barely matter on BROAD).
FUSION_GRID = tuple((3.0, th, 10.0, sh) for th in (10.0, 30.0, 100.0, 300.0) for sh in (1.0, 10.0, 30.0))
#: The anchor of each filter (jaxatt.data.broad.ANCHORS; "ahrs Mahony (BROAD best)" = BROAD's published Mahony).
ANCHOR_KEY = {
    "jaxatt-mahony-broad": "ahrs Mahony (BROAD best)",
    "vqf-online": "VQF online 9D",
    "vqf-offline": "VQF offline 9D",
    "jaxatt-robust-offline": "VQF offline 9D",
    "jaxatt-robust-offline-oof": "VQF offline 9D",
    "jaxatt-vqf-offline": "VQF offline 9D",
    "jaxatt-vqf-offline-oof": "VQF offline 9D",
    "ahrs-madgwick": "ahrs Madgwick beta=0.12",
    "ahrs-mahony": "ahrs Mahony (BROAD best)",
    "imufusion": "imufusion defaults",
}


def filter_names():
    """Every row: the robust AHRS rows, one per other registered recorded observer, BROAD's Mahony, the others."""
    from jaxatt.observers import registry

    own = tuple(f"jaxatt-{n}" for n in registry.names(recorded=True) if n != "robust")
    return SPECIAL[:2] + own + tuple(f"jaxatt-{n}-oof" for n in TUNED_OOF) + SPECIAL[2:] + OFFLINE + EXTERNAL


def _triad(acc, mag, frame):
    """Sensor-to-``frame`` quaternion (w, x, y, z), w >= 0, from one acc (up) and mag sample (numpy)."""
    import jax.numpy as jnp
    import numpy as np

    from jaxatt import so3

    r = so3.triad(jnp.asarray(acc, jnp.float64), jnp.asarray(mag, jnp.float64), frame)
    return np.asarray(so3.quat_canonical(so3.matrix_to_quat(r)), np.float64)


def run_vqf(tr, offline=False):
    import numpy as np
    import vqf

    g, a, m = (np.ascontiguousarray(x, dtype=np.float64) for x in (tr.samples.gyr, tr.samples.acc, tr.samples.mag))
    ts = 1.0 / tr.rate_hz
    t0 = time.perf_counter()
    q = vqf.offlineVQF(g, a, m, ts, None)["quat9D"] if offline else vqf.VQF(ts).updateBatch(g, a, m)["quat9D"]
    return q, time.perf_counter() - t0


def run_ahrs(tr, kind, beta=0.12, k_p=0.74, k_i=0.0012):
    """ahrs' Madgwick (``beta``, rad/s) or Mahony (``k_p``, ``k_i``) from TRIAD of sample 0 (module docstring):
    (sensor-to-ENU quaternions (N, 4), wall s of the loop)."""
    import numpy as np
    from ahrs.filters import Madgwick, Mahony

    from jaxatt import frames

    g, a, m = (np.asarray(x, dtype=np.float64) for x in (tr.samples.gyr, tr.samples.acc, tr.samples.mag))
    dt = 1.0 / tr.rate_hz
    f = (
        Madgwick(frequency=tr.rate_hz, beta=beta)
        if kind == "madgwick"
        else Mahony(frequency=tr.rate_hz, k_P=k_p, k_I=k_i)
    )
    q = _triad(a[0], m[0], "NWU" if kind == "madgwick" else "ENU")
    out = np.empty((len(g), 4))
    t0 = time.perf_counter()
    for k in range(len(g)):
        q = f.updateMARG(q, g[k], a[k], m[k], dt=dt) if kind == "madgwick" else f.updateMARG(q, g[k], a[k], m[k])
        out[k] = q
    wall = time.perf_counter() - t0
    return (frames.change_frame(out, "ENU", "NWU") if kind == "madgwick" else out), wall


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


def robust_params(gains, dtype):
    """Robust AHRS params: a shipped gains file by name (all, fold1, fold2) or a gains-file path."""
    from jaxatt.data import gains as shipped
    from jaxatt.fitting import gainsfile

    if str(gains).endswith(".json") and os.path.exists(gains):
        return gainsfile.read_params(gains, "robust", dtype=dtype)
    return shipped.load_params(gains, dtype=dtype)


def _pick_q(t, truth, out):
    """The record of each estimate: the sensor-to-ENU quaternion (module level: the compiled scan is cached)."""
    from jaxatt import engine

    return engine.estimate_q(out)


def run_jaxatt_robust(trials, gains, repeats):
    """All trials in one batched scan (``jaxatt.engine.compiled`` of the recorded robust AHRS over the padded
    trials, keeping the quaternion of every estimate, as ``jaxatt.filter`` does for one recording); returns
    (per-trial metrics of the float32 run, timing dict)."""
    import jax
    import numpy as np

    from jaxatt import engine
    from jaxatt.data import broad
    from jaxatt.observers import registry

    entry = registry.get("robust")
    obs = registry.recorded_observer(entry)
    padded = broad.pad_trials(trials)
    n = np.asarray(padded.lengths)
    n_steps = int(padded.samples.t.shape[1]) - 1
    timing = {"real_samples": int(n.sum()), "padded_samples": int(padded.samples.t.size)}
    per = None
    for dtype in ("float32", "float64"):
        p = robust_params(gains, dtype)
        fn = engine.compiled(
            obs,
            engine.Recorded(n_steps, False),
            engine.records_of(_pick_q, 1),
            hold=registry.hold_of(entry),
            obs_dtype=np.dtype(dtype),
        )
        item = jax.device_put({**broad.batch_item(padded, dtype), "truth": None})  # arrays on the device first
        t0 = time.perf_counter()
        q = jax.block_until_ready(fn(None, p, item).records)
        first = time.perf_counter() - t0
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            q = jax.block_until_ready(fn(None, p, item).records)
            times.append(time.perf_counter() - t0)
        med = statistics.median(times)
        timing[dtype] = {
            "first_call_s": first,
            "times_s": times,
            "median_s": med,
            "samples_per_s": float(n.sum() / med),
        }
        if dtype == "float32":
            q = np.asarray(q, np.float64)
            per = {tr.name: broad.broad_errors(q[i, : n[i]], tr.quat_true, tr.movement) for i, tr in enumerate(trials)}
    # one trial at a time through the front door (float32; each length compiles once, timed on a second call)
    import jaxatt

    p = robust_params(gains, "float32")
    tot = 0.0
    for tr in trials:
        args = [np.asarray(x, np.float32) for x in (tr.samples.gyr, tr.samples.acc, tr.samples.mag)]
        jaxatt.filter("robust", *args, dt=1.0 / tr.rate_hz, params=p, dtype="float32")
        t0 = time.perf_counter()
        jaxatt.filter("robust", *args, dt=1.0 / tr.rate_hz, params=p, dtype="float32")
        tot += time.perf_counter() - t0
    timing["unbatched_float32"] = {
        "total_s": tot,
        "samples_per_s": float(n.sum() / tot),
        "how": "jaxatt.filter per trial, warm",
    }
    return per, timing


def run_jaxatt_mahony_broad(trials):
    """BROAD's Mahony protocol (see the module docstring); returns (per-trial metrics, wall s incl. compile, wall s
    of a second, warm call per trial)."""
    import jax
    import numpy as np

    from jaxatt import frames, montecarlo
    from jaxatt.data import broad
    from jaxatt.observers import mahony

    run = montecarlo.log_runner(mahony.make_observer("broad"), "next", "float64")
    p = mahony.default_params(*mahony.BROAD_TAGP, dtype="float64")
    per, wall, warm = {}, 0.0, 0.0
    for tr in trials:
        dup = jax.tree_util.tree_map(lambda a: np.concatenate([a[:1], a]), tr.samples)
        dt = broad.step_dt(tr.rate_hz, np.float64)
        t0 = time.perf_counter()
        q_nwu = np.asarray(run(p, dup, dt).q_nwu, np.float64)
        wall += time.perf_counter() - t0
        t0 = time.perf_counter()
        jax.block_until_ready(run(p, dup, dt).q_nwu)
        warm += time.perf_counter() - t0
        per[tr.name] = broad.broad_errors(frames.change_frame(q_nwu[1:], "ENU", "NWU"), tr.quat_true, tr.movement)
    return per, wall, warm


def run_registered(trials, name):
    """The row of the registered observer ``name`` with its default (or shipped) gains: ``jaxatt.broad_score``,
    float64, all trials in one batched scan. Returns (per-trial metrics, wall s of a second, warm call, extra)."""
    import jaxatt
    from jaxatt.data import broad

    sc = jaxatt.broad_score(name, None, trials)
    warm = jaxatt.broad_score(name, None, trials).wall_s
    per = {n: {m: getattr(v, m) for m in broad.METRICS} for n, v in sc.trials.items()}
    extra = {
        "first_call_s": sc.wall_s,
        "note": "warm jaxatt.broad_score call (padding, scan, metric), float64, default gains",
    }
    return per, warm, extra


def _train_trials(payload):
    """The trials a gains file was tuned on (jaxatt 0.1's broad-tune key, or the fitter's settings)."""
    return payload.get("train_trials") or payload.get("settings", {}).get("train_trials") or []


def fold_gains_path(name, k, gains_dir):
    """The gains file tuned on fold ``k`` for the out-of-fold row of ``name``: the robust AHRS's shipped
    ``robust_broad_fold{k}.json``, the others' ``<gains_dir>/<name>_broad_fold{k}.json``."""
    from jaxatt.data import gains as shipped

    if name == "robust":
        return pathlib.Path(str(shipped.path(f"robust_broad_fold{k}.json")))
    path = pathlib.Path(gains_dir) / f"{name}_broad_fold{k}.json"
    if not path.exists():
        raise SystemExit(f"{path} not found: make it with research/broad_oof_tuning.py --observers {name}")
    return path


def run_jaxatt_oof(data_dir, trials, name="robust", *, retrain=False, steps=40, lr=0.05, folds_dir=".", gains_dir=None):
    """Out-of-fold metrics of the registered observer ``name``: the folds are
    ``broad.stratified_folds`` of all trials in ``data_dir``; each selected trial is scored (``jaxatt.broad_score``,
    float64, the fold's test trials in one batched call) with the gains tuned on the OTHER fold
    (:func:`fold_gains_path`; the file must name that fold as its training trials). ``retrain`` (robust only):
    re-learn them first into ``folds_dir``. Returns (per-trial metrics, fold info, wall s of the first calls incl.
    compiling, wall s of a second, warm call per fold)."""
    import jax.numpy as jnp

    import jaxatt
    from jaxatt.data import broad
    from jaxatt.fitting import gainsfile
    from jaxatt.observers import registry

    all_names = broad.resolve_trials(data_dir)
    folds = broad.stratified_folds(all_names, broad.load_trial_info(data_dir))
    if len(folds) != 2:
        raise SystemExit("the out-of-fold rows are written for 2 folds")
    by_name = {tr.name: tr for tr in trials}
    per, info, wall, warm = {}, [], 0.0, 0.0
    for k, train in enumerate(folds, start=1):
        test = [tr for tr in trials if tr.name not in train]
        if retrain:
            if name != "robust":
                raise SystemExit("--retrain-folds re-learns the robust AHRS's folds only")
            out_dir = pathlib.Path(folds_dir)
            out_dir.mkdir(parents=True, exist_ok=True)
            path = out_dir / f"robust_broad_fold{k}.json"
            train_trials = [by_name.get(n) for n in train]
            if None in train_trials:
                train_trials = broad.load(data_dir, train)
            print(f"  fold {k}: fitting on {len(train)} trials -> {path} ...", flush=True)
            # from the untuned defaults: the shipped gains have seen every trial
            start = registry.get("robust").default_params(jnp.float32)
            jaxatt.fit(
                "robust", start, train_trials, steps=steps, lr=lr, dtype="float32", out=str(path), overwrite=True
            )
        else:
            path = fold_gains_path(name, k, gains_dir)
        payload = gainsfile.read(path)
        if payload.get("observer") not in (None, name):
            raise SystemExit(f"{path} holds gains of {payload.get('observer')!r}, not {name!r}")
        if sorted(_train_trials(payload)) != sorted(train):
            raise SystemExit(f"{path} was tuned on {_train_trials(payload)}, not on fold {k} = {train}")
        fold = {"fold": k, "train": train, "test": [tr.name for tr in test], "gains": str(path)}
        if test:
            p = str(path)  # as a user passes it: the data-dependent defaults (VQF's ts0) follow the trials
            res = jaxatt.broad_score(name, p, test, dtype="float64")
            wall += res.wall_s
            warm += jaxatt.broad_score(name, p, test).wall_s
            for n, sc in res.trials.items():
                per[n] = {**{m: getattr(sc, m) for m in broad.METRICS}, "gains": path.name}
        info.append(fold)
    return {tr.name: per[tr.name] for tr in trials}, info, wall, warm


def run_jaxatt_robust_oof(data_dir, trials, *, retrain, steps, lr, folds_dir):
    """The robust AHRS's out-of-fold row (:func:`run_jaxatt_oof`): (per-trial metrics, fold info, wall s)."""
    per, info, wall, _ = run_jaxatt_oof(
        data_dir, trials, "robust", retrain=retrain, steps=steps, lr=lr, folds_dir=folds_dir
    )
    return per, info, wall


def _offline_params(name, gains, trials):
    """Params of the offline rows: the robust AHRS's gains file ``gains`` (shipped name or path), VQF's defaults
    with its data-dependent ones set from ``trials`` as ``jaxatt.broad_score`` sets them (``ts0``: the first step)."""
    import numpy as np

    from jaxatt.api import recording_defaults_for_trials
    from jaxatt.observers import registry

    if name == "robust":
        return robust_params(gains, "float64")
    entry = registry.get(name)
    return recording_defaults_for_trials(entry, None, entry.params(dtype=np.float64), trials)


def _fuse_q(passes, fusion):
    from jaxatt import smoothing

    return smoothing.fuse_passes(passes, fusion).q


_FUSE = None


def offline_passes(trials, name, params):
    """Both passes of the registered observer ``name`` over ``trials`` (padded, one batched call, float64):
    (passes, padded, wall s of the first call incl. compiling)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxatt import smoothing
    from jaxatt.data import broad
    from jaxatt.observers import registry

    entry = registry.get(name)
    padded = broad.pad_trials(trials)
    item = jax.device_put({**broad.batch_item(padded, "float64"), "truth": None})
    fn = smoothing.compiled_passes(
        registry.recorded_observer(entry), int(padded.samples.t.shape[1]) - 1, obs_dtype=np.float64
    )
    t0 = time.perf_counter()
    passes = jax.block_until_ready(fn(params, item, jnp.asarray(padded.lengths)))
    return passes, padded, time.perf_counter() - t0, (fn, item)


def offline_metrics(passes, padded, trials, fusion=None, forward=False):
    """Per-trial BROAD metrics (numpy, float64) of the fused estimate (or of the forward pass)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxatt import smoothing
    from jaxatt.data import broad

    global _FUSE
    if _FUSE is None:
        _FUSE = jax.jit(_fuse_q)
    if forward:
        q = np.asarray(passes.forward["q"], np.float64)
    else:
        f = smoothing.default_fusion(jnp.float64) if fusion is None else smoothing.FusionParams(*map(float, fusion))
        q = np.asarray(_FUSE(passes, smoothing.FusionParams(*(jnp.asarray(v, jnp.float64) for v in f))), np.float64)
    n = np.asarray(padded.lengths)
    return {tr.name: broad.broad_errors(q[i, : n[i]], tr.quat_true, tr.movement) for i, tr in enumerate(trials)}


def _balanced_total(per, names):
    """Mean of the two group means of the total RMSE over ``names`` (the out-of-fold rows' selection criterion)."""
    import numpy as np

    from jaxatt.data import broad

    means = [
        np.mean([per[n]["total_rmse_deg"] for n in names if broad.group_of(n) == g])
        for g in broad.GROUPS
        if any(broad.group_of(n) == g for n in names)
    ]
    return float(np.mean(means))


def run_offline(trials, name, gains):
    """The in-sample offline row: (per-trial metrics, extra, wall s of a warm call of both passes and fusion)."""
    import jax
    import jax.numpy as jnp

    from jaxatt import smoothing

    p = _offline_params(name, gains, trials)
    passes, padded, first, (fn, item) = offline_passes(trials, name, p)
    per = offline_metrics(passes, padded, trials)
    fwd = offline_metrics(passes, padded, trials, forward=True)
    t0 = time.perf_counter()
    jax.block_until_ready(_FUSE(fn(p, item, jnp.asarray(padded.lengths)), smoothing.default_fusion(jnp.float64)))
    wall = time.perf_counter() - t0
    extra = {
        "first_call_s": first,
        "fusion": {k: float(v) for k, v in smoothing.default_fusion()._asdict().items()},
        "gains": gains if name == "robust" else "defaults",
        "forward": {n: {"total_rmse_deg": v["total_rmse_deg"]} for n, v in fwd.items()},
        "note": "warm call of both passes (float64) and the fusion; forward = the causal filter's metrics",
    }
    return per, extra, wall


def run_offline_oof(data_dir, trials, name):
    """Out-of-fold offline row: per fold, the fusion params chosen on the training fold from FUSION_GRID with the
    gains tuned there, the other fold scored. Returns (per-trial metrics, fold info, wall s incl. compiling,
    samples/s of a warm call of both passes and the fusion over all trials of ``data_dir``, mean over the folds)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxatt import smoothing
    from jaxatt.data import broad
    from jaxatt.data import gains as shipped

    t_start = time.perf_counter()
    all_names = broad.resolve_trials(data_dir)
    folds = broad.stratified_folds(all_names, broad.load_trial_info(data_dir))
    by_name = {tr.name: tr for tr in trials}
    missing = [n for n in all_names if n not in by_name]
    pool = list(trials) + (broad.load(data_dir, missing) if missing else [])
    per, info, cache, rates = {}, [], {}, []
    for k, train in enumerate(folds, start=1):
        test = [tr.name for tr in trials if tr.name not in train]
        if not test:
            continue
        gains = str(shipped.path(f"robust_broad_fold{k}.json")) if name == "robust" else "defaults"
        if gains not in cache:  # VQF's defaults: one pair of passes serves both folds
            params = _offline_params(name, gains, pool)
            passes, padded, _, call = offline_passes(pool, name, params)
            grid = {g: offline_metrics(passes, padded, pool, g) for g in FUSION_GRID}
            cache[gains] = (grid, offline_metrics(passes, padded, pool, forward=True), params, padded, call)
        grid, fwd, params, padded, (fn, item) = cache[gains]
        best = min(FUSION_GRID, key=lambda g: _balanced_total(grid[g], train))
        fusion = smoothing.FusionParams(*(jnp.asarray(v, jnp.float64) for v in best))
        t0 = time.perf_counter()  # a warm call of both passes and the fusion over all trials, this fold's choice
        jax.block_until_ready(_FUSE(fn(params, item, jnp.asarray(padded.lengths)), fusion))
        rates.append(float(np.sum(padded.lengths)) / (time.perf_counter() - t0))
        for n in test:
            per[n] = {**grid[best][n], "fold": k, "forward_total_rmse_deg": fwd[n]["total_rmse_deg"]}
        info.append(
            {
                "fold": k,
                "train": train,
                "test": test,
                "gains": pathlib.Path(gains).name,
                "fusion": dict(zip(("tau_inclination", "tau_heading", "start_inclination", "start_heading"), best)),
                "train_criterion_deg": _balanced_total(grid[best], train),
            }
        )
    rate = float(np.mean(rates)) if rates else None
    return {tr.name: per[tr.name] for tr in trials}, info, time.perf_counter() - t_start, rate


def _groups(per):
    """Group means of per-trial metrics, as jaxatt.broad_score computes them."""
    from jaxatt.api import TrialScore, group_means
    from jaxatt.data import broad

    rows = {n: TrialScore(*(v[m] for m in broad.METRICS), v["group"]) for n, v in per.items()}
    return {g: s._asdict() for g, s in group_means(rows).items()}


def _trial_order(rows):
    """Trial names of the rows grouped as BROAD groups them (undisturbed, then disturbed; by name in each) and the
    group of each."""
    from jaxatt.data import broad

    groups = {}
    for r in rows.values():
        for n, v in r["trials"].items():
            groups.setdefault(n, v.get("group") or broad.group_of(n))
    order = [n for g in broad.GROUPS for n in sorted(groups) if groups[n] == g]
    return order + sorted(n for n in groups if n not in order), groups


def draw_figure(body, title=""):
    """The per-trial figure of a results payload: total RMSE (deg, log axis) of every trial, one series (markers
    and line, gid = the row's name) per filter row, trials on the x axis (tick labels: the trial names' number and
    kind) grouped undisturbed | disturbed, a NaN point at the empty slot between the groups (a row missing a trial
    has NaN there too); each legend label ends with the row's group means (undisturbed / disturbed,
    from the payload's ``groups``). Returns the matplotlib Figure (Agg canvas; pyplot is not used)."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter

    rows = body["results"]
    order, groups = _trial_order(rows)
    n_u = sum(groups[n] == "undisturbed" for n in order)
    gap = 0 < n_u < len(order)  # an empty slot between the groups: the lines break there
    x = np.arange(len(order), dtype=float) + (np.arange(len(order)) >= n_u) * gap
    fig = Figure(figsize=(15, 7.5), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    import matplotlib

    palette = list(matplotlib.colormaps["tab20"].colors) + list(matplotlib.colormaps["tab20b"].colors)
    markers = "osD^v<>pXh*P"
    for i, (flt, r) in enumerate(rows.items()):
        y = np.array([float(r["trials"].get(n, {}).get("total_rmse_deg", np.nan)) for n in order])
        xs, ys = (np.insert(x, n_u, n_u), np.insert(y, n_u, np.nan)) if gap else (x, y)
        g = r.get("groups", {})
        means = " / ".join(f"{g[k]['total_rmse_deg']:.2f}" if k in g else "-" for k in ("undisturbed", "disturbed"))
        ax.plot(
            xs,
            ys,
            marker=markers[i % len(markers)],
            linestyle="-" if flt.startswith("jaxatt") else "--",
            linewidth=0.8,
            markersize=4,
            color=palette[i % len(palette)],
            label=f"{flt}: {means}",
            gid=flt,
        )
    if gap:
        ax.axvline(n_u, color="0.3", linewidth=1.0)
    for sel, name in ((x[:n_u], "undisturbed"), (x[n_u:], "disturbed")):
        if len(sel):
            ax.text(sel.mean(), 1.01, name, transform=ax.get_xaxis_transform(), ha="center", va="bottom")
    ax.set_xticks(x, [n.split("_", 2)[0] + " " + n.split("_", 2)[-1] if n.count("_") >= 2 else n for n in order])
    ax.tick_params(axis="x", labelrotation=70, labelsize=7)
    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:g}" if f"{v:.0e}"[0] in "235" else ""))
    ax.set_ylabel("total RMSE (deg)")
    ax.grid(True, which="both", axis="y", alpha=0.3)
    ax.set_xlim(-0.5, x[-1] + 0.5)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, title="row: mean undisturbed / disturbed (deg)")
    ax.set_title(title or "BROAD: total RMSE per trial", pad=18)
    return fig


def figure_from(results_path, png=None):
    """Draw :func:`draw_figure` of a results file (JSON) to ``png`` (default: the JSON's path with .png); returns
    the PNG's path."""
    import json

    results_path = pathlib.Path(results_path)
    res = json.loads(results_path.read_text())
    body = res.get("payload", res)
    if not isinstance(body.get("results"), dict) or not body["results"]:
        raise SystemExit(f"{results_path}: no 'results' rows (not a benchmarks/broad.py results file)")
    n = len(_trial_order(body["results"])[0])
    fig = draw_figure(body, f"BROAD, {n} trials: total RMSE per trial ({results_path.name})")
    out = pathlib.Path(png) if png else results_path.with_suffix(".png")
    fig.savefig(out, dpi=110, pil_kwargs={"optimize": True})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data-dir", default=str(C.REPO_ROOT.parent / "shared" / "data" / "broad"))
    ap.add_argument(
        "--filters",
        nargs="+",
        default=None,
        help="rows to run (default all): jaxatt-robust, jaxatt-robust-oof, jaxatt-<registered name>, "
        f"jaxatt-mahony-broad, {', '.join(OFFLINE)}, {', '.join(EXTERNAL)}",
    )
    ap.add_argument("--trials", nargs="*", default=None, help="names, numbers, groups or fold1/fold2 (default all)")
    ap.add_argument("--gains", default="all", help="robust AHRS gains: shipped name (all, fold1, fold2) or a path")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--retrain-folds",
        action="store_true",
        help="re-learn the fold gains of the out-of-fold row first (jaxatt.fit, minutes per fold)",
    )
    ap.add_argument("--steps", type=int, default=40, help="--retrain-folds: Adam steps")
    ap.add_argument("--lr", type=float, default=0.05, help="--retrain-folds: learning rate")
    ap.add_argument("--folds-dir", default=".", help="--retrain-folds: where robust_broad_fold{k}.json are written")
    ap.add_argument(
        "--oof-gains-dir",
        default=str(OOF_GAINS_DIR),
        help="the fold gains <name>_broad_fold{1,2}.json of the jaxatt-<name>-oof rows (vqf, madgwick, mahony)",
    )
    ap.add_argument("--out", default=str(C.RESULTS_DIR))
    ap.add_argument(
        "--figure-from",
        default=None,
        metavar="JSON",
        help="only draw the per-trial figure of an existing results file (no filter runs)",
    )
    ap.add_argument("--figure-out", default=None, help="--figure-from: the PNG (default: beside the JSON)")
    args = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxatt.data import broad

    if args.figure_from:
        png = figure_from(args.figure_from, args.figure_out)
        print(f"figure written to {png}")
        return 0
    known = filter_names()
    tuned_oof = tuple(f"jaxatt-{n}-oof" for n in TUNED_OOF)
    args.filters = list(args.filters or known)
    bad = [f for f in args.filters if f not in known]
    if bad:
        ap.error(f"unknown filters {bad}; known: {', '.join(known)}")
    meta = C.metadata(sys.argv if argv is None else ["broad.py"] + list(argv))
    names = broad.resolve_trials(args.data_dir, args.trials)
    trials = broad.load(args.data_dir, names)
    n_samples = int(sum(len(tr.samples.t) for tr in trials))
    results = {}
    for flt in args.filters:
        print(f"{flt} ...", flush=True)
        per, wall, extra, rate = {}, 0.0, {}, None
        if flt == "jaxatt-robust":
            per, extra = run_jaxatt_robust(trials, args.gains, args.repeats)
            wall = n_samples / extra["float32"]["samples_per_s"]
        elif flt == "jaxatt-robust-oof" or flt in tuned_oof:
            per, folds, wall, warm = run_jaxatt_oof(
                args.data_dir,
                trials,
                flt[len("jaxatt-") : -len("-oof")],
                retrain=args.retrain_folds and flt == "jaxatt-robust-oof",
                steps=args.steps,
                lr=args.lr,
                folds_dir=args.folds_dir,
                gains_dir=args.oof_gains_dir,
            )
            rate = n_samples / warm
            extra = {
                "folds": folds,
                "warm_wall_s": warm,
                "note": "wall includes compile; each trial scored with the other fold's gains; samples/s from a "
                "second, warm jaxatt.broad_score call per fold (float64)",
            }
        elif flt in ("jaxatt-robust-offline", "jaxatt-vqf-offline"):
            per, extra, wall = run_offline(trials, flt.split("-")[1], args.gains)
        elif flt in ("jaxatt-robust-offline-oof", "jaxatt-vqf-offline-oof"):
            per, folds, wall, rate = run_offline_oof(args.data_dir, trials, flt.split("-")[1])
            extra = {
                "folds": folds,
                "fusion_grid": FUSION_GRID,
                "note": "wall includes compile; fusion chosen on the training fold, each trial scored with the other "
                "fold's gains and fusion; samples/s from a warm call of both passes and the fusion (float64) over "
                "all trials of --data-dir with each fold's gains and fusion (mean of the folds)",
            }
        elif flt == "jaxatt-mahony-broad":
            per, wall, warm = run_jaxatt_mahony_broad(trials)
            rate = n_samples / warm
            extra = {
                "warm_wall_s": warm,
                "note": "BROAD's protocol (start, sample 0 twice), float64; wall includes compile; samples/s from a "
                "second, warm call per trial",
            }
        elif flt.startswith("jaxatt-"):  # a registered observer through the front door
            per, wall, extra = run_registered(trials, flt[len("jaxatt-") :])
        else:
            for tr in trials:
                if flt.startswith("vqf"):
                    q, w = run_vqf(tr, offline=flt == "vqf-offline")
                elif flt.startswith("ahrs"):
                    q, w = run_ahrs(tr, flt.split("-")[1])
                else:
                    q, w = run_imufusion(tr)
                per[tr.name] = broad.broad_errors(q, tr.quat_true, tr.movement)
                wall += w
        per = {tr.name: {**per[tr.name], "group": tr.group or broad.group_of(tr.name)} for tr in trials}
        groups = _groups(per)
        if rate is None and wall > 0 and not flt.endswith("-oof"):
            rate = n_samples / wall  # a row timed by its wall (the out-of-fold rows give a warm rate or none)
        results[flt] = {"trials": per, "groups": groups, "wall_s": wall, "samples_per_s": rate, **extra}
        shown = f"  ({rate:.3g} samples/s)" if rate else ""
        print("  " + ", ".join(f"{g} {v['total_rmse_deg']:.2f}" for g, v in groups.items()) + shown, flush=True)

    print(f"\nBROAD, {len(names)} trials, {n_samples} samples: mean total RMSE (deg)")
    print(f"{'filter':26s} {'undisturbed':>12s} {'disturbed':>10s} {'anchor':>14s} {'samples/s':>11s}")
    for flt, r in results.items():
        a = broad.ANCHORS.get(ANCHOR_KEY.get(flt, ""), None)
        anc = f"{a['undisturbed']:.2f} / {a['disturbed']:.2f}" if a else ""
        g = r["groups"]
        sps = f"{r['samples_per_s']:11.3g}" if r["samples_per_s"] else f"{'-':>11s}"
        print(
            f"{flt:26s} {g.get('undisturbed', {}).get('total_rmse_deg', float('nan')):12.2f} "
            f"{g.get('disturbed', {}).get('total_rmse_deg', float('nan')):10.2f} {anc:>14s} {sps}"
        )
    if "jaxatt-robust" in results:
        t = results["jaxatt-robust"]
        print(
            f"jaxatt robust, all trials batched: {t['float32']['samples_per_s']:.3g} samples/s float32, "
            f"{t['float64']['samples_per_s']:.3g} float64; one trial at a time "
            f"{t['unbatched_float32']['samples_per_s']:.3g}"
            f" (load average {os.getloadavg()[0]:.1f})"
        )
    path = C.write_results(
        "broad",
        {
            "settings": vars(args),
            "n_samples": n_samples,
            "trials": names,
            "results": results,
            "anchors": broad.ANCHORS,
            "data": broad.ATTRIBUTION,
            "load_avg_at_end": os.getloadavg(),
        },
        out_dir=args.out,
        meta=meta,
    )
    print(f"results written to {path}")
    print(f"figure written to {figure_from(path)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
