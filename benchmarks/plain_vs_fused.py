"""jaxatt's fused Monte Carlo against a plain JAX implementation of the same study (issue 19), in run-steps per
second (batch x steps / wall time), float64.

Measured, for each study (batista-ges, batista-so3, nlio-case1 (NLIO-FG), complementary) and each batch size:

* ``fused``: what ``monte_carlo`` compiles for one chunk on one device: ``jaxatt.engine.compiled`` of the study's
  (tuned) observer with an ``engine.Simulated`` source (truth and sensors in the scan, the study's per-run
  initial-estimate draw if any) and ``montecarlo.metrics_reducer`` (window from t = 0, no traces): every error of
  the study's ``errors`` and the angle error reduced in the scan (as benchmarks/throughput.py's ``fused`` rows).
* ``plain``: benchmarks/plain_jax.py: truth, sensors and observer of a run in one ``lax.scan``, ``vmap`` over the
  runs' keys, ``jit``; noise drawn per step with ``fold_in(key, k)``; only the angle error is accumulated.

Both are compiled ahead of time (compile time reported separately), called once to warm up, then timed
interleaved (fused, plain, fused, plain, ...; best of each), so both see the same machine load. ``ratio`` =
fused run-steps/s / plain run-steps/s; the issue's goals are >= 10 (batista-ges) and >= 5 (the others). The mean
angle error over runs of both is printed as a sanity check (different noise streams: equal in distribution, not
in value).

Usage: python benchmarks/plain_vs_fused.py [--quick] [--batches 1000 100] [--steps 2000] [--studies ...]
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import time
from typing import Dict, List

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

import _common as C  # noqa: E402

STUDIES = ("batista-ges", "batista-so3", "nlio-case1", "complementary")
#: The issue's goals: fused / plain run-steps per second.
GOALS = {"batista-ges": 10.0, "batista-so3": 5.0, "nlio-case1": 5.0, "complementary": 5.0}
DEFAULT_BATCHES = (1000,)


def _load():
    try:
        return round(os.getloadavg()[0], 2)
    except OSError:
        return None


def _compile(fn, *args):
    t0 = time.perf_counter()
    lowered = fn.lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    return compiled, t1 - t0, time.perf_counter() - t1


def _first(compiled, *args):
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    return out, time.perf_counter() - t0


def measure(study: str, batch: int, n_steps: int, *, repeats: int, min_time: float, seed: int = 0):
    """Compile both programs of ``study``, then time them interleaved; one result row."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    import plain_jax

    from jaxatt import engine, montecarlo, studies

    s = studies.get(study).setup(duration=n_steps * 0.01)
    dt = float(s.dt)
    if dt != 0.01:
        raise ValueError(f"{study}: dt = {dt} s, expected 0.01 s")
    f64 = jnp.dtype(jnp.float64)
    source = engine.Simulated(n_steps, dt, f64, s.init_params)
    reducer = montecarlo.metrics_reducer(s.errors_fn, 0.0, (), 0, None, 0.5 * dt)
    fused_fn = engine.compiled(s.observer, source, reducer, None, hold=s.hold, obs_dtype=f64)
    keys = montecarlo.run_keys(seed, np.arange(batch))
    fused, fused_lower_s, fused_compile_s = _compile(fused_fn, s.scenario, s.params, keys)
    plain, plain_lower_s, plain_compile_s = _compile(plain_jax.STUDIES[study](n_steps, dt), keys)
    fused_out, fused_first_s = _first(fused, s.scenario, s.params, keys)
    plain_out, plain_first_s = _first(plain, keys)

    times: Dict[str, List[float]] = {"fused": [], "plain": []}
    calls = {"fused": lambda: fused(s.scenario, s.params, keys), "plain": lambda: plain(keys)}
    while min(len(v) for v in times.values()) < repeats or min(sum(v) for v in times.values()) < min_time:
        for kind in ("fused", "plain"):
            t0 = time.perf_counter()
            jax.block_until_ready(calls[kind]())
            times[kind].append(time.perf_counter() - t0)
        if len(times["fused"]) >= 50:
            break
    run_steps = batch * n_steps
    fused_best, plain_best = min(times["fused"]), min(times["plain"])
    mean_err = lambda out: float(np.mean(np.asarray(out["mean_angle_error_deg"], float)))  # noqa: E731
    fused_err = mean_err(fused_out.summary)
    plain_err = mean_err(plain_out)
    ratio = plain_best / fused_best
    return {
        "study": study,
        "observer": s.observer.name,
        "hold": s.hold,
        "batch": batch,
        "steps": n_steps,
        "fused_lower_s": fused_lower_s,
        "fused_compile_s": fused_compile_s,
        "plain_lower_s": plain_lower_s,
        "plain_compile_s": plain_compile_s,
        "fused_first_call_s": fused_first_s,
        "plain_first_call_s": plain_first_s,
        "fused_times_s": times["fused"],
        "plain_times_s": times["plain"],
        "fused_wall_s": fused_best,
        "plain_wall_s": plain_best,
        "fused_run_steps_per_s": run_steps / fused_best,
        "plain_run_steps_per_s": run_steps / plain_best,
        "ratio": ratio,
        "goal": GOALS[study],
        "meets_goal": bool(ratio >= GOALS[study]),
        "fused_mean_angle_error_deg": fused_err,
        "plain_mean_angle_error_deg": plain_err,
        "finite": bool(np.isfinite(fused_err) and np.isfinite(plain_err)),
        "loadavg_1m": _load(),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="batch 100, 500 steps, 2 timed calls each (a smoke run)")
    ap.add_argument("--batches", type=int, nargs="+", default=None, help="runs per call (default 1000; quick 100)")
    ap.add_argument("--steps", type=int, default=None, help="steps per run at 100 Hz (default 2000; quick 500)")
    ap.add_argument("--studies", nargs="+", default=list(STUDIES), choices=STUDIES)
    ap.add_argument("--repeats", type=int, default=None, help="timed calls of each (default 3; quick 2)")
    ap.add_argument("--min-time", type=float, default=None, help="at least this many seconds of timed calls each")
    ap.add_argument(
        "--out", default=str(C.RESULTS_DIR), help="directory of the JSON result (default benchmarks/results)"
    )
    args = ap.parse_args(argv)
    batches = args.batches or ([100] if args.quick else list(DEFAULT_BATCHES))
    n_steps = args.steps or (500 if args.quick else 2000)
    repeats = args.repeats or (2 if args.quick else 3)
    min_time = args.min_time if args.min_time is not None else (0.0 if args.quick else 1.0)
    if n_steps < 1 or min(batches) < 1 or repeats < 1:
        raise SystemExit("--steps, --batches and --repeats must be >= 1")

    import jax

    jax.config.update("jax_enable_x64", True)
    meta = C.metadata(sys.argv if argv is None else ["plain_vs_fused.py"] + list(argv))
    t_start = time.perf_counter()
    rows = []
    for study in args.studies:
        for b in batches:
            print(f"{study}: batch {b} x {n_steps} steps (load {_load()}) ...", flush=True)
            rows.append(measure(study, b, n_steps, repeats=repeats, min_time=min_time))
    C.print_table(
        rows,
        [
            "study",
            "batch",
            "steps",
            "fused_compile_s",
            "plain_compile_s",
            "fused_run_steps_per_s",
            "plain_run_steps_per_s",
            "ratio",
            "goal",
            "loadavg_1m",
        ],
        title="jaxatt fused Monte Carlo vs plain JAX, float64 (ratio = fused / plain run-steps per second)",
    )
    C.print_table(
        rows,
        ["study", "batch", "fused_mean_angle_error_deg", "plain_mean_angle_error_deg"],
        title="Mean angle error over runs (deg; different noise streams, same distribution)",
    )
    meta["machine"]["loadavg_1_5_15_end"] = C.machine_info()["loadavg_1_5_15"]
    data = {
        "settings": {
            "quick": args.quick,
            "batches": batches,
            "steps": n_steps,
            "studies": args.studies,
            "repeats": repeats,
            "min_time_s": min_time,
            "dt_s": 0.01,
            "dtype": "float64",
            "timing": "AOT-compiled functions, one warm-up call each, then fused and plain called alternately; "
            "wall = best call; run_steps_per_s = batch * steps / wall; ratio = fused / plain run-steps per second",
        },
        "rows": rows,
        "peak_rss_mib_this_process": C.peak_rss_mib(),
        "total_wall_s": time.perf_counter() - t_start,
    }
    path = C.write_results("plain_vs_fused", data, args.out, meta=meta)
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
