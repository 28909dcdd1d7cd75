"""Three structural variants of the robust AHRS tried against BROAD's undisturbed out-of-fold error (issue 18), each
scored out of fold with the shipped fold gains (``jaxatt/data/gains/robust_broad_fold{1,2}.json``: each fold's
trials filtered with the gains learnt on the other fold, float64) and one new parameter scanned; the gains are not
tuned again. Each variant is off at its default, where it reproduces the shipped filter to the last digit.

* ``scale``: an online gyro-scale estimate per sensor axis, gyr_i <- (1 + s_i) gyr_i, learnt by LMS from the
  step's corrections (earth frame: the inclination correction and the heading correction theta) against each axis's
  share of the step's rotation, s_i += k_scale (R^T c)_i w_i, |s_i| <= ``--scale-max``; ``--scale-from`` feeds it
  both corrections, the inclination's only or the heading's only. Scanned: k_scale (s / rad^2).
* ``mag-new``: the magnetic reference (norm, dip) follows the field with time constant tau_mag_new (s) also while
  the gate is shut (VQF's acceptance of a new field), not only while undisturbed. Scanned: tau_mag_new.
* ``rate``: the heading gain grows with the turn rate, k_mag sqrt(1 + |w|^2 / rate_ref^2) (a Kalman-like gain when
  the gyro's heading drift grows with |w|, e.g. from a scale error). Scanned: rate_ref (rad/s) x a factor on the
  shipped tau_mag.

The variant is built from the library's own source (jaxatt/observers/robust_ahrs.py) by exact text replacements,
which fail loudly when the source has changed. They match the source up to f4eb711: since d0f5047 (the gain
accumulators of a slower magnetometer) run it against that version, e.g. from a worktree at f4eb711. Prints one
line per value (group means and every trial).

``--fit STEPS``: instead of the scan, learn the variant's new parameter together with the shipped filter's tuned
gains (jaxatt.fit on your own observer, float32, Adam lr ``--lr``, cosine), each fold from its own shipped fold
gains with the new parameter at the first of ``--values``; scored on the other fold (float64). Fold gains:
research/results/broad_folds/robust-variant-<variant>_broad_fold<k>.json.

``--diagnose TRIAL`` (e.g. 08): per 5-s window of that trial, the turn rate, |m| over its median in the first 10 s
(at the table), the shipped filter's magnetometer weight and its heading error against the truth (deg), filtered
with the fold gains learnt without that trial.

Usage: python research/broad_robust_variants.py --diagnose 08
       python research/broad_robust_variants.py --variant scale --values 0 0.001 0.003 0.01 0.03
       python research/broad_robust_variants.py --variant mag-new --values 1e9 300 100 30 10 3
       python research/broad_robust_variants.py --variant rate --values 1e6 3 1 0.5 --tau-mag-factors 1 2 4
"""

from __future__ import annotations

import argparse
import importlib.util
import itertools
import pathlib
import sys
import time

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
REPO = HERE.parent
GAINS = REPO / "jaxatt" / "data" / "gains"

# (old, new) exact replacements on jaxatt/observers/robust_ahrs.py
_EDITS = [
    (
        "from .. import so3\nfrom ..types import ArrayLike, ImuSample, Interval, Observer\nfrom . import registry\n",
        "from jaxatt import so3\nfrom jaxatt.types import ArrayLike, ImuSample, Interval, Observer\n"
        "from jaxatt.observers import registry\n",
    ),
    (
        "    mag_delay: ArrayLike = 0.0\n\n\nPARAM_NAMES",
        "    mag_delay: ArrayLike = 0.0\n    k_scale: ArrayLike = 0.0\n    scale_max: ArrayLike = 0.02\n"
        "    tau_mag_new: ArrayLike = 1e9\n    mag_rate_ref: ArrayLike = 1e6\n\n\nPARAM_NAMES",
    ),
    (
        "    mag_delay=0.0,\n)\n",
        "    mag_delay=0.0,\n    k_scale=0.0,\n    scale_max=0.02,\n    tau_mag_new=1e9,\n    mag_rate_ref=1e6,\n)\n",
    ),
    (
        "    mag_sin_dip_ref: jax.Array\n\n\nclass Out",
        "    mag_sin_dip_ref: jax.Array\n    scale: jax.Array\n\n\nclass Out",
    ),
    (
        "    mag_delay: jax.Array\n\n\ndef coefficients",
        "    mag_delay: jax.Array\n    k_scale: jax.Array\n    scale_max: jax.Array\n    k_mag_new: jax.Array\n"
        "    inv_rate_ref2: jax.Array\n\n\ndef coefficients",
    ),
    (
        "        mag_delay=p.mag_delay,\n    )\n",
        "        mag_delay=p.mag_delay,\n        k_scale=p.k_scale,\n        scale_max=p.scale_max,\n"
        "        k_mag_new=gain_from_tau(p.tau_mag_new, dt),\n"
        "        inv_rate_ref2=1.0 / (p.mag_rate_ref * p.mag_rate_ref),\n    )\n",
    ),
    (
        '    "mag_sin_dip_ref",\n    "w_mag",',
        '    "mag_sin_dip_ref",\n    "sc_x",\n    "sc_y",\n    "sc_z",\n    "w_mag",',
    ),
    ("_N_STATE = 24", "_N_STATE = 27"),
    (
        "        mref,\n        sref,\n    ) = s\n",
        "        mref,\n        sref,\n        scx,\n        scy,\n        scz,\n    ) = s\n",
    ),
    (
        "    gx, gy, gz = jnp.where(gyr_ok, gx, glx), jnp.where(gyr_ok, gy, gly), jnp.where(gyr_ok, gz, glz)\n",
        "    gx, gy, gz = jnp.where(gyr_ok, gx, glx), jnp.where(gyr_ok, gy, gly), jnp.where(gyr_ok, gz, glz)\n"
        "    gx, gy, gz = gx * (1.0 + scx), gy * (1.0 + scy), gz * (1.0 + scz)\n",
    ),
    (
        "    theta = w_mag * c.k_mag * psi",
        "    rate_fac = jnp.sqrt(1.0 + (wx * wx + wy * wy + wz * wz) * c.inv_rate_ref2)\n"
        "    theta = w_mag * jnp.minimum(c.k_mag * rate_fac, 0.5) * psi",
    ),
    ("    kref = w_mag * c.k_mag_ref\n", "    kref = (w_mag * c.k_mag_ref + (1.0 - w_mag) * c.k_mag_new) * fm\n"),
    (
        "    bz = jnp.clip(bz - pbz, -c.bias_max, c.bias_max)\n",
        "    bz = jnp.clip(bz - pbz, -c.bias_max, c.bias_max)\n"
        "    ccx, ccy, ccz = _rot_inv_c(qa, (SCALE_FROM_ACC * sx, SCALE_FROM_ACC * sy, SCALE_FROM_HEADING * theta))\n"
        "    scx = jnp.clip(scx + c.k_scale * ccx * wx, -c.scale_max, c.scale_max)\n"
        "    scy = jnp.clip(scy + c.k_scale * ccy * wy, -c.scale_max, c.scale_max)\n"
        "    scz = jnp.clip(scz + c.k_scale * ccz * wz, -c.scale_max, c.scale_max)\n",
    ),
    (
        "        mref,\n        sref,\n        w_mag,",
        "        mref,\n        sref,\n        scx,\n        scy,\n        scz,\n        w_mag,",
    ),
    ("        s.mag_sin_dip_ref,\n    )\n", "        s.mag_sin_dip_ref,\n        *sp(s.scale),\n    )\n"),
    ("        mag_sin_dip_ref=f[23],\n    )", "        mag_sin_dip_ref=f[23],\n        scale=st(24, 27),\n    )"),
    (
        "        mag_sin_dip_ref=sdip,\n    )",
        "        mag_sin_dip_ref=sdip,\n        scale=jnp.zeros_like(acc_s),\n    )",
    ),
]


def variant_module(scale_from: str = "both"):
    """The robust AHRS module with the three variants' parameters (all off by default)."""
    src = (REPO / "jaxatt" / "observers" / "robust_ahrs.py").read_text()
    for old, new in _EDITS:
        if src.count(old) != 1:
            raise SystemExit(f"robust_ahrs.py changed: cannot apply the edit at {old.strip()[:60]!r}")
        src = src.replace(old, new)
    src = src[: src.index("ENTRIES = (")] + "ENTRIES = ()\n"  # not registered
    src += f"\nSCALE_FROM_ACC = {0.0 if scale_from == 'heading' else 1.0}\n"
    src += f"SCALE_FROM_HEADING = {0.0 if scale_from == 'acc' else 1.0}\n"
    spec = importlib.util.spec_from_loader("robust_variants", loader=None)
    mod = importlib.util.module_from_spec(spec)
    exec(compile(src, "robust_variants", "exec"), mod.__dict__)
    return mod


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data-dir", default=str(REPO.parent / "shared" / "data" / "broad"))
    ap.add_argument("--variant", choices=("scale", "mag-new", "rate"))
    ap.add_argument("--values", type=float, nargs="+")
    ap.add_argument("--diagnose", metavar="TRIAL", help="the shipped filter through one trial, per 5-s window")
    ap.add_argument("--scale-from", choices=("both", "acc", "heading"), default="both")
    ap.add_argument("--scale-max", type=float, default=0.02)
    ap.add_argument("--tau-mag-factors", type=float, nargs="+", default=[1.0])
    ap.add_argument("--fit", type=int, default=0, metavar="STEPS", help="learn the new parameter with the gains")
    ap.add_argument("--lr", type=float, default=0.05)
    ap.add_argument("--control", action="store_true", help="--fit: the same fit with the new parameter off")
    a = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxatt
    from jaxatt.data import broad
    from jaxatt.fitting import gainsfile

    by = {t.name: t for t in broad.load(a.data_dir)}
    folds = broad.stratified_folds(list(by))
    if a.diagnose:
        return diagnose(by, folds, a.diagnose)
    if not a.variant or not a.values:
        ap.error("--variant and --values are required (or --diagnose TRIAL)")
    rv = variant_module(a.scale_from)
    name = {"scale": "k_scale", "mag-new": "tau_mag_new", "rate": "mag_rate_ref"}[a.variant]
    if a.fit:
        return fit(a, rv, by, folds, name)
    for factor, value in itertools.product(a.tau_mag_factors, a.values):
        t0, res = time.perf_counter(), {}
        for k, test in enumerate((folds[1], folds[0])):  # fold-1 gains score fold 2 and the other way round
            p = gainsfile.read_params(GAINS / f"robust_broad_fold{k + 1}.json", "robust")
            d = {f: float(np.asarray(v)) for f, v in zip(p._fields, p)}
            d["tau_mag"] *= factor
            q = rv.default_params(jax.numpy.float64, **d, **{name: value, "scale_max": a.scale_max})
            s = jaxatt.broad_score(rv.make_observer(), q, [by[n] for n in test])
            res.update({n: (v.total_rmse_deg, v.group) for n, v in s.trials.items()})
        m = {g: np.mean([v for v, gg in res.values() if gg == g]) for g in ("undisturbed", "disturbed")}
        cells = " ".join(f"{n[:2]}:{v:.2f}" for n, (v, _) in sorted(res.items()))
        print(
            f"{name} {value:g}, tau_mag x{factor:g}: undisturbed {m['undisturbed']:.3f} disturbed "
            f"{m['disturbed']:.3f} ({time.perf_counter() - t0:.0f} s) | {cells}",
            flush=True,
        )
    return 0


def diagnose(by, folds, prefix: str) -> int:
    """Per 5-s window of one trial: turn rate, |m| / |m at the table|, mag weight and heading error (deg)."""
    import jaxatt
    from jaxatt.data.broad import error_angles_jax

    name = next(n for n in by if n.startswith(prefix))
    tr, k = by[name], 2 if name in folds[0] else 1  # the fold gains learnt without this trial
    est = jaxatt.filter(
        "robust",
        tr.samples.gyr,
        tr.samples.acc,
        tr.samples.mag,
        dt=1.0 / tr.rate_hz,
        params=str(GAINS / f"robust_broad_fold{k}.json"),
    )
    q_true = np.asarray(tr.quat_true, float)
    ok = np.all(np.isfinite(q_true), axis=1)
    heading = np.full(len(q_true), np.nan)
    heading[ok] = np.degrees(np.asarray(error_angles_jax(est.quat[ok], q_true[ok])[1]))
    rate = np.degrees(np.linalg.norm(np.asarray(tr.samples.gyr, float), axis=1))
    mnorm = np.linalg.norm(np.asarray(tr.samples.mag, float), axis=1)
    fs, w = float(tr.rate_hz), est.outputs["mag_weight"]
    ref = np.nanmedian(mnorm[: int(10 * fs)])
    print(f"{name} (fold {k} gains): t (s), turn rate (deg/s), |m| / |m at the table|, mag weight, |heading err| (deg)")
    for i in range(0, len(rate), int(5 * fs)):
        sl = slice(i, i + int(5 * fs))
        print(
            f"{i / fs:6.0f} {np.nanmean(rate[sl]):7.1f} {np.nanmean(mnorm[sl]) / ref:6.3f} {np.mean(w[sl]):5.2f} "
            f"{np.nanmean(np.abs(heading[sl])):6.2f}"
        )
    return 0


def fit(a, rv, by, folds, name) -> int:
    """Each fold: the shipped fold gains plus the new parameter learnt on that fold, scored on the other."""
    import jax.numpy as jnp

    import jaxatt
    from jaxatt.fitting import gainsfile
    from jaxatt.observers import robust_ahrs

    tune = list(robust_ahrs.TUNABLE) + ([] if a.control else [name])
    tag = f"{a.variant}-control" if a.control else a.variant
    res = {}
    for k, (train, test) in enumerate(((folds[0], folds[1]), (folds[1], folds[0])), start=1):
        p = gainsfile.read_params(GAINS / f"robust_broad_fold{k}.json", "robust")
        d = {f: float(np.asarray(v)) for f, v in zip(p._fields, p)}
        new = {name: a.values[0], "scale_max": a.scale_max} if not a.control else {}  # control: defaults, off
        start = rv.default_params(jnp.float32, **d, **new)
        out = HERE / "results" / "broad_folds" / f"robust-variant-{tag}_broad_fold{k}.json"
        t0 = time.perf_counter()
        r = jaxatt.fit(
            rv.make_observer(),
            start,
            [by[n] for n in train],
            steps=a.fit,
            lr=a.lr,
            tune=tune,
            dtype="float32",
            out=str(out),
            overwrite=True,
        )
        learnt = {f: float(np.asarray(v)) for f, v in zip(r.params._fields, r.params)}
        q = rv.default_params(jnp.float64, **learnt)
        s = jaxatt.broad_score(rv.make_observer(), q, [by[n] for n in test])
        res.update({n: (v.total_rmse_deg, v.group) for n, v in s.trials.items()})
        print(f"fold {k}: {name} {learnt[name]:g}, tau_mag {learnt['tau_mag']:.2f} ({time.perf_counter() - t0:.0f} s)")
    m = {g: np.mean([v for v, gg in res.values() if gg == g]) for g in ("undisturbed", "disturbed")}
    cells = " ".join(f"{n[:2]}:{v:.2f}" for n, (v, _) in sorted(res.items()))
    label = "fitted (control)" if a.control else "fitted"
    print(f"{label}, out of fold: undisturbed {m['undisturbed']:.3f} disturbed {m['disturbed']:.3f} | {cells}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
