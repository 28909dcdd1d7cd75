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
    fused = rows["vqf-offline"]["trials"]
    lines = {ln.split("|")[1].strip(): ln for ln in text.splitlines() if ln.startswith("| ")}
    for name, t in fused.items():
        assert f"{t['total_rmse_deg']:.2f} |" in lines[name], name
    for group in ("undisturbed", "disturbed"):
        names = [n for n, t in fused.items() if t["group"] == group]
        mean = np.mean([fused[n]["total_rmse_deg"] for n in names])
        cells = [c.strip() for c in lines[f"**mean, {group}** ({len(names)})"].split("|")]
        assert cells[-2] == f"**{mean:.2f}**", (group, cells[-2], mean)  # the last column: vqf.offlineVQF
