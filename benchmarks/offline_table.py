"""The offline-mode table: per-trial and per-group BROAD total RMSE (deg) of jaxatt's offline rows beside their
forward (causal) passes and VQF's offline filter, read from a ``benchmarks/broad.py`` results file.

Run: ``python benchmarks/broad.py --filters jaxatt-robust-offline jaxatt-robust-offline-oof jaxatt-vqf-offline
jaxatt-vqf-offline-oof jaxatt-robust-oof jaxatt-vqf vqf-offline`` and then
``python benchmarks/offline_table.py benchmarks/results/broad-<host>-<UTC>.json [--out benchmarks/results/offline.md]``.
"""

from __future__ import annotations

import argparse
import json
import pathlib

HERE = pathlib.Path(__file__).resolve().parent

#: (column title, row of the results file, where the number is: "fused" or "forward")
COLUMNS = (
    ("robust fwd, in sample", "jaxatt-robust-offline", "forward"),
    ("robust offline, in sample", "jaxatt-robust-offline", "fused"),
    ("robust fwd, out of fold", "jaxatt-robust-offline-oof", "forward"),
    ("robust offline, out of fold", "jaxatt-robust-offline-oof", "fused"),
    ("jaxatt VQF fwd", "jaxatt-vqf-offline", "forward"),
    ("jaxatt VQF offline", "jaxatt-vqf-offline", "fused"),
    ("jaxatt VQF offline, fusion out of fold", "jaxatt-vqf-offline-oof", "fused"),
    ("vqf.offlineVQF", "vqf-offline", "fused"),
)


def _value(row, trial, where):
    t = row["trials"][trial]
    if where == "fused":
        return t["total_rmse_deg"]
    if "forward" in row:
        return row["forward"][trial]["total_rmse_deg"]
    return t["forward_total_rmse_deg"]


def table(results: dict) -> str:
    rows = results["results"]
    cols = [c for c in COLUMNS if c[1] in rows]
    trials = list(next(iter(rows.values()))["trials"])
    groups = {n: next(iter(rows.values()))["trials"][n]["group"] for n in trials}
    head = "| trial | group | " + " | ".join(c[0] for c in cols) + " |"
    lines = [head, "|" + "---|" * (len(cols) + 2)]
    for n in trials:
        vals = " | ".join(f"{_value(rows[c[1]], n, c[2]):.2f}" for c in cols)
        lines.append(f"| {n} | {groups[n]} | {vals} |")
    for g in ("undisturbed", "disturbed"):
        names = [n for n in trials if groups[n] == g]
        vals = " | ".join(f"**{sum(_value(rows[c[1]], n, c[2]) for n in names) / len(names):.2f}**" for c in cols)
        lines.append(f"| **mean, {g}** ({len(names)}) | | {vals} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", help="a benchmarks/broad.py results file (JSON)")
    ap.add_argument("--out", default=str(HERE / "results" / "offline.md"))
    args = ap.parse_args(argv)
    res = json.loads(pathlib.Path(args.results).read_text())
    body = res.get("payload", res)
    text = (
        "# Offline mode on BROAD: total RMSE (deg) per trial\n\n"
        f"From `{pathlib.Path(args.results).name}` (`benchmarks/offline_table.py`; rows and protocol: the docstring "
        "of `benchmarks/broad.py`). fwd = the forward pass, i.e. the causal filter; out of fold = gains (and "
        "fusion params) chosen on the other fold of the 2-fold split. BROAD data: Laidig, Caruso, Cereatti, Seel, "
        "Data 6(7), 2021, CC BY 4.0.\n\n" + table(body) + "\n"
    )
    pathlib.Path(args.out).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
