"""jaxatt's fused Monte Carlo against a plain JAX implementation of the same study (issue 19), in run-steps per
second (batch x steps / wall time), float64.

Measured, for each study (batista-ges, batista-so3, nlio-case1 (NLIO-FG), complementary) and each batch size:

* ``fused``: what ``monte_carlo`` compiles for one chunk on one device: ``jaxatt.engine.compiled`` of the study's
  (tuned) observer with an ``engine.Simulated`` source (truth and sensors in the scan, the study's per-run
  initial-estimate draw if any) and ``montecarlo.metrics_reducer`` (window from t = 0, no traces): every error of
  the study's ``errors`` and the angle error reduced in the scan (as benchmarks/throughput.py's ``fused`` rows).
* ``fused_angle`` (unless ``--no-angle-only``): the same with a reducer that accumulates only the angle error's
  mean, max and last value, as the plain version does (what the metrics cost, and a like-for-like ratio).
* ``plain``: benchmarks/plain_jax.py: truth, sensors and observer of a run in one ``lax.scan``, ``vmap`` over the
  runs' keys, ``jit``; noise drawn per step with ``fold_in(key, k)``; only the angle error is accumulated.

Both are compiled ahead of time (compile time reported separately), called once to warm up, then timed
interleaved (fused, fused_angle, plain, fused, ...; best of each), so all see the same machine load. ``ratio`` =
fused run-steps/s / plain run-steps/s (``ratio_angle_only``: fused_angle / plain); the issue's goals are >= 10
(batista-ges) and >= 5 (the others). The mean angle error over runs is printed as a sanity check (jaxatt and the
plain version draw different noise streams: equal in distribution, not in value).

Usage: python benchmarks/plain_vs_fused.py [--quick] [--batches 1000 100] [--steps 2000] [--studies ...]
"""

from __future__ import annotations

import argparse
import functools
import os
import pathlib
import sys
import time
from typing import Any, Dict, List, Tuple

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


@functools.lru_cache(maxsize=None)
def angle_only_reducer():
    """A reducer that accumulates only what the plain version does: the angle error's mean, max and last value."""
    import jax.numpy as jnp

    from jaxatt import engine, metrics

    def init(t0, truth0, out0):
        z = jnp.zeros((), engine.estimate_r(out0).dtype)
        return (z, z, z, z), None

    def update(acc, t, truth, out):
        r = engine.estimate_r(out)
        ang = metrics.angle_error_deg(truth.r.astype(r.dtype), r)
        return (acc[0] + ang, acc[1] + 1.0, jnp.maximum(acc[2], ang), ang), None

    def finish(acc):
        return {
            "mean_angle_error_deg": acc[0] / jnp.maximum(acc[1], 1.0),
            "max_angle_error_deg": acc[2],
            "final_angle_error_deg": acc[3],
        }

    return engine.Reducer(init, update, finish, 0)


def measure(study: str, batch: int, n_steps: int, *, repeats: int, min_time: float, angle_only: bool, seed: int = 0):
    """Compile the programs of ``study``, then time them interleaved; one result row."""
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
    keys = montecarlo.run_keys(seed, np.arange(batch))
    reducers = {"fused": montecarlo.metrics_reducer(s.errors_fn, 0.0, (), 0, None, 0.5 * dt)}
    if angle_only:
        reducers["fused_angle"] = angle_only_reducer()
    programs: Dict[str, Tuple[Any, tuple]] = {}  # kind -> (jitted, args)
    for kind, reducer in reducers.items():
        fn = engine.compiled(s.observer, source, reducer, None, hold=s.hold, obs_dtype=f64)
        programs[kind] = (fn, (s.scenario, s.params, keys))
    programs["plain"] = (plain_jax.STUDIES[study](n_steps, dt), (keys,))

    row: Dict[str, Any] = {"study": study, "observer": s.observer.name, "hold": s.hold, "batch": batch}
    row["steps"] = n_steps
    compiled, first_out = {}, {}
    for kind, (fn, args) in programs.items():
        compiled[kind], row[f"{kind}_lower_s"], row[f"{kind}_compile_s"] = _compile(fn, *args)
    for kind, (_, args) in programs.items():
        first_out[kind], row[f"{kind}_first_call_s"] = _first(compiled[kind], *args)

    times: Dict[str, List[float]] = {kind: [] for kind in programs}
    while min(len(v) for v in times.values()) < repeats or min(sum(v) for v in times.values()) < min_time:
        for kind, (_, args) in programs.items():  # interleaved: fused, (fused_angle,) plain, fused, ...
            t0 = time.perf_counter()
            jax.block_until_ready(compiled[kind](*args))
            times[kind].append(time.perf_counter() - t0)
        if len(times["plain"]) >= 50:
            break
    errs = {}
    for kind, out in first_out.items():
        summary = out if kind == "plain" else out.summary
        errs[kind] = float(np.mean(np.asarray(summary["mean_angle_error_deg"], float)))
        best = min(times[kind])
        row[f"{kind}_times_s"] = times[kind]
        row[f"{kind}_wall_s"] = best
        row[f"{kind}_run_steps_per_s"] = batch * n_steps / best
        row[f"{kind}_mean_angle_error_deg"] = errs[kind]
    row["ratio"] = row["fused_run_steps_per_s"] / row["plain_run_steps_per_s"]
    if angle_only:
        row["ratio_angle_only"] = row["fused_angle_run_steps_per_s"] / row["plain_run_steps_per_s"]
    row["goal"] = GOALS[study]
    row["meets_goal"] = bool(row["ratio"] >= GOALS[study])
    row["finite"] = bool(np.all(np.isfinite(list(errs.values()))))
    row["loadavg_1m"] = _load()
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="batch 100, 500 steps, 2 timed calls each (a smoke run)")
    ap.add_argument("--batches", type=int, nargs="+", default=None, help="runs per call (default 1000; quick 100)")
    ap.add_argument("--steps", type=int, default=None, help="steps per run at 100 Hz (default 2000; quick 500)")
    ap.add_argument("--studies", nargs="+", default=list(STUDIES), choices=STUDIES)
    ap.add_argument("--repeats", type=int, default=None, help="timed calls of each (default 3; quick 2)")
    ap.add_argument("--min-time", type=float, default=None, help="at least this many seconds of timed calls each")
    ap.add_argument(
        "--no-angle-only", action="store_true", help="skip the fused program with the angle-only reducer (fused_angle)"
    )
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
            rows.append(
                measure(study, b, n_steps, repeats=repeats, min_time=min_time, angle_only=not args.no_angle_only)
            )
    C.print_table(
        rows,
        [
            "study",
            "batch",
            "steps",
            "fused_compile_s",
            "plain_compile_s",
            "fused_run_steps_per_s",
            "fused_angle_run_steps_per_s",
            "plain_run_steps_per_s",
            "ratio",
            "ratio_angle_only",
            "goal",
            "loadavg_1m",
        ],
        title="jaxatt fused Monte Carlo vs plain JAX, float64 (ratio = fused / plain run-steps per second)",
    )
    C.print_table(
        rows,
        [
            "study",
            "batch",
            "fused_mean_angle_error_deg",
            "fused_angle_mean_angle_error_deg",
            "plain_mean_angle_error_deg",
        ],
        title="Mean angle error over runs (deg; different noise streams, same distribution)",
    )
    meta["machine"]["loadavg_1_5_15_end"] = C.machine_info()["loadavg_1_5_15"]
    data = {
        "settings": {
            "quick": args.quick,
            "batches": batches,
            "steps": n_steps,
            "studies": args.studies,
            "angle_only": not args.no_angle_only,
            "repeats": repeats,
            "min_time_s": min_time,
            "dt_s": 0.01,
            "dtype": "float64",
            "timing": "AOT-compiled functions, one warm-up call each, then fused, fused_angle and plain called in "
            "turn; "
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
