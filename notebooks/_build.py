"""Build the notebooks from their "percent" sources, check they are up to date, or execute them headless.

The sources are plain Python files in ``notebooks/src/`` (readable diffs, runnable as scripts): ``# %%`` starts a
code cell, ``# %% [markdown]`` a markdown cell whose lines are comments (``# `` is stripped). Each source
``src/NN_name.py`` becomes ``NN_name.ipynb`` next to this file (nbformat 4, no outputs, deterministic bytes).

    python notebooks/_build.py                       # write every .ipynb from src/
    python notebooks/_build.py --check               # exit 1 if an .ipynb differs from its source
    python notebooks/_build.py --execute notebooks/01_quickstart.ipynb [--results out.json]

``--execute`` runs the code cells of an .ipynb top to bottom in one namespace, in the notebook's folder, with
no Jupyter kernel (what CI and ``tests/test_notebooks.py`` do): matplotlib uses the Agg backend, figures are
closed after each cell (as the inline backend does), cell timings are printed, and with ``--results`` the
notebook's ``RESULTS`` dict (key numbers) is written as JSON. Set ``JAXATT_NOTEBOOK_QUICK=1`` for the reduced
mode and ``JAXATT_FIGURE_DIR`` for where figures go.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent
SRC = HERE / "src"

KERNELSPEC = {"display_name": "Python 3", "language": "python", "name": "python3"}


def parse_percent(text: str) -> list:
    """[(cell_type, source)] from a percent-format script; text before the first ``# %%`` is ignored."""
    cells, cur, kind = [], None, None

    def close():
        if cur is None:
            return
        lines = list(cur)
        while lines and not lines[0].strip():
            lines.pop(0)
        while lines and not lines[-1].strip():
            lines.pop()
        if kind == "markdown":
            lines = [ln[2:] if ln.startswith("# ") else ln[1:] if ln.startswith("#") else ln for ln in lines]
        if lines:
            cells.append((kind, "\n".join(lines)))

    for line in text.splitlines():
        if line.startswith("# %%"):
            close()
            kind = "markdown" if "[markdown]" in line else "code"
            cur = []
        elif cur is not None:
            cur.append(line)
    close()
    return cells


def to_notebook(cells: list, stem: str) -> dict:
    out = []
    for i, (kind, src) in enumerate(cells):
        lines = src.split("\n")
        source = [ln + "\n" for ln in lines[:-1]] + [lines[-1]]
        cell = {"cell_type": kind, "id": f"{stem[:2]}-{i:03d}", "metadata": {}, "source": source}
        if kind == "code":
            cell.update(execution_count=None, outputs=[])
        out.append(cell)
    return {
        "cells": out,
        "metadata": {"kernelspec": KERNELSPEC, "language_info": {"name": "python", "pygments_lexer": "ipython3"}},
        "nbformat": 4,
        "nbformat_minor": 5,
    }


def render(src: Path) -> str:
    nb = to_notebook(parse_percent(src.read_text(encoding="utf-8")), src.stem)
    return json.dumps(nb, indent=1, ensure_ascii=False) + "\n"


def build(check: bool = False) -> int:
    stale = []
    for src in sorted(SRC.glob("[0-9][0-9]_*.py")):
        target = HERE / f"{src.stem}.ipynb"
        text = render(src)
        if check:
            if not target.exists() or target.read_text(encoding="utf-8") != text:
                stale.append(target.name)
        else:
            target.write_text(text, encoding="utf-8")
            print(f"wrote {target.relative_to(HERE.parent)}")
    if stale:
        print(f"out of date (run python notebooks/_build.py): {', '.join(stale)}", file=sys.stderr)
        return 1
    return 0


def _jsonable(o):
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)


def execute(path: Path, results: str = None) -> int:
    """Run the code cells of ``path`` in one namespace (cwd = the notebook's folder); 0 on success."""
    os.environ.setdefault("MPLBACKEND", "Agg")
    import warnings

    warnings.filterwarnings("ignore", message=".*non-interactive.*cannot be shown")
    path = Path(path).resolve()
    nb = json.loads(path.read_text(encoding="utf-8"))
    os.chdir(path.parent)
    sys.path.insert(0, str(path.parent))
    ns = {"__name__": "__main__", "__file__": str(path)}
    t_all = time.perf_counter()
    timings = []
    code_cells = [c for c in nb["cells"] if c["cell_type"] == "code"]
    for i, cell in enumerate(code_cells):
        src = "".join(cell["source"])
        t0 = time.perf_counter()
        try:
            exec(compile(src, f"<{path.name} code cell {i}>", "exec"), ns)
        except Exception:
            traceback.print_exc()
            print(f"FAILED in {path.name}, code cell {i}:\n{src}", file=sys.stderr)
            return 1
        finally:
            if "matplotlib.pyplot" in sys.modules:
                sys.modules["matplotlib.pyplot"].close("all")
        timings.append(time.perf_counter() - t0)
        print(f"[cell {i:2d}] {timings[-1]:6.1f} s", flush=True)
    total = time.perf_counter() - t_all
    print(f"{path.name}: {len(code_cells)} code cells in {total:.1f} s", flush=True)
    if results:
        payload = {"notebook": path.name, "wall_s": total, "cell_s": timings, "RESULTS": ns.get("RESULTS", {})}
        Path(results).write_text(json.dumps(payload, indent=1, default=_jsonable), encoding="utf-8")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if a notebook differs from its source")
    ap.add_argument("--execute", metavar="IPYNB", help="run a notebook's code cells headless")
    ap.add_argument("--results", metavar="JSON", help="with --execute: write RESULTS and timings here")
    args = ap.parse_args(argv)
    if args.execute:
        return execute(Path(args.execute), args.results)
    return build(check=args.check)


if __name__ == "__main__":
    sys.exit(main())
