"""Cost of one gradient of the tuning loss (jaxatt.fit on a study) against one forward pass, and its memory.

Measured, per study (batista-ges, batista-so3), for a horizon T (s, at 100 Hz) and B Monte Carlo seeds:

* ``forward``: the loss alone, ``jit(lambda theta, keys: objective(theta, keys)[0])`` with the objective the
  fitter builds (``jaxatt.fitting.fitter.simulated_objective``: the study's default loss over its steady window,
  every gain the registry tunes by default, ``jaxatt.fitting.parametrize.for_gains``): the fused simulator +
  observer scan of ``monte_carlo`` with the loss accumulated on the fly.
* ``grad``: ``jit(value_and_grad(...))`` of the same function, reverse mode through the whole scan, with the
  scan split into ``jax.checkpoint``-ed segments (``--checkpoint``, default "auto": about sqrt(T) steps, in
  multiples of the 1000-step noise block; 1000 steps for 360,000) or without checkpointing (``off``).

Each measurement runs in its own subprocess, so its peak RSS (ru_maxrss) is its own: reported are the RSS
after compiling (``rss_after_compile_mib``; includes the compiler's peak), the peak over the whole process
(``peak_rss_mib``) and XLA's own buffer accounting of the compiled program (``xla_temp_mib``: scratch memory
of one call, the part that grows with T when reverse mode stores the steps). Times: compile, then the best of
``--repeats`` warm calls (one call when a call is long).

``--scaling`` adds a sweep of horizons at a few seeds, checkpointed and not, showing memory ~ T without
checkpointing and ~ sqrt(T) with it (T / c stored carries + c recomputed steps).

Usage:
  python benchmarks/gradient.py                       # 3600 s x 64 seeds, both experiments (long on 2 cores)
  python benchmarks/gradient.py --duration 360 --runs 8 --experiments batista-ges   # reduced scale
  python benchmarks/gradient.py --scaling-only        # the memory-vs-horizon sweep only
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


def _rss_now_mib() -> float:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def _load():
    try:
        return round(os.getloadavg()[0], 2)
    except OSError:
        return None


def measure(
    experiment: str,
    duration: float,
    runs: int,
    mode: str,
    checkpoint,
    repeats: int,
    max_repeat_s: float,
    step_remat=None,
) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from jaxatt import montecarlo, studies
    from jaxatt.fitting import fitter, losses
    from jaxatt.fitting import parametrize as P
    from jaxatt.observers import registry

    rss0 = _rss_now_mib()
    # the objective jaxatt.fit(None, None, study) builds: default gains, the study's loss and windows
    setup = studies.get(experiment).setup(duration=duration)
    bound = P.for_gains(registry.get(setup.entry).gains).bind(setup.params)
    (ss, se), (ts, te) = setup.loss_windows["steady"], setup.loss_windows["transient"]
    spec = losses.loss_spec(setup.loss_kind, steady_start=ss, steady_end=se, transient_start=ts, transient_end=te)
    objective = fitter.simulated_objective(setup, bound, spec, checkpoint=checkpoint, step_remat=step_remat, devices=1)
    keys = montecarlo.run_keys(0, np.arange(runs))
    theta = bound.init()

    def loss(th, k):
        return objective(th, k)[0]

    fn = jax.jit(loss) if mode == "forward" else jax.jit(jax.value_and_grad(loss))
    t0 = time.perf_counter()
    compiled = fn.lower(theta, keys).compile()
    compile_s = time.perf_counter() - t0
    mem = {}
    try:
        ma = compiled.memory_analysis()
        mem = {
            "xla_temp_mib": ma.temp_size_in_bytes / 2**20,
            "xla_argument_mib": ma.argument_size_in_bytes / 2**20,
            "xla_output_mib": ma.output_size_in_bytes / 2**20,
        }
    except Exception as e:  # noqa: BLE001 - not every backend reports it
        mem = {"xla_memory_analysis_error": repr(e)}
    rss_compiled = _rss_now_mib()
    peak_compiled = C.peak_rss_mib()
    times, cpu = [], []
    out = None
    while len(times) < repeats:
        t0, c0 = time.perf_counter(), time.process_time()
        out = jax.block_until_ready(compiled(theta, keys))
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        if times[-1] > max_repeat_s:
            break
    value = float(out if mode == "forward" else out[0])
    gnorm = None
    if mode == "grad":
        gnorm = float(np.sqrt(sum(float(np.sum(np.square(np.asarray(g)))) for g in jax.tree_util.tree_leaves(out[1]))))
    n_steps = int(round(duration / setup.dt))
    return {
        "experiment": experiment,
        "mode": mode,
        "duration_s": duration,
        "steps": n_steps,
        "runs": runs,
        "checkpoint_segment": losses.segment_length(n_steps, checkpoint),
        "step_remat": step_remat,
        "compile_s": compile_s,
        "wall_s": min(times),
        "cpu_s": min(cpu),
        "calls": len(times),
        "times_s": times,
        "cpu_times_s": cpu,
        "run_steps_per_s": runs * n_steps / min(times),
        "loss": value,
        "grad_norm": gnorm,
        "finite": bool(np.isfinite(value) and (gnorm is None or np.isfinite(gnorm))),
        "rss_start_mib": rss0,
        "rss_after_compile_mib": rss_compiled,
        "peak_rss_after_compile_mib": peak_compiled,
        "peak_rss_mib": C.peak_rss_mib(),
        "n_tunable": bound.n_free(),
        "loadavg_1m_end": _load(),
        **mem,
    }


def _subprocess(argv, timeout=None) -> dict:
    cmd = [sys.executable, str(pathlib.Path(__file__).resolve())] + argv
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, timeout=timeout)
    for line in proc.stdout.splitlines():
        if line.startswith(MARK):
            return json.loads(line[len(MARK) :])
    raise RuntimeError(f"subprocess {argv} failed (rc {proc.returncode}): {proc.stdout[-2000:]}")


def run_one(experiment, duration, runs, mode, checkpoint, repeats, max_repeat_s, step_remat="auto") -> dict:
    print(
        f"  {experiment} {mode:7s} T={duration:g} s B={runs} checkpoint={checkpoint} step_remat={step_remat} ...",
        flush=True,
    )
    t0 = time.perf_counter()
    r = _subprocess(
        [
            "--_worker",
            experiment,
            "--duration",
            str(duration),
            "--runs",
            str(runs),
            "--_mode",
            mode,
            "--checkpoint",
            str(checkpoint),
            "--repeats",
            str(repeats),
            "--max-repeat-s",
            str(max_repeat_s),
            "--step-remat",
            str(step_remat),
        ]
    )
    r["subprocess_wall_s"] = time.perf_counter() - t0
    print(
        f"    compile {r['compile_s']:.1f} s, call {r['wall_s']:.2f} s (CPU {r['cpu_s']:.2f} s), peak RSS "
        f"{r['peak_rss_mib']:.0f} MiB, XLA temp {r.get('xla_temp_mib', float('nan')):.1f} MiB, load "
        f"{r['loadavg_1m_end']}",
        flush=True,
    )
    return r


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--experiments", nargs="+", default=["batista-ges", "batista-so3"])
    ap.add_argument("--duration", type=float, default=3600.0, help="horizon of the main measurement, s")
    ap.add_argument("--runs", type=int, default=64, help="Monte Carlo seeds of the main measurement")
    ap.add_argument(
        "--checkpoint", default="auto", help="segment length: auto, off, or steps (divides 1000 or a multiple)"
    )
    ap.add_argument(
        "--step-remat",
        default="auto",
        choices=["auto", "on", "off"],
        help="per-step rematerialisation inside checkpointed segments (auto: on when checkpointing)",
    )
    ap.add_argument("--repeats", type=int, default=2, help="warm calls timed (best reported)")
    ap.add_argument("--max-repeat-s", type=float, default=60.0, help="no further repeats after a call this long")
    ap.add_argument("--scaling", action="store_true", help="also the memory-vs-horizon sweep")
    ap.add_argument("--scaling-only", action="store_true", help="only the memory-vs-horizon sweep")
    ap.add_argument("--scaling-runs", type=int, default=4)
    ap.add_argument("--scaling-durations", type=float, nargs="+", default=[60.0, 240.0, 960.0, 3600.0])
    ap.add_argument(
        "--scaling-max-plain",
        type=float,
        default=960.0,
        help="longest horizon measured without checkpointing (memory ~ T)",
    )
    ap.add_argument("--out", default=str(C.RESULTS_DIR))
    ap.add_argument("--_worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--_mode", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    ckpt = args.checkpoint
    ckpt = False if ckpt in ("off", "0", "false", "False") else (ckpt if ckpt == "auto" else int(ckpt))
    if args._worker:
        sr = {"auto": None, "on": True, "off": False}[args.step_remat]
        r = measure(args._worker, args.duration, args.runs, args._mode, ckpt, args.repeats, args.max_repeat_s, sr)
        print(MARK + json.dumps(r), flush=True)
        return 0

    meta = C.metadata(sys.argv if argv is None else ["gradient.py"] + list(argv))
    rows, scaling, summary = [], [], []
    t_start = time.perf_counter()
    if not args.scaling_only:
        print(f"main: T = {args.duration:g} s, {args.runs} seeds, checkpoint {args.checkpoint}", flush=True)
        for exp in args.experiments:
            fwd = run_one(exp, args.duration, args.runs, "forward", args.checkpoint, args.repeats, args.max_repeat_s)
            grd = run_one(
                exp, args.duration, args.runs, "grad", args.checkpoint, args.repeats, args.max_repeat_s, args.step_remat
            )
            rows += [fwd, grd]
            summary.append(
                {
                    "experiment": exp,
                    "duration_s": args.duration,
                    "runs": args.runs,
                    "checkpoint_segment": grd["checkpoint_segment"],
                    "step_remat": args.step_remat,
                    "forward_s": fwd["wall_s"],
                    "grad_s": grd["wall_s"],
                    "grad_over_forward": grd["wall_s"] / fwd["wall_s"],
                    "forward_cpu_s": fwd["cpu_s"],
                    "grad_cpu_s": grd["cpu_s"],
                    "grad_over_forward_cpu": grd["cpu_s"] / fwd["cpu_s"],
                    "forward_peak_rss_mib": fwd["peak_rss_mib"],
                    "grad_peak_rss_mib": grd["peak_rss_mib"],
                    "grad_xla_temp_mib": grd.get("xla_temp_mib"),
                    "forward_xla_temp_mib": fwd.get("xla_temp_mib"),
                    "grad_compile_s": grd["compile_s"],
                    "forward_compile_s": fwd["compile_s"],
                }
            )
        C.print_table(
            summary,
            [
                "experiment",
                "duration_s",
                "runs",
                "checkpoint_segment",
                "forward_s",
                "grad_s",
                "grad_over_forward",
                "grad_over_forward_cpu",
                "forward_peak_rss_mib",
                "grad_peak_rss_mib",
                "grad_xla_temp_mib",
            ],
            title="one gradient vs one forward pass",
        )
    if args.scaling or args.scaling_only:
        exp = args.experiments[0]
        print(f"scaling: {exp}, {args.scaling_runs} seeds", flush=True)
        for d in args.scaling_durations:
            for ck in ["auto", "off"] if d <= args.scaling_max_plain else ["auto"]:
                r = run_one(exp, d, args.scaling_runs, "grad", ck, 1, 0.0)
                r["checkpointed"] = ck == "auto"
                scaling.append(r)
            scaling.append(run_one(exp, d, args.scaling_runs, "forward", "auto", 1, 0.0))
        C.print_table(
            scaling,
            [
                "mode",
                "duration_s",
                "steps",
                "runs",
                "checkpoint_segment",
                "wall_s",
                "cpu_s",
                "xla_temp_mib",
                "peak_rss_mib",
                "rss_after_compile_mib",
            ],
            title="memory vs horizon",
        )
    data = {
        "settings": {
            "experiments": args.experiments,
            "duration_s": args.duration,
            "runs": args.runs,
            "checkpoint": args.checkpoint,
            "repeats": args.repeats,
            "dt_s": 0.01,
            "grad": "jit(value_and_grad(loss)) in theta (the gains the registry tunes by default, "
            "jaxatt.fitting.parametrize.for_gains), float64, reverse mode through the whole scan",
            "forward": "jit(loss): the same scan without the gradient",
            "rss": "ru_maxrss of a fresh subprocess per measurement (includes the compiler's peak)",
        },
        "summary": summary,
        "rows": rows,
        "scaling": scaling,
        "wall_s": time.perf_counter() - t_start,
    }
    path = C.write_results("gradient", data, args.out, meta)
    print(f"results written to {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
