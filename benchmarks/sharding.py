"""Monte Carlo throughput with the seed axis split over devices (jaxatt.sharding) against one device.

The devices here are CPU "host devices" forced with XLA_FLAGS=--xla_force_host_platform_device_count=N (set by
this script before JAX starts), so on an N-core machine each device gets about one core; on GPUs run it with
``--real-devices`` to use the visible accelerators instead. For each device count the same batista-ges Monte
Carlo (float64, warm: compile excluded, best of --repeats) is timed with ``devices=1`` and ``devices=None``
(all), and the per-run metrics of the two are compared (they must agree to rounding).

Usage:
  python benchmarks/sharding.py [--devices 2] [--runs 1000] [--duration 20] [--repeats 3]

Writes benchmarks/results/sharding-<host>-<UTC>.json.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--devices", type=int, default=2, help="forced CPU host devices")
    ap.add_argument("--real-devices", action="store_true", help="use the visible accelerators, force nothing")
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--duration", type=float, default=20.0, help="simulated s per run (100 Hz)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if not args.real_devices:
        os.environ["XLA_FLAGS"] = (
            os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={args.devices}"
        ).strip()
    import _common as C
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from jaxatt import montecarlo
    from jaxatt.studies import batista_ges as E

    meta = C.metadata(sys.argv if argv is None else ["sharding.py"] + list(argv))
    cfg = E.Config(duration=args.duration)
    scn, obs, p = E.scenario(cfg), E.observer(cfg), E.params(cfg)
    n_steps = int(round(args.duration / cfg.dt))
    rows, results = [], {}
    for label, devices in (("one device", 1), (f"{len(jax.devices())} devices", None)):

        def call(devices=devices):
            return montecarlo.monte_carlo(
                scn,
                obs,
                p,
                runs=args.runs,
                chunk=args.runs,
                duration=args.duration,
                dt=cfg.dt,
                errors_fn=E.errors,
                window_start=0.0,
                devices=devices,
            )

        t0 = time.perf_counter()
        res = call()
        first = time.perf_counter() - t0
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            res = call()
            times.append(time.perf_counter() - t0)
        best = min(times)
        results[label] = res
        rows.append(
            {
                "label": label,
                "devices": len(jax.devices()) if devices is None else 1,
                "first_call_s": first,
                "best_s": best,
                "times_s": times,
                "run_steps_per_s": args.runs * n_steps / best,
            }
        )
        print(
            f"{label:12s}: {args.runs * n_steps / best:.3g} run-steps/s (best of {args.repeats}: {best:.2f} s; "
            f"first call with compile {first:.1f} s)",
            flush=True,
        )
    a, b = results.values()
    rel = max(float(np.max(np.abs(a.per_run[k] - b.per_run[k]) / (np.abs(a.per_run[k]) + 1e-300))) for k in a.per_run)
    speedup = rows[1]["run_steps_per_s"] / rows[0]["run_steps_per_s"]
    print(f"speed-up {speedup:.2f}x; largest relative difference of the per-run metrics {rel:.2g}")
    path = C.write_results(
        "sharding",
        {
            "settings": vars(args),
            "rows": rows,
            "speedup": speedup,
            "max_rel_difference": rel,
            "jax_devices": [str(d) for d in jax.devices()],
            "cpu_count": os.cpu_count(),
            "load_avg_at_end": os.getloadavg(),
        },
        out_dir=args.out,
        meta=meta,
    )
    print(f"results written to {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
