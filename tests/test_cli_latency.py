"""benchmarks/cli_latency.py: its smallest run measures every row it prints (fresh jaxatt processes) and writes
them with the Monte Carlo rate computed from the two durations' own timings."""

import json
import math
import pathlib
import sys

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import cli_latency  # noqa: E402


def test_quick_run_writes_what_it_measured(tmp_path, capsys):
    assert cli_latency.main(["--quick", "--out", str(tmp_path)]) == 0
    (path,) = tmp_path.glob("cli_latency-*.json")
    d = json.loads(path.read_text())
    rows = {r["measure"]: r for r in d["rows"]}
    assert 0 < rows["jaxatt --help"]["wall_s"] < 60
    first = rows["reproduce batista-ges --runs 2 --duration 2.0 (cold cache)"]
    assert 0 < first["command_wall_s"] < first["wall_s"]  # the command's own time excludes the start-up
    runs = [r for m, r in rows.items() if m.startswith("simulate --observer batista-ges --runs 2 --duration")]
    assert len(runs) == 2 and all(0 < r["command_wall_s"] < r["wall_s"] for r in runs)
    c0, c1 = runs[0]["command_wall_s"], runs[1]["command_wall_s"]
    if c1 > c0:  # 2 runs x (200 - 100) steps over the difference of the commands' times
        assert abs(d["mc_run_steps_per_s"] - 2 * 100 / (c1 - c0)) <= 1e-9 * d["mc_run_steps_per_s"]
    else:  # at two seconds of simulated time the compile's spread can exceed the scan: no rate, not a made-up one
        assert math.isnan(d["mc_run_steps_per_s"])
    assert d["meta"]["versions"]["jax"] and "jaxatt --help" in capsys.readouterr().out
