"""Throughput of the fused Monte Carlo (truth + sensors + GES observer + on-the-fly metrics) of the
batista-ges experiment, in run-steps per second (batch x steps / wall time), against a plain-numpy loop.

Measured:

* ``fused``: the batch function ``monte_carlo`` runs for each chunk: ``jaxatt.engine.compiled`` of the study's
  observer with an ``engine.Simulated`` source and ``montecarlo.metrics_reducer`` (one device, no traces),
  compiled ahead of time per (dtype, batch) (compile time reported), run once to warm up, then timed (best of
  several calls). One call = one vmapped batch of B runs (``monte_carlo`` itself splits runs into chunks of 250
  by default). dtypes: ``float64``; ``float32`` = observer in float32, truth and noise in float64 (what
  ``monte_carlo(dtype=float32)`` does with x64 enabled); ``float32-x64off`` = everything float32 (x64
  disabled, in a subprocess).
* ``observer_only``: the GES observer alone over a pre-generated log (``montecarlo.log_runner``, the scan of
  ``montecarlo.run``), batch 1.
* ``numpy``: benchmarks/numpy_reference.py at batch 1, fused truth + sensors + observer loop, and observer
  alone over a log.
* ``api``: wall time of two identical ``monte_carlo`` calls (small), which shows the per-call compile.
* ``--full``: a 1000-run x 3600 s Monte Carlo through the public ``monte_carlo`` (chunk 250), in a fresh
  subprocess: wall time, peak RSS (ru_maxrss) and the paper's headline number.

Usage: python benchmarks/throughput.py [--quick] [--full] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

import _common as C  # noqa: E402

MARK = "@@RESULT@@ "
DEFAULT_BATCHES = (1, 10, 100, 1000)


def steps_for(batch: int, quick: bool) -> int:
    """Steps per run: at least 2000 (20 s at 100 Hz), more for small batches (~2e5 run-steps per call)."""
    lo, total = (1000, 20_000) if quick else (2000, 200_000)
    return max(lo, -(-total // batch))


def _load():
    """1-minute load average (other processes on the machine distort timings; compare with cpu_count)."""
    try:
        return round(os.getloadavg()[0], 2)
    except OSError:
        return None


# ----------------------------------------------------------------------------------------------------------
# JAX measurements
# ----------------------------------------------------------------------------------------------------------
def _experiment():
    from jaxatt.studies import batista_ges as exp

    return exp


def measure_fused(batch: int, n_steps: int, dtype: str, *, repeats: int, min_time: float):
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxatt import engine, montecarlo

    exp = _experiment()
    cfg = exp.Config(duration=n_steps * exp.DT)
    # what monte_carlo(dtype=...) compiles for one chunk on one device: the observer in obs_dtype, truth and
    # sensors in the widest float available, metrics reduced in the scan (window from t = 0), no traces
    obs_dtype = jnp.dtype(jnp.float32 if dtype.startswith("float32") else jnp.float64)
    sim_dtype = jnp.dtype(jnp.result_type(float))
    source = engine.Simulated(n_steps, cfg.dt, sim_dtype)
    reducer = montecarlo.metrics_reducer(exp.errors, 0.0, (), 0, None, 0.5 * cfg.dt)
    fn = engine.compiled(exp.observer(cfg), source, reducer, None, hold=cfg.hold, obs_dtype=obs_dtype)
    scn, params = exp.scenario(cfg), exp.params(cfg)
    keys = montecarlo.run_keys(0, np.arange(batch))
    t0 = time.perf_counter()
    compiled = fn.lower(scn, params, keys).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    summary = jax.block_until_ready(compiled(scn, params, keys)).summary
    first_s = time.perf_counter() - t0
    tm = C.time_it(lambda: compiled(scn, params, keys), repeats=repeats, min_time=min_time, sync=jax.block_until_ready)
    final_angle = np.asarray(summary["final_angle_error_deg"], float)
    return {
        "kind": "fused",
        "dtype": dtype,
        "obs_dtype": str(obs_dtype),
        "sim_dtype": str(sim_dtype),
        "batch": batch,
        "steps": n_steps,
        "compile_s": compile_s,
        "first_call_s": first_s,
        "wall_s": tm["best_s"],
        "wall_median_s": tm["median_s"],
        "calls": len(tm["times_s"]),
        "run_steps_per_s": batch * n_steps / tm["best_s"],
        "us_per_run_step": 1e6 * tm["best_s"] / (batch * n_steps),
        "finite": bool(np.all(np.isfinite(final_angle))),
        "loadavg_1m": _load(),
    }


def _log(n_steps: int, seed: int = 0):
    """Noisy Section-IV log from the numpy simulator (t, gyr, mag)."""
    import numpy as np
    import numpy_reference as npref

    exp = _experiment()
    cfg = exp.Config()
    t, gyr, mag, _ = npref.simulate_numpy(
        n_steps,
        cfg.dt,
        rate=npref.batista_rates(),
        ref_nav=np.asarray(cfg.reference_nT, float),
        earth_rate_nav=np.asarray(exp.earth.earth_rate_ned(cfg.latitude_deg)),
        gyro_arw=exp.imu.arw_deg_per_hour_to_rad(cfg.gyro_arw_deg_h_rthz),
        mag_noise=cfg.mag_noise_nT,
        rng=np.random.default_rng(seed),
    )
    return t, gyr, mag


def measure_observer_only(n_steps: int, dtype: str, *, repeats: int, min_time: float):
    import jax
    import jax.numpy as jnp

    from jaxatt import montecarlo
    from jaxatt.types import ImuSample

    exp = _experiment()
    cfg = exp.Config()
    dt_ = jnp.float32 if dtype == "float32" else jnp.float64
    t, gyr, mag = _log(n_steps)
    samples = ImuSample(t=jnp.asarray(t, dt_), gyr=jnp.asarray(gyr, dt_), mag=jnp.asarray(mag, dt_))
    p = exp.params(cfg, dtype=dt_)
    dts = jnp.asarray(cfg.dt, dt_)
    go = montecarlo.log_runner(exp.observer(cfg), cfg.hold, dt_)  # what montecarlo.run runs
    t0 = time.perf_counter()
    compiled = jax.jit(go).lower(p, samples, dts).compile()  # the padding (if any) and the scan, one program
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(p, samples, dts))
    tm = C.time_it(lambda: compiled(p, samples, dts), repeats=repeats, min_time=min_time, sync=jax.block_until_ready)
    return {
        "kind": "observer_only",
        "dtype": dtype,
        "batch": 1,
        "steps": n_steps,
        "compile_s": compile_s,
        "wall_s": tm["best_s"],
        "wall_median_s": tm["median_s"],
        "calls": len(tm["times_s"]),
        "run_steps_per_s": n_steps / tm["best_s"],
        "us_per_run_step": 1e6 * tm["best_s"] / n_steps,
        "loadavg_1m": _load(),
    }


def measure_api_recompile(runs: int = 10, duration: float = 20.0):
    """Two identical monte_carlo calls with the same objects: does the second one compile again?"""
    import jax.numpy as jnp

    from jaxatt import montecarlo
    from jaxatt.observers import batista_ges as ges

    exp = _experiment()
    cfg = exp.Config(duration=duration)
    scn, obs, p = exp.scenario(cfg), exp.observer(cfg), exp.params(cfg)
    walls = []
    for _ in range(2):
        r = montecarlo.monte_carlo(
            scn,
            obs,
            p,
            runs=runs,
            duration=duration,
            dt=cfg.dt,
            errors_fn=exp.errors,
            window_start=0.0,
            dtype=jnp.float64,
            validate=ges.check_params,
        )
        walls.append(r.wall_s)
    return {
        "kind": "api_monte_carlo",
        "dtype": "float64",
        "batch": runs,
        "steps": int(round(duration / cfg.dt)),
        "first_call_s": walls[0],
        "second_call_s": walls[1],
    }


# ----------------------------------------------------------------------------------------------------------
# numpy reference
# ----------------------------------------------------------------------------------------------------------
def measure_numpy(n_steps: int):
    import numpy as np
    import numpy_reference as npref

    exp = _experiment()
    cfg = exp.Config()
    p = npref.NpParams.from_any(exp.params(cfg))
    kw = dict(
        rate=npref.batista_rates(),
        ref_nav=np.asarray(cfg.reference_nT, float),
        earth_rate_nav=np.asarray(exp.earth.earth_rate_ned(cfg.latitude_deg)),
        gyro_arw=exp.imu.arw_deg_per_hour_to_rad(cfg.gyro_arw_deg_h_rthz),
        mag_noise=cfg.mag_noise_nT,
    )
    npref.simulate_and_observe(50, cfg.dt, p, rng=np.random.default_rng(1), **kw)  # warm caches
    t0 = time.perf_counter()
    npref.simulate_and_observe(n_steps, cfg.dt, p, rng=np.random.default_rng(0), **kw)
    fused_s = time.perf_counter() - t0
    t, gyr, mag = _log(n_steps)

    class Log:
        pass

    log = Log()
    log.t, log.gyr, log.mag = t, gyr, mag
    t0 = time.perf_counter()
    npref.run_numpy(log, p, dt=cfg.dt)
    obs_s = time.perf_counter() - t0
    return [
        {
            "kind": "numpy_fused",
            "dtype": "float64",
            "batch": 1,
            "steps": n_steps,
            "wall_s": fused_s,
            "run_steps_per_s": n_steps / fused_s,
            "us_per_run_step": 1e6 * fused_s / n_steps,
            "loadavg_1m": _load(),
        },
        {
            "kind": "numpy_observer_only",
            "dtype": "float64",
            "batch": 1,
            "steps": n_steps,
            "wall_s": obs_s,
            "run_steps_per_s": n_steps / obs_s,
            "us_per_run_step": 1e6 * obs_s / n_steps,
            "loadavg_1m": _load(),
        },
    ]


# ----------------------------------------------------------------------------------------------------------
# Full-size Monte Carlo (subprocess: a clean peak RSS)
# ----------------------------------------------------------------------------------------------------------
def full_monte_carlo(runs: int, duration: float, chunk: int, dtype: str):
    import jax.numpy as jnp
    import numpy as np

    from jaxatt import montecarlo
    from jaxatt.observers import batista_ges as ges

    exp = _experiment()
    cfg = exp.Config(duration=duration)
    rss0 = C.peak_rss_mib()
    chunks = []
    t_last = [time.perf_counter()]

    def on_chunk(res):
        now = time.perf_counter()
        chunks.append(
            {"runs_done": int(len(res.run_indices)), "chunk_s": now - t_last[0], "peak_rss_mib": C.peak_rss_mib()}
        )
        t_last[0] = now
        print(
            f"  {len(res.run_indices)}/{runs} runs, {res.wall_s:.1f} s, peak RSS {C.peak_rss_mib():.0f} MiB",
            file=sys.stderr,
            flush=True,
        )

    t0 = time.perf_counter()
    res = montecarlo.monte_carlo(
        exp.scenario(cfg),
        exp.observer(cfg),
        exp.params(cfg),
        runs=runs,
        duration=duration,
        dt=cfg.dt,
        errors_fn=exp.errors,
        window_start=cfg.window_start,
        hold=cfg.hold,
        chunk=chunk,
        dtype=jnp.float32 if dtype == "float32" else jnp.float64,
        validate=ges.check_params,
        on_chunk=on_chunk,
    )
    wall = time.perf_counter() - t0
    n_steps = int(round(duration / cfg.dt))
    mean_err = np.asarray(res.per_run["mean_angle_error_deg"], float)
    return {
        "kind": "full_monte_carlo",
        "dtype": dtype,
        "runs": runs,
        "duration_s": duration,
        "steps": n_steps,
        "chunk": chunk,
        "wall_s": wall,
        "run_steps_per_s_incl_compile": runs * n_steps / wall,
        "steady_run_steps_per_s": (chunk * n_steps / min(c["chunk_s"] for c in chunks[1:]))
        if len(chunks) > 1
        else None,
        "peak_rss_mib": C.peak_rss_mib(),
        "rss_before_mib": rss0,
        "chunks": chunks,
        "complete": res.complete,
        "mean_angle_error_deg_over_runs": float(np.mean(mean_err)),
        "paper_mean_angle_error_deg": exp.PAPER["slow"]["mean_angle_error_deg"],
    }


# ----------------------------------------------------------------------------------------------------------
# Driver
# ----------------------------------------------------------------------------------------------------------
def _worker(args) -> None:
    """Run in a subprocess; print one JSON line after MARK."""
    import jax

    if args._worker == "x64off":
        jax.config.update("jax_enable_x64", False)
        rows = [
            measure_fused(b, steps_for(b, args.quick), "float32-x64off", repeats=args.repeats, min_time=args.min_time)
            for b in args.batches
        ]
        out = {"rows": rows, "jax": C.jax_info()}
    elif args._worker == "full":
        jax.config.update("jax_enable_x64", True)
        out = {
            "row": full_monte_carlo(args.full_runs, args.full_duration, args.full_chunk, args.full_dtype),
            "jax": C.jax_info(),
        }
    else:
        raise SystemExit(f"unknown worker {args._worker}")
    print(MARK + json.dumps(out), flush=True)


def _subprocess(argv, timeout=None):
    cmd = [sys.executable, str(pathlib.Path(__file__).resolve())] + argv
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, timeout=timeout)
    for line in proc.stdout.splitlines():
        if line.startswith(MARK):
            return json.loads(line[len(MARK) :])
    raise RuntimeError(f"subprocess {argv} failed (rc {proc.returncode}): {proc.stdout[-2000:]}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer steps and repeats (a smoke run, ~1-2 min)")
    ap.add_argument(
        "--full", action="store_true", help="also a 1000-run x 3600 s Monte Carlo (minutes): wall and peak RSS"
    )
    ap.add_argument(
        "--out", default=str(C.RESULTS_DIR), help="directory of the JSON result (default benchmarks/results)"
    )
    ap.add_argument("--batches", type=int, nargs="+", default=list(DEFAULT_BATCHES))
    ap.add_argument(
        "--dtypes",
        nargs="+",
        default=["float64", "float32", "float32-x64off"],
        choices=["float64", "float32", "float32-x64off"],
    )
    ap.add_argument("--numpy-steps", type=int, default=None, help="steps of the numpy loop (default 2000, quick 500)")
    ap.add_argument("--full-runs", type=int, default=1000)
    ap.add_argument("--full-duration", type=float, default=3600.0)
    ap.add_argument("--full-chunk", type=int, default=250)
    ap.add_argument("--full-dtype", default="float64", choices=["float64", "float32"])
    ap.add_argument("--_worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--repeats", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--min-time", type=float, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    args.repeats = args.repeats or (2 if args.quick else 3)
    args.min_time = args.min_time if args.min_time is not None else (0.3 if args.quick else 1.0)
    if args._worker:
        _worker(args)
        return 0

    import jax

    jax.config.update("jax_enable_x64", True)
    meta = C.metadata(sys.argv if argv is None else ["throughput.py"] + list(argv))
    t_start = time.perf_counter()
    rows = []
    common = ["--repeats", str(args.repeats), "--min-time", str(args.min_time), "--batches", *map(str, args.batches)]
    if args.quick:
        common.append("--quick")

    for dtype in args.dtypes:
        if dtype == "float32-x64off":
            print("fused float32 with x64 disabled (subprocess) ...", flush=True)
            rows += _subprocess(["--_worker", "x64off"] + common)["rows"]
            continue
        for b in args.batches:
            n = steps_for(b, args.quick)
            print(f"fused {dtype} batch {b} x {n} steps ...", flush=True)
            rows.append(measure_fused(b, n, dtype, repeats=args.repeats, min_time=args.min_time))

    n_obs = 20_000 if args.quick else 100_000
    for dtype in ("float64", "float32"):
        print(f"observer only {dtype}, {n_obs} steps ...", flush=True)
        rows.append(measure_observer_only(n_obs, dtype, repeats=args.repeats, min_time=args.min_time))

    n_np = args.numpy_steps or (500 if args.quick else 2000)
    print(f"numpy reference, {n_np} steps ...", flush=True)
    rows += measure_numpy(n_np)

    print("monte_carlo API, two identical calls ...", flush=True)
    api = measure_api_recompile()

    numpy_rate = next(r["run_steps_per_s"] for r in rows if r["kind"] == "numpy_fused")
    for r in rows:
        r["speedup_vs_numpy"] = r["run_steps_per_s"] / numpy_rate

    full = None
    if args.full:
        print(
            f"full Monte Carlo: {args.full_runs} runs x {args.full_duration:g} s, {args.full_dtype} (subprocess) ...",
            flush=True,
        )
        full = _subprocess(
            [
                "--_worker",
                "full",
                "--full-runs",
                str(args.full_runs),
                "--full-duration",
                str(args.full_duration),
                "--full-chunk",
                str(args.full_chunk),
                "--full-dtype",
                args.full_dtype,
            ]
        )["row"]

    cols = [
        "kind",
        "dtype",
        "batch",
        "steps",
        "compile_s",
        "wall_s",
        "run_steps_per_s",
        "us_per_run_step",
        "speedup_vs_numpy",
        "loadavg_1m",
    ]
    C.print_table(rows, cols, title="Run-steps per second (truth + sensors + observer unless 'observer_only')")
    C.print_table(
        [api],
        ["kind", "dtype", "batch", "steps", "first_call_s", "second_call_s"],
        title="monte_carlo called twice with the same objects (wall incl. compile)",
    )
    if full is not None:
        C.print_table(
            [full],
            [
                "kind",
                "dtype",
                "runs",
                "steps",
                "chunk",
                "wall_s",
                "run_steps_per_s_incl_compile",
                "steady_run_steps_per_s",
                "peak_rss_mib",
                "mean_angle_error_deg_over_runs",
            ],
            title="Full Monte Carlo",
        )

    meta["machine"]["loadavg_1_5_15_end"] = C.machine_info()["loadavg_1_5_15"]
    data = {
        "settings": {
            "quick": args.quick,
            "batches": args.batches,
            "dtypes": args.dtypes,
            "repeats": args.repeats,
            "min_time_s": args.min_time,
            "dt_s": 0.01,
            "experiment": "batista-ges (slow trajectory)",
            "timing": "best of `calls` warm calls of an AOT-compiled function; "
            "run_steps_per_s = batch * steps / wall_s",
        },
        "rows": rows,
        "api_monte_carlo": api,
        "full_monte_carlo": full,
        "peak_rss_mib_this_process": C.peak_rss_mib(),
        "total_wall_s": time.perf_counter() - t_start,
    }
    path = C.write_results("throughput", data, args.out, meta=meta)
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
