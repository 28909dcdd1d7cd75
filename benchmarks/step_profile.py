"""What bounds one Monte Carlo time step on this machine: the compiled program's time loop, op by op.

For each study (default: batista-ges, batista-so3, nlio-case1, complementary) this compiles the fused Monte Carlo
program that ``jaxatt.montecarlo.monte_carlo`` runs for one chunk on one device (truth, sensors, observer and the
study's on-the-fly metrics: ``engine.compiled`` with an ``engine.Simulated`` source and
``montecarlo.metrics_reducer``, float64) at ``--batch`` runs, reads the optimised HLO of the scan's loop body
(the ``while`` body with the most instructions), and reports:

* ``fusions``: XLA fusions per time step (each one a separate loop over the batch that writes its result to
  memory), ``custom_calls`` (LAPACK calls such as the SVD of a projection), ``other_ops`` (copies, dots, slices...
  that were not fused);
* ``bytes_written_per_run_step``: the sum of the output sizes of every instruction of the body, divided by the
  batch: a lower bound on the memory traffic of one run-step (each result is read again at least once);
* ``us_per_run_step`` (timed, best of ``--repeats`` warm calls of ``--steps`` steps) and from it
  ``ns_per_op_per_run`` (time per run-step / ops per step) and the write bandwidth it implies (GB/s).

A step of a few hundred flops per run that costs ~1 us per run over ~100 separate loops is bound by the number of
passes over memory and their per-pass overhead, not by arithmetic; this script prints the numbers that say so.

Usage: python benchmarks/step_profile.py [--studies batista-ges ...] [--batch 128] [--steps 2000] [--out DIR]
"""

from __future__ import annotations

import argparse
import os
import pathlib
import re
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

import _common as C  # noqa: E402

STUDIES = ("batista-ges", "batista-so3", "nlio-case1", "complementary")
_DTYPE_BYTES = {"f64": 8, "f32": 4, "s64": 8, "s32": 4, "u32": 4, "u64": 8, "pred": 1, "u8": 1, "s8": 1, "f16": 2}


def _computations(hlo: str):
    """name -> list of instruction lines, for every computation of an HLO module's text."""
    comps, name, body = {}, None, []
    for line in hlo.splitlines():
        m = re.match(r"^(?:ENTRY )?%?([\w.\-]+) .*\{\s*$", line)
        if m and not line.startswith(" "):
            name, body = m.group(1), []
            comps[name] = body
        elif name is not None and line.startswith("  ") and "=" in line:
            body.append(line.strip())
    return comps


def _shape_bytes(text: str) -> int:
    """Bytes of every array shape in an instruction's result type, e.g. ``(f64[128,3]{1,0}, s32[])``."""
    total = 0
    for dt, dims in re.findall(r"\b(f64|f32|f16|s64|s32|u32|u64|u8|s8|pred)\[([\d,]*)\]", text):
        n = 1
        for d in filter(None, dims.split(",")):
            n *= int(d)
        total += n * _DTYPE_BYTES[dt]
    return total


def _split_instruction(line: str):
    """(result type, opcode) of an HLO instruction line ``%x = TYPE opcode(operands), attrs``; TYPE may be a
    tuple with spaces, e.g. ``(f64[3]{0}, s32[])``."""
    rhs = line.partition(" = ")[2]
    if rhs.startswith("("):
        depth, end = 0, 0
        while end == 0 or depth:
            depth += (rhs[end] == "(") - (rhs[end] == ")")
            end += 1
        result_type, rest = rhs[:end], rhs[end:].lstrip()
    else:
        result_type, _, rest = rhs.partition(" ")
    return result_type, rest.split("(", 1)[0]


def loop_body_profile(hlo: str) -> dict:
    """Counts of the time loop's body: the ``while`` body computation with the most instructions."""
    comps = _computations(hlo)
    bodies = set(re.findall(r"body=%?([\w.\-]+)", hlo))
    if not bodies:
        raise ValueError("no while loop in the compiled program")
    body = max(bodies, key=lambda b: len(comps.get(b, [])))
    lines = comps[body]
    fusions = custom = other = 0
    written = 0
    for ln in lines:
        result_type, op = _split_instruction(ln)
        if op in ("parameter", "get-tuple-element", "tuple", "constant", "bitcast"):
            continue  # no work, no memory written
        written += _shape_bytes(result_type)
        if op == "fusion":
            fusions += 1
        elif op == "custom-call":
            custom += 1
        else:
            other += 1
    return {"body": body, "fusions": fusions, "custom_calls": custom, "other_ops": other, "bytes_written": written}


def measure(study: str, batch: int, n_steps: int, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxatt import engine, montecarlo, studies

    s = studies.get(study).setup()
    source = engine.Simulated(n_steps, s.dt, jnp.float64)
    reducer = montecarlo.metrics_reducer(s.errors_fn, s.window_start, s.windows, 0, None, 0.5 * s.dt)
    fn = engine.compiled(s.observer, source, reducer, None, hold=s.hold, obs_dtype=jnp.float64)
    keys = montecarlo.run_keys(0, np.arange(batch))
    t0 = time.perf_counter()
    compiled = fn.lower(s.scenario, s.params, keys).compile()
    compile_s = time.perf_counter() - t0
    prof = loop_body_profile(compiled.as_text())
    jax.block_until_ready(compiled(s.scenario, s.params, keys))
    tm = C.time_it(lambda: compiled(s.scenario, s.params, keys), repeats=repeats, sync=jax.block_until_ready)
    us = 1e6 * tm["best_s"] / (batch * n_steps)
    ops = prof["fusions"] + prof["custom_calls"] + prof["other_ops"]
    per_run_bytes = prof["bytes_written"] / batch
    return {
        "study": study,
        "batch": batch,
        "steps": n_steps,
        "compile_s": compile_s,
        **{k: prof[k] for k in ("fusions", "custom_calls", "other_ops")},
        "ops_per_step": ops,
        "bytes_written_per_run_step": per_run_bytes,
        "us_per_run_step": us,
        "run_steps_per_s": 1e6 / us,
        "ns_per_op_per_run": 1e3 * us / ops,
        "write_gb_per_s": per_run_bytes / us * 1e-3,
        "loadavg_1m": round(os.getloadavg()[0], 2),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--studies", nargs="+", default=list(STUDIES), choices=STUDIES)
    ap.add_argument("--batch", type=int, default=128, help="runs per call (default 128: the CPU group size)")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=None, help="results folder (default benchmarks/results)")
    a = ap.parse_args(argv)
    if a.batch < 1 or a.steps < 1 or a.repeats < 1:
        ap.error("--batch, --steps and --repeats must be positive")
    import jax

    jax.config.update("jax_enable_x64", True)
    rows = [measure(st, a.batch, a.steps, a.repeats) for st in a.studies]
    cols = ["study", "fusions", "custom_calls", "other_ops", "bytes_written_per_run_step", "us_per_run_step"]
    C.print_table(rows, cols + ["ns_per_op_per_run", "write_gb_per_s", "loadavg_1m"], title="one time step")
    path = C.write_results("step_profile", {"settings": vars(a), "rows": rows}, a.out)
    print(f"results written to {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
