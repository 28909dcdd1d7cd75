"""Where the test suite's time goes: a pytest plugin that records, per test, every program JAX traces, lowers and
compiles (``jax_log_compiles``) and writes them to ``/tmp/compile_events_<pid>.json`` at the end (one file per
xdist worker). Compiles in the subprocesses some tests start (CLI, notebooks, jax.distributed) are not seen.

Run: ``PYTHONPATH=research python -m pytest tests -p ci_compile_profile`` (the logging slows the suite by ~20 %),
then ``python research/ci_compile_profile.py`` for the summary: the share of compile work, the programs compiled
most, and the tests that compile a program of the same name more than once (a recompile from a new closure or a
weakly typed argument shows up there).
"""

from __future__ import annotations

import collections
import glob
import json
import logging
import os
import re
import time

import pytest

_EVENT = re.compile(
    r"Finished (XLA compilation|tracing|jaxpr to MLIR module conversion) (?:of |for )?(\S+).* in ([\d.e-]+) sec"
)
_current: dict = {"events": [], "hits": 0}
_results: list = []


class _Recorder(logging.Handler):
    def emit(self, record):
        msg = record.getMessage()
        m = _EVENT.search(msg)
        if m:
            _current["events"].append((m.group(1).split()[0], m.group(2), float(m.group(3))))
        elif "cache hit" in msg.lower():
            _current["hits"] += 1


def pytest_configure(config):
    import jax

    jax.config.update("jax_log_compiles", True)
    handler = _Recorder(logging.DEBUG)
    for name in ("jax._src.dispatch", "jax._src.interpreters.pxla", "jax._src.compiler", "jax"):
        logger = logging.getLogger(name)
        logger.addHandler(handler)
        logger.setLevel(logging.DEBUG)
        logger.propagate = False
    from jaxatt import engine

    original = engine.batch_fn

    def recording_batch_fn(observer, source, reducer, **kw):  # which observer, length and record interval
        _current["events"].append(
            (
                "batch_fn",
                f"{getattr(observer, 'name', '?')}/{type(source).__name__}/{source.n_steps}/{reducer.every}/"
                f"{sorted((k, str(v)) for k, v in kw.items())}",
                0.0,
            )
        )
        return original(observer, source, reducer, **kw)

    engine.batch_fn = recording_batch_fn


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _current["events"], _current["hits"] = [], 0
    t0 = time.perf_counter()
    yield
    _results.append({"wall": time.perf_counter() - t0, "id": item.nodeid, **_current})


def pytest_sessionfinish(session):
    with open(f"/tmp/compile_events_{os.getpid()}.json", "w") as f:
        json.dump(_results, f)


def summary(pattern: str = "/tmp/compile_events_*.json") -> None:
    """Print the share of compile work, the programs compiled most and the repeated compiles within a test."""
    res = [r for path in glob.glob(pattern) for r in json.load(open(path))]
    total = {k: sum(t for r in res for kind, _, t in r["events"] if kind == k) for k in ("XLA", "tracing", "jaxpr")}
    wall = sum(r["wall"] for r in res)
    print(
        f"{len(res)} tests, {wall:.0f} s of worker time: XLA compile {total['XLA']:.0f} s, tracing "
        f"{total['tracing']:.0f} s, lowering to MLIR {total['jaxpr']:.0f} s; persistent-cache hits "
        f"{sum(r['hits'] for r in res)}"
    )
    by_name = collections.defaultdict(list)
    repeats = []
    for r in res:
        seen = collections.defaultdict(list)
        for kind, name, t in r["events"]:
            if kind == "XLA" and t > 0.3:
                by_name[name].append(t)
                seen[name].append(t)
        repeats += [(sum(sorted(ts)[:-1]), r["id"], n, ts) for n, ts in seen.items() if len(ts) > 1]
    for name, ts in sorted(by_name.items(), key=lambda kv: -sum(kv[1]))[:10]:
        print(f"  {sum(ts):7.1f} s in {len(ts):4d} compiles of {name}")
    lengths = collections.defaultdict(set)  # observer -> the step counts its engine programs were built for
    for r in res:
        for kind, name, _ in r["events"]:
            if kind == "batch_fn":
                observer, _source, n_steps = name.split("/[")[0].rsplit("/", 4)[:3]
                lengths[observer].add(n_steps)
    print(
        "distinct step counts per observer (batch_fn):",
        {o: len(n) for o, n in sorted(lengths.items(), key=lambda kv: -len(kv[1]))[:8]},
    )
    print("tests compiling a program of the same name more than once (s beyond the first):")
    for extra, test, name, ts in sorted(repeats, reverse=True)[:15]:
        print(f"  {extra:6.1f} s {test} {name} {[round(t, 1) for t in ts]}")


if __name__ == "__main__":
    summary()
