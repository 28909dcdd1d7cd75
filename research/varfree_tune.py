"""Gradient tuning of batista-ges on the variance-free loss (issue 20 item 2), evaluated held out by Monte Carlo.

* Tune: ``jaxatt.fit(data="batista-ges", objective="varfree", ...)`` from the paper's gains (Section IV of
  batista2019-ges: Table 1 and the literal Q), the schedule refined at the growing-memory times (900, 1200, ...,
  3300 s; :func:`jaxatt.schedule.refine`, the observer is unchanged until the tuner moves them), through the
  8-number family of research/ges_refined_start.py (``family_transforms``: two levels of alpha1, two levels and a
  power of t of alpha2, one scale per row of gain_z; the same family the Monte Carlo tuning of
  research/batista_ges_tuning.md used), Adam at ``--lr``; then (``--optimizer lbfgs``) L-BFGS with a line search from
  the Adam stage's best gains. The loss is E[theta^2] (deg^2) averaged over the
  steady window t >= 2400 s, computed by :mod:`jaxatt.fitting.varfree` (no runs, no sampling noise: no minibatch,
  no validation runs). Gains file: research/results/gains-batista-ges-varfree.json (rewritten after every
  step; ``--resume`` continues it).
* Predict: the variance-free RMS and mean angle error over the window of the paper's, the tuned and the shipped
  growing-memory gains (jaxatt/data/gains/batista-ges-growing.json), and the wall time of one forward pass.
* Evaluate (held out): Monte Carlo of the three gain sets on the same ``--eval-runs`` runs of seed
  ``--eval-seed`` (never used for tuning; the variance-free loss uses no runs at all): per run the steady-state
  mean angle error (t >= 2400 s, ``mean_angle_error_deg`` of :func:`jaxatt.montecarlo.monte_carlo`), paired
  changes against the paper's gains with their standard errors, and the share of runs that improve (a phase
  interrupted part-way runs again from its first run).

Results: research/results/varfree-tune-batista-ges.json (tuning history with the time of every step, predictions,
held-out evaluation), updated after every phase and every chunk of runs.

Usage: python research/varfree_tune.py --phase tune [--steps 12] [--lr 0.1] [--resume]
       python research/varfree_tune.py --phase predict
       python research/varfree_tune.py --phase tune --optimizer lbfgs --steps 15   (from the Adam stage's best)
       python research/varfree_tune.py --phase evaluate [--eval-runs 300] [--eval-seed 4000]
       python research/varfree_tune.py --phase ship   (jaxatt/data/gains/batista-ges-gradient.json)
       python research/varfree_tune.py --study batista-so3 --phase tune --optimizer lbfgs --steps 19
       python research/varfree_tune.py --study batista-so3 --phase ship   (.../batista-so3-gradient.json)
"""

from __future__ import annotations

import argparse
import math
import pathlib
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np

from jaxatt import io, montecarlo, studies
from jaxatt.fitting import gainsfile
from jaxatt.fitting import varfree as V
from jaxatt.observers import batista_ges as ges

RESULTS = HERE / "results"
GAINS_DIR = HERE.parent / "jaxatt" / "data" / "gains"
#: which study ``--study`` tunes (batista-ges unless said); the paths below follow it (:func:`_use`)
STUDY = "batista-ges"
OUT = RESULTS / "varfree-tune-batista-ges.json"
GAINS_OUT = RESULTS / "gains-batista-ges-varfree.json"
#: the L-BFGS stage: from the Adam stage's best gains (``--optimizer lbfgs``)
GAINS_LBFGS = RESULTS / "gains-batista-ges-varfree-lbfgs.json"
#: the shipped gains the tuned ones are compared with (``None``: none)
GROWING = GAINS_DIR / "batista-ges-growing.json"
#: the shipped gradient-tuned gains (``--phase ship``: the L-BFGS stage's file without its resume state)
SHIPPED = GAINS_DIR / "batista-ges-gradient.json"


def _use(study: str) -> None:
    """Point the module's paths at ``study`` (batista-ges: the names above; batista-so3: the ``-so3-family`` files,
    compared with the shipped Monte Carlo-tuned ``batista-so3.json``)."""
    global STUDY, OUT, GAINS_OUT, GAINS_LBFGS, GROWING, SHIPPED
    STUDY = study
    if study == "batista-so3":
        OUT = RESULTS / "varfree-tune-batista-so3.json"
        GAINS_OUT = RESULTS / "gains-batista-so3-varfree-family.json"
        GAINS_LBFGS = RESULTS / "gains-batista-so3-varfree-family-lbfgs.json"
        GROWING = GAINS_DIR / "batista-so3.json"
        SHIPPED = GAINS_DIR / "batista-so3-gradient.json"


def so3_family_transforms(switch_times, grow_from: float = 900.0):
    """batista-so3's share of the family of research/ges_refined_start.py: alpha1 = one level before ``grow_from``
    and one after, alpha2 = the same two levels and a power of t after ``grow_from`` (eq. (9) of batista2019-so3
    has the same linear block as the GES paper's eq. (15) after 720 s); alpha0, alpha3, alpha4 tuned as they are
    (one positive number each). 8 numbers."""
    from ges_refined_start import family_transforms

    t = family_transforms(switch_times, grow_from)
    return {"alpha1": t["alpha1"], "alpha2": t["alpha2"]}


def _restart_path() -> pathlib.Path:
    """The gains file of ``--restart``: L-BFGS with a fresh memory from the L-BFGS stage's best gains."""
    return GAINS_LBFGS.with_name(GAINS_LBFGS.stem + "-restart.json")


def _payload():
    return io.read_json(OUT) if OUT.exists() else {"experiment": f"{STUDY} variance-free tuning"}


def tune(steps: int, lr, resume: bool, optimizer: str = "adam", restart: bool = False) -> None:
    from ges_refined_start import family_transforms

    import jaxatt
    from jaxatt import schedule

    s = studies.get(STUDY).setup()
    times = np.asarray(schedule.refine(s.params, ges.GROWING_MEMORY_TIMES, ["alpha1", "alpha2"]).switch_times)
    lbfgs = optimizer == "lbfgs"
    out = GAINS_LBFGS if lbfgs else GAINS_OUT
    # batista-so3: L-BFGS straight from the paper's gains (no Adam stage)
    start = str(GAINS_OUT) if lbfgs and STUDY == "batista-ges" else None
    if restart:  # L-BFGS again, with a fresh memory, from the L-BFGS stage's best gains
        lbfgs, optimizer, out, start = True, "lbfgs", _restart_path(), str(GAINS_LBFGS)
    t0 = time.perf_counter()
    res = jaxatt.fit(
        data=STUDY,
        objective="varfree",
        steps=steps,
        lr=lr if lr is not None else (1.0 if lbfgs else 0.1),
        optimizer=optimizer,
        start=start,
        refine_schedule=ges.GROWING_MEMORY_TIMES,
        transforms=family_transforms(times) if STUDY == "batista-ges" else so3_family_transforms(times),
        out=str(out),
        resume=resume,
        overwrite=not resume,
        quiet=False,
    )
    payload = _payload()
    payload["tuning-lbfgs-restart" if restart else "tuning-lbfgs" if lbfgs else "tuning"] = {
        "status": res.status,
        "best_step": res.best_step,
        "best_loss_deg2": res.best_loss,
        "history": res.history,
        "wall_s": time.perf_counter() - t0,
        "step_s": [h.get("step_s") for h in res.history if "train_loss" in h],
        "gains": str(out.relative_to(HERE.parent)),
        "settings": {
            "steps": steps,
            "lr": lr,
            "optimizer": optimizer,
            "start": start and str(pathlib.Path(start).relative_to(HERE.parent)) or "paper",
            "family": "research/ges_refined_start.py family_transforms (8)"
            if STUDY == "batista-ges"
            else "so3_family_transforms (8)",
        },
    }
    io.write_json(OUT, payload)


def gain_sets():
    s = studies.get(STUDY).setup()
    shipped = "growing" if STUDY == "batista-ges" else "shipped"
    sets = {"paper": s.params, shipped: gainsfile.apply(s.params, gainsfile.read(GROWING)["gains"])}
    if GAINS_OUT.exists():
        sets["varfree-tuned"] = gainsfile.apply(s.params, gainsfile.read(GAINS_OUT)["gains"])
    if GAINS_LBFGS.exists():
        sets["varfree-lbfgs"] = gainsfile.apply(s.params, gainsfile.read(GAINS_LBFGS)["gains"])
    if _restart_path().exists():
        sets["varfree-lbfgs-restart"] = gainsfile.apply(s.params, gainsfile.read(_restart_path())["gains"])
    return s, sets


def predict() -> None:
    s, sets = gain_sets()
    payload = _payload()
    out = {}
    for label, p in sets.items():
        t0 = time.perf_counter()
        r = V.predict(s.observer, s.scenario, p, duration=s.duration, dt=s.dt, windows=(("steady", 2400.0, math.inf),))
        w = r["windows"]["steady"]
        out[label] = {
            "rms_deg": w["rms_deg"],
            "mean_deg": w["mean_deg"],
            "mean_sq_deg2": w["mean_sq_deg2"],
            "wall_s": time.perf_counter() - t0,
        }
        print(f"{label}: predicted RMS {w['rms_deg']:.4f} deg, mean {w['mean_deg']:.4f} deg", flush=True)
    payload["prediction"] = out
    io.write_json(OUT, payload)


def evaluate(runs: int, seed: int, chunk: int, only=None) -> None:
    s, sets = gain_sets()
    if only:
        sets = {k: v for k, v in sets.items() if k in only}
    payload = _payload()
    ev = payload.setdefault("heldout", {"seed": seed, "runs": runs, "per_run_mean_angle_deg": {}})
    if ev.get("seed") != seed or ev.get("runs") != runs:
        ev = payload["heldout"] = {"seed": seed, "runs": runs, "per_run_mean_angle_deg": {}}
    for label, p in sets.items():
        if len(ev["per_run_mean_angle_deg"].get(label, [])) >= runs:
            continue
        t0 = time.perf_counter()

        def save(res, label=label, t0=t0):
            ev["per_run_mean_angle_deg"][label] = np.asarray(res.per_run["mean_angle_error_deg"], float).tolist()
            io.write_json(OUT, payload)
            print(f"{label}: {len(res.run_indices)}/{runs} runs ({time.perf_counter() - t0:.0f} s)", flush=True)

        r = montecarlo.monte_carlo(
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
            on_chunk=save,
        )
        save(r)
    if "paper" not in ev["per_run_mean_angle_deg"]:
        return
    base = np.asarray(ev["per_run_mean_angle_deg"]["paper"])
    ev["summary"] = {}
    for label, v in ev["per_run_mean_angle_deg"].items():
        v = np.asarray(v)
        d = v - base
        ev["summary"][label] = {
            "mean_deg": float(v.mean()),
            "se_deg": float(v.std(ddof=1) / math.sqrt(len(v))),
            "change_vs_paper": float(v.mean() / base.mean() - 1.0),
            "change_se": float(d.std(ddof=1) / math.sqrt(len(d)) / base.mean()),
            "runs_better": float(np.mean(d < 0)),
        }
        e = ev["summary"][label]
        print(
            f"{label}: {e['mean_deg']:.4f} deg (SE {e['se_deg']:.4f}); vs paper {100 * e['change_vs_paper']:+.1f} % "
            f"(paired SE {100 * e['change_se']:.1f}), {100 * e['runs_better']:.0f} % of runs better",
            flush=True,
        )
    io.write_json(OUT, payload)


def ship(restart: bool = False) -> None:
    """Write the L-BFGS stage's best gains as the shipped gains file (batista-ges: batista-ges-gradient.json, with the
    Adam stage's history, so the file holds the whole path from the paper's gains; batista-so3:
    batista-so3-gradient.json, L-BFGS straight from the paper's gains): the gains file without its resume state.
    ``restart``: the restarted L-BFGS stage's best gains (batista-so3), with the first stage's history."""
    src = _restart_path() if restart else GAINS_LBFGS
    d = io.read_json(src)
    if d.get("status") not in ("done", "early-stopped"):
        raise SystemExit(f"{src}: status {d.get('status')!r}; finish the tuning first")
    d.pop("resume", None)
    n_lbfgs = sum("train_loss" in h for h in d["history"])
    n_restart = 0
    if restart:
        first = io.read_json(GAINS_LBFGS)
        n_restart, n_lbfgs = n_lbfgs, sum("train_loss" in h for h in first["history"])
        d["restart_start"], d["start"] = d["start"], first["start"]  # the whole path starts at the paper's gains
        d["first_lbfgs_stage"] = {
            "history": first["history"],
            "settings": first["settings"],
            "best_loss": first.get("best_loss"),
        }
    if STUDY == "batista-ges":
        adam = io.read_json(GAINS_OUT)
        d["notes"] = [
            "tuned by gradients alone from the paper's gains (Table 1 and the literal Q of batista2019-ges Section IV) "
            "on the variance-free loss (expected squared angle error over t >= 2400 s, jaxatt.fitting.varfree): "
            f"{sum('train_loss' in h for h in adam['history'])} Adam steps (lr 0.1), then "
            f"{n_lbfgs} L-BFGS steps, through the 8-number family of "
            "research/ges_refined_start.py; no Monte Carlo runs were used",
            "rerun: python research/varfree_tune.py --phase tune --steps 13; "
            "--phase tune --optimizer lbfgs --steps 15; --phase ship",
        ]
        d["adam_stage"] = {"history": adam["history"], "settings": adam["settings"], "best_loss": adam.get("best_loss")}
    else:
        d["notes"] = [
            "tuned by gradients alone from the paper's gains (Table 1 and Section 4 of batista2019-so3) on the "
            "variance-free loss (expected squared angle error over t >= 2400 s, jaxatt.fitting.varfree): "
            f"{n_lbfgs} L-BFGS steps through 8 numbers (two levels of alpha1, two levels and a power of t of alpha2 "
            "on the schedule refined at 900, 1200, ..., 3300 s; alpha0, alpha3, alpha4)"
            + (f", then {n_restart} L-BFGS steps with a fresh memory from that stage's best" if restart else "")
            + "; no Monte Carlo runs were used",
            "rerun: python research/varfree_tune.py --study batista-so3 --phase tune --optimizer lbfgs "
            f"--steps {n_lbfgs}; "
            + (f"--study batista-so3 --phase tune --restart --steps {n_restart}; " if restart else "")
            + "--study batista-so3 --phase ship"
            + (" --restart" if restart else ""),
        ]
    io.write_json(SHIPPED, d)
    print(f"wrote {SHIPPED.relative_to(HERE.parent)} (best loss {d.get('best_loss')})")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--phase", choices=("tune", "predict", "evaluate", "ship"), required=True)
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--lr", type=float, default=None, help="Adam: 0.1; L-BFGS: the cap on its step (1)")
    ap.add_argument(
        "--optimizer",
        choices=("adam", "lbfgs"),
        default="adam",
        help="adam from the paper's gains, or lbfgs from the Adam stage's best gains",
    )
    ap.add_argument("--resume", action="store_true")
    ap.add_argument(
        "--restart",
        action="store_true",
        help="--phase tune: L-BFGS with a fresh memory from the L-BFGS stage's best gains (its own gains file); "
        "--phase ship: ship that stage's best gains",
    )
    ap.add_argument("--eval-runs", type=int, default=300)
    ap.add_argument("--eval-seed", type=int, default=4000)
    ap.add_argument("--eval-chunk", type=int, default=100)
    ap.add_argument("--sets", nargs="*", help="evaluate only these gain sets (paper, growing, varfree-tuned)")
    ap.add_argument(
        "--study",
        choices=("batista-ges", "batista-so3"),
        default="batista-ges",
        help="batista-so3: the same family on alpha1 / alpha2, L-BFGS from the paper's gains (--optimizer lbfgs)",
    )
    a = ap.parse_args(argv)
    _use(a.study)
    if a.phase == "tune":
        tune(a.steps, a.lr, a.resume, a.optimizer, a.restart)
    elif a.phase == "predict":
        predict()
    elif a.phase == "ship":
        ship(a.restart)
    else:
        evaluate(a.eval_runs, a.eval_seed, a.eval_chunk, a.sets)


if __name__ == "__main__":
    main()
