"""Cost per step of the variance-free loss (jaxatt.fitting.varfree) before and after the speed-ups of branch
vfspeed, in one process, interleaved: the module as it was at commit 4a161d1 (loaded from git under another name)
against the working tree's, on batista-ges (float64, dt 0.01 s) with the steady window covering the last third
of the run, as in the 3600-s study (t >= 2400 s).

* forward: ``make_predict_fn`` (E|e|^2 and E|e|) per step;
* gradient: ``jax.value_and_grad`` of ``make_loss_fn`` (checkpoint "auto", the fitter's setting) per step;
* the predictions and gradients of both must agree to 1e-10 relative (asserted);
* estimate of one 3600-s gradient: the per-step time times 360,000 steps (same checkpoint segment, 1000 steps).

Writes research/results/varfree-speed.json. Usage: python research/varfree_speed.py [--duration 30] [--reps 3]
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import pathlib
import subprocess
import sys
import tempfile
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np
from jax import flatten_util

from jaxatt import io, studies
from jaxatt.fitting import losses
from jaxatt.fitting import varfree as NEW

BEFORE = "4a161d1"  # main before the speed-ups


def _old_module():
    cmd = ["git", "show", f"{BEFORE}:jaxatt/fitting/varfree.py"]
    src = subprocess.run(cmd, cwd=HERE.parent, capture_output=True, text=True, check=True).stdout
    path = pathlib.Path(tempfile.mkdtemp()) / "varfree_before.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("jaxatt.fitting._varfree_before", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args()
    s = studies.get("batista-ges").setup()
    dur = args.duration
    start = dur * 2400.0 / 3600.0
    n = int(round(dur / s.dt))
    mods = {"before": _old_module(), "after": NEW}
    fns, compile_s, out = {}, {}, {}
    for name, m in mods.items():
        f = m.make_predict_fn(
            s.observer, s.scenario, s.params, duration=dur, dt=s.dt, windows=(("steady", start, math.inf),)
        )
        fns[("forward", name)] = lambda f=f: f(s.scenario, s.params)
        spec = losses.loss_spec("angle_sq", steady_start=start)
        loss = m.make_loss_fn(s.observer, s.scenario, s.params, duration=dur, dt=s.dt, spec=spec)
        g = jax.jit(jax.value_and_grad(lambda p, loss=loss: loss(s.scenario, p)[0]))
        fns[("gradient", name)] = lambda g=g: g(s.params)
    for key, f in fns.items():
        t0 = time.perf_counter()
        out[key] = jax.block_until_ready(f())
        compile_s[key] = time.perf_counter() - t0
        print(key, "compile + first run", round(compile_s[key], 1), "s", flush=True)
    times = {k: [] for k in fns}
    for _ in range(args.reps):
        for key, f in fns.items():
            t0 = time.perf_counter()
            jax.block_until_ready(f())
            times[key].append(time.perf_counter() - t0)
    rel = {}
    for what in ("forward", "gradient"):
        a = np.asarray(flatten_util.ravel_pytree(out[(what, "before")])[0])
        b = np.asarray(flatten_util.ravel_pytree(out[(what, "after")])[0])
        fin = np.isfinite(a)
        assert np.array_equal(fin, np.isfinite(b)), what
        rel[what] = float(np.max(np.abs(a[fin] - b[fin]) / np.maximum(np.max(np.abs(a[fin])), 1e-300)))
        assert rel[what] < 1e-10, (what, rel[what])
    res = {}
    for what in ("forward", "gradient"):
        per = {k: 1e6 * min(times[(what, k)]) / n for k in mods}
        res[what] = {
            "us_per_step_before": per["before"],
            "us_per_step_after": per["after"],
            "speedup": per["before"] / per["after"],
            "compile_s_before": compile_s[(what, "before")],
            "compile_s_after": compile_s[(what, "after")],
            "max_rel_difference": rel[what],
        }
        print(what, {k: round(v, 3) if isinstance(v, float) else v for k, v in res[what].items()}, flush=True)
    steps_3600 = int(round(3600.0 / s.dt))
    res["gradient_3600s_estimate_s"] = {
        k: res["gradient"][f"us_per_step_{k}"] * steps_3600 * 1e-6 for k in ("before", "after")
    }
    print("3600-s gradient estimate (s)", res["gradient_3600s_estimate_s"])
    io.write_json(
        HERE / "results" / "varfree-speed.json",
        {
            "experiment": "variance-free loss cost per step, before (commit 4a161d1) and after, interleaved",
            "study": "batista-ges",
            "duration_s": dur,
            "window_start_s": start,
            "steps": n,
            "reps": args.reps,
            "note": "min over reps of interleaved calls in one process; the machine was shared (loaded)",
            **res,
        },
    )


if __name__ == "__main__":
    main()
