"""Monte Carlo throughput on the devices JAX sees (one GPU, several GPUs, several hosts, or the CPU): the one script
to run on a GPU machine.

What it measures, on batista-ges (Section IV of Batista et al. 2019 GES: truth, KVH gyro and magnetometer noise,
the observer and the on-the-fly metrics fused in one scan), through the public ``jaxatt.monte_carlo`` with
every visible device (the runs split over them, :mod:`jaxatt.sharding`):

* **throughput**: for each batch B (default 1e3, 1e4, 1e5 runs) and each dtype, one chunk of B runs x
  ``--duration`` s at 100 Hz, called twice; the second (warm) call is timed: run-steps per second = B x steps /
  wall. The first call's extra time is the compile. Peak device memory where the device reports it (GPUs do).
  A batch that does not fit in memory is recorded as failed and the script goes on.
* **consistency**: run k has the same key in every batch, so the first runs of the larger batch must equal the
  smaller batch's to rounding (largest relative difference reported; a wrong result fails loudly here).
* **the full study** (``--full``, default on an accelerator): the paper's 1000 runs x 3600 s, chunk
  ``--full-chunk``, wall time of the call as a user sees it (compile included) and its headline number (mean angle
  error over the steady-state window, against the paper's).

dtypes: ``float64`` (x64 on, as the CLI), ``float32`` (observer in float32, truth and sensors in float64, what
``monte_carlo(dtype=float32)`` does with x64 on); ``--no-x64`` turns x64 off for the whole run (everything
float32: the fastest on consumer GPUs; only ``float32`` then).

On the CPU (or with ``--quick``) the defaults shrink so that it finishes in a few minutes: batches 100 and 1000,
5-s runs, no full study unless ``--full``. tests/test_gpu_script.py runs its smallest form.

Several processes (hosts): start it in every process with ``JAXATT_COORDINATOR``, ``JAXATT_NUM_PROCESSES`` and
``JAXATT_PROCESS_ID`` set (docs/gpu.md); the runs split over every process's devices, process 0 prints and writes.

Usage:
  python benchmarks/gpu.py                       # on a GPU: batches 1e3 1e4 1e5, float64 and float32, full study
  python benchmarks/gpu.py --quick               # smaller: a smoke run
  python benchmarks/gpu.py --batches 1000 --dtypes float32 --no-full
  python benchmarks/gpu.py --no-x64 --dtypes float32

Writes benchmarks/results/gpu-<host>-<UTC>.json (``--out`` to change the folder): the measurements with the
machine, the versions, the git commit, the devices and the date.
"""

from __future__ import annotations

import argparse
import math
import pathlib
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

#: defaults on an accelerator, and on the CPU / with --quick
ACCEL = {"batches": [1000, 10_000, 100_000], "duration": 60.0, "dtypes": ["float64", "float32"], "repeats": 2}
SMALL = {"batches": [100, 1000], "duration": 5.0, "dtypes": ["float64", "float32"], "repeats": 1}


def _say(*a, **kw):
    """Print on process 0 only (every process runs the same script)."""
    from jaxatt.io import is_main_process

    if is_main_process():
        print(*a, **kw, flush=True)


def _peak_device_bytes():
    """Peak bytes in use on the first local device, where it reports them (GPUs, TPUs; the CPU does not)."""
    import jax

    try:
        stats = jax.local_devices()[0].memory_stats()
    except Exception:  # noqa: BLE001 - a diagnostic, never a failure
        return None
    return None if not stats else stats.get("peak_bytes_in_use")


def _study():
    from jaxatt.studies import batista_ges as exp

    return exp


def _mc(exp, cfg, *, runs, chunk, duration, dtype, devices, window_start=0.0, on_chunk=None):
    import jax.numpy as jnp

    from jaxatt import montecarlo

    return montecarlo.monte_carlo(
        exp.scenario(cfg),
        exp.observer(cfg),
        exp.params(cfg),
        runs=runs,
        chunk=chunk,
        duration=duration,
        dt=cfg.dt,
        errors_fn=exp.errors,
        window_start=window_start,
        hold=cfg.hold,
        dtype=jnp.float32 if dtype == "float32" else jnp.float64,
        devices=devices,
        on_chunk=on_chunk,
    )


def measure_batch(batch: int, duration: float, dtype: str, *, repeats: int, devices=None) -> dict:
    """One chunk of ``batch`` runs x ``duration`` s: first call (compile + run), then ``repeats`` warm calls."""
    import numpy as np

    exp = _study()
    cfg = exp.Config(duration=duration)
    n_steps = int(round(duration / cfg.dt))
    row = {"batch": batch, "dtype": dtype, "duration_s": duration, "steps": n_steps}
    try:
        t0 = time.perf_counter()
        _mc(exp, cfg, runs=batch, chunk=batch, duration=duration, dtype=dtype, devices=devices)
        first = time.perf_counter() - t0
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            res = _mc(exp, cfg, runs=batch, chunk=batch, duration=duration, dtype=dtype, devices=devices)
            times.append(time.perf_counter() - t0)
    except Exception as e:  # noqa: BLE001 - out of memory at the largest batch is a result, not a crash
        row.update(ok=False, error=f"{type(e).__name__}: {str(e).splitlines()[0][:300]}")
        return row
    best = min(times)
    final = np.asarray(res.per_run["final_angle_error_deg"], float)
    row.update(
        ok=True,
        first_call_s=first,
        warm_s=best,
        warm_times_s=times,
        compile_s_estimate=max(first - best, 0.0),
        run_steps_per_s=batch * n_steps / best,
        ns_per_run_step=1e9 * best / (batch * n_steps),
        peak_device_bytes=_peak_device_bytes(),
        finite=bool(np.all(np.isfinite(final))),
        per_run={k: np.asarray(v) for k, v in res.per_run.items()},
    )
    return row


def consistency(rows) -> dict:
    """Largest relative difference between the runs common to two batch sizes (same dtype): runs 0 ... B-1 are the
    same runs in every batch, so only rounding may differ."""
    import numpy as np

    out = {}
    for dtype in sorted({r["dtype"] for r in rows}):
        ok = sorted((r for r in rows if r["dtype"] == dtype and r.get("ok")), key=lambda r: r["batch"])
        for small, big in zip(ok, ok[1:]):
            n = small["batch"]
            rel = 0.0
            for k, a in small["per_run"].items():
                b = big["per_run"][k][:n]
                scale = np.maximum(np.abs(a), 1e-300)
                rel = max(rel, float(np.max(np.abs(a - b) / scale)))
            out[f"{dtype}: {n} vs first {n} of {big['batch']}"] = rel
    return out


def full_study(runs: int, duration: float, chunk: int, dtype: str, devices=None) -> dict:
    """The paper's Monte Carlo as a user runs it: wall time of the call (compile included) and its headline."""
    import numpy as np

    exp = _study()
    cfg = exp.Config(duration=duration)
    window = cfg.window_start if duration > cfg.window_start else 0.0
    n_steps = int(round(duration / cfg.dt))
    chunks = []

    def on_chunk(res):
        chunks.append({"runs_done": int(len(res.run_indices)), "wall_s": res.wall_s})
        _say(f"  full study: {len(res.run_indices)}/{runs} runs, {res.wall_s:.1f} s", file=sys.stderr)

    t0 = time.perf_counter()
    res = _mc(
        exp,
        cfg,
        runs=runs,
        chunk=chunk,
        duration=duration,
        dtype=dtype,
        devices=devices,
        window_start=window,
        on_chunk=on_chunk,
    )
    wall = time.perf_counter() - t0
    mean_err = np.asarray(res.per_run["mean_angle_error_deg"], float)
    return {
        "runs": runs,
        "duration_s": duration,
        "steps": n_steps,
        "chunk": chunk,
        "dtype": dtype,
        "window_start_s": window,
        "wall_s": wall,
        "run_steps_per_s_incl_compile": runs * n_steps / wall,
        "chunks": chunks,
        "complete": bool(res.complete),
        "mean_angle_error_deg_over_runs": float(np.mean(mean_err)),
        "paper_mean_angle_error_deg": exp.PAPER["slow"]["mean_angle_error_deg"] if window else None,
        "peak_device_bytes": _peak_device_bytes(),
    }


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--quick", action="store_true", help="the small defaults (automatic on the CPU)")
    ap.add_argument("--batches", type=int, nargs="+", default=None, help="runs per chunk (default 1e3 1e4 1e5)")
    ap.add_argument("--duration", type=float, default=None, help="s per run of the throughput rows (100 Hz)")
    ap.add_argument("--dtypes", nargs="+", default=None, choices=["float64", "float32"])
    ap.add_argument("--no-x64", action="store_true", help="x64 off: everything float32 (with --dtypes float32)")
    ap.add_argument("--repeats", type=int, default=None, help="warm calls per row (best kept)")
    ap.add_argument("--devices", type=int, default=None, help="use the first N devices (default: all)")
    full = ap.add_mutually_exclusive_group()
    full.add_argument("--full", dest="full", action="store_true", default=None, help="run the full study")
    full.add_argument("--no-full", dest="full", action="store_false", help="skip the full study")
    ap.add_argument("--full-runs", type=int, default=1000)
    ap.add_argument("--full-duration", type=float, default=3600.0, help="s per run of the full study")
    ap.add_argument("--full-chunk", type=int, default=1000)
    ap.add_argument("--full-dtype", default="float64", choices=["float64", "float32"])
    ap.add_argument("--out", default=None, help="folder of the JSON result (default benchmarks/results)")
    return ap


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    for name in ("batches", "repeats", "full_runs", "full_chunk", "devices"):
        v = getattr(args, name)
        if v is not None and min(v if isinstance(v, list) else [v]) < 1:
            raise SystemExit(f"gpu.py: error: --{name.replace('_', '-')} must be >= 1, got {v}")
    for name in ("duration", "full_duration"):
        v = getattr(args, name)
        if v is not None and not (math.isfinite(v) and v > 0):
            raise SystemExit(f"gpu.py: error: --{name.replace('_', '-')} must be a positive number of s, got {v}")
    import jax

    from jaxatt.sharding import initialize_distributed

    jax.config.update("jax_enable_x64", not args.no_x64)  # this script decides the precision, not the library
    initialize_distributed()  # several processes when the JAXATT_* variables are set; else nothing
    import _common as C

    from jaxatt.io import is_main_process

    backend = jax.default_backend()
    small = args.quick or backend == "cpu"
    d = SMALL if small else ACCEL
    batches = args.batches or d["batches"]
    duration = args.duration or d["duration"]
    dtypes = args.dtypes or (["float32"] if args.no_x64 else d["dtypes"])
    if args.no_x64 and "float64" in dtypes:
        raise SystemExit("gpu.py: error: --no-x64 runs everything in float32: use --dtypes float32")
    if args.no_x64 and args.full_dtype == "float64":
        args.full_dtype = "float32"
    repeats = args.repeats or d["repeats"]
    run_full = (not small) if args.full is None else args.full
    meta = C.metadata(sys.argv if argv is None else ["gpu.py"] + list(argv))
    devs = jax.devices() if args.devices is None else jax.devices()[: args.devices]
    _say(
        f"backend {backend}: {len(devs)} device(s) {[str(x) for x in devs][:8]} in {jax.process_count()} "
        f"process(es); x64 {'on' if not args.no_x64 else 'off'}"
        + ("; small defaults (CPU or --quick)" if small else "")
    )

    t_start = time.perf_counter()
    rows = []
    for dtype in dtypes:
        for b in batches:
            n_steps = int(round(duration / _study().DT))
            _say(f"{dtype} batch {b} x {n_steps} steps ...")
            row = measure_batch(b, duration, dtype, repeats=repeats, devices=args.devices)
            rows.append(row)
            if row["ok"]:
                _say(
                    f"  {row['run_steps_per_s']:.3g} run-steps/s ({row['ns_per_run_step']:.3g} ns per run-step; warm "
                    f"{row['warm_s']:.2f} s, first call {row['first_call_s']:.1f} s)"
                    + (
                        f"; peak device memory {row['peak_device_bytes'] / 2**30:.2f} GiB"
                        if row["peak_device_bytes"]
                        else ""
                    )
                )
            else:
                _say(f"  failed: {row['error']}")
    cons = consistency(rows)
    for k, v in cons.items():
        _say(f"same runs in two batches, {k}: largest relative difference {v:.2g}")
    full = None
    if run_full:
        _say(
            f"full study: {args.full_runs} runs x {args.full_duration:g} s, chunk {args.full_chunk}, "
            f"{args.full_dtype} ..."
        )
        full = full_study(args.full_runs, args.full_duration, args.full_chunk, args.full_dtype, devices=args.devices)
        _say(
            f"  wall {full['wall_s']:.1f} s (compile included), "
            f"{full['run_steps_per_s_incl_compile']:.3g} run-steps/s; "
            f"mean angle error {full['mean_angle_error_deg_over_runs']:.4g} deg"
            + (f" (paper {full['paper_mean_angle_error_deg']})" if full["paper_mean_angle_error_deg"] else "")
        )
    summary = [{k: v for k, v in r.items() if k != "per_run"} for r in rows]
    if not is_main_process():
        return 0
    path = C.write_results(
        "gpu",
        {
            "settings": {
                "batches": batches,
                "duration_s": duration,
                "dtypes": dtypes,
                "x64": not args.no_x64,
                "repeats": repeats,
                "small_defaults": small,
                "devices": [str(x) for x in devs],
                "process_count": jax.process_count(),
                "full": run_full,
                "full_runs": args.full_runs,
                "full_duration_s": args.full_duration,
                "full_chunk": args.full_chunk,
                "full_dtype": args.full_dtype,
            },
            "rows": summary,
            "consistency_max_rel": cons,
            "full_study": full,
            "total_wall_s": time.perf_counter() - t_start,
        },
        out_dir=args.out,
        meta=meta,
    )
    print(f"results written to {path}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
