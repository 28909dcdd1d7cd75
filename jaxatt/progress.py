"""Progress display for long Monte Carlo and tuning runs: optional and injectable.

The jitted runners report from inside the scan once per noise block (1000 time steps of every run in the batch)
through ``jax.debug.callback`` - never a Python loop over time steps. What is shown is up to the *reporter*:

* ``progress=True``: :class:`TextProgress`, a tqdm bar of run-steps (on stderr in a terminal, a widget in a
  notebook when ipywidgets is installed): runs done, run-steps per second, time left;
* ``progress=callable``: ``callable(info)`` with ``info`` = {"runs_done", "runs_total", "chunk_steps_done",
  "steps_per_run", "run_steps_done", "run_steps_total", "elapsed_s"} (your own display or logger);
* ``progress=None`` / ``False`` (default): nothing is compiled in and nothing is called.

:func:`jaxatt.montecarlo.monte_carlo` reports per block and per chunk; :func:`jaxatt.fit` reports per
optimizer step (its ``callback``).
"""

from __future__ import annotations

import sys
import threading
import time
from typing import Any, Callable, Dict, Optional, Union

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
#: stderr's progress line: time of the last report (s, perf_counter), whether a \r line is left open, the open bar
_LINE: Dict[str, Any] = {"last_report": -1e9, "open": False, "bar": None}


def report_line(text: str, file=None) -> None:
    """Print a full progress line on ``file`` (default stderr), ending an open self-overwriting line first."""
    file = file if file is not None else sys.stderr
    bar = _LINE.get("bar")
    if bar is not None and not bar.disable:  # print above the bar, which stays open
        bar.clear()
        print(text, file=file, flush=True)
        bar.refresh()
    else:
        close_line(file)
        print(text, file=file, flush=True)
    _LINE["last_report"] = max(_LINE["last_report"], time.perf_counter())


def done_reporting(file=None) -> None:
    """Results are about to be printed: end the progress line and keep :class:`Heartbeat` quiet from now on."""
    _LINE["last_report"] = float("inf")
    close_line(file)


def close_line(file=None) -> None:
    """End the progress bar or self-overwriting line left open on ``file`` (call before printing a full line)."""
    bar = _LINE.get("bar")
    if bar is not None:
        _LINE["bar"] = None
        bar.close()
    if _LINE["open"]:
        (file if file is not None else sys.stderr).write("\n")
        _LINE["open"] = False


def _tqdm_class():
    """tqdm's notebook bar in a Jupyter kernel with ipywidgets, its text bar otherwise (no IProgress warning)."""
    from tqdm import tqdm as text_bar

    if "ipykernel" in sys.modules:
        try:
            import ipywidgets  # noqa: F401
            from tqdm.notebook import tqdm as widget_bar

            return widget_bar
        except ImportError:
            pass
    return text_bar


class TextProgress:
    """A tqdm progress bar of run-steps (terminal: on ``file``, default stderr; notebook: a widget), refreshed at
    most every ``min_interval_s`` seconds, closed when the last run-step is reported."""

    def __init__(self, label: str = "monte carlo", file=None, min_interval_s: float = 0.5):
        self.label = label
        self.file = file if file is not None else sys.stderr
        self.min_interval_s = min_interval_s
        self._bar: Any = None

    def __call__(self, info: dict) -> None:
        total, done = int(info["run_steps_total"]), int(info["run_steps_done"])
        bar = self._bar
        if bar is None or _LINE.get("bar") is not bar:  # first report, or the bar was closed
            bar = self._bar = _tqdm_class()(
                total=total,
                initial=done,
                desc=self.label,
                unit="run-steps",
                unit_scale=True,
                file=self.file,
                mininterval=self.min_interval_s,
                dynamic_ncols=True,
            )
            _LINE["bar"] = bar
        bar.set_postfix_str(f"runs {info['runs_done']}/{info['runs_total']}", refresh=False)
        bar.update(done - bar.n)
        _LINE["last_report"] = time.perf_counter()
        if done >= total and info["runs_done"] >= info["runs_total"]:
            close_line(self.file)


def _is_terminal(file) -> bool:
    try:
        return bool(file.isatty())
    except (AttributeError, ValueError):
        return False


class Heartbeat:
    """Context manager: while a long call runs, rewrite one line ``label: N s`` on ``file`` (default stderr) every
    ``every_s`` seconds in which no other progress report (:class:`TextProgress`) came (compiling, a BROAD batch,
    a long log); nothing when ``enabled`` is false. The line is ended when the block exits. On a file that is not
    a terminal (a log) it writes whole lines instead, at most one every ``log_every_s`` seconds."""

    def __init__(self, label: str, enabled: bool = True, every_s: float = 2.0, file=None, log_every_s: float = 60.0):
        self.label, self.enabled, self.every_s = label, bool(enabled), every_s
        self.file = file if file is not None else sys.stderr
        self.log_every_s = log_every_s
        self._stop = threading.Event()

    def _beat(self):
        t0 = time.perf_counter()
        terminal = _is_terminal(self.file)
        every = self.every_s if terminal else max(self.every_s, self.log_every_s)
        while not self._stop.wait(every):
            if time.perf_counter() - _LINE["last_report"] < every:
                continue
            if terminal:
                self.file.write(f"\r{self.label}: {time.perf_counter() - t0:.0f} s ")
                _LINE["open"] = True
            else:
                self.file.write(f"{self.label}: {time.perf_counter() - t0:.0f} s\n")
            self.file.flush()

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
