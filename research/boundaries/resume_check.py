"""Resumed against uninterrupted, through the command line (issue 16's acceptance numbers).

1. Monte Carlo: ``jaxatt reproduce batista-so3 --runs 8 --chunk 2 --duration 60`` killed with SIGKILL after its first
   saved chunk, then rerun with ``--resume``; against the same command uninterrupted: max |difference| of every
   per-run metric.
2. Fit: ``jaxatt tune --experiment batista-so3 --steps 12`` interrupted with SIGINT after step 4 (exit 130), then
   ``--resume``; against the same tune uninterrupted: max relative difference of the gains and of the loss history.

Run: ``python research/boundaries/resume_check.py`` (about 3 min on 2 cores); writes resume_check.json here.
"""

import json
import os
import re
import select
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent


def cli(*args, wait=True):
    p = subprocess.Popen(
        [sys.executable, "-m", "jaxatt", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )
    if wait:
        out, err = p.communicate()
        assert p.returncode == 0, err.decode()[-2000:]
    return p


def wait_for(p, pattern, timeout=600):
    seen, fd, t0 = b"", p.stderr.fileno(), time.time()
    while time.time() - t0 < timeout:
        if select.select([fd], [], [], 0.1)[0]:
            chunk = os.read(fd, 65536)
            if not chunk:
                break
            seen += chunk
            if re.search(pattern, seen.decode(errors="replace")):
                return
    raise RuntimeError(f"never saw {pattern!r}: {seen[-500:]!r}")


def main():
    d = Path(tempfile.mkdtemp())
    out = {}
    # 1. Monte Carlo, SIGKILL + --resume
    mc = ["reproduce", "batista-so3", "--runs", "8", "--chunk", "2", "--duration", "60", "--seed", "5", "--quiet"]
    cli(*mc, "--json", str(d / "ref.json"))
    p = cli(*mc, "--json", str(d / "k.json"), wait=False)
    runs = d / "k.json.runs.npz"
    while not (runs.exists() and (d / "k.json").exists()) and p.poll() is None:
        time.sleep(0.05)
    p.send_signal(signal.SIGKILL)
    p.communicate()
    killed = json.loads((d / "k.json").read_text())
    cli(*mc, "--json", str(d / "k.json"), "--resume")
    ref, got = json.loads((d / "ref.json").read_text()), json.loads((d / "k.json").read_text())
    diffs = {
        k: float(np.max(np.abs(np.asarray(got["metrics"][k]["per_run"]) - np.asarray(v["per_run"]))))
        for k, v in ref["metrics"].items()
    }
    out["monte_carlo"] = {
        "command": "jaxatt " + " ".join(mc),
        "runs_saved_when_killed": killed["runs_done"],
        "resumed_complete": got["complete"],
        "max_abs_diff_per_metric": diffs,
        "mean_angle_error_deg": {
            "uninterrupted": ref["metrics"]["mean_angle_error_deg"]["mean"],
            "resumed": got["metrics"]["mean_angle_error_deg"]["mean"],
        },
    }
    print(json.dumps(out["monte_carlo"], indent=1))
    # 2. tune, SIGINT + --resume
    tune = [
        "tune",
        "--experiment",
        "batista-so3",
        "--steps",
        "12",
        "--train-runs",
        "4",
        "--val-runs",
        "2",
        "--duration",
        "20",
        "--quiet",
    ]
    cli(*tune, "--out", str(d / "g_ref.json"))
    p = subprocess.Popen(
        [sys.executable, "-m", "jaxatt", *tune[:-1], "--progress", "--out", str(d / "g.json")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )
    wait_for(p, r"step +4/12")
    p.send_signal(signal.SIGINT)
    p.communicate()
    rc = p.returncode
    interrupted = json.loads((d / "g.json").read_text())
    cli(*tune, "--out", str(d / "g.json"), "--resume")
    a, b = json.loads((d / "g_ref.json").read_text()), json.loads((d / "g.json").read_text())

    def rel(x, y):
        x, y = np.asarray(x, float), np.asarray(y, float)
        return float(np.max(np.abs(x - y) / np.maximum(np.abs(y), 1e-300)))

    out["tune"] = {
        "command": "jaxatt " + " ".join(tune),
        "exit_status_on_sigint": rc,
        "steps_saved_when_interrupted": len(interrupted["history"]) - 1,
        "status_after_resume": b["status"],
        "max_rel_diff_gains": max(rel(b["gains"][k]["value"], v["value"]) for k, v in a["gains"].items()),
        "max_rel_diff_train_loss": rel(
            [h.get("train_loss", np.nan) for h in b["history"] if "train_loss" in h],
            [h.get("train_loss", np.nan) for h in a["history"] if "train_loss" in h],
        ),
        "best_loss": {"uninterrupted": a["best_loss"], "resumed": b["best_loss"]},
    }
    print(json.dumps(out["tune"], indent=1))
    (HERE / "resume_check.json").write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
