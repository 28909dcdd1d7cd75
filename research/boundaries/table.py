"""Before/after acceptance table for the "boundaries" issue (bad input, non-finite results).

Runs every case of ``tests/test_boundaries.py`` (``BAD_INPUT``, ``NON_FINITE``) plus one normal Monte Carlo run
through ``python -m jaxatt`` as a subprocess, once with jaxatt 0.1 (commit 6dbe213, checked out in /work/base with
its own venv) and once with the current working tree, and writes ``results.json`` (raw records) and ``README.md``
(the table) next to this file.

    python research/boundaries/table.py            # from /work/main, with /work/main/.venv active
    python research/boundaries/table.py --workers 2 --timeout 300 --only filter   # a subset

The "after" side runs a snapshot of /work/main/jaxatt copied at the start (on PYTHONPATH, ahead of the editable
install), so that edits made to the tree while the script runs do not mix code states; results.json records
HEAD, the uncommitted diff of jaxatt/ and its sha256. ``--reuse-before`` takes the 0.1 records from an existing
results.json for argv already run there (0.1 does not change, and its runs are the slow ones: ~13 of ~15 min).

Each run gets its own copy of the input files (so parallel runs cannot see each other's keep files) and a fresh,
empty working directory outside both checkouts. Before each run ``keep.json`` / ``keep.csv`` are written in the
input folder with fixed content; afterwards they are compared byte for byte.
"""

import argparse
import datetime as dt
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

HERE = Path(__file__).resolve().parent
MAIN = HERE.parents[1]
BASE = Path("/work/base")
BASE_COMMIT = "6dbe213"
PY = {"before": BASE / ".venv" / "bin" / "python", "after": MAIN / ".venv" / "bin" / "python"}
ROOT = {"before": BASE, "after": MAIN}

sys.path.insert(0, str(MAIN / "tests"))
import test_boundaries as tb  # noqa: E402  (the case lists and the file helpers)

KEEP = tb.KEEP
EXTRA = [
    (["reproduce", "batista-ges", "--runs", "1", "--duration", "5", "--quiet", "--json", "{d}/mc.json"], None),
]
RATE_SCALE = [
    "simulate",
    "--observer",
    "batista-ges",
    "--runs",
    "1",
    "--duration",
    "3",
    "--quiet",
    "--rate-scale",
    "1e6",
]

# Progress output is not an error line: the current version's progress lines carry '\r'; 0.1 printed
# "  k/N runs done, t s" lines, and the current version a closing "  <study>: k/N runs, t s" line.
PROGRESS = [re.compile(r"\r"), re.compile(r"^\s+\d+/\d+ runs done, [\d.]+ s$"), re.compile(r"^\s+\S+: \d+/\d+ runs, ")]


NOTES = [
    "- The two non-finite `simulate` cases (#75, #76) say the right thing (exit 1, `non-finite result ... run 0 ... "
    "t = ...`) but a terminal also gets three numpy RuntimeWarnings (6 lines: `Mean of empty slice`, `Degrees of "
    "freedom <= 0`, `All-NaN slice`, from `jaxatt/io.py:132` summarising the all-NaN metrics) before it. The test "
    "passes anyway: it calls `cli.main` in-process and pytest's warning capture takes the warnings off stderr "
    "(`5 passed, 6 warnings`).",
    "- 0.1's one-step `tune --experiment batista-so3` takes ~280-300 s on this 2-core machine, so #38 and #39 end "
    "either at the 300 s timeout or with their traceback at the very end; in two full runs of the script a "
    "different one of the two timed out (the counts stayed the same: 2 timeouts).",
    "- Writes into the cwd by 0.1: `tune` (#41, killed at the timeout) and `broad-tune --steps -1` (#63, exit 0) "
    "wrote a default `gains.json`; 0.1 also overwrote `keep.json` in #25 (then failed on `--plot /proc/x.png`) and "
    "#44 (`tune --out keep.json`), and left `folder.tmp*` (#23, #38) and `folder.png` (#73) in the input folder.",
    "- After: a finished normal run (#79) leaves `mc.json.runs.npz` beside `mc.json` (the per-chunk runs for "
    "`--resume`); 0.1 left only `mc.json`.",
]


def make_files(d: Path) -> None:
    """The input files of the cases (the ``files`` fixture of tests/test_boundaries.py)."""
    tb.make_files(d)


def cases():
    out = [("bad_input", argv, match) for argv, match in tb.BAD_INPUT]
    out += [("non_finite", argv, match) for argv, match in tb.NON_FINITE]
    if not any(argv == RATE_SCALE for argv, _ in tb.NON_FINITE):
        out.append(("non_finite", RATE_SCALE, r"run 0.*t = "))
    out += [("normal", argv, match) for argv, match in EXTRA]
    return out


def listing(p: Path):
    return sorted(str(q.relative_to(p)) for q in p.rglob("*"))


def error_lines(err: str):
    lines = [ln for ln in err.split("\n") if ln.strip()]
    return [ln for ln in lines if not any(p.search(ln) for p in PROGRESS)]


def run_one(version, kind, argv, match, inputs: Path, scratch: Path, timeout: float, snapshot: Path | None):
    work = Path(tempfile.mkdtemp(prefix=f"{version}_", dir=scratch))
    d, cwd = work / "in", work / "cwd"
    shutil.copytree(inputs, d)
    cwd.mkdir()
    for name in ("keep.json", "keep.csv"):
        (d / name).write_bytes(KEEP)
    before_d, before_cwd = listing(d), listing(cwd)
    args = [a.format(d=d) for a in argv]
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env.update(PYTHONUNBUFFERED="1", JAX_PLATFORMS="cpu")
    if version == "after" and snapshot is not None:
        env["PYTHONPATH"] = str(snapshot)
    t0 = time.time()
    p = subprocess.Popen(
        [str(PY[version]), "-m", "jaxatt", *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    try:
        out, err = p.communicate(timeout=timeout)
        rc = p.returncode
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)  # the process group this run started, nothing else
        out, err = p.communicate()
        rc = "timeout"
    wall = time.time() - t0
    err = err.decode(errors="replace")
    out = out.decode(errors="replace")
    lines = error_lines(err)
    last = lines[-1].replace(str(d), "{d}").replace(str(cwd), "{cwd}") if lines else ""
    changed = [name for name in ("keep.json", "keep.csv") if (d / name).read_bytes() != KEEP]
    rec = {
        "version": version,
        "kind": kind,
        "argv": argv,
        "match": match,
        "rc": rc,
        "stderr_lines": len(lines),
        "traceback": "Traceback" in err,
        "last_line": last[:110],
        "matches": bool(match and lines and re.search(match, lines[-1])),
        "keep_changed": changed,
        "left_in_input": sorted(set(listing(d)) - set(before_d)),
        "left_in_cwd": sorted(set(listing(cwd)) - set(before_cwd)),
        "wall_s": round(wall, 2),
        "stderr_tail": err[-1500:].replace(str(d), "{d}"),
        "stdout_tail": out[-400:].replace(str(d), "{d}"),
        "error_lines": [ln.replace(str(d), "{d}")[:300] for ln in lines[-12:]],
    }
    shutil.rmtree(work, ignore_errors=True)
    return rec


def category(r):
    if r["traceback"]:
        return "traceback"
    if r["rc"] == 2 and r["stderr_lines"] == 1:
        return "exit 2, one line"
    if r["rc"] == 1 and r["stderr_lines"] == 1:
        return "exit 1, one line"
    if r["rc"] == 0 and r["stderr_lines"] == 0:
        return "exit 0 silently"
    return "other"


def other_detail(r):
    if r["rc"] == "timeout":
        return "timeout"
    if r["rc"] == 2 and r["stderr_lines"] > 1:
        return "exit 2, usage + error (argparse)"
    return f"exit {r['rc']}, {r['stderr_lines']} lines"


def short_argv(argv, width=78):
    if not argv:
        return "(no arguments)"
    s = " ".join(argv).replace("{d}/", "").replace("--runs 1 --duration 5 --quiet", "MC")
    return s if len(s) <= width else s[: width - 1] + "…"


def gist(r, width=70):
    m = r["last_line"]
    m = re.sub(r"^jaxatt(?: \S+)?: error: ", "", m)
    m = m.replace("{d}/", "")
    m = m if len(m) <= width else m[: width - 1] + "…"
    return m.replace("|", "\\|").replace("`", "'")


def cell(r):
    rc = r["rc"]
    how = {
        "traceback": "**traceback**",
        "exit 2, one line": "1 line",
        "exit 1, one line": "1 line",
        "exit 0 silently": "silent",
    }.get(category(r), f"{r['stderr_lines']} lines")
    extra = ""
    if r["keep_changed"]:
        extra += " **overwrote " + "+".join(r["keep_changed"]) + "**"
    left = r["left_in_input"] + [f"cwd/{n}" for n in r["left_in_cwd"]]
    if left:
        extra += " (left " + ", ".join(left) + ")"
    msg = gist(r)
    return f"{rc}, {how}{extra}" + (f": {msg}" if msg else "") + f" ({r['wall_s']:.0f} s)"


def git(*args, cwd=MAIN):
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True).stdout.strip()


def expected_after(kind, r):
    if kind == "bad_input":
        return r["rc"] == 2 and r["stderr_lines"] == 1 and not r["traceback"] and not r["keep_changed"]
    if kind == "non_finite":
        return r["rc"] == 1 and r["stderr_lines"] == 1 and r["last_line"].startswith("jaxatt: error: non-finite")
    return r["rc"] == 0 and not r["traceback"]


def write_readme(meta, rows):
    from collections import Counter

    L = []
    L.append("# Boundaries: before/after acceptance (bad input, non-finite results)\n")
    after = meta["after"]
    tree = f"HEAD `{after['commit'][:12]}`"
    if after["dirty"]:
        tree += f" + uncommitted changes to jaxatt/ (sha256 of the diff {after['jaxatt_diff_sha256'][:12]})"
    if after["snapshot_of_working_tree"]:
        tree += "; a copy of jaxatt/ taken when the script started"
    reused = ""
    if meta["before_records_from"]:
        reused = f"The before records were reused from the run of {meta['before_records_from']}. "
    L.append(
        f"Every case of `tests/test_boundaries.py` (`BAD_INPUT`: {meta['n_bad_input']}, `NON_FINITE`: "
        f"{meta['n_non_finite']}) plus one normal Monte Carlo run was run as `python -m jaxatt <argv>` in a "
        f"subprocess, with jaxatt 0.1 (**before**, commit `{meta['before']['commit'][:12]}`, a worktree at "
        f"/work/base with its own venv) and the current working tree (**after**, {tree}). {reused}Each run had "
        "its own copy of the input files (made as the test fixture `files` makes them), a fresh empty cwd, "
        "`keep.json` / `keep.csv` written with fixed content beforehand and compared afterwards, and a "
        f"{meta['timeout_s']:.0f} s timeout; {meta['workers']} runs at a time, CPU only (`JAX_PLATFORMS=cpu`), "
        f"on {meta['cpus']} cores. Run on {meta['date']}; the whole script took {meta['wall_s'] / 60:.1f} min.\n"
    )
    L.append(
        "Rerun: `. .venv/bin/activate && python research/boundaries/table.py` (`--reuse-before` keeps 0.1's "
        "records from results.json and reruns only the current tree, ~3 min; needs /work/base: "
        "`git worktree add /work/base 6dbe213`, `python3 -m venv /work/base/.venv`, "
        "`/work/base/.venv/bin/pip install -e '/work/base[test]'`). Raw records, with stderr tails: "
        "`results.json`.\n"
    )
    L.append(
        "Stderr lines counted are the non-empty lines that are not progress (progress lines carry `\\r`, or are "
        "0.1's `k/N runs done` lines). `d/` is the input folder; `MC` = `--runs 1 --duration 5 --quiet`. 0.1 "
        "had no `filter` command and no `--resume` / `--progress` / `--debug` flags: there, argparse's usage "
        "block + error is what it did.\n"
    )
    for kind, title in (
        ("bad_input", "Bad input (want: exit 2, exactly one line, no traceback, keep files untouched)"),
        ("non_finite", "Non-finite results (want: exit 1, one line `non-finite result ...`)"),
        ("normal", "A normal run (want: exit 0)"),
    ):
        sub = [x for x in rows if x["kind"] == kind]
        if not sub:
            continue
        L.append(f"\n## {title}\n")
        for v in ("before", "after"):
            c = Counter(category(x[v]) for x in sub)
            o = Counter(other_detail(x[v]) for x in sub if category(x[v]) == "other")
            parts = [f"{k}: {c[k]}" for k in ("exit 2, one line", "exit 1, one line", "traceback", "exit 0 silently")]
            parts.append(f"other: {c['other']}" + (f" ({', '.join(f'{k}: {n}' for k, n in o.items())})" if o else ""))
            ow = sum(bool(x[v]["keep_changed"]) for x in sub)
            L.append(f"- **{v}** ({len(sub)} cases): " + "; ".join(parts) + f"; keep files overwritten: {ow}")
        ok = sum(expected_after(kind, x["after"]) for x in sub)
        L.append(f"- after as wanted: {ok}/{len(sub)}\n")
        L.append("| # | case | before | after |")
        L.append("|---|---|---|---|")
        for x in sub:
            mark = "" if expected_after(kind, x["after"]) else " ⚠"
            L.append(f"| {x['i']} | `{short_argv(x['argv'])}` | {cell(x['before'])} | {cell(x['after'])}{mark} |")
    bad = [x for x in rows if not expected_after(x["kind"], x["after"])]
    L.append("\n## After, not as wanted\n")
    if not bad:
        L.append("None.")
    snap = re.compile(r"\S*/boundaries_table_[^/]+/after_src/")
    for x in bad:
        a = x["after"]
        L.append(
            f"- #{x['i']} `{short_argv(x['argv'], 200)}`: rc {a['rc']}, {a['stderr_lines']} line(s), "
            f"traceback {a['traceback']}, keep changed {a['keep_changed'] or 'no'}; stderr (progress left out):"
        )
        L.append("  ```")
        L += [f"  {snap.sub('', ln)}" for ln in a["error_lines"]]
        L.append("  ```")
    L.append("\n## Notes (from the runs of 2026-12-02)\n")
    L += NOTES
    (HERE / "README.md").write_text("\n".join(L) + "\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--timeout", type=float, default=300.0)
    ap.add_argument("--reuse-before", action="store_true", help="take 0.1's records from results.json")
    ap.add_argument("--no-snapshot", action="store_true", help="run /work/main/jaxatt as it is, live")
    ap.add_argument("--only", help="run only cases whose argv contains this string (results go to *_only.*)")
    ap.add_argument("--render-only", action="store_true", help="rewrite README.md from results.json, run nothing")
    a = ap.parse_args()
    if a.render_only:
        d = json.loads((HERE / "results.json").read_text())
        write_readme(d["meta"], d["cases"])
        return
    t_start = time.time()
    scratch = Path(tempfile.mkdtemp(prefix="boundaries_table_"))
    snapshot = None
    diff = git("diff", "HEAD", "--", "jaxatt")
    if not a.no_snapshot:
        snapshot = scratch / "after_src"
        shutil.copytree(MAIN / "jaxatt", snapshot / "jaxatt", ignore=shutil.ignore_patterns("__pycache__"))
        ROOT["after"] = snapshot
    for v in ("before", "after"):
        env = {k: val for k, val in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
        if v == "after" and snapshot is not None:
            env["PYTHONPATH"] = str(snapshot)
        where = subprocess.run(
            [str(PY[v]), "-c", "import jaxatt; print(jaxatt.__file__)"],
            cwd=tempfile.gettempdir(),
            env=env,
            capture_output=True,
            text=True,
        ).stdout.strip()
        assert where.startswith(str(ROOT[v] / "jaxatt")), (v, where)
        print(f"{v}: {PY[v]} imports {where}", flush=True)
    reuse = {}
    if a.reuse_before and (HERE / "results.json").exists():
        old = json.loads((HERE / "results.json").read_text())
        reuse = {json.dumps(c["argv"]): c["before"] for c in old["cases"]}
        reused_from = old["meta"].get("before_records_from") or old["meta"]["date"]
    todo = cases()
    if a.only:
        todo = [c for c in todo if a.only in " ".join(c[1])]
    inputs = scratch / "inputs"
    inputs.mkdir()
    make_files(inputs)
    res = {}
    for i, (_, argv, _) in enumerate(todo):
        if json.dumps(argv) in reuse:
            res[i, "before"] = reuse[json.dumps(argv)]
    jobs = [
        (i, v, kind, argv, match)
        for i, (kind, argv, match) in enumerate(todo)
        for v in ("after", "before")
        if (i, v) not in res
    ]
    with ThreadPoolExecutor(a.workers) as ex:
        futs = {
            ex.submit(run_one, v, kind, argv, match, inputs, scratch, a.timeout, snapshot): (i, v)
            for i, v, kind, argv, match in jobs
        }
        for n, f in enumerate(as_completed(futs), 1):
            i, v = futs[f]
            r = f.result()
            res[i, v] = r
            print(
                f"[{n}/{len(jobs)}] #{i} {v:6s} rc={r['rc']} lines={r['stderr_lines']} {r['wall_s']:.1f}s "
                f"{short_argv(r['argv'], 60)} | {r['last_line'][:80]}",
                flush=True,
            )
    shutil.rmtree(scratch, ignore_errors=True)
    rows = [
        {"i": i, "kind": kind, "argv": argv, "match": match, "before": res[i, "before"], "after": res[i, "after"]}
        for i, (kind, argv, match) in enumerate(todo)
    ]
    wall = time.time() - t_start
    meta = {
        "date": dt.datetime.now().astimezone().isoformat(timespec="seconds"),
        "before": {"commit": git("rev-parse", BASE_COMMIT), "python": str(PY["before"])},
        "after": {
            "commit": git("rev-parse", "HEAD"),
            "dirty": bool(diff),
            "snapshot_of_working_tree": snapshot is not None,
            "jaxatt_diff_sha256": hashlib.sha256(diff.encode()).hexdigest() if diff else None,
            "jaxatt_diff": diff,
            "status": git("status", "--porcelain"),
            "python": str(PY["after"]),
        },
        "workers": a.workers,
        "timeout_s": a.timeout,
        "cpus": os.cpu_count(),
        "wall_s": round(wall, 1),
        "n_bad_input": sum(k == "bad_input" for k, _, _ in todo),
        "n_non_finite": sum(k == "non_finite" for k, _, _ in todo),
        "n_normal": sum(k == "normal" for k, _, _ in todo),
        "only": a.only,
        "before_records_from": reused_from if reuse else None,
    }
    suffix = "_only" if a.only else ""
    (HERE / f"results{suffix}.json").write_text(json.dumps({"meta": meta, "cases": rows}, indent=1) + "\n")
    if not a.only:
        write_readme(meta, rows)
    print(f"done in {wall:.0f} s", flush=True)


if __name__ == "__main__":
    main()
