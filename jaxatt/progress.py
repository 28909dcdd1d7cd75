"""Progress display for long Monte Carlo and tuning runs: optional and injectable.

The jitted runners report from inside the scan once per noise block (1000 time steps of every run in the batch)
through ``jax.debug.callback`` - never a Python loop over time steps. What is shown is up to the *reporter*:

* ``progress=True``: :class:`TextProgress` (one self-overwriting line on stderr: runs done, simulated steps,
  run-steps per second, time left);
* ``progress=callable``: ``callable(info)`` with ``info`` = {"runs_done", "runs_total", "chunk_steps_done",
  "steps_per_run", "run_steps_done", "run_steps_total", "elapsed_s"} (e.g. a tqdm bar or a notebook widget);
* ``progress=None`` / ``False`` (default): nothing is compiled in and nothing is called.

:func:`jaxatt.montecarlo.monte_carlo` reports per block and per chunk; :func:`jaxatt.fit` reports per
optimizer step (its ``callback``).
"""

from __future__ import annotations

import sys
import threading
import time
from typing import Callable, Optional, Union

import numpy as np

__all__ = [
    "TextProgress",
    "Heartbeat",
    "close_line",
    "done_reporting",
    "report_line",
    "make_reporter",
    "steps_hook",
    "active",
]

#: The reporting call in progress (module level: XLA runs host callbacks on its own threads).
_CURRENT: list = [None]
#: stderr's progress line: time of the last report (s, perf_counter) and whether a \r line is left open
_LINE = {"last_report": -1e9, "open": False}


def report_line(text: str, file=None) -> None:
    """Print a full progress line on ``file`` (default stderr), ending an open self-overwriting line first."""
    file = file if file is not None else sys.stderr
    close_line(file)
    print(text, file=file, flush=True)
    _LINE["last_report"] = max(_LINE["last_report"], time.perf_counter())


def done_reporting(file=None) -> None:
    """Results are about to be printed: end the progress line and keep :class:`Heartbeat` quiet from now on."""
    _LINE["last_report"] = float("inf")
    close_line(file)


def close_line(file=None) -> None:
    """End a self-overwriting progress line left open on ``file`` (call before printing a full line)."""
    if _LINE["open"]:
        (file if file is not None else sys.stderr).write("\n")
        _LINE["open"] = False


class TextProgress:
    """One line on ``file`` (default stderr), rewritten at most every ``min_interval_s`` seconds."""

    def __init__(self, label: str = "monte carlo", file=None, min_interval_s: float = 0.5):
        self.label = label
        self.file = file if file is not None else sys.stderr
        self.min_interval_s = min_interval_s
        self._last = -1e9

    def __call__(self, info: dict) -> None:
        now = time.perf_counter()
        final = info["run_steps_done"] >= info["run_steps_total"]
        if not final and now - self._last < self.min_interval_s:
            return
        self._last = now
        frac = info["run_steps_done"] / max(info["run_steps_total"], 1)
        rate = info["run_steps_done"] / max(info["elapsed_s"], 1e-9)
        left = (info["run_steps_total"] - info["run_steps_done"]) / max(rate, 1e-9)
        self.file.write(
            f"\r{self.label}: {100 * frac:5.1f} %  runs {info['runs_done']}/{info['runs_total']}  "
            f"{rate:.3g} run-steps/s  {left:.0f} s left   " + ("\n" if final else "")
        )
        self.file.flush()
        _LINE["last_report"], _LINE["open"] = now, not final


class Heartbeat:
    """Context manager: while a long call runs, rewrite one line ``label: N s`` on ``file`` (default stderr) every
    ``every_s`` seconds in which no other progress report (:class:`TextProgress`) came (compiling, a BROAD batch,
    a long log); nothing when ``enabled`` is false. The line is ended when the block exits."""

    def __init__(self, label: str, enabled: bool = True, every_s: float = 2.0, file=None):
        self.label, self.enabled, self.every_s = label, bool(enabled), every_s
        self.file = file if file is not None else sys.stderr
        self._stop = threading.Event()

    def _beat(self):
        t0 = time.perf_counter()
        while not self._stop.wait(self.every_s):
            if time.perf_counter() - _LINE["last_report"] < self.every_s:
                continue
            self.file.write(f"\r{self.label}: {time.perf_counter() - t0:.0f} s ")
            self.file.flush()
            _LINE["open"] = True

    def __enter__(self):
        _LINE["last_report"] = -1e9
        if self.enabled:
            self._thread = threading.Thread(target=self._beat, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc):
        if self.enabled:
            self._stop.set()
            self._thread.join()
            close_line(self.file)
            self.file.flush()
        return False


def make_reporter(progress: Union[None, bool, Callable], label: str = "monte carlo") -> Optional[Callable]:
    """The reporter of a ``progress`` argument (None when off)."""
    if progress is None or progress is False:
        return None
    if progress is True:
        return TextProgress(label)
    if callable(progress):
        return progress
    raise ValueError(f"progress must be None, a bool or a callable, got {type(progress).__name__}")


class _Run:
    """The state of one reporting Monte Carlo call (set by :func:`active`)."""

    def __init__(self, reporter, runs_total, steps_per_run, block_steps):
        self.reporter, self.runs_total, self.steps_per_run = reporter, runs_total, steps_per_run
        self.block_steps = block_steps
        self.runs_done = 0
        self.chunk_runs = 0  # runs of the chunk in progress
        self.chunk_steps = 0  # steps of the chunk in progress already reported
        self.t0 = time.perf_counter()

    def report(self, chunk_steps_done: int):
        done = self.runs_done * self.steps_per_run + self.chunk_runs * chunk_steps_done
        self.reporter(
            {
                "runs_done": self.runs_done,
                "runs_total": self.runs_total,
                "chunk_steps_done": int(chunk_steps_done),
                "steps_per_run": self.steps_per_run,
                "run_steps_done": int(done),
                "run_steps_total": self.runs_total * self.steps_per_run,
                "elapsed_s": time.perf_counter() - self.t0,
            }
        )


class active:
    """Context manager: make ``run`` the target of :func:`block_hook` (one reporting call at a time)."""

    def __init__(self, run: Optional[_Run]):
        self.run = run

    def __enter__(self):
        self.prev = _CURRENT[0]
        _CURRENT[0] = self.run
        return self.run

    def __exit__(self, *exc):
        _CURRENT[0] = self.prev
        return False


def steps_hook(steps_done) -> None:
    """Host side of the in-scan report (``jax.debug.callback`` of :mod:`jaxatt.engine`): the first
    ``steps_done`` steps of every run of the chunk are done."""
    run = _CURRENT[0]
    if run is None:
        return
    steps = min(int(np.max(np.asarray(steps_done))), run.steps_per_run)
    if steps > run.chunk_steps:  # every device reports each block: keep the first report of each
        run.chunk_steps = steps
        run.report(steps)
