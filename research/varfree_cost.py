"""What one tuning step costs with the variance-free loss against one 64-run Monte Carlo gradient step (issue 20
item 2), measured back to back in one process on batista-ges (Section IV: 3600 s at 100 Hz, window t >= 2400 s,
float64, CPU), both as ``jaxatt.fit`` computes them for the tuning of research/varfree_tune.py: the paper's gains
with the schedule refined at the growing-memory times, tuned through the 8-number family of
research/ges_refined_start.py.

* ``varfree_forward``: the variance-free loss alone (:func:`jaxatt.fitting.varfree.varfree_objective`);
* ``varfree_step``: its value and gradient in forward mode (``fitter.value_and_grad_forward``, what the fitter uses
  for at most ``fitter.FORWARD_MODE_MAX`` numbers): one tuning step, no runs, no sampling noise;
* ``mc_forward`` / ``mc_step``: the Monte Carlo loss over ``--runs`` runs (``fitter.simulated_objective``) and its
  value and gradient in reverse mode through the checkpointed scan (the fitter's Monte Carlo step).

Each is compiled ahead of time (compile time reported apart) and called once. Both costs are linear in the
number of time steps, so their ratio does not depend on ``--duration``. Results: research/results/varfree-cost.json.

Usage: python research/varfree_cost.py [--runs 64] [--duration 3600]
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np

from jaxatt import io, montecarlo, schedule, studies
from jaxatt.fitting import fitter, losses
from jaxatt.fitting import parametrize as P
from jaxatt.fitting import varfree as V
from jaxatt.observers import batista_ges as ges
from jaxatt.observers import registry


def timed(fn, *args):
    """(compile s, one call s, result) of a jitted function: compiled ahead of time, then called once."""
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    c = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    return c, time.perf_counter() - t0, out


def main(argv=None):
    from ges_refined_start import family_transforms

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=64)
    ap.add_argument("--duration", type=float, default=3600.0)
    a = ap.parse_args(argv)
    s = studies.get("batista-ges").setup(duration=a.duration, window_start=a.duration * 2 / 3)
    times = [t for t in ges.GROWING_MEMORY_TIMES if t < a.duration]
    s = s._replace(params=schedule.refine(s.params, times, ["alpha1", "alpha2"]))
    bound = P.for_gains(
        registry.get(s.entry).gains, transforms=family_transforms(np.asarray(s.params.switch_times))
    ).bind(s.params)
    theta = bound.init(jnp.float64)
    spec = losses.loss_spec("angle_sq", steady_start=s.window_start)
    res = {
        "environment": io.environment(),
        "study": "batista-ges",
        "duration_s": s.duration,
        "dt_s": s.dt,
        "window_start_s": s.window_start,
        "n_tunable": int(sum(np.size(v) for v in theta.values())),
        "runs": a.runs,
    }
    out = HERE / "results" / "varfree-cost.json"

    def record(name, fn, *args):
        c, r, val = timed(fn, *args)
        res[name] = {"compile_s": c, "call_s": r}
        print(f"{name}: {r:.1f} s (compiled in {c:.1f} s)", flush=True)
        io.write_json(out, res)
        return val

    vf = V.varfree_objective(s, bound, spec)
    batch = jnp.zeros(())
    record("varfree_forward", jax.jit(lambda th: vf(th, batch)[0]), theta)
    record("varfree_step", jax.jit(lambda th: fitter.value_and_grad_forward(vf)(th, batch)), theta)
    mc = fitter.simulated_objective(s, bound, spec, devices=1)
    keys = montecarlo.run_keys(0, range(a.runs))
    record("mc_forward", jax.jit(lambda th: mc(th, keys)[0]), theta)
    record("mc_step", jax.jit(jax.value_and_grad(lambda th: mc(th, keys)[0])), theta)
    res["varfree_step_over_mc_step"] = res["varfree_step"]["call_s"] / res["mc_step"]["call_s"]
    res["varfree_step_over_varfree_forward"] = res["varfree_step"]["call_s"] / res["varfree_forward"]["call_s"]
    res["mc_step_over_mc_forward"] = res["mc_step"]["call_s"] / res["mc_forward"]["call_s"]
    print(
        f"variance-free step / 64-run Monte Carlo step: {res['varfree_step_over_mc_step']:.2f}; "
        f"steps over forward passes: varfree {res['varfree_step_over_varfree_forward']:.1f}, "
        f"Monte Carlo {res['mc_step_over_mc_forward']:.1f}",
        flush=True,
    )
    io.write_json(out, res)


if __name__ == "__main__":
    main()
