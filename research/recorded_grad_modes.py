"""What the reverse pass through BROAD trials costs under each memory mode (issue 19 numbers; why ``jaxatt.fit`` on
recorded trials checkpoints segments by default instead of rematerialising every step).

For the robust AHRS (float32, default params) on the first ``--trials`` BROAD trials, one process per mode (so
that peak memory is the mode's own): ``jax.value_and_grad`` of the mean total RMSE through
:func:`jaxatt.data.broad.metric_batch` with

* ``none``: every step's residuals stored;
* ``step``: each step rematerialised (``step_remat=True``; the fitter's default before 2026-12-03);
* ``segment``: checkpointed segments of about sqrt(T) steps (``checkpoint="auto"``; the default now).

Prints and writes research/results/recorded-grad-modes-<host>-<UTC>.json: compile + first call, the best of
``--repeats`` warm calls, and the peak resident memory (ru_maxrss of the child) per mode.

Usage: python research/recorded_grad_modes.py [--trials 10] [--repeats 2]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "benchmarks"))

import _common as C  # noqa: E402

CHILD = r"""
import json, resource, sys, time
import jax, jax.numpy as jnp
from jaxatt.data import broad
from jaxatt.observers import registry
data_dir, n, mode, repeats = sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4])
trials = broad.load(data_dir, broad.list_trials(data_dir)[:n])
entry = registry.get("robust")
obs = registry.recorded_observer(entry)
kw = {"none": {}, "step": {"step_remat": True}, "segment": {"checkpoint": "auto"}}[mode]
fn, item = broad.metric_batch(obs, trials, hold=registry.hold_of(entry), dtype="float32", **kw)
p = entry.default_params(jnp.float32)
vg = jax.jit(jax.value_and_grad(lambda p, item: jnp.mean(fn(p, item)["total_rmse_deg"])))
t = time.perf_counter(); v, g = jax.block_until_ready(vg(p, item)); first = time.perf_counter() - t
warm = []
for _ in range(repeats):
    t = time.perf_counter(); jax.block_until_ready(vg(p, item)); warm.append(time.perf_counter() - t)
print(json.dumps({"mode": mode, "first_call_s": first, "warm_s": warm, "best_s": min(warm), "loss": float(v),
                  "grad_tau_mag": float(g.tau_mag), "samples": int(sum(len(tr.samples.t) for tr in trials)),
                  "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}))
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data-dir", default=str(C.REPO_ROOT.parent / "shared" / "data" / "broad"))
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args(argv)
    meta = C.metadata(sys.argv if argv is None else ["recorded_grad_modes.py"] + list(argv))
    rows = []
    for mode in ("none", "step", "segment"):
        cmd = [sys.executable, "-c", CHILD, args.data_dir, str(args.trials), mode, str(args.repeats)]
        out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.strip().splitlines()[-1]
        row = json.loads(out)
        rows.append(row)
        print(
            f"{mode:8s} first call {row['first_call_s']:6.1f} s  warm {row['best_s']:6.1f} s  "
            f"peak RSS {row['peak_rss_gib']:.2f} GiB  loss {row['loss']:.6f}  d/d tau_mag {row['grad_tau_mag']:.6g}",
            flush=True,
        )
    path = C.write_results("recorded-grad-modes", {"settings": vars(args), "rows": rows}, out_dir=args.out, meta=meta)
    print(f"results written to {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
