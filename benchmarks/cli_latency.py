"""What a user waits for at the command line (issue 19): ``jaxatt --help``, the first result of ``jaxatt reproduce
batista-ges --runs 20`` with a cold compile cache, and the Monte Carlo rate of ``jaxatt simulate``.

Each command runs as a user runs it, in a fresh process (``python -m jaxatt``, this checkout first on the path),
timed from outside (wall time of the process, start-up and imports included):

* ``help``: ``jaxatt --help``, best of ``--help-repeats`` (no JAX import);
* ``first_result``: ``jaxatt reproduce batista-ges --runs R`` (R = ``--first-runs``, 20) with an empty compile
  cache (``JAX_COMPILATION_CACHE_DIR`` a new folder each time), ``--repeats`` times, and the same command at
  ``--short`` s of simulated time (compile, start-up and set-up with almost no scan): their difference is the scan;
  the command's own ``timing.wall_s`` (its JSON) is reported beside the process's wall time (``--quick``: no
  ``--short`` run);
* ``monte_carlo``: ``jaxatt simulate --observer batista-ges --runs N`` (N = ``--mc-runs``, 1000) at two durations
  (``--mc-durations``, 60 and 360 s), each with an empty compile cache: run-steps/s from the difference of the
  commands' ``timing.wall_s``, which cancels the compile and the fixed costs (the issue's method).

Usage: python benchmarks/cli_latency.py [--quick] [--out DIR]
Writes benchmarks/results/cli_latency-<host>-<UTC>.json and prints one table.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

HERE = pathlib.Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))

import _common as C  # noqa: E402


def run_cli(args, *, cold_cache: bool, workdir: str):
    """(process wall time s, the command's JSON or None) of ``python -m jaxatt *args`` in a fresh process."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    if cold_cache:
        env["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="xla-", dir=workdir)
    out = None
    if args[0] != "--help":
        out = os.path.join(workdir, f"r{time.monotonic_ns()}.json")
        args = [*args, "--quiet", "--json", out]
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "jaxatt", *args], env=env, capture_output=True, text=True, cwd=workdir)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(f"jaxatt {' '.join(args)} exited {r.returncode}: {r.stderr[-2000:]}")
    return wall, (json.loads(pathlib.Path(out).read_text()) if out else None)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a smoke run: 2 runs, seconds of simulated time")
    ap.add_argument("--help-repeats", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=2, help="cold-cache first results")
    ap.add_argument("--first-runs", type=int, default=20)
    ap.add_argument("--short", type=float, default=10.0, help="simulated s of the compile-and-set-up run (0: none)")
    ap.add_argument("--mc-runs", type=int, default=1000)
    ap.add_argument("--mc-durations", type=float, nargs=2, default=[60.0, 360.0])
    ap.add_argument("--out", default=None, help="results folder (default benchmarks/results)")
    a = ap.parse_args(argv)
    first_duration = None
    if a.quick:  # no compile-only run; the first result is one of the two Monte Carlo durations' programs
        a.help_repeats, a.repeats, a.first_runs, a.short = 1, 1, 2, None
        a.mc_runs, a.mc_durations, first_duration = 2, [1.0, 2.0], 2.0
    rows = []
    with tempfile.TemporaryDirectory(prefix="jaxatt-cli-latency-") as wd:
        helps = [run_cli(["--help"], cold_cache=False, workdir=wd)[0] for _ in range(a.help_repeats)]
        rows.append({"measure": "jaxatt --help", "wall_s": min(helps), "note": f"best of {len(helps)}"})
        first = ["reproduce", "batista-ges", "--runs", str(a.first_runs)]
        if first_duration is not None:
            first += ["--duration", str(first_duration)]
        for i in range(a.repeats):
            wall, d = run_cli(first, cold_cache=True, workdir=wd)
            rows.append({"measure": f"{' '.join(first)} (cold cache)", "wall_s": wall,
                         "command_wall_s": d["timing"]["wall_s"], "note": f"repeat {i + 1}"})  # fmt: skip
            if a.short:
                wall, d = run_cli([*first[:4], "--duration", str(a.short)], cold_cache=True, workdir=wd)
                rows.append({"measure": f"the same at --duration {a.short:g} (cold cache)", "wall_s": wall,
                             "command_wall_s": d["timing"]["wall_s"], "note": "compile, start-up, set-up"})  # fmt: skip
        sim = ["simulate", "--observer", "batista-ges", "--runs", str(a.mc_runs)]
        mc = []
        for dur in a.mc_durations:
            wall, d = run_cli([*sim, "--duration", f"{dur:g}"], cold_cache=True, workdir=wd)  # both compile
            mc.append((dur, wall, d["timing"]["wall_s"], d["timing"]["steps_per_run"]))
            rows.append({"measure": f"{' '.join(sim)} --duration {dur:g}", "wall_s": wall,
                         "command_wall_s": d["timing"]["wall_s"]})  # fmt: skip
    (d0, _, c0, n0), (d1, _, c1, n1) = mc
    rate = a.mc_runs * (n1 - n0) / (c1 - c0) if c1 > c0 else float("nan")
    rows.append({"measure": f"simulate: run-steps/s from {d0:g} s and {d1:g} s", "run_steps_per_s": rate})
    C.print_table(rows, ["measure", "wall_s", "command_wall_s", "run_steps_per_s", "note"], title="jaxatt CLI")
    settings = {k: v for k, v in vars(a).items() if k != "out"}
    path = C.write_results("cli_latency", {"settings": settings, "rows": rows, "mc_run_steps_per_s": rate}, a.out)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
