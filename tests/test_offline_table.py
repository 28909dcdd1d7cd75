"""benchmarks/offline_table.py: the offline-mode table it writes from a benchmarks/broad.py results file holds
that file's numbers (per trial, and the group means recomputed here from the JSON)."""

import json
import pathlib
import sys

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import offline_table  # noqa: E402

RESULTS = REPO / "benchmarks" / "results" / "broad-vm-20261202T212157Z.json"


def test_table_holds_the_results_files_numbers(tmp_path):
    out = tmp_path / "offline.md"
    assert offline_table.main([str(RESULTS), "--out", str(out)]) == 0
    text = out.read_text()
    rows = json.loads(RESULTS.read_text())
    rows = rows.get("payload", rows)["results"]
    cols = [c for c in offline_table.COLUMNS if c[1] in rows]
    assert len(cols) == len(offline_table.COLUMNS)  # this file has every row

    def number(row, trial, where):  # read here from the JSON, not with offline_table's helper
        t = rows[row]["trials"][trial] if where == "fused" else rows[row].get("forward", {}).get(trial)
        return t["total_rmse_deg"] if t is not None else rows[row]["trials"][trial]["forward_total_rmse_deg"]

    lines = {ln.split("|")[1].strip(): [c.strip() for c in ln.split("|")[3:-1]] for ln in text.splitlines()
             if ln.startswith("| ")}  # fmt: skip
    trials = rows["vqf-offline"]["trials"]
    for name in trials:
        assert lines[name] == [f"{number(row, name, where):.2f}" for _, row, where in cols], name
    for group in ("undisturbed", "disturbed"):
        names = [n for n, t in trials.items() if t["group"] == group]
        means = [np.mean([number(row, n, where) for n in names]) for _, row, where in cols]
        assert lines[f"**mean, {group}** ({len(names)})"] == [f"**{m:.2f}**" for m in means], group
