"""benchmarks/gpu.py (the script a GPU user runs) in its smallest CPU form: it runs, prints its measurements and
writes the JSON of benchmarks/_common.py (machine, versions, date), and its numbers hold together: runs 0-3 of the
batch of 8 are the batch of 4 (same keys: equal to rounding), the full-study path completes."""

import json
import os
import pathlib
import subprocess
import sys

REPO = pathlib.Path(__file__).resolve().parents[1]


def test_gpu_script_smallest_cpu_form(tmp_path):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env = {k: v for k, v in env.items() if not k.startswith("JAXATT_")}  # one process
    # 2 compiles (batches 4 and 8, float64); the full study has batch 4's shape and reuses its program
    argv = ["--batches", "4", "8", "--duration", "1", "--dtypes", "float64", "--full", "--full-runs", "4"]
    argv += ["--full-chunk", "4", "--full-duration", "1", "--out", str(tmp_path)]
    r = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "gpu.py"), *argv],
        cwd=str(REPO),
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "backend cpu" in r.stdout and "run-steps/s" in r.stdout and "results written to" in r.stdout
    (path,) = tmp_path.glob("gpu-*.json")
    d = json.loads(path.read_text())
    assert d["benchmark"] == "gpu"
    assert {"date_utc", "machine", "versions", "git", "jax"} <= set(d["meta"])
    assert d["meta"]["jax"]["backend"] == "cpu" and d["meta"]["versions"]["jax"]
    rows = d["rows"]
    assert [(x["batch"], x["dtype"], x["steps"]) for x in rows] == [(4, "float64", 100), (8, "float64", 100)]
    for x in rows:
        assert x["ok"] and x["finite"] and x["warm_s"] > 0
        assert abs(x["run_steps_per_s"] - x["batch"] * x["steps"] / x["warm_s"]) <= 1e-9 * x["run_steps_per_s"]
    (rel,) = d["consistency_max_rel"].values()
    assert rel < 1e-9, rel  # 0 on this CPU; the batch size may change XLA's vectorisation, so rounding
    full = d["full_study"]
    assert full["complete"] and full["runs"] == 4 and full["steps"] == 100 and full["wall_s"] > 0
    assert d["settings"]["small_defaults"] and d["settings"]["x64"]
