"""What one gradient of the variance-free loss costs against one Monte Carlo gradient (issue 20 item 2), measured
back to back in one process on batista-ges (Section IV: 3600 s at 100 Hz, window t >= 2400 s, the paper's gains,
the fitter's default parametrization; float64, CPU).

* variance-free: ``jax.value_and_grad`` of :func:`jaxatt.fitting.varfree.make_loss_fn` (checkpointed scan of the
  linearised observer), and the forward prediction alone;
* Monte Carlo: ``jax.value_and_grad`` of :func:`jaxatt.fitting.losses.make_loss_fn` over ``--runs`` runs (64: the
  step the issue compares with).

Each is called twice: the first call includes compilation, the second is the cost of a step. Results:
research/results/varfree-cost.json.

Usage: python research/varfree_cost.py [--runs 64]
"""

from __future__ import annotations

import argparse
import math
import pathlib
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import jax

jax.config.update("jax_enable_x64", True)

from jaxatt import io, montecarlo, studies
from jaxatt.fitting import losses
from jaxatt.fitting import varfree as V


def timed(fn, *args):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return first, time.perf_counter() - t0, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=64)
    a = ap.parse_args(argv)
    s = studies.get("batista-ges").setup()
    spec = losses.loss_spec("angle_sq", steady_start=s.window_start)
    res = {"environment": io.environment(), "study": "batista-ges", "duration_s": s.duration, "dt_s": s.dt}

    pred = V.make_predict_fn(
        s.observer, s.scenario, s.params, duration=s.duration, dt=s.dt, windows=(("steady", s.window_start, math.inf),)
    )
    c, r, _ = timed(pred, s.scenario, s.params)
    res["varfree_forward"] = {"first_call_s": c, "call_s": r}
    print(f"variance-free forward: {r:.0f} s ({c:.0f} s with compilation)", flush=True)

    vf = V.make_loss_fn(s.observer, s.scenario, s.params, duration=s.duration, dt=s.dt, spec=spec)
    g = jax.jit(jax.value_and_grad(lambda p: vf(s.scenario, p)[0]))
    c, r, _ = timed(g, s.params)
    res["varfree_gradient"] = {"first_call_s": c, "call_s": r}
    print(f"variance-free gradient: {r:.0f} s ({c:.0f} s with compilation)", flush=True)
    io.write_json(HERE / "results" / "varfree-cost.json", res)

    mc = losses.make_loss_fn(s.observer, duration=s.duration, dt=s.dt, spec=spec)
    keys = montecarlo.run_keys(0, range(a.runs))
    gm = jax.jit(jax.value_and_grad(lambda p: mc(s.scenario, p, keys)[0]))
    c, r, _ = timed(gm, s.params)
    res["mc_gradient"] = {"runs": a.runs, "first_call_s": c, "call_s": r}
    print(f"Monte Carlo gradient, {a.runs} runs: {r:.0f} s ({c:.0f} s with compilation)", flush=True)
    io.write_json(HERE / "results" / "varfree-cost.json", res)


if __name__ == "__main__":
    main()
